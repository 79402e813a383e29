//! Watertight ray–triangle intersection (`renderer/src/triangle.rs`) and the eight-wide leaf test.
//!
//! A ray aimed exactly at an edge shared by two triangles must hit one of them: Möller-Trumbore,
//! which tests each triangle in its own edge frame, lets some through (kept here as a model of
//! the test before the change, and shown to leak on the same rays, so this test can fail).
//! Then: a closed sphere seen from inside is hit by every ray, through the whole BVH; and every
//! test scene renders to the same bits with the eight-wide leaf test as with the one-at-a-time
//! reference.

use renderer::accel::Accel;
use renderer::film::Rect;
use renderer::light::LightSamplerKind;
use renderer::math::{Vec3, Vec3A};
use renderer::sampler::hash_unit as u;
use renderer::testing::{load_bit_test_scene, sum_bits, BIT_TEST_SCENES};
use renderer::triangle::{RtTriangle, WatertightRay};
use renderer::{render_tile, RenderSettings};
use std::collections::HashMap;
use std::path::Path;

/// Möller & Trumbore 1997 as Tessera had it before the watertight test.
fn moller_trumbore(v: [Vec3; 3], o: Vec3, d: Vec3) -> bool {
    let (e1, e2) = (v[1] - v[0], v[2] - v[0]);
    let pvec = d.cross(e2);
    let det = e1.dot(pvec);
    if det == 0.0 || !det.is_finite() {
        return false;
    }
    let inv = 1.0 / det;
    let tvec = o - v[0];
    let b1 = tvec.dot(pvec) * inv;
    if !(0.0..=1.0).contains(&b1) {
        return false;
    }
    let qvec = tvec.cross(e1);
    let b2 = d.dot(qvec) * inv;
    if b2 < 0.0 || b1 + b2 > 1.0 {
        return false;
    }
    e2.dot(qvec) * inv > 0.0
}

/// The icosphere's edges with the two triangles that share each.
fn shared_edges(f: &[[u32; 3]]) -> Vec<((u32, u32), [usize; 2])> {
    let mut by_edge: HashMap<(u32, u32), Vec<usize>> = HashMap::new();
    for (i, t) in f.iter().enumerate() {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            by_edge.entry((a.min(b), a.max(b))).or_default().push(i);
        }
    }
    let mut edges: Vec<_> = by_edge.into_iter().filter(|(_, v)| v.len() == 2).map(|(e, v)| (e, [v[0], v[1]])).collect();
    edges.sort();
    edges
}

#[test]
fn rays_at_shared_edges_hit_one_of_the_two_triangles() {
    let (p, f) = renderer::testing::icosphere(5);
    let edges = shared_edges(&f);
    let tri = |i: usize| [p[f[i][0] as usize], p[f[i][1] as usize], p[f[i][2] as usize]];
    let (mut rays, mut mt_leaks, mut leaks) = (0usize, 0usize, 0usize);
    for (k, ((a, b), pair)) in edges.iter().enumerate() {
        // Points along the edge, as f32 computes them, from origins scattered inside the sphere.
        for j in 0..4u64 {
            let s = (j as f32 + 0.5) / 4.0;
            let target = p[*a as usize] + (p[*b as usize] - p[*a as usize]) * s;
            let seed = 8 * (4 * k as u64 + j);
            let o = (Vec3::new(u(seed), u(seed + 1), u(seed + 2)) - 0.5) * 0.6;
            let d = target - o;
            rays += 1;
            let w = WatertightRay::new(Vec3A::from(o), Vec3A::from(d));
            if !pair.iter().any(|&i| RtTriangle::new(tri(i), 0).intersect(&w, f32::INFINITY).is_some()) {
                leaks += 1;
            }
            if !pair.iter().any(|&i| moller_trumbore(tri(i), o, d)) {
                mt_leaks += 1;
            }
        }
    }
    eprintln!("{rays} rays at shared edges: Möller-Trumbore lets {mt_leaks} through, watertight {leaks}");
    assert!(mt_leaks > 0, "the model of the old test should leak on these rays (else this test proves nothing)");
    assert_eq!(leaks, 0, "{leaks} of {rays} rays slipped between two triangles sharing an edge");
}

#[test]
fn closed_sphere_from_inside_is_hit_by_every_ray() {
    let mut b = renderer::testing::SceneBuilder::default();
    let m = b.material(renderer::testing::lambert(Vec3::splat(0.5)));
    b.sphere(Vec3::new(0.3, -0.2, 0.1), 2.0, 6, false, m);
    let (p, f) = renderer::testing::icosphere(6);
    let mesh = b.mesh;
    let mut accel = Accel::build(&mesh);
    for scalar in [false, true] {
        accel.set_scalar_reference(scalar);
        let mut misses = 0;
        let n = 200_000u64;
        for i in 0..n {
            // Aimed at vertices and edge points, where a non-watertight test leaks.
            let t = &f[(i as usize * 7919) % f.len()];
            let s = u(4 * i);
            let target =
                Vec3::new(0.3, -0.2, 0.1) + (p[t[0] as usize] + (p[t[1] as usize] - p[t[0] as usize]) * s) * 2.0;
            let o = Vec3::new(u(4 * i + 1), u(4 * i + 2), u(4 * i + 3)) - 0.5;
            if accel.intersect(o, target - o, f32::INFINITY).is_none() {
                misses += 1;
            }
        }
        assert_eq!(misses, 0, "{misses} of {n} rays escaped a closed sphere (scalar reference: {scalar})");
    }
}

fn root() -> &'static Path {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))
}

/// The rule for batching: the eight-wide leaf test and the light tree's family walk change no bit
/// of any test scene's image (with the light sampler each scene's `auto` picks, and the tree forced).
#[test]
fn every_test_scene_renders_the_same_bits_with_the_scalar_reference() {
    for (entry, light_sampler) in
        BIT_TEST_SCENES.iter().flat_map(|s| [(*s, LightSamplerKind::Auto), (*s, LightSamplerKind::Tree)])
    {
        let rel = entry.0;
        let mut settings =
            RenderSettings { width: 40, height: 30, spp: 4, seed: 3, light_sampler, ..RenderSettings::default() };
        let mut scene = load_bit_test_scene(root(), entry, &mut settings);
        let rect = Rect { x0: 0, y0: 0, width: settings.width, height: settings.height };
        let simd = render_tile(&scene, &settings, rect, 0..settings.spp);
        scene.set_scalar_reference(true);
        let scalar = render_tile(&scene, &settings, rect, 0..settings.spp);
        let total: f64 = simd.sum_rgb.iter().flatten().sum();
        assert!(total > 0.0, "{rel}: a black image tests nothing");
        assert!(sum_bits(&simd) == sum_bits(&scalar), "{rel} ({light_sampler:?}): the SIMD paths changed the image");
    }
}
