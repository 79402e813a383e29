//! Tracing two samples' paths together (`integrator::radiance_pair`, used above
//! `accel::PAIR_RAYS_ABOVE` triangles) changes no bit of any image: each path does the arithmetic
//! it does alone and the pixel's sums add the samples in the same order. Every test scene is
//! rendered with pairing forced on and off; a scene large enough to pair by default is rendered
//! both ways too.

use renderer::accel::PAIR_RAYS_ABOVE;
use renderer::film::Rect;
use renderer::math::Vec3;
use renderer::scene::Scene;
use renderer::testing::{emitter, lambert, load_bit_test_scene, metal, sum_bits, SceneBuilder, BIT_TEST_SCENES};
use renderer::{render_tile, RenderSettings};
use std::path::Path;

fn root() -> &'static Path {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))
}

/// Renders `scene` with pairing on and off; panics naming `what` if a bit differs. An odd sample
/// count leaves each pixel one sample traced alone after the pairs.
fn same_both_ways(scene: &mut Scene, settings: &RenderSettings, what: &str) {
    let rect = Rect { x0: 0, y0: 0, width: settings.width, height: settings.height };
    scene.set_pair_rays(true);
    assert!(scene.pairs_rays(), "{what}: forcing pairing must pair");
    let paired = render_tile(scene, settings, rect, 0..settings.spp);
    scene.set_pair_rays(false);
    assert!(!scene.pairs_rays());
    let single = render_tile(scene, settings, rect, 0..settings.spp);
    let total: f64 = single.sum_rgb.iter().flatten().sum();
    assert!(total > 0.0, "{what}: a black image tests nothing");
    assert!(sum_bits(&paired) == sum_bits(&single), "{what}: pairing changed the image");
}

#[test]
fn paired_paths_render_every_test_scene_bit_for_bit() {
    let mut paired = 0;
    for entry in BIT_TEST_SCENES {
        let rel = entry.0;
        let mut settings = RenderSettings { width: 40, height: 30, spp: 5, seed: 7, ..RenderSettings::default() };
        let mut scene = load_bit_test_scene(root(), entry, &mut settings);
        scene.set_pair_rays(true);
        // Instanced (two-level) and transparent scenes trace one ray at a time whatever is asked.
        if !scene.pairs_rays() {
            eprintln!("{rel}: does not pair (instances or transparency)");
            continue;
        }
        same_both_ways(&mut scene, &settings, rel);
        paired += 1;
    }
    assert!(paired >= 9, "only {paired} scenes paired: the test lost its coverage");
}

/// A mesh above the size limit pairs by default, one below does not, and the large one's image is
/// the same paired or not (glossy and diffuse bounces, an area light, NEE and MIS).
#[test]
fn large_scenes_pair_by_default_and_render_the_same() {
    let scene_with = |level: u32| {
        let mut b = SceneBuilder::default();
        let wall = b.material(lambert(Vec3::splat(0.6)));
        let shiny = b.material(metal(Vec3::new(0.9, 0.7, 0.5), 0.3));
        let light = b.material(emitter(Vec3::splat(8.0)));
        b.sphere(Vec3::ZERO, 4.0, 2, true, wall);
        b.sphere(Vec3::new(0.0, -1.0, 0.0), 1.5, level, false, shiny);
        b.quad(Vec3::new(0.0, 3.5, 0.0), Vec3::new(0.8, 0.0, 0.0), Vec3::new(0.0, 0.0, 0.8), light);
        b.look_at(Vec3::new(0.0, 0.5, 3.5), Vec3::new(0.0, -0.8, 0.0), 50.0);
        b.build()
    };
    let small = scene_with(3);
    assert!(small.mesh.triangles.len() <= PAIR_RAYS_ABOVE && !small.pairs_rays());
    let mut large = scene_with(6);
    assert!(large.mesh.triangles.len() > PAIR_RAYS_ABOVE && large.pairs_rays());
    let settings = RenderSettings { width: 32, height: 24, spp: 7, seed: 11, ..RenderSettings::default() };
    same_both_ways(&mut large, &settings, "the large sphere");
}
