//! Furnace tests: inside a closed uniform emitter of radiance 1, a white Lambert sphere must render
//! exactly 1 everywhere (energy conservation with no loss), and GGX metals never more than 1.

use renderer::film::Rect;
use renderer::math::Vec3;
use renderer::testing::{furnace, lambert, metal};
use renderer::{render_tile, IntegratorKind, RenderSettings};

fn settings(integrator: IntegratorKind, spp: u32) -> RenderSettings {
    RenderSettings {
        width: 24,
        height: 24,
        spp,
        integrator,
        max_depth: 1000,
        rr_depth: 1000,
        ..RenderSettings::default()
    }
}

#[test]
fn white_lambert_sphere_vanishes_in_the_furnace() {
    let scene = furnace(lambert(Vec3::ONE));
    for integrator in [IntegratorKind::Bsdf, IntegratorKind::Nee, IntegratorKind::Mis] {
        let s = settings(integrator, 32);
        let sums = render_tile(&scene, &s, Rect { x0: 0, y0: 0, width: 24, height: 24 }, 0..s.spp);
        let mut worst_z = 0.0f32;
        for i in 0..sums.rect.pixels() {
            let m = sums.mean(i);
            if integrator == IntegratorKind::Bsdf {
                // With BSDF sampling every path carries exactly 1 (albedo 1, unbounded depth, no
                // roulette), up to f32 rounding along the path.
                assert!(m.iter().all(|c| (c - 1.0).abs() < 1e-3), "{integrator:?} pixel {i}: {m:?}");
            } else {
                // NEE estimates are random per path; the mean must be 1 within noise.
                let sd = sums.variance_of_mean(i).sqrt();
                worst_z = worst_z.max((m[0] - 1.0).abs() / sd.max(1e-6));
            }
        }
        assert!(worst_z < 5.0, "{integrator:?}: worst z {worst_z}");
    }
}

#[test]
fn grey_lambert_sphere_reflects_its_albedo() {
    // A convex sphere of albedo a sees only the emitter, so it reflects exactly a.
    let scene = furnace(lambert(Vec3::splat(0.5)));
    let s = settings(IntegratorKind::Mis, 64);
    let sums = render_tile(&scene, &s, Rect { x0: 8, y0: 8, width: 8, height: 8 }, 0..s.spp);
    for i in 0..sums.rect.pixels() {
        let m = sums.mean(i)[0];
        let sd = sums.variance_of_mean(i).sqrt();
        assert!((m - 0.5).abs() < 5.0 * sd + 1e-4, "pixel {i}: {m} ± {sd}");
    }
}

#[test]
fn ggx_metals_never_gain_energy() {
    let mut previous_mean = f32::INFINITY;
    for roughness in [0.0f32, 0.05, 0.3, 0.6, 1.0] {
        let scene = furnace(metal(Vec3::ONE, roughness));
        let s = settings(IntegratorKind::Mis, 64);
        let sums = render_tile(&scene, &s, Rect { x0: 0, y0: 0, width: 24, height: 24 }, 0..s.spp);
        let mut min = f32::INFINITY;
        for i in 0..sums.rect.pixels() {
            let m = sums.mean(i)[0];
            let sd = sums.variance_of_mean(i).sqrt();
            assert!(m.is_finite());
            assert!(m <= 1.0 + 4.0 * sd + 1e-4, "roughness {roughness}, pixel {i}: {m} ± {sd}");
            min = min.min(m);
        }
        if roughness == 0.0 {
            // A perfect white mirror loses nothing.
            assert!(min > 0.999, "mirror furnace min {min}");
        }
        // Single-scattering GGX loses more energy the rougher it is.
        let mean: f32 = (0..sums.rect.pixels()).map(|i| sums.mean(i)[0]).sum::<f32>() / sums.rect.pixels() as f32;
        assert!(mean <= previous_mean + 1e-3, "roughness {roughness}: mean {mean} above the smoother {previous_mean}");
        previous_mean = mean;
    }
}

#[test]
fn white_lambert_sphere_vanishes_under_a_uniform_environment() {
    use renderer::environment::EnvironmentSettings;
    use renderer::testing::SceneBuilder;
    for sampling in [true, false] {
        let mut b = SceneBuilder::default();
        let m = b.material(lambert(Vec3::ONE));
        b.sphere(Vec3::ZERO, 1.0, 3, false, m);
        b.look_at(Vec3::new(0.0, 0.0, 4.0), Vec3::ZERO, 35.0);
        let mut scene = b.build();
        let env = EnvironmentSettings { color: Some([1.0, 1.0, 1.0]), sampling, ..Default::default() };
        scene.attach_environment(&env, std::path::Path::new("."), true).unwrap();
        for integrator in [IntegratorKind::Bsdf, IntegratorKind::Nee, IntegratorKind::Mis] {
            let s = RenderSettings { environment: env.clone(), ..settings(integrator, 32) };
            let sums = render_tile(&scene, &s, Rect { x0: 0, y0: 0, width: 24, height: 24 }, 0..s.spp);
            let mut worst = 0.0f32;
            for i in 0..sums.rect.pixels() {
                let m = sums.mean(i)[0];
                let sd = sums.variance_of_mean(i).sqrt();
                worst = worst.max((m - 1.0).abs() / sd.max(1e-4));
            }
            assert!(worst < 5.0, "sampling {sampling}, {integrator:?}: worst z {worst}");
        }
    }
}

fn glass(roughness: f32, ior: f32) -> renderer::material::Material {
    renderer::material::Material {
        name: "glass".into(),
        base_color: renderer::math::Vec4::ONE,
        metallic: 0.0,
        roughness,
        transmission: 1.0,
        ior,
        ..Default::default()
    }
}

#[test]
fn smooth_glass_vanishes_in_the_furnace_and_rough_glass_never_gains() {
    for (roughness, ior) in [(0.0f32, 1.5f32), (0.0, 1.0001), (0.0, 3.0), (0.3, 1.5), (1.0, 1.5)] {
        let scene = furnace(glass(roughness, ior));
        for integrator in [IntegratorKind::Bsdf, IntegratorKind::Mis] {
            let s = settings(integrator, 64);
            let sums = render_tile(&scene, &s, Rect { x0: 0, y0: 0, width: 24, height: 24 }, 0..s.spp);
            let (mut worst_low, mut worst_high) = (0.0f32, 0.0f32);
            for i in 0..sums.rect.pixels() {
                let m = sums.mean(i)[0];
                let sd = sums.variance_of_mean(i).sqrt().max(1e-4);
                assert!(m.is_finite());
                worst_high = worst_high.max((m - 1.0) / sd);
                worst_low = worst_low.max((1.0 - m) / sd);
            }
            assert!(worst_high < 5.0, "roughness {roughness} ior {ior} {integrator:?}: gains energy (z {worst_high})");
            if roughness == 0.0 {
                // Smooth glass loses nothing: every path eventually leaves and sees radiance 1.
                assert!(
                    worst_low < 5.0,
                    "roughness {roughness} ior {ior} {integrator:?}: loses energy (z {worst_low})"
                );
            }
        }
    }
}

/// Mean over the image and its standard error, plus the worst per-pixel z above and below 1.
fn furnace_stats(scene: &renderer::Scene, integrator: IntegratorKind, spp: u32) -> (f64, f64, f32, f32) {
    let s = settings(integrator, spp);
    let sums = render_tile(scene, &s, Rect { x0: 0, y0: 0, width: 24, height: 24 }, 0..s.spp);
    let (mut sum, mut var, mut n) = (0.0f64, 0.0f64, 0.0f64);
    let (mut worst_low, mut worst_high) = (0.0f32, 0.0f32);
    for i in 0..sums.rect.pixels() {
        let m = sums.mean(i)[0];
        assert!(sums.mean(i).iter().all(|c| c.is_finite()), "pixel {i} not finite");
        let sd = sums.variance_of_mean(i).sqrt().max(1e-4);
        worst_high = worst_high.max((m - 1.0) / sd);
        worst_low = worst_low.max((1.0 - m) / sd);
        sum += m as f64;
        var += (sd as f64).powi(2);
        n += 1.0;
    }
    (sum / n, var.sqrt() / n, worst_high, worst_low)
}

fn layered(clearcoat: f32, coat_roughness: f32, sheen: f32, sheen_roughness: f32) -> renderer::material::Material {
    renderer::material::Material {
        name: "layered".into(),
        clearcoat,
        clearcoat_roughness: coat_roughness,
        sheen_color: Vec3::splat(sheen),
        sheen_roughness,
        ..lambert(Vec3::ONE)
    }
}

#[test]
fn smooth_clearcoat_over_white_lambert_vanishes_in_the_furnace() {
    // A mirror coat reflects c·F(μo) and scales what is below by exactly 1 − c·F(μo): no loss, no gain.
    for c in [0.5f32, 1.0] {
        let scene = furnace(layered(c, 0.0, 0.0, 0.0));
        for integrator in [IntegratorKind::Bsdf, IntegratorKind::Mis] {
            let (mean, se, high, low) = furnace_stats(&scene, integrator, 64);
            assert!(high < 5.0 && low < 5.0, "clearcoat {c} {integrator:?}: z +{high} −{low}, mean {mean}");
            assert!((mean - 1.0).abs() < 5.0 * se + 1e-4, "clearcoat {c} {integrator:?}: mean {mean} ± {se}");
        }
    }
}

#[test]
fn rough_clearcoat_never_gains_energy() {
    for r in [0.05f32, 0.3, 0.7, 1.0] {
        let scene = furnace(layered(1.0, r, 0.0, 0.0));
        let (mean, se, high, _) = furnace_stats(&scene, IntegratorKind::Mis, 64);
        assert!(high < 5.0 && mean < 1.0 + 5.0 * se, "coat roughness {r}: gains (z {high}, mean {mean})");
        // Single-scattering GGX loses a few percent at most at roughness 1 (Kulla & Conty 2017).
        assert!(mean > 0.93, "coat roughness {r}: loses too much ({mean})");
    }
}

#[test]
fn white_sheen_over_white_lambert_vanishes_in_the_furnace() {
    // f = f_sheen + (1 − E(μo))·base: with a white base the sphere reflects E + (1 − E) = 1, to the
    // accuracy of the tabulated albedo E (its interpolation error is the 0.5 % allowed here).
    for r in [0.07f32, 0.3, 0.6, 1.0] {
        let scene = furnace(layered(0.0, 0.0, 1.0, r));
        for integrator in [IntegratorKind::Bsdf, IntegratorKind::Mis] {
            let (mean, se, _, _) = furnace_stats(&scene, integrator, 64);
            assert!((mean - 1.0).abs() < 5.0 * se + 5e-3, "sheen roughness {r} {integrator:?}: mean {mean} ± {se}");
        }
    }
}

#[test]
fn coat_and_sheen_over_rough_metal_never_gain_energy() {
    for r in [0.0f32, 0.4, 1.0] {
        let m = renderer::material::Material {
            clearcoat: 1.0,
            clearcoat_roughness: r,
            sheen_color: Vec3::ONE,
            sheen_roughness: 1.0 - r,
            ..metal(Vec3::ONE, r)
        };
        let scene = furnace(m);
        let (mean, se, high, _) = furnace_stats(&scene, IntegratorKind::Mis, 64);
        assert!(high < 5.0 && mean < 1.0 + 5.0 * se + 5e-3, "roughness {r}: gains (z {high}, mean {mean})");
    }
}
