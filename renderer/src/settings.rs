//! Render settings: everything that determines an image, and so the identity of a job's result.

use crate::sampler::SamplerKind;
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum IntegratorKind {
    /// Random walk with BSDF importance sampling only; emission counted where a path hits it.
    Bsdf,
    /// Next-event estimation; emission hit by BSDF rays counted only where NEE could not sample it
    /// (camera rays and after delta bounces).
    Nee,
    /// NEE and BSDF sampling combined by multiple importance sampling.
    Mis,
}

crate::named_choices!(IntegratorKind, "integrator", { "mis" => Self::Mis, "nee" => Self::Nee, "bsdf" => Self::Bsdf });

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MisHeuristic {
    Power,
    Balance,
}

crate::named_choices!(MisHeuristic, "MIS heuristic", { "power" => Self::Power, "balance" => Self::Balance });

/// Pixel reconstruction filter, applied by importance sampling the filter (each sample lands in
/// exactly one pixel with weight 1, so tiles stay independent).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PixelFilter {
    /// Uniform over the pixel.
    Box,
    /// Tent of radius 1 pixel.
    Tent,
}

crate::named_choices!(PixelFilter, "pixel filter", { "box" => Self::Box, "tent" => Self::Tent });

/// Largest image side accepted (bounds the film allocation).
pub const MAX_IMAGE_SIDE: u32 = 16384;
/// Largest sample count accepted per pixel.
pub const MAX_SPP: u32 = 1 << 24;
/// Longest time budget accepted (30 days).
pub const MAX_TIME_BUDGET_S: f64 = 30.0 * 86400.0;
/// Deepest path accepted.
pub const MAX_DEPTH_LIMIT: u32 = 1024;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RenderSettings {
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    /// Samples per pass: the unit of accumulation of the determinism rule (ARCHITECTURE.md).
    pub pass_spp: u32,
    pub integrator: IntegratorKind,
    pub mis_heuristic: MisHeuristic,
    pub sampler: SamplerKind,
    pub seed: u64,
    /// Number of scattering events: 0 renders only emission seen directly, 1 adds direct lighting.
    pub max_depth: u32,
    /// Russian roulette starts after this many bounces.
    pub rr_depth: u32,
    pub camera: Option<usize>,
    pub filter: PixelFilter,
    pub environment: crate::environment::EnvironmentSettings,
    pub light_sampler: crate::light::LightSamplerKind,
    /// Stop each tile once its estimated relative standard error is at most this (adaptive
    /// sampling; `spp` stays the cap). See `budget::tile_needs_more`.
    pub noise_target: Option<f64>,
    /// With a noise target: samples every pixel gets before its tile may stop.
    pub min_spp: u32,
    /// Stop at the last pass boundary that fits in this many seconds (`spp` stays the cap).
    pub time_budget: Option<f64>,
    /// How punctual light intensities are read (`auto`: Blender's exporter's files as Blender).
    pub light_units: crate::punctual::LightUnits,
    /// Frame rate of an animated scene: frame N is at time N / fps (Blender's convention).
    pub fps: f32,
    /// Which glTF animation plays (name or index); None: all of them together.
    pub animation: Option<String>,
    /// The frame this image is of (a farm job of several frames is one job per frame; locally,
    /// each frame of `--frames`). Time = frame / fps.
    pub frame: u32,
}

impl Default for RenderSettings {
    fn default() -> Self {
        RenderSettings {
            width: 640,
            height: 480,
            spp: 64,
            pass_spp: 16,
            integrator: IntegratorKind::Mis,
            mis_heuristic: MisHeuristic::Power,
            sampler: SamplerKind::Sobol,
            seed: 0,
            max_depth: 64,
            rr_depth: 5,
            camera: None,
            filter: PixelFilter::Box,
            environment: Default::default(),
            light_sampler: Default::default(),
            noise_target: None,
            min_spp: 32,
            fps: crate::animation::DEFAULT_FPS,
            animation: None,
            frame: 0,
            time_budget: None,
            light_units: Default::default(),
        }
    }
}

/// Image size from optional width/height and the camera's aspect ratio: both given are used as they
/// are; one given keeps the aspect; none gives 640 wide.
pub fn image_size(aspect: Option<f32>, width: Option<u32>, height: Option<u32>) -> (u32, u32) {
    let aspect = aspect.filter(|a| a.is_finite() && *a > 0.0).unwrap_or(640.0 / 480.0);
    match (width, height) {
        (Some(w), Some(h)) => (w, h),
        (Some(w), None) => (w, ((w as f32 / aspect).round() as u32).max(1)),
        (None, Some(h)) => (((h as f32 * aspect).round() as u32).max(1), h),
        (None, None) => (640, ((640.0 / aspect).round() as u32).max(1)),
    }
}

impl RenderSettings {
    pub fn validate(&self) -> Result<(), String> {
        if self.width == 0 || self.height == 0 {
            return Err(format!("resolution {}x{} has a zero side", self.width, self.height));
        }
        if self.width > MAX_IMAGE_SIDE || self.height > MAX_IMAGE_SIDE {
            return Err(format!(
                "resolution {}x{} exceeds the limit of {MAX_IMAGE_SIDE} per side",
                self.width, self.height
            ));
        }
        if self.spp == 0 || self.spp > MAX_SPP {
            return Err(format!("spp {} must be between 1 and {MAX_SPP}", self.spp));
        }
        if self.pass_spp == 0 {
            return Err("pass_spp must be at least 1".into());
        }
        if self.max_depth > MAX_DEPTH_LIMIT {
            return Err(format!("max depth {} exceeds the limit of {MAX_DEPTH_LIMIT}", self.max_depth));
        }
        if let Some(t) = self.noise_target {
            if !(1e-6..=10.0).contains(&t) {
                return Err(format!("noise target {t} must be a relative error between 1e-6 and 10"));
            }
        }
        if self.min_spp < 2 || self.min_spp > MAX_SPP {
            return Err(format!(
                "min_spp {} must be between 2 and {MAX_SPP} (a variance needs two samples)",
                self.min_spp
            ));
        }
        if let Some(b) = self.time_budget {
            if !(b > 0.0 && b <= MAX_TIME_BUDGET_S) {
                return Err(format!("time budget {b} s must be positive and at most {MAX_TIME_BUDGET_S} s"));
            }
        }
        Ok(())
    }

    /// Number of passes of a render that reaches `spp`.
    pub fn pass_count(&self) -> u32 {
        self.spp.div_ceil(self.pass_spp.max(1))
    }

    /// Samples per pixel after the first `passes` passes.
    pub fn samples_after(&self, passes: u32) -> u32 {
        passes.saturating_mul(self.pass_spp).min(self.spp)
    }

    /// The sample range of pass `k`.
    pub fn pass_range(&self, k: u32) -> std::ops::Range<u32> {
        self.samples_after(k)..self.samples_after(k.saturating_add(1))
    }
}
