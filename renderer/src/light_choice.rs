//! `--light-sampler auto`: chooses power, uniform or tree selection for a scene by *measured
//! benefit*, with a small deterministic pilot run at scene preparation.
//!
//! Why a pilot and not a light count: the count says nothing about benefit. Four 1152-triangle
//! sphere bulbs are 4608 "lights" to a count (the old rule picked the tree, whose walk then made
//! each sample 2.25–2.7× dearer), yet whether the tree pays for that depends on where the lights
//! are and on what a walk costs: on `scenes/veach` (four equal bulbs seen from everywhere) uniform
//! selection reached 1.6× lower error than the tree at equal time while a walk cost 2.25× a power
//! sample (docs/speed-vs-accuracy/summary.md); since the walk chooses among eight children per
//! AVX pass (1.54×) the tree is 2.0× as efficient there; on `scenes/sphere_lights` (four unequal
//! bulbs over a floor) the tree was 1.3× better than uniform and 2.4× better than power (issue 10,
//! `tessera bench convergence --switches light_sampler`).
//! (Since closed convex emitters became one light each, `bulb`, those scenes have four lights,
//! sampled by their cones; the three choices then measure within 14 % of each other there. The
//! pilot picks power on `veach`, and on `sphere_lights` the tree through its camera, uniform
//! without one: `tests/light_choice.rs`.)
//!
//! The pilot: the first surfaces hit by `PILOT_POINTS` camera rays (stratified over the image; for a
//! scene seen by no camera ray, area-weighted points on its non-emissive surfaces), and at each
//! `PILOT_REPLICATES` independently scrambled Sobol sets of `PILOT_SAMPLES` unshadowed next-event
//! estimates f·Le·cos·w/pdf towards the camera with every candidate (w: the render's MIS weight
//! against BSDF sampling), the same numbers for all candidates. Score = Σ over points of the
//! relative variance of the estimate (measured across the replicates, so that it sees what Sobol's
//! stratification does with each selection; see `pilot_variance`; the light a further bounce
//! gathers, the same for every candidate, adds its variance: `rest_of_light`), × a per-sample cost model (1 for
//! power and uniform, 1 + `TREE_FIXED_COST` + `TREE_LEVEL_COST` × tree depth for the tree). The
//! lowest score wins.
//! Everything is a function of the scene alone (hashed scrambles, no clocks), so a farm worker and
//! `tessera render` choose the same sampler: the determinism rule holds.
//!
//! Both refinements were measured against the choice that wins at equal time
//! (`bench_peers.py --variants none --runs 5 --tessera-args "--light-sampler K"`, issue 15). With
//! independent samples the pilot chose power on `sphere_light` at every image shape tried, where
//! the tree was 1.9× as efficient (relMSE 1.23e-4 in 0.59 s against 3.54e-4 in 0.39 s; 2.2× since
//! the walk chooses among eight children at a time: 1.03e-4 in 0.622 s against 0.405 s, 2026-11-23).
//! Replicates alone fix that but on `veach` score the three within 2 % and choose uniform, power
//! or tree with the image's shape (the tree was 1.65× as efficient there, relMSE 1.94e-3 in 0.24 s
//! against 3.92e-3 in 0.19 s; now 2.0×, 1.41e-3 in 0.274 s against 0.196 s): unweighted, NEE's
//! variance on veach is that of the glossy plates' reflections of the bulbs, which BSDF sampling
//! carries in the render whatever the selection. With the MIS weight the tree scores 1.3–1.6×
//! better there at every shape.

use crate::bsdf::Bsdf;
use crate::camera::Camera;
use crate::light::{LightSamplerKind, LightSet};
use crate::material::Material;
use crate::math::{cosine_hemisphere_pdf, luminance, power_heuristic, Frame, Vec2, Vec3};
use crate::mesh::Mesh;
use crate::sampler::dims;
use crate::scene::Scene;
use crate::texture::Texture;

/// Shading points of the pilot.
pub const PILOT_POINTS: u64 = 256;
/// Light samples per replicate (one Sobol set of this size, as the render's first samples).
pub const PILOT_SAMPLES: u64 = 16;
/// Independently scrambled replicates per point and candidate: the spread of their means is the
/// pilot's variance (see `pilot_variance`).
pub const PILOT_REPLICATES: u64 = 8;
/// Extra cost of one tree level (of the binary depth log2 N) relative to a whole path sample with
/// power selection: measured on `scenes/sphere_lights` (4608 emissive triangles, log2 N = 12.2)
/// with `tessera bench` (256×192, 16 spp, medians of 3, three runs each): a tree sample costs 1.54×
/// a power sample (0.209 against 0.136 s), (1.54 − 1) / 12.2 ≈ 0.044. (It was 2.25× and 0.10
/// before the walk evaluated a node's children and grandchildren in one AVX pass, then 1.73× and
/// 0.06 until the walk chose among eight children at a time, `light_tree::WideNode`.) Measured
/// again after the walk's d-scaled importances (2026-11-23, walk 170 → 133 ns): 0.175, 0.175 and
/// 0.178 s against 0.108, 0.112 and 0.113 s, 1.56× and ≈ 0.046, within the spread of the figure
/// above, so it stays: the tree's paths also trace more shadow rays (2.33 rays a path against
/// 2.04: fewer of its light samples face away), which the faster walk does not change.
/// Measured again once a batch's walks were interleaved (`LightSet::select_batch`, 2026-11-24;
/// one thread, 128×96, 64 spp, 11 alternating runs, median of per-pair ratios): tree ÷ power
/// 1.38 against 1.44 for the binary before, in the same hour (two threads, `tessera bench`
/// 256×192, 16 spp, median of three rounds' ratios: 1.29 against 1.47, noisier). A level then
/// costs ≈ 0.86 × as much, 0.038; the constant stays at 0.044, the change being inside the
/// spread of the figures it was set from.
pub const TREE_LEVEL_COST: f64 = 0.044;
/// What a tree sample costs over a power sample whatever the tree's depth: a walk's setup and its
/// root's eight-wide importance evaluation, which a tree of two lights pays as much as one of
/// thousands. Without it the model put a two-triangle lamp's tree at 1.044× a power sample; it
/// measures 1.17× on `scenes/cornell` and 1.13× on `scenes/glass` (two threads, 128×96, 256 spp,
/// 5 alternating runs, medians 0.927 / 0.794 s and 1.402 / 1.239 s), and 1.63× on
/// `scenes/sphere_light` (2208 lights: 0.691 / 0.423 s), where the depth term alone gives 1.49×.
/// Fitted with `TREE_LEVEL_COST` kept (from the unrounded ratios): 0.124, 0.088 and 0.145, so 0.12.
pub const TREE_FIXED_COST: f64 = 0.12;

/// A uniform number in [0, 1) from a hash of (stream, index).
fn rand(stream: u64, i: u64) -> f32 {
    crate::sampler::hash_unit(stream.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ i)
}

/// A shading point of the pilot: position (offset off the surface), normal on the viewer's side,
/// direction to the viewer, and the BSDF there (None: Lambert, for points no camera ray found).
struct PilotPoint {
    p: Vec3,
    n: Vec3,
    wo: Vec3,
    bsdf: Option<Bsdf>,
}

/// First hits of a stratified grid of camera rays (`view`: camera and image size).
fn camera_points(scene: &Scene, view: Option<(Camera, u32, u32)>) -> Vec<PilotPoint> {
    let Some((camera, w, h)) = view else { return Vec::new() };
    let side = (PILOT_POINTS as f64).sqrt() as u64;
    let mut out = Vec::new();
    for k in 0..side * side {
        let film = Vec2::new(
            ((k % side) as f32 + rand(8, k)) / side as f32 * w as f32,
            ((k / side) as f32 + rand(9, k)) / side as f32 * h as f32,
        );
        let d = camera.ray_direction(film, w, h);
        out.extend(shading_point(scene, camera.origin, d));
    }
    out
}

/// The point a ray from `o` along `d` shades, as a pilot point: None where it finds nothing, an
/// emitter or a surface no light sample can reach (delta-only: a mirror, smooth glass).
fn shading_point(scene: &Scene, o: Vec3, d: Vec3) -> Option<PilotPoint> {
    let hit = scene.intersect(o, d, f32::INFINITY)?;
    let sp = scene.surface_point(&hit);
    let material = scene.mesh.triangles[hit.triangle as usize].material;
    if scene.materials[material as usize].is_emissive() {
        return None;
    }
    let n = if sp.ng.dot(d) < 0.0 { sp.ng } else { -sp.ng };
    let bsdf = scene.bsdf(material, &sp);
    if bsdf.is_delta_only() {
        return None;
    }
    Some(PilotPoint { p: scene.spawn_origin(sp.p, n, sp.plane_error), n, wo: -d, bsdf: Some(bsdf) })
}

/// Deterministic area-weighted points on non-emissive world triangles, either side (instances'
/// object-space triangles are left out: the camera's view points cover them).
fn surface_points(scene: &Scene) -> Vec<PilotPoint> {
    let (mesh, materials) = (&scene.mesh, &scene.materials);
    let mut cdf = Vec::new();
    let mut tris = Vec::new();
    let mut total = 0.0f64;
    for (i, t) in mesh.triangles.iter().enumerate() {
        if t.flags & crate::mesh::flags::OBJECT_SPACE != 0
            || materials.get(t.material as usize).is_none_or(|m| m.is_emissive())
        {
            continue;
        }
        let a = mesh.area(i as u32) as f64;
        if a > 0.0 && a.is_finite() {
            total += a;
            cdf.push(total);
            tris.push(i as u32);
        }
    }
    if tris.is_empty() {
        return Vec::new();
    }
    (0..PILOT_POINTS)
        .map(|k| {
            let u = rand(1, k) as f64 * total;
            let j = cdf.partition_point(|&c| c <= u).min(tris.len() - 1);
            let b = crate::math::sample_uniform_triangle(Vec2::new(rand(2, k), rand(3, k)));
            let sp = mesh.surface_point(tris[j], b.y, b.z);
            let n = if rand(4, k) < 0.5 { sp.ng } else { -sp.ng };
            PilotPoint { p: scene.spawn_origin(sp.p, n, sp.plane_error), n, wo: n, bsdf: None }
        })
        .collect()
}

/// Σ over points of the relative variance of the unshadowed NEE estimate with the light set's
/// current selection, *as the render's sampler sees it*.
///
/// Why replicates of Sobol means and not the variance of independent samples: the render draws a
/// light sample's (selection, position) from one Owen-scrambled Sobol 4D set, and a selection
/// that keeps neighbouring `u` on neighbouring emitters (the tree: its leaves are in spatial
/// order) turns Sobol's stratification of `u` into stratification over the emitters. Independent
/// samples cannot see that: on `scenes/sphere_light` they score the tree 1.28× better than power
/// in variance, while with Sobol it is 2.9× (issue 15's note). So each point draws
/// `PILOT_REPLICATES` independently scrambled `PILOT_SAMPLES`-sample Sobol sets (the dimensions
/// the integrator uses: position in 0–1, selection in 2), and the variance of the mean is measured
/// across the replicates (unbiased, R − 1 degrees of freedom), × `PILOT_SAMPLES` to put it per
/// sample. Every candidate sees the same scrambles (common random numbers).
fn pilot_variance(
    lights: &LightSet,
    mesh: &Mesh,
    materials: &[Material],
    textures: &[Texture],
    points: &[PilotPoint],
    rest: &[(f64, f64)],
) -> f64 {
    let mut per_point = Vec::with_capacity(points.len());
    for (k, pt) in points.iter().enumerate() {
        let frame = Frame::from_normal(pt.n);
        let wo = frame.to_local(pt.wo);
        per_point.push(across_replicates(|r| {
            let seed = crate::sampler::hash_u64(0x5eed_0000 ^ (k as u64 * PILOT_REPLICATES + r)) as u32;
            let mut sum = 0.0f64;
            for i in 0..PILOT_SAMPLES {
                let v = crate::sampler::sobol_4d(i as u32, seed);
                let c = nee_estimate(lights, mesh, materials, textures, pt, &frame, wo, v);
                sum += if c.is_finite() { c } else { 0.0 };
            }
            sum
        }));
    }
    // The light the point gathers after a further bounce, the same for every candidate
    // (`rest_of_light`): its mean adds to the level, its variance to the point's.
    for (p, r) in per_point.iter_mut().zip(rest) {
        *p = (p.0 + r.0, p.1 + r.1);
    }
    // Relative to each point's own level (as the image relMSE is per pixel), floored at 1 % of the
    // average level so that points no light reaches do not dominate.
    let avg = per_point.iter().map(|p| p.0).sum::<f64>() / per_point.len().max(1) as f64;
    per_point.iter().map(|&(m, v)| v / (m * m + 0.01 * avg * avg).max(1e-30)).sum()
}

/// One unshadowed next-event estimate f·Le·cos·w/pdf (luminance) at `pt` with the light set's
/// current selection, from the Sobol set `v` (the dimensions the integrator uses: position in 0–1,
/// selection in 2); `frame` is `pt`'s and `wo` its outgoing direction in it.
#[allow(clippy::too_many_arguments)]
fn nee_estimate(
    lights: &LightSet,
    mesh: &Mesh,
    materials: &[Material],
    textures: &[Texture],
    pt: &PilotPoint,
    frame: &Frame,
    wo: Vec3,
    v: [f32; 4],
) -> f64 {
    let u_sel = v[(dims::LIGHT_SELECT % 4) as usize];
    let u = Vec2::new(v[(dims::LIGHT_POS % 4) as usize], v[(dims::LIGHT_POS % 4 + 1) as usize]);
    match lights.sample(mesh, materials, textures, pt.p, Some(pt.n), u_sel, u) {
        Some(ls) if ls.pdf > 0.0 && ls.wi.dot(pt.n) > 0.0 => {
            let wi = frame.to_local(ls.wi);
            let (f, bsdf_pdf) = match &pt.bsdf {
                Some(b) => {
                    let (f, p) = b.eval_pdf(wo, wi);
                    (luminance(f) as f64, p)
                }
                None => (std::f64::consts::FRAC_1_PI, cosine_hemisphere_pdf(wi.z)),
            };
            // The render's MIS weight: where BSDF sampling finds the light better (a glossy
            // reflection of it), NEE's share is small, and so is its variance.
            let w = if ls.delta { 1.0 } else { power_heuristic(ls.pdf, bsdf_pdf) as f64 };
            f * luminance(ls.le) as f64 * wi.z as f64 * w / ls.pdf as f64
        }
        _ => 0.0,
    }
}

/// Per point, the mean and per-sample variance (measured as `pilot_variance` measures NEE's, across
/// Sobol replicates) of the light it gathers after one more bounce: a BSDF-sampled direction and, at
/// the surface it meets, the unshadowed power-selected NEE estimate `pilot_variance` takes (emitters
/// met are NEE's and MIS's business, not counted). It is the same for every candidate, so it cannot favour one; it stands
/// for the variance no light selection at the first hit can remove, which the image's relMSE also
/// holds. Without it the pilot compared first-hit NEE alone: on `scenes/cornell` at 4:3 it scored
/// the tree 16 % lower in variance than power, but the render's relMSE against the reference was
/// the same with either (2.895e-4 tree, 2.889e-4 power, 128², 256 spp, 5 runs) while the tree took
/// 1.16× the time. In an open scene (veach's plates, sphere_light's floor) a bounce finds little,
/// and the scores are NEE's as before.
fn rest_of_light(scene: &mut Scene, points: &[PilotPoint]) -> Vec<(f64, f64)> {
    scene.lights.set_kind_exact(LightSamplerKind::Power, &scene.mesh);
    let scene = &*scene;
    let mut out = Vec::with_capacity(points.len());
    for (k, pt) in points.iter().enumerate() {
        let Some(bsdf) = &pt.bsdf else {
            out.push((0.0, 0.0));
            continue;
        };
        let frame = Frame::from_normal(pt.n);
        let wo = frame.to_local(pt.wo);
        out.push(across_replicates(|r| {
            let stream = k as u64 * PILOT_REPLICATES + r;
            let seed_bsdf = crate::sampler::hash_u64(0x1d1d_0000 ^ stream) as u32;
            let seed_light = crate::sampler::hash_u64(0x1d2d_0000 ^ stream) as u32;
            let mut sum = 0.0f64;
            for i in 0..PILOT_SAMPLES {
                let a = crate::sampler::sobol_4d(i as u32, seed_bsdf);
                let b = crate::sampler::sobol_4d(i as u32, seed_light);
                let c = bounce_estimate(scene, pt, bsdf, &frame, wo, a, b);
                sum += if c.is_finite() { c } else { 0.0 };
            }
            sum
        }));
    }
    out
}

/// The mean of [`PILOT_REPLICATES`] replicates' means and the per-sample variance measured across
/// them (unbiased, R − 1 degrees of freedom, × [`PILOT_SAMPLES`] to put it per sample);
/// `replicate(r)` is replicate r's sum over its samples.
fn across_replicates(mut replicate: impl FnMut(u64) -> f64) -> (f64, f64) {
    let (mut s, mut s2) = (0.0f64, 0.0f64);
    for r in 0..PILOT_REPLICATES {
        let m = replicate(r) / PILOT_SAMPLES as f64;
        s += m;
        s2 += m * m;
    }
    let r = PILOT_REPLICATES as f64;
    let mean = s / r;
    let var_of_mean = ((s2 - r * mean * mean) / (r - 1.0)).max(0.0);
    (mean, var_of_mean * PILOT_SAMPLES as f64)
}

/// One sample of `rest_of_light`'s estimate (luminance): f·|cos|/pdf at the point times the
/// NEE estimate at the surface the sampled direction meets (`nee_estimate`, with its MIS weight).
fn bounce_estimate(
    scene: &Scene,
    pt: &PilotPoint,
    bsdf: &Bsdf,
    frame: &Frame,
    wo: Vec3,
    a: [f32; 4],
    b: [f32; 4],
) -> f64 {
    let u_dir = Vec2::new(a[(dims::BSDF_DIR % 4) as usize], a[(dims::BSDF_DIR % 4 + 1) as usize]);
    let Some(bs) = bsdf.sample(wo, a[(dims::BSDF_LOBE % 4) as usize], u_dir) else { return 0.0 };
    if bs.pdf <= 0.0 || bs.wi.z <= 0.0 {
        return 0.0;
    }
    let weight = luminance(bs.f) as f64 * bs.wi.z as f64 / bs.pdf as f64;
    let Some(next) = shading_point(scene, pt.p, frame.to_world(bs.wi)) else { return 0.0 };
    let next_frame = Frame::from_normal(next.n);
    let next_wo = next_frame.to_local(next.wo);
    let (mesh, materials, textures) = (&scene.mesh, &scene.materials, &scene.textures);
    weight * nee_estimate(&scene.lights, mesh, materials, textures, &next, &next_frame, next_wo, b)
}

/// The pilot's choice for `scene` seen through `view` (camera, width, height), and the scores it
/// compared. Leaves the scene's light set switched to the choice.
pub fn choose(scene: &mut Scene, view: Option<(Camera, u32, u32)>) -> (LightSamplerKind, Vec<(LightSamplerKind, f64)>) {
    if scene.lights.finite_count() < 2 {
        scene.lights.set_kind_exact(LightSamplerKind::Power, &scene.mesh);
        return (LightSamplerKind::Power, Vec::new());
    }
    let mut points = camera_points(scene, view);
    if points.len() < PILOT_POINTS as usize / 8 {
        points.extend(surface_points(scene));
    }
    let rest = rest_of_light(scene, &points);
    let mut scores = Vec::new();
    for kind in [LightSamplerKind::Power, LightSamplerKind::Uniform, LightSamplerKind::Tree] {
        scene.lights.set_kind_exact(kind, &scene.mesh);
        let cost = match kind {
            LightSamplerKind::Tree => {
                1.0 + TREE_FIXED_COST + TREE_LEVEL_COST * (scene.lights.finite_count() as f64).log2()
            }
            _ => 1.0,
        };
        let v = pilot_variance(&scene.lights, &scene.mesh, &scene.materials, &scene.textures, &points, &rest);
        scores.push((kind, v * cost));
    }
    let best =
        scores.iter().copied().fold((LightSamplerKind::Power, f64::INFINITY), |b, s| if s.1 < b.1 { s } else { b });
    scene.lights.set_kind_exact(best.0, &scene.mesh);
    (best.0, scores)
}
