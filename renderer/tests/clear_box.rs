//! Shadow rays to isolated convex emitters stop at the emitter's box (`renderer::clear_box`,
//! `LightSet::shadow_tmax`): the answers are the full walks' own, but for a walk's false hit on
//! the light's own triangles (rounding, near the sampled point), which the stop leaves out.

use glam::Vec3;
use renderer::math::SHADOW_EPSILON;
use renderer::sampler::hash_unit as u;
use renderer::testing::{emitter, lambert, one_sided_emitter, SceneBuilder};

/// A floor under four lights: an icosphere and a UV sphere (one-sided), a two-sided icosphere
/// with a blocker plate below it, and an icosphere with a small plate reaching into its box
/// (not isolated: no box).
fn scene() -> renderer::scene::Scene {
    let mut b = SceneBuilder::default();
    let floor = b.material(lambert(Vec3::splat(0.5)));
    let one = b.material(one_sided_emitter(Vec3::splat(5.0)));
    let two = b.material(emitter(Vec3::splat(5.0)));
    b.quad(Vec3::ZERO, Vec3::new(6.0, 0.0, 0.0), Vec3::new(0.0, 0.0, -6.0), floor);
    b.sphere(Vec3::new(-3.0, 3.0, 0.0), 0.6, 2, false, one);
    b.uv_sphere(Vec3::new(-1.0, 2.5, 1.0), 0.3, 24, 12, one);
    b.sphere(Vec3::new(1.5, 3.0, -1.0), 0.5, 2, false, two);
    b.quad(Vec3::new(1.5, 1.5, -1.0), Vec3::new(0.4, 0.0, 0.0), Vec3::new(0.0, 0.0, -0.4), floor);
    b.sphere(Vec3::new(3.5, 2.0, 1.0), 0.4, 1, false, one);
    b.quad(Vec3::new(3.5, 1.65, 1.0), Vec3::new(0.1, 0.0, 0.0), Vec3::new(0.0, 0.0, -0.1), floor);
    b.build()
}

#[test]
fn shadow_rays_stopped_at_clear_boxes_see_what_the_full_walks_see() {
    let s = scene();
    let lights = &s.lights.lights;
    let (mut stopped, mut blocked, mut self_hits) = (0, 0, 0);
    let n = 40_000u64;
    for i in 0..n {
        // A point just above the floor, to a random point of a random light triangle, built as
        // the integrator builds its shadow rays.
        let p = Vec3::new(-6.0 + 12.0 * u(4 * i), 0.0, -6.0 + 12.0 * u(4 * i + 1));
        let origin = s.offset_ray_origin(p, Vec3::Y);
        let li = ((u(4 * i + 2) * lights.len() as f32) as usize).min(lights.len() - 1);
        let l = &lights[li];
        let (b1, b2) = (u(4 * i + 3), u(4 * i + 3 + n * 8));
        let (b1, b2) = if b1 + b2 > 1.0 { (1.0 - b1, 1.0 - b2) } else { (b1, b2) };
        let [a, bb, c] = s.mesh.vertices(l.triangle);
        let q = a + (bb - a) * b1 + (c - a) * b2;
        let ng = (bb - a).cross(c - a).normalize();
        let n_side = if ng.dot(origin - q) > 0.0 { ng } else { -ng };
        let target = s.offset_ray_origin(q, n_side);
        let to = target - origin;
        let dist = to.length();
        let d = to / dist;
        let tmax = dist * (1.0 - SHADOW_EPSILON);
        let short = s.lights.shadow_tmax(li as u32, origin, d, tmax);
        assert!(short <= tmax);
        let full = s.accel.occluded(origin, d, tmax);
        let cut = s.accel.occluded(origin, d, short);
        if short < tmax {
            stopped += 1;
        }
        if full {
            blocked += 1;
        }
        if full != cut {
            // Only the stop can differ, and only by a hit beyond it on the light's own triangles.
            assert!(!cut && short < tmax, "ray {i}: the stopped walk is blocked where the full one is not");
            let hit = s.accel.intersect(origin, d, tmax).expect("the full walk is blocked");
            assert!(hit.t >= short, "ray {i}: a hit before the stop ({} < {short})", hit.t);
            // Beyond the stop is the light's box, where only its own triangles are.
            assert!(s.lights.is_light(hit.triangle), "ray {i}: blocked by triangle {} beyond the stop", hit.triangle);
            self_hits += 1;
        }
    }
    // The first three lights have boxes (from the floor their lower faces face the rays); the
    // fourth has none, as the check below shows.
    assert!(stopped > n / 4, "{stopped} of {n} rays stopped at a box");
    // The blocker plate and the back faces of the lights block a good share.
    assert!(blocked > n / 10, "{blocked} of {n} rays blocked");
    assert!(self_hits * 1000 < n, "{self_hits} false self-hits left out");
    eprintln!("{stopped} of {n} rays stopped at a box, {blocked} blocked, {self_hits} false self-hits left out");
}

#[test]
fn only_isolated_convex_lights_have_boxes() {
    let s = scene();
    let lights = &s.lights.lights;
    // A ray from far below each light's lowest triangle centre: stopped only where there is a box.
    let stops = |centre: Vec3| {
        lights.iter().enumerate().any(|(li, l)| {
            let [a, b, c] = s.mesh.vertices(l.triangle);
            let q = (a + b + c) / 3.0;
            if (q - centre).length() > 1.0 {
                return false;
            }
            let o = Vec3::new(q.x + 0.01, 0.01, q.z + 0.02);
            let to = q - o;
            let tmax = to.length() * (1.0 - SHADOW_EPSILON);
            s.lights.shadow_tmax(li as u32, o, to.normalize(), tmax) < tmax
        })
    };
    assert!(stops(Vec3::new(-3.0, 3.0, 0.0)));
    assert!(stops(Vec3::new(-1.0, 2.5, 1.0)));
    assert!(stops(Vec3::new(1.5, 3.0, -1.0)));
    assert!(!stops(Vec3::new(3.5, 2.0, 1.0)), "a plate reaches into this light's box");
}
