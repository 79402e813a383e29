//! Statistics used to judge renders and samplers: per-pixel z-tests against a reference image and
//! chi-square goodness-of-fit tests of sampling routines (as Mitsuba's test suite does them).

use crate::math::Vec3;

/// Complementary error function, |relative error| < 1.2e-7 (Numerical Recipes 3rd ed. §6.2, `erfcc`).
pub fn erfc(x: f64) -> f64 {
    let z = x.abs();
    let t = 2.0 / (2.0 + z);
    let ty = 4.0 * t - 2.0;
    #[allow(clippy::excessive_precision)]
    const COF: [f64; 28] = [
        -1.3026537197817094,
        6.419_697_923_564_902e-1,
        1.9476473204185836e-2,
        -9.561_514_786_808_631e-3,
        -9.46595344482036e-4,
        3.66839497852761e-4,
        4.2523324806907e-5,
        -2.0278578112534e-5,
        -1.624290004647e-6,
        1.303655835580e-6,
        1.5626441722e-8,
        -8.5238095915e-8,
        6.529054439e-9,
        5.059343495e-9,
        -9.91364156e-10,
        -2.27365122e-10,
        9.6467911e-11,
        2.394038e-12,
        -6.886027e-12,
        8.94487e-13,
        3.13092e-13,
        -1.12708e-13,
        3.81e-16,
        7.106e-15,
        -1.523e-15,
        -9.4e-17,
        1.21e-16,
        -2.8e-17,
    ];
    let (mut d, mut dd) = (0.0f64, 0.0f64);
    for &c in COF.iter().skip(1).rev() {
        let tmp = d;
        d = ty * d - dd + c;
        dd = tmp;
    }
    let r = t * (-z * z + 0.5 * (COF[0] + ty * d) - dd).exp();
    if x >= 0.0 {
        r
    } else {
        2.0 - r
    }
}

fn ln_gamma(x: f64) -> f64 {
    // Lanczos approximation (g = 7, n = 9).
    #[allow(clippy::excessive_precision)]
    const C: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.5203681218851,
        -1259.1392167224028,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507343278686905,
        -0.13857109526572012,
        9.984_369_578_019_572e-6,
        1.5056327351493116e-7,
    ];
    if x < 0.5 {
        return (std::f64::consts::PI / (std::f64::consts::PI * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut a = C[0];
    let t = x + 7.5;
    for (i, &c) in C.iter().enumerate().skip(1) {
        a += c / (x + i as f64);
    }
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + a.ln()
}

/// Regularized upper incomplete gamma Q(a, x) (Numerical Recipes §6.2: series or continued fraction).
pub fn gamma_q(a: f64, x: f64) -> f64 {
    if x <= 0.0 {
        return 1.0;
    }
    let gln = ln_gamma(a);
    if x < a + 1.0 {
        let (mut ap, mut del) = (a, 1.0 / a);
        let mut sum = del;
        for _ in 0..10_000 {
            ap += 1.0;
            del *= x / ap;
            sum += del;
            if del.abs() < sum.abs() * 1e-15 {
                break;
            }
        }
        1.0 - sum * (-x + a * x.ln() - gln).exp()
    } else {
        let tiny = 1e-300;
        let mut b = x + 1.0 - a;
        let mut c = 1.0 / tiny;
        let mut d = 1.0 / b;
        let mut h = d;
        for i in 1..10_000 {
            let an = -(i as f64) * (i as f64 - a);
            b += 2.0;
            d = an * d + b;
            if d.abs() < tiny {
                d = tiny;
            }
            c = b + an / c;
            if c.abs() < tiny {
                c = tiny;
            }
            d = 1.0 / d;
            let del = d * c;
            h *= del;
            if (del - 1.0).abs() < 1e-15 {
                break;
            }
        }
        (-x + a * x.ln() - gln).exp() * h
    }
}

/// P(χ²_dof ≥ x).
pub fn chi2_sf(x: f64, dof: f64) -> f64 {
    gamma_q(dof / 2.0, x / 2.0)
}

/// Šidák-corrected per-test significance for `tests` tests at family-wise level `alpha`.
pub fn sidak(alpha: f64, tests: usize) -> f64 {
    1.0 - (1.0 - alpha).powf(1.0 / tests.max(1) as f64)
}

/// Result of a chi-square goodness-of-fit test.
#[derive(Debug, Clone)]
pub struct ChiSquare {
    pub statistic: f64,
    pub dof: usize,
    pub p_value: f64,
    /// Cells whose expected count was below 5 and were pooled into one.
    pub pooled_cells: usize,
}

/// Chi-square test of a direction sampler against its pdf over the full sphere, binned in
/// (θ, φ) (pbrt-v4 `test/bsdfs.cpp`, Mitsuba `chi2.py`). `sample(i)` returns the i-th sampled
/// direction (or None for a failed sample, which counts as mass outside every cell); `pdf(w)` is the
/// solid-angle density. Expected counts integrate the pdf over each cell with a `sub × sub`
/// midpoint rule; cells with expected count < 5 are pooled.
pub fn chi2_directions(
    n: usize,
    theta_bins: usize,
    phi_bins: usize,
    sub: usize,
    mut sample: impl FnMut(usize) -> Option<Vec3>,
    pdf: impl Fn(Vec3) -> f64,
) -> ChiSquare {
    let cells = theta_bins * phi_bins;
    let mut observed = vec![0.0f64; cells];
    for i in 0..n {
        if let Some(w) = sample(i) {
            if !w.is_finite() {
                continue;
            }
            let w = w.normalize();
            let theta = (w.z as f64).clamp(-1.0, 1.0).acos();
            let mut phi = (w.y as f64).atan2(w.x as f64);
            if phi < 0.0 {
                phi += 2.0 * std::f64::consts::PI;
            }
            let ti = ((theta / std::f64::consts::PI * theta_bins as f64) as usize).min(theta_bins - 1);
            let pi = ((phi / (2.0 * std::f64::consts::PI) * phi_bins as f64) as usize).min(phi_bins - 1);
            observed[ti * phi_bins + pi] += 1.0;
        }
    }
    let dt = std::f64::consts::PI / theta_bins as f64;
    let dp = 2.0 * std::f64::consts::PI / phi_bins as f64;
    let mut expected = vec![0.0f64; cells];
    for ti in 0..theta_bins {
        for pi in 0..phi_bins {
            let mut sum = 0.0;
            for a in 0..sub {
                let theta = (ti as f64 + (a as f64 + 0.5) / sub as f64) * dt;
                for b in 0..sub {
                    let phi = (pi as f64 + (b as f64 + 0.5) / sub as f64) * dp;
                    let w = Vec3::new(
                        (theta.sin() * phi.cos()) as f32,
                        (theta.sin() * phi.sin()) as f32,
                        theta.cos() as f32,
                    );
                    sum += pdf(w) * theta.sin();
                }
            }
            expected[ti * phi_bins + pi] = sum * dt * dp / (sub * sub) as f64 * n as f64;
        }
    }
    // Pool low-expectation cells into one.
    let (mut stat, mut dof, mut pooled) = (0.0, 0usize, 0usize);
    let (mut pool_o, mut pool_e) = (0.0, 0.0);
    for i in 0..cells {
        if expected[i] < 5.0 {
            pool_o += observed[i];
            pool_e += expected[i];
            pooled += 1;
        } else {
            let d = observed[i] - expected[i];
            stat += d * d / expected[i];
            dof += 1;
        }
    }
    if pool_e >= 5.0 {
        let d = pool_o - pool_e;
        stat += d * d / pool_e;
        dof += 1;
    } else if pool_o > 0.0 && pool_e < 1e-12 {
        // Samples where the pdf says there is nothing: certain failure.
        stat = f64::INFINITY;
    }
    let dof = dof.saturating_sub(1).max(1);
    ChiSquare { statistic: stat, dof, p_value: chi2_sf(stat, dof as f64), pooled_cells: pooled }
}

/// Outcome of a per-pixel z-test of an image against a reference.
#[derive(Debug, Clone)]
pub struct ZTest {
    pub pixels: usize,
    pub accepted: usize,
    pub per_pixel_alpha: f64,
    pub worst_z: f64,
    pub worst_pixel: usize,
}

impl ZTest {
    pub fn accepted_fraction(&self) -> f64 {
        self.accepted as f64 / self.pixels.max(1) as f64
    }
}

/// Per pixel z = |mean − ref| / sqrt(var_mean + var_ref) on luminance; a pixel is accepted when its
/// two-sided p-value exceeds the Šidák-corrected α (family-wise 0.01 over all pixels), as in
/// Mitsuba's render tests and ../shared/guide.
///
/// Differences below 1e-4 × the reference's mean luminance are treated as zero before dividing:
/// an estimator that has not yet found a path of relative weight 1e-6 (BSDF sampling of a far GGX
/// tail, say) reports zero mean with zero sample variance, which is no evidence of bias.
pub fn z_test(mean: &[f32], var: &[f32], reference: &[f32], ref_var: &[f32]) -> ZTest {
    let n = mean.len();
    let floor = 1e-4 * reference.iter().map(|&v| v as f64).sum::<f64>() / n.max(1) as f64;
    let alpha = sidak(0.01, n);
    let (mut accepted, mut worst_z, mut worst_pixel) = (0usize, 0.0f64, 0usize);
    for i in 0..n {
        let diff =
            ((mean[i] as f64 - reference[i] as f64).abs() - floor.max(1e-5 * reference[i].abs() as f64)).max(0.0);
        let v = var[i] as f64 + ref_var[i] as f64;
        let z = if v > 0.0 {
            diff / v.sqrt()
        } else if diff <= 1e-4 * reference[i].abs() as f64 {
            0.0
        } else {
            f64::INFINITY
        };
        let p = erfc(z / std::f64::consts::SQRT_2);
        if p > alpha {
            accepted += 1;
        }
        if z > worst_z {
            worst_z = z;
            worst_pixel = i;
        }
    }
    ZTest { pixels: n, accepted, per_pixel_alpha: alpha, worst_z, worst_pixel }
}

/// Luminance of an RGB triple as f32 (matches `math::luminance`).
pub fn lum(rgb: [f32; 3]) -> f32 {
    crate::math::luminance(Vec3::from(rgb))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn erfc_known_values() {
        assert!((erfc(0.0) - 1.0).abs() < 1e-7);
        assert!((erfc(1.0) - 0.157_299_207_050_285_1).abs() < 1e-7);
        assert!((erfc(3.0) - 2.209_049_699_858_544e-5).abs() < 1e-10);
        assert!((erfc(-1.0) - 1.842_700_792_949_715).abs() < 1e-7);
    }

    #[test]
    fn chi2_sf_known_values() {
        // χ²(1) at 3.841 → 0.05; χ²(10) at 18.307 → 0.05; χ²(100) at 124.342 → 0.05.
        assert!((chi2_sf(3.841_458_820_694_124, 1.0) - 0.05).abs() < 1e-6);
        assert!((chi2_sf(18.307_038_053_275_146, 10.0) - 0.05).abs() < 1e-6);
        assert!((chi2_sf(124.342_113_404_180_2, 100.0) - 0.05).abs() < 1e-6);
    }

    #[test]
    fn chi2_accepts_right_pdf_and_rejects_wrong_one() {
        use crate::sampler::{PixelSample, SamplerKind};
        let sample = |i: usize| {
            let s = PixelSample::new(SamplerKind::Independent, 99, (0, 0), i as u32);
            Some(crate::math::sample_cosine_hemisphere(s.get_2d(0)))
        };
        let right = chi2_directions(200_000, 10, 20, 8, sample, |w| crate::math::cosine_hemisphere_pdf(w.z) as f64);
        assert!(right.p_value > 1e-3, "{right:?}");
        let wrong = chi2_directions(200_000, 10, 20, 8, sample, |w| {
            if w.z > 0.0 {
                1.0 / (2.0 * std::f64::consts::PI)
            } else {
                0.0
            }
        });
        assert!(wrong.p_value < 1e-6, "{wrong:?}");
    }

    #[test]
    fn z_test_flags_a_biased_image() {
        let n = 1000;
        let r = vec![1.0f32; n];
        let rv = vec![0.0f32; n];
        let v = vec![0.01f32; n];
        let ok = z_test(&vec![1.05f32; n], &v, &r, &rv);
        assert_eq!(ok.accepted, n);
        let bad = z_test(&vec![1.6f32; n], &v, &r, &rv);
        assert_eq!(bad.accepted, 0);
    }
}
