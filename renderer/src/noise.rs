//! How noisy a result is, estimated from its own variance buffer, and how wrong it is against a
//! reference. Both use the same metric, so the estimate can be checked against the truth:
//!
//! relMSE = mean over pixels of (Y − Y_ref)² / (Y_ref² + ε), with Y the luminance and ε = 0.01.
//!
//! ε keeps black pixels from dominating a relative metric (a pixel darker than 0.1 is judged on an
//! absolute scale); it is the denominator of the relMSE the convergence benchmark and the
//! reference scripts measure. The *estimate* replaces (Y − Y_ref)² by its expectation for an
//! unbiased pixel, the variance of the mean, and Y_ref by the pixel's own mean. The relative
//! standard error reported to users is √relMSE.

use crate::film::{PartialSums, Rect};
use crate::math::{luminance, Vec3};

/// ε of the relMSE denominator (see the module documentation).
pub const REL_MSE_FLOOR: f64 = 0.01;

/// The noise of a whole image or of one tile.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NoiseEstimate {
    /// Expected relMSE against the converged image (infinite when some pixel has < 2 samples).
    pub rel_mse: f64,
    /// √rel_mse: the relative standard error.
    pub rel_error: f64,
    /// Smallest and largest samples per pixel.
    pub spp_min: u32,
    pub spp_max: u32,
}

/// Expected squared relative error of pixel `i` of `sums`; infinite below two samples (the
/// variance is unknown, so nothing may be concluded from it).
pub fn pixel_rel_mse(sums: &PartialSums, i: usize) -> f64 {
    let var = sums.variance_of_mean(i) as f64;
    if !var.is_finite() {
        return f64::INFINITY;
    }
    let y = luminance(Vec3::from(sums.mean(i))) as f64;
    var / (y * y + REL_MSE_FLOOR)
}

/// The estimate over every pixel of `sums` (a tile or a whole image).
pub fn estimate(sums: &PartialSums) -> NoiseEstimate {
    estimate_rect(sums, sums.rect)
}

/// The estimate over the pixels of `rect`, which must lie inside `sums.rect` (pixels outside are
/// ignored).
pub fn estimate_rect(sums: &PartialSums, rect: Rect) -> NoiseEstimate {
    let r = sums.rect;
    let (mut total, mut n) = (0.0f64, 0usize);
    let (mut spp_min, mut spp_max) = (u32::MAX, 0u32);
    for y in rect.y0.max(r.y0)..(rect.y0 + rect.height).min(r.y0 + r.height) {
        for x in rect.x0.max(r.x0)..(rect.x0 + rect.width).min(r.x0 + r.width) {
            let i = ((y - r.y0) * r.width + (x - r.x0)) as usize;
            total += pixel_rel_mse(sums, i);
            spp_min = spp_min.min(sums.count[i]);
            spp_max = spp_max.max(sums.count[i]);
            n += 1;
        }
    }
    let rel_mse = if n == 0 { f64::INFINITY } else { total / n as f64 };
    NoiseEstimate { rel_mse, rel_error: rel_mse.sqrt(), spp_min: if n == 0 { 0 } else { spp_min }, spp_max }
}

/// The noisiest of `tiles` whose noise is known (every pixel with two samples or more).
pub fn worst<'a>(tiles: impl IntoIterator<Item = &'a PartialSums>) -> Option<(Rect, NoiseEstimate)> {
    tiles
        .into_iter()
        .map(|t| (t.rect, estimate(t)))
        .filter(|(_, e)| e.rel_mse.is_finite())
        .max_by(|a, b| a.1.rel_mse.total_cmp(&b.1.rel_mse))
}

/// The measured relMSE of an RGB image against a reference of the same size (luminance, the
/// metric of the module documentation). `None` when the sizes differ.
pub fn rel_mse_against(image: &[[f32; 3]], reference: &[[f32; 3]]) -> Option<f64> {
    if image.len() != reference.len() || image.is_empty() {
        return None;
    }
    let sum: f64 = image
        .iter()
        .zip(reference)
        .map(|(a, b)| {
            let ya = luminance(Vec3::from(*a)) as f64;
            let yb = luminance(Vec3::from(*b)) as f64;
            (ya - yb) * (ya - yb) / (yb * yb + REL_MSE_FLOOR)
        })
        .sum();
    Some(sum / image.len() as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampler::{PixelSample, SamplerKind};

    /// Pixels whose samples are i.i.d. exponential with mean m: the estimate must match the true
    /// squared error of the mean on average, which is what it claims to be.
    #[test]
    fn estimate_is_the_expected_squared_relative_error() {
        let rect = Rect { x0: 0, y0: 0, width: 64, height: 64 };
        let mut sums = PartialSums::new(rect);
        let n = 16;
        let mut truth = 0.0;
        for i in 0..rect.pixels() {
            let m = 0.05 + 2.0 * (i as f32 / rect.pixels() as f32);
            for s in 0..n {
                let u = PixelSample::new(SamplerKind::Independent, 7, (i as u32, 0), s).get_1d(0);
                sums.add_sample(i, Vec3::splat(-m * (1.0 - u).max(1e-9).ln()));
            }
            let mean = sums.mean(i)[0] as f64;
            truth += (mean - m as f64).powi(2) / ((m * m) as f64 + REL_MSE_FLOOR);
        }
        truth /= rect.pixels() as f64;
        let est = estimate(&sums);
        assert_eq!((est.spp_min, est.spp_max), (n, n));
        let ratio = est.rel_mse / truth;
        assert!((0.8..1.25).contains(&ratio), "estimate {} vs true {truth} (ratio {ratio})", est.rel_mse);
    }

    #[test]
    fn one_sample_is_unknown_noise_and_sub_rects_are_clipped() {
        let rect = Rect { x0: 0, y0: 0, width: 4, height: 4 };
        let mut sums = PartialSums::new(rect);
        for i in 0..16 {
            sums.add_sample(i, Vec3::ONE);
        }
        assert!(estimate(&sums).rel_mse.is_infinite());
        for i in 0..16 {
            sums.add_sample(i, Vec3::ONE);
        }
        let e = estimate_rect(&sums, Rect { x0: 2, y0: 2, width: 10, height: 10 });
        assert_eq!(e.rel_mse, 0.0);
        assert_eq!((e.spp_min, e.spp_max), (2, 2));
        assert_eq!(rel_mse_against(&[[1.0; 3]], &[[1.0; 3]]), Some(0.0));
        assert_eq!(rel_mse_against(&[[1.0; 3]], &[]), None);
    }
}
