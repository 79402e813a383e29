//! The GGX (Trowbridge-Reitz) microfacet distribution with Smith masking-shadowing and sampling of
//! visible normals. All vectors are in the local shading frame (normal = +z).
//!
//! References: Walter et al. 2007 "Microfacet Models for Refraction through Rough Surfaces";
//! Heitz 2014 "Understanding the Masking-Shadowing Function"; Dupuy & Benyoub 2023 "Sampling Visible
//! GGX Normals with Spherical Caps".

use crate::math::{Vec2, Vec3, PI};

/// Isotropic GGX with `alpha = roughness²` (glTF convention).
#[derive(Clone, Copy, Debug)]
pub struct Ggx {
    pub alpha: f32,
}

impl Ggx {
    /// Below this alpha a specular lobe is treated as a perfect mirror (delta). Chosen where the GGX
    /// lobe's half-width (~alpha radians) is far below a pixel's footprint in any practical camera and
    /// where `D` would start to overflow f32 (`1 / (π α²)`).
    pub const DELTA_ALPHA: f32 = 1e-3;

    pub fn from_roughness(roughness: f32) -> Self {
        let r = roughness.clamp(0.0, 1.0);
        Ggx { alpha: r * r }
    }

    #[inline]
    pub fn is_delta(&self) -> bool {
        self.alpha < Self::DELTA_ALPHA
    }

    /// Normal distribution D(h).
    #[inline]
    pub fn d(&self, h: Vec3) -> f32 {
        let cos2 = h.z * h.z;
        if cos2 <= 0.0 {
            return 0.0;
        }
        let a2 = self.alpha * self.alpha;
        let denom = cos2 * (a2 - 1.0) + 1.0;
        a2 / (PI * denom * denom)
    }

    /// Smith Λ(w) for GGX.
    #[inline]
    pub fn lambda(&self, w: Vec3) -> f32 {
        let cos2 = w.z * w.z;
        if cos2 <= 0.0 {
            return f32::INFINITY;
        }
        let tan2 = ((1.0 - cos2).max(0.0)) / cos2;
        let a2tan2 = self.alpha * self.alpha * tan2;
        // (sqrt(1 + x) - 1) / 2 written as x / (2 (1 + sqrt(1 + x))) to avoid cancellation for small x.
        a2tan2 / (2.0 * (1.0 + (1.0 + a2tan2).sqrt()))
    }

    #[inline]
    pub fn g1(&self, w: Vec3) -> f32 {
        1.0 / (1.0 + self.lambda(w))
    }

    /// Height-correlated masking-shadowing G2 (Heitz 2014, eq. 99).
    #[inline]
    pub fn g2(&self, wo: Vec3, wi: Vec3) -> f32 {
        1.0 / (1.0 + self.lambda(wo) + self.lambda(wi))
    }

    /// Distribution of visible normals D_wo(h) = G1(wo) max(0, wo·h) D(h) / cos θo.
    #[inline]
    pub fn visible_d(&self, wo: Vec3, h: Vec3) -> f32 {
        self.visible_d_given(wo, h, self.d(h))
    }

    /// [`Self::visible_d`] with D(h) already computed (`d`), for callers that also need D.
    #[inline]
    pub fn visible_d_given(&self, wo: Vec3, h: Vec3, d: f32) -> f32 {
        if wo.z <= 0.0 {
            return 0.0;
        }
        self.g1(wo) * wo.dot(h).max(0.0) * d / wo.z
    }

    /// Samples a visible normal for `wo` (upper hemisphere) with spherical caps (Dupuy & Benyoub 2023).
    #[inline]
    pub fn sample_visible_normal(&self, wo: Vec3, u: Vec2) -> Vec3 {
        let wo_std = Vec3::new(wo.x * self.alpha, wo.y * self.alpha, wo.z).normalize();
        let phi = 2.0 * PI * u.x;
        let z = (1.0 - u.y) * (1.0 + wo_std.z) - wo_std.z;
        let sin_theta = (1.0 - z * z).clamp(0.0, 1.0).sqrt();
        let (sin_phi, cos_phi) = crate::math::sin_cos_azimuth(phi);
        let c = Vec3::new(sin_theta * cos_phi, sin_theta * sin_phi, z);
        let h_std = c + wo_std;
        let h = Vec3::new(h_std.x * self.alpha, h_std.y * self.alpha, h_std.z.max(0.0));
        let len = h.length();
        if len > 0.0 && len.is_finite() {
            h / len
        } else {
            Vec3::Z
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// ∫ D(h) cos θh dω = 1 (the projected microfacet area equals the macro-surface area).
    #[test]
    fn d_is_normalized() {
        for alpha in [0.01f32, 0.1, 0.5, 1.0] {
            let g = Ggx { alpha };
            let nt = 4000;
            let mut sum = 0.0f64;
            // Integrate in μ = cos θ with a substitution that concentrates points near μ = 1.
            for i in 0..nt {
                let t = (i as f64 + 0.5) / nt as f64;
                let mu = 1.0 - t * t; // dμ = 2 t dt
                let sin = (1.0 - mu * mu).max(0.0).sqrt();
                let h = Vec3::new(sin as f32, 0.0, mu as f32);
                sum += g.d(h) as f64 * mu * 2.0 * t * (1.0 / nt as f64) * 2.0 * std::f64::consts::PI;
            }
            assert!((sum - 1.0).abs() < 0.01, "alpha {alpha}: {sum}");
        }
    }

    #[test]
    fn g1_limits() {
        let g = Ggx { alpha: 0.5 };
        assert!((g.g1(Vec3::Z) - 1.0).abs() < 1e-6);
        assert_eq!(g.g1(Vec3::new(1.0, 0.0, 0.0)), 0.0);
        let graze = Vec3::new((1.0f32 - 1e-12).sqrt(), 0.0, 1e-6);
        assert!(g.g1(graze).is_finite());
    }
}
