//! Eight paths in lock step, their shading done on eight-lane registers ([`crate::lanes`]): the
//! first SPMD kernel of issue 15, for the scenes whose every surface is a plain Lambert material
//! lit by emissive triangles (the Cornell box's kind).
//!
//! Each lane runs exactly [`crate::integrator::radiance`]'s arithmetic for its path, in its
//! order, so a lane's radiance is bit-equal to the scalar path's (`renderer/tests/spmd.rs`
//! compares whole images). What stays one lane at a time: drawing the sample sets, tracing the
//! rays, the surface point and the light choice (table lookups); what goes eight-wide: the frame,
//! the BSDF's sample and value, the point on the light, the pdfs and MIS weights, the ray
//! offsets, the throughput and Russian roulette.

#![cfg(all(target_arch = "x86_64", target_feature = "avx2"))]

use crate::lanes::{select, F8, M8, V8, LANES};
use crate::math::{Vec3, INV_PI, PI, SHADOW_EPSILON};
use crate::mesh::flags;
use crate::sampler::{dims, PixelSample};
use crate::scene::Scene;
use crate::settings::{IntegratorKind, MisHeuristic, RenderSettings};

/// What the kernel reads of a scene it can render: per material its albedo and whether NEE runs
/// there, per area light its triangle and emission.
pub struct LambertScene {
    /// Per material: base colour (the Lambert BSDF's), emission (zero if none), and whether
    /// next-event estimation samples a light at a vertex of it.
    albedo: Vec<Vec3>,
    nee: Vec<bool>,
    /// Per area light: p0, e1, e2, ng, area, emitted radiance, two-sidedness, emissive.
    light_p0: Vec<Vec3>,
    light_e1: Vec<Vec3>,
    light_e2: Vec<Vec3>,
    light_ng: Vec<Vec3>,
    light_area: Vec<f32>,
    light_le: Vec<Vec3>,
    light_two_sided: Vec<bool>,
}

impl LambertScene {
    /// The kernel's tables, or None when the scene or settings need something it does not do:
    /// textures, vertex colours or tangents, non-Lambert or unlit materials, transparency,
    /// punctual or environment lights, an integrator other than MIS.
    pub fn new(scene: &Scene, settings: &RenderSettings) -> Option<LambertScene> {
        if settings.integrator != IntegratorKind::Mis
            || scene.has_transparency()
            || scene.lights.environment.is_some()
            || !scene.lights.punctual.is_empty()
            || scene.lights.is_empty()
            || !scene.mesh.instances.is_empty()
        {
            return None;
        }
        if scene.mesh.triangles.iter().any(|t| t.flags & (flags::TANGENTS | flags::COLORS) != 0) {
            return None;
        }
        let mut used = vec![false; scene.materials.len()];
        for t in &scene.mesh.triangles {
            *used.get_mut(t.material as usize)? = true;
        }
        let mut albedo = Vec::with_capacity(scene.materials.len());
        let mut nee = Vec::with_capacity(scene.materials.len());
        for (i, m) in scene.materials.iter().enumerate() {
            if !used[i] {
                // Never hit: its entry is never read.
                albedo.push(Vec3::ZERO);
                nee.push(false);
                continue;
            }
            let b = scene.uniform_bsdf(i as u32)?;
            if m.unlit || !b.is_lambert() || m.normal_texture.is_some() || m.emissive_texture.is_some() {
                return None;
            }
            albedo.push(b.base_color);
            nee.push(!b.is_delta_only());
        }
        let lights = &scene.lights.lights;
        let mut s = LambertScene {
            albedo,
            nee,
            light_p0: Vec::with_capacity(lights.len()),
            light_e1: Vec::with_capacity(lights.len()),
            light_e2: Vec::with_capacity(lights.len()),
            light_ng: Vec::with_capacity(lights.len()),
            light_area: Vec::with_capacity(lights.len()),
            light_le: Vec::with_capacity(lights.len()),
            light_two_sided: Vec::with_capacity(lights.len()),
        };
        for l in lights {
            let m = scene.materials.get(l.material as usize)?;
            s.light_p0.push(l.p0);
            s.light_e1.push(l.e1);
            s.light_e2.push(l.e2);
            s.light_ng.push(l.ng);
            s.light_area.push(l.area);
            // `light::emitted`: zero from a material that does not emit.
            s.light_le.push(if m.is_emissive() { m.emissive } else { Vec3::ZERO });
            s.light_two_sided.push(m.double_sided);
        }
        Some(s)
    }
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
fn sample_cosine_hemisphere(ux: F8, uy: F8) -> V8 {
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

/// `math::sample_uniform_triangle`'s b1 and b2, eight lanes.
#[inline(always)]
fn sample_uniform_triangle(ux: F8, uy: F8) -> (F8, F8) {
    let half = F8::splat(2.0);
    let first = ux.lt(uy);
    let b0_a = ux / half;
    let b1_a = uy - b0_a;
    let b1_b = uy / half;
    let b0_b = ux - b1_b;
    let (b0, b1) = (select(first, b0_a, b0_b), select(first, b1_a, b1_b));
    let b2 = F8::splat(1.0) - b0 - b1;
    (b1, b2)
}

/// `math::Frame`, eight lanes.
#[derive(Clone, Copy)]
struct Frame8 {
    s: V8,
    t: V8,
    n: V8,
}

impl Frame8 {
    /// `Frame::from_normal` (Duff et al. 2017).
    #[inline(always)]
    fn from_normal(n: V8) -> Frame8 {
        let one = F8::splat(1.0);
        let sign = n.z.sign_one();
        let a = F8::splat(-1.0) / (sign + n.z);
        let b = n.x * n.y * a;
        let s = V8 { x: one + sign * n.x * n.x * a, y: sign * b, z: -sign * n.x };
        let t = V8 { x: b, y: sign + n.y * n.y * a, z: -n.y };
        Frame8 { s, t, n }
    }
    #[inline(always)]
    fn to_local(&self, v: V8) -> V8 {
        V8 { x: v.dot(self.s), y: v.dot(self.t), z: v.dot(self.n) }
    }
    #[inline(always)]
    fn to_world(&self, v: V8) -> V8 {
        self.s.scale(v.x).add(self.t.scale(v.y)).add(self.n.scale(v.z))
    }
    #[inline(always)]
    fn select(m: M8, a: Frame8, b: Frame8) -> Frame8 {
        Frame8 { s: V8::select(m, a.s, b.s), t: V8::select(m, a.t, b.t), n: V8::select(m, a.n, b.n) }
    }
}

/// `math::offset_ray_origin_scaled`, eight lanes.
#[inline(always)]
fn offset_ray_origin(p: V8, n: V8, scale: f32) -> V8 {
    let near = F8::splat((1.0 / 32.0) * scale);
    let float_scale = F8::splat((1.0 / 65536.0) * scale);
    let int_scale = F8::splat(16.0);
    let zero = F8::zero();
    let axis = |p: F8, n: F8| {
        let o = (int_scale * n).to_i32_in_range();
        let o = crate::lanes::I8::select(p.lt(zero), o.neg(), o);
        let pi = p.add_to_bits(o);
        select(p.abs().lt(near), p + float_scale * n, pi)
    };
    V8 { x: axis(p.x, n.x), y: axis(p.y, n.y), z: axis(p.z, n.z) }
}

/// `integrator::mis_weight`, eight lanes.
#[inline(always)]
fn mis_weight(h: MisHeuristic, f: F8, g: F8) -> F8 {
    let (zero, one) = (F8::zero(), F8::splat(1.0));
    let (f, g) = match h {
        MisHeuristic::Power => (f * f, g * g),
        MisHeuristic::Balance => (f, g),
    };
    let sum = f + g;
    let w = f / sum;
    let w = select(sum.le(zero), zero, w);
    select(f.abs().eq(F8::splat(f32::INFINITY)), one, w)
}

/// [`crate::integrator::radiance`] for eight samples of one pixel at once (`d[k]` with
/// `samplers[k]`; lanes from `n` on are empty), into `out[..n]`. Adds the rays traced to `rays`.
#[allow(clippy::too_many_arguments)]
pub fn radiance8(
    scene: &Scene,
    tables: &LambertScene,
    settings: &RenderSettings,
    o: Vec3,
    d: &[Vec3; LANES],
    samplers: &[PixelSample; LANES],
    n: usize,
    rays: &mut u64,
    out: &mut [Vec3],
) {
    let zero = F8::zero();
    let one = F8::splat(1.0);
    let mut l = V8::zero();
    let mut beta = V8::splat(Vec3::ONE);
    let mut prev_p = [Vec3::ZERO; LANES];
    let mut prev_n = [Vec3::ZERO; LANES];
    let mut prev_pdf = [0f32; LANES];
    // Lanes whose last bounce left a previous vertex (all but the camera ray: Lambert has no delta).
    let mut has_prev = false;
    let mut ro = [o; LANES];
    let mut rd = V8::from_lanes(d);
    let mut alive: u32 = (1u32 << n.min(LANES)) - 1;
    let mut depth = 0u32;
    let scale = scene.offset_scale();
    while alive != 0 {
        // One lane at a time: the sample sets, the ray, the surface point and the emission met.
        let dirs = rd.to_lanes();
        let mut u_bsdf = [[0f32; LANES]; 4];
        let mut u_light = [[0f32; LANES]; 4];
        let (mut p, mut ng, mut ns) = ([Vec3::ZERO; LANES], [Vec3::ZERO; LANES], [Vec3::ZERO; LANES]);
        let mut plane_error = [0f32; LANES];
        let mut albedo = [Vec3::ZERO; LANES];
        let mut nee_bits = 0u32;
        let mut emit = [Vec3::ZERO; LANES];
        let mut emit_w = [1f32; LANES];
        let mut shading = 0u32;
        let base = dims::BOUNCE_BASE + dims::BOUNCE_STRIDE * depth;
        let sets = ((base + dims::BSDF_DIR) / 4, (base + dims::LIGHT_POS) / 4);
        let mut bits = alive;
        while bits != 0 {
            let k = bits.trailing_zeros() as usize;
            bits &= bits - 1;
            *rays += 1;
            let draw = |u_bsdf: &mut [[f32; LANES]; 4], u_light: &mut [[f32; LANES]; 4]| {
                let (a, b) = samplers[k].get_4d_pair(sets.0, sets.1);
                for i in 0..4 {
                    u_bsdf[i][k] = a[i];
                    u_light[i][k] = b[i];
                }
            };
            if depth > 0 {
                draw(&mut u_bsdf, &mut u_light);
            }
            // A lane that finds nothing, or stops here, is not shading: it is not alive next round.
            let Some(hit) = scene.accel.intersect(ro[k], dirs[k], f32::INFINITY) else { continue };
            if depth == 0 {
                draw(&mut u_bsdf, &mut u_light);
            }
            let sp = scene.mesh.surface_point(hit.triangle, hit.b1, hit.b2);
            let material_id = scene.mesh.triangles[hit.triangle as usize].material as usize;
            let material = &scene.materials[material_id];
            if material.is_emissive() {
                let le = crate::light::emitted(material, &scene.textures, sp.ng, sp.uv, -dirs[k]);
                if le != Vec3::ZERO {
                    emit[k] = le;
                    if has_prev {
                        let light_pdf =
                            scene.lights.pdf(hit.triangle, prev_p[k], Some(prev_n[k]), sp.p, sp.ng);
                        emit_w[k] = crate::integrator::mis_weight(settings.mis_heuristic, prev_pdf[k], light_pdf);
                    }
                }
            }
            if depth >= settings.max_depth {
                continue;
            }
            shading |= 1 << k;
            (p[k], ng[k], ns[k], plane_error[k]) = (sp.p, sp.ng, sp.ns, sp.plane_error);
            albedo[k] = tables.albedo[material_id];
            if tables.nee[material_id] {
                nee_bits |= 1 << k;
            }
        }
        // Emission found (each lane's l += β·Le·w; lanes without add zero).
        let emit_v = V8::from_lanes(&emit);
        let w = F8::from_array(emit_w);
        let add = beta.mul(emit_v).scale(w);
        l = V8::select(emit_v.ne_zero(), l.add(add), l);
        if shading == 0 {
            break;
        }

        // Eight lanes: the frame, the BSDF's sample, the light's point, MIS, the next ray.
        let act = M8::from_bits(shading);
        let wo_world = rd.neg();
        let (pv, mut ngv, mut nsv) = (V8::from_lanes(&p), V8::from_lanes(&ng), V8::from_lanes(&ns));
        let flip = ngv.dot(wo_world).lt(zero);
        ngv = V8::select(flip, ngv.neg(), ngv);
        let flip = nsv.dot(ngv).lt(zero);
        nsv = V8::select(flip, nsv.neg(), nsv);
        let frame_s = Frame8::from_normal(nsv);
        let wo_s = frame_s.to_local(wo_world);
        let back = wo_s.z.le(zero);
        let (frame, wo) = if back.any() {
            let frame_g = Frame8::from_normal(ngv);
            let wo_g = frame_g.to_local(wo_world);
            (Frame8::select(back, frame_g, frame_s), V8::select(back, wo_g, wo_s))
        } else {
            (frame_s, wo_s)
        };
        let act = act.and_not(wo.z.le(zero));
        let plane_error = F8::from_array(plane_error);
        let origin = offset_ray_origin(pv.add(ngv.scale(plane_error)), ngv, scale);
        let albedo = V8::from_lanes(&albedo);
        let f_lambert = V8::zero().add(albedo.scale(F8::splat(INV_PI)));

        // BSDF sample (Lambert: cosine hemisphere), drawn before NEE as the scalar path does.
        let u_dir = (F8::from_array(u_bsdf[(dims::BSDF_DIR % 4) as usize]), F8::from_array(u_bsdf[(dims::BSDF_DIR % 4 + 1) as usize]));
        let wi = sample_cosine_hemisphere(u_dir.0, u_dir.1);
        let bsdf_pdf = wi.z.max_finite(zero) * F8::splat(INV_PI);
        let has_next = act & wi.z.gt(zero) & bsdf_pdf.gt(zero) & bsdf_pdf.is_finite();

        // Next-event estimation: the light chosen one lane at a time, the rest eight-wide.
        let nee = act & M8::from_bits(nee_bits);
        if nee.any() {
            let u_sel = u_light[(dims::LIGHT_SELECT % 4) as usize];
            let (mut lp0, mut le1, mut le2, mut lng) = ([Vec3::ZERO; LANES], [Vec3::ZERO; LANES], [Vec3::ZERO; LANES], [Vec3::ZERO; LANES]);
            let (mut larea, mut lpmf) = ([1f32; LANES], [0f32; LANES]);
            let mut lle = [Vec3::ZERO; LANES];
            let mut two_sided = 0u32;
            let mut chosen = 0u32;
            let (pl, nl) = (pv.to_lanes(), nsv.to_lanes());
            let mut bits = nee.bits();
            while bits != 0 {
                let k = bits.trailing_zeros() as usize;
                bits &= bits - 1;
                let Some((idx, pmf)) = scene.lights.select(pl[k], Some(nl[k]), u_sel[k]) else { continue };
                if idx >= tables.light_p0.len() {
                    continue;
                }
                chosen |= 1 << k;
                (lp0[k], le1[k], le2[k], lng[k]) =
                    (tables.light_p0[idx], tables.light_e1[idx], tables.light_e2[idx], tables.light_ng[idx]);
                (larea[k], lpmf[k], lle[k]) = (tables.light_area[idx], pmf, tables.light_le[idx]);
                if tables.light_two_sided[idx] {
                    two_sided |= 1 << k;
                }
            }
            let ok = nee & M8::from_bits(chosen);
            // `LightSet::sample_selected`'s area light.
            let (ux, uy) = (
                F8::from_array(u_light[(dims::LIGHT_POS % 4) as usize]),
                F8::from_array(u_light[(dims::LIGHT_POS % 4 + 1) as usize]),
            );
            let (b1, b2) = sample_uniform_triangle(ux, uy);
            let lng = V8::from_lanes(&lng);
            let lp = V8::from_lanes(&lp0).add(V8::from_lanes(&le1).scale(b1)).add(V8::from_lanes(&le2).scale(b2));
            let to = lp.sub(pv);
            let dist2 = to.dot(to);
            let ok = ok & dist2.gt(zero) & dist2.is_finite();
            let dist = dist2.sqrt();
            let lwi = to.div(dist);
            let cos_l = lng.dot(lwi.neg());
            let ok = ok & !cos_l.eq(zero);
            // `light::emitted`: one-sided emitters are dark from behind.
            let lit = M8::from_bits(two_sided) | cos_l.gt(zero);
            let lle = V8::select(lit, V8::from_lanes(&lle), V8::zero());
            let lpdf = F8::from_array(lpmf) * dist2 / (cos_l.abs() * F8::from_array(larea));
            let ok = ok & lpdf.gt(zero) & lpdf.is_finite();
            let ln = V8::select(cos_l.gt(zero), lng, lng.neg());
            // `Path::finish`: the light above the true surface, f from the Lambert BSDF.
            let wil = frame.to_local(lwi);
            let above = wil.z.gt(zero) & lwi.dot(ngv).gt(zero);
            let ok = ok & above & lle.ne_zero();
            let f_pdf = wil.z.max_finite(zero) * F8::splat(INV_PI);
            let f = V8::select(wo.z.le(zero) | wil.z.le(zero), V8::zero(), f_lambert);
            let f_pdf = select(wo.z.le(zero) | wil.z.le(zero), zero, f_pdf);
            let ok = ok & f.ne_zero();
            if ok.any() {
                *rays += ok.bits().count_ones() as u64;
                let target = offset_ray_origin(lp, ln, scale);
                let sto = target.sub(origin);
                let sdist = sto.dot(sto).sqrt();
                let ok = ok & sdist.gt(zero);
                let sd = sto.div(sdist);
                let tmax = sdist * F8::splat(1.0 - SHADOW_EPSILON);
                let w = mis_weight(settings.mis_heuristic, lpdf, f_pdf);
                let unshadowed = beta.mul(f).mul(lle);
                let sc = wil.z.abs() * w / lpdf;
                // Shadow rays one lane at a time.
                let (so, sdl, tm) = (origin.to_lanes(), sd.to_lanes(), tmax.to_array());
                let mut visible = 0u32;
                let mut bits = ok.bits();
                while bits != 0 {
                    let k = bits.trailing_zeros() as usize;
                    bits &= bits - 1;
                    if scene.visibility(so[k], sdl[k], tm[k]) != 0.0 {
                        visible |= 1 << k;
                    }
                }
                let shadow = ok & M8::from_bits(visible);
                // `Path::add_direct`: β·f·Le, times visibility (1), times |cos|·w/pdf.
                let add = unshadowed.scale(one).scale(sc);
                l = V8::select(shadow, l.add(add), l);
            }
        }

        // The step to the next vertex (`Path::finish`).
        let wi_world = frame.to_world(wi);
        let dn = wi_world.dot(ngv);
        let go = has_next & !dn.le(zero) & !dn.eq(zero);
        // BsdfSample::weight: f·|cos|/pdf.
        let weight = f_lambert.scale(wi.z.abs()).div(bsdf_pdf);
        let nb = beta.mul(weight);
        let go = go & nb.is_finite() & nb.ne_zero();
        beta = V8::select(go, nb, beta);
        let (pl, nl, pdfl) = (pv.to_lanes(), nsv.to_lanes(), bsdf_pdf.to_array());
        prev_p = pl;
        prev_n = nl;
        prev_pdf = pdfl;
        has_prev = true;
        ro = origin.to_lanes();
        rd = wi_world;
        depth += 1;
        let mut go = go;
        if depth >= settings.rr_depth {
            let m = beta.max_element() * one;
            let low = m.lt(one);
            let q = (one - m).max_finite(zero);
            let u_rr = F8::from_array(u_bsdf[(dims::RUSSIAN_ROULETTE % 4) as usize]);
            let killed = low & u_rr.lt(q);
            go = go.and_not(killed);
            let kept = low.and_not(killed);
            beta = V8::select(kept, beta.div(one - q), beta);
        }
        alive = go.bits() & shading;
    }
    let lanes = l.to_lanes();
    out[..n].copy_from_slice(&lanes[..n]);
}
