//! Tracing a pixel's samples' paths as a batch (`integrator::radiance_batch`: their bounce rays
//! together, their light choices together, then their shadow rays together; used above
//! `accel::BATCH_RAYS_ABOVE` triangles and wherever a light tree chooses lights) changes no bit
//! of any image: each path does the arithmetic it does alone, its light sample is
//! added before anything later in the path, and the pixel's sums add the samples in the same
//! order. Every test scene is rendered with batching forced on and off; a scene large enough to
//! batch by default is rendered both ways too.

use renderer::accel::{BATCH_RAYS_ABOVE, MAX_BATCH};
use renderer::film::Rect;
use renderer::light::LightSamplerKind;
use renderer::material::{AlphaMode, Material};
use renderer::math::{Vec3, Vec4};
use renderer::scene::Scene;
use renderer::testing::{emitter, lambert, load_bit_test_scene, metal, sum_bits, SceneBuilder, BIT_TEST_SCENES};
use renderer::{render_tile, RenderSettings};
use std::path::Path;

fn root() -> &'static Path {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))
}

/// Renders `scene` with batching on and off; panics naming `what` if a bit differs. A sample count
/// of one more than a batch leaves each pixel one sample traced alone after the batch.
fn same_both_ways(scene: &mut Scene, settings: &RenderSettings, what: &str) {
    scene.set_batch_rays(true);
    assert!(scene.batches_rays(), "{what}: forcing batching must batch");
    same_with_paths_batched_or_not(scene, settings, what);
}

/// Renders `scene` with its paths batched (`radiance_batch`, its rays traced as
/// `Scene::batches_rays` says) and one at a time; panics naming `what` if a bit differs.
fn same_with_paths_batched_or_not(scene: &mut Scene, settings: &RenderSettings, what: &str) {
    let rect = Rect { x0: 0, y0: 0, width: settings.width, height: settings.height };
    scene.set_batch_paths(Some(true));
    let batched = render_tile(scene, settings, rect, 0..settings.spp);
    scene.set_batch_rays(false);
    scene.set_batch_paths(Some(false));
    assert!(!scene.batches_rays() && !scene.batches_paths());
    let single = render_tile(scene, settings, rect, 0..settings.spp);
    scene.set_batch_paths(None);
    let total: f64 = single.sum_rgb.iter().flatten().sum();
    assert!(total > 0.0, "{what}: a black image tests nothing");
    assert!(sum_bits(&batched) == sum_bits(&single), "{what}: batching changed the image");
}

#[test]
fn batched_paths_render_every_test_scene_bit_for_bit() {
    let mut batched = 0;
    for (i, entry) in BIT_TEST_SCENES.into_iter().enumerate() {
        let rel = entry.0;
        // Batches of 5, and of a full batch and a sample alone.
        let spp = if i % 2 == 0 { 5 } else { MAX_BATCH as u32 + 1 };
        let mut settings = RenderSettings { width: 40, height: 30, spp, seed: 7, ..RenderSettings::default() };
        let mut scene = load_bit_test_scene(root(), entry, &mut settings);
        scene.set_batch_rays(true);
        // Instanced (two-level) and transparent scenes trace one ray at a time whatever is asked.
        if !scene.batches_rays() {
            eprintln!("{rel}: does not batch (instances or transparency)");
            continue;
        }
        same_both_ways(&mut scene, &settings, rel);
        batched += 1;
    }
    assert!(batched >= 9, "only {batched} scenes batched: the test lost its coverage");
}

/// Where a light tree chooses the lights, a pixel's paths run as a batch by default and choose
/// their lights together (`LightSet::select_batch`: the walks down the tree interleaved), with
/// the BVH's rays traced one at a time: every test scene with two or more lights, the tree forced,
/// renders the same so as one path at a time (an environment chosen beside the tree included:
/// DamagedHelmet under the sunset; directional lights beside it are `light.rs`'s unit test).
#[test]
fn paths_choosing_lights_together_render_every_test_scene_bit_for_bit() {
    let mut walked = 0;
    for (i, entry) in BIT_TEST_SCENES.into_iter().enumerate() {
        let rel = entry.0;
        let spp = if i % 2 == 1 { 5 } else { MAX_BATCH as u32 + 1 };
        let mut settings = RenderSettings {
            width: 40,
            height: 30,
            spp,
            seed: 3,
            light_sampler: LightSamplerKind::Tree,
            ..RenderSettings::default()
        };
        let mut scene = load_bit_test_scene(root(), entry, &mut settings);
        if !scene.lights.walks_tree() {
            eprintln!("{rel}: fewer than two lights, no tree");
            continue;
        }
        assert!(scene.batches_paths() && !scene.batches_rays(), "{rel}: a tree must batch paths by default");
        same_with_paths_batched_or_not(&mut scene, &settings, rel);
        walked += 1;
    }
    assert!(walked >= 8, "only {walked} scenes walked a tree: the test lost its coverage");
}

/// A mesh above the size limit batches by default, one below does not, and the large one's image
/// is the same batched or not (glossy and diffuse bounces, absorbing glass, an area light, NEE and
/// MIS); also with a BLEND sphere and a MASK quad in it, which bounce rays pass through on their own
/// after the batch's first layer.
#[test]
fn large_scenes_batch_by_default_and_render_the_same() {
    let scene_with = |level: u32, transparent: bool| {
        let mut b = SceneBuilder::default();
        let wall = b.material(lambert(Vec3::splat(0.6)));
        let shiny = b.material(metal(Vec3::new(0.9, 0.7, 0.5), 0.3));
        let light = b.material(emitter(Vec3::splat(8.0)));
        let glass = b.material(Material {
            name: "absorbing glass".into(),
            base_color: Vec4::ONE,
            roughness: 0.1,
            transmission: 1.0,
            absorption: Vec3::new(0.2, 0.5, 0.9),
            ..Material::default()
        });
        b.sphere(Vec3::ZERO, 4.0, 2, true, wall);
        b.sphere(Vec3::new(0.0, -1.0, 0.0), 1.5, level, false, shiny);
        b.sphere(Vec3::new(1.6, -2.0, 1.0), 0.7, 2, false, glass);
        b.quad(Vec3::new(0.0, 3.5, 0.0), Vec3::new(0.8, 0.0, 0.0), Vec3::new(0.0, 0.0, 0.8), light);
        if transparent {
            let mut blend = Material { alpha_mode: AlphaMode::Blend, ..lambert(Vec3::new(0.2, 0.8, 0.3)) };
            blend.base_color.w = 0.4;
            let blend = b.material(blend);
            let mut mask = Material { alpha_mode: AlphaMode::Mask(0.5), ..lambert(Vec3::new(0.9, 0.2, 0.2)) };
            mask.base_color.w = 0.3;
            let mask = b.material(mask);
            b.sphere(Vec3::new(-1.2, -1.5, 1.5), 0.8, 2, false, blend);
            b.quad(Vec3::new(0.0, -0.5, 2.0), Vec3::new(1.5, 0.0, 0.0), Vec3::new(0.0, 1.5, 0.0), mask);
        }
        b.look_at(Vec3::new(0.0, 0.5, 3.5), Vec3::new(0.0, -0.8, 0.0), 50.0);
        b.build()
    };
    let small = scene_with(3, false);
    assert!(small.mesh.triangles.len() <= BATCH_RAYS_ABOVE && !small.batches_rays());
    let settings =
        RenderSettings { width: 32, height: 24, spp: MAX_BATCH as u32 + 3, seed: 11, ..RenderSettings::default() };
    for transparent in [false, true] {
        let mut large = scene_with(6, transparent);
        assert!(large.mesh.triangles.len() > BATCH_RAYS_ABOVE && large.batches_rays());
        assert_eq!(large.has_transparency(), transparent);
        same_both_ways(&mut large, &settings, &format!("the large sphere (transparent layers: {transparent})"));
    }
}
