//! Chi-square goodness-of-fit of every sampling routine against its pdf (pbrt-v4 / Mitsuba style):
//! ≥ 10⁶ samples binned in (θ, φ), expected counts from the pdf integrated over each cell, low cells
//! pooled, family-wise α = 0.01 with a Šidák correction over every configuration in this file.

use renderer::bsdf::Bsdf;
use renderer::clearcoat::Clearcoat;
use renderer::light::LightSamplerKind;
use renderer::math::{cosine_hemisphere_pdf, sample_cosine_hemisphere, Vec3};
use renderer::microfacet::Ggx;
use renderer::sampler::{PixelSample, SamplerKind};
use renderer::sheen::Sheen;
use renderer::stats::{chi2_directions, sidak, ChiSquare};
use renderer::testing::{emitter, SceneBuilder};

const N: usize = 1_000_000;

fn rng(i: usize, seed: u64) -> PixelSample {
    PixelSample::new(SamplerKind::Independent, seed, (7, 11), i as u32)
}

fn bsdf(metallic: f32, roughness: f32, specular: f32) -> Bsdf {
    Bsdf {
        base_color: Vec3::new(0.7, 0.5, 0.3),
        metallic,
        ggx: Ggx::from_roughness(roughness),
        specular,
        f0_dielectric: Bsdf::f0_from_ior(1.5, Vec3::ONE),
        transmission: 0.0,
        eta: 1.5,
        coat: None,
        sheen: None,
    }
}

fn bsdf_case(b: Bsdf, cos_theta_o: f32, seed: u64) -> ChiSquare {
    let sin = (1.0 - cos_theta_o * cos_theta_o).sqrt();
    let wo = Vec3::new(sin * 0.8, sin * 0.6, cos_theta_o);
    chi2_directions(
        N,
        20,
        40,
        // Near grazing the lobe hugs the horizon: integrate the pdf on a finer grid there.
        if cos_theta_o < 0.1 { 96 } else { 24 },
        |i| {
            let s = rng(i, seed);
            b.sample(wo, s.get_1d(0), s.get_2d(2)).filter(|x| !x.delta).map(|x| x.wi)
        },
        |wi| b.pdf(wo, wi) as f64,
    )
}

#[test]
fn every_sampler_matches_its_pdf() {
    let mut results: Vec<(String, ChiSquare)> = Vec::new();

    results.push((
        "cosine hemisphere".into(),
        chi2_directions(
            N,
            20,
            40,
            8,
            |i| Some(sample_cosine_hemisphere(rng(i, 1).get_2d(0))),
            |w| cosine_hemisphere_pdf(w.z) as f64,
        ),
    ));

    // GGX visible normals through the metal BSDF, several roughnesses and incident angles down to grazing.
    for (k, &r) in [0.2f32, 0.5, 0.8, 1.0].iter().enumerate() {
        for (j, &c) in [1.0f32, 0.7, 0.2, 0.02].iter().enumerate() {
            results.push((
                format!("GGX metal roughness {r} cosθo {c}"),
                bsdf_case(bsdf(1.0, r, 1.0), c, 100 + (k * 10 + j) as u64),
            ));
        }
    }
    // The full glTF mixture (diffuse + dielectric specular) and pure Lambert.
    for (k, &r) in [0.3f32, 0.7].iter().enumerate() {
        for (j, &c) in [0.9f32, 0.3].iter().enumerate() {
            results.push((
                format!("glTF dielectric roughness {r} cosθo {c}"),
                bsdf_case(bsdf(0.0, r, 1.0), c, 200 + (k * 10 + j) as u64),
            ));
        }
    }
    results.push(("Lambert via Bsdf".into(), bsdf_case(bsdf(0.0, 1.0, 0.0), 0.5, 300)));

    // KHR_materials_clearcoat (rough coat, straight and tilted coat normal) and KHR_materials_sheen
    // over the glTF mixture, alone and together.
    let tilted = Vec3::new(0.35, -0.2, 0.9).normalize();
    for (k, &(coat_r, normal, sheen_r)) in [
        (Some(0.3f32), Vec3::Z, None),
        (Some(0.1), tilted, None),
        (Some(0.6), tilted, None),
        (None, Vec3::Z, Some(0.3f32)),
        (None, Vec3::Z, Some(1.0)),
        (Some(0.2), tilted, Some(0.5)),
    ]
    .iter()
    .enumerate()
    {
        for (j, &c) in [0.9f32, 0.35, 0.05].iter().enumerate() {
            let mut b = bsdf(0.0, 0.5, 1.0);
            b.coat = coat_r.map(|r| Clearcoat { weight: 0.8, ggx: Ggx::from_roughness(r), normal });
            b.sheen = sheen_r.map(|r| Sheen::new(Vec3::new(0.9, 0.6, 0.8), r));
            results.push((
                format!("layered: coat {coat_r:?} normal {normal:?}, sheen {sheen_r:?}, cosθo {c}"),
                bsdf_case(b, c, 500 + (k * 10 + j) as u64),
            ));
        }
    }

    // Area-light sampling from a point: two triangles of different size, emission and orientation.
    let mut b = SceneBuilder::default();
    let bright = b.material(emitter(Vec3::splat(5.0)));
    let dim = b.material(emitter(Vec3::splat(1.0)));
    b.triangles(
        &[Vec3::new(-1.0, 1.0, -1.0), Vec3::new(1.0, 1.0, -1.0), Vec3::new(0.0, 1.0, 1.0)],
        &[[0, 1, 2]],
        bright,
    );
    b.triangles(&[Vec3::new(1.5, -0.5, -0.5), Vec3::new(1.5, 0.5, -0.5), Vec3::new(1.5, 0.0, 1.5)], &[[0, 2, 1]], dim);
    let mut scene = b.build();
    let reference = Vec3::new(0.1, -0.2, 0.05);
    let normal = Some(Vec3::new(0.3, 0.9, 0.1).normalize());
    for kind in [LightSamplerKind::Uniform, LightSamplerKind::Power, LightSamplerKind::Tree] {
        scene.lights.set_kind_exact(kind, &scene.mesh);
        let scene = &scene;
        let light_chi2 = chi2_directions(
            N,
            40,
            80,
            64,
            |i| {
                let s = rng(i, 400);
                scene
                    .lights
                    .sample(&scene.mesh, &scene.materials, &scene.textures, reference, normal, s.get_1d(0), s.get_2d(2))
                    .map(|ls| ls.wi)
            },
            |w| match scene.intersect(reference, w, f32::INFINITY) {
                Some(h) => {
                    let sp = scene.mesh.surface_point(h.triangle, h.b1, h.b2);
                    scene.lights.pdf(h.triangle, reference, normal, sp.p, sp.ng) as f64
                }
                None => 0.0,
            },
        );
        results.push((format!("area lights from a point, {kind:?} selection"), light_chi2));
    }

    let alpha = sidak(0.01, results.len());
    let mut failures = Vec::new();
    for (name, r) in &results {
        println!(
            "{name}: χ² = {:.1}, dof {}, p = {:.3e} (pooled {} cells)",
            r.statistic, r.dof, r.p_value, r.pooled_cells
        );
        if r.p_value.is_nan() || r.p_value <= alpha {
            failures.push(format!("{name}: p = {:.3e} < {alpha:.3e}", r.p_value));
        }
    }
    assert!(failures.is_empty(), "chi-square rejections:\n{}", failures.join("\n"));
}

#[test]
fn environment_sampling_matches_its_pdf() {
    use renderer::environment::Environment;
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/env/sunset.exr");
    let mut results = Vec::new();
    // Bin in the map's own frame (pole = +Y, φ = atan2(z, x)), so the 32×64 chi-square cells are
    // exactly 16×16-texel blocks of the 1024×512 map and the sub-grid hits texel centres: the expected
    // counts are then exact for a piecewise-constant pdf, sun included.
    for (rotate, mis_compensation) in [(0.0f32, false), (37.0, false), (0.0, true), (37.0, true)] {
        let env = Environment::load(&path, 1.0, rotate, true, mis_compensation).expect("sunset.exr");
        let (c, s) = (rotate.to_radians().cos(), rotate.to_radians().sin());
        let to_map = move |d: Vec3| Vec3::new(c * d.x - s * d.z, d.y, s * d.x + c * d.z);
        let to_world = move |d: Vec3| Vec3::new(c * d.x + s * d.z, d.y, -s * d.x + c * d.z);
        let to_chi = |d: Vec3| Vec3::new(d.x, d.z, d.y);
        let from_chi = |w: Vec3| Vec3::new(w.x, w.z, w.y);
        let r = chi2_directions(
            N,
            32,
            64,
            16,
            |i| env.sample(rng(i, 500 + rotate as u64).get_2d(0)).map(|smp| to_chi(to_map(smp.0))),
            |w| env.pdf(to_world(from_chi(w))) as f64,
        );
        results.push((format!("environment sunset.exr rotated {rotate}°, MIS compensation {mis_compensation}"), r));
    }
    let uniform = Environment::uniform(Vec3::ONE, true);
    results.push((
        "uniform environment".into(),
        chi2_directions(
            N,
            20,
            40,
            8,
            |i| uniform.sample(rng(i, 600).get_2d(0)).map(|s| s.0),
            |w| uniform.pdf(w) as f64,
        ),
    ));
    let alpha = sidak(0.01, results.len());
    for (name, r) in &results {
        println!("{name}: χ² = {:.1}, dof {}, p = {:.3e}", r.statistic, r.dof, r.p_value);
        assert!(r.p_value > alpha, "{name}: p = {:.3e} < {alpha:.3e}", r.p_value);
    }
}

#[test]
fn rough_dielectric_sampling_matches_its_pdf_on_both_sides() {
    use renderer::dielectric::Dielectric;
    let mut results = Vec::new();
    for (k, &eta) in [1.5f32, 1.0 / 1.5, 1.33].iter().enumerate() {
        for (j, &rough) in [0.3f32, 0.7].iter().enumerate() {
            for (i, &c) in [0.9f32, 0.4, 0.1].iter().enumerate() {
                let g = Dielectric { eta, ggx: renderer::microfacet::Ggx::from_roughness(rough), tint: Vec3::ONE };
                let s = (1.0 - c * c).sqrt();
                let wo = Vec3::new(s * 0.8, s * 0.6, c);
                let seed = 700 + (k * 100 + j * 10 + i) as u64;
                let r = chi2_directions(
                    N,
                    20,
                    40,
                    if c < 0.2 || rough > 0.5 { 96 } else { 24 },
                    |n| {
                        let smp = rng(n, seed);
                        g.sample(wo, smp.get_1d(0), smp.get_2d(2)).map(|x| x.0)
                    },
                    |wi| g.pdf(wo, wi) as f64,
                );
                results.push((format!("dielectric eta {eta:.3} roughness {rough} cosθo {c}"), r));
            }
        }
    }
    let alpha = sidak(0.01, results.len());
    let mut failures = Vec::new();
    for (name, r) in &results {
        println!("{name}: χ² = {:.1}, dof {}, p = {:.3e}", r.statistic, r.dof, r.p_value);
        if r.p_value.is_nan() || r.p_value <= alpha {
            failures.push(format!("{name}: p = {:.3e}", r.p_value));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn rough_dielectric_is_energy_bounded_and_weights_match() {
    use renderer::dielectric::Dielectric;
    for eta in [1.5f32, 1.0 / 1.5] {
        for rough in [0.05f32, 0.3, 1.0] {
            let g = Dielectric { eta, ggx: renderer::microfacet::Ggx::from_roughness(rough), tint: Vec3::ONE };
            let wo = Vec3::new(0.5, 0.1, 0.86).normalize();
            let (mut sum, n) = (0.0f64, 100_000);
            for i in 0..n {
                let smp = rng(i, 900);
                if let Some((wi, f, pdf, _)) = g.sample(wo, smp.get_1d(0), smp.get_2d(2)) {
                    let w = f.x * wi.z.abs() / pdf;
                    let expect = g.eval(wo, wi).x * wi.z.abs() / g.pdf(wo, wi);
                    assert!((w - expect).abs() <= 1e-3 * expect.max(1.0));
                    // Count transmitted energy in flux terms (× η² undoes the radiance scaling).
                    sum += if wi.z < 0.0 { (w * eta * eta) as f64 } else { w as f64 };
                }
            }
            let albedo = sum / n as f64;
            assert!(albedo <= 1.01, "eta {eta} roughness {rough}: albedo {albedo}");
            if rough <= 0.05 {
                // Nearly smooth: single scattering loses almost nothing.
                assert!(albedo > 0.97, "eta {eta} roughness {rough}: albedo {albedo}");
            }
        }
    }
}
