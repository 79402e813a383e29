//! Ray queries at every scale: a surface is found however close it lies along the ray.
//!
//! The BVH's node tests once culled every child box the ray leaves before t = 10⁻⁴ (obvhs'
//! `EPSILON`, copied into our node tests), an absolute distance in scene units. A ray leaving a
//! wall within 10⁻⁴ of a corner toward the neighbouring wall then missed that wall and left the
//! room: in the Cornell box 9 of 300 000 rays off its surfaces (`tessera bench rays --scene`,
//! against a test of every triangle), and in a closed room a millimetre across the sky outside
//! showed in 574 of 576 pixels. Here a closed room with a bright sky outside must render
//! black from inside, from a millimetre to a kilometre across, with every BVH, one ray at a time
//! and in batches; and rays off its walls toward a corner must hit the neighbouring wall.
//!
//! And the ray-origin offset once had an absolute part (2⁻¹⁶ within 1/32 of the origin, Wächter
//! & Binder's constants): a lit room a millimetre across came out 5.5 % brighter than the same
//! room a metre across. Now scaled to the scene (`math::offset_scale`), the room renders the same
//! from a millimetre to a kilometre.

use renderer::accel::AccelKind;
use renderer::environment::Environment;
use renderer::film::Rect;
use renderer::math::Vec3;
use renderer::sampler::hash_unit as u;
use renderer::scene::Scene;
use renderer::testing::{lambert, trace_in_batches, SceneBuilder};
use renderer::{render_tile, RenderSettings};

/// Room sides tested, in scene units: a millimetre to a kilometre in glTF's metres.
const SIDES: [f32; 5] = [1e-3, 1e-2, 1.0, 30.0, 1e3];

/// A closed cube of `side` around `center`, front faces inward, white Lambert walls, a camera at
/// its centre looking into a corner, and a uniform sky of radiance 10⁴ outside.
fn closed_room(center: Vec3, side: f32) -> Scene {
    let mut scene = room(center, side).build();
    scene.set_environment(Some(Environment::uniform(Vec3::splat(1e4), true)));
    scene
}

/// [`closed_room`]'s walls and camera, without the sky.
fn room(center: Vec3, side: f32) -> SceneBuilder {
    let mut b = SceneBuilder::default();
    let m = b.material(lambert(Vec3::splat(0.9)));
    let h = side / 2.0;
    let (x, y, z) = (Vec3::X * h, Vec3::Y * h, Vec3::Z * h);
    // quad(c, u, v) faces u × v: each wall's u × v points into the room.
    b.quad(center - y, z, x, m); // floor, normal +y
    b.quad(center + y, x, z, m); // ceiling, −y
    b.quad(center - x, y, z, m); // +x
    b.quad(center + x, z, y, m); // −x
    b.quad(center - z, x, y, m); // +z
    b.quad(center + z, y, x, m); // −z
    b.look_at(center, center + Vec3::new(1.0, -1.0, 1.0) * h, 100.0);
    b
}

/// Rays from just off a wall (the renderer's origin offset), within `side`·10⁻⁵ to `side`·10⁻²
/// of an edge, aimed at the neighbouring wall across that edge, must hit it; shadow rays from the
/// same origins to a point outside the room must be blocked.
#[test]
fn rays_toward_a_near_corner_hit_the_neighbouring_wall() {
    for side in SIDES {
        let center = Vec3::new(0.3, -0.2, 0.1) * side;
        let h = side / 2.0;
        for kind in [AccelKind::Obvhs, AccelKind::ObvhsCompressed, AccelKind::Own] {
            let mut scene = closed_room(center, side);
            scene.use_accel(kind);
            let (mut o, mut d) = (Vec::new(), Vec::new());
            for i in 0..2000u64 {
                // A point on the floor at distance `gap` from the +x wall (x = center.x + h).
                let gap = h * 10f32.powf(-5.0 + 3.0 * u(4 * i));
                let p = center + Vec3::new(h - gap, -h, (u(4 * i + 1) - 0.5) * side * 0.9);
                let origin = scene.offset_ray_origin(p, Vec3::Y);
                // Toward +x, upward and sideways: it crosses x = center.x + h just above the floor.
                let dir = Vec3::new(1.0, 0.2 + u(4 * i + 2), u(4 * i + 3) - 0.5).normalize();
                o.push(origin);
                d.push(dir);
            }
            let mut misses = 0;
            let mut unblocked = 0;
            for k in 0..o.len() {
                misses += scene.intersect(o[k], d[k], f32::INFINITY).is_none() as usize;
                unblocked += !scene.occluded(o[k], d[k], side) as usize;
            }
            // The same rays in batches (the renderer's path for large scenes), where the BVH has them.
            let (mut batch_misses, mut batch_unblocked) = (0, 0);
            if kind != AccelKind::Own {
                let (hits, seen) = trace_in_batches(&mut scene, &o, &d, side);
                batch_misses = hits.iter().filter(|h| h.is_none()).count();
                batch_unblocked = seen.iter().filter(|&&v| v != 0.0).count();
            }
            assert_eq!(
                (misses, unblocked, batch_misses, batch_unblocked),
                (0, 0, 0, 0),
                "room of side {side} ({}): of {} rays toward a near wall, (missed, not blocked) alone and in batches",
                kind.name(),
                o.len()
            );
        }
    }
}

/// The user's view of the same: inside a closed room, nothing of the sky outside may show, at
/// any scale, whichever BVH and whether paths are traced alone or as batches.
#[test]
fn a_closed_room_lets_no_sky_in_at_any_scale() {
    for side in SIDES {
        for kind in [AccelKind::Obvhs, AccelKind::ObvhsCompressed, AccelKind::Own] {
            for batched in [false, true] {
                if batched && kind == AccelKind::Own {
                    continue;
                }
                let mut scene = closed_room(Vec3::new(0.3, -0.2, 0.1) * side, side);
                scene.use_accel(kind);
                scene.set_batch_rays(batched);
                let settings = RenderSettings {
                    width: 24,
                    height: 24,
                    spp: 16,
                    max_depth: 6,
                    seed: 1,
                    ..RenderSettings::default()
                };
                let rect = Rect { x0: 0, y0: 0, width: settings.width, height: settings.height };
                let sums = render_tile(&scene, &settings, rect, 0..settings.spp);
                let lit = sums.sum_rgb.iter().filter(|p| p.iter().any(|&c| c != 0.0)).count();
                assert_eq!(
                    lit,
                    0,
                    "room of side {side} ({}, batched: {batched}): {lit} of {} pixels see the sky through the walls",
                    kind.name(),
                    settings.width * settings.height
                );
            }
        }
    }
}

/// Radiance does not depend on the unit a scene is modelled in: the same lit room at 2⁻¹⁰, 2⁻⁶,
/// 2⁻⁴ and 2¹⁰ times its size (powers of two, so every coordinate scales exactly) renders the
/// image it renders at size 1, within its noise per pixel and within 0.5 % over the whole image
/// (the sample sequences are the same, so the paths correspond one to one and their noise
/// largely cancels in the difference).
#[test]
fn a_lit_room_renders_the_same_at_any_scale() {
    let render = |side: f32| {
        let center = Vec3::new(0.3, -0.2, 0.1) * side;
        let mut b = room(center, side);
        let light = b.material(renderer::testing::emitter(Vec3::splat(20.0)));
        // A small square lamp a little below the ceiling, facing down, off centre.
        let h = side / 2.0;
        b.quad(center + Vec3::new(0.2 * h, 0.9 * h, -0.1 * h), Vec3::X * 0.15 * h, Vec3::Z * 0.15 * h, light);
        let scene = b.build();
        let settings =
            RenderSettings { width: 24, height: 24, spp: 64, max_depth: 8, seed: 5, ..RenderSettings::default() };
        let rect = Rect { x0: 0, y0: 0, width: settings.width, height: settings.height };
        render_tile(&scene, &settings, rect, 0..settings.spp)
    };
    let lum_and_var = |s: &renderer::film::PartialSums| {
        let n = (s.rect.width * s.rect.height) as usize;
        let mean: Vec<f32> = (0..n).map(|i| renderer::stats::lum(s.mean(i))).collect();
        let var: Vec<f32> = (0..n).map(|i| s.variance_of_mean(i)).collect();
        (mean, var)
    };
    let (reference, ref_var) = lum_and_var(&render(1.0));
    let total = |m: &[f32]| m.iter().map(|&v| v as f64).sum::<f64>();
    assert!(total(&reference) > 0.0, "a black image tests nothing");
    for side in [1.0 / 1024.0, 1.0 / 64.0, 1.0 / 16.0, 1024.0] {
        let (mean, var) = lum_and_var(&render(side));
        let t = renderer::stats::z_test(&mean, &var, &reference, &ref_var);
        let ratio = total(&mean) / total(&reference);
        assert_eq!(t.accepted, t.pixels, "side {side}: {t:?}");
        assert!((ratio - 1.0).abs() < 5e-3, "side {side}: the image's mean is {ratio} times that at side 1");
    }
}
