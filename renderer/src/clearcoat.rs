//! KHR_materials_clearcoat: a thin dielectric coat (IOR 1.5, F0 = 0.04) with its own roughness and
//! normal, on top of everything else (sheen and the base material).
//!
//! ```text
//! f = c · F(wo·h) · D(h) G2(wo, wi) / (4 (n_c·wo)(n·wi))  +  (1 − c · F(n_c·wo)) · f_below
//! ```
//! The coat's lobe is divided by the shading cosine n·wi rather than its own n_c·wi, so that
//! f·(n·wi) — what the integrator uses — is the coat's reflection in its own frame: a tilted coat
//! normal then neither creates nor loses energy (with n_c = n the two are the same).
//! (the KHR_materials_clearcoat specification's `fresnel_coat` layering; GGX as in `microfacet.rs`;
//! Schlick's Fresnel). `n_c` is the coat's normal in the base shading frame (from the clearcoat
//! normal map, or the shading normal). Below [`Ggx::DELTA_ALPHA`] (clearcoatRoughness 0, the
//! glTF default) the coat is a mirror reached only by sampling. Directions below the shading
//! surface are given zero coat value and zero pdf, so `sample`, `pdf` and `eval` stay consistent.

use crate::math::{reflect, Frame, Vec2, Vec3};
use crate::microfacet::Ggx;

/// Fresnel reflectance at normal incidence of a coat of IOR 1.5: ((1.5 − 1)/(1.5 + 1))².
pub const COAT_F0: f32 = 0.04;

#[derive(Clone, Copy, Debug)]
pub struct Clearcoat {
    /// clearcoatFactor × texture, in [0, 1].
    pub weight: f32,
    pub ggx: Ggx,
    /// The coat's normal in the base shading frame (unit, upper hemisphere).
    pub normal: Vec3,
}

#[inline]
fn schlick(c: f32) -> f32 {
    let m = (1.0 - c).clamp(0.0, 1.0);
    let m2 = m * m;
    COAT_F0 + (1.0 - COAT_F0) * (m2 * m2 * m)
}

impl Clearcoat {
    #[inline]
    fn frame(&self) -> Frame {
        Frame::from_normal(self.normal)
    }

    /// The share of light the coat reflects at `wo`: c·F(n_c·wo). What lies below is scaled by one
    /// minus this.
    #[inline]
    pub fn reflectance(&self, wo: Vec3) -> f32 {
        self.weight * schlick(wo.dot(self.normal).max(0.0))
    }

    pub fn is_delta(&self) -> bool {
        self.ggx.is_delta()
    }

    /// `wo`, `wi` and their half vector in the coat's frame, when both lie above the coat and `wi`
    /// above the shading surface (else the coat neither reflects nor samples there).
    fn coat_frame(&self, wo: Vec3, wi: Vec3) -> Option<(Vec3, Vec3, Vec3)> {
        if self.is_delta() || wi.z <= 0.0 {
            return None;
        }
        let fr = self.frame();
        let (o, i) = (fr.to_local(wo), fr.to_local(wi));
        let h = (o + i).normalize_or_zero();
        (o.z > 0.0 && i.z > 0.0 && h != Vec3::ZERO).then_some((o, i, h))
    }

    pub fn eval(&self, wo: Vec3, wi: Vec3) -> f32 {
        let Some((o, i, h)) = self.coat_frame(wo, wi) else { return 0.0 };
        // The coat's BRDF in its own frame times its own cosine n_c·wi, expressed per unit of the
        // shading frame's cosine (which the integrator multiplies by): divide by wi.z, not i.z.
        let f = self.weight * schlick(o.dot(h).abs()) * self.ggx.d(h) * self.ggx.g2(o, i) / (4.0 * o.z * wi.z);
        if f.is_finite() {
            f
        } else {
            0.0
        }
    }

    pub fn pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        let Some((o, _, h)) = self.coat_frame(wo, wi) else { return 0.0 };
        let oh = o.dot(h);
        if oh <= 0.0 {
            return 0.0;
        }
        self.ggx.visible_d(o, h) / (4.0 * oh)
    }

    /// A direction from the coat lobe: for a mirror coat, `(wi, reflectance)`; otherwise a GGX
    /// visible-normal sample (value and pdf come from `eval`/`pdf`). None when it falls below.
    pub fn sample(&self, wo: Vec3, u: Vec2) -> Option<Vec3> {
        let wi = if self.is_delta() {
            reflect(wo, self.normal)
        } else {
            let fr = self.frame();
            let o = fr.to_local(wo);
            if o.z <= 0.0 {
                return None;
            }
            let h = self.ggx.sample_visible_normal(o, u);
            fr.to_world(reflect(o, h))
        };
        (wi.z > 0.0 && wi.dot(self.normal) > 0.0 && wi.is_finite()).then_some(wi)
    }
}
