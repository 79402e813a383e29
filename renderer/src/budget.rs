//! Budgets instead of sample counts: a noise target met tile by tile (adaptive sampling) and a
//! time budget met at pass boundaries. The same rules run in `tessera render` and in the
//! coordinator, so a budgeted farm job and a budgeted local render make the same decisions.
//!
//! Determinism: whether a tile gets another pass depends only on that tile's own folded sums
//! (which the determinism rule fixes bit for bit), never on timing or on the number of workers. So
//! a noise-target image is a function of its settings. A time budget is, by nature, a function of
//! the machine's speed; it only ever stops at a whole-pass boundary of the whole image, so the
//! result is bit-identical to the fixed-`spp` render of the sample count it reached (which the
//! EXR records).

use crate::film::PartialSums;
use crate::noise;
use crate::settings::RenderSettings;

/// Side of the square tiles an image is cut into for adaptive sampling and for farm scheduling.
/// With a noise target the tile grid is part of the image's identity (each tile stops on its own).
pub const TILE: u32 = 32;

/// Samples per pixel used when a budget is given without an explicit `spp` cap.
pub const BUDGET_SPP_CAP: u32 = 1 << 16;

/// Why a render stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StopReason {
    /// Every tile reached `spp`.
    SampleCount,
    /// Every tile reached the noise target (or `spp`, whichever came first).
    NoiseTarget,
    /// The time budget would have been exceeded by another pass.
    TimeBudget,
    /// Cancelled by the user (at a pass boundary).
    Cancelled,
}

impl StopReason {
    pub fn as_str(&self) -> &'static str {
        match self {
            StopReason::SampleCount => "sample_count",
            StopReason::NoiseTarget => "noise_target",
            StopReason::TimeBudget => "time_budget",
            StopReason::Cancelled => "cancelled",
        }
    }
}

/// How far along a tile is, in [0, 1], for progress displays (`tessera render`'s bar, the farm's
/// `progress.fraction` and ETA). A tile that will get no more passes (`finished`) is done. Else
/// the share of its planned passes it holds; under a noise target at least (target / error)²,
/// since relative MSE falls as 1/spp, capped at 0.99 until the tile actually stops (a sample cap
/// of 65536 spp would otherwise make a converging job look near 0 %).
pub fn tile_progress(settings: &RenderSettings, passes_folded: u32, finished: bool, rel_error: f64) -> f64 {
    if finished {
        return 1.0;
    }
    let by_samples = passes_folded as f64 / settings.pass_count().max(1) as f64;
    match settings.noise_target {
        Some(target) if rel_error.is_finite() && rel_error > 0.0 => {
            by_samples.max((target / rel_error).powi(2).min(0.99))
        }
        _ => by_samples,
    }
}

/// The fraction shown and the seconds left, from the fraction of the work done after `elapsed_s`
/// seconds: the rate so far, extrapolated. A time budget bounds both: progress is at least the
/// share of the budget spent, and what is left at most the budget that is left. None while
/// nothing is known (no work done, no budget).
pub fn fraction_and_eta(settings: &RenderSettings, work: f64, elapsed_s: f64) -> (f64, Option<f64>) {
    let mut fraction = work.clamp(0.0, 1.0);
    let mut eta = (fraction > 0.0).then(|| elapsed_s * (1.0 - fraction) / fraction);
    if let Some(b) = settings.time_budget {
        fraction = fraction.max((elapsed_s / b).min(1.0));
        eta = Some(eta.unwrap_or(f64::INFINITY).min((b - elapsed_s).max(0.0)));
    }
    (fraction, eta)
}

/// Whether a tile holding `passes_folded` passes (folded in order into `tile`) gets another one.
///
/// Without a noise target: until the sample count is reached. With one: also stop once the tile
/// holds at least `min_spp` samples and its estimated relative error (√ of the mean per-pixel
/// relMSE, see [`noise`]) is at most the target. Tiles meeting the target keep the image's
/// relMSE — the pixel-weighted mean of the tiles' — below target², so a converged image meets it
/// too. `min_spp` guards against variance estimates from a handful of samples, which are biased
/// low where rare bright paths (caustics, small lights) have not been found yet; the same role as
/// Cycles' adaptive minimum samples.
pub fn tile_needs_more(settings: &RenderSettings, tile: &PartialSums, passes_folded: u32) -> bool {
    if passes_folded >= settings.pass_count() {
        return false;
    }
    let Some(target) = settings.noise_target else { return true };
    if settings.samples_after(passes_folded) < settings.min_spp.max(2) {
        return true;
    }
    noise::estimate(tile).rel_error > target
}

/// Whether to start another pass of the whole image after `passes_done` passes took `elapsed_s`
/// seconds: always the first; then only while the mean pass time so far predicts that the next
/// one ends within the budget (so a budget is rarely overrun, and by less than one pass when it is).
pub fn may_start_pass(settings: &RenderSettings, elapsed_s: f64, passes_done: u32) -> bool {
    let Some(budget) = settings.time_budget else { return true };
    if passes_done == 0 {
        return true;
    }
    let per_pass = elapsed_s / passes_done as f64;
    elapsed_s + per_pass <= budget
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::film::Rect;
    use crate::math::Vec3;

    fn tile(samples: &[f32]) -> PartialSums {
        let mut t = PartialSums::new(Rect { x0: 0, y0: 0, width: 1, height: 1 });
        for &v in samples {
            t.add_sample(0, Vec3::splat(v));
        }
        t
    }

    #[test]
    fn eta_extrapolates_the_rate_and_a_time_budget_bounds_it() {
        let fixed = RenderSettings::default();
        assert_eq!(fraction_and_eta(&fixed, 0.25, 10.0), (0.25, Some(30.0)));
        assert_eq!(fraction_and_eta(&fixed, 0.0, 10.0), (0.0, None), "nothing done: nothing known");
        let budget = RenderSettings { time_budget: Some(20.0), ..RenderSettings::default() };
        // The work says 30 s more; the budget has 10 s left and is half spent.
        assert_eq!(fraction_and_eta(&budget, 0.25, 10.0), (0.5, Some(10.0)));
        assert_eq!(fraction_and_eta(&budget, 0.0, 25.0), (1.0, Some(0.0)), "an overrun budget is done");
    }

    #[test]
    fn noise_target_stops_a_tile_only_after_min_spp_and_below_target() {
        let s =
            RenderSettings { spp: 64, pass_spp: 4, noise_target: Some(0.05), min_spp: 8, ..RenderSettings::default() };
        let flat = tile(&[1.0; 4]);
        // Zero variance but only 4 of the 8 minimum samples: keep going.
        assert!(tile_needs_more(&s, &flat, 1));
        let flat8 = tile(&[1.0; 8]);
        assert!(!tile_needs_more(&s, &flat8, 2));
        // Noisy: relative error of {0, 2, 0, 2, ...} with mean 1 over 8 samples is ~0.38.
        let noisy = tile(&[0.0, 2.0, 0.0, 2.0, 0.0, 2.0, 0.0, 2.0]);
        assert!(tile_needs_more(&s, &noisy, 2));
        // The sample count still caps it.
        assert!(!tile_needs_more(&s, &noisy, 16));
        let plain = RenderSettings { spp: 64, pass_spp: 4, ..RenderSettings::default() };
        assert!(tile_needs_more(&plain, &flat8, 2));
        assert!(!tile_needs_more(&plain, &flat8, 16));
    }

    #[test]
    fn time_budget_predicts_the_next_pass() {
        let s = RenderSettings { time_budget: Some(10.0), ..RenderSettings::default() };
        assert!(may_start_pass(&s, 100.0, 0), "the first pass always runs");
        assert!(may_start_pass(&s, 6.0, 3), "6 s + 2 s per pass fits in 10 s");
        assert!(may_start_pass(&s, 6.0, 2), "6 s + 3 s = 9 s fits");
        assert!(!may_start_pass(&s, 7.0, 2), "7 s + 3.5 s does not");
        assert!(may_start_pass(&RenderSettings::default(), 1e9, 5));
    }
}
