//! A BVH8 node whose eight child boxes are plain `f32` planes: obvhs' compressed node
//! ([`CwBvhNode`], Ylitie et al. 2017) decompressed once after the build, for BVHs small enough
//! that three times the bytes still stay in cache (`accel::WIDE_NODES_UP_TO`).
//!
//! Why: the compressed test widens each plane byte to a float and rescales it (load, zero-extend,
//! convert, multiply, add) before the slab arithmetic; here a plane is loaded as a float and
//! becomes a distance by a subtract and a multiply. On the suite's scenes (`tessera bench rays
//! --scene`) that made closest-hit rays 3–10 % and occlusion rays 6–25 % faster. The price is
//! size: 256 bytes a node against 80.
//!
//! Robustness: a distance is `(plane − o) · (1/d)`, the subtraction first. Precomputing `o · 1/d`
//! to make it one fused multiply-subtract (Embree's fast path) cancels catastrophically when the
//! origin is far from the world origin and close to the plane (a test here lost 370 of 17 605
//! boxes that way), and grazing shadow rays were slower with it (`bench rays --scene` on
//! sphere_light: occluded rays 21 % slower than the compressed nodes). The far distances use `1/d · (1 + 4γ₃)` (pbrt-v4 `Bounds3::IntersectP`
//! scales them by 1 + 2γ₃, after Ize 2013; the extra margin covers rounding the scaled inverse):
//! rounding can then only widen a box's interval, never lose a box the ray touches.
//!
//! The decompressed boxes are the compressed ones exactly, each plane rounded outward to `f32`
//! (the quantised plane `p + 2^e · q` is computed in `f64`, where it is exact), so a box still
//! contains everything the compressed one did. The child metadata is obvhs' own, pre-split per
//! node into the parts of `CwBvhNode::get_child_and_index_bits` that do not depend on the ray.

use crate::node_ray::NodeRay;
use crate::ray_bundle::RayBundle;
use obvhs::cwbvh::node::CwBvhNode;

// The lower bound on a child's entry distance (0, not obvhs' 10⁻⁴), the scalar lane operations
// and the scalar mask: shared with the compressed node's test.
use crate::cwbvh_node::{mask_and_entry, simd_max, simd_min};

#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
pub struct WideNode {
    /// `planes[axis][0]` the children's lower planes on that axis, `[1]` the upper, by child slot.
    /// An empty slot has lower +∞ and upper −∞, which no ray enters.
    planes: [[[f32; 8]; 2]; 3],
    /// Per child byte: inner children 1, leaves their unary primitive count.
    child_bits8: u64,
    /// Per child byte: inner children their slot + 24, leaves their first primitive's offset.
    index8: u64,
    /// 0xff in the bytes of inner children: the bytes the ray octant permutes.
    inner8: u64,
    pub child_base_idx: u32,
    pub primitive_base_idx: u32,
    /// Bit i set when slot i holds an inner node.
    pub imask: u32,
}

impl WideNode {
    pub fn from_compressed(n: &CwBvhNode) -> Self {
        let ext = n.compute_extent();
        let q = [(&n.child_min_x, &n.child_max_x), (&n.child_min_y, &n.child_max_y), (&n.child_min_z, &n.child_max_z)];
        let mut planes = [[[0f32; 8]; 2]; 3];
        for (axis, (lo, hi)) in q.iter().enumerate() {
            for slot in 0..8 {
                if n.child_meta[slot] == 0 {
                    planes[axis][0][slot] = f32::INFINITY;
                    planes[axis][1][slot] = f32::NEG_INFINITY;
                    continue;
                }
                let exact = |b: u8| n.p[axis] as f64 + ext[axis] as f64 * b as f64;
                planes[axis][0][slot] = round_down(exact(lo[slot]));
                planes[axis][1][slot] = round_up(exact(hi[slot]));
            }
        }
        // obvhs' get_child_and_index_bits, less its one ray-dependent step (the octant XOR).
        let meta8 = u64::from_le_bytes(n.child_meta);
        let is_inner8 = (meta8 & (meta8 << 1)) & 0x1010_1010_1010_1010;
        WideNode {
            planes,
            child_bits8: (meta8 >> 5) & 0x0707_0707_0707_0707,
            index8: meta8 & 0x1f1f_1f1f_1f1f_1f1f,
            inner8: (is_inner8 >> 4) * 0xff,
            child_base_idx: n.child_base_idx,
            primitive_base_idx: n.primitive_base_idx,
            imask: n.imask as u32,
        }
    }

    /// Child `slot`'s box as its lower and upper corners, or None for an empty slot.
    pub fn child_box(&self, slot: usize) -> Option<([f32; 3], [f32; 3])> {
        let lo = [0, 1, 2].map(|a| self.planes[a][0][slot]);
        let hi = [0, 1, 2].map(|a| self.planes[a][1][slot]);
        // An empty slot's lower planes are +∞ and its upper −∞.
        (lo[0] <= hi[0]).then_some((lo, hi))
    }

    /// Bit `slot` set for each used child some ray of `bundle` may enter (with AVX2, the mask of
    /// [`Self::bundle_span`]).
    #[inline]
    pub fn bundle_mask(&self, bundle: &RayBundle) -> u32 {
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
        {
            self.bundle_span(bundle).0
        }
        #[cfg(not(all(target_arch = "x86_64", target_feature = "avx2")))]
        self.bundle_mask_scalar(bundle)
    }

    /// [`Self::bundle_mask`] with, per slot, a lower bound on the distance at which any ray of
    /// the bundle enters that child (0 at least; meaningless where the mask's bit is clear):
    /// [`RayBundle::may_enter`] on all eight children at once (written as a loop over slots,
    /// LLVM left it scalar: the background test, then `bundle_misses`, since folded into
    /// `Accel::intersect_bundle`, took 780 instructions a pixel batch against 470, callgrind on
    /// veach).
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[inline]
    pub fn bundle_span(&self, bundle: &RayBundle) -> (u32, [f32; 8]) {
        use crate::lanes::F8;
        let (mut enter, mut leave) = (F8::zero(), F8::splat(f32::INFINITY));
        for a in 0..3 {
            let Some(ax) = bundle.axis(a) else { continue };
            let (e, l) = ax.span8(F8::from_array(self.planes[a][0]), F8::from_array(self.planes[a][1]));
            enter = enter.max(e);
            leave = leave.min(l);
        }
        // An empty slot (lower +∞, upper −∞) is entered by nothing.
        let used = F8::from_array(self.planes[0][0]).le(F8::from_array(self.planes[0][1]));
        ((used & enter.le(leave)).bits(), enter.to_array())
    }

    /// The primitive bits (obvhs' hit-mask format, relative to `primitive_base_idx`) of leaf
    /// child `slot`: its unary primitive count shifted to its first primitive's offset.
    #[inline(always)]
    pub fn leaf_prims(&self, slot: usize) -> u32 {
        let count = ((self.child_bits8 >> (8 * slot)) & 0x7) as u32;
        let offset = ((self.index8 >> (8 * slot)) & 0x1f) as u32;
        count << offset
    }

    /// [`Self::bundle_mask`] a child at a time by [`RayBundle::may_enter`] (the build without
    /// AVX2, and the reference in tests).
    pub fn bundle_mask_scalar(&self, bundle: &RayBundle) -> u32 {
        (0..8)
            .filter(|&s| self.child_box(s).is_some_and(|(lo, hi)| bundle.may_enter(lo, hi)))
            .fold(0, |mask, s| mask | 1 << s)
    }

    /// The hit mask of the children `ray` enters before `ray.tmax` (obvhs' format: leaf
    /// children's primitive bits in the low 24 bits, inner children's bits in the high 8 at
    /// their traversal-priority slot) and each child's entry distance by slot.
    #[inline(always)]
    pub fn intersect(&self, ray: &NodeRay) -> (u32, [f32; 8]) {
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
        // SAFETY: AVX2 is enabled at compile time; every load reads a 32-byte-aligned
        // [f32; 8] of `self` (the struct is 64-byte aligned, each row 32 bytes).
        unsafe {
            self.intersect_avx2(ray)
        }
        #[cfg(not(all(target_arch = "x86_64", target_feature = "avx2")))]
        {
            self.intersect_scalar(ray)
        }
    }

    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[inline(always)]
    unsafe fn intersect_avx2(&self, ray: &NodeRay) -> (u32, [f32; 8]) {
        use std::arch::x86_64::*;
        // A ray with a negative inverse enters a box through its upper plane ([`NodeRay::negative`]):
        // the rows to load, as byte offsets from a table. Worked out from the sign bits, they
        // cost 13 to 15 more instructions a query (callgrind, `bench rays --scene glass` and
        // `--scene veach`, `--accel obvhs --no-batches`).
        let rows = &PLANE_ROWS[ray.negative as usize & 7];
        let planes = self.planes.as_ptr() as *const u8;
        // SAFETY: every offset in `PLANE_ROWS` is that of one of `planes`' six 32-byte-aligned rows.
        let ld = |row: usize| _mm256_load_ps(planes.add(row) as *const f32);
        let slab = |axis: usize| {
            let o = _mm256_set1_ps(ray.origin[axis]);
            let (inv, inv_far) = (_mm256_set1_ps(ray.inv[axis]), _mm256_set1_ps(ray.inv_far[axis]));
            (
                _mm256_mul_ps(_mm256_sub_ps(ld(rows[2 * axis]), o), inv),
                _mm256_mul_ps(_mm256_sub_ps(ld(rows[2 * axis + 1]), o), inv_far),
            )
        };
        let (nx, fx) = slab(0);
        let (ny, fy) = slab(1);
        let (nz, fz) = slab(2);
        let tmin = _mm256_max_ps(_mm256_max_ps(nx, ny), _mm256_max_ps(nz, _mm256_set1_ps(ray.tmin)));
        let tmax = _mm256_min_ps(_mm256_min_ps(fx, fy), _mm256_min_ps(fz, _mm256_set1_ps(ray.tmax)));
        let hit = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_LE_OQ>(tmin, tmax));
        // Each hit child's bits shifted to its place in the mask, ORed across the lanes. Every
        // shift is below 32 (a slot + 24 or a primitive offset below 24, the octant XOR touching
        // only bits 0–2); the mask says so to LLVM, which otherwise guards `vpsllvd`'s
        // out-of-range rule with five more instructions a node.
        let index8 = self.index8(ray.oct_inv4) & 0x1f1f_1f1f_1f1f_1f1f;
        let widen = |x: u64| _mm256_cvtepu8_epi32(_mm_cvtsi64_si128(x as i64));
        let bits = _mm256_and_si256(_mm256_sllv_epi32(widen(self.child_bits8), widen(index8)), hit);
        let x = _mm_or_si128(_mm256_castsi256_si128(bits), _mm256_extracti128_si256::<1>(bits));
        let x = _mm_or_si128(x, _mm_shuffle_epi32::<0b01_00_11_10>(x));
        let x = _mm_or_si128(x, _mm_shuffle_epi32::<0b10_11_00_01>(x));
        let mut entry = [0f32; 8];
        _mm256_storeu_ps(entry.as_mut_ptr(), tmin);
        (_mm_cvtsi128_si32(x) as u32, entry)
    }

    /// Each child's place in the hit mask for a ray of octant code `oct_inv4`: obvhs'
    /// `get_child_and_index_bits` step that depends on the ray.
    #[inline(always)]
    fn index8(&self, oct_inv4: u32) -> u64 {
        self.index8 ^ ((oct_inv4 as u64 | (oct_inv4 as u64) << 32) & self.inner8)
    }

    /// The same, one child at a time: the reference the SIMD test is held to, and the test where
    /// AVX2 is missing.
    pub fn intersect_scalar(&self, ray: &NodeRay) -> (u32, [f32; 8]) {
        mask_and_entry(self.child_bits8, self.index8(ray.oct_inv4), |slot| self.slot_interval(slot, ray))
    }

    /// The part of the ray inside child `slot`'s box, as the SIMD test computes it lane by lane
    /// (the child is hit when the first is at most the second).
    fn slot_interval(&self, slot: usize, ray: &NodeRay) -> (f32, f32) {
        let t = |axis: usize, far: bool| {
            let side = ray.enters_upper(axis) != far;
            let inv = if far { ray.inv_far[axis] } else { ray.inv[axis] };
            (self.planes[axis][side as usize][slot] - ray.origin[axis]) * inv
        };
        // The SIMD operand order, which decides what a NaN does.
        let tmin = simd_max(simd_max(t(0, false), t(1, false)), simd_max(t(2, false), ray.tmin));
        let tmax = simd_min(simd_min(t(0, true), t(1, true)), simd_min(t(2, true), ray.tmax));
        (tmin, tmax)
    }
}

/// By [`NodeRay::negative`]: the byte offsets in [`WideNode::planes`] of each axis's near and far
/// rows, `[near x, far x, near y, far y, near z, far z]` (`planes[axis][side]` lies at
/// `64·axis + 32·side`; the near side is the upper one where the axis is negative).
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
const PLANE_ROWS: [[usize; 6]; 8] = {
    let mut table = [[0usize; 6]; 8];
    let mut negative = 0;
    while negative < 8 {
        let mut axis = 0;
        while axis < 3 {
            let upper = (negative >> axis) & 1;
            table[negative][2 * axis] = 64 * axis + 32 * upper;
            table[negative][2 * axis + 1] = 64 * axis + 32 * (1 - upper);
            axis += 1;
        }
        negative += 1;
    }
    table
};

/// The largest f32 ≤ x.
fn round_down(x: f64) -> f32 {
    let f = x as f32;
    if f as f64 > x {
        f.next_down()
    } else {
        f
    }
}

/// The smallest f32 ≥ x.
fn round_up(x: f64) -> f32 {
    let f = x as f32;
    if (f as f64) < x {
        f.next_up()
    } else {
        f
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3A;

    /// On every node of a real CWBVH and thousands of random rays: the SIMD test equals the
    /// one-child-at-a-time reference bit for bit (mask and entry distances of the hit children),
    /// and every child the compressed test (obvhs' boxes) hits, the decompressed boxes hit too.
    #[test]
    fn simd_equals_reference_and_contains_the_compressed_boxes() {
        let bvh = crate::testing::icosphere_cwbvh(4, |v| v, true);
        let wide: Vec<WideNode> = bvh.nodes.iter().map(WideNode::from_compressed).collect();
        let (mut checked, mut hits) = (0usize, 0usize);
        for i in 0..3000u64 {
            let Some(theirs) = crate::testing::node_test_ray(i) else { continue };
            let ray = NodeRay::new(theirs.origin, theirs.direction, theirs.tmax);
            for (n, w) in bvh.nodes.iter().zip(&wide) {
                let (mask, entry) = w.intersect(&ray);
                let (mask_ref, entry_ref) = w.intersect_scalar(&ray);
                assert_eq!(mask, mask_ref, "ray {i}");
                assert_eq!(entry.map(f32::to_bits), entry_ref.map(f32::to_bits), "ray {i}");
                let compressed = crate::cwbvh_node::intersect(n, &ray);
                assert_eq!(compressed & !mask, 0, "ray {i}: a child the compressed box test hits was missed");
                checked += 1;
                hits += (mask != 0) as usize;
            }
        }
        assert!(checked > 100_000 && hits > 10_000, "{checked} node tests, {hits} with hits");
    }

    /// The eight-at-once bundle test equals the one-box test on every child of every node, for
    /// bundles that cull some children and keep others.
    #[test]
    fn bundle_mask_is_the_one_box_test_on_each_child() {
        let bvh = crate::testing::icosphere_cwbvh(3, |v| v, true);
        let wide: Vec<WideNode> = bvh.nodes.iter().map(WideNode::from_compressed).collect();
        let u = crate::sampler::hash_unit;
        let (mut kept, mut culled) = (0, 0);
        for i in 0..200u64 {
            let o = [0, 1, 2].map(|a| u(32 * i + a) * 4.0 - 2.0);
            let aim = [0, 1, 2].map(|a| u(32 * i + 3 + a) * 2.0 - 1.0 - o[a as usize]);
            let dirs: Vec<[f32; 3]> =
                (0..8u64).map(|k| [0, 1, 2].map(|a| aim[a as usize] + 0.05 * u(32 * i + 6 + 3 * k + a))).collect();
            let dirs: Vec<crate::math::Vec3> = dirs.into_iter().map(crate::math::Vec3::from).collect();
            let Some(b) = RayBundle::new(crate::math::Vec3::from(o), &dirs) else { continue };
            for w in &wide {
                let mask = w.bundle_mask(&b);
                assert_eq!(mask, w.bundle_mask_scalar(&b), "bundle {i}");
                for slot in 0..8 {
                    let want = w.child_box(slot).is_some_and(|(lo, hi)| b.may_enter(lo, hi));
                    assert_eq!(mask >> slot & 1 == 1, want, "bundle {i}, slot {slot}");
                    kept += want as usize;
                    culled += (!want && w.child_box(slot).is_some()) as usize;
                }
            }
        }
        assert!(kept > 1000 && culled > 1000, "{kept} kept, {culled} culled");
    }

    /// Far from the world origin, with rays grazing the boxes' faces, every child the ray truly
    /// crosses (slab intervals in f64 from the same planes) is hit: rounding may widen a box,
    /// never lose it. The one-FMA form `plane·1/d − o·1/d` fails this (370 of 17 605 lost).
    #[test]
    fn boxes_far_from_the_origin_are_never_lost_to_rounding() {
        let bvh = crate::testing::icosphere_cwbvh(3, |v| v * 3.0 + Vec3A::new(5000.0, -3000.0, 7000.0), false);
        let wide: Vec<WideNode> = bvh.nodes.iter().map(WideNode::from_compressed).collect();
        let u = crate::sampler::hash_unit;
        let (mut crossings, mut lost) = (0usize, 0usize);
        for i in 0..20_000u64 {
            let w = &wide[(i as usize * 7) % wide.len()];
            let slot = (i % 8) as usize;
            if w.planes[0][0][slot] > w.planes[0][1][slot] {
                continue; // an empty slot
            }
            // Aim at a point on one face of the child's box, nearly parallel to that face.
            let axis = (i / 8 % 3) as usize;
            let mut target = Vec3A::ZERO;
            for a in 0..3 {
                let (lo, hi) = (w.planes[a][0][slot], w.planes[a][1][slot]);
                target[a] = if a == axis {
                    if i % 2 == 0 {
                        lo
                    } else {
                        hi
                    }
                } else {
                    lo + (hi - lo) * u(4 * i + a as u64)
                };
            }
            let mut d = Vec3A::new(u(4 * i + 3) - 0.5, u(4 * i + 5) - 0.5, u(4 * i + 6) - 0.5).normalize();
            d[axis] = (0.002 + 0.01 * u(4 * i + 7)) * if i % 4 < 2 { 1.0 } else { -1.0 };
            let d = d.normalize();
            if d.abs().min_element() <= 1e-3 {
                continue; // keep clear of obvhs' capped inverse (safe_inverse)
            }
            let ray = NodeRay::new(target - d * (2.0 + 10.0 * u(4 * i + 8)), d, f32::INFINITY);
            let (mut lo_t, mut hi_t) = (crate::cwbvh_node::NODE_TMIN as f64, f64::INFINITY);
            for a in 0..3 {
                let (p0, p1) = (w.planes[a][0][slot] as f64, w.planes[a][1][slot] as f64);
                let (o, dd) = (ray.origin[a] as f64, d[a] as f64);
                let (t0, t1) = ((p0 - o) / dd, (p1 - o) / dd);
                lo_t = lo_t.max(t0.min(t1));
                hi_t = hi_t.min(t0.max(t1));
            }
            if lo_t <= hi_t {
                crossings += 1;
                let (tmin, tmax) = w.slot_interval(slot, &ray);
                lost += (tmin > tmax) as usize;
            }
        }
        assert!(crossings > 5000, "{crossings} crossings");
        assert_eq!(lost, 0, "{lost} of {crossings} boxes the rays cross were lost");
    }

    #[test]
    fn outward_rounding_brackets_the_exact_value() {
        for x in [0.1f64, -0.1, 1.0 / 3.0, -7.000000000000001, 1e-30, 0.0, 3.0e38] {
            assert!((round_down(x) as f64) <= x && (round_up(x) as f64) >= x, "{x}");
            assert!(round_up(x) as f64 - round_down(x) as f64 <= (x.abs() * 2.4e-7).max(1e-44), "{x}");
        }
    }
}
