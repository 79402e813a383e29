//! Integrator agreement suite (issue 10): for a matrix of emitters (quad, disc, tessellated spheres of
//! 8…96 segments, tiny and huge triangles, one- and two-sided, near and far, over an open floor and
//! inside a closed box), diffuse and glossy receivers and every light sampler, the three estimators
//! `bsdf`, `nee` and `mis` must agree with each other within statistics, and with the exact
//! irradiance where it is known.
//!
//! Estimates are *region means*: a set of probe rays aimed at points of the receiver, each estimated
//! with independent samples, so the standard error of the mean is exact (Sobol would make it
//! conservative). The analytic value is the irradiance of the emitting polygons themselves (Lambert's
//! polygon formula, exact for any tessellation), so a tessellated sphere is checked against the
//! sphere it really is, not the ideal one.
//!
//! The suite was written against the bug of issue 10 (NEE and MIS 9 % too dark under a 48 × 24 UV
//! sphere): it failed there on every NEE/MIS estimate of a tessellated emitter.

use rayon::prelude::*;
use renderer::light::LightSamplerKind;
use renderer::math::{luminance, Vec3};
use renderer::sampler::{PixelSample, SamplerKind};
use renderer::testing::{emitter, lambert, metal, one_sided_emitter, SceneBuilder};
use renderer::{IntegratorKind, RenderSettings, Scene};

/// A camera ray aimed at a point of the receiver, and that point.
#[derive(Clone, Copy)]
struct Probe {
    eye: Vec3,
    target: Vec3,
}

/// Mean and standard error of the luminance averaged over the probes.
#[derive(Clone, Copy, Debug)]
struct Estimate {
    mean: f64,
    se: f64,
}

fn estimate(scene: &Scene, settings: &RenderSettings, probes: &[Probe], samples: u32, seed: u64) -> Estimate {
    let per_probe: Vec<(f64, f64)> = probes
        .par_iter()
        .enumerate()
        .map(|(k, p)| {
            let d = (p.target - p.eye).normalize();
            let (mut s, mut s2, mut rays) = (0.0f64, 0.0f64, 0u64);
            for i in 0..samples {
                let sampler = PixelSample::new(SamplerKind::Independent, seed, (k as u32, 7), i);
                let l = renderer::integrator::radiance(scene, settings, p.eye, d, &sampler, &mut rays);
                assert!(l.is_finite(), "non-finite radiance {l:?}");
                let y = luminance(l) as f64;
                s += y;
                s2 += y * y;
            }
            let n = samples as f64;
            let mean = s / n;
            let var = ((s2 - n * mean * mean) / (n - 1.0)).max(0.0);
            (mean, var / n)
        })
        .collect();
    let k = per_probe.len() as f64;
    Estimate {
        mean: per_probe.iter().map(|p| p.0).sum::<f64>() / k,
        se: (per_probe.iter().map(|p| p.1).sum::<f64>()).sqrt() / k,
    }
}

/// Irradiance at `x` (normal `n`) from a triangle of uniform radiance `le` seen in full: Lambert's
/// polygon formula E = L/2 · |Σᵢ Θᵢ (n · γ̂ᵢ)|, Θᵢ the angle edge i subtends at x and γ̂ᵢ the unit
/// normal of the plane through x and that edge (Arvo 1995, "Applications of Irradiance Tensors").
fn triangle_irradiance(x: Vec3, n: Vec3, v: [Vec3; 3], le: f64) -> f64 {
    let a = v.map(|p| (p - x).as_dvec3());
    let n = n.as_dvec3();
    let mut sum = 0.0;
    for i in 0..3 {
        let (p, q) = (a[i], a[(i + 1) % 3]);
        let theta = p.normalize().dot(q.normalize()).clamp(-1.0, 1.0).acos();
        let g = p.cross(q);
        if g.length() > 0.0 {
            sum += theta * n.dot(g.normalize());
        }
    }
    0.5 * le * sum.abs()
}

/// Exact outgoing radiance of a Lambert receiver of albedo `rho` at `x` lit directly by the
/// emissive triangles of material `light_material` whose emitting side faces `x`. Valid for the
/// convex or planar emitters used here (no emitter triangle shadows another one that faces `x`) and
/// emitters wholly above the receiver's plane.
fn analytic_lambert(scene: &Scene, light_material: u32, closed: bool, le: f64, rho: f64, x: Vec3, n: Vec3) -> f64 {
    let two_sided = scene.materials[light_material as usize].double_sided;
    let mut e = 0.0;
    for (i, t) in scene.mesh.triangles.iter().enumerate() {
        if t.material != light_material {
            continue;
        }
        let v = scene.mesh.vertices(i as u32);
        assert!(v.iter().all(|p| (*p - x).dot(n) > 0.0), "emitter must lie above the receiver");
        let ng = (v[1] - v[0]).cross(v[2] - v[0]);
        let faces = ng.dot(x - v[0]) > 0.0;
        if faces || (two_sided && !closed) {
            e += triangle_irradiance(x, n, v, le);
        }
    }
    rho / std::f64::consts::PI * e
}

#[derive(Clone, Copy, Debug)]
enum Emitter {
    /// 1 × 1 quad at height 1 (every emitter is centred at the origin, the floor below it).
    Quad,
    /// Disc of radius 0.5 at height 1 (48-triangle fan).
    Disc,
    /// UV sphere (segments × segments/2) of radius 0.3 at this height above the floor.
    Sphere { segments: u32, height: f32 },
    /// Triangle of side 0.01 at height 0.5, radiance 1e4.
    Tiny,
    /// Triangle of side 60 at height 2 (most of the sky).
    Huge,
}

struct Case {
    scene: Scene,
    light_material: u32,
    /// A closed emitter (sphere): its back faces are hidden behind its front faces.
    closed: bool,
    le: f64,
    receiver_albedo: Option<f64>,
    probes: Vec<Probe>,
    /// The BSDF-only estimator finds the light often enough to be compared.
    bsdf_ok: bool,
    max_depth: u32,
}

/// Emitter centred at the origin (as modellers place lights: small coordinates, hence small ulps),
/// receiver floor below it at y = −height (Lambert 0.4, or a rough metal); probes on a ring of
/// points under the emitter, seen from 45° (diffuse) or from the mirror direction of the light
/// (glossy, so the highlight is in view).
fn open_floor(emitter_kind: Emitter, two_sided: bool, glossy: bool) -> Case {
    let mut b = SceneBuilder::default();
    let floor = if glossy { b.material(metal(Vec3::splat(0.8), 0.3)) } else { b.material(lambert(Vec3::splat(0.4))) };
    let (le, height) = match emitter_kind {
        Emitter::Tiny => (1e4, 0.5),
        Emitter::Sphere { height, .. } => (11.11, height),
        Emitter::Huge => (1.0, 2.0),
        _ => (5.0, 1.0),
    };
    let y0 = -height;
    b.quad(Vec3::new(0.0, y0, 0.0), Vec3::new(5.0, 0.0, 0.0), Vec3::new(0.0, 0.0, -5.0), floor);
    let m = if two_sided { emitter(Vec3::splat(le)) } else { one_sided_emitter(Vec3::splat(le)) };
    let light = b.material(m);
    let down = Vec3::NEG_Y;
    let c = Vec3::ZERO;
    match emitter_kind {
        // u × v = (1,0,0) × (0,0,1) = (0,−1,0): facing the floor.
        Emitter::Quad => b.quad(c, Vec3::new(0.5, 0.0, 0.0), Vec3::new(0.0, 0.0, 0.5), light),
        Emitter::Disc => b.disc(c, down, 0.5, 48, light),
        Emitter::Sphere { segments, .. } => b.uv_sphere(c, 0.3, segments, segments / 2, light),
        Emitter::Tiny | Emitter::Huge => {
            let s = if matches!(emitter_kind, Emitter::Tiny) { 0.01 } else { 60.0 };
            let p = [
                c + Vec3::new(-s * 0.5, 0.0, s * 0.3),
                c + Vec3::new(0.0, 0.0, -s * 0.6),
                c + Vec3::new(s * 0.5, 0.0, s * 0.3),
            ];
            b.triangles(&p, &[[0, 1, 2]], light);
        }
    }
    let ring = match emitter_kind {
        Emitter::Tiny => 0.2,
        _ => 0.25 * height.max(1.6),
    };
    let probes = (0..12)
        .map(|k| {
            let phi = k as f32 * std::f32::consts::TAU / 12.0;
            let r = if k == 0 { 0.0 } else { ring * (1.0 + (k % 3) as f32) / 3.0 };
            let target = Vec3::new(r * phi.cos(), y0, r * phi.sin());
            let eye = if glossy {
                // Mirror the light's centre in the floor plane: the highlight is along this ray.
                let to_light = (c - target).normalize();
                let mirror = Vec3::new(-to_light.x, to_light.y, -to_light.z);
                let off = if mirror.x.abs() + mirror.z.abs() < 1e-3 { Vec3::new(0.3, 0.0, 0.0) } else { Vec3::ZERO };
                target + (mirror + off).normalize() * 0.1
            } else {
                target + Vec3::new(phi.cos() + 0.7, 1.0, phi.sin()).normalize() * 0.1
            };
            Probe { eye, target }
        })
        .collect();
    let bsdf_ok = match emitter_kind {
        Emitter::Tiny => false,
        Emitter::Sphere { height, .. } => height < 2.0,
        _ => true,
    };
    Case {
        scene: b.build(),
        light_material: light,
        closed: matches!(emitter_kind, Emitter::Sphere { .. }),
        le: le as f64,
        receiver_albedo: (!glossy).then_some(0.4),
        probes,
        bsdf_ok,
        max_depth: 1,
    }
}

/// A closed box (inward Lambert walls, albedo 0.5) with a one-sided sphere light inside. With
/// `max_depth` > 1 indirect light off the walls is part of what must agree; with 1 (diffuse floor)
/// the floor's direct light is known exactly.
fn closed_box(segments: u32, glossy: bool, max_depth: u32) -> Case {
    let mut b = SceneBuilder::default();
    let wall = b.material(lambert(Vec3::splat(0.5)));
    let floor = if glossy { b.material(metal(Vec3::splat(0.8), 0.3)) } else { wall };
    let light = b.material(one_sided_emitter(Vec3::splat(11.11)));
    let s = 4.0;
    // Six inward-facing faces of [-1,1]³ (u × v points inwards).
    b.quad(Vec3::new(0.0, -s, 0.0), Vec3::new(s, 0.0, 0.0), Vec3::new(0.0, 0.0, -s), floor);
    b.quad(Vec3::new(0.0, s, 0.0), Vec3::new(s, 0.0, 0.0), Vec3::new(0.0, 0.0, s), wall);
    b.quad(Vec3::new(-s, 0.0, 0.0), Vec3::new(0.0, 0.0, s), Vec3::new(0.0, s, 0.0), wall);
    b.quad(Vec3::new(s, 0.0, 0.0), Vec3::new(0.0, s, 0.0), Vec3::new(0.0, 0.0, s), wall);
    b.quad(Vec3::new(0.0, 0.0, -s), Vec3::new(0.0, s, 0.0), Vec3::new(s, 0.0, 0.0), wall);
    b.quad(Vec3::new(0.0, 0.0, s), Vec3::new(s, 0.0, 0.0), Vec3::new(0.0, s, 0.0), wall);
    b.uv_sphere(Vec3::new(0.02, 0.01, -0.03), 0.3, segments, segments / 2, light);
    let probes = (0..12)
        .map(|k| {
            let phi = k as f32 * std::f32::consts::TAU / 12.0;
            let target = Vec3::new(2.4 * phi.cos(), -s, 2.4 * phi.sin());
            Probe { eye: Vec3::new(-2.0, 2.4, 2.8), target }
        })
        .collect();
    Case {
        scene: b.build(),
        light_material: light,
        closed: true,
        le: 11.11,
        receiver_albedo: (!glossy && max_depth == 1).then_some(0.5),
        probes,
        bsdf_ok: true,
        max_depth,
    }
}

/// Compares every estimator of one case; returns the failures (described) instead of panicking, so
/// one run reports the whole matrix.
fn check(name: &str, mut case: Case, failures: &mut Vec<String>) {
    const Z: f64 = 5.0;
    let settings = |integrator| RenderSettings {
        integrator,
        max_depth: case.max_depth,
        rr_depth: 1000,
        sampler: SamplerKind::Independent,
        ..RenderSettings::default()
    };
    let mut estimates: Vec<(String, Estimate)> = Vec::new();
    if case.bsdf_ok {
        let samples = if case.max_depth > 1 { 65536 } else { 16384 };
        estimates
            .push(("bsdf".into(), estimate(&case.scene, &settings(IntegratorKind::Bsdf), &case.probes, samples, 1)));
    }
    for ls in [LightSamplerKind::Uniform, LightSamplerKind::Power, LightSamplerKind::Tree] {
        case.scene.set_light_sampler(ls);
        for integrator in [IntegratorKind::Nee, IntegratorKind::Mis] {
            let e = estimate(&case.scene, &settings(integrator), &case.probes, 8192, 2);
            estimates.push((format!("{integrator:?}/{ls:?}").to_lowercase(), e));
        }
    }
    if let Some(rho) = case.receiver_albedo {
        let exact: f64 = case
            .probes
            .iter()
            .map(|p| analytic_lambert(&case.scene, case.light_material, case.closed, case.le, rho, p.target, Vec3::Y))
            .sum::<f64>()
            / case.probes.len() as f64;
        for (what, e) in &estimates {
            let z = (e.mean - exact) / e.se.max(1e-9 * exact);
            if z.abs() > Z {
                failures.push(format!(
                    "{name}: {what} = {:.5} ± {:.5}, exact {exact:.5} ({:+.2} %, z = {z:.1})",
                    e.mean,
                    e.se,
                    100.0 * (e.mean / exact - 1.0)
                ));
            }
        }
    }
    for i in 0..estimates.len() {
        for j in i + 1..estimates.len() {
            let ((a, ea), (b, eb)) = (&estimates[i], &estimates[j]);
            let z = (ea.mean - eb.mean) / (ea.se * ea.se + eb.se * eb.se).sqrt().max(1e-12);
            if z.abs() > Z {
                failures.push(format!(
                    "{name}: {a} = {:.5} ± {:.5} vs {b} = {:.5} ± {:.5} (z = {z:.1})",
                    ea.mean, ea.se, eb.mean, eb.se
                ));
            }
        }
    }
    eprintln!(
        "{name}: {}",
        estimates.iter().map(|(w, e)| format!("{w} {:.4}±{:.4}", e.mean, e.se)).collect::<Vec<_>>().join(", ")
    );
}

#[test]
fn integrators_agree_on_every_light_shape() {
    let mut failures = Vec::new();
    let shapes = [
        ("quad", Emitter::Quad),
        ("disc", Emitter::Disc),
        ("sphere 8", Emitter::Sphere { segments: 8, height: 0.9 }),
        ("sphere 24", Emitter::Sphere { segments: 24, height: 0.9 }),
        ("sphere 48", Emitter::Sphere { segments: 48, height: 0.9 }),
        ("sphere 96", Emitter::Sphere { segments: 96, height: 0.9 }),
        ("sphere 48 far", Emitter::Sphere { segments: 48, height: 4.2 }),
        ("tiny triangle", Emitter::Tiny),
        ("huge triangle", Emitter::Huge),
    ];
    for (name, shape) in shapes {
        for two_sided in [false, true] {
            for glossy in [false, true] {
                if glossy && matches!(shape, Emitter::Tiny | Emitter::Huge) {
                    continue; // a highlight of a 0.01 triangle is a needle; the huge one is the sky
                }
                let label = format!(
                    "{name}, {}, {}",
                    if two_sided { "two-sided" } else { "one-sided" },
                    if glossy { "glossy" } else { "diffuse" }
                );
                check(&label, open_floor(shape, two_sided, glossy), &mut failures);
            }
        }
    }
    for segments in [8, 48] {
        for (glossy, depth) in [(false, 1), (false, 4), (true, 4)] {
            let label =
                format!("closed box, sphere {segments}, {}, depth {depth}", if glossy { "glossy" } else { "diffuse" });
            check(&label, closed_box(segments, glossy, depth), &mut failures);
        }
    }
    assert!(failures.is_empty(), "{} disagreements:\n{}", failures.len(), failures.join("\n"));
}

/// The probe helper itself: a tessellated sphere's polygon irradiance approaches the ideal sphere's
/// π L sin²θ as the tessellation refines (so the analytic values above are the right ones).
#[test]
fn polygon_irradiance_matches_the_ideal_sphere() {
    let mut b = SceneBuilder::default();
    let light = b.material(one_sided_emitter(Vec3::ONE));
    b.uv_sphere(Vec3::new(0.0, 4.2, 0.0), 0.3, 192, 96, light);
    let scene = b.build();
    let e = analytic_lambert(&scene, light, true, 1.0, std::f64::consts::PI, Vec3::ZERO, Vec3::Y);
    let sin2 = (0.3f64 / 4.2).powi(2);
    let ideal = std::f64::consts::PI * sin2;
    assert!((e / ideal - 1.0).abs() < 2e-3, "{e} vs {ideal}");
}
