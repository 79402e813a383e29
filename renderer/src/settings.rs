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
        Ok(())
    }

    /// The sample passes of this render: `[k·pass_spp, min((k+1)·pass_spp, spp))`.
    pub fn passes(&self) -> impl Iterator<Item = std::ops::Range<u32>> + '_ {
        let p = self.pass_spp.max(1);
        (0..self.spp.div_ceil(p)).map(move |k| k * p..((k + 1) * p).min(self.spp))
    }
}
