//! The one settings schema (issue 11): what a user may ask for, as the REST API's `settings` JSON and
//! as the flags of `tessera render` / `tessera submit`. Every field is optional; [`SettingsRequest::resolve`]
//! applies the defaults of [`RenderSettings::default`] and checks every field against its bounds in
//! [`FIELDS`], naming the field when it refuses. The CLI builds a `SettingsRequest` from its flags and
//! `tessera submit` sends that same value as JSON, so defaults and bounds live here only; a test checks
//! `coordinator/src/openapi.json` against [`FIELDS`].
//!
//! Numbers are read in wide types (u64, i64, f64) so that an out-of-range value (1e39 for an f32
//! strength, 2^40 samples) is refused by name instead of overflowing to `inf` or failing to parse.

use crate::environment::EnvironmentSettings;
use crate::light::LightSamplerKind;
use crate::sampler::SamplerKind;
use crate::settings::{
    image_size, IntegratorKind, MisHeuristic, PixelFilter, RenderSettings, MAX_DEPTH_LIMIT, MAX_IMAGE_SIDE, MAX_SPP,
    MAX_TIME_BUDGET_S,
};
use serde::{Deserialize, Serialize};

/// Longest job name accepted, in characters.
pub const MAX_NAME_CHARS: usize = 256;
/// Largest environment radiance multiplier or color component.
pub const MAX_ENV_RADIANCE: f64 = 1e6;

/// Bounds and default of one numeric field (inclusive).
#[derive(Clone, Copy, Debug)]
pub struct FieldSpec {
    pub name: &'static str,
    pub min: f64,
    pub max: f64,
    /// The default when the field is absent (None: no number, e.g. "from the camera" or "off").
    pub default: Option<f64>,
}

const fn field(name: &'static str, min: f64, max: f64, default: Option<f64>) -> FieldSpec {
    FieldSpec { name, min, max, default }
}

/// Every numeric field of [`SettingsRequest`] with its bounds and default.
pub const FIELDS: &[FieldSpec] = &[
    field("priority", -1000.0, 1000.0, Some(0.0)),
    field("spp", 1.0, MAX_SPP as f64, Some(64.0)),
    field("width", 1.0, MAX_IMAGE_SIDE as f64, None),
    field("height", 1.0, MAX_IMAGE_SIDE as f64, None),
    field("camera", 0.0, u32::MAX as f64, None),
    field("seed", 0.0, u64::MAX as f64, Some(0.0)),
    field("max_depth", 0.0, MAX_DEPTH_LIMIT as f64, Some(64.0)),
    field("rr_depth", 0.0, MAX_DEPTH_LIMIT as f64, Some(5.0)),
    field("env_strength", 0.0, MAX_ENV_RADIANCE, Some(1.0)),
    field("env_rotate", -3600.0, 3600.0, Some(0.0)),
    field("env_color", 0.0, MAX_ENV_RADIANCE, None),
    field("pass_spp", 1.0, MAX_SPP as f64, Some(16.0)),
    field("time_budget", 0.01, MAX_TIME_BUDGET_S, None),
    field("noise_target", 1e-6, 10.0, None),
    field("min_spp", 2.0, MAX_SPP as f64, Some(32.0)),
    field("fps", 0.001, 1000.0, Some(crate::animation::DEFAULT_FPS as f64)),
];

fn spec(name: &str) -> FieldSpec {
    FIELDS.iter().copied().find(|f| f.name == name).unwrap_or(field("?", f64::NEG_INFINITY, f64::INFINITY, None))
}

/// A refused setting: which field and why.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("settings.{field}: {message}")]
pub struct SettingsError {
    pub field: &'static str,
    pub message: String,
}

fn bad(field: &'static str, message: impl Into<String>) -> SettingsError {
    SettingsError { field, message: message.into() }
}

/// What the scene offers that settings are checked against.
#[derive(Clone, Copy, Debug)]
pub struct SceneFacts {
    /// Number of cameras in the file (0: a framing camera is made).
    pub cameras: usize,
    /// Aspect ratio of the camera that will be used, if it has one.
    pub aspect: Option<f32>,
}

/// A farm's (or the machine's) limits, tighter than the renderer's own.
#[derive(Clone, Copy, Debug)]
pub struct SettingsLimits {
    pub max_side: u32,
    pub max_spp: u32,
}

impl Default for SettingsLimits {
    fn default() -> Self {
        SettingsLimits { max_side: MAX_IMAGE_SIDE, max_spp: MAX_SPP }
    }
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SettingsRequest {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub priority: Option<i64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub spp: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub width: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub height: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub camera: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub integrator: Option<IntegratorKind>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mis_heuristic: Option<MisHeuristic>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sampler: Option<SamplerKind>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_depth: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rr_depth: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub filter: Option<PixelFilter>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub env_color: Option<[f64; 3]>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub env_strength: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub env_rotate: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub env_sampling: Option<bool>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub light_sampler: Option<LightSamplerKind>,
    /// How punctual intensities are read: auto (Blender's exporter's files as blender), gltf, blender.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub light_units: Option<crate::punctual::LightUnits>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pass_spp: Option<u64>,
    /// Seconds; with it (or a noise target) `spp` is a cap, by default min(limit, 65536).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub time_budget: Option<f64>,
    /// Relative standard error each tile must reach (adaptive sampling).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub noise_target: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub min_spp: Option<u64>,
    /// Frames to render: `N`, `A-B` or `A-B:step` (animated scenes; default: frame 0 only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub frames: Option<String>,
    /// Frame rate: frame N is at time N / fps.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fps: Option<f64>,
    /// The glTF animation that plays (name or index); default: all of them together.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub animation: Option<String>,
}

/// An integer field within its bounds (and `cap`, a limit of this farm).
fn int(name: &'static str, v: Option<u64>, cap: Option<u64>) -> Result<Option<u32>, SettingsError> {
    let Some(v) = v else { return Ok(None) };
    let s = spec(name);
    let max = cap.map_or(s.max, |c| (c as f64).min(s.max));
    if (v as f64) > max && max < s.max {
        return Err(bad(s.name, format!("{v} is over this farm's limit of {max}")));
    }
    if (v as f64) < s.min || (v as f64) > max {
        return Err(bad(s.name, format!("{v} is outside {}..={max}", s.min)));
    }
    Ok(Some(v as u32))
}

/// A real field: finite and within its bounds.
fn real(name: &'static str, v: Option<f64>) -> Result<Option<f64>, SettingsError> {
    let Some(v) = v else { return Ok(None) };
    let s = spec(name);
    if !v.is_finite() || v < s.min || v > s.max {
        return Err(bad(s.name, format!("{v} is outside {}..={}", s.min, s.max)));
    }
    Ok(Some(v))
}

impl SettingsRequest {
    /// The frames asked for (default: the single frame 0), checked.
    pub fn frame_range(&self) -> Result<crate::frames::FrameRange, SettingsError> {
        match &self.frames {
            None => Ok(crate::frames::FrameRange::single(0)),
            Some(f) => crate::frames::FrameRange::parse(f).map_err(|m| bad("frames", m)),
        }
    }

    /// The job name and priority (farm-level fields), checked.
    pub fn job_fields(&self) -> Result<(Option<String>, i32), SettingsError> {
        if let Some(n) = &self.name {
            let chars = n.chars().count();
            if chars > MAX_NAME_CHARS {
                return Err(bad("name", format!("{chars} characters, more than {MAX_NAME_CHARS}")));
            }
            if n.chars().any(char::is_control) {
                return Err(bad("name", "contains control characters"));
            }
        }
        let s = spec("priority");
        let priority = match self.priority {
            Some(p) if (p as f64) < s.min || (p as f64) > s.max => {
                return Err(bad(s.name, format!("{p} is outside {}..={}", s.min, s.max)))
            }
            Some(p) => p as i32,
            None => s.default.unwrap_or(0.0) as i32,
        };
        Ok((self.name.clone(), priority))
    }

    /// Resolves defaults and validates every field against its bounds, the farm's `limits` and the
    /// scene (`facts`); `env_map` is the environment map file, if any.
    pub fn resolve(
        &self,
        facts: SceneFacts,
        env_map: Option<String>,
        limits: SettingsLimits,
    ) -> Result<RenderSettings, SettingsError> {
        self.job_fields()?;
        self.frame_range()?;
        if let Some(a) = &self.animation {
            if a.chars().count() > MAX_NAME_CHARS || a.chars().any(char::is_control) {
                return Err(bad("animation", "a name of at most 256 printable characters, or an index"));
            }
        }
        let d = RenderSettings::default();
        let camera = int("camera", self.camera, None)?.map(|c| c as usize);
        if let Some(c) = camera {
            if c >= facts.cameras {
                return Err(bad(
                    "camera",
                    format!(
                        "the scene has no camera {c} (it has {}; omit the field for the default view)",
                        facts.cameras
                    ),
                ));
            }
        }
        let side = Some(limits.max_side as u64);
        let (w, h) = (int("width", self.width, side)?, int("height", self.height, side)?);
        let (width, height) = image_size(facts.aspect, w, h);
        if width > limits.max_side || height > limits.max_side {
            return Err(bad(
                if width > limits.max_side { "width" } else { "height" },
                format!("the image would be {width}x{height}, over the limit of {} per side", limits.max_side),
            ));
        }
        let time_budget = real("time_budget", self.time_budget)?;
        let noise_target = real("noise_target", self.noise_target)?;
        let budgeted = time_budget.is_some() || noise_target.is_some();
        let spp = match int("spp", self.spp, Some(limits.max_spp as u64))? {
            Some(n) => n,
            None if budgeted => limits.max_spp.min(crate::budget::BUDGET_SPP_CAP),
            None => d.spp.min(limits.max_spp),
        };
        let env_color = match self.env_color {
            Some(c) => {
                for v in c {
                    real("env_color", Some(v))?;
                }
                Some([c[0] as f32, c[1] as f32, c[2] as f32])
            }
            None => None,
        };
        let env_default = EnvironmentSettings::default();
        let s = RenderSettings {
            width,
            height,
            spp,
            pass_spp: int("pass_spp", self.pass_spp, None)?.unwrap_or(d.pass_spp),
            integrator: self.integrator.unwrap_or(d.integrator),
            mis_heuristic: self.mis_heuristic.unwrap_or(d.mis_heuristic),
            sampler: self.sampler.unwrap_or(d.sampler),
            seed: self.seed.unwrap_or(d.seed),
            max_depth: int("max_depth", self.max_depth, None)?.unwrap_or(d.max_depth),
            rr_depth: int("rr_depth", self.rr_depth, None)?.unwrap_or(d.rr_depth),
            camera,
            filter: self.filter.unwrap_or(d.filter),
            environment: EnvironmentSettings {
                map: env_map,
                color: env_color,
                strength: real("env_strength", self.env_strength)?.map_or(env_default.strength, |v| v as f32),
                rotate_deg: real("env_rotate", self.env_rotate)?.map_or(env_default.rotate_deg, |v| v as f32),
                sampling: self.env_sampling.unwrap_or(env_default.sampling),
            },
            light_sampler: self.light_sampler.unwrap_or(d.light_sampler),
            light_units: self.light_units.unwrap_or(d.light_units),
            noise_target,
            min_spp: int("min_spp", self.min_spp, None)?.unwrap_or(d.min_spp),
            time_budget,
            fps: real("fps", self.fps)?.map_or(d.fps, |v| v as f32),
            animation: self.animation.clone(),
            frame: self.frame_range()?.first,
        };
        s.validate().map_err(|m| bad("settings", m))?;
        Ok(s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const FACTS: SceneFacts = SceneFacts { cameras: 1, aspect: Some(1.0) };

    fn req(json: &str) -> SettingsRequest {
        serde_json::from_str(json).expect("parses")
    }

    #[test]
    fn an_empty_request_resolves_to_the_defaults() {
        let s = req("{}").resolve(FACTS, None, SettingsLimits::default()).expect("resolves");
        let d = RenderSettings::default();
        assert_eq!(
            (s.spp, s.pass_spp, s.max_depth, s.rr_depth, s.min_spp),
            (d.spp, d.pass_spp, d.max_depth, d.rr_depth, d.min_spp)
        );
        assert_eq!(s.environment, EnvironmentSettings::default());
        for f in FIELDS {
            if let Some(v) = f.default {
                let expect = match f.name {
                    "priority" => 0.0,
                    "spp" => d.spp as f64,
                    "seed" => d.seed as f64,
                    "max_depth" => d.max_depth as f64,
                    "rr_depth" => d.rr_depth as f64,
                    "env_strength" => d.environment.strength as f64,
                    "env_rotate" => d.environment.rotate_deg as f64,
                    "pass_spp" => d.pass_spp as f64,
                    "min_spp" => d.min_spp as f64,
                    "fps" => d.fps as f64,
                    other => panic!("no default check for {other}"),
                };
                assert_eq!(v, expect, "{}", f.name);
            }
        }
    }

    #[test]
    fn out_of_range_values_are_refused_by_field() {
        let lim = SettingsLimits::default();
        for (json, field) in [
            (r#"{"env_strength": 1e39}"#, "env_strength"),
            (r#"{"env_strength": -1}"#, "env_strength"),
            (r#"{"time_budget": 1e-300}"#, "time_budget"),
            (r#"{"camera": 5}"#, "camera"),
            (r#"{"spp": 0}"#, "spp"),
            (r#"{"spp": 1099511627776}"#, "spp"),
            (r#"{"env_color": [1, 1e30, 0]}"#, "env_color"),
            (r#"{"env_rotate": 1e20}"#, "env_rotate"),
            (r#"{"priority": -5000}"#, "priority"),
            (r#"{"max_depth": 5000}"#, "max_depth"),
        ] {
            let e = req(json).resolve(FACTS, None, lim).err().unwrap_or_else(|| panic!("{json} must be refused"));
            assert_eq!(e.field, field, "{json}: {e}");
        }
        let long = SettingsRequest { name: Some("x".repeat(10_000_000)), ..Default::default() };
        assert_eq!(long.resolve(FACTS, None, lim).err().map(|e| e.field), Some("name"));
        // A farm's limit is named as such.
        let farm = SettingsLimits { max_side: 4096, max_spp: 1000 };
        let e = req(r#"{"spp": 2000}"#).resolve(FACTS, None, farm).expect_err("over the farm limit");
        assert!(e.message.contains("farm"), "{e}");
    }

    #[test]
    fn a_request_round_trips_through_json() {
        let r = req(r#"{"spp": 4, "env_strength": 2.5, "integrator": "nee", "noise_target": 0.02}"#);
        let back: SettingsRequest =
            serde_json::from_str(&serde_json::to_string(&r).expect("encodes")).expect("decodes");
        assert_eq!(r, back);
        assert_eq!(serde_json::to_string(&SettingsRequest::default()).expect("encodes"), "{}");
    }
}
