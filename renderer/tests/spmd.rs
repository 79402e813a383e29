//! The eight-lane kernel (`spmd::radiance8`: eight paths in lock step, their shading on AVX
//! registers) changes no bit of any image it renders: each lane does the scalar path's
//! arithmetic in its order. Every test scene it renders, and programmatic scenes at the
//! extremes (black and white albedo, smooth shading normals, one-sided emitters seen from behind, a tiny bright light,
//! a millimetre-sized room, a mesh large enough that the BVH batches its rays, every light
//! sampler, both MIS heuristics, depths 0 to 8, roulette from the first bounce; textures, vertex
//! colours, normal maps and tangent frames, textured emitters, instances), is rendered with
//! the kernel and with the scalar path and compared sum for sum, and ray count for ray count.

#![cfg(all(target_arch = "x86_64", target_feature = "avx2"))]

use glam::Mat4;
use renderer::accel::BATCH_RAYS_ABOVE;
use renderer::environment::Environment;
use renderer::film::Rect;
use renderer::light::LightSamplerKind;
use renderer::material::{AlphaMode, Material};
use renderer::math::{Vec2, Vec3, Vec4};
use renderer::mesh::{flags, Instance, Triangle};
use renderer::microfacet::Ggx;
use renderer::punctual::{PunctualKind, PunctualLight};
use renderer::render::render_tile_counted;
use renderer::scene::Scene;
use renderer::settings::MisHeuristic;
use renderer::testing::{
    emitter, lambert, load_bit_test_scene, metal, one_sided_emitter, sum_bits, SceneBuilder, BIT_TEST_SCENES,
};
use renderer::texture::{Texture, TextureRef, Wrap};
use renderer::{Counters, IntegratorKind, RenderSettings};
use std::path::Path;
use std::sync::atomic::Ordering;

fn root() -> &'static Path {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))
}

/// Renders `scene` with the kernel and without; panics naming `what` if the kernel does not take
/// the scene or a bit differs.
fn same_with_lanes_or_not(scene: &mut Scene, settings: &RenderSettings, what: &str) {
    let rect = Rect { x0: 0, y0: 0, width: settings.width, height: settings.height };
    scene.set_lanes(true);
    assert!(scene.lanes(settings).is_some(), "{what}: the kernel must take this scene");
    let (lane_count, single_count) = (Counters::default(), Counters::default());
    let lanes = render_tile_counted(scene, settings, rect, 0..settings.spp, &lane_count);
    scene.set_lanes(false);
    assert!(scene.lanes(settings).is_none());
    let single = render_tile_counted(scene, settings, rect, 0..settings.spp, &single_count);
    scene.set_lanes(true);
    let rays = |c: &Counters| c.rays.load(Ordering::Relaxed);
    assert_eq!(rays(&lane_count), rays(&single_count), "{what}: the kernel counted other rays");
    let total: f64 = single.sum_rgb.iter().flatten().sum();
    assert!(total > 0.0, "{what}: a black image tests nothing");
    assert!(total.is_finite(), "{what}: not finite");
    assert!(sum_bits(&lanes) == sum_bits(&single), "{what}: the eight-lane kernel changed the image");
}

#[test]
fn eight_lanes_render_every_test_scene_they_take_bit_for_bit() {
    let mut taken = Vec::new();
    for (i, entry) in BIT_TEST_SCENES.into_iter().enumerate() {
        for light_sampler in [LightSamplerKind::Auto, LightSamplerKind::Tree] {
            // A pass of 13 leaves a pixel's last five samples in a part-filled register.
            let spp = [5, 8, 13][i % 3];
            let mut settings =
                RenderSettings { width: 40, height: 30, spp, seed: 11, light_sampler, ..RenderSettings::default() };
            let mut scene = load_bit_test_scene(root(), entry, &mut settings);
            if scene.lanes(&settings).is_none() {
                continue;
            }
            same_with_lanes_or_not(&mut scene, &settings, &format!("{} ({light_sampler:?})", entry.0));
            taken.push(entry.0);
        }
    }
    taken.dedup();
    for must in [
        "cornell",
        "envlit",
        "glass",
        "many_lights",
        "sphere_light",
        "sphere_lights",
        "veach",
        "lights.glb",
        "materials.glb",
        "BoxTextured.glb",
        "DamagedHelmet",
    ] {
        assert!(taken.iter().any(|t| t.contains(must)), "the kernel no longer takes {must} ({taken:?})");
    }
}

/// The camera rays and sample sets drawn eight lanes at once (`render::camera_rays8`,
/// `sampler::get_4d_pair_each_lanes`) are each sample's own: both pixel filters, both samplers
/// (the independent one draws one lane at a time), and sample ranges that cross a 2^16 block
/// (where a pixel's camera rays no longer share their Sobol seed and fall back to one at a
/// time, and the lanes' sets carry each sample's own block), some ending in a part-filled
/// register.
#[test]
fn eight_lanes_draw_each_samples_own_numbers() {
    use renderer::sampler::SamplerKind;
    use renderer::settings::PixelFilter;
    let mut scene = room(Vec3::splat(0.6), 1.0, 4.0);
    for filter in [PixelFilter::Box, PixelFilter::Tent] {
        for sampler in [SamplerKind::Sobol, SamplerKind::Independent] {
            for samples in [0..16u32, 65_530..65_545, 131_060..131_077] {
                let settings = RenderSettings {
                    width: 6,
                    height: 5,
                    spp: samples.len() as u32,
                    seed: 5,
                    filter,
                    sampler,
                    ..RenderSettings::default()
                };
                let rect = Rect { x0: 0, y0: 0, width: settings.width, height: settings.height };
                scene.set_lanes(true);
                assert!(scene.lanes(&settings).is_some());
                let lanes = render_tile_counted(&scene, &settings, rect, samples.clone(), &Counters::default());
                scene.set_lanes(false);
                let single = render_tile_counted(&scene, &settings, rect, samples.clone(), &Counters::default());
                let total: f64 = single.sum_rgb.iter().flatten().sum();
                assert!(total > 0.0 && total.is_finite());
                assert!(
                    sum_bits(&lanes) == sum_bits(&single),
                    "{filter:?} {sampler:?} samples {samples:?}: the kernel changed the image"
                );
            }
        }
    }
}

/// A box of Lambert walls (albedo `wall`) around a sphere, lit by a two-sided quad and a
/// one-sided one turned away from the camera's side of the room, `size` across.
fn room(wall: Vec3, size: f32, light_radiance: f32) -> Scene {
    room_with(lambert(wall), lambert(Vec3::ONE), size, light_radiance)
}

/// [`room`] with the floor, ceiling and two walls of `wall` and the smooth-shaded sphere of
/// `sphere`.
fn room_with(wall: Material, sphere: Material, size: f32, light_radiance: f32) -> Scene {
    let mut b = SceneBuilder::default();
    let w = b.material(wall);
    let red = b.material(lambert(Vec3::new(0.9, 0.1, 0.1)));
    let white = b.material(sphere);
    let black = b.material(lambert(Vec3::ZERO));
    let e = b.material(emitter(Vec3::splat(light_radiance)));
    let back = b.material(one_sided_emitter(Vec3::new(3.0, 2.0, 1.0)));
    let s = size;
    for (c, u, v) in [
        (Vec3::new(0.0, -s, 0.0), Vec3::X, Vec3::NEG_Z),
        (Vec3::new(0.0, s, 0.0), Vec3::X, Vec3::Z),
        (Vec3::new(-s, 0.0, 0.0), Vec3::Z, Vec3::Y),
        (Vec3::new(0.0, 0.0, -s), Vec3::X, Vec3::Y),
    ] {
        b.quad(c, u * s, v * s, w);
    }
    b.quad(Vec3::new(s, 0.0, 0.0), Vec3::Y * s, Vec3::Z * s, red);
    // Smooth-shaded (vertex normals, coarse): shading normals that send some directions below
    // the true surface.
    let (first_vertex, first_triangle) = (b.mesh.positions.len(), b.mesh.triangles.len());
    let centre = Vec3::new(-0.4, -0.6, -0.2) * s;
    b.sphere(centre, 0.35 * s, 1, false, white);
    for v in first_vertex..b.mesh.positions.len() {
        b.mesh.normals[v] = (b.mesh.positions[v] - centre).normalize();
    }
    for t in &mut b.mesh.triangles[first_triangle..] {
        t.flags |= flags::NORMALS;
    }
    b.sphere(Vec3::new(0.45, -0.7, 0.3) * s, 0.25 * s, 1, false, black);
    b.quad(Vec3::new(0.0, 0.99 * s, 0.0), Vec3::X * 0.2 * s, Vec3::Z * 0.2 * s, e);
    // Faces −x: lit side away from most of the room, so many samples see its back.
    b.quad(Vec3::new(-0.5 * s, 0.3 * s, -0.5 * s), Vec3::Z * 0.15 * s, Vec3::Y * 0.15 * s, back);
    b.look_at(Vec3::new(0.0, 0.0, 3.5 * s), Vec3::ZERO, 45.0);
    b.build()
}

/// The kernel streams sixteen pixels' samples through its lanes, refilling a lane as its path
/// ends (`render::kernel_pixels`, `spmd::radiance8`): a pixel's samples split across streams
/// (40 samples a pixel: streams of 256, 256 and 128 paths), a last group of three pixels, a
/// tile away from the image's corner, sample ranges that start and end off a multiple of eight,
/// and a ray count, all as the scalar path has them.
#[test]
fn eight_lanes_stream_pixels_and_samples_as_the_scalar_path_sums_them() {
    let mut scene = room(Vec3::splat(0.6), 1.0, 5.0);
    let settings = RenderSettings { width: 20, height: 12, spp: 64, seed: 9, ..RenderSettings::default() };
    for (rect, samples) in [
        (Rect { x0: 0, y0: 0, width: 7, height: 5 }, 0..40u32),
        (Rect { x0: 9, y0: 4, width: 5, height: 3 }, 3..61),
        (Rect { x0: 10, y0: 6, width: 1, height: 1 }, 13..14),
    ] {
        let (lane_count, single_count) = (Counters::default(), Counters::default());
        scene.set_lanes(true);
        assert!(scene.lanes(&settings).is_some());
        let lanes = render_tile_counted(&scene, &settings, rect, samples.clone(), &lane_count);
        scene.set_lanes(false);
        let single = render_tile_counted(&scene, &settings, rect, samples.clone(), &single_count);
        let rays = |c: &Counters| c.rays.load(Ordering::Relaxed);
        assert_eq!(rays(&lane_count), rays(&single_count), "{rect:?} {samples:?}: other rays counted");
        let total: f64 = single.sum_rgb.iter().flatten().sum();
        assert!(total > 0.0 && total.is_finite(), "{rect:?} {samples:?}: a black tile tests nothing ({total})");
        assert_eq!(lanes.count, single.count, "{rect:?} {samples:?}");
        assert!(sum_bits(&lanes) == sum_bits(&single), "{rect:?} {samples:?}: the kernel changed the sums");
    }
}

#[test]
fn eight_lanes_match_the_scalar_path_at_the_extremes() {
    let base = RenderSettings { width: 24, height: 18, spp: 11, seed: 5, ..RenderSettings::default() };
    let cases: [(&str, Vec3, f32, f32); 4] = [
        ("grey room", Vec3::splat(0.6), 1.0, 5.0),
        ("white room (albedo 1)", Vec3::ONE, 1.0, 5.0),
        ("black room", Vec3::ZERO, 1.0, 5.0),
        ("millimetre room, 1e4 light", Vec3::splat(0.5), 1e-3, 1e4),
    ];
    for (what, wall, size, le) in cases {
        let mut scene = room(wall, size, le);
        for kind in [LightSamplerKind::Power, LightSamplerKind::Uniform, LightSamplerKind::Tree] {
            scene.set_light_sampler(kind);
            for (max_depth, rr_depth, mis_heuristic) in [
                (0, 5, MisHeuristic::Power),
                (1, 5, MisHeuristic::Power),
                (8, 1, MisHeuristic::Power),
                (5, 0, MisHeuristic::Balance),
            ] {
                let s = RenderSettings { max_depth, rr_depth, mis_heuristic, light_sampler: kind, ..base.clone() };
                let what = format!("{what}, {kind:?}, depth {max_depth}, rr {rr_depth}, {mis_heuristic:?}");
                same_with_lanes_or_not(&mut scene, &s, &what);
            }
        }
    }
}

/// Metal and plastic, from mirrors (roughness 0, and alpha just under and just over
/// `Ggx::DELTA_ALPHA`) to roughness 1, black to white, half-metal, KHR_materials_specular 0,
/// beside Lambert walls so that batches mix the general BSDF and Lambert lanes.
#[test]
fn eight_lanes_match_on_metal_and_plastic_at_the_extremes() {
    let base = RenderSettings { width: 24, height: 18, spp: 11, seed: 9, ..RenderSettings::default() };
    let threshold = Ggx::DELTA_ALPHA.sqrt();
    let plastic = |c: Vec3, roughness: f32| Material { metallic: 0.0, ..metal(c, roughness) };
    let gold = Vec3::new(1.0, 0.78, 0.34);
    let cases: Vec<(String, Material, Material)> = vec![
        ("mirror metal walls, rough sphere".into(), metal(gold, 0.0), metal(Vec3::ONE, 0.5)),
        ("rough metal walls, mirror plastic sphere".into(), metal(gold, 0.3), plastic(Vec3::splat(0.5), 0.0)),
        ("alpha under the delta threshold".into(), metal(Vec3::ONE, threshold * 0.99), plastic(gold, threshold * 0.99)),
        ("alpha over the delta threshold".into(), metal(Vec3::ONE, threshold * 1.01), plastic(gold, threshold * 1.01)),
        ("roughness 1".into(), metal(gold, 1.0), plastic(Vec3::ONE, 1.0)),
        ("black metal, white plastic".into(), metal(Vec3::ZERO, 0.2), plastic(Vec3::ONE, 0.2)),
        (
            "half metal".into(),
            Material { metallic: 0.5, ..metal(gold, 0.4) },
            Material { metallic: 0.3, ..metal(gold, 0.05) },
        ),
        (
            "specular 0 metal and plastic".into(),
            Material { specular: 0.0, ..metal(gold, 0.3) },
            Material { specular: 0.0, ..plastic(gold, 0.3) },
        ),
    ];
    for (what, wall, sphere) in cases {
        let mut scene = room_with(wall, sphere, 1.0, 5.0);
        for (max_depth, rr_depth, mis_heuristic, kind) in [
            (1, 5, MisHeuristic::Power, LightSamplerKind::Power),
            (8, 1, MisHeuristic::Power, LightSamplerKind::Tree),
            (5, 0, MisHeuristic::Balance, LightSamplerKind::Uniform),
        ] {
            scene.set_light_sampler(kind);
            let s = RenderSettings { max_depth, rr_depth, mis_heuristic, light_sampler: kind, ..base.clone() };
            let what = format!("{what}, {kind:?}, depth {max_depth}, rr {rr_depth}, {mis_heuristic:?}");
            same_with_lanes_or_not(&mut scene, &s, &what);
        }
    }
}

/// An open scene (a floor, a metal and a Lambert sphere, a small emitter) under each kind of
/// light the kernel samples besides emissive triangles: environments (uniform, sampled and not;
/// the sunset map, with and without MIS compensation; a 1e4 uniform sky) and point, spot and
/// directional lights.
#[test]
fn eight_lanes_match_under_environments_and_punctual_lights() {
    let mut b = SceneBuilder::default();
    let floor = b.material(lambert(Vec3::splat(0.5)));
    let steel = b.material(metal(Vec3::new(0.9, 0.8, 0.7), 0.25));
    let mirror = b.material(Material { metallic: 0.0, ..metal(Vec3::splat(0.2), 0.0) });
    let white = b.material(lambert(Vec3::ONE));
    let e = b.material(emitter(Vec3::splat(3.0)));
    b.quad(Vec3::ZERO, Vec3::X * 4.0, Vec3::NEG_Z * 4.0, floor);
    b.sphere(Vec3::new(-0.6, 0.5, 0.0), 0.5, 2, false, steel);
    b.sphere(Vec3::new(0.6, 0.4, 0.2), 0.4, 2, false, white);
    b.sphere(Vec3::new(0.0, 0.3, 0.8), 0.3, 2, false, mirror);
    b.quad(Vec3::new(0.0, 2.0, -1.0), Vec3::X * 0.3, Vec3::Z * 0.3, e);
    // A shade 1e-4 under the point light (below), about 5e-5 of the way from the objects: inside
    // the point light's shadow-ray stop (1e-5 short), outside an area light's (1e-4 short).
    b.quad(Vec3::new(1.0, 1.5 - 1e-4, 1.0), Vec3::X * 0.05, Vec3::Z * 0.05, white);
    b.look_at(Vec3::new(0.0, 1.2, 3.0), Vec3::new(0.0, 0.4, 0.0), 50.0);
    let mut scene = b.build();
    let sunset = |mis_compensation| {
        Environment::load(&root().join("scenes/env/sunset.exr"), 1.0, 30.0, true, mis_compensation)
            .expect("scenes/env/sunset.exr")
    };
    let envs = [
        ("no environment", None),
        ("uniform sky, sampled", Some(Environment::uniform(Vec3::new(0.3, 0.4, 0.6), true))),
        ("uniform sky, not sampled", Some(Environment::uniform(Vec3::new(0.3, 0.4, 0.6), false))),
        ("1e4 uniform sky", Some(Environment::uniform(Vec3::splat(1e4), true))),
        ("sunset map", Some(sunset(false))),
        ("sunset map, MIS compensation", Some(sunset(true))),
    ];
    let point = PunctualLight {
        kind: PunctualKind::Point,
        intensity: Vec3::splat(5.0),
        position: Vec3::new(1.0, 1.5, 1.0),
        direction: Vec3::NEG_Y,
    };
    let spot = PunctualLight {
        kind: PunctualKind::Spot { cos_inner: 0.95, cos_outer: 0.8 },
        intensity: Vec3::new(20.0, 10.0, 5.0),
        position: Vec3::new(-1.0, 2.0, 0.5),
        direction: Vec3::new(0.5, -1.0, -0.25).normalize(),
    };
    let sun = PunctualLight {
        kind: PunctualKind::Directional,
        intensity: Vec3::splat(1e4),
        position: Vec3::ZERO,
        direction: Vec3::new(0.3, -1.0, -0.4).normalize(),
    };
    let base = RenderSettings { width: 24, height: 18, spp: 13, seed: 3, ..RenderSettings::default() };
    for (what, env) in envs {
        scene.set_environment(env);
        for (lights, punctual) in [("", vec![]), (", point, spot and sun", vec![point, spot, sun])] {
            scene.set_punctual(punctual);
            for (kind, max_depth, rr_depth) in [(LightSamplerKind::Power, 4, 1), (LightSamplerKind::Tree, 8, 0)] {
                scene.set_light_sampler(kind);
                let s = RenderSettings { max_depth, rr_depth, light_sampler: kind, ..base.clone() };
                same_with_lanes_or_not(&mut scene, &s, &format!("{what}{lights}, {kind:?}"));
            }
        }
    }
}

/// Glass: smooth and rough (alpha just under and over `Ggx::DELTA_ALPHA`, roughness 0.3 and 1),
/// ior 1 (no interface: a delta), 1.0001, 1.5 and 3 (total internal reflection inside the
/// sphere), tinted, as a smooth-shaded closed sphere in a room of Lambert or metal walls.
#[test]
fn eight_lanes_match_through_glass_at_the_extremes() {
    let absorbing = |m: Material, absorption: Vec3| Material { absorption, ..m };
    let base = RenderSettings { width: 24, height: 18, spp: 11, seed: 13, ..RenderSettings::default() };
    let threshold = Ggx::DELTA_ALPHA.sqrt();
    let glass = |ior: f32, roughness: f32, tint: Vec3| Material {
        transmission: 1.0,
        metallic: 0.0,
        ior,
        ..metal(tint, roughness)
    };
    let grey = lambert(Vec3::splat(0.6));
    let cases = [
        ("smooth glass", grey.clone(), glass(1.5, 0.0, Vec3::ONE)),
        ("rough glass 0.3 in a metal room", metal(Vec3::splat(0.9), 0.2), glass(1.5, 0.3, Vec3::ONE)),
        ("glass roughness 1", grey.clone(), glass(1.5, 1.0, Vec3::new(0.9, 0.6, 0.3))),
        ("glass alpha under the delta threshold", grey.clone(), glass(1.5, threshold * 0.99, Vec3::ONE)),
        ("glass alpha over the delta threshold", grey.clone(), glass(1.5, threshold * 1.01, Vec3::ONE)),
        ("ior 1", grey.clone(), glass(1.0, 0.3, Vec3::ONE)),
        ("ior 1.0001", grey.clone(), glass(1.0001, 0.2, Vec3::ONE)),
        ("ior 3, tinted", grey.clone(), glass(3.0, 0.1, Vec3::new(0.2, 0.9, 0.5))),
        // KHR_materials_volume inside: Beer–Lambert on the segments within, on the light samples
        // that leave through a rough surface (none inside: the medium of their side), and a
        // channel that absorbs nothing beside two that do.
        ("absorbing smooth glass", grey.clone(), absorbing(glass(1.5, 0.0, Vec3::ONE), Vec3::new(0.5, 2.0, 0.0))),
        ("absorbing rough glass", grey.clone(), absorbing(glass(1.5, 0.3, Vec3::ONE), Vec3::new(3.0, 0.2, 1.0))),
        ("absorbing glass roughness 1", grey.clone(), absorbing(glass(1.5, 1.0, Vec3::ONE), Vec3::splat(1.5))),
        ("nearly opaque absorbing glass", grey.clone(), absorbing(glass(1.5, 0.2, Vec3::ONE), Vec3::splat(1e4))),
    ];
    for (what, wall, sphere) in cases {
        let mut scene = room_with(wall, sphere, 1.0, 5.0);
        for (max_depth, rr_depth, kind) in [(3, 5, LightSamplerKind::Power), (12, 1, LightSamplerKind::Tree)] {
            scene.set_light_sampler(kind);
            let s = RenderSettings { max_depth, rr_depth, light_sampler: kind, ..base.clone() };
            same_with_lanes_or_not(&mut scene, &s, &format!("{what}, {kind:?}, depth {max_depth}, rr {rr_depth}"));
        }
    }
}

/// All glass of the default index and `roughness`, absorbing `absorption` inside
/// (KHR_materials_volume).
fn absorbing_glass(roughness: f32, absorption: Vec3) -> Material {
    Material { transmission: 1.0, metallic: 0.0, absorption, ..metal(Vec3::ONE, roughness) }
}

/// A lamp inside an absorbing glass ball (rough, so light samples are taken at its inner
/// surface): paths inside the medium reach the lamp by light samples on their own side, which
/// the medium attenuates, and by hitting it; paths outside see it through the glass.
#[test]
fn eight_lanes_match_with_a_lamp_inside_absorbing_glass() {
    // The lamp a quad, or a bulb (a small emissive sphere: one light, whose sure directions the
    // kernel samples eight-wide) with a second bulb outside the ball.
    let scene = |bulb: bool| {
        let mut b = SceneBuilder::default();
        let floor = b.material(lambert(Vec3::splat(0.6)));
        let ball = b.material(absorbing_glass(0.3, Vec3::new(1.5, 0.4, 0.0)));
        let e = b.material(emitter(Vec3::splat(30.0)));
        b.quad(Vec3::new(0.0, -1.0, 0.0), Vec3::X * 3.0, Vec3::NEG_Z * 3.0, floor);
        b.sphere(Vec3::ZERO, 0.7, 2, false, ball);
        if bulb {
            b.sphere(Vec3::new(0.0, 0.05, 0.0), 0.12, 2, false, e);
            b.sphere(Vec3::new(1.2, 0.2, -0.4), 0.15, 2, false, e);
        } else {
            b.quad(Vec3::new(0.0, 0.1, 0.0), Vec3::X * 0.15, Vec3::Z * 0.15, e);
        }
        b.look_at(Vec3::new(0.0, 0.6, 3.0), Vec3::ZERO, 40.0);
        b.build()
    };
    let base = RenderSettings { width: 24, height: 18, spp: 13, seed: 21, ..RenderSettings::default() };
    for (what, bulb) in [("lamp", false), ("bulb", true)] {
        let mut scene = scene(bulb);
        for (max_depth, rr_depth) in [(4, 5), (16, 2)] {
            let s = RenderSettings { max_depth, rr_depth, ..base.clone() };
            same_with_lanes_or_not(&mut scene, &s, &format!("{what} inside absorbing glass, depth {max_depth}"));
        }
    }
}

/// An open sheet of absorbing rough glass (one quad: a path that crosses it through its front
/// face stays in its medium) under a sky, a point light and a sun: light samples of lights at
/// a distance and at infinity through the medium (zero in the channels it absorbs, whole in
/// the one it does not), and paths that escape from it to the sky, which get nothing out of the
/// channels it absorbs.
#[test]
fn eight_lanes_match_under_an_open_absorbing_sheet() {
    let mut b = SceneBuilder::default();
    let floor = b.material(lambert(Vec3::splat(0.6)));
    let sheet = b.material(absorbing_glass(0.4, Vec3::new(0.8, 0.0, 2.5)));
    let e = b.material(emitter(Vec3::splat(6.0)));
    b.quad(Vec3::ZERO, Vec3::X * 3.0, Vec3::NEG_Z * 3.0, floor);
    // Facing the camera and the sky (+y and +z tilt): the camera's rays enter its medium.
    b.quad(Vec3::new(0.0, 0.6, 0.5), Vec3::X * 1.2, Vec3::new(0.0, 0.5, -1.0), sheet);
    b.quad(Vec3::new(0.8, 1.8, -0.5), Vec3::X * 0.2, Vec3::Z * 0.2, e);
    b.look_at(Vec3::new(0.0, 1.6, 2.8), Vec3::new(0.0, 0.3, 0.0), 50.0);
    let mut scene = b.build();
    scene.set_environment(Some(Environment::uniform(Vec3::new(0.3, 0.4, 0.6), true)));
    scene.set_punctual(vec![
        PunctualLight {
            kind: PunctualKind::Point,
            intensity: Vec3::splat(4.0),
            position: Vec3::new(-0.8, 1.2, 0.4),
            direction: Vec3::NEG_Y,
        },
        PunctualLight {
            kind: PunctualKind::Directional,
            intensity: Vec3::splat(3.0),
            position: Vec3::ZERO,
            direction: Vec3::new(0.2, -1.0, -0.3).normalize(),
        },
    ]);
    let base = RenderSettings { width: 24, height: 18, spp: 13, seed: 8, max_depth: 8, ..RenderSettings::default() };
    for kind in [LightSamplerKind::Power, LightSamplerKind::Tree] {
        scene.set_light_sampler(kind);
        let s = RenderSettings { light_sampler: kind, ..base.clone() };
        same_with_lanes_or_not(&mut scene, &s, &format!("open absorbing sheet, {kind:?}"));
    }
}

/// A mesh above `BATCH_RAYS_ABOVE` triangles: the kernel's rays go to the BVH in batches.
#[test]
fn eight_lanes_match_where_the_bvh_batches_rays() {
    let mut b = SceneBuilder::default();
    let grey = b.material(lambert(Vec3::splat(0.7)));
    let e = b.material(emitter(Vec3::splat(4.0)));
    b.sphere(Vec3::ZERO, 1.0, 7, false, grey);
    b.sphere(Vec3::ZERO, 6.0, 1, true, grey);
    b.quad(Vec3::new(0.0, 3.0, 0.0), Vec3::X, Vec3::NEG_Z, e);
    b.look_at(Vec3::new(0.0, 0.5, 3.5), Vec3::ZERO, 40.0);
    let mut scene = b.build();
    assert!(scene.mesh.triangles.len() > BATCH_RAYS_ABOVE);
    assert!(scene.batches_rays());
    let s = RenderSettings { width: 16, height: 12, spp: 9, ..RenderSettings::default() };
    same_with_lanes_or_not(&mut scene, &s, "level-7 sphere");
}

/// A 4×4 texture of `texels` (row-major), `srgb` for colour data.
fn texture(texels: [[u8; 4]; 16], srgb: bool) -> Texture {
    Texture { width: 4, height: 4, texels: texels.to_vec(), srgb }
}

/// Texture `texture` read through texture coordinate set 0, repeating.
fn feed(texture: u32) -> Option<TextureRef> {
    Some(TextureRef { texture, wrap_s: Wrap::Repeat, wrap_t: Wrap::Repeat, set: 0, transform: None })
}

/// [`room`] whose walls, floor, ceiling and sphere are textured: a base colour checker from black
/// to white, and metallic-roughness and specular texels from a mirror (roughness 0, metallic 1:
/// a delta BSDF, which samples no light) and black-white dielectrics with no specular (plain
/// Lambert) to rough plastic, tiled three times across each wall so a bilinear lookup blends
/// neighbours. Each lane's material is resolved at its hit, so one register holds Lambert,
/// plastic, metal and mirror lanes at once.
fn textured_room() -> Scene {
    let mut b = SceneBuilder::default();
    let textured = Material {
        name: "textured".into(),
        base_color: Vec4::ONE,
        base_color_texture: feed(0),
        metallic: 1.0,
        roughness: 1.0,
        metallic_roughness_texture: feed(1),
        specular: 1.0,
        specular_texture: feed(2),
        ..Material::default()
    };
    let bumpy = Material { normal_texture: feed(3), normal_scale: 0.8, ..textured.clone() };
    let w = b.material(textured);
    let n = b.material(bumpy);
    // Untextured plastic whose colour comes from its vertices alone.
    let painted = b.material(Material { name: "painted".into(), roughness: 0.4, ..lambert(Vec3::ONE) });
    let e = b.material(Material { emissive_texture: feed(0), ..emitter(Vec3::splat(9.0)) });
    // A pane of rough glass, normal-mapped: glass lanes bend their normals and frames too.
    let pane = b.material(Material {
        name: "pane".into(),
        transmission: 1.0,
        metallic: 0.0,
        normal_texture: feed(3),
        ..metal(Vec3::ONE, 0.2)
    });
    let first_vertex = b.mesh.positions.len();
    // The floor and back wall normal-mapped; the ceiling and side walls with tangents but no
    // normal map (their frames still follow the tangent).
    for (c, u, v, m) in [
        (Vec3::new(0.0, -1.0, 0.0), Vec3::X, Vec3::NEG_Z, n),
        (Vec3::new(0.0, 1.0, 0.0), Vec3::X, Vec3::Z, w),
        (Vec3::new(-1.0, 0.0, 0.0), Vec3::Z, Vec3::Y, w),
        (Vec3::new(1.0, 0.0, 0.0), Vec3::Y, Vec3::Z, painted),
        (Vec3::new(0.0, 0.0, -1.0), Vec3::X, Vec3::Y, n),
        (Vec3::new(0.3, -0.3, 0.5), Vec3::X * 0.35, Vec3::Y * 0.35, pane),
    ] {
        b.quad(c, u, v, m);
        // Tangent along u; the back wall's bitangent flipped (handedness −1).
        let w = if c.z < 0.0 { -1.0 } else { 1.0 };
        let last = b.mesh.tangents.len();
        b.mesh.tangents[last - 4..].fill(u.extend(w));
    }
    for (i, uv) in b.mesh.uvs[first_vertex..].iter_mut().enumerate() {
        // `SceneBuilder::quad`'s corners in order, three tiles across.
        *uv = [Vec2::new(0.0, 0.0), Vec2::new(3.0, 0.0), Vec2::new(3.0, 3.0), Vec2::new(0.0, 3.0)][i % 4];
    }
    for t in &mut b.mesh.triangles {
        t.flags |= flags::UVS | flags::TANGENTS;
    }
    // Vertex colours on the side walls (the textured one tinted, the painted one coloured).
    let colours =
        [Vec4::new(1.0, 0.2, 0.2, 1.0), Vec4::new(0.2, 1.0, 0.2, 1.0), Vec4::ONE, Vec4::new(0.3, 0.3, 1.0, 1.0)];
    b.mesh.colors.resize(b.mesh.positions.len(), Vec4::ONE);
    for wall in [2, 3] {
        b.mesh.colors[first_vertex + 4 * wall..first_vertex + 4 * wall + 4].copy_from_slice(&colours);
        for t in &mut b.mesh.triangles[2 * wall..2 * wall + 2] {
            t.flags |= flags::COLORS;
        }
    }
    // No texture coordinates or tangents: every hit reads the texel at (0, 0), no normal map.
    b.sphere(Vec3::new(-0.3, -0.6, -0.2), 0.35, 1, false, n);
    // The lamp's radiance textured too: read at each hit and at each point NEE samples on it.
    let (lamp_vertex, lamp_triangle) = (b.mesh.positions.len(), b.mesh.triangles.len());
    b.quad(Vec3::new(0.0, 0.99, 0.0), Vec3::X * 0.25, Vec3::Z * 0.25, e);
    b.mesh.uvs[lamp_vertex..].copy_from_slice(&[Vec2::ZERO, Vec2::X, Vec2::ONE, Vec2::Y]);
    for t in &mut b.mesh.triangles[lamp_triangle..] {
        t.flags |= flags::UVS;
    }
    b.look_at(Vec3::new(0.0, 0.0, 3.5), Vec3::ZERO, 45.0);
    let grey = |i: usize| [(i * 17) as u8, (255 - i * 13) as u8, (i * 29 % 256) as u8, 255];
    let colour = texture(std::array::from_fn(grey), true);
    // G roughness, B metallic: mirror, rough metal, Lambert-like dielectrics, plastic.
    let mr = [[0, 0, 255, 255], [0, 200, 255, 255], [0, 255, 0, 255], [0, 90, 0, 255]];
    let metal_rough = texture(std::array::from_fn(|i| mr[(i + i / 4) % 4]), false);
    // Alpha: the specular weight, none on half the texels (with metallic 0 and specular 0: Lambert).
    let specular = texture(std::array::from_fn(|i| [0, 0, 0, if (i / 2) % 2 == 0 { 0 } else { 255 }]), false);
    // Tangent-space normals tilted up to 60° in every direction, one flat texel.
    let normal = texture(
        std::array::from_fn(|i| {
            let (x, y) = ((i % 4) as f32 / 3.0 * 2.0 - 1.0, (i / 4) as f32 / 3.0 * 2.0 - 1.0);
            let v = Vec3::new(x * 0.6, y * 0.6, 1.0).normalize() * 0.5 + Vec3::splat(0.5);
            if i == 5 {
                [128, 128, 255, 255]
            } else {
                [(v.x * 255.0) as u8, (v.y * 255.0) as u8, (v.z * 255.0) as u8, 255]
            }
        }),
        false,
    );
    Scene::new(b.mesh, b.materials, vec![colour, metal_rough, specular, normal], b.cameras)
}

/// Textured surfaces (base colour, metallic-roughness, specular and emissive textures, normal
/// maps on opaque surfaces and on glass, tangent frames, vertex colours) go through the kernel, each lane's BSDF and shading frame resolved at its own
/// hit as the scalar path resolves them; same bits, with the light tree and by power.
#[test]
fn eight_lanes_match_on_textured_surfaces() {
    same_by_power_and_tree(&mut textured_room(), 3, "textured room");
}

/// [`same_with_lanes_or_not`] at 32×24, 16 spp, seed `seed`, lights chosen by power and by the tree.
fn same_by_power_and_tree(scene: &mut Scene, seed: u64, what: &str) {
    for light_sampler in [LightSamplerKind::Power, LightSamplerKind::Tree] {
        let settings =
            RenderSettings { width: 32, height: 24, spp: 16, seed, light_sampler, ..RenderSettings::default() };
        same_with_lanes_or_not(scene, &settings, &format!("{what} ({light_sampler:?})"));
    }
}

/// Instances (a prototype placed three times, rotated, mirrored and stretched unevenly, so
/// normals go through the inverse transpose and tangents through the linear part): each lane's
/// hit carried to the world as the scalar path carries it (`Scene::surface_point`); same bits,
/// among world-space walls, with a normal map on the prototype.
#[test]
fn eight_lanes_match_on_instances() {
    let mut scene = textured_room();
    use std::mem::take;
    let (mut mesh, materials) = (take(&mut scene.mesh), take(&mut scene.materials));
    let (textures, cameras) = (take(&mut scene.textures), take(&mut scene.cameras));
    let bumpy = 1; // `textured_room`'s normal-mapped material
    let (first_vertex, first_triangle) = (mesh.positions.len(), mesh.triangles.len());
    let mut b = SceneBuilder::default();
    b.sphere(Vec3::ZERO, 0.3, 1, false, bumpy);
    let offset = first_vertex as u32;
    for (v, p) in b.mesh.positions.iter().enumerate() {
        mesh.positions.push(*p);
        mesh.normals.push(p.normalize());
        mesh.tangents.push(Vec3::Y.cross(*p).normalize_or(Vec3::X).extend(if v % 2 == 0 { 1.0 } else { -1.0 }));
        mesh.uvs.push(Vec2::new(p.x + 0.5, p.y + 0.5));
        if !mesh.colors.is_empty() {
            mesh.colors.push(Vec4::ONE);
        }
    }
    for t in &b.mesh.triangles {
        let flags = flags::OBJECT_SPACE | flags::NORMALS | flags::TANGENTS | flags::UVS;
        mesh.triangles.push(Triangle { v: t.v.map(|i| i + offset), material: bumpy, flags });
    }
    mesh.prototypes.push(first_triangle as u32..mesh.triangles.len() as u32);
    let proto = mesh.prototypes.len() as u32 - 1;
    let place = [
        Mat4::from_translation(Vec3::new(0.5, -0.6, 0.1)) * Mat4::from_rotation_y(0.7),
        Mat4::from_translation(Vec3::new(-0.5, 0.2, -0.4)) * Mat4::from_scale(Vec3::new(1.6, 0.7, 1.0)),
        Mat4::from_translation(Vec3::new(0.1, 0.5, 0.3)) * Mat4::from_scale(Vec3::new(-0.8, 0.8, 0.8)),
    ];
    mesh.instances.extend(place.into_iter().filter_map(|m| Instance::new(proto, m)));
    assert_eq!(mesh.instances.len(), 3);
    scene = Scene::new(mesh, materials, textures, cameras);
    same_by_power_and_tree(&mut scene, 5, "instances");
}

/// A room with leaves of `alpha_mode` textured with alpha 0, ⅓, ⅔ and 1 in a checker: before
/// the camera, under the lamp, and two deep.
fn leafy_room(alpha_mode: AlphaMode) -> Scene {
    let mut b = SceneBuilder::default();
    let wall = b.material(lambert(Vec3::splat(0.7)));
    let shiny = b.material(metal(Vec3::new(0.9, 0.2, 0.1), 0.3));
    let e = b.material(emitter(Vec3::splat(8.0)));
    let leaf = Material { alpha_mode, base_color_texture: feed(0), ..lambert(Vec3::new(0.3, 0.8, 0.2)) };
    let leaf = b.material(leaf);
    for (c, u, v, m) in [
        (Vec3::new(0.0, -1.0, 0.0), Vec3::X, Vec3::NEG_Z, wall),
        (Vec3::new(0.0, 1.0, 0.0), Vec3::X, Vec3::Z, wall),
        (Vec3::new(-1.0, 0.0, 0.0), Vec3::Z, Vec3::Y, shiny),
        (Vec3::new(1.0, 0.0, 0.0), Vec3::Y, Vec3::Z, wall),
        (Vec3::new(0.0, 0.0, -1.0), Vec3::X, Vec3::Y, wall),
    ] {
        b.quad(c, u, v, m);
    }
    let (first_vertex, first_triangle) = (b.mesh.positions.len(), b.mesh.triangles.len());
    for (c, u, v) in [
        (Vec3::new(0.1, 0.0, 1.2), Vec3::X * 0.6, Vec3::Y * 0.6),
        (Vec3::new(0.0, 0.7, 0.0), Vec3::X * 0.5, Vec3::Z * 0.5),
        (Vec3::new(-0.4, -0.5, 0.0), Vec3::Z * 0.4, Vec3::Y * 0.4),
        (Vec3::new(-0.3, -0.5, 0.05), Vec3::Z * 0.4, Vec3::Y * 0.4),
    ] {
        b.quad(c, u, v, leaf);
    }
    for (i, uv) in b.mesh.uvs[first_vertex..].iter_mut().enumerate() {
        *uv = [Vec2::new(0.0, 0.0), Vec2::new(2.0, 0.0), Vec2::new(2.0, 2.0), Vec2::new(0.0, 2.0)][i % 4];
    }
    for t in &mut b.mesh.triangles[first_triangle..] {
        t.flags |= flags::UVS;
    }
    b.quad(Vec3::new(0.0, 0.99, 0.0), Vec3::X * 0.3, Vec3::Z * 0.3, e);
    b.look_at(Vec3::new(0.0, 0.0, 3.5), Vec3::ZERO, 45.0);
    let alpha = [255, 0, 85, 170];
    let holes = texture(std::array::from_fn(|i| [200, 255, 120, alpha[(i + i / 4) % 4]]), true);
    Scene::new(b.mesh, b.materials, vec![holes], b.cameras)
}

/// Leaves the rays pass: MASK cut-outs where the texel's alpha is under the cutoff, BLEND
/// surfaces with probability 1 − alpha by the bounce's stochastic-transparency seed (shadow
/// rays carry 1 − alpha of the light). The kernel traces them as the scalar path does (camera
/// rays one at a time through the layers rather than as a bundle, each ray with its sample's
/// seed, partial visibility multiplied in); same bits and ray counts.
#[test]
fn eight_lanes_match_through_cut_outs_and_blended_surfaces() {
    for (alpha_mode, what) in [(AlphaMode::Mask(0.5), "cut-outs"), (AlphaMode::Blend, "blended leaves")] {
        let mut scene = leafy_room(alpha_mode);
        assert!(scene.has_transparency());
        same_by_power_and_tree(&mut scene, 4, what);
        let settings =
            RenderSettings { width: 32, height: 24, spp: 16, seed: 6, max_depth: 2, ..RenderSettings::default() };
        same_with_lanes_or_not(&mut scene, &settings, &format!("{what}, two bounces"));
    }
}

/// The materials the kernel does not shade (`LaneMaterial::table`'s scalar entries), textured
/// where the kind is.
fn materials_the_kernel_hands_over() -> Vec<(&'static str, Material)> {
    let glass = Material { transmission: 1.0, metallic: 0.0, ..metal(Vec3::ONE, 0.0) };
    let rough_glass = Material { transmission: 1.0, metallic: 0.0, ..metal(Vec3::ONE, 0.4) };
    vec![
        ("half glass", Material { transmission: 0.5, ..rough_glass.clone() }),
        ("metal over glass", Material { metallic: 0.5, ..glass.clone() }),
        // Absorbing inside: a path the scalar path sends into it comes back to its lane in the
        // medium, which the kernel then carries.
        (
            "absorbing half glass",
            Material { absorption: Vec3::new(2.0, 0.5, 0.1), transmission: 0.5, ..rough_glass.clone() },
        ),
        ("a coat", Material { clearcoat: 1.0, clearcoat_roughness: 0.1, ..metal(Vec3::new(0.8, 0.2, 0.1), 0.3) }),
        ("sheen", Material { sheen_color: Vec3::ONE, sheen_roughness: 0.5, ..lambert(Vec3::splat(0.5)) }),
        ("unlit", Material { unlit: true, ..lambert(Vec3::new(0.2, 0.9, 0.4)) }),
        ("textured glass", Material { base_color_texture: feed(0), ..glass.clone() }),
        ("a transmission texture", Material { transmission_texture: feed(0), ..lambert(Vec3::ONE) }),
        ("a textured coat", Material { clearcoat: 1.0, clearcoat_texture: feed(0), ..metal(Vec3::ONE, 0.3) }),
        // A lamp too: NEE samples it, and a path that hits it weighs its emission by MIS.
        ("a coated lamp", Material { clearcoat: 1.0, ..emitter(Vec3::new(4.0, 3.0, 2.0)) }),
    ]
}

/// A lane whose ray reaches a surface the kernel does not shade has that vertex shaded by the
/// scalar path's code (`integrator::bounce_from_hit`) and goes on in its lane: at its camera ray
/// (the sphere in view), after diffuse, glossy and glass bounces (the walls, a metal wall, glass
/// spheres of the kernel's own, where η² is carried), at the depth limit, under roulette from
/// the first bounce, with its MIS state for the emission it may find there, and back in the
/// kernel with the state the scalar path left (in the absorbing medium it may have entered). Same
/// bits and ray counts as the scalar path's render, for each material in turn as the sphere, and
/// all of them at once as walls.
#[test]
fn eight_lanes_hand_the_surfaces_they_do_not_shade_to_the_scalar_path() {
    let glass = Material { transmission: 1.0, metallic: 0.0, ..metal(Vec3::ONE, 0.0) };
    let with_texture = |scene: Scene| {
        let mut scene = scene;
        use std::mem::take;
        let (mesh, materials, cameras) = (take(&mut scene.mesh), take(&mut scene.materials), take(&mut scene.cameras));
        let checker = [[250, 30, 90, 255], [20, 200, 60, 255], [128; 4], [255; 4]];
        Scene::new(mesh, materials, vec![texture(std::array::from_fn(|i| checker[i % 4]), true)], cameras)
    };
    for (what, m) in materials_the_kernel_hands_over() {
        let mut scene = with_texture(room_with(lambert(Vec3::splat(0.7)), m, 1.0, 6.0));
        assert!(scene.lanes(&RenderSettings::default()).is_some(), "{what}: the kernel must take the room");
        same_by_power_and_tree(&mut scene, 3, what);
    }
    // Every such material at once, as walls, with the kernel's glass and metal between them.
    let mut b = SceneBuilder::default();
    let handed: Vec<u32> = materials_the_kernel_hands_over().into_iter().map(|(_, m)| b.material(m)).collect();
    let (kernel_glass, kernel_metal) = (b.material(glass), b.material(metal(Vec3::new(0.9, 0.8, 0.5), 0.2)));
    let (floor, e) = (b.material(lambert(Vec3::splat(0.6))), b.material(emitter(Vec3::splat(8.0))));
    b.quad(Vec3::new(0.0, -1.0, 0.0), Vec3::X, Vec3::NEG_Z, floor);
    for (i, &m) in handed.iter().enumerate() {
        let x = -1.0 + 0.2 * i as f32 + 0.1;
        b.quad(Vec3::new(x, 0.0, -1.0), Vec3::X * 0.1, Vec3::Y, m);
    }
    b.quad(Vec3::new(-1.0, 0.0, 0.0), Vec3::Z, Vec3::Y, kernel_metal);
    b.sphere(Vec3::new(0.3, -0.6, 0.2), 0.35, 1, false, kernel_glass);
    b.sphere(Vec3::new(-0.4, -0.7, 0.3), 0.25, 1, false, handed[2]);
    b.quad(Vec3::new(0.0, 0.99, 0.0), Vec3::X * 0.3, Vec3::Z * 0.3, e);
    b.look_at(Vec3::new(0.0, 0.0, 3.5), Vec3::ZERO, 45.0);
    let mut scene = with_texture(b.build());
    same_by_power_and_tree(&mut scene, 9, "every handed-over material");
    for (max_depth, rr_depth) in [(0, 5), (1, 5), (2, 5), (7, 1)] {
        let settings = RenderSettings {
            width: 32,
            height: 24,
            spp: 16,
            seed: 2,
            max_depth,
            rr_depth,
            ..RenderSettings::default()
        };
        same_with_lanes_or_not(
            &mut scene,
            &settings,
            &format!("every handed-over material, depth {max_depth}, roulette from {rr_depth}"),
        );
    }
}

/// The kernel takes a scene where some material it shades is used; the surfaces it does not
/// shade it hands to the scalar path. A scene with none of its own it leaves to the scalar path
/// whole, as it does other integrators and the scalar reference.
#[test]
fn eight_lanes_take_only_what_they_render() {
    let s = RenderSettings::default();
    let mut plain = room(Vec3::splat(0.5), 1.0, 5.0);
    assert!(plain.lanes(&s).is_some());
    for integrator in [IntegratorKind::Nee, IntegratorKind::Bsdf] {
        assert!(plain.lanes(&RenderSettings { integrator, ..s.clone() }).is_none(), "{integrator:?}");
    }
    plain.set_scalar_reference(true);
    assert!(plain.lanes(&s).is_none(), "the scalar reference must not run the kernel");
    let glass = Material { transmission: 1.0, metallic: 0.0, ..metal(Vec3::ONE, 0.0) };
    let shaded = [
        ("a metal surface", metal(Vec3::ONE, 0.3)),
        ("glass", glass.clone()),
        ("absorbing glass", Material { absorption: Vec3::new(0.2, 1.0, 3.0), ..glass.clone() }),
        ("a base colour texture", Material { base_color_texture: feed(0), ..lambert(Vec3::ONE) }),
        ("a normal map", Material { normal_texture: feed(0), ..lambert(Vec3::ONE) }),
        ("an emissive texture", Material { emissive_texture: feed(0), ..emitter(Vec3::ONE) }),
    ];
    let cases = shaded.into_iter().map(|(w, m)| (w, m, true));
    let cases = cases.chain(materials_the_kernel_hands_over().into_iter().map(|(w, m)| (w, m, false)));
    // The light: one the kernel shades, and a coated one it hands over.
    let lamps = [(emitter(Vec3::ONE), true), (Material { clearcoat: 1.0, ..emitter(Vec3::ONE) }, false)];
    for (what, m, shades) in cases {
        for (lamp, lamp_shaded) in &lamps {
            let mut b = SceneBuilder::default();
            let m = b.material(m.clone());
            let e = b.material(lamp.clone());
            b.quad(Vec3::ZERO, Vec3::X, Vec3::Y, m);
            b.quad(Vec3::Z, Vec3::X, Vec3::NEG_Y, e);
            let scene = Scene::new(b.mesh, b.materials, vec![texture([[128; 4]; 16], true)], Vec::new());
            assert_eq!(scene.lanes(&s).is_some(), shades || *lamp_shaded, "{what} (lamp shaded: {lamp_shaded})");
        }
    }
    // Cut-outs and blended surfaces: both taken.
    for alpha_mode in [AlphaMode::Mask(0.5), AlphaMode::Blend] {
        let mut b = SceneBuilder::default();
        let m = b.material(Material { alpha_mode, base_color_texture: feed(0), ..lambert(Vec3::ONE) });
        let e = b.material(emitter(Vec3::ONE));
        b.quad(Vec3::ZERO, Vec3::X, Vec3::Y, m);
        b.quad(Vec3::Z, Vec3::X, Vec3::NEG_Y, e);
        let scene = Scene::new(b.mesh, b.materials, vec![texture([[128; 4]; 16], true)], Vec::new());
        assert!(scene.lanes(&s).is_some(), "{alpha_mode:?}");
    }
}
