//! The ray–triangle test: watertight (Woop, Benthin & Wald 2013, "Watertight Ray/Triangle
//! Intersection", JCGT 2(1); the form of pbrt-v4 §6.5.3), one triangle at a time ([`RtTriangle`])
//! and eight at a time with AVX2 ([`TriangleBlocks::intersect8`]).
//!
//! Why watertight: Möller-Trumbore tests each triangle in its own edge frame, so two triangles
//! sharing an edge round that edge differently and a ray can slip between them (7 of 10⁶ rays from
//! inside a 1.3M-triangle sphere did, against Embree, in `scenes/references/bench_embree.py`).
//! Here the ray is sheared so it points along +z and every vertex is moved into that frame by the
//! same operations; a shared edge's edge function is then computed from the same two transformed
//! vertices in both triangles, as exact negations of each other, so a ray on the edge hits one of
//! them (or both), never neither.
//!
//! The eight-wide test performs the scalar test's operations in the same order, lane by lane
//! (multiply then add, no fused multiply-add, the same double-precision recomputation when an edge
//! function is exactly 0), so both report the same hits to the bit: the scalar one is the
//! reference a test holds the SIMD one to.

use crate::math::{Vec3, Vec3A};
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
use std::arch::x86_64::__m256;

/// A ray prepared for the watertight test: the axis it points most along becomes z (`kz`), the
/// other two follow cyclically (`kx`, `ky`), and the shear (sx, sy, sz) maps the direction to
/// (0, 0, 1). Computed once per ray, used for every triangle.
#[derive(Clone, Copy, Debug)]
pub struct WatertightRay {
    /// The origin's components in the permuted order (x ← kx, y ← ky, z ← kz).
    o: [f32; 3],
    /// The axes: a permutation of 0, 1, 2 (only [`Self::new`] makes one, so the eight-wide test
    /// can load rows by them unchecked).
    k: [usize; 3],
    s: [f32; 3],
}

/// The axes (kx, ky, kz) of each [`axis_case`]: index 2·x_wins + y_wins; both cannot win, so
/// the last row is never read.
const AXES: [[usize; 3]; 4] = [[0, 1, 2], [2, 0, 1], [1, 2, 0], [1, 2, 0]];

/// Which axis direction `d` points most along, as an index into [`AXES`]: kz is x where |x| beats
/// |y| and |z|, else y where it beats |z|, else z (ties go to the later axis), as the comparisons
/// `a.x > a.y`, `a.x > a.z`, `a.y > a.z` decide.
#[inline(always)]
fn axis_case(d: Vec3A) -> usize {
    let a = d.abs();
    let x_gt_y = a.x > a.y;
    let x_wins = x_gt_y & (a.x > a.z);
    let y_wins = !x_gt_y & (a.y > a.z);
    2 * x_wins as usize + y_wins as usize
}

impl WatertightRay {
    /// The ray from `o` along `d`, prepared.
    ///
    /// Without branches: the axis follows the direction, which in a path tracer is random, so
    /// branches on it were mispredicted about every other ray (cachegrind's branch simulation of a
    /// Cornell render put 15 % of all mispredictions here).
    #[inline(always)]
    pub fn new(o: Vec3A, d: Vec3A) -> Self {
        let case = axis_case(d);
        let k = AXES[case];
        #[cfg(all(target_arch = "x86_64", target_feature = "avx"))]
        // SAFETY: AVX is enabled at compile time; each row of `ORDER` is four i32s.
        unsafe {
            // The permutation as lane indices, and one division for the three shear terms, in
            // place of the scalar form's three divisions and its indexing by the axes (bounds
            // checks, the vectors stored and reloaded as floats): 12 instructions fewer a ray
            // (callgrind, `bench rays --scene glass --accel obvhs --no-batches`).
            use std::arch::x86_64::*;
            // `AXES` as lane indices, the fourth lane kept in place.
            const ORDER: [[i32; 4]; 4] = {
                let mut order = [[0, 1, 2, 3]; 4];
                let mut case = 0;
                while case < 4 {
                    let mut lane = 0;
                    while lane < 3 {
                        order[case][lane] = AXES[case][lane] as i32;
                        lane += 1;
                    }
                    case += 1;
                }
                order
            };
            let idx = _mm_loadu_si128(ORDER[case].as_ptr().cast());
            let (op, dp) = (_mm_permutevar_ps(o.into(), idx), _mm_permutevar_ps(d.into(), idx));
            // (−d[kx], −d[ky], 1) / d[kz], lane by lane the scalar form's divisions (the sign
            // flipped by an XOR, as `-x` flips it).
            let num = _mm_blend_ps::<0b1100>(_mm_xor_ps(dp, _mm_set1_ps(-0.0)), _mm_set1_ps(1.0));
            let s = _mm_div_ps(num, _mm_permute_ps::<0b10_10_10_10>(dp));
            WatertightRay { o: Vec3A::from(op).to_array(), k, s: Vec3A::from(s).to_array() }
        }
        #[cfg(not(all(target_arch = "x86_64", target_feature = "avx")))]
        {
            let [kx, ky, kz] = k;
            let (o, d) = (o.to_array(), d.to_array());
            let dz = d[kz];
            WatertightRay { o: [o[kx], o[ky], o[kz]], k, s: [-d[kx] / dz, -d[ky] / dz, 1.0 / dz] }
        }
    }
}

/// A triangle for ray queries: its three vertices and the index of the mesh triangle
/// (`Mesh::triangles`) it is.
#[derive(Clone, Copy, Debug)]
pub struct RtTriangle {
    pub v: [Vec3A; 3],
    pub id: u32,
}

impl RtTriangle {
    pub fn new(v: [Vec3; 3], id: u32) -> Self {
        RtTriangle { v: v.map(Vec3A::from), id }
    }

    /// (t, b1, b2) of a hit with `0 < t < tmax`: b1 and b2 weight vertices 1 and 2.
    #[inline(always)]
    pub fn intersect(&self, r: &WatertightRay, tmax: f32) -> Option<(f32, f32, f32)> {
        let [kx, ky, kz] = r.k;
        // The vertices relative to the origin, permuted and sheared: the ray is now the +z axis.
        let rel = |p: Vec3A| {
            // An array, not `Vec3A`'s index (a match on the axis).
            let p = p.to_array();
            let (x, y, z) = (p[kx] - r.o[0], p[ky] - r.o[1], p[kz] - r.o[2]);
            (x + r.s[0] * z, y + r.s[1] * z, z)
        };
        let (a, b, c) = (rel(self.v[0]), rel(self.v[1]), rel(self.v[2]));
        let (mut e0, mut e1, mut e2) = edge_functions(a, b, c);
        if e0 == 0.0 || e1 == 0.0 || e2 == 0.0 {
            (e0, e1, e2) = edge_functions_f64(a, b, c);
        }
        finish(e0, e1, e2, a.2, b.2, c.2, r.s[2], tmax)
    }
}

/// The three edge functions of the transformed triangle at the origin (each the doubled signed
/// area of the sub-triangle opposite one vertex).
#[inline(always)]
fn edge_functions(a: (f32, f32, f32), b: (f32, f32, f32), c: (f32, f32, f32)) -> (f32, f32, f32) {
    (b.0 * c.1 - b.1 * c.0, c.0 * a.1 - c.1 * a.0, a.0 * b.1 - a.1 * b.0)
}

/// The same in double precision, for when an f32 edge function rounded to exactly 0 (the ray on,
/// or within rounding of, an edge): the products of two f32 are exact in f64, so the sign is right.
#[cold]
fn edge_functions_f64(a: (f32, f32, f32), b: (f32, f32, f32), c: (f32, f32, f32)) -> (f32, f32, f32) {
    let f = |p: f32, q: f32, r: f32, s: f32| (p as f64 * q as f64 - r as f64 * s as f64) as f32;
    (f(b.0, c.1, b.1, c.0), f(c.0, a.1, c.1, a.0), f(a.0, b.1, a.1, b.0))
}

/// From the edge functions: inside test (all of one sign), distance and barycentrics.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn finish(e0: f32, e1: f32, e2: f32, az: f32, bz: f32, cz: f32, sz: f32, tmax: f32) -> Option<(f32, f32, f32)> {
    if (e0 < 0.0 || e1 < 0.0 || e2 < 0.0) && (e0 > 0.0 || e1 > 0.0 || e2 > 0.0) {
        return None;
    }
    let det = e0 + e1 + e2;
    if det == 0.0 {
        return None;
    }
    let t_scaled = e0 * (sz * az) + e1 * (sz * bz) + e2 * (sz * cz);
    let inv = 1.0 / det;
    let t = t_scaled * inv;
    (t > 0.0 && t < tmax).then_some((t, e1 * inv, e2 * inv))
}

/// Triangles in blocks of eight slots (slot s in block s/8, lane s%8), each block nine rows of
/// eight floats (vertex j's axis k in row 3j + k): eight triangles load as nine vectors from 288
/// contiguous bytes. Contiguous matters: nine separate coordinate arrays made every window touch
/// nine cache lines far apart, and closest-hit rays/s on a 1.3M-triangle mesh fell 17 % below
/// one-triangle-at-a-time Möller-Trumbore; a block is 4½ adjacent lines the prefetcher follows.
/// The BVH stores a node's leaf triangles in consecutive slots, so a node's group spans few blocks.
#[derive(Clone, Debug, Default)]
pub struct TriangleBlocks {
    blocks: Vec<Block>,
    /// Mesh triangle index of each slot.
    pub ids: Vec<u32>,
}

#[derive(Clone, Copy, Debug, Default)]
#[repr(C, align(32))]
struct Block {
    rows: [[f32; LANES]; 9],
}

/// Lanes of [`TriangleBlocks::intersect8`].
pub const LANES: usize = 8;

/// [`TriangleBlocks::closest8`]'s "no hit".
pub const NO_HIT8: (f32, usize, f32, f32) = (f32::INFINITY, 0, 0.0, 0.0);

impl TriangleBlocks {
    pub fn new(tris: impl ExactSizeIterator<Item = RtTriangle>) -> Self {
        let n = tris.len();
        let mut out = TriangleBlocks { blocks: vec![Block::default(); n.div_ceil(LANES)], ids: Vec::with_capacity(n) };
        for (i, t) in tris.enumerate() {
            for j in 0..3 {
                for k in 0..3 {
                    out.blocks[i / LANES].rows[3 * j + k][i % LANES] = t.v[j][k];
                }
            }
            out.ids.push(t.id);
        }
        out
    }

    pub fn len(&self) -> usize {
        self.ids.len()
    }

    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }

    /// Slot `i` as one triangle.
    #[inline(always)]
    pub fn get(&self, i: usize) -> RtTriangle {
        let rows = &self.blocks[i / LANES].rows;
        let v = |j: usize| Vec3A::new(rows[3 * j][i % LANES], rows[3 * j + 1][i % LANES], rows[3 * j + 2][i % LANES]);
        RtTriangle { v: [v(0), v(1), v(2)], id: self.ids[i] }
    }

    /// Asks the cache for the blocks holding slots `base + i` for the bits i of `mask` (a
    /// batched traversal's leaf, tested a step later).
    #[inline(always)]
    pub fn prefetch(&self, base: usize, mask: u32) {
        if mask == 0 {
            return;
        }
        let first = (base + mask.trailing_zeros() as usize) / LANES;
        let last = (base + 31 - mask.leading_zeros() as usize) / LANES;
        for b in self.blocks.get(first..=last).unwrap_or(&[]) {
            crate::accel::prefetch(b);
        }
    }

    /// The closest hit among the slots `start + l` for the lanes l set in `lanes` (bit l), with
    /// `0 < t < tmax`: (t, slot, b1, b2). `start` is a block's first slot (a multiple of
    /// [`LANES`]) and every slot `lanes` names exists. Among equal distances the highest slot
    /// wins, as when the slots are tested one at a time from the highest down with a shrinking `tmax`.
    #[inline(always)]
    pub fn intersect8(&self, r: &WatertightRay, start: usize, lanes: u32, tmax: f32) -> Option<(f32, usize, f32, f32)> {
        debug_assert!(lanes < 1 << LANES && start.is_multiple_of(LANES) && start / LANES < self.blocks.len());
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
        // SAFETY: AVX2 is enabled at compile time; the block is found with a bounds check and
        // its rows are 32-byte aligned (`Block`'s repr).
        unsafe {
            self.intersect8_avx2(r, start, lanes, tmax)
        }
        #[cfg(not(all(target_arch = "x86_64", target_feature = "avx2")))]
        {
            self.intersect8_scalar(r, start, lanes, tmax)
        }
    }

    /// [`Self::intersect8`] one slot at a time: the reference.
    pub fn intersect8_scalar(
        &self,
        r: &WatertightRay,
        start: usize,
        lanes: u32,
        mut tmax: f32,
    ) -> Option<(f32, usize, f32, f32)> {
        let mut best = None;
        for l in (0..LANES).rev() {
            if lanes & (1 << l) != 0 {
                if let Some((t, b1, b2)) = self.get(start + l).intersect(r, tmax) {
                    tmax = t;
                    best = Some((t, start + l, b1, b2));
                }
            }
        }
        best
    }

    /// Whether any of the lanes' slots is hit with `0 < t < tmax`.
    #[inline(always)]
    pub fn any8(&self, r: &WatertightRay, start: usize, lanes: u32, tmax: f32) -> bool {
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
        // SAFETY: as in `intersect8`.
        unsafe {
            let l = self.lanes_avx2(r, start, lanes, tmax);
            if l.on_edge != 0 {
                return self.intersect8_scalar(r, start, lanes, tmax).is_some();
            }
            std::arch::x86_64::_mm256_movemask_ps(l.hit) != 0
        }
        #[cfg(not(all(target_arch = "x86_64", target_feature = "avx2")))]
        {
            self.intersect8_scalar(r, start, lanes, tmax).is_some()
        }
    }

    /// [`Self::intersect8`] with "no hit" as t = ∞ (slot and barycentrics then meaningless):
    /// the form a traversal can take without a branch on whether the block was hit.
    #[inline(always)]
    pub fn closest8(&self, r: &WatertightRay, start: usize, lanes: u32, tmax: f32) -> (f32, usize, f32, f32) {
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
        // SAFETY: as in `intersect8`.
        unsafe {
            self.closest8_avx2(r, start, lanes, tmax)
        }
        #[cfg(not(all(target_arch = "x86_64", target_feature = "avx2")))]
        {
            self.intersect8_scalar(r, start, lanes, tmax).unwrap_or(NO_HIT8)
        }
    }

    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[inline(always)]
    unsafe fn intersect8_avx2(
        &self,
        r: &WatertightRay,
        start: usize,
        lanes: u32,
        tmax: f32,
    ) -> Option<(f32, usize, f32, f32)> {
        let hit = self.closest8_avx2(r, start, lanes, tmax);
        (hit.0 != f32::INFINITY).then_some(hit)
    }

    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[inline(always)]
    unsafe fn closest8_avx2(&self, r: &WatertightRay, start: usize, lanes: u32, tmax: f32) -> (f32, usize, f32, f32) {
        use std::arch::x86_64::*;
        let l = self.lanes_avx2(r, start, lanes, tmax);
        if l.on_edge != 0 {
            // Rare (a ray within rounding of an edge): the reference answer for the whole group.
            return self.intersect8_scalar(r, start, lanes, tmax).unwrap_or(NO_HIT8);
        }
        let hits = _mm256_movemask_ps(l.hit) as u32;
        if hits & hits.wrapping_sub(1) == 0 {
            // No lane or one lane hit (nearly every block: a ray rarely crosses two of a block's
            // triangles): that lane is the nearest, without `nearest_lane`'s chain of shuffles
            // and minima (Cornell: 0.4 % fewer instructions). Lane 0 when none (tzcnt of 0 is
            // 32), whose t is then ∞: `nearest_lane`'s answer either way, bit for bit.
            let k = hits.trailing_zeros() & 7;
            let pick = |v: __m256| _mm256_cvtss_f32(_mm256_permutevar8x32_ps(v, _mm256_set1_epi32(k as i32)));
            let t = _mm256_blendv_ps(_mm256_set1_ps(f32::INFINITY), l.t, l.hit);
            let inv = pick(l.inv);
            return (pick(t), start + k as usize, pick(l.e1) * inv, pick(l.e2) * inv);
        }
        Self::nearest_lane(&l, start).0
    }

    /// The nearest of `l`'s hit lanes as `closest8` answers (t, slot, b1, b2), and the lanes at
    /// that distance. Without branches on the hits (the data decide them, so they were
    /// mispredicted often): the smallest t of the hit lanes (∞ for none), the highest hit lane
    /// holding it (the scalar order, highest lane first with a strict comparison, keeps that
    /// one), then its barycentrics. A hit's t is below tmax, so finite: ∞ means no hit.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[inline(always)]
    unsafe fn nearest_lane(l: &Lanes8, start: usize) -> ((f32, usize, f32, f32), u32) {
        use std::arch::x86_64::*;
        let inf = _mm256_set1_ps(f32::INFINITY);
        let t = _mm256_blendv_ps(inf, l.t, l.hit);
        let m = _mm256_min_ps(t, _mm256_permute2f128_ps::<1>(t, t));
        let m = _mm256_min_ps(m, _mm256_permute_ps::<0b01_00_11_10>(m));
        let m = _mm256_min_ps(m, _mm256_permute_ps::<0b10_11_00_01>(m));
        let at_min = _mm256_movemask_ps(_mm256_and_ps(_mm256_cmp_ps::<_CMP_EQ_OQ>(t, m), l.hit)) as u32;
        // The highest lane at the minimum; lane 0 (ignored) when nothing is hit.
        let k = 31 - (at_min | 1).leading_zeros();
        let pick = |v: __m256| _mm256_cvtss_f32(_mm256_permutevar8x32_ps(v, _mm256_set1_epi32(k as i32)));
        let inv = pick(l.inv);
        ((_mm256_cvtss_f32(m), start + k as usize, pick(l.e1) * inv, pick(l.e2) * inv), at_min)
    }

    /// [`Self::closest8`]'s answer where it is the only one a test of these slots can give
    /// (`Some`), else None: when a lane lies within rounding of an edge (`closest8` then asks the
    /// scalar reference) or two lanes share the least t (which one is kept then depends on the
    /// slots grouped with them). A bundle of rays that tests other groupings of the slots than a
    /// ray's own walk would (`Accel::intersect_bundle`) keeps only such answers and leaves the
    /// others to that walk. "No hit" is t = ∞.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[inline(always)]
    pub fn closest8_unique(
        &self,
        r: &WatertightRay,
        start: usize,
        lanes: u32,
        tmax: f32,
    ) -> Option<(f32, usize, f32, f32)> {
        // SAFETY: as in `intersect8`.
        unsafe {
            let l = self.lanes_avx2(r, start, lanes, tmax);
            if l.on_edge != 0 {
                return None;
            }
            let (hit, at_min) = Self::nearest_lane(&l, start);
            (at_min.count_ones() <= 1).then_some(hit)
        }
    }

    /// The watertight test on eight slots at once, lane by lane as `RtTriangle::intersect`.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[inline(always)]
    unsafe fn lanes_avx2(&self, r: &WatertightRay, start: usize, lanes: u32, tmax: f32) -> Lanes8 {
        use std::arch::x86_64::*;
        // The axes as offsets into the block's rows, without bounds checks: indexed loads on a
        // ray's axes were compiled into branches on them, which the ray's random direction
        // mispredicts.
        let [kx, ky, kz] = r.k;
        let rows = self.blocks[start / LANES].rows.as_ptr() as *const f32;
        // SAFETY: j ≤ 2 and every axis is 0, 1 or 2 (`WatertightRay::new` is the only maker of
        // one), so row 3j + k is one of the block's nine rows of LANES floats, 32-byte aligned
        // (`Block`'s repr).
        let load = |j: usize, k: usize| _mm256_load_ps(rows.add((3 * j + k) * LANES));
        let (ox, oy, oz) = (_mm256_set1_ps(r.o[0]), _mm256_set1_ps(r.o[1]), _mm256_set1_ps(r.o[2]));
        let (sx, sy) = (_mm256_set1_ps(r.s[0]), _mm256_set1_ps(r.s[1]));
        // As `RtTriangle::intersect`'s `rel`, operation for operation.
        let rel = |j: usize| {
            let x = _mm256_sub_ps(load(j, kx), ox);
            let y = _mm256_sub_ps(load(j, ky), oy);
            let z = _mm256_sub_ps(load(j, kz), oz);
            (_mm256_add_ps(x, _mm256_mul_ps(sx, z)), _mm256_add_ps(y, _mm256_mul_ps(sy, z)), z)
        };
        let active = crate::lanes::M8::from_bits(lanes).0;
        let w = watertight8((rel(0), rel(1), rel(2)), _mm256_set1_ps(r.s[2]), _mm256_set1_ps(tmax));
        let on_edge = _mm256_movemask_ps(_mm256_and_ps(w.on_edge, active)) as u32;
        Lanes8 { hit: _mm256_and_ps(w.hit, active), on_edge, t: w.t, e1: w.e1, e2: w.e2, inv: w.inv }
    }
}

/// Up to eight rays prepared for the watertight test that share an origin and their axes (a
/// camera bundle's, as a rule): the triangle-major form of [`WatertightRay`], for testing one
/// triangle against all of them at once ([`TriangleBlocks::slot_rays8`]). Where the rays share
/// an origin and axes, a triangle's vertices relative to the origin are the same numbers for
/// every ray, and only the shear differs from lane to lane.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[derive(Clone, Copy)]
pub struct RayLanes8 {
    o: [f32; 3],
    k: [usize; 3],
    /// Each lane's shear terms (a lane past the rays repeats the first ray's).
    s: [std::arch::x86_64::__m256; 3],
}

#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
impl RayLanes8 {
    /// The rays from `o` along the directions `d` (lanes past them repeat the first), or None
    /// where they do not all point most along one axis. Each lane's axes and shear are
    /// [`WatertightRay::new`]'s for its ray, bit for bit: `axis_case`'s comparisons and the same
    /// division of the same numbers, eight lanes at once.
    #[inline(always)]
    pub fn from_lanes(o: Vec3A, d: &crate::ray_bundle::Directions8) -> Option<Self> {
        use std::arch::x86_64::*;
        // SAFETY: AVX is enabled at compile time.
        unsafe {
            let abs = |x: __m256| _mm256_andnot_ps(_mm256_set1_ps(-0.0), x);
            let [ax, ay, az] = d.xyz.map(abs);
            let gt = |a: __m256, b: __m256| _mm256_cmp_ps::<_CMP_GT_OQ>(a, b);
            let x_gt_y = gt(ax, ay);
            let x_wins = _mm256_movemask_ps(_mm256_and_ps(x_gt_y, gt(ax, az)));
            let y_wins = _mm256_movemask_ps(_mm256_andnot_ps(x_gt_y, gt(ay, az)));
            // Every lane the same case of `axis_case`.
            let case = match (x_wins, y_wins) {
                (0xff, 0) => 2,
                (0, 0xff) => 1,
                (0, 0) => 0,
                _ => return None,
            };
            let k = AXES[case];
            let [dx, dy, dz] = k.map(|a| d.xyz[a]);
            let neg = _mm256_set1_ps(-0.0);
            let s = [
                _mm256_div_ps(_mm256_xor_ps(dx, neg), dz),
                _mm256_div_ps(_mm256_xor_ps(dy, neg), dz),
                _mm256_div_ps(_mm256_set1_ps(1.0), dz),
            ];
            let o = o.to_array();
            Some(RayLanes8 { o: [o[k[0]], o[k[1]], o[k[2]]], k, s })
        }
    }
}

impl TriangleBlocks {
    /// The watertight test of slot `slot` against the eight rays of `r` (lane l: ray l), each
    /// stopping at its own lane of `tmax`: lane by lane the numbers [`Self::lanes_avx2`] gives
    /// ray l for that slot, operation for operation (a vertex's position relative to the
    /// shared origin is one subtraction either way, and the products' operands are the same,
    /// in either order). `hit` and `on_edge` are lane masks.
    ///
    /// # Safety
    /// AVX2 must be available (it is enabled at compile time where this is compiled).
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[inline(always)]
    pub unsafe fn slot_rays8(&self, r: &RayLanes8, slot: usize, tmax: std::arch::x86_64::__m256) -> SlotRays8 {
        use std::arch::x86_64::*;
        let [kx, ky, kz] = r.k;
        let rows = &self.blocks[slot / LANES].rows;
        let lane = slot % LANES;
        let (sx, sy, sz) = (r.s[0], r.s[1], r.s[2]);
        // `RtTriangle::intersect`'s `rel`: the subtractions once, the shear lane by lane.
        let rel = |j: usize| {
            let x = _mm256_set1_ps(rows[3 * j + kx][lane] - r.o[0]);
            let y = _mm256_set1_ps(rows[3 * j + ky][lane] - r.o[1]);
            let z = _mm256_set1_ps(rows[3 * j + kz][lane] - r.o[2]);
            (_mm256_add_ps(x, _mm256_mul_ps(sx, z)), _mm256_add_ps(y, _mm256_mul_ps(sy, z)), z)
        };
        let w = watertight8((rel(0), rel(1), rel(2)), sz, tmax);
        SlotRays8 {
            hit: w.hit,
            on_edge: w.on_edge,
            t: w.t,
            b1: _mm256_mul_ps(w.e1, w.inv),
            b2: _mm256_mul_ps(w.e2, w.inv),
        }
    }
}

/// What [`TriangleBlocks::slot_rays8`] found for each ray: whether it hits (all ones), whether
/// an edge function rounded to 0 (all ones: the hit is then meaningless, the scalar test's f64
/// recomputation would decide it), t and the barycentrics (e1 · 1/det and e2 · 1/det, as
/// `nearest_lane` computes them).
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
pub struct SlotRays8 {
    pub hit: std::arch::x86_64::__m256,
    pub on_edge: std::arch::x86_64::__m256,
    pub t: std::arch::x86_64::__m256,
    pub b1: std::arch::x86_64::__m256,
    pub b2: std::arch::x86_64::__m256,
}

/// A vertex moved into the rays' frame (`RtTriangle::intersect`'s `rel`), eight lanes: x, y, z.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
type Vertex8 = (__m256, __m256, __m256);

/// Eight lanes of `RtTriangle::intersect` from the transformed vertices on: the edge functions,
/// the inside test, distance and 1/det, operation for operation (multiply then subtract, no fused
/// multiply-add), each lane stopping at its lane of `tmax`. `hit` and `on_edge` are lane masks,
/// for every lane (the callers mask the lanes they test); `hit` is meaningless where `on_edge`.
///
/// # Safety
/// AVX2 must be available (it is enabled at compile time where this is compiled).
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[inline(always)]
unsafe fn watertight8((a, b, c): (Vertex8, Vertex8, Vertex8), sz: __m256, tmax: __m256) -> Watertight8 {
    use std::arch::x86_64::*;
    let cross = |p: __m256, q: __m256, r: __m256, s: __m256| _mm256_sub_ps(_mm256_mul_ps(p, q), _mm256_mul_ps(r, s));
    let e0 = cross(b.0, c.1, b.1, c.0);
    let e1 = cross(c.0, a.1, c.1, a.0);
    let e2 = cross(a.0, b.1, a.1, b.0);
    let zero = _mm256_setzero_ps();
    let eq0 = |e: __m256| _mm256_cmp_ps::<_CMP_EQ_OQ>(e, zero);
    let on_edge = _mm256_or_ps(eq0(e0), _mm256_or_ps(eq0(e1), eq0(e2)));
    let lt = |e: __m256| _mm256_cmp_ps::<_CMP_LT_OQ>(e, zero);
    let gt = |e: __m256| _mm256_cmp_ps::<_CMP_GT_OQ>(e, zero);
    let any_neg = _mm256_or_ps(lt(e0), _mm256_or_ps(lt(e1), lt(e2)));
    let any_pos = _mm256_or_ps(gt(e0), _mm256_or_ps(gt(e1), gt(e2)));
    let det = _mm256_add_ps(_mm256_add_ps(e0, e1), e2);
    let t_scaled = _mm256_add_ps(
        _mm256_add_ps(_mm256_mul_ps(e0, _mm256_mul_ps(sz, a.2)), _mm256_mul_ps(e1, _mm256_mul_ps(sz, b.2))),
        _mm256_mul_ps(e2, _mm256_mul_ps(sz, c.2)),
    );
    let inv = _mm256_div_ps(_mm256_set1_ps(1.0), det);
    let t = _mm256_mul_ps(t_scaled, inv);
    let ok = _mm256_andnot_ps(_mm256_and_ps(any_neg, any_pos), _mm256_castsi256_ps(_mm256_set1_epi32(-1)));
    let ok = _mm256_andnot_ps(eq0(det), ok);
    let ok = _mm256_and_ps(ok, _mm256_cmp_ps::<_CMP_GT_OQ>(t, zero));
    let hit = _mm256_and_ps(ok, _mm256_cmp_ps::<_CMP_LT_OQ>(t, tmax));
    Watertight8 { hit, on_edge, t, e1, e2, inv }
}

/// What [`watertight8`] found, lane by lane.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
struct Watertight8 {
    hit: __m256,
    on_edge: __m256,
    t: __m256,
    e1: __m256,
    e2: __m256,
    inv: __m256,
}

/// What [`TriangleBlocks::lanes_avx2`] found: the lanes hit (meaningless where `on_edge` is set:
/// those lanes need the scalar test's f64 recomputation), and per lane t, e1, e2 and 1/det.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
struct Lanes8 {
    /// All ones in the lanes hit.
    hit: std::arch::x86_64::__m256,
    on_edge: u32,
    t: std::arch::x86_64::__m256,
    e1: std::arch::x86_64::__m256,
    e2: std::arch::x86_64::__m256,
    inv: std::arch::x86_64::__m256,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampler::hash_unit as u;

    /// `RayLanes8::from_lanes` gives each lane its ray's `WatertightRay`, bit for bit (origin, axes
    /// and shear), for one to eight rays whose directions share their axis, of either sign and
    /// with zero components; rays that do not share it are refused.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[test]
    fn ray_lanes_are_each_rays_own() {
        let o = Vec3A::new(0.3, -2.0, 7.5);
        let mut refused = 0;
        for i in 0..4000u64 {
            let n = 1 + (i % 8) as usize;
            let axis = (i / 8 % 3) as usize;
            let sign = if i % 5 == 0 { -1.0 } else { 1.0 };
            let dirs: Vec<Vec3> = (0..n as u64)
                .map(|l| {
                    let mut v = [u(i * 64 + 3 * l) - 0.5, u(i * 64 + 3 * l + 1) - 0.5, u(i * 64 + 3 * l + 2) - 0.5];
                    if i % 7 == 0 {
                        v[(axis + 1) % 3] = 0.0;
                    }
                    // Mostly along `axis`; every ninth bundle's last ray along another.
                    v[axis] = sign * (1.0 + u(i * 64 + 50 + l));
                    if i % 9 == 0 && l + 1 == n as u64 && n > 1 {
                        v[(axis + 2) % 3] = 9.0;
                    }
                    Vec3::from_array(v)
                })
                .collect();
            let rays: Vec<WatertightRay> = dirs.iter().map(|&d| WatertightRay::new(o, Vec3A::from(d))).collect();
            let shared = rays.iter().all(|r| r.k == rays[0].k);
            let lanes = crate::ray_bundle::Directions8::new(&dirs).and_then(|d| RayLanes8::from_lanes(o, &d));
            let Some(lanes) = lanes else {
                assert!(!shared, "bundle {i}: refused rays that share axes {:?}", rays[0].k);
                refused += 1;
                continue;
            };
            assert!(shared, "bundle {i}: took rays of different axes");
            assert_eq!((lanes.k, lanes.o.map(f32::to_bits)), (rays[0].k, rays[0].o.map(f32::to_bits)));
            let mut s = [[0f32; LANES]; 3];
            for (row, lane) in s.iter_mut().zip(lanes.s) {
                // SAFETY: AVX is enabled at compile time; each row is eight floats.
                unsafe { std::arch::x86_64::_mm256_storeu_ps(row.as_mut_ptr(), lane) };
            }
            for (l, r) in rays.iter().enumerate() {
                assert_eq!([s[0][l], s[1][l], s[2][l]].map(f32::to_bits), r.s.map(f32::to_bits), "bundle {i} ray {l}");
            }
        }
        assert!(refused > 100, "{refused} bundles refused");
    }

    /// The branch-free axis choice is pbrt-v4's `MaxComponentIndex(Abs(d))` (ties to the later
    /// axis), with kx and ky following cyclically, on directions with every sign, zeros and ties.
    #[test]
    fn ray_axes_follow_the_largest_component() {
        let values = [0.0f32, -0.0, 0.5, -0.5, 1.0, -1.0, 2.0, -3.0, 1e-30];
        for &x in &values {
            for &y in &values {
                for &z in &values {
                    let a = Vec3A::new(x, y, z).abs();
                    let kz = if a.x > a.y {
                        if a.x > a.z {
                            0
                        } else {
                            2
                        }
                    } else if a.y > a.z {
                        1
                    } else {
                        2
                    };
                    let r = WatertightRay::new(Vec3A::new(7.0, 8.0, 9.0), Vec3A::new(x, y, z));
                    assert_eq!(r.k, [(kz + 1) % 3, (kz + 2) % 3, kz], "direction ({x}, {y}, {z})");
                    let (o, d) = ([7.0f32, 8.0, 9.0], [x, y, z]);
                    let [kx, ky] = [(kz + 1) % 3, (kz + 2) % 3];
                    assert_eq!(r.o, [o[kx], o[ky], o[kz]]);
                    let s = [-d[kx] / d[kz], -d[ky] / d[kz], 1.0 / d[kz]];
                    assert_eq!(r.s.map(f32::to_bits), s.map(f32::to_bits), "direction ({x}, {y}, {z})");
                }
            }
        }
    }

    fn v3(i: u64) -> Vec3 {
        Vec3::new(u(i), u(i + 1), u(i + 2)) * 2.0 - 1.0
    }

    /// Every lane subset of groups of random, degenerate, edge-sharing and vertex-sharing
    /// triangles, against rays of every kind: the eight-wide test and the one-at-a-time reference
    /// agree to the bit, misses included.
    #[test]
    fn eight_wide_equals_one_at_a_time() {
        let mut tris = Vec::new();
        for i in 0..400u64 {
            let (a, b, c) = (v3(10 * i), v3(10 * i + 3), v3(10 * i + 6));
            let tri = match i % 5 {
                0 => [a, b, b],                 // degenerate
                1 => [a, b, a + (b - a) * 0.5], // collinear
                2 => [Vec3::ZERO, a, b],        // many share the origin vertex
                3 => {
                    // Shares an edge with the triangle before it, wound the other way.
                    let prev: &RtTriangle = &tris[tris.len() - 1];
                    [prev.v[1].into(), prev.v[0].into(), c]
                }
                _ => [a, b, c],
            };
            tris.push(RtTriangle::new(tri, i as u32));
        }
        let blocks = TriangleBlocks::new(tris.iter().copied());
        let (mut compared, mut hits) = (0usize, 0usize);
        for i in 0..3000u64 {
            let o = v3(7 * i + 100_000) * 2.0;
            let target = match i % 4 {
                0 => Vec3::ZERO,                                                                     // a shared vertex
                1 => tris[(i % 400) as usize].v[0].into(),                                           // a vertex
                2 => ((tris[(i % 400) as usize].v[0] + tris[(i % 400) as usize].v[1]) * 0.5).into(), // an edge
                _ => v3(7 * i + 200_000) * 0.5,
            };
            let mut d = target - o;
            if i % 9 == 0 {
                d.y = 0.0; // a zero direction component
            }
            if d.length_squared() == 0.0 {
                continue;
            }
            let r = WatertightRay::new(o.into(), d.into());
            let tmax = if i % 3 == 0 { 1.0 } else { f32::INFINITY };
            let start = (i as usize * 13) % (blocks.len() - LANES) / LANES * LANES;
            for lanes in [0xFF, 0x01, 0x80, 0x5A, (i as u32 * 2654435761) >> 24] {
                let (a, b) =
                    (blocks.intersect8(&r, start, lanes, tmax), blocks.intersect8_scalar(&r, start, lanes, tmax));
                let bits = |h: Option<(f32, usize, f32, f32)>| {
                    h.map(|(t, s, b1, b2)| (t.to_bits(), s, b1.to_bits(), b2.to_bits()))
                };
                assert_eq!(bits(a), bits(b), "ray {i} start {start} lanes {lanes:#x}");
                assert_eq!(blocks.any8(&r, start, lanes, tmax), b.is_some(), "ray {i} start {start} lanes {lanes:#x}");
                compared += 1;
                hits += a.is_some() as usize;
            }
        }
        assert!(compared > 10_000 && hits > 1000, "{compared} groups, {hits} hits");
    }

    /// The reported distance and barycentrics give back the point: t along the ray equals the
    /// barycentric interpolation of the vertices.
    #[test]
    fn distance_and_barycentrics_agree() {
        for i in 0..2000u64 {
            let tri = RtTriangle::new([v3(9 * i), v3(9 * i + 3), v3(9 * i + 6)], 0);
            let o = Vec3A::from(v3(9 * i + 50_000) * 3.0);
            let (b1, b2) = (u(9 * i + 7) * 0.5, u(9 * i + 8) * 0.5);
            let p = tri.v[0] + (tri.v[1] - tri.v[0]) * b1 + (tri.v[2] - tri.v[0]) * b2;
            let d = p - o;
            let Some((t, h1, h2)) = tri.intersect(&WatertightRay::new(o, d), f32::INFINITY) else {
                // Only near-degenerate triangles seen edge-on may miss.
                let n = (tri.v[1] - tri.v[0]).cross(tri.v[2] - tri.v[0]);
                assert!(n.normalize().dot(d.normalize()).abs() < 1e-3, "ray {i} missed");
                continue;
            };
            let q = tri.v[0] + (tri.v[1] - tri.v[0]) * h1 + (tri.v[2] - tri.v[0]) * h2;
            assert!((t - 1.0).abs() < 1e-3, "ray {i}: t = {t}");
            assert!((q - (o + d * t)).length() < 1e-3 * (1.0 + o.length()), "ray {i}: {q} vs {}", o + d * t);
        }
    }
}
