//! Russian roulette must judge a path by what it will carry, not by its radiance-scaled throughput:
//! crossing into glass of index η divides radiance by η² (the BTDF's 1/η² factor), and leaving it
//! multiplies it back. A roulette on raw throughput kills 1 − 1/η² of the paths inside every glass
//! object and returns the survivors η² brighter — unbiased, but a firefly generator (pbrt-v4 §13.4.3
//! tracks `etaScale` for this; Mitsuba its `eta`).

use renderer::film::Rect;
use renderer::material::Material;
use renderer::math::{Vec3, Vec4};
use renderer::testing::{emitter, SceneBuilder};
use renderer::{render_tile, IntegratorKind, RenderSettings};

/// A glass slab (two facing quads, a closed-enough medium for a narrow camera) between the camera
/// and a uniform emitter, roulette from the first bounce on: per-sample (mean, relative std. dev.)
/// of the radiance over all pixels.
fn through_slab(integrator: IntegratorKind) -> (f64, f64) {
    let mut b = SceneBuilder::default();
    let e = b.material(emitter(Vec3::ONE));
    let glass = b.material(Material {
        name: "glass".into(),
        base_color: Vec4::ONE,
        metallic: 0.0,
        roughness: 0.0,
        transmission: 1.0,
        ior: 1.5,
        ..Material::default()
    });
    b.quad(Vec3::new(0.0, 0.0, -3.0), Vec3::X * 50.0, Vec3::Y * 50.0, e);
    // Front face wound towards the camera (+z), back face towards the emitter (−z).
    b.quad(Vec3::new(0.0, 0.0, -0.5), Vec3::X * 20.0, Vec3::Y * 20.0, glass);
    b.quad(Vec3::new(0.0, 0.0, -1.5), Vec3::Y * 20.0, Vec3::X * 20.0, glass);
    b.look_at(Vec3::new(0.0, 0.0, 2.0), Vec3::new(0.0, 0.0, -1.0), 2.0);
    let scene = b.build();
    let s = RenderSettings {
        width: 8,
        height: 8,
        spp: 64,
        integrator,
        max_depth: 16,
        rr_depth: 1,
        ..RenderSettings::default()
    };
    let sums = render_tile(&scene, &s, Rect { x0: 0, y0: 0, width: 8, height: 8 }, 0..s.spp);
    // White light through clear glass: luminance equals every channel, so the green sums and the
    // luminance squares describe one quantity.
    let (mut n, mut sum, mut sum_sq) = (0.0f64, 0.0f64, 0.0f64);
    for i in 0..sums.rect.pixels() {
        let c = sums.count[i] as f64;
        n += c;
        sum += sums.sum_rgb[i][1];
        sum_sq += sums.sum_lum_sq[i];
    }
    let mean = sum / n;
    let var = (sum_sq / n - mean * mean).max(0.0);
    (mean, var.sqrt() / mean)
}

#[test]
fn roulette_inside_glass_does_not_make_fireflies() {
    for integrator in [IntegratorKind::Bsdf, IntegratorKind::Mis] {
        let (mean, rel_sd) = through_slab(integrator);
        eprintln!("{integrator:?}: mean {mean:.4}, relative s.d. {rel_sd:.3}");
        // Two interfaces at normal incidence pass (1 − 0.04)² = 0.92 directly, plus inter-reflections.
        assert!((0.85..1.0).contains(&mean), "{integrator:?}: mean {mean}");
        // With the η² correction only the Fresnel reflections vary a sample (≈ 0.2); without it,
        // 56 % of paths die inside the slab and the rest return 2.25×: relative s.d. ≈ 1.1.
        assert!(rel_sd < 0.4, "{integrator:?}: relative standard deviation {rel_sd:.3}");
    }
}

/// A white-furnace render (`testing::furnace`) of a grey Lambert sphere of `albedo`, BSDF
/// sampling only, roulette from the first bounce on: the sums of the central 8×8 pixels, which
/// see only the sphere (it spans 29° of the camera's 35°).
fn furnace_centre(albedo: f32) -> renderer::film::PartialSums {
    let scene = renderer::testing::furnace(renderer::testing::lambert(Vec3::splat(albedo)));
    let s = RenderSettings {
        width: 16,
        height: 16,
        spp: 32,
        integrator: IntegratorKind::Bsdf,
        max_depth: 16,
        rr_depth: 1,
        ..RenderSettings::default()
    };
    render_tile(&scene, &s, Rect { x0: 4, y0: 4, width: 8, height: 8 }, 0..s.spp)
}

/// Russian roulette leaves a path alone while its throughput is at least
/// `integrator::RR_THRESHOLD`: the sphere (albedo 0.5) sends every path on to the black emitter
/// carrying 0.5, so every sample of every pixel is 0.5 and the pixels have no variance. The
/// roulette of pbrt and Mitsuba (played below throughput 1) killed half of those paths and
/// doubled the rest: samples of 0 or 1, a variance of the mean of 0.008 at 32 spp (Sobol's
/// stratification kept the means at exactly 0.5, so it is the variance that tells).
#[test]
fn roulette_spares_paths_above_its_threshold() {
    // What the scene relies on, checked at compile time: the sphere's throughput, 0.5, is at or
    // above the threshold.
    const { assert!(renderer::integrator::RR_THRESHOLD <= 0.5, "the test's albedo must not be below the threshold") };
    let sums = furnace_centre(0.5);
    for i in 0..sums.rect.pixels() {
        let (m, v) = (sums.mean(i)[1], sums.variance_of_mean(i));
        assert!(
            (m - 0.5).abs() < 1e-4 && v < 1e-8,
            "pixel {i}: mean {m}, variance {v}: a roulette played above the threshold"
        );
    }
}

/// Below the threshold it plays, unbiased: an albedo-0.2 sphere's paths survive with probability
/// 0.8 and go on carrying 0.25, so each sample is 0 or 0.25 and the mean stays 0.2.
#[test]
fn roulette_below_its_threshold_stays_unbiased() {
    let sums = furnace_centre(0.2);
    let n = sums.rect.pixels();
    let (mut sum, mut var, mut played) = (0.0f64, 0.0f64, 0);
    for i in 0..n {
        sum += sums.mean(i)[1] as f64;
        let v = sums.variance_of_mean(i) as f64;
        var += v;
        played += (v > 0.0) as usize;
    }
    let mean = sum / n as f64;
    let sd = (var / (n * n) as f64).sqrt();
    assert!(played > n / 2, "the roulette plays below the threshold ({played} of {n} pixels vary)");
    assert!((mean - 0.2).abs() < 4.0 * sd, "mean {mean} ± {sd}, expected 0.2");
}
