//! KHR_lights_punctual: point, spot and directional lights. They are delta lights: only next-event
//! estimation can reach them (a BSDF-sampled ray never hits a point), so they take no MIS weight.
//!
//! Units: the extension gives point/spot intensity in candela and directional illuminance in lux.
//! Tessera's radiance unit is the one of emissive and environment texels (../shared/guide), read as
//! nits (cd/m²); in those units a point light of I cd gives irradiance I/r² at distance r and a
//! directional light of E lux gives irradiance E, so the numbers are used as they are (`LightUnits::Gltf`),
//! except for files from Blender's exporter, whose lights are divided by 683 (`LightUnits::Blender`).

use crate::math::{luminance, Vec3, PI};

/// How punctual intensities relate to emissive strength and environment radiance (`--light-units`).
///
/// Tessera's radiance unit is the one of emissive strength and environment texels. Blender's glTF
/// exporter ("Lighting Mode: Standard", its default) writes a point or spot light of P watts as
/// P·683/4π cd and a sun of S W/m² as S·683 lux, while Cycles shows emission strength as it is; in
/// Cycles a P-watt point gives irradiance P/(4π r²) and an S W/m² sun irradiance S. So a Blender
/// export's candela and lux are 683× the radiometric values Cycles used (issue 12 measured its scene
/// 184× too bright; `scenes/blender` 669×), and `Blender` divides them by 683 (the luminous efficacy
/// the exporter multiplied by).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LightUnits {
    /// `blender` for files whose `asset.generator` is Blender's exporter, else `gltf`.
    #[default]
    Auto,
    /// Candela and lux used as they are (the numbers glTF gives, in Tessera's radiance unit).
    Gltf,
    /// Candela and lux ÷ 683: the watts Blender had (matches Cycles).
    Blender,
}

crate::named_choices!(LightUnits, "light units", { "auto" => Self::Auto, "gltf" => Self::Gltf, "blender" => Self::Blender });

/// Blender's exporter's luminous efficacy (lm/W): what its photometric values were multiplied by.
pub const BLENDER_LM_PER_W: f32 = 683.0;

impl LightUnits {
    /// The units a file is read in: `Auto` decided by its `asset.generator`.
    pub fn resolve(self, generator: Option<&str>) -> LightUnits {
        match self {
            LightUnits::Auto if generator.is_some_and(|g| g.starts_with("Khronos glTF Blender I/O")) => {
                LightUnits::Blender
            }
            LightUnits::Auto => LightUnits::Gltf,
            u => u,
        }
    }

    /// Factor applied to the file's punctual intensities.
    pub fn scale(self) -> f32 {
        if self == LightUnits::Blender {
            1.0 / BLENDER_LM_PER_W
        } else {
            1.0
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PunctualKind {
    Point,
    /// Cone cosines (inner > outer).
    Spot {
        cos_inner: f32,
        cos_outer: f32,
    },
    Directional,
}

#[derive(Clone, Copy, Debug)]
pub struct PunctualLight {
    pub kind: PunctualKind,
    /// color × intensity (cd for point/spot, lux for directional).
    pub intensity: Vec3,
    pub position: Vec3,
    /// Unit direction the light shines along (spot, directional): the node's −Z in world space.
    pub direction: Vec3,
}

impl PunctualLight {
    /// glTF's spot falloff: a smooth ramp in cos θ between the outer and inner cone, squared
    /// (KHR_lights_punctual, "Inner and Outer Cone Angles").
    #[inline]
    pub fn spot_attenuation(cos_inner: f32, cos_outer: f32, cos_theta: f32) -> f32 {
        let scale = 1.0 / (cos_inner - cos_outer).max(1e-3);
        let t = ((cos_theta - cos_outer) * scale).clamp(0.0, 1.0);
        t * t
    }

    /// Radiance-equivalent arriving at `reference`: (unit direction to the light, distance, value
    /// to use as L·(solid angle) — i.e. irradiance at normal incidence).
    pub fn illuminate(&self, reference: Vec3) -> Option<(Vec3, f32, Vec3)> {
        match self.kind {
            PunctualKind::Directional => Some((-self.direction, f32::INFINITY, self.intensity)),
            PunctualKind::Point | PunctualKind::Spot { .. } => {
                let to = self.position - reference;
                let d2 = to.length_squared();
                if !(d2 > 0.0) || !d2.is_finite() {
                    return None;
                }
                let dist = d2.sqrt();
                let wi = to / dist;
                let mut e = self.intensity / d2;
                if let PunctualKind::Spot { cos_inner, cos_outer } = self.kind {
                    e *= Self::spot_attenuation(cos_inner, cos_outer, (-wi).dot(self.direction));
                }
                Some((wi, dist, e))
            }
        }
    }

    /// Emitted power (luminance), for light selection; directional lights are sized by the scene.
    pub fn power(&self, scene_radius: f32) -> f32 {
        let i = luminance(self.intensity);
        match self.kind {
            PunctualKind::Point => 4.0 * PI * i,
            PunctualKind::Spot { cos_inner, cos_outer } => 2.0 * PI * i * (1.0 - 0.5 * (cos_inner + cos_outer)),
            PunctualKind::Directional => PI * scene_radius * scene_radius * i,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inverse_square_and_spot_cone() {
        let p = PunctualLight {
            kind: PunctualKind::Point,
            intensity: Vec3::splat(4.0),
            position: Vec3::new(0.0, 2.0, 0.0),
            direction: -Vec3::Y,
        };
        let (wi, d, e) = p.illuminate(Vec3::ZERO).unwrap();
        assert!((wi - Vec3::Y).length() < 1e-6 && (d - 2.0).abs() < 1e-6 && (e.x - 1.0).abs() < 1e-6);
        let (ci, co) = (10f32.to_radians().cos(), 20f32.to_radians().cos());
        let s = PunctualLight { kind: PunctualKind::Spot { cos_inner: ci, cos_outer: co }, ..p };
        assert!((s.illuminate(Vec3::ZERO).unwrap().2.x - 1.0).abs() < 1e-6, "inside the inner cone: full");
        let outside = Vec3::new(2.0 * 30f32.to_radians().tan(), 0.0, 0.0);
        assert_eq!(s.illuminate(outside).unwrap().2.x, 0.0, "outside the outer cone: dark");
        let mid = Vec3::new(2.0 * 15f32.to_radians().tan(), 0.0, 0.0);
        let m = s.illuminate(mid).unwrap().2.x;
        assert!(m > 0.0 && m < 1.0, "between the cones: {m}");
    }
}
