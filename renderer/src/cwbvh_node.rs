//! The ray–node test of a compressed wide BVH (Ylitie, Karras & Laine 2017, "Efficient Incoherent
//! Ray Traversal on GPUs Through Compressed Wide BVHs", §3.1 and §4) on all eight children in one
//! AVX2 instruction stream.
//!
//! `obvhs` tests a node as two groups of four children with SSE, widening each quantised byte to
//! a float one at a time (`_mm_set_ps` of four loads), then builds the hit mask child by child.
//! Here the six child-plane byte arrays are widened eight at a time (`vpmovzxbd` + `vcvtdq2ps`)
//! and the hit mask — each hit child's bits shifted to its traversal slot — is made with one
//! variable shift (`vpsllvd`) and an OR across lanes.
//!
//! The arithmetic is obvhs' own, operation for operation (multiply then add, no fused
//! multiply-add; the same max/min operand order, which decides what a NaN does), but for the
//! lower bound on a child's entry distance: obvhs clamps it to 10⁻⁴ (its `EPSILON`), which
//! drops every child the ray leaves before t = 10⁻⁴, an absolute distance in scene units; here
//! it is the ray's [`NodeRay::tmin`], 0 ([`NODE_TMIN`]) but where `convex_solid` raises it;
//! and the near plane on an axis is chosen by the sign of the inverse
//! direction, not by obvhs' `d < 0`, which for a component of −0.0 (safe inverse −1/ε) swapped
//! the planes and missed every box. So the hit masks are obvhs' (`CwBvhNode::intersect_ray`)
//! plus the children that end within 10⁻⁴ of the origin (and, for −0.0, the boxes it missed); a
//! test compares the two on every node a set of random rays visits, and holds the SIMD test to a
//! scalar reference ([`intersect_scalar`]).

use crate::node_ray::NodeRay;
use obvhs::cwbvh::node::CwBvhNode;

/// The default lower bound on a child's entry distance ([`NodeRay::tmin`], which a ray inside a
/// closed convex glass solid raises: `convex_solid`): 0, the ray's own start (the renderer offsets
/// origins off surfaces, `math::offset_ray_origin`, so a surface behind the origin is never
/// hit). obvhs uses 10⁻⁴ (`cwbvh::node::EPSILON`); with it a ray leaving a wall within 10⁻⁴ of
/// a corner missed the neighbouring wall and escaped the room (9 of 300 000 rays off the Cornell
/// box's surfaces; in a closed room a millimetre across, all 2 000 rays toward a near corner, and
/// the sky outside showed in 574 of 576 pixels: `renderer/tests/scale.rs`).
pub(crate) const NODE_TMIN: f32 = 0.0;

/// Hit mask of `node`'s children for `ray` (the format `obvhs::traverse!` expects: leaf children's
/// primitive bits in the low 24 bits, inner children's bits in the high 8 at their octant slot).
#[inline(always)]
pub fn intersect(node: &CwBvhNode, ray: &NodeRay) -> u32 {
    intersect_entry(node, ray).0
}

/// [`intersect`] and each child's entry distance (lane = child slot; meaningful for the children
/// hit): the near end of the ray's overlap with the child's box, no less than obvhs' lower bound.
/// A closest-hit traversal keeps it with a child it defers, and skips the child if the ray has
/// meanwhile been cut shorter than that.
#[inline(always)]
pub fn intersect_entry(node: &CwBvhNode, ray: &NodeRay) -> (u32, [f32; 8]) {
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    // SAFETY: AVX2 is enabled at compile time (the cfg above); every load reads 8 bytes of an
    // `[u8; 8]` field of `node`.
    unsafe {
        intersect_avx2(node, ray)
    }
    #[cfg(not(all(target_arch = "x86_64", target_feature = "avx2")))]
    {
        intersect_scalar(node, ray)
    }
}

/// [`intersect_entry`] one child at a time, in the SIMD test's operations and operand order: the
/// reference that test is held to, and the test where AVX2 is missing.
pub fn intersect_scalar(node: &CwBvhNode, ray: &NodeRay) -> (u32, [f32; 8]) {
    let (child_bits8, bit_index8) = node.get_child_and_index_bits(ray.oct_inv4);
    let intervals = slot_intervals(node, ray);
    mask_and_entry(child_bits8, bit_index8, |slot| intervals[slot])
}

/// A scalar node test's answer (hit mask, entry distances by slot) from each child's interval
/// along the ray, `interval(slot)` (hit when the first is at most the second), and the node's
/// per-child bits and their places in the mask (`CwBvhNode::get_child_and_index_bits`).
pub(crate) fn mask_and_entry(child_bits8: u64, index8: u64, interval: impl Fn(usize) -> (f32, f32)) -> (u32, [f32; 8]) {
    let (mut mask, mut entry) = (0u32, [0f32; 8]);
    for (slot, e) in entry.iter_mut().enumerate() {
        let (tmin, tmax) = interval(slot);
        *e = tmin;
        if tmin <= tmax {
            mask |= child_bits(child_bits8, index8, slot);
        }
    }
    (mask, entry)
}

/// Child `slot`'s bits in a node's hit mask: its bits (a leaf's unary primitive count, an inner
/// child's 1) shifted to its place.
pub(crate) fn child_bits(child_bits8: u64, index8: u64, slot: usize) -> u32 {
    let byte = |x: u64| ((x >> (8 * slot)) & 0xff) as u32;
    byte(child_bits8) << byte(index8)
}

/// The part of the ray inside each child's box, by slot, as the SIMD test computes it lane by
/// lane (a child is hit when the first is at most the second).
fn slot_intervals(node: &CwBvhNode, ray: &NodeRay) -> [(f32, f32); 8] {
    let adj_dir = node.compute_extent() * ray.inv;
    let adj_org = (glam::Vec3A::from(node.p) - ray.origin) * ray.inv;
    let planes = [
        (&node.child_min_x, &node.child_max_x),
        (&node.child_min_y, &node.child_max_y),
        (&node.child_min_z, &node.child_max_z),
    ];
    std::array::from_fn(|slot| {
        let t = |axis: usize, far: bool| {
            let (lo, hi) = planes[axis];
            let upper = ray.enters_upper(axis) != far;
            let q = if upper { hi[slot] } else { lo[slot] } as f32;
            q * adj_dir[axis] + adj_org[axis]
        };
        // The SIMD operand order, which decides what a NaN does.
        let tmin = simd_max(simd_max(t(0, false), simd_max(t(1, false), t(2, false))), ray.tmin);
        let tmax = simd_min(simd_min(t(0, true), simd_min(t(1, true), t(2, true))), ray.tmax);
        (tmin, tmax)
    })
}

/// `_mm256_max_ps(a, b)` on one lane: b when either is NaN.
#[inline(always)]
pub(crate) fn simd_max(a: f32, b: f32) -> f32 {
    if a > b {
        a
    } else {
        b
    }
}

/// `_mm256_min_ps(a, b)` on one lane: b when either is NaN.
#[inline(always)]
pub(crate) fn simd_min(a: f32, b: f32) -> f32 {
    if a < b {
        a
    } else {
        b
    }
}

#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[inline(always)]
unsafe fn intersect_avx2(node: &CwBvhNode, ray: &NodeRay) -> (u32, [f32; 8]) {
    use glam::Vec3A;
    use std::arch::x86_64::*;

    // The ray in the node's quantised frame: child plane q (a byte) lies at t = q·adj_dir + adj_org.
    let adj_dir = node.compute_extent() * ray.inv;
    let adj_org = (Vec3A::from(node.p) - ray.origin) * ray.inv;
    // Eight plane bytes as eight floats.
    let q = |b: &[u8; 8]| _mm256_cvtepi32_ps(_mm256_cvtepu8_epi32(_mm_loadl_epi64(b.as_ptr() as *const __m128i)));
    // `negative`: the inverse direction's sign (a direction of −0.0 has a negative safe inverse,
    // so enters through the upper plane; obvhs' `d < 0` misses every box for it).
    let slab = |lo: &[u8; 8], hi: &[u8; 8], negative: bool, dir: f32, org: f32| {
        let (near, far) = if negative { (hi, lo) } else { (lo, hi) };
        let (d, o) = (_mm256_set1_ps(dir), _mm256_set1_ps(org));
        (_mm256_add_ps(_mm256_mul_ps(q(near), d), o), _mm256_add_ps(_mm256_mul_ps(q(far), d), o))
    };
    let (tmin_x, tmax_x) = slab(&node.child_min_x, &node.child_max_x, ray.enters_upper(0), adj_dir.x, adj_org.x);
    let (tmin_y, tmax_y) = slab(&node.child_min_y, &node.child_max_y, ray.enters_upper(1), adj_dir.y, adj_org.y);
    let (tmin_z, tmax_z) = slab(&node.child_min_z, &node.child_max_z, ray.enters_upper(2), adj_dir.z, adj_org.z);
    let tmin = _mm256_max_ps(tmin_x, _mm256_max_ps(tmin_y, tmin_z));
    let tmax = _mm256_min_ps(tmax_x, _mm256_min_ps(tmax_y, tmax_z));
    let tmin = _mm256_max_ps(tmin, _mm256_set1_ps(ray.tmin));
    let tmax = _mm256_min_ps(tmax, _mm256_set1_ps(ray.tmax));
    let hit = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_LE_OQ>(tmin, tmax));

    // Per child: its bits (leaf: unary primitive count; inner: 1) shifted to its slot, kept where hit.
    let (child_bits8, bit_index8) = node.get_child_and_index_bits(ray.oct_inv4);
    let widen = |x: u64| _mm256_cvtepu8_epi32(_mm_cvtsi64_si128(x as i64));
    // The shifts are below 32; masking says so to LLVM, which else guards `vpsllvd` (as in
    // `WideNode::intersect`).
    let bit_index8 = bit_index8 & 0x1f1f_1f1f_1f1f_1f1f;
    let bits = _mm256_and_si256(_mm256_sllv_epi32(widen(child_bits8), widen(bit_index8)), hit);
    // OR across the eight lanes.
    let x = _mm_or_si128(_mm256_castsi256_si128(bits), _mm256_extracti128_si256::<1>(bits));
    let x = _mm_or_si128(x, _mm_shuffle_epi32::<0b01_00_11_10>(x));
    let x = _mm_or_si128(x, _mm_shuffle_epi32::<0b10_11_00_01>(x));
    let mut entry = [0f32; 8];
    _mm256_storeu_ps(entry.as_mut_ptr(), tmin);
    (_mm_cvtsi128_si32(x) as u32, entry)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// For a few thousand random rays, every node of a real CWBVH (those the ray hits and those it
    /// misses) gives the scalar reference's hit mask and entry distances, and obvhs' own mask
    /// but for children the ray leaves before obvhs' 10⁻⁴ (which only obvhs drops); the rays
    /// include some that start a hair off a child's box, so that case is seen.
    #[test]
    fn hit_masks_equal_obvhs_on_every_visited_node() {
        // A second, offset and flattened shell so nodes have mixed leaf and inner children.
        let bvh = crate::testing::icosphere_cwbvh(4, |v| v, true);
        let (mut nodes_checked, mut hits, mut near) = (0usize, 0usize, 0usize);
        for i in 0..4000u64 {
            let Some(mut obvhs_ray) = crate::testing::node_test_ray(i) else { continue };
            let mut ray = NodeRay::new(obvhs_ray.origin, obvhs_ray.direction, obvhs_ray.tmax);
            if i % 4 == 0 {
                // Moved to 5·10⁻⁵ before where it leaves the first child box it crosses (of
                // some node): that child ends before obvhs' 10⁻⁴.
                let crossed = (0..bvh.nodes.len()).find_map(|n| {
                    let intervals = slot_intervals(&bvh.nodes[(n + i as usize) % bvh.nodes.len()], &ray);
                    intervals.into_iter().find(|&(t0, t1)| t0 <= t1 && t1.is_finite() && t1 > 1e-3).map(|(_, t1)| t1)
                });
                if let Some(t1) = crossed {
                    let origin = obvhs_ray.origin + obvhs_ray.direction * (t1 - 5e-5);
                    obvhs_ray = obvhs::ray::Ray::new(origin, obvhs_ray.direction, 0.0, obvhs_ray.tmax);
                    ray = NodeRay::new(origin, obvhs_ray.direction, obvhs_ray.tmax);
                }
            }
            let oct = bvh.new_traversal(obvhs_ray.direction).oct_inv4;
            // Every node, hit or not (not just those a closest-hit traversal would reach).
            for (n, node) in bvh.nodes.iter().enumerate() {
                let (ours, entry) = intersect_entry(node, &ray);
                let (reference, ref_entry) = intersect_scalar(node, &ray);
                let intervals = slot_intervals(node, &ray);
                assert_eq!(ours, reference, "ray {i} node {n}: SIMD against the scalar reference");
                let bits = |e: [f32; 8]| e.map(f32::to_bits);
                // Entry distances only matter for hit children; compare those.
                for (slot, &(t0, t1)) in intervals.iter().enumerate() {
                    if t0 <= t1 {
                        assert_eq!(bits(entry)[slot], bits(ref_entry)[slot], "ray {i} node {n} slot {slot}");
                    }
                }
                let theirs = node.intersect_ray(&obvhs_ray, oct);
                assert_eq!(theirs & !ours, 0, "ray {i} node {n}: obvhs hits a child we miss");
                if ours != theirs {
                    // Every child only we hit ends before obvhs' 10⁻⁴.
                    let (child_bits8, bit_index8) = node.get_child_and_index_bits(oct);
                    for (slot, &(_, t1)) in intervals.iter().enumerate() {
                        if child_bits(child_bits8, bit_index8, slot) & ours & !theirs != 0 {
                            assert!(t1 < 1e-4, "ray {i} node {n} slot {slot}: ends at {t1}");
                        }
                    }
                    near += 1;
                }
                nodes_checked += 1;
                hits += (ours != 0) as usize;
            }
        }
        eprintln!("{nodes_checked} nodes, {hits} with hits, {near} with children only we hit");
        assert!(near > 0, "no ray started near enough to a child's far plane to tell the two apart");
        assert!(nodes_checked > 100_000 && hits > 10_000, "{nodes_checked} nodes, {hits} with hits");
    }
}
