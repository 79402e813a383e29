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
//! multiply-add; the same max/min operand order, which decides what a NaN does), so the hit
//! masks — and so every image — are bit for bit those of `CwBvhNode::intersect_ray`; a test
//! compares the two on every node a set of random rays visits.

use obvhs::cwbvh::node::CwBvhNode;
use obvhs::ray::Ray;

/// obvhs' lower bound on a child's entry distance (`cwbvh::node::EPSILON`, crate-private there).
const NODE_TMIN: f32 = 0.0001;

/// Hit mask of `node`'s children for `ray` (the format `obvhs::traverse!` expects: leaf children's
/// primitive bits in the low 24 bits, inner children's bits in the high 8 at their octant slot).
#[inline(always)]
pub fn intersect(node: &CwBvhNode, ray: &Ray, oct_inv4: u32) -> u32 {
    intersect_entry(node, ray, oct_inv4).0
}

/// [`intersect`] and each child's entry distance (lane = child slot; meaningful for the children
/// hit): the near end of the ray's overlap with the child's box, no less than obvhs' lower bound.
/// A closest-hit traversal keeps it with a child it defers, and skips the child if the ray has
/// meanwhile been cut shorter than that.
#[inline(always)]
pub fn intersect_entry(node: &CwBvhNode, ray: &Ray, oct_inv4: u32) -> (u32, [f32; 8]) {
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    // SAFETY: AVX2 is enabled at compile time (the cfg above); every load reads 8 bytes of an
    // `[u8; 8]` field of `node`.
    unsafe {
        intersect_avx2(node, ray, oct_inv4)
    }
    #[cfg(not(all(target_arch = "x86_64", target_feature = "avx2")))]
    {
        // Entry distance 0: a deferred child is never skipped (the result is the same).
        (node.intersect_ray(ray, oct_inv4), [0.0; 8])
    }
}

#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[inline(always)]
unsafe fn intersect_avx2(node: &CwBvhNode, ray: &Ray, oct_inv4: u32) -> (u32, [f32; 8]) {
    use glam::Vec3A;
    use std::arch::x86_64::*;

    // The ray in the node's quantised frame: child plane q (a byte) lies at t = q·adj_dir + adj_org.
    let adj_dir = node.compute_extent() * ray.inv_direction;
    let adj_org = (Vec3A::from(node.p) - ray.origin) * ray.inv_direction;
    // Eight plane bytes as eight floats.
    let q = |b: &[u8; 8]| _mm256_cvtepi32_ps(_mm256_cvtepu8_epi32(_mm_loadl_epi64(b.as_ptr() as *const __m128i)));
    let slab = |lo: &[u8; 8], hi: &[u8; 8], negative: bool, dir: f32, org: f32| {
        let (near, far) = if negative { (hi, lo) } else { (lo, hi) };
        let (d, o) = (_mm256_set1_ps(dir), _mm256_set1_ps(org));
        (_mm256_add_ps(_mm256_mul_ps(q(near), d), o), _mm256_add_ps(_mm256_mul_ps(q(far), d), o))
    };
    let (tmin_x, tmax_x) = slab(&node.child_min_x, &node.child_max_x, ray.direction.x < 0.0, adj_dir.x, adj_org.x);
    let (tmin_y, tmax_y) = slab(&node.child_min_y, &node.child_max_y, ray.direction.y < 0.0, adj_dir.y, adj_org.y);
    let (tmin_z, tmax_z) = slab(&node.child_min_z, &node.child_max_z, ray.direction.z < 0.0, adj_dir.z, adj_org.z);
    let tmin = _mm256_max_ps(tmin_x, _mm256_max_ps(tmin_y, tmin_z));
    let tmax = _mm256_min_ps(tmax_x, _mm256_min_ps(tmax_y, tmax_z));
    let tmin = _mm256_max_ps(tmin, _mm256_set1_ps(NODE_TMIN));
    let tmax = _mm256_min_ps(tmax, _mm256_set1_ps(ray.tmax));
    let hit = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_LE_OQ>(tmin, tmax));

    // Per child: its bits (leaf: unary primitive count; inner: 1) shifted to its slot, kept where hit.
    let (child_bits8, bit_index8) = node.get_child_and_index_bits(oct_inv4);
    let widen = |x: u64| _mm256_cvtepu8_epi32(_mm_cvtsi64_si128(x as i64));
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
    /// misses) gives the same hit mask as obvhs' own test.
    #[test]
    fn hit_masks_equal_obvhs_on_every_visited_node() {
        // A second, offset and flattened shell so nodes have mixed leaf and inner children.
        let bvh = crate::testing::icosphere_cwbvh(4, |v| v, true);
        let (mut nodes_checked, mut hits) = (0usize, 0usize);
        for i in 0..4000u64 {
            let Some(ray) = crate::testing::node_test_ray(i) else { continue };
            let oct = bvh.new_traversal(ray.direction).oct_inv4;
            // Every node, hit or not (not just those a closest-hit traversal would reach).
            for (n, node) in bvh.nodes.iter().enumerate() {
                let ours = intersect(node, &ray, oct);
                assert_eq!(ours, node.intersect_ray(&ray, oct), "ray {i} node {n}");
                nodes_checked += 1;
                hits += (ours != 0) as usize;
            }
        }
        eprintln!("{nodes_checked} nodes, {hits} with hits");
        assert!(nodes_checked > 100_000 && hits > 10_000, "{nodes_checked} nodes, {hits} with hits");
    }
}
