//! Eight paths in lock step, their shading done on eight-lane registers ([`crate::lanes`]): the
//! SPMD kernel of issue 15, for the scenes whose every surface is a metallic-roughness material,
//! opaque (Lambert, plastic, metal) or all glass, clear or absorbing inside ([`crate::bsdf8`];
//! Beer–Lambert on the segments and light samples within), lit by emissive triangles, an
//! environment or punctual lights (every scene of the benchmark suite). Opaque surfaces may be
//! textured (base colour, metallic-roughness, specular), vertex-coloured, normal-mapped, placed
//! as instances and emit through a texture: what those vary is resolved one lane at a time at
//! each hit, with the scalar path's own functions (`HitDetail`, `InstancedLanes`), and the
//! eight-wide shading takes the numbers per lane. A vertex on a surface the eight-wide BSDF does
//! not know (coated, sheened, partly transmissive, unlit) is shaded by the scalar
//! path's own code (`integrator::bounce_from_hit`) and its path goes on in its lane; a scene
//! with alpha-blended or masked surfaces traces its rays through them as the scalar path does
//! (`Scene::intersect_surface` with the bounce's stochastic-transparency seed,
//! `integrator::transparency_seed`; shadow rays' partial visibility multiplied in).
//!
//! Each lane runs exactly [`crate::integrator::radiance`]'s arithmetic for its path, in its
//! order, so a lane's radiance is bit-equal to the scalar path's (`renderer/tests/spmd.rs`
//! compares whole images). What stays one lane at a time: drawing the sample sets, tracing the
//! rays, the surface point, the light choice (table lookups), the environment's and punctual
//! lights' samples and the environment seen by escaping rays; what goes eight-wide: the frame,
//! the BSDF's sample and value, the point on an area light, the pdfs and MIS weights, the ray
//! offsets, the throughput and Russian roulette. Where every shading lane is plain Lambert the
//! BSDF takes `Bsdf::is_lambert`'s shortcut, as the scalar path does.
//!
//! The table of what the kernel can render is built on every target; the kernel itself needs AVX2
//! (`Scene::lanes` answers None without it).

// The lanes whose bits are set in a mask, in lane order.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
use crate::accel::bits_of as lanes_of;
use crate::bsdf::Bsdf;
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
use crate::bsdf8::{normalize_or_zero, sample_cosine_hemisphere, Glass8, OpaqueBsdf8, Sample8};
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
use crate::environment::MapPoint;
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
use crate::integrator::PathState;
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
use crate::lanes::{select, F8, I8, M8, V8};
use crate::material::Material;
use crate::math::Vec3;
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
use crate::math::{INV_PI, SHADOW_EPSILON};
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
use crate::mesh::PLANE_ERROR_ULPS;
use crate::mesh::{flags, Mesh};
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
use crate::sampler::{dims, PixelSample};
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
use crate::scene::Scene;
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
use crate::settings::{MisHeuristic, RenderSettings};
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
use std::ops::{Add, Div, Mul, Neg, Sub};

/// The paths [`radiance8`] runs side by side: one AVX register's f32 lanes.
pub const LANES: usize = 8;

/// What the kernel reads of a material: its metallic-roughness parameters (`Bsdf` without coat or
/// sheen, and either opaque or all glass), whether it is plain Lambert (`Bsdf::is_lambert`: the
/// shading takes a shortcut when every lane's is) or glass, and whether next-event estimation
/// samples a light at a vertex of it (not on a black, mirror or smooth-glass one:
/// `Bsdf::is_delta_only`). A `textured` material's entry holds none of these: a lane that hits
/// it reads them from the material's `Bsdf` at the hit's texture coordinates
/// ([`LaneMaterial::at_hit`]), as the scalar path resolves it (`Scene::bsdf`).
#[derive(Clone, Copy, Debug)]
#[cfg_attr(not(all(target_arch = "x86_64", target_feature = "avx2")), allow(dead_code))]
pub struct LaneMaterial {
    base: Vec3,
    metallic: f32,
    specular: f32,
    f0: Vec3,
    alpha: f32,
    /// Glass's relative index of refraction (entering through the front face).
    eta: f32,
    /// Glass's absorption inside (KHR_materials_volume's σ; zero for clear glass).
    absorption: Vec3,
    lambert: bool,
    glass: bool,
    nee: bool,
    /// Resolved at each hit ([`LaneMaterial::at_hit`]).
    textured: bool,
    /// Some lane that hits this material needs more than the table: it is `textured`, or some
    /// triangle of it has tangents (a tangent frame, maybe a normal map: [`HitDetail`]).
    per_lane: bool,
    /// The kernel does not shade it (unlit, coated, sheened, partly transmissive, or textured
    /// other than [`LaneMaterial::textured_opaque`] allows): a lane whose ray hits it
    /// has that vertex shaded by the scalar path ([`crate::integrator::bounce_from_hit`]) and
    /// goes on.
    scalar: bool,
}

impl LaneMaterial {
    const UNUSED: LaneMaterial = LaneMaterial {
        base: Vec3::ZERO,
        metallic: 0.0,
        specular: 0.0,
        f0: Vec3::ZERO,
        alpha: 1.0,
        eta: 1.0,
        absorption: Vec3::ZERO,
        lambert: true,
        glass: false,
        nee: false,
        textured: false,
        per_lane: false,
        scalar: false,
    };

    /// The entry of a material the kernel hands its paths' hits on to the scalar path for.
    const SCALAR: LaneMaterial = LaneMaterial { scalar: true, ..LaneMaterial::UNUSED };

    /// The entry of a material whose BSDF is `b` everywhere (`glass`: all glass, absorbing
    /// `absorption` inside; else opaque).
    fn of(b: &Bsdf, glass: bool, absorption: Vec3) -> LaneMaterial {
        LaneMaterial {
            base: b.base_color,
            metallic: b.metallic,
            specular: b.specular,
            f0: b.f0_dielectric,
            alpha: b.ggx.alpha,
            eta: b.eta,
            absorption: if glass { absorption } else { Vec3::ZERO },
            lambert: b.is_lambert(),
            glass,
            nee: !b.is_delta_only(),
            textured: false,
            per_lane: false,
            scalar: false,
        }
    }

    /// Whether a textured material is one the kernel shades lane by lane: opaque, its BSDF's
    /// textures feeding only the base colour, metallic-roughness and specular parameters (no
    /// transmission, coat or sheen texture, no coat or sheen at all: what varies is numbers the
    /// eight-wide BSDF takes per lane, never the BSDF's kind). Normal maps and emissive textures
    /// are read lane by lane wherever the material is, textured or not.
    fn textured_opaque(m: &Material) -> bool {
        m.transmission == 0.0
            && m.transmission_texture.is_none()
            && m.clearcoat <= 0.0
            && m.sheen_color.max_element() <= 0.0
            && m.sheen_color_texture.is_none()
            && m.sheen_roughness_texture.is_none()
            && m.clearcoat_texture.is_none()
            && m.clearcoat_roughness_texture.is_none()
            && m.clearcoat_normal_texture.is_none()
    }

    /// A textured (or vertex-coloured) material's entry at the hit (`tri`, `b1`, `b2`): its
    /// `Bsdf` where the scalar path resolves it (`Scene::bsdf`: the texture coordinates and
    /// colour `Mesh::surface_point` gives; a material's precomputed `Bsdf` is the same bits as
    /// one resolved under white), the same bits.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[inline]
    fn at_hit(
        scene: &Scene,
        material: usize,
        tri: u32,
        b1: f32,
        b2: f32,
        uv: impl FnOnce() -> crate::texture::TexCoords,
    ) -> LaneMaterial {
        let b = scene.bsdf_at(material as u32, uv, scene.mesh.color_at(tri, b1, b2));
        LaneMaterial::of(&b, false, Vec3::ZERO)
    }

    /// The table for a scene (`base_colour_bsdfs`: `Material::bsdf_but_base_colour` of each
    /// material, the BSDF everywhere where no base colour texture feeds it either). A
    /// material the kernel does not shade — unlit, coated or sheened, partly transmissive
    /// (transmission between 0 and 1, or metal over glass), or textured or vertex-coloured other
    /// than as [`LaneMaterial::textured_opaque`] allows — gets a `scalar` entry: a lane's vertex
    /// on it is shaded by the scalar path's code. None when every
    /// material a triangle uses is such (the kernel would hand each path over at its first hit)
    /// or a triangle names a material that does not exist. Materials no triangle uses do not
    /// count (the loader's default one among them).
    pub fn table(
        mesh: &Mesh,
        materials: &[Material],
        base_colour_bsdfs: &[Option<Bsdf>],
        textures: &[crate::texture::Texture],
    ) -> Option<LaneTable> {
        let n = materials.len();
        let (mut used, mut tangents, mut colors) = (vec![false; n], vec![false; n], vec![false; n]);
        for t in &mesh.triangles {
            *used.get_mut(t.material as usize)? = true;
            tangents[t.material as usize] |= t.flags & flags::TANGENTS != 0;
            colors[t.material as usize] |= t.flags & flags::COLORS != 0;
        }
        let mut table = Vec::with_capacity(materials.len());
        for (i, m) in materials.iter().enumerate() {
            if !used[i] {
                table.push(LaneMaterial::UNUSED);
                continue;
            }
            if m.unlit {
                table.push(LaneMaterial::SCALAR);
                continue;
            }
            let uniform = (*base_colour_bsdfs.get(i)?).filter(|_| !colors[i] && m.base_color_texture.is_none());
            let Some(b) = uniform else {
                // Textured or vertex-coloured: resolved lane by lane at each hit, where it is
                // opaque whatever the texels and colours say.
                if !LaneMaterial::textured_opaque(m) {
                    table.push(LaneMaterial::SCALAR);
                    continue;
                }
                table.push(LaneMaterial { textured: true, per_lane: true, ..LaneMaterial::UNUSED });
                continue;
            };
            let layered = b.coat.is_some() || b.sheen.is_some();
            // All glass (absorbing inside or clear): `Bsdf`'s glass weight (1 − metallic)·transmission
            // is exactly 1.
            let glass = b.transmission == 1.0 && b.metallic == 0.0;
            let opaque = b.transmission == 0.0;
            if layered || !(opaque || glass) {
                table.push(LaneMaterial::SCALAR);
                continue;
            }
            table.push(LaneMaterial { per_lane: tangents[i], ..LaneMaterial::of(&b, glass, m.absorption) });
        }
        if table.iter().zip(&used).all(|(e, &u)| !u || e.scalar) {
            return None;
        }
        let absorbs = materials.iter().zip(&used).any(|(m, &u)| u && m.absorption != Vec3::ZERO);
        let hit_detail = !mesh.instances.is_empty()
            || absorbs
            || table.iter().any(|m| m.per_lane || m.scalar)
            || crate::material::any_blends(materials)
            || materials.iter().any(|m| m.emissive_texture.is_some());
        let mut large_textures: Vec<bool> = materials.iter().map(|m| m.reads_large_texture(textures)).collect();
        if !large_textures.contains(&true) {
            large_textures.clear();
        }
        Some(LaneTable { entries: table, hit_detail, large_textures, absorbs })
    }
}

/// A scene's [`LaneMaterial`]s, by material index, and whether some lane may need more than
/// they tell (`hit_detail`: a material resolved at its hits, [`LaneMaterial::per_lane`]; one
/// whose vertices the scalar path shades, [`LaneMaterial::scalar`]; an emissive texture;
/// instances; an absorbing medium): then the renderer runs [`radiance8`]`::<true>`, which
/// resolves those one lane at a time, else `::<false>`, the kernel without that code.
#[derive(Clone, Debug)]
pub struct LaneTable {
    entries: Vec<LaneMaterial>,
    pub hit_detail: bool,
    /// By material: whether it reads a texture too large to stay cached
    /// ([`Material::reads_large_texture`]), whose texels the kernel asks for ahead of its hits'
    /// lookups; empty where no material does.
    large_textures: Vec<bool>,
    /// Whether some material a triangle uses absorbs inside (KHR_materials_volume): only then
    /// can a lane be in a medium, and [`radiance8`] runs Beer–Lambert's steps (in its `DETAIL`
    /// build, which `hit_detail` then asks for).
    absorbs: bool,
}

impl std::ops::Deref for LaneTable {
    type Target = [LaneMaterial];
    fn deref(&self) -> &[LaneMaterial] {
        &self.entries
    }
}

/// Lane `k`'s path as the scalar path keeps it ([`PathState`]): its radiance, throughput and η²
/// from the kernel's registers, its previous vertex, bounce, ray (origin, direction, the
/// triangle it starts on) and the medium it is in.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[cold]
#[inline(never)]
fn lane_state(
    k: usize,
    (l, beta, eta_scale): (V8, V8, F8),
    prev: Option<(Vec3, Vec3, f32)>,
    depth: u32,
    (o, d, from): (Vec3, Vec3, u32),
    medium: Vec3,
) -> PathState {
    let (l, beta, eta_scale) = (l.to_lanes()[k], beta.to_lanes()[k], eta_scale.to_array()[k]);
    PathState { l, beta, prev, depth, eta_scale, o, d, from, medium }
}

/// The vertices [`radiance8`] handed to the scalar path this bounce (`handed`, their states and
/// hits in `over`), each shaded by [`crate::integrator::bounce_from_hit`] after the eight-wide
/// bounce has updated the other lanes: a path that goes on is back in its lane, its state as the
/// scalar path left it, and its lane alive; one that ended has its radiance out and stays in
/// `handed`, so the kernel does not write its lane's radiance over it.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[cold]
#[inline(never)]
#[allow(clippy::too_many_arguments, clippy::type_complexity)]
fn shade_handed_lanes(
    scene: &Scene,
    settings: &RenderSettings,
    samplers: &[PixelSample; LANES],
    (handed, over): (&mut u32, &mut [Option<(PathState, crate::accel::Hit)>; LANES]),
    (l, beta, eta_scale, rd): (&mut V8, &mut V8, &mut F8, &mut V8),
    (ro, tri, depth, medium): (&mut [Vec3; LANES], &mut [u32; LANES], &mut [u32; LANES], &mut [Vec3; LANES]),
    (prev_p, prev_n, prev_pdf, prev_bits): (&mut [Vec3; LANES], &mut [Vec3; LANES], &mut [f32; LANES], &mut u32),
    alive: &mut u32,
    (out, path): (&mut [Vec3], &[usize; LANES]),
    rays: &mut u64,
) {
    let (mut ls, mut bs) = (l.to_lanes(), beta.to_lanes());
    let (mut es, mut ds) = (eta_scale.to_array(), rd.to_lanes());
    for k in lanes_of(*handed) {
        let Some((mut state, hit)) = over[k].take() else { continue };
        if crate::integrator::bounce_from_hit(scene, settings, &samplers[k], &mut state, hit, rays) {
            (ls[k], bs[k], es[k], ds[k]) = (state.l, state.beta, state.eta_scale, state.d);
            (ro[k], tri[k], depth[k], medium[k]) = (state.o, state.from, state.depth, state.medium);
            match state.prev {
                Some(prev) => {
                    (prev_p[k], prev_n[k], prev_pdf[k]) = prev;
                    *prev_bits |= 1 << k;
                }
                None => *prev_bits &= !(1 << k),
            }
            *alive |= 1 << k;
            *handed &= !(1 << k);
        } else if let Some(o) = out.get_mut(path[k]) {
            *o = state.l;
        }
    }
    (*l, *beta) = (V8::from_lanes(&ls), V8::from_lanes(&bs));
    (*eta_scale, *rd) = (F8::from_array(es), V8::from_lanes(&ds));
}

/// β with each lane of `lanes` that is in a medium (its `medium` not zero) multiplied by
/// `factor(lane, medium)`, channel by channel as the scalar path's `Vec3` product; the other
/// lanes as they are. Out of line: lanes are in a medium only inside absorbing glass.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[cold]
#[inline(never)]
fn in_medium_lanes(beta: V8, medium: &[Vec3; LANES], lanes: u32, factor: impl Fn(usize, Vec3) -> Vec3) -> V8 {
    let mut b = beta.to_lanes();
    let mut changed = false;
    for k in lanes_of(lanes) {
        if medium[k] != Vec3::ZERO {
            b[k] *= factor(k, medium[k]);
            changed = true;
        }
    }
    if changed {
        V8::from_lanes(&b)
    } else {
        beta
    }
}

/// Each lane of `shadow`'s transmittance along its shadow ray (`Path::finish`'s
/// `ShadowRay::medium`): the medium of the side the ray leaves by
/// ([`crate::integrator::medium_beyond`]: through the surface where `below`, into the mesh's
/// `absorption(k)` where `entering`) over the light sample's distance `dist(k)`; None for a lane
/// whose ray crosses no medium, and None in all when no lane's does.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[cold]
#[inline(never)]
fn shadow_transmittance(
    medium: &[Vec3; LANES],
    (shadow, below, entering): (u32, u32, u32),
    absorption: impl Fn(usize) -> Vec3,
    dist: impl Fn(usize) -> f32,
) -> Option<[Option<Vec3>; LANES]> {
    let mut t = [None; LANES];
    let mut any = false;
    for k in lanes_of(shadow) {
        let bit = |b: u32| b & (1 << k) != 0;
        let m = crate::integrator::medium_beyond(medium[k], bit(below), bit(entering), absorption(k));
        if m != Vec3::ZERO {
            t[k] = Some(crate::integrator::transmittance(m, dist(k)));
            any = true;
        }
    }
    any.then_some(t)
}

/// Emission found: l + β·Le·w on the lanes that met some (w = 1 after the camera ray).
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[inline(always)]
fn add_emission(l: V8, beta: V8, emit: &[Vec3; LANES], emit_w: [f32; LANES]) -> V8 {
    let emit_v = V8::from_lanes(emit);
    let add = beta.mul(emit_v).scale(F8::from_array(emit_w));
    V8::select(emit_v.ne_zero(), l.add(add), l)
}

/// `math::sample_uniform_triangle`'s b1 and b2, eight lanes.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[inline(always)]
fn sample_uniform_triangle(ux: F8, uy: F8) -> (F8, F8) {
    let two = F8::splat(2.0);
    let first = ux.lt(uy);
    let b0_a = ux / two;
    let b1_a = uy - b0_a;
    let b1_b = uy / two;
    let b0_b = ux - b1_b;
    let (b0, b1) = (select(first, b0_a, b0_b), select(first, b1_a, b1_b));
    let b2 = F8::splat(1.0) - b0 - b1;
    (b1, b2)
}

/// `Mesh::surface_point`'s position, normals and plane error, eight lanes.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[derive(Clone, Copy)]
struct SurfacePoint8 {
    p: V8,
    ng: V8,
    ns: V8,
    plane_error: F8,
}

#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
impl SurfacePoint8 {
    /// The point at barycentrics (`b1`, `b2`) of triangles `v`, with vertex normals `n` on the
    /// lanes in `smooth`.
    #[inline(always)]
    fn new(v: [V8; 3], n: Option<[V8; 3]>, smooth: M8, b1: F8, b2: F8) -> SurfacePoint8 {
        let (zero, one) = (F8::zero(), F8::splat(1.0));
        let z_axis = V8 { x: zero, y: zero, z: one };
        let b0 = one - b1 - b2;
        let (e1, e2) = (v[1].sub(v[0]), v[2].sub(v[0]));
        // From the vertices, relative to the first: on the triangle's plane to about an ulp.
        let p = v[0].add(e1.scale(b1)).add(e2.scale(b2));
        let ng = normalize_or_zero(e1.cross(e2));
        let ng = V8::select(ng.ne_zero(), ng, z_axis);
        let ns = match n {
            Some(n) => {
                let s = normalize_or_zero(n[0].scale(b0).add(n[1].scale(b1)).add(n[2].scale(b2)));
                V8::select(smooth & s.ne_zero() & s.is_finite(), s, ng)
            }
            None => ng,
        };
        // `mesh::plane_error`.
        let extent = V8 { x: e1.x.abs() + e2.x.abs(), y: e1.y.abs() + e2.y.abs(), z: e1.z.abs() + e2.z.abs() };
        let plane_error = F8::splat(PLANE_ERROR_ULPS * (f32::EPSILON / 2.0)) * extent.max_element();
        SurfacePoint8 { p, ng, ns, plane_error }
    }
}

/// `math::Frame`, eight lanes.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[derive(Clone, Copy)]
struct Frame8 {
    s: V8,
    t: V8,
    n: V8,
}

#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
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
    fn to_local(self, v: V8) -> V8 {
        V8 { x: v.dot(self.s), y: v.dot(self.t), z: v.dot(self.n) }
    }
    #[inline(always)]
    fn to_world(self, v: V8) -> V8 {
        self.s.scale(v.x).add(self.t.scale(v.y)).add(self.n.scale(v.z))
    }
    #[inline(always)]
    fn select(m: M8, a: Frame8, b: Frame8) -> Frame8 {
        Frame8 { s: V8::select(m, a.s, b.s), t: V8::select(m, a.t, b.t), n: V8::select(m, a.n, b.n) }
    }
}

/// What a bounce's lanes resolve at their hits beyond the material table, one lane at a time
/// and only for the lanes that need it ([`LaneMaterial::per_lane`]): a textured material's entry
/// at the hit, and a tangent (`Mesh::surface_point`'s) with the normal map's texel there.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
struct HitDetail {
    textured: u32,
    m: [LaneMaterial; LANES],
    tangent_bits: u32,
    tangent: [crate::math::Vec4; LANES],
    normal_ts: [Option<Vec3>; LANES],
}

#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
impl HitDetail {
    fn new() -> Self {
        HitDetail {
            textured: 0,
            m: [LaneMaterial::UNUSED; LANES],
            tangent_bits: 0,
            tangent: [crate::math::Vec4::ZERO; LANES],
            normal_ts: [None; LANES],
        }
    }

    /// Lane `k`'s hit on triangle `tri` at (b1, b2) with material `id`, whose table entry is
    /// `m`, and the hit's world-space `tangent` (`Scene::surface_point`'s): the entry the lane
    /// shades with (`m` resolved where it is textured). `uv`: the hit's texture coordinates
    /// where the kernel has them already (worked out here otherwise, once for all lookups).
    #[inline(never)]
    #[allow(clippy::too_many_arguments)]
    fn resolve(
        &mut self,
        scene: &Scene,
        k: usize,
        id: usize,
        m: LaneMaterial,
        tri: u32,
        b1: f32,
        b2: f32,
        tangent: Option<crate::math::Vec4>,
        mut uv: Option<crate::texture::TexCoords>,
    ) -> LaneMaterial {
        // The texture coordinates once, for whichever lookups below read them (the prefetch
        // pass may have worked them out already: `uv`).
        let mut uv_at = || *uv.get_or_insert_with(|| scene.mesh.tex_coords_at(tri, b1, b2));
        let m = if m.textured {
            self.textured |= 1 << k;
            self.m[k] = LaneMaterial::at_hit(scene, id, tri, b1, b2, &mut uv_at);
            self.m[k]
        } else {
            m
        };
        // A triangle with tangents: its frame is built around the tangent, and a normal map
        // bends its shading normal (`Path::shade`).
        if let Some(t) = tangent {
            (self.tangent[k], self.tangent_bits) = (t, self.tangent_bits | 1 << k);
            let material = &scene.materials[id];
            if material.normal_texture.is_some() {
                self.normal_ts[k] = material.tangent_space_normal(&scene.textures, uv_at());
            }
        }
        m
    }
}

/// The lanes whose hits are on instances, and their world-space tangents.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
struct InstancedLanes {
    bits: u32,
    tangent: [Option<crate::math::Vec4>; LANES],
}

#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
impl InstancedLanes {
    /// Finds the `hit_bits` lanes of `hits` on an instance and writes their surface points
    /// (`Mesh::instance_surface_point`: position, normals and plane error) into `sp`.
    #[inline(never)]
    fn of(scene: &Scene, hits: &[Option<crate::accel::Hit>; LANES], hit_bits: u32, sp: &mut SurfacePoint8) -> Self {
        let mut lanes = InstancedLanes { bits: 0, tangent: [None; LANES] };
        let (mut p, mut ng, mut ns, mut err) =
            (sp.p.to_lanes(), sp.ng.to_lanes(), sp.ns.to_lanes(), sp.plane_error.to_array());
        for k in lanes_of(hit_bits) {
            let Some(hit) = hits[k] else { continue };
            let Some(inst) = scene.mesh.instances.get(hit.instance as usize) else { continue };
            let w = scene.mesh.instance_surface_point(inst, hit.triangle, hit.b1, hit.b2);
            (p[k], ng[k], ns[k], err[k]) = (w.p, w.ng, w.ns, w.plane_error);
            (lanes.bits, lanes.tangent[k]) = (lanes.bits | 1 << k, w.tangent);
        }
        if lanes.bits != 0 {
            (sp.p, sp.ng, sp.ns) = (V8::from_lanes(&p), V8::from_lanes(&ng), V8::from_lanes(&ns));
            sp.plane_error = F8::from_array(err);
        }
        lanes
    }
}

/// `math::offset_ray_origin_scaled`, eight lanes.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[inline(always)]
fn offset_ray_origin(p: V8, n: V8, scale: f32) -> V8 {
    let near = F8::splat((1.0 / 32.0) * scale);
    let float_scale = F8::splat((1.0 / 65536.0) * scale);
    let int_scale = F8::splat(16.0);
    let zero = F8::zero();
    let axis = |p: F8, n: F8| {
        let o = (int_scale * n).to_i32_in_range();
        let o = I8::select(p.lt(zero), o.neg(), o);
        let pi = p.add_to_bits(o);
        select(p.abs().lt(near), p + float_scale * n, pi)
    };
    V8 { x: axis(p.x, n.x), y: axis(p.y, n.y), z: axis(p.z, n.z) }
}

/// `integrator::mis_weight`, eight lanes.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
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

/// How many of a stream's paths have their camera rays traced together (one pass's samples of a
/// pixel at the default `pass_spp`: one walk of the bundle's nodes for sixteen rays, where it
/// was one for eight before the thirty-fourth round).
const CAMERA_GROUP: usize = crate::accel::BUNDLE_RAYS;

/// The camera rays `d` from `o` (a group of at most [`CAMERA_GROUP`] of a stream's paths): their
/// hits into `hits`, found together (a bundle where the BVH has one: `Scene::intersect_bundle`); the
/// radiance of those that escape into `out`, the environment they see or black. That radiance is
/// the kernel's `add_emission` on a fresh lane (0 + 1·Le·1, where Le is not zero), so it is the
/// scalar path's bit for bit.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[inline(always)]
fn camera_group(
    scene: &Scene,
    o: Vec3,
    (d, samplers): (&[Vec3], &[PixelSample]),
    blends: bool,
    hits: &mut [Option<crate::accel::Hit>; CAMERA_GROUP],
    out: &mut [Vec3],
) {
    let n = d.len().min(samplers.len()).min(out.len()).min(CAMERA_GROUP);
    let hits = &mut hits[..n];
    // (`Scene::intersect_bundle` declines where cut-outs or blended surfaces may pass the rays.)
    if !scene.intersect_bundle(o, &d[..n], hits) {
        let none = crate::convex_solid::NONE;
        // BLEND surfaces pass a ray by its sample's numbers (`Path::begin_bounce`'s seed).
        let mut seeds = [0u32; CAMERA_GROUP];
        if blends {
            for (seed, sampler) in seeds.iter_mut().zip(samplers) {
                *seed = crate::integrator::transparency_seed(sampler, 0);
            }
        }
        scene.intersect_surface_batch(&[o; CAMERA_GROUP][..n], &d[..n], &seeds[..n], &[none; CAMERA_GROUP][..n], hits);
    }
    let escaped = || hits.iter().enumerate().filter(|(_, h)| h.is_none()).map(|(j, _)| j);
    match &scene.lights.environment {
        Some(env) => {
            // Every escaped ray's map lines asked for first, so the misses overlap
            // (`Environment::prefetch`).
            let mut points = [MapPoint::default(); CAMERA_GROUP];
            for j in escaped() {
                points[j] = env.map_point(d[j]);
                env.prefetch(&points[j]);
            }
            for j in escaped() {
                let le = env.eval_at(points[j]);
                out[j] = if le != Vec3::ZERO { Vec3::ZERO + le } else { Vec3::ZERO };
            }
        }
        None => {
            for j in escaped() {
                out[j] = Vec3::ZERO;
            }
        }
    }
}

/// The most paths one call of [`radiance8`] takes (its caller's buffers are on the stack).
pub const STREAM: usize = 256;

/// [`crate::integrator::radiance`] for a stream of up to [`STREAM`] paths: path j is the camera
/// ray `d[j]` from `o` with sampler `samplers[j]`, its radiance into `out[j]`. Adds the rays
/// traced to `rays`.
///
/// The eight lanes take the stream's paths in order and a lane whose path ends takes the next
/// one at the following bounce (path regeneration), so the lanes stay full until the stream runs
/// dry: a pixel's eight paths in lock step until the longest ended left half the lanes empty on
/// long paths (the twenty-second round counted 4.13 live lanes a bounce on cornell). Each lane
/// keeps its own bounce (its sample dimensions, roulette and depth limit); a path's numbers do
/// not depend on its lane or its neighbours, so each path's radiance is still the scalar path's,
/// bit for bit. The camera rays are traced sixteen at a time as the lanes reach them (a bundle
/// where they share an origin: `Scene::intersect_bundle`; the caller lays a pixel's samples out
/// together), and a path whose camera ray escapes ends there without taking a lane.
///
/// Two builds of it: `DETAIL` also resolves what some hits need one lane at a time (textures,
/// vertex colours, tangent frames and normal maps, instances, textured emitters) and hands the
/// vertices on surfaces it does not shade to the scalar path (`shade_handed_lanes`); the caller
/// takes it where the scene's [`LaneTable::hit_detail`] says so. Without it, it is the kernel as
/// it was before that code existed, which every scene of the benchmark suite runs
/// (docs/performance-journal.md, thirty-first round: +0.7 % instructions on cornell remain).
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[allow(clippy::too_many_arguments)]
pub fn radiance8<const DETAIL: bool>(
    scene: &Scene,
    table: &LaneTable,
    settings: &RenderSettings,
    o: Vec3,
    d: &[Vec3],
    samplers: &[PixelSample],
    rays: &mut u64,
    out: &mut [Vec3],
) {
    let materials: &[LaneMaterial] = table;
    let total = d.len().min(samplers.len()).min(out.len()).min(STREAM);
    let Some(&first_sampler) = samplers.first().filter(|_| total > 0) else { return };
    let zero = F8::zero();
    let one = F8::splat(1.0);
    let none = crate::convex_solid::NONE;
    let mut l = V8::zero();
    let mut beta = V8::splat(Vec3::ONE);
    let mut prev_p = [Vec3::ZERO; LANES];
    let mut prev_n = [Vec3::ZERO; LANES];
    let mut prev_pdf = [0f32; LANES];
    // The lanes whose last bounce left a previous vertex for MIS: not the camera ray's, not a
    // mirror's (`Path::prev`).
    let mut prev_bits = 0u32;
    // `Path::eta_scale`: η² of the transmissions so far.
    let mut eta_scale = one;
    // `Path::medium`: the absorption of the medium each lane's path is in (zero outside).
    let mut medium = [Vec3::ZERO; LANES];
    // (In the `DETAIL` build only, which such scenes run: the others' kernel stays without it.)
    let absorbs = DETAIL && table.absorbs;
    let mut ro = [o; LANES];
    let mut rd = V8::zero();
    // Each lane's path (its index in the stream), sampler and bounce.
    let mut path = [0usize; LANES];
    let mut lane_samplers = [first_sampler; LANES];
    let mut depth = [0u32; LANES];
    // The camera rays' hits of the stream's paths `group`, traced sixteen at a time as the lanes
    // reach them, and the bits of those of the group that hit something and have no lane yet
    // (found by their bits, so the escaped ones cost no step each); each fresh lane's hit.
    let (mut group, mut group_hits, mut group_waiting) = (0..0, [None; CAMERA_GROUP], 0u32);
    let mut fresh_hit = [None; LANES];
    let mut alive = 0u32;
    // Each lane's hit triangle, where its next ray starts (`Path::from`; none for the camera's).
    let mut tri = [none; LANES];
    let scale = scene.offset_scale();
    // Whether BLEND surfaces pass rays by the samples' numbers and shadow rays in part.
    let blends = DETAIL && scene.blends();
    // Whether the lanes' rays are answered where they lie (`Scene::walks_lanes`).
    let walks_lanes = scene.walks_lanes();
    // The lanes that ran the last bounce: those of them not alive now ended there.
    let mut started = 0u32;
    // The lanes whose vertex the scalar path shades this bounce (`integrator::bounce_from_hit`),
    // each with its state and hit; after the bounce, those of them whose path ended there (their
    // radiance is out).
    let mut handed = 0u32;
    let mut handed_over: [Option<(PathState, crate::accel::Hit)>; LANES] = [None; LANES];
    // The handed lanes' vertices shaded one at a time once the eight-wide bounce has updated the
    // other lanes (`shade_handed_lanes`; out of line, so the registers above stay where the
    // kernel keeps them when no lane is handed).
    macro_rules! shade_handed_lanes {
        () => {
            if DETAIL && handed != 0 {
                shade_handed_lanes(
                    scene,
                    settings,
                    &lane_samplers,
                    (&mut handed, &mut handed_over),
                    (&mut l, &mut beta, &mut eta_scale, &mut rd),
                    (&mut ro, &mut tri, &mut depth, &mut medium),
                    (&mut prev_p, &mut prev_n, &mut prev_pdf, &mut prev_bits),
                    &mut alive,
                    (out, &path),
                    rays,
                );
            }
        };
    }
    loop {
        // The paths that ended at the last bounce: their radiance out.
        let ended = started & !alive & !handed;
        if ended != 0 {
            let lanes = l.to_lanes();
            for k in lanes_of(ended) {
                out[path[k]] = lanes[k];
            }
        }
        handed = 0;
        // The empty lanes take the stream's next paths: a camera ray each, from a fresh state.
        let mut dirs = rd.to_lanes();
        let mut fresh = 0u32;
        'refill: for k in lanes_of(!alive & ((1 << LANES) - 1)) {
            // The next path whose camera ray hits something; those that escape end at once.
            let (j, hit) = loop {
                if group_waiting == 0 {
                    if group.end == total {
                        break 'refill;
                    }
                    group = group.end..(group.end + CAMERA_GROUP).min(total);
                    let camera_rays = (&d[group.clone()], &samplers[group.clone()]);
                    camera_group(scene, o, camera_rays, blends, &mut group_hits, &mut out[group.clone()]);
                    *rays += group.len() as u64;
                    for (i, hit) in group_hits.iter().enumerate().take(group.len()) {
                        group_waiting |= u32::from(hit.is_some()) << i;
                    }
                    continue;
                }
                let i = group_waiting.trailing_zeros() as usize;
                group_waiting &= group_waiting - 1;
                if let Some(hit) = group_hits[i] {
                    break (group.start + i, hit);
                }
            };
            (path[k], lane_samplers[k], dirs[k], depth[k]) = (j, samplers[j], d[j], 0);
            (ro[k], tri[k], fresh_hit[k], medium[k]) = (o, none, Some(hit), Vec3::ZERO);
            fresh |= 1 << k;
        }
        if fresh != 0 {
            let f = M8::from_bits(fresh);
            (l, beta) = (V8::select(f, V8::zero(), l), V8::select(f, V8::splat(Vec3::ONE), beta));
            eta_scale = select(f, one, eta_scale);
            rd = V8::from_lanes(&dirs);
            prev_bits &= !fresh;
            alive |= fresh;
        }
        if alive == 0 {
            break;
        }
        started = alive;
        // One lane at a time: the rays (together where the BVH batches them:
        // `Scene::intersect_surface_batch`), the sample sets, the surface points and the
        // emission met.
        let mut u_bsdf = [[0f32; LANES]; 4];
        let mut u_light = [[0f32; LANES]; 4];
        let mut albedo = [Vec3::ZERO; LANES];
        let mut mat_id = [0usize; LANES];
        // What some lanes resolve at their hits (textures, tangents), made for the first.
        let mut detail: Option<HitDetail> = None;
        let mut nee_bits = 0u32;
        // The shading lanes whose material is opaque but not plain Lambert, and those of glass.
        let (mut general, mut glass_bits) = (0u32, 0u32);
        let mut emit = [Vec3::ZERO; LANES];
        let mut emit_w = [1f32; LANES];
        let mut shading = 0u32;
        // The live lanes past their camera ray, in lane order, and their rays; a fresh lane's
        // camera ray was answered when it took its path (`camera_group`).
        let mut hits = [None; LANES];
        let mut bounce = 0u32;
        for k in lanes_of(alive) {
            if depth[k] == 0 {
                hits[k] = fresh_hit[k];
            } else {
                bounce |= 1 << k;
            }
        }
        *rays += u64::from(bounce.count_ones());
        if walks_lanes {
            // No transparent surface and a small BVH: the rays are answered where they lie
            // (`Scene::intersect_lanes_where`, as `Scene::intersect_surface_batch` would).
            scene.intersect_lanes_where(&ro, &dirs, &tri, bounce, &mut hits);
        } else if bounce != 0 {
            // Packed into a batch (transparent layers, and solids on a large BVH, answer some
            // rays themselves; a large BVH walks them together), each with its BLEND seed
            // (`Path::begin_bounce`'s).
            let (mut lane, mut count) = ([0u8; LANES], 0);
            let (mut qo, mut qd, mut qf, mut seeds) =
                ([Vec3::ZERO; LANES], [Vec3::ZERO; LANES], [0u32; LANES], [0u32; LANES]);
            for k in lanes_of(bounce) {
                (lane[count], qo[count], qd[count], qf[count]) = (k as u8, ro[k], dirs[k], tri[k]);
                if blends {
                    seeds[count] = crate::integrator::transparency_seed(&lane_samplers[k], depth[k]);
                }
                count += 1;
            }
            let mut found = [None; LANES];
            scene.intersect_surface_batch(
                &qo[..count],
                &qd[..count],
                &seeds[..count],
                &qf[..count],
                &mut found[..count],
            );
            for j in 0..count {
                hits[lane[j] as usize] = found[j];
            }
        }
        // The lanes that hit something (one that finds nothing, or stops here, is not shading:
        // its path ends), and their triangles' records asked of the cache: they are read after
        // the sample sets are drawn, so a miss has that long (a hit triangle is any of
        // thousands: `perf annotate` of `scenes/sphere_lights` had 2.4 % of this kernel's samples
        // waiting on the record's load).
        let (mut hit_bits, mut escaped) = (0u32, 0u32);
        for k in lanes_of(alive) {
            match hits[k] {
                Some(hit) => {
                    hit_bits |= 1 << k;
                    if let Some(t) = scene.mesh.triangles.get(hit.triangle as usize) {
                        crate::accel::prefetch_record(t);
                    }
                }
                None => escaped |= 1 << k,
            }
        }
        // The hit lanes' two sample sets (`Path::begin_bounce`), each at its own bounce: all
        // eight lanes at once where four or more want them and every sampler is Sobol
        // (`sampler::get_4d_pair_each_lanes`), else lane by lane. A value is a function of its
        // sample and dimension alone, so drawing a lane that will not read it changes nothing.
        let (mut sets_a, mut sets_b) = ([0u32; LANES], [0u32; LANES]);
        for k in 0..LANES {
            let base = dims::BOUNCE_BASE + dims::BOUNCE_STRIDE * depth[k];
            (sets_a[k], sets_b[k]) = ((base + dims::BSDF_DIR) / 4, (base + dims::LIGHT_POS) / 4);
        }
        let drawn = hit_bits.count_ones() >= 4
            && crate::sampler::get_4d_pair_each_lanes(&lane_samplers, &sets_a, &sets_b, &mut u_bsdf, &mut u_light);
        if !drawn {
            for k in lanes_of(hit_bits) {
                let (a, b) = lane_samplers[k].get_4d_pair(sets_a[k], sets_b[k]);
                for i in 0..4 {
                    u_bsdf[i][k] = a[i];
                    u_light[i][k] = b[i];
                }
            }
        }
        // The hit triangles' vertices, gathered lane by lane; the surface points eight-wide.
        // One register a vertex (`lanes::xyz_register`), so the transposes read what was stored whole.
        let none3 = [crate::lanes::xyz_register(&Vec3::ZERO); LANES];
        let (mut v0, mut v1, mut v2) = (none3, none3, none3);
        let (mut n0, mut n1, mut n2) = (none3, none3, none3);
        let (mut hb1, mut hb2) = ([0f32; LANES], [0f32; LANES]);
        let mut smooth = 0u32;
        for k in lanes_of(hit_bits) {
            let Some(hit) = hits[k] else { continue };
            let mesh = &scene.mesh;
            let t = &mesh.triangles[hit.triangle as usize];
            let [i0, i1, i2] = [t.v[0] as usize, t.v[1] as usize, t.v[2] as usize];
            let xyz = crate::lanes::xyz_register;
            (v0[k], v1[k], v2[k]) = (xyz(&mesh.positions[i0]), xyz(&mesh.positions[i1]), xyz(&mesh.positions[i2]));
            if t.flags & flags::NORMALS != 0 {
                smooth |= 1 << k;
                (n0[k], n1[k], n2[k]) = (xyz(&mesh.normals[i0]), xyz(&mesh.normals[i1]), xyz(&mesh.normals[i2]));
            }
            (hb1[k], hb2[k], tri[k]) = (hit.b1, hit.b2, hit.triangle);
        }
        // The environment, seen by BSDF sampling (`Path::shade`'s escape): the escaped lanes'
        // lookups in a loop of their own, so their cache misses (the map and its rows are
        // megabytes) overlap rather than wait a whole lane's shading apart.
        if let (true, Some(env)) = (escaped != 0, &scene.lights.environment) {
            // Every escaped lane's map lines asked for first (`Environment::prefetch`).
            let mut points = [MapPoint::default(); LANES];
            for k in lanes_of(escaped) {
                points[k] = env.map_point(dirs[k]);
                env.prefetch(&points[k]);
            }
            for k in lanes_of(escaped) {
                if prev_bits & (1 << k) == 0 {
                    emit[k] = env.eval_at(points[k]);
                } else if let Some((le, light_pdf)) =
                    scene.lights.environment_eval_pdf_at(points[k], prev_p[k], Some(prev_n[k]))
                {
                    emit[k] = le;
                    emit_w[k] = crate::integrator::mis_weight(settings.mis_heuristic, prev_pdf[k], light_pdf);
                }
            }
        }
        // `Path::shade`'s escape from an absorbing medium that never ends (an open mesh): nothing
        // gets out.
        if absorbs && escaped != 0 {
            beta = in_medium_lanes(beta, &medium, escaped, |_, m| crate::integrator::transmittance(m, f32::INFINITY));
        }
        // Nothing hit (a background): no surface point to build, the path ends here.
        if hit_bits == 0 {
            l = add_emission(l, beta, &emit, emit_w);
            alive = 0;
            continue;
        }
        let mut sp = SurfacePoint8::new(
            [v0, v1, v2].map(|v| V8::from_registers(&v)),
            (smooth != 0).then(|| [n0, n1, n2].map(|n| V8::from_registers(&n))),
            M8::from_bits(smooth),
            F8::from_array(hb1),
            F8::from_array(hb2),
        );
        // Hits on instances: the prototype's point carried to the world one lane at a time
        // (`Scene::surface_point`), over the object-space point computed above.
        let instanced =
            (DETAIL && !scene.mesh.instances.is_empty()).then(|| InstancedLanes::of(scene, &hits, hit_bits, &mut sp));
        let (sp_p, sp_ng) = (sp.p.to_lanes(), sp.ng.to_lanes());
        // Lanes' texture coordinates, worked out by the first lookup that needs them (the
        // prefetch pass, an emissive texture) and read by the others (`HitDetail::resolve`).
        let mut uvs = [None::<crate::texture::TexCoords>; LANES];
        if DETAIL && !table.large_textures.is_empty() {
            // Every lane's texels on a large texture asked for before the loop below reads the
            // first lane's, so the lanes' cache misses overlap (`Texture::prefetch`; the lanes
            // the scalar path shades read theirs after the bounce).
            for k in lanes_of(hit_bits) {
                let material_id = scene.mesh.triangles[tri[k] as usize].material as usize;
                if table.large_textures[material_id] {
                    let uv = scene.mesh.tex_coords_at(tri[k], hb1[k], hb2[k]);
                    scene.materials[material_id].prefetch_texels(&scene.textures, uv);
                    uvs[k] = Some(uv);
                }
            }
        }
        for k in lanes_of(hit_bits) {
            let material_id = scene.mesh.triangles[tri[k] as usize].material as usize;
            if DETAIL && materials[material_id].scalar {
                // A surface the kernel does not shade: the scalar path shades this vertex once
                // the bounce is done (`shade_handed_lanes`).
                if let Some(hit) = hits[k] {
                    let prev = (prev_bits & (1 << k) != 0).then(|| (prev_p[k], prev_n[k], prev_pdf[k]));
                    // (The ray is traced; its next one starts where the vertex says.)
                    let ray = (ro[k], dirs[k], tri[k]);
                    handed_over[k] = Some((lane_state(k, (l, beta, eta_scale), prev, depth[k], ray, medium[k]), hit));
                    handed |= 1 << k;
                }
                continue;
            }
            let material = &scene.materials[material_id];
            if material.is_emissive() {
                // Texture coordinates only for an emissive texture (`Path::shade` reads `sp.uv`).
                let uv = match material.emissive_texture {
                    Some(_) if DETAIL => {
                        *uvs[k].get_or_insert_with(|| scene.mesh.tex_coords_at(tri[k], hb1[k], hb2[k]))
                    }
                    _ => Default::default(),
                };
                let le = crate::light::emitted(material, &scene.textures, sp_ng[k], uv, -dirs[k]);
                if le != Vec3::ZERO {
                    emit[k] = le;
                    if prev_bits & (1 << k) != 0 {
                        let light_pdf = scene.lights.pdf(tri[k], prev_p[k], Some(prev_n[k]), sp_p[k], sp_ng[k]);
                        emit_w[k] = crate::integrator::mis_weight(settings.mis_heuristic, prev_pdf[k], light_pdf);
                    }
                }
            }
            if depth[k] >= settings.max_depth {
                continue;
            }
            shading |= 1 << k;
            let resolved;
            let mut m = &materials[material_id];
            if DETAIL && m.per_lane {
                let d = detail.get_or_insert_with(HitDetail::new);
                let tangent = match &instanced {
                    Some(i) if i.bits & (1 << k) != 0 => i.tangent[k],
                    _ => scene.mesh.tangent_at(tri[k], hb1[k], hb2[k]),
                };
                resolved = d.resolve(scene, k, material_id, *m, tri[k], hb1[k], hb2[k], tangent, uvs[k]);
                m = &resolved;
            }
            (albedo[k], mat_id[k]) = (m.base, material_id);
            if m.nee {
                nee_bits |= 1 << k;
            }
            if m.glass {
                glass_bits |= 1 << k;
            } else if !m.lambert {
                general |= 1 << k;
            }
        }
        let p = sp_p;
        if absorbs {
            // `Path::shade`: Beer–Lambert over the segment just traced (from its origin to the
            // surface point), before the vertex's emission counts; the handed lanes' the scalar
            // path applies.
            beta = in_medium_lanes(beta, &medium, hit_bits & !handed, |k, m| {
                crate::integrator::transmittance(m, (p[k] - ro[k]).length())
            });
        }
        l = add_emission(l, beta, &emit, emit_w);
        if shading == 0 {
            alive = 0;
            shade_handed_lanes!();
            continue;
        }

        // Eight lanes: the frame, the BSDF's sample, the light's point, MIS, the next ray.
        let act = M8::from_bits(shading);
        let wo_world = rd.neg();
        let (pv, mut ngv, mut nsv) = (sp.p, sp.ng, sp.ns);
        // Normal maps first, in the mesh's orientation (`Path::shade`), one lane at a time.
        let tangents = detail.as_ref().filter(|d| DETAIL && d.tangent_bits != 0);
        if let Some(d) = tangents.filter(|d| d.normal_ts.iter().any(Option::is_some)) {
            let mut ns = nsv.to_lanes();
            for k in lanes_of(d.tangent_bits) {
                if let Some(n_ts) = d.normal_ts[k] {
                    ns[k] = crate::integrator::normal_mapped(ns[k], d.tangent[k], n_ts);
                }
            }
            nsv = V8::from_lanes(&ns);
        }
        // Seen from the back face: also where glass's relative index inverts.
        let ng_wo = ngv.dot(wo_world);
        let back_face = ng_wo.lt(zero);
        // Arrived on the front (winding) face: a transmission enters the mesh's medium.
        let entering = ng_wo.gt(zero).bits();
        ngv = V8::select(back_face, ngv.neg(), ngv);
        let flip = nsv.dot(ngv).lt(zero);
        nsv = V8::select(flip, nsv.neg(), nsv);
        let ns_flipped = nsv.to_lanes();
        let mut frame_s = Frame8::from_normal(nsv);
        if let Some(d) = tangents {
            // `Frame::from_normal_tangent` on the lanes with tangents.
            let (mut fs, mut ft, mut fnl) = (frame_s.s.to_lanes(), frame_s.t.to_lanes(), frame_s.n.to_lanes());
            for k in lanes_of(d.tangent_bits) {
                let f = crate::math::Frame::from_normal_tangent(ns_flipped[k], d.tangent[k].truncate());
                (fs[k], ft[k], fnl[k]) = (f.s, f.t, f.n);
            }
            frame_s = Frame8 { s: V8::from_lanes(&fs), t: V8::from_lanes(&ft), n: V8::from_lanes(&fnl) };
        }
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
        let plane_error = sp.plane_error;
        let origin = offset_ray_origin(pv.add(ngv.scale(plane_error)), ngv, scale);
        // Glass: the other side's origin (`Scene::spawn_origin` with −ng), for transmission.
        let glass = M8::from_bits(glass_bits);
        let origin_below = (glass_bits != 0).then(|| {
            let down = ngv.neg();
            offset_ray_origin(pv.add(down.scale(plane_error)), down, scale)
        });
        let albedo = V8::from_lanes(&albedo);
        let f_lambert = V8::zero().add(albedo.scale(F8::splat(INV_PI)));
        // Lane k's material: its hit's own where a texture resolved it, else the table's. Read a
        // field at a time where some lane needs more than its albedo (gathering whole materials
        // copied eight 60-byte records a bounce, 1.3 % of glass's instructions).
        let lane_material = |k: usize| match detail.as_ref().filter(|_| DETAIL) {
            Some(d) if d.textured & (1 << k) != 0 => &d.m[k],
            _ => &materials[mat_id[k]],
        };
        let field = |f: fn(&LaneMaterial) -> f32| F8::from_array(std::array::from_fn(|k| f(lane_material(k))));
        // Where some lane is not plain Lambert, every lane takes the general opaque BSDF (whose
        // numbers are the Lambert shortcut's on a Lambert lane: `bsdf.rs`'s test).
        let bsdf = (general != 0).then(|| OpaqueBsdf8 {
            base: albedo,
            metallic: field(|m| m.metallic),
            specular: field(|m| m.specular),
            f0: V8::from_lanes(&std::array::from_fn(|k| lane_material(k).f0)),
            alpha: field(|m| m.alpha),
        });

        // The NEE lanes' light choices together (a light tree's walks interleaved), as
        // `LightSet::sample` makes them: at the vertex, with its shading normal. Made before the
        // BSDF's sample, which does not read them, so the chosen lights' records (asked of the
        // cache as they are chosen: `LightSet::select_batch`) arrive while it is computed.
        let nee = act & M8::from_bits(nee_bits);
        // The light each NEE lane chose, lane by lane.
        let mut selected = [None; LANES];
        if nee.any() {
            let u_sel = u_light[(dims::LIGHT_SELECT % 4) as usize];
            let mut by_table = [(0usize, 0f32); LANES];
            if scene.lights.select_by_table_lanes(&u_sel, &mut by_table) {
                // The power table's choices where the lanes lie (a lane not choosing ignores its own).
                for k in lanes_of(nee.bits()) {
                    selected[k] = Some(by_table[k]);
                }
            } else if scene.lights.select_root_lanes(&p, &ns_flipped, &u_sel, nee.bits(), &mut selected) {
                // A one-node light tree's choices where the lanes lie.
            } else {
                // The NEE lanes packed in order, and their choices unpacked.
                let (mut nee_lane, mut chose) = ([0u8; LANES], 0);
                let (mut qp, mut qn, mut qu) = ([Vec3::ZERO; LANES], [None; LANES], [0f32; LANES]);
                if scene.lights.walks_tree() {
                    for k in lanes_of(nee.bits()) {
                        (nee_lane[chose], qp[chose], qn[chose], qu[chose]) =
                            (k as u8, p[k], Some(ns_flipped[k]), u_sel[k]);
                        chose += 1;
                    }
                } else {
                    // Uniform choices read `u` alone, not the point and normal.
                    for k in lanes_of(nee.bits()) {
                        (nee_lane[chose], qu[chose]) = (k as u8, u_sel[k]);
                        chose += 1;
                    }
                }
                let mut found = [None; LANES];
                scene.lights.select_batch(&qp[..chose], &qn[..chose], &qu[..chose], &mut found[..chose]);
                for j in 0..chose {
                    selected[nee_lane[j] as usize] = found[j];
                }
            }
        }

        // BSDF sample, drawn before NEE as the scalar path does.
        let u_dir = (
            F8::from_array(u_bsdf[(dims::BSDF_DIR % 4) as usize]),
            F8::from_array(u_bsdf[(dims::BSDF_DIR % 4 + 1) as usize]),
        );
        let u_lobe = F8::from_array(u_bsdf[(dims::BSDF_LOBE % 4) as usize]);
        let cosine = sample_cosine_hemisphere(u_dir.0, u_dir.1);
        let next = match &bsdf {
            // Lambert: the cosine hemisphere.
            None => {
                let pdf = cosine.z.max_finite(zero) * F8::splat(INV_PI);
                let ok = cosine.z.gt(zero) & pdf.gt(zero) & pdf.is_finite();
                Sample8 { wi: cosine, f: f_lambert, pdf, delta: M8::from_bits(0), ok }
            }
            Some(b) => b.sample(wo, u_lobe, u_dir.0, u_dir.1, cosine),
        };
        let glass8 = (glass_bits != 0).then(|| {
            let eta = field(|m| m.eta);
            Glass8 { eta: select(back_face, one / eta, eta), alpha: field(|m| m.alpha), tint: albedo }
        });
        let next = match &glass8 {
            None => next,
            Some(g) => Sample8::select(glass, g.sample(glass, wo, u_lobe, u_dir.0, u_dir.1), next),
        };
        let has_next = act & next.ok;

        // Next-event estimation: each chosen light read one lane at a time, the rest eight-wide.
        if nee.any() {
            let u_pos = (u_light[(dims::LIGHT_POS % 4) as usize], u_light[(dims::LIGHT_POS % 4 + 1) as usize]);
            // Each lane's area light (`LightSample::light`), for `LightSet::shadow_tmax` and the
            // eight-wide sample below, and the probability it was chosen with; the lanes that
            // chose one.
            let mut lidx = [crate::clear_box::NONE; LANES];
            let mut lpmf = [0f32; LANES];
            let mut area = 0u32;
            // Any other light's sample (`LightSet::sample_selected`, one lane at a time): its
            // direction, radiance, pdf and point; which are delta (punctual) and which at infinity.
            let (mut owi, mut ole, mut op, mut opdf) =
                ([Vec3::ZERO; LANES], [Vec3::ZERO; LANES], [Vec3::ZERO; LANES], [1f32; LANES]);
            // Their distances (`LightSample::dist`), which a shadow ray through a medium reads.
            let mut odist = [0f32; LANES];
            let (mut other, mut delta, mut infinite) = (0u32, 0u32, 0u32);
            // The lanes that chose a bulb (its sure directions eight-wide where it is isolated).
            let mut bulb = 0u32;
            // Of those, the ones on a surface (a bulb's): their shadow rays aim just off it, as an
            // area light's do (`op` then holds that offset point) and may stop at its clear box.
            let mut surface = 0u32;
            // The lanes that chose another kind of light, sampled together after the loop
            // (`LightSet::sample_selected_batch`: an environment's samples overlap their misses).
            let (mut olane, mut ocount) = ([0u8; LANES], 0);
            let (mut oref, mut ochoice, mut ou) =
                ([Vec3::ZERO; LANES], [None; LANES], [crate::math::Vec2::ZERO; LANES]);
            for k in lanes_of(nee.bits()) {
                let choice = selected[k];
                let Some((idx, pmf)) = choice else { continue };
                if scene.lights.area_light(idx).is_none() {
                    // A bulb: its sure directions eight-wide below, the rest with the other lights.
                    if scene.lights.is_bulb(idx) {
                        bulb |= 1 << k;
                        continue;
                    }
                    let u = crate::math::Vec2::new(u_pos.0[k], u_pos.1[k]);
                    (olane[ocount], oref[ocount], ochoice[ocount], ou[ocount]) = (k as u8, p[k], choice, u);
                    ocount += 1;
                    continue;
                }
                area |= 1 << k;
                (lidx[k], lpmf[k]) = (idx as u32, pmf);
            }
            // `Bulb::sample`'s cone and `LightSet::sample_selected`'s sure direction, eight-wide
            // in the same arithmetic: (the lanes that took one, the direction, the shadow ray's
            // target, the radiance and the pdf). A lane whose direction is not sure (inside the
            // ball, near the silhouette, beyond the range) goes to the other lights' samples.
            let bulbs = (bulb != 0).then(|| {
                // Each isolated bulb lane's ball, inner ball, clear box, radiance and choice
                // probability (gathered here, so that a scene without bulbs does not fill these).
                let (mut bc, mut blo, mut bhi, mut ble) =
                    ([Vec3::ZERO; LANES], [Vec3::ZERO; LANES], [Vec3::ZERO; LANES], [Vec3::ZERO; LANES]);
                let (mut br2, mut bi2, mut bpmf) = ([1f32; LANES], [0f32; LANES], [0f32; LANES]);
                let mut isolated = 0u32;
                for k in lanes_of(nee.bits()) {
                    let choice = selected[k];
                    let (true, Some((idx, pmf))) = (bulb & (1 << k) != 0, choice) else { continue };
                    let Some(b) = scene.lights.bulb_lane(idx, &scene.materials) else { continue };
                    isolated |= 1 << k;
                    (bc[k], blo[k], bhi[k], ble[k]) = (b.center, b.lo, b.hi, b.le);
                    (br2[k], bi2[k], bpmf[k]) = (b.radius2, b.inner2, pmf);
                }
                let (one, two) = (one, F8::splat(2.0));
                let to = V8::from_lanes(&bc).sub(pv);
                let d2 = to.dot(to);
                let r2 = F8::from_array(br2);
                let outside = M8::from_bits(isolated) & d2.gt(r2) & d2.is_finite();
                let sin2 = r2 / d2;
                let cos_max = (one - sin2).max(zero).sqrt();
                let omc = sin2 / (one + cos_max);
                let one_minus_cos = F8::from_array(u_pos.0) * omc;
                let cos = one - one_minus_cos;
                let sin = (one_minus_cos * (two - one_minus_cos)).max(zero).sqrt();
                let (s, c) = crate::bsdf8::sin_cos_azimuth(F8::splat(2.0 * crate::math::PI) * F8::from_array(u_pos.1));
                let frame = Frame8::from_normal(to.div(d2.sqrt()));
                let d = frame.to_world(V8 { x: sin * c, y: sin * s, z: cos });
                let cr = to.cross(d);
                let inner2 = F8::from_array(bi2);
                let sure = outside & cr.dot(cr).lt(inner2) & d2.lt(F8::splat(crate::bulb::SURE_RANGE2) * inner2);
                // `ClearBox::entry`: the slab test, glam's min and max.
                let inv = V8 { x: one / d.x, y: one / d.y, z: one / d.z };
                let (a, b) = (V8::from_lanes(&blo).sub(pv).mul(inv), V8::from_lanes(&bhi).sub(pv).mul(inv));
                let near = a.glam_min(b).max_element();
                let far = a.glam_max(b).min_element();
                let sure = sure & near.gt(zero) & near.le(far);
                // `Bulb::cone_pdf` times the choice's (a lane where that is not positive and
                // finite goes to the scalar path, which drops the sample).
                let pdf = F8::from_array(bpmf) * (one / (F8::splat(2.0 * crate::math::PI) * omc));
                let sure = sure & pdf.gt(zero) & pdf.is_finite();
                let target = offset_ray_origin(pv.add(d.scale(near)), d.neg(), scale);
                (sure, d, target, V8::from_lanes(&ble), pdf)
            });
            // A lane whose shadow ray may cross a medium (it is in one, or it is on absorbing glass,
            // whose inside a sample through the surface enters) takes its bulb's sample with the
            // other lights': the medium's transmittance reads the scalar sample's distance.
            let bulbs = match bulbs {
                Some((sure, d, target, le, pdf)) if absorbs => {
                    let may_cross = lanes_of(nee.bits()).fold(0u32, |b, k| {
                        let media = medium[k] != Vec3::ZERO || materials[mat_id[k]].absorption != Vec3::ZERO;
                        b | (u32::from(media) << k)
                    });
                    Some((sure.and_not(M8::from_bits(may_cross)), d, target, le, pdf))
                }
                b => b,
            };
            if let Some((sure, ..)) = bulbs {
                let unsure = bulb & !sure.bits();
                for k in lanes_of(nee.bits()) {
                    let choice = selected[k];
                    if unsure & (1 << k) != 0 {
                        let u = crate::math::Vec2::new(u_pos.0[k], u_pos.1[k]);
                        (olane[ocount], oref[ocount], ochoice[ocount], ou[ocount]) = (k as u8, p[k], choice, u);
                        ocount += 1;
                    }
                }
            }
            if ocount > 0 {
                let mut samples = [None; LANES];
                let (mesh, mats, textures) = (&scene.mesh, &scene.materials, &scene.textures);
                scene.lights.sample_selected_batch(
                    mesh,
                    mats,
                    textures,
                    &oref[..ocount],
                    &ochoice[..ocount],
                    &ou[..ocount],
                    &mut samples[..ocount],
                );
                for (j, ls) in samples[..ocount].iter().enumerate() {
                    let (Some(ls), k) = (ls, olane[j] as usize) else { continue };
                    other |= 1 << k;
                    (owi[k], ole[k], op[k], opdf[k], odist[k]) = (ls.wi, ls.le, ls.p, ls.pdf, ls.dist);
                    delta |= u32::from(ls.delta) << k;
                    infinite |= u32::from(ls.dist.is_infinite()) << k;
                    if !ls.delta && ls.dist.is_finite() {
                        // `Path::finish`'s area-light target, in its scalar arithmetic.
                        surface |= 1 << k;
                        op[k] = scene.offset_ray_origin(ls.p, ls.n);
                        lidx[k] = ls.light;
                    }
                }
            }
            // `LightSet::sample_selected`'s area light: the point, the direction to it, its
            // radiance and pdf, and the side it faces (None when no lane chose an area light).
            let areas = (area != 0).then(|| {
                // Each area lane's triangle, area, radiance and sidedness, its vectors one
                // register each (`lanes::xyz_register`: the transposes read what was stored whole).
                let none3 = [crate::lanes::xyz_register(&Vec3::ZERO); LANES];
                let (mut lp0, mut le1, mut le2, mut lng, mut lle) = (none3, none3, none3, none3, none3);
                let mut larea = [1f32; LANES];
                let (mut two_sided, mut textured_light) = (0u32, 0u32);
                for k in lanes_of(area) {
                    let Some(light) = scene.lights.area_light(lidx[k] as usize) else { continue };
                    let xyz = crate::lanes::xyz_register;
                    (lp0[k], le1[k], le2[k], lng[k]) = (xyz(&light.p0), xyz(&light.e1), xyz(&light.e2), xyz(&light.ng));
                    // Every area light's material is emissive (`LightSet::build`).
                    (larea[k], lle[k]) = (light.area, xyz(&light.le));
                    two_sided |= u32::from(light.two_sided) << k;
                    // A textured emitter's radiance is read at the sampled point, once that is drawn.
                    if DETAIL {
                        textured_light |= u32::from(light.textured) << k;
                    }
                }
                let (b1, b2) = sample_uniform_triangle(F8::from_array(u_pos.0), F8::from_array(u_pos.1));
                if DETAIL && textured_light != 0 {
                    // A textured emitter's radiance at the point (`LightSet::sample_selected`: the
                    // texture coordinates `Mesh::position_normal_uv` gives there).
                    let (b1, b2) = (b1.to_array(), b2.to_array());
                    for k in lanes_of(textured_light) {
                        let Some(light) = scene.lights.area_light(lidx[k] as usize) else { continue };
                        let uv = scene.mesh.tex_coords_at(light.triangle, b1[k], b2[k]);
                        let le = scene.materials[light.material as usize].emission(&scene.textures, uv);
                        lle[k] = crate::lanes::xyz_register(&le);
                    }
                }
                let le = V8::from_registers(&lle);
                let lng = V8::from_registers(&lng);
                let lp = V8::from_registers(&lp0)
                    .add(V8::from_registers(&le1).scale(b1))
                    .add(V8::from_registers(&le2).scale(b2));
                let to = lp.sub(pv);
                let dist2 = to.dot(to);
                let ok = nee & M8::from_bits(area) & dist2.gt(zero) & dist2.is_finite();
                let dist = dist2.sqrt();
                let lwi = to.div(dist);
                let cos_l = lng.dot(lwi.neg());
                let ok = ok & !cos_l.eq(zero);
                // `light::emitted`: one-sided emitters are dark from behind.
                let lit = M8::from_bits(two_sided) | cos_l.gt(zero);
                let lle = V8::select(lit, le, V8::zero());
                let lpdf = F8::from_array(lpmf) * dist2 / (cos_l.abs() * F8::from_array(larea));
                let ok = ok & lpdf.gt(zero) & lpdf.is_finite();
                let ln = V8::select(cos_l.gt(zero), lng, lng.neg());
                (lp, ln, lwi, lle, lpdf, ok, dist)
            });
            let (lwi, lle, lpdf, ok) = match areas {
                Some((_, _, lwi, lle, lpdf, ok, _)) => (lwi, lle, lpdf, ok),
                None => (V8::zero(), V8::zero(), one, M8::from_bits(0)),
            };
            // The other lights' samples in with the area lights'.
            let others = other != 0;
            let (other, delta, infinite) = (M8::from_bits(other), M8::from_bits(delta), M8::from_bits(infinite));
            let point = delta.and_not(infinite);
            let surface = M8::from_bits(surface);
            let (lwi, lle, lpdf, ok) = if others {
                (
                    V8::select(other, V8::from_lanes(&owi), lwi),
                    V8::select(other, V8::from_lanes(&ole), lle),
                    select(other, F8::from_array(opdf), lpdf),
                    ok | other,
                )
            } else {
                (lwi, lle, lpdf, ok)
            };
            // The bulbs' sure directions in with them.
            let (lwi, lle, lpdf, ok) = match bulbs {
                Some((sure, d, _, le, pdf)) => {
                    (V8::select(sure, d, lwi), V8::select(sure, le, lle), select(sure, pdf, lpdf), ok | sure)
                }
                None => (lwi, lle, lpdf, ok),
            };
            // `Path::finish`: the light above the true surface (reflection) or, through glass,
            // below it; f from the BSDF.
            let wil = frame.to_local(lwi);
            let above = wil.z.gt(zero) & lwi.dot(ngv).gt(zero);
            let below = glass & wil.z.lt(zero) & lwi.dot(ngv).lt(zero);
            let ok = ok & (above | below) & lle.ne_zero();
            // `Bsdf::eval_pdf`. Its Lambert shortcut: wo.z > 0 on every shading lane and
            // wil.z > 0 on every `above` one, so f is base/π and the pdf cos/π there.
            let (f, f_pdf) = match &bsdf {
                None => (f_lambert, wil.z.max_finite(zero) * F8::splat(INV_PI)),
                Some(b) => b.eval_pdf(wo, wil),
            };
            let (f, f_pdf) = match &glass8 {
                None => (f, f_pdf),
                // Smooth glass has no f towards a light (`Dielectric::eval_pdf`: zero), so only a
                // rough glass lane that samples one needs the evaluation.
                Some(g) if (glass & ok).and_not(g.is_delta()).any() => {
                    let (gf, gp) = g.eval_pdf(wo, wil);
                    (V8::select(glass, gf, f), select(glass, gp, f_pdf))
                }
                Some(_) => (V8::select(glass, V8::zero(), f), select(glass, zero, f_pdf)),
            };
            let ok = ok & f.ne_zero();
            if ok.any() {
                *rays += ok.bits().count_ones() as u64;
                // The shadow ray: to just off an area light's surface, stopping a relative
                // SHADOW_EPSILON short; to a point light, stopping 1e-5 short; to infinity along
                // the sample's direction.
                let origin = match origin_below {
                    Some(o) => V8::select(below, o, origin),
                    None => origin,
                };
                let target = match areas {
                    Some((lp, ln, ..)) => offset_ray_origin(lp, ln, scale),
                    None => V8::zero(),
                };
                let target = if others { V8::select(point | surface, V8::from_lanes(&op), target) } else { target };
                let target = match bulbs {
                    Some((sure, _, bulb_target, ..)) => V8::select(sure, bulb_target, target),
                    None => target,
                };
                let sto = target.sub(origin);
                let sdist = sto.dot(sto).sqrt();
                let sd = sto.div(sdist);
                let tmax = sdist * F8::splat(1.0 - SHADOW_EPSILON);
                let w = mis_weight(settings.mis_heuristic, lpdf, f_pdf);
                let (ok, sd, tmax, w) = if others {
                    let short = select(point, F8::splat(1.0 - 1e-5), F8::splat(1.0 - SHADOW_EPSILON));
                    (
                        ok & (infinite | sdist.gt(zero)),
                        V8::select(infinite, lwi, sd),
                        select(infinite, F8::splat(f32::INFINITY), sdist * short),
                        // Delta lights take no MIS weight.
                        select(delta, one, w),
                    )
                } else {
                    (ok & sdist.gt(zero), sd, tmax, w)
                };
                let unshadowed = beta.mul(f).mul(lle);
                let sc = wil.z.abs() * w / lpdf;
                // The shadow rays: where the lanes lie (`Scene::walks_lanes`), else packed for
                // `Scene::visibility_batch`.
                let (so, sdl, mut tm) = (origin.to_lanes(), sd.to_lanes(), tmax.to_array());
                // An area light's ray may stop at its clear box (as the scalar path's).
                if scene.lights.has_clear_boxes() {
                    for k in lanes_of(ok.bits()) {
                        tm[k] = scene.lights.shadow_tmax(lidx[k], so[k], sdl[k], tm[k]);
                    }
                }
                let (mut visible, mut fraction) = (0u32, [1f32; LANES]);
                if walks_lanes {
                    // No transparent surface and a small BVH: the rays are answered where they
                    // lie (`Scene::occluded_lanes_where`, as `Scene::visibility_batch` would).
                    visible = ok.bits() & !scene.occluded_lanes_where(&so, &sdl, &tm, &tri, ok.bits());
                } else {
                    let (mut lane, mut count) = ([0u8; LANES], 0);
                    let (mut qo, mut qd, mut qt) = ([Vec3::ZERO; LANES], [Vec3::ZERO; LANES], [0f32; LANES]);
                    let mut qf = [0u32; LANES];
                    for k in lanes_of(ok.bits()) {
                        (lane[count], qo[count], qd[count], qt[count], qf[count]) =
                            (k as u8, so[k], sdl[k], tm[k], tri[k]);
                        count += 1;
                    }
                    let mut seen = [0f32; LANES];
                    scene.visibility_batch(&qo[..count], &qd[..count], &qt[..count], &qf[..count], &mut seen[..count]);
                    for j in 0..count {
                        if seen[j] != 0.0 {
                            visible |= 1 << lane[j];
                        }
                        if blends {
                            fraction[lane[j] as usize] = seen[j];
                        }
                    }
                }
                let shadow = ok & M8::from_bits(visible);
                // `Path::add_direct`: β·f·Le, times visibility, times |cos|·w/pdf; the visibility
                // of a scene without BLEND surfaces is 0 or 1, and x·1 = x exactly, so there it
                // is left out. Through a medium the visibility is a colour: the fraction times
                // the medium's transmittance over the light sample's distance.
                let through_medium = if absorbs {
                    let dist = areas.map(|a| a.6.to_array());
                    shadow_transmittance(
                        &medium,
                        (shadow.bits(), below.bits(), entering),
                        |k| materials[mat_id[k]].absorption,
                        |k| if other.bits() & (1 << k) != 0 { odist[k] } else { dist.map_or(0.0, |d| d[k]) },
                    )
                } else {
                    None
                };
                let add = match through_medium {
                    Some(t) => {
                        let f = if blends { fraction } else { [1.0; LANES] };
                        let vis: [Vec3; LANES] = std::array::from_fn(|k| match t[k] {
                            Some(t) => f[k] * t,
                            None => Vec3::splat(f[k]),
                        });
                        unshadowed.mul(V8::from_lanes(&vis))
                    }
                    None if blends => unshadowed.scale(F8::from_array(fraction)),
                    None => unshadowed,
                }
                .scale(sc);
                l = V8::select(shadow, l.add(add), l);
            }
        }

        // The step to the next vertex (`Path::finish`).
        let wi_world = frame.to_world(next.wi);
        let dn = wi_world.dot(ngv);
        // A shading normal can send a direction to the wrong side of the true surface.
        let transmitted = next.wi.z.lt(zero);
        let go = has_next.and_not(dn.le(zero).xor(transmitted) | dn.eq(zero));
        let nb = beta.mul(next.weight());
        let go = go & nb.is_finite() & nb.ne_zero();
        beta = V8::select(go, nb, beta);
        let through = go & transmitted;
        if let (true, Some(g)) = (through.any(), &glass8) {
            eta_scale = select(through, eta_scale * (g.eta * g.eta), eta_scale);
            if absorbs {
                // Into the mesh's medium or out of it (`Path::finish`).
                for k in lanes_of(through.bits()) {
                    let into = entering & (1 << k) != 0;
                    medium[k] =
                        crate::integrator::medium_beyond(medium[k], true, into, materials[mat_id[k]].absorption);
                }
            }
        }
        (prev_p, prev_n, prev_pdf) = (p, ns_flipped, next.pdf.to_array());
        prev_bits = (!next.delta).bits();
        ro = match origin_below {
            Some(o) => V8::select(transmitted, o, origin).to_lanes(),
            None => origin.to_lanes(),
        };
        rd = wi_world;
        let mut roulette = 0u32;
        for (k, depth) in depth.iter_mut().enumerate() {
            *depth += 1;
            roulette |= u32::from(*depth >= settings.rr_depth) << k;
        }
        let mut go = go;
        if roulette & go.bits() != 0 {
            // β's largest channel times η² of the transmissions so far, in units of the threshold
            // (`integrator::RR_THRESHOLD`; the scalar path's arithmetic, in its order).
            let m = beta.max_element() * eta_scale * F8::splat(1.0 / crate::integrator::RR_THRESHOLD);
            let low = M8::from_bits(roulette) & m.lt(one);
            let q = (one - m).max_finite(zero);
            let u_rr = F8::from_array(u_bsdf[(dims::RUSSIAN_ROULETTE % 4) as usize]);
            let killed = low & u_rr.lt(q);
            go = go.and_not(killed);
            let kept = low.and_not(killed);
            beta = V8::select(kept, beta.div(one - q), beta);
        }
        alive = go.bits() & shading;
        shade_handed_lanes!();
    }
}
