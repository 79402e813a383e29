//! The opaque part of the glTF metallic-roughness BSDF ([`crate::bsdf`]: Lambert diffuse under a
//! GGX dielectric coat, mixed with a GGX conductor by `metallic`), eight lanes at once, one
//! material per lane: what [`crate::spmd::radiance8`] shades metal and plastic with.
//!
//! Every function is its scalar counterpart's arithmetic in its order (`bsdf.rs`'s
//! `specular_probability`, `specular_tint`, `diffuse_scale`, `eval_pdf_opaque` and
//! `sample_opaque`; `microfacet.rs`'s `Ggx`; `math.rs`'s `sin_cos_azimuth` and `reflect`), its
//! branches worked out on every lane and blended, so each lane's numbers are `Bsdf::eval_pdf`'s
//! and `Bsdf::sample`'s bit for bit for a material without transmission, coat or sheen
//! (`renderer/tests/spmd.rs` compares whole images). What the scalar code multiplies by a
//! transmission of 0 (`1 − 0`) or a glass weight of 0 is left out: x·1 = x exactly.

#![cfg(all(target_arch = "x86_64", target_feature = "avx2"))]

use crate::lanes::{select, F8, I8, M8, V8};
use crate::math::{INV_PI, PI};
use crate::microfacet::Ggx;
use std::ops::{Add, Div, Neg, Sub};

/// `bsdf::schlick`: F0 + (1 − F0)(1 − c)⁵, the power as (m²·m²)·m.
#[inline(always)]
fn schlick(f0: V8, c: F8) -> V8 {
    let one = F8::splat(1.0);
    let m = (one - c).clamp(F8::zero(), one);
    let m2 = m * m;
    let k = m2 * m2 * m;
    let ones = V8 { x: one, y: one, z: one };
    f0.add(ones.sub(f0).scale(k))
}

/// `math::luminance`.
#[inline(always)]
fn luminance(c: V8) -> F8 {
    F8::splat(0.2126) * c.x + F8::splat(0.7152) * c.y + F8::splat(0.0722) * c.z
}

/// `math::sin_cos_quarter`, eight lanes.
#[inline(always)]
fn sin_cos_quarter(x: F8) -> (F8, F8) {
    let z = x * x;
    let c = F8::splat;
    let s = ((c(-1.951_529_6e-4) * z + c(8.332_161e-3)) * z - c(1.666_665_5e-1)) * z * x + x;
    let co = ((c(2.443_315_7e-5) * z - c(1.388_731_6e-3)) * z + c(4.166_664_6e-2)) * z * z - c(0.5) * z + c(1.0);
    (s, co)
}

/// `math::sample_cosine_hemisphere`, eight lanes (both wedges worked out, one kept).
#[inline(always)]
pub(crate) fn sample_cosine_hemisphere(ux: F8, uy: F8) -> V8 {
    let (two, one, zero) = (F8::splat(2.0), F8::splat(1.0), F8::zero());
    let (ox, oy) = (two * ux - one, two * uy - one);
    let centre = ox.eq(zero) & oy.eq(zero);
    let wide = ox.abs().gt(oy.abs());
    let q = F8::splat(PI / 4.0);
    let arg = select(wide, q * (oy / ox), q * (ox / oy));
    let (s, c) = sin_cos_quarter(arg);
    let dx = select(wide, ox * c, oy * s);
    let dy = select(wide, ox * s, oy * c);
    let (dx, dy) = (select(centre, zero, dx), select(centre, zero, dy));
    let z = (one - dx * dx - dy * dy).max_finite(zero).sqrt();
    V8 { x: dx, y: dy, z }
}

/// `math::sin_cos_azimuth`: reduced to the nearest multiple of π/2, then turned by its quadrant.
#[inline(always)]
pub(crate) fn sin_cos_azimuth(x: F8) -> (F8, F8) {
    let k = (x * F8::splat(2.0 / PI)).round();
    let (s, c) = sin_cos_quarter(x - k * F8::splat(PI / 2.0));
    // Quadrant 0: (s, c); 1: (c, −s); 2: (−s, −c); 3: (−c, s).
    let q = k.to_i32_in_range().and(I8::splat(3));
    let (q1, q2, q3) = (q.eq(I8::splat(1)), q.eq(I8::splat(2)), q.eq(I8::splat(3)));
    let swap = q1 | q3;
    let (sin, cos) = (select(swap, c, s), select(swap, s, c));
    (select(q2 | q3, -sin, sin), select(q1 | q2, -cos, cos))
}

/// A 3-vector's `normalize_or_zero` (glam: times 1/length where that is finite and positive).
#[inline(always)]
pub(crate) fn normalize_or_zero(v: V8) -> V8 {
    let rcp = F8::splat(1.0) / v.dot(v).sqrt();
    V8::select(rcp.is_finite() & rcp.gt(F8::zero()), v.scale(rcp), V8::zero())
}

/// [`Ggx`] with one alpha per lane.
#[derive(Clone, Copy)]
struct Ggx8 {
    alpha: F8,
}

impl Ggx8 {
    #[inline(always)]
    fn is_delta(self) -> M8 {
        self.alpha.lt(F8::splat(Ggx::DELTA_ALPHA))
    }

    /// `Ggx::d`.
    #[inline(always)]
    fn d(self, h: V8) -> F8 {
        let cos2 = h.z * h.z;
        let a2 = self.alpha * self.alpha;
        let one = F8::splat(1.0);
        let denom = cos2 * (a2 - one) + one;
        let d = a2 / (F8::splat(PI) * denom * denom);
        select(cos2.le(F8::zero()), F8::zero(), d)
    }

    /// `Ggx::lambda`.
    #[inline(always)]
    fn lambda(self, w: V8) -> F8 {
        let (zero, one) = (F8::zero(), F8::splat(1.0));
        let cos2 = w.z * w.z;
        let tan2 = (one - cos2).max(zero) / cos2;
        let a2tan2 = self.alpha * self.alpha * tan2;
        let l = a2tan2 / (F8::splat(2.0) * (one + (one + a2tan2).sqrt()));
        select(cos2.le(zero), F8::splat(f32::INFINITY), l)
    }

    /// `Ggx::visible_d_given` for a `wo` above the surface, with Λ(wo) known.
    #[inline(always)]
    fn visible_d_given(self, lambda_o: F8, wo: V8, h: V8, d: F8) -> F8 {
        let g1 = F8::splat(1.0) / (F8::splat(1.0) + lambda_o);
        g1 * wo.dot(h).max(F8::zero()) * d / wo.z
    }

    /// `Ggx::sample_visible_normal` (Dupuy & Benyoub 2023, spherical caps).
    #[inline(always)]
    fn sample_visible_normal(self, wo: V8, ux: F8, uy: F8) -> V8 {
        let (zero, one) = (F8::zero(), F8::splat(1.0));
        let a = self.alpha;
        let v = V8 { x: wo.x * a, y: wo.y * a, z: wo.z };
        // glam's `normalize`: times 1/length.
        let wo_std = v.scale(one / v.dot(v).sqrt());
        let phi = F8::splat(2.0 * PI) * ux;
        let z = (one - uy) * (one + wo_std.z) - wo_std.z;
        let sin_theta = (one - z * z).clamp(zero, one).sqrt();
        let (sin_phi, cos_phi) = sin_cos_azimuth(phi);
        let c = V8 { x: sin_theta * cos_phi, y: sin_theta * sin_phi, z };
        let h_std = c.add(wo_std);
        let h = V8 { x: h_std.x * a, y: h_std.y * a, z: h_std.z.max(zero) };
        let len = h.dot(h).sqrt();
        let ok = len.gt(zero) & len.is_finite();
        V8::select(ok, h.div(len), V8 { x: zero, y: zero, z: one })
    }
}

/// A sample of [`OpaqueBsdf8::sample`] on the lanes in `ok`: the direction, f, the pdf (for a
/// mirror lane, the mirror lobe's probability), and which lanes are mirror (delta) events.
#[derive(Clone, Copy)]
pub(crate) struct Sample8 {
    pub wi: V8,
    pub f: V8,
    pub pdf: F8,
    pub delta: M8,
    pub ok: M8,
}

impl Sample8 {
    /// Lane by lane, `a` where `m` is set, else `b`.
    #[inline(always)]
    pub fn select(m: M8, a: Sample8, b: Sample8) -> Sample8 {
        Sample8 {
            wi: V8::select(m, a.wi, b.wi),
            f: V8::select(m, a.f, b.f),
            pdf: select(m, a.pdf, b.pdf),
            delta: M8::select(m, a.delta, b.delta),
            ok: M8::select(m, a.ok, b.ok),
        }
    }
    /// `BsdfSample::weight`: f·|cos θi|/pdf, or f/pdf for a delta event.
    #[inline(always)]
    pub fn weight(&self) -> V8 {
        let rough = self.f.scale(self.wi.z.abs()).div(self.pdf);
        if self.delta.any() {
            V8::select(self.delta, self.f.div(self.pdf), rough)
        } else {
            rough
        }
    }
}

/// Eight opaque metallic-roughness BSDFs (`Bsdf` with no transmission, coat or sheen), one per
/// lane, in the shading frame.
#[derive(Clone, Copy)]
pub(crate) struct OpaqueBsdf8 {
    pub base: V8,
    pub metallic: F8,
    /// KHR_materials_specular's weight.
    pub specular: F8,
    /// The dielectric F0.
    pub f0: V8,
    /// GGX's alpha (roughness²).
    pub alpha: F8,
}

impl OpaqueBsdf8 {
    #[inline(always)]
    fn ggx(&self) -> Ggx8 {
        Ggx8 { alpha: self.alpha }
    }

    /// `Bsdf::specular_probability` (transmission 0: the opaque share is 1 − metallic).
    #[inline(always)]
    fn specular_probability(&self, cos_o: F8) -> F8 {
        let (zero, one) = (F8::zero(), F8::splat(1.0));
        let fd = schlick(self.f0, cos_o);
        let fm = schlick(self.base, cos_o);
        let opaque = one - self.metallic;
        let spec = self.metallic * luminance(fm) + opaque * self.specular * luminance(fd);
        let diff = opaque * luminance(self.base) * (one - self.specular * fd.max_element());
        let (spec, diff) = (spec.max(zero), diff.max(zero));
        let sum = spec + diff;
        select(sum.le(zero), zero, spec / sum)
    }

    /// `Bsdf::specular_tint`: (1 − m)·s·F_d + m·F_m.
    #[inline(always)]
    fn specular_tint(&self, c: F8) -> V8 {
        let dielectric = schlick(self.f0, c).scale((F8::splat(1.0) - self.metallic) * self.specular);
        dielectric.add(schlick(self.base, c).scale(self.metallic))
    }

    /// `Bsdf::diffuse_scale` (transmission 0).
    #[inline(always)]
    fn diffuse_scale(&self, c: F8) -> F8 {
        let one = F8::splat(1.0);
        (one - self.metallic) * (one - self.specular * schlick(self.f0, c).max_element())
    }

    /// `Bsdf::eval_pdf`: f(wo, wi) and the pdf of [`Self::sample`] giving `wi`, without the
    /// mirror lobe (`eval_pdf_opaque`, then `eval_pdf_base`'s sums from a glass share of 0).
    #[inline(always)]
    pub fn eval_pdf(&self, wo: V8, wi: V8) -> (V8, F8) {
        let (zero, one, four) = (F8::zero(), F8::splat(1.0), F8::splat(4.0));
        let ggx = self.ggx();
        let below = wo.z.le(zero) | wi.z.le(zero);
        let h = normalize_or_zero(wo.add(wi));
        let ps = self.specular_probability(wo.z);
        let pdf_diffuse = (one - ps) * (wi.z.max(zero) * F8::splat(INV_PI));
        let c = wo.dot(h).abs();
        let f_diffuse = self.base.scale(self.diffuse_scale(c) * F8::splat(INV_PI));
        let d = ggx.d(h);
        let lambda_o = ggx.lambda(wo);
        let g2 = one / (one + lambda_o + ggx.lambda(wi));
        let s = d * g2 / (four * wo.z * wi.z);
        // A Lambert material (no metal, KHR_materials_specular 0) has no specular lobe.
        let lobe = self.metallic.gt(zero) | self.specular.gt(zero);
        let rough = !ggx.is_delta();
        let f = V8::select(lobe & rough, f_diffuse.add(self.specular_tint(c).scale(s)), f_diffuse);
        let woh = wo.dot(h);
        let pdf_specular = pdf_diffuse + ps * ggx.visible_d_given(lambda_o, wo, h, d) / (four * woh);
        let pdf = select(rough & ps.gt(zero) & woh.gt(zero), pdf_specular, pdf_diffuse);
        // h = 0 (wi = −wo): the diffuse pdf alone; below the surface: nothing.
        let h_zero = !h.ne_zero();
        let f = V8::select(h_zero | below, V8::zero(), f);
        let pdf = select(below, zero, pdf);
        // `eval_pdf_base`: 0 + f and 0 + 1·pdf (signed zeros become +0).
        (V8::zero().add(f), zero + pdf)
    }

    /// `Bsdf::sample` (through `sample_base` with a glass share of 0, then `sample_opaque`) for a
    /// `wo` above the surface: the lobe by `u_lobe`, the direction by (`ux`, `uy`); a rough
    /// sample takes f and pdf from [`Self::eval_pdf`] (`finish`).
    #[inline(always)]
    pub fn sample(&self, wo: V8, u_lobe: F8, ux: F8, uy: F8, cosine: V8) -> Sample8 {
        let zero = F8::zero();
        let ggx = self.ggx();
        // (u_lobe − 0)/(1 − 0) is u_lobe exactly.
        let u_lobe = u_lobe.min(F8::splat(1.0 - f32::EPSILON));
        let ps = self.specular_probability(wo.z);
        let specular = u_lobe.lt(ps);
        let mirror = specular & ggx.is_delta();
        let rough_specular = specular.and_not(mirror);
        let wi = if rough_specular.any() {
            let h = ggx.sample_visible_normal(wo, ux, uy);
            // `math::reflect`: 2(w·h)·h − w.
            let r = h.scale(F8::splat(2.0) * wo.dot(h)).sub(wo);
            V8::select(rough_specular, r, cosine)
        } else {
            cosine
        };
        let ok = wi.z.gt(zero);
        let (f, pdf) = self.eval_pdf(wo, wi);
        let ok = ok & pdf.gt(zero) & pdf.is_finite();
        if !mirror.any() {
            return Sample8 { wi, f, pdf, delta: mirror, ok };
        }
        // The mirror: f is the specular tint at wo, the pdf the lobe's probability (times the
        // opaque share, 1).
        let wi = V8::select(mirror, V8 { x: -wo.x, y: -wo.y, z: wo.z }, wi);
        let f = V8::select(mirror, self.specular_tint(wo.z), f);
        let pdf = select(mirror, ps, pdf);
        Sample8 { wi, f, pdf, delta: mirror, ok: ok | mirror }
    }
}

/// `dielectric::fresnel_dielectric`: unpolarized Fresnel reflectance, `cos_i` on wo's side (a
/// negative one flips the side and inverts `eta`).
#[inline(always)]
fn fresnel_dielectric(cos_i: F8, eta: F8) -> F8 {
    let (zero, one) = (F8::zero(), F8::splat(1.0));
    let flip = cos_i.lt(zero);
    let (cos_i, eta) = (select(flip, -cos_i, cos_i), select(flip, one / eta, eta));
    let cos_i = cos_i.min(one);
    let sin2_t = (one - cos_i * cos_i) / (eta * eta);
    let cos_t = (one - sin2_t).max(zero).sqrt();
    let r_parl = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
    let r_perp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
    let r = F8::splat(0.5) * (r_parl * r_parl + r_perp * r_perp);
    // Total internal reflection.
    select(sin2_t.ge(one), one, r)
}

/// `dielectric::refract`: `wi` through the interface with normal `n` and relative index `eta`;
/// the mask is false on total internal reflection.
#[inline(always)]
fn refract(wi: V8, n: V8, eta: F8) -> (V8, M8) {
    let (zero, one) = (F8::zero(), F8::splat(1.0));
    let cos_i = n.dot(wi);
    let sin2_i = (one - cos_i * cos_i).max(zero);
    let sin2_t = sin2_i / (eta * eta);
    let cos_t = (one - sin2_t).sqrt();
    let t = wi.neg().div(eta).add(n.scale(cos_i / eta - cos_t));
    (t, !sin2_t.ge(one))
}

/// Eight glass interfaces (`Bsdf` with transmission 1 and no metal, coat or sheen: its glass part
/// [`crate::dielectric::Dielectric`] alone, at weight 1), one per lane, in the shading frame.
#[derive(Clone, Copy)]
pub(crate) struct Glass8 {
    /// n(far side)/n(wo's side).
    pub eta: F8,
    pub alpha: F8,
    /// The transmitted light's tint (the base colour).
    pub tint: V8,
}

impl Glass8 {
    /// `Dielectric::is_delta`.
    #[inline(always)]
    pub fn is_delta(&self) -> M8 {
        Ggx8 { alpha: self.alpha }.is_delta() | self.eta.eq(F8::splat(1.0))
    }

    /// `Dielectric::eval_pdf` (times the glass weight 1).
    #[inline(always)]
    pub fn eval_pdf(&self, wo: V8, wi: V8) -> (V8, F8) {
        let (zero, one, four) = (F8::zero(), F8::splat(1.0), F8::splat(4.0));
        let ggx = Ggx8 { alpha: self.alpha };
        // `half_vector`.
        let reflect = wi.z.gt(zero);
        let etap = select(reflect, one, self.eta);
        let wm = wi.scale(etap).add(wo);
        let len2 = wm.dot(wm);
        let none = self.is_delta() | wi.z.eq(zero) | wo.z.le(zero) | len2.eq(zero);
        let wm = wm.scale(one / len2.sqrt());
        let wm = V8::select(wm.z.lt(zero), wm.neg(), wm);
        let (wm_i, wm_o) = (wm.dot(wi), wm.dot(wo));
        let none = none | (wm_i * wi.z).lt(zero) | (wm_o * wo.z).lt(zero);
        // The pair's terms.
        let f = fresnel_dielectric(wm_o, self.eta);
        let d = ggx.d(wm);
        let lambda_o = ggx.lambda(wo);
        let g = one / (one + lambda_o + ggx.lambda(wi));
        let dvis = ggx.visible_d_given(lambda_o, wo, wm, d);
        // Reflection.
        let fr = d * g * f / (four * wo.z * wi.z).abs();
        let pr = dvis / (four * wm_o.abs()) * f;
        // Transmission.
        let denom = wm_i + wm_o / etap;
        let pt = dvis * (wm_i.abs() / (denom * denom)) * (one - f);
        let denom = denom * denom * wi.z * wo.z;
        let ft = d * (one - f) * g * (wm_i * wm_o / denom).abs() / (etap * etap);
        let ft = select(denom.eq(zero), zero, ft);
        let f_val = V8::select(reflect, V8 { x: fr, y: fr, z: fr }, self.tint.scale(ft));
        let pdf = select(reflect, pr, pt);
        (V8::select(none, V8::zero(), f_val), select(none, zero, pdf))
    }

    /// `Bsdf::sample` through `sample_base` (glass weight 1: `u_lobe` is the glass's own choice
    /// between reflection and transmission) and `Dielectric::sample_direction`, for a `wo` above
    /// the surface; a rough direction takes f and pdf from [`Self::eval_pdf`] (`finish`). Only
    /// the lanes `lanes` are read (the caller's glass lanes; the others' answers are meaningless):
    /// where none of them is rough, the rough sample is not computed, and where none is smooth,
    /// the smooth one (a scene's other surfaces left the rough path running wherever one glass
    /// lane was smooth: docs/performance-journal.md, thirty-fourth round).
    #[inline(always)]
    pub fn sample(&self, lanes: M8, wo: V8, u_lobe: F8, ux: F8, uy: F8) -> Sample8 {
        let (zero, one) = (F8::zero(), F8::splat(1.0));
        let ggx = Ggx8 { alpha: self.alpha };
        let delta = self.is_delta();
        let z_axis = V8 { x: zero, y: zero, z: one };
        let mirror = |w: V8| V8 { x: -w.x, y: -w.y, z: w.z };
        // Rough: a visible microfacet, then reflection or refraction through it by Fresnel.
        let rough = lanes.and_not(delta);
        let (wi_rough, ok_rough, f_rough, pdf_rough) = if rough.any() {
            let wm = ggx.sample_visible_normal(wo, ux, uy);
            let r = fresnel_dielectric(wo.dot(wm), self.eta);
            let reflects = u_lobe.lt(r);
            let reflected = wm.scale(F8::splat(2.0) * wo.dot(wm)).sub(wo);
            let (refracted, through) = refract(wo, wm, self.eta);
            let wi = V8::select(reflects, reflected, refracted);
            let ok = select(reflects, wi.z, -wi.z).gt(zero) & (reflects | through);
            let (f, pdf) = self.eval_pdf(wo, wi);
            (wi, ok & pdf.gt(zero) & pdf.is_finite(), f, pdf)
        } else {
            (z_axis, M8::from_bits(0), V8::zero(), zero)
        };
        if !(lanes & delta).any() {
            return Sample8 { wi: wi_rough, f: f_rough, pdf: pdf_rough, delta, ok: ok_rough };
        }
        // Smooth: the mirror with probability R, else the refracted direction.
        let r = fresnel_dielectric(wo.z, self.eta);
        let reflects = u_lobe.lt(r);
        let (refracted, through) = refract(wo, z_axis, self.eta);
        let t = one - r;
        let wi = V8::select(reflects, mirror(wo), refracted);
        let f = V8::select(reflects, V8 { x: r, y: r, z: r }, self.tint.scale(t / (self.eta * self.eta)));
        let pdf = select(reflects, r, t);
        let ok_delta = reflects | through;
        Sample8 {
            wi: V8::select(delta, wi, wi_rough),
            f: V8::select(delta, f, f_rough),
            pdf: select(delta, pdf, pdf_rough),
            delta,
            ok: M8::select(delta, ok_delta, ok_rough),
        }
    }
}
