//! Smooth and rough dielectric interfaces (glass): GGX microfacet reflection and refraction with the
//! exact dielectric Fresnel term (Walter et al. 2007, "Microfacet Models for Refraction through Rough
//! Surfaces"; sampling of visible normals and the formulation of pbrt-v4 `DielectricBxDF`, §9.7).
//!
//! Conventions: local frame with the shading normal at +z, `wo.z > 0` (the caller turns the frame to
//! the side the ray came from) and `eta` = n(other side) / n(wo's side), so entering glass of ior 1.5
//! has eta = 1.5 and leaving it eta = 1/1.5. Transmission carries radiance, so it is divided by η²
//! (the η² of the solid-angle compression; it cancels when a path leaves the medium again).

use crate::math::{Vec2, Vec3};
use crate::microfacet::Ggx;

/// Fresnel reflectance of a dielectric interface for unpolarized light, `cos_i` on wo's side.
#[inline]
pub fn fresnel_dielectric(cos_i: f32, eta: f32) -> f32 {
    let (cos_i, eta) = if cos_i < 0.0 { (-cos_i, 1.0 / eta) } else { (cos_i, eta) };
    let cos_i = cos_i.min(1.0);
    let sin2_t = (1.0 - cos_i * cos_i) / (eta * eta);
    if sin2_t >= 1.0 {
        return 1.0; // total internal reflection
    }
    let cos_t = (1.0 - sin2_t).max(0.0).sqrt();
    let r_parl = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
    let r_perp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
    0.5 * (r_parl * r_parl + r_perp * r_perp)
}

/// Refracts `wi` (pointing away from the surface, on `n`'s side) through the interface with relative
/// index `eta`; None on total internal reflection.
#[inline]
pub fn refract(wi: Vec3, n: Vec3, eta: f32) -> Option<Vec3> {
    let cos_i = n.dot(wi);
    let sin2_i = (1.0 - cos_i * cos_i).max(0.0);
    let sin2_t = sin2_i / (eta * eta);
    if sin2_t >= 1.0 {
        return None;
    }
    let cos_t = (1.0 - sin2_t).sqrt();
    Some(-wi / eta + (cos_i / eta - cos_t) * n)
}

#[derive(Clone, Copy, Debug)]
pub struct Dielectric {
    pub eta: f32,
    pub ggx: Ggx,
    /// Tint of transmitted light (glTF: the base color).
    pub tint: Vec3,
}

/// A sampled direction: (wi, f, pdf, delta).
pub type DielectricSample = (Vec3, Vec3, f32, bool);

impl Dielectric {
    pub fn is_delta(&self) -> bool {
        self.ggx.is_delta() || self.eta == 1.0
    }

    /// The half vector of a reflection or refraction pair, facing +z; None when degenerate.
    #[inline]
    fn half_vector(&self, wo: Vec3, wi: Vec3) -> Option<(Vec3, bool, f32)> {
        let reflect = wi.z > 0.0;
        let etap = if reflect { 1.0 } else { self.eta };
        let wm = wi * etap + wo;
        if wi.z == 0.0 || wo.z <= 0.0 || wm.length_squared() == 0.0 {
            return None;
        }
        let mut wm = wm.normalize();
        if wm.z < 0.0 {
            wm = -wm;
        }
        // Microfacets seen from behind by either direction contribute nothing.
        if wm.dot(wi) * wi.z < 0.0 || wm.dot(wo) * wo.z < 0.0 {
            return None;
        }
        Some((wm, reflect, etap))
    }

    pub fn eval(&self, wo: Vec3, wi: Vec3) -> Vec3 {
        self.eval_pdf(wo, wi).0
    }

    pub fn pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        self.eval_pdf(wo, wi).1
    }

    /// f(wo, wi) and the pdf of `sample` choosing wi, together: they share the half vector, the
    /// Fresnel term and D, which NEE (f for the estimate, pdf for its MIS weight) and sampling
    /// (both for the sample) would otherwise compute twice.
    pub fn eval_pdf(&self, wo: Vec3, wi: Vec3) -> (Vec3, f32) {
        if self.is_delta() {
            return (Vec3::ZERO, 0.0);
        }
        let Some((wm, reflect, etap)) = self.half_vector(wo, wi) else { return (Vec3::ZERO, 0.0) };
        let f = fresnel_dielectric(wo.dot(wm), self.eta);
        let d = self.ggx.d(wm);
        let g = self.ggx.g2(wo, wi);
        let dvis = self.ggx.visible_d_given(wo, wm, d);
        if reflect {
            return (Vec3::splat(d * g * f / (4.0 * wo.z * wi.z).abs()), dvis / (4.0 * wo.dot(wm).abs()) * f);
        }
        let denom = wi.dot(wm) + wo.dot(wm) / etap;
        let pdf = dvis * (wi.dot(wm).abs() / (denom * denom)) * (1.0 - f);
        let denom = denom * denom * wi.z * wo.z;
        if denom == 0.0 {
            return (Vec3::ZERO, pdf);
        }
        let ft = d * (1.0 - f) * g * (wi.dot(wm) * wo.dot(wm) / denom).abs() / (etap * etap);
        (self.tint * ft, pdf)
    }

    /// Samples reflection or transmission in proportion to Fresnel: (wi, f, pdf, delta).
    pub fn sample(&self, wo: Vec3, uc: f32, u: Vec2) -> Option<DielectricSample> {
        match self.sample_direction(wo, uc, u)? {
            DielectricDirection::Delta { wi, f, p } => Some((wi, f, p, true)),
            DielectricDirection::Rough(wi) => {
                let (f, pdf) = self.eval_pdf(wo, wi);
                if !(pdf > 0.0) || !pdf.is_finite() {
                    return None;
                }
                Some((wi, f, pdf, false))
            }
        }
    }

    /// The direction `sample` chooses, without evaluating a rough one (a BSDF mixing glass with
    /// other lobes evaluates the whole mixture there instead).
    pub fn sample_direction(&self, wo: Vec3, uc: f32, u: Vec2) -> Option<DielectricDirection> {
        if wo.z <= 0.0 {
            return None;
        }
        if self.is_delta() {
            let r = fresnel_dielectric(wo.z, self.eta);
            if uc < r {
                let wi = Vec3::new(-wo.x, -wo.y, wo.z);
                return Some(DielectricDirection::Delta { wi, f: Vec3::splat(r), p: r });
            }
            let wi = refract(wo, Vec3::Z, self.eta)?;
            let t = 1.0 - r;
            return Some(DielectricDirection::Delta { wi, f: self.tint * (t / (self.eta * self.eta)), p: t });
        }
        let wm = self.ggx.sample_visible_normal(wo, u);
        let r = fresnel_dielectric(wo.dot(wm), self.eta);
        if uc < r {
            let wi = crate::math::reflect(wo, wm);
            (wi.z > 0.0).then_some(DielectricDirection::Rough(wi))
        } else {
            let wi = refract(wo, wm, self.eta)?;
            (wi.z < 0.0).then_some(DielectricDirection::Rough(wi))
        }
    }
}

/// What [`Dielectric::sample_direction`] chose.
#[derive(Clone, Copy, Debug)]
pub enum DielectricDirection {
    /// Smooth glass: the mirror or refracted direction, its f (the delta removed) and probability.
    Delta { wi: Vec3, f: Vec3, p: f32 },
    /// A direction through a sampled microfacet, for the caller to evaluate.
    Rough(Vec3),
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fresnel_limits() {
        assert!((fresnel_dielectric(1.0, 1.5) - 0.04).abs() < 1e-6);
        assert_eq!(fresnel_dielectric(1.0, 1.0), 0.0);
        assert_eq!(fresnel_dielectric(0.1, 1.0 / 1.5), 1.0, "total internal reflection");
        assert!((fresnel_dielectric(1e-6, 1.5) - 1.0).abs() < 1e-3, "grazing reflects everything");
    }

    #[test]
    fn refraction_obeys_snell() {
        let wo = Vec3::new(0.6, 0.0, 0.8);
        let wt = refract(wo, Vec3::Z, 1.5).unwrap();
        assert!((0.6 - 1.5 * (1.0 - wt.z * wt.z).sqrt()).abs() < 1e-5, "{wt:?}");
        assert!(wt.z < 0.0);
        assert!(refract(Vec3::new(0.9, 0.0, 0.436), Vec3::Z, 1.0 / 1.5).is_none());
    }

    #[test]
    fn smooth_glass_weights_conserve_energy() {
        for eta in [1.5f32, 1.0 / 1.5, 1.0001, 3.0] {
            let g = Dielectric { eta, ggx: Ggx { alpha: 0.0 }, tint: Vec3::ONE };
            let wo = Vec3::new(0.3, 0.2, 0.933).normalize();
            let r = g.sample(wo, 0.0, Vec2::ZERO).unwrap();
            assert!((r.1.x / r.2 - 1.0).abs() < 1e-5, "reflection weight is 1");
            if let Some(t) = g.sample(wo, 0.9999, Vec2::ZERO) {
                // Transmission weight is 1/η² (radiance compression).
                assert!((t.1.x / t.2 - 1.0 / (eta * eta)).abs() < 1e-4, "eta {eta}: {}", t.1.x / t.2);
            }
        }
    }
}
