//! A ray prepared once for the BVH node tests ([`crate::wide_node`], [`crate::cwbvh_node`]): the
//! inverse direction and everything the tests would otherwise work out again at every node.
//!
//! Why its own type rather than obvhs' `Ray`: the walks need the far-plane inverse, the
//! inverse's signs and obvhs' octant code too, which each walk derived again from the direction
//! (three compare-and-select chains). Here one sign mask gives them all, and the signs are the
//! inverse's: choosing planes by the direction's `d < 0` missed every box for a −0.0 component.
//! (On its own this saved 4 of ~605 instructions a glass closest-hit query; the rest of that
//! round's setup cut, to 564, is in `accel.rs`.)

use glam::Vec3A;

#[derive(Clone, Copy, Debug)]
pub struct NodeRay {
    pub origin: Vec3A,
    /// obvhs' safe inverse of the direction, bit for bit (`obvhs::ray::safe_inverse`): `1/d`, or
    /// `±1/ε` (the direction's sign) where `|d| ≤ ε`, so no lane is infinite.
    pub inv: Vec3A,
    /// The inverse for far-plane distances, `inv · (1 + 4γ₃)` (see [`far_inverse`]).
    pub inv_far: Vec3A,
    /// Where the ray ends; the closest-hit walk shortens it.
    pub tmax: f32,
    /// Where the node tests start: a box the ray leaves before this distance is not entered.
    /// `cwbvh_node::NODE_TMIN` (0) but for a ray known to meet nothing sooner (one
    /// inside a closed convex glass solid: `crate::convex_solid`).
    pub tmin: f32,
    /// Bit a set when `inv[a]` is negative: the ray enters a box through its upper plane on that
    /// axis. The inverse's sign, which a direction of −0.0 (inverse −1/ε) shares; a test of
    /// `d < 0` is false there, swapped the planes and missed every box.
    pub negative: u32,
    /// obvhs' octant code (`CwBvh::new_traversal`): in every byte, bit 2, 1, 0 set where x, y, z
    /// is not [`Self::negative`]. XORed with a child's slot it gives the child's traversal
    /// priority (the node test's hit-mask bit).
    pub oct_inv4: u32,
}

impl NodeRay {
    /// The ray `origin + t·direction`, `t < tmax`; `direction` need not be normalised.
    #[inline(always)]
    pub fn new(origin: Vec3A, direction: Vec3A, tmax: f32) -> Self {
        let inv = safe_inverse(direction);
        let negative = inv.is_negative_bitmask() & 7;
        NodeRay {
            origin,
            inv,
            inv_far: far_inverse(inv),
            tmax,
            tmin: crate::cwbvh_node::NODE_TMIN,
            negative,
            oct_inv4: OCTANT[negative as usize],
        }
    }

    /// Whether the ray enters boxes through their upper plane on `axis`.
    #[inline(always)]
    pub fn enters_upper(&self, axis: usize) -> bool {
        self.negative & (1 << axis) != 0
    }
}

/// [`NodeRay::oct_inv4`] by [`NodeRay::negative`]: bit 2 − a of each byte set where axis a is not
/// negative.
const OCTANT: [u32; 8] = {
    let mut table = [0u32; 8];
    let mut negative = 0;
    while negative < 8 {
        let positive = !negative & 7;
        let octant = ((positive & 1) << 2) | (positive & 2) | ((positive >> 2) & 1);
        table[negative] = octant as u32 * 0x0101_0101;
        negative += 1;
    }
    table
};

/// obvhs' `safe_inverse` on every lane: `1/d`, or `signum(d)/ε` (exactly ±2²³) where `|d| ≤ ε`.
#[inline(always)]
fn safe_inverse(d: Vec3A) -> Vec3A {
    let small = d.abs().cmple(Vec3A::splat(f32::EPSILON));
    Vec3A::select(small, Vec3A::ONE.copysign(d) / f32::EPSILON, Vec3A::ONE / d)
}

/// The inverse direction for far-plane distances: `1/d · (1 + 4γ₃)`, γ₃ = 3u/(1 − 3u) with u the
/// unit roundoff 2⁻²⁴ (pbrt-v4 §6.8.1 and `Bounds3::IntersectP`): rounding can then only widen a
/// box's interval, never lose a box the ray touches.
#[inline(always)]
fn far_inverse(inv: Vec3A) -> Vec3A {
    const U: f32 = f32::EPSILON * 0.5;
    const GAMMA3: f32 = 3.0 * U / (1.0 - 3.0 * U);
    inv * (1.0 + 4.0 * GAMMA3)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The inverse is obvhs' bit for bit (huge, tiny, ±0 and ±ε components), and the signs and
    /// the octant code follow the inverse's sign, −0.0 counted negative.
    #[test]
    fn inverse_signs_and_octant_follow_obvhs() {
        let values = [1.0f32, -1.0, 0.0, -0.0, f32::EPSILON, -f32::EPSILON, 1.5e-7, -3e-8, 1e30, -2.5e-30, 0.37];
        for &x in &values {
            for &y in &values {
                for &z in &values {
                    let d = Vec3A::new(x, y, z);
                    let ray = NodeRay::new(Vec3A::ZERO, d, 1.0);
                    let theirs = obvhs::ray::Ray::new(Vec3A::ZERO, d, 0.0, 1.0);
                    assert_eq!(
                        ray.inv.to_array().map(f32::to_bits),
                        theirs.inv_direction.to_array().map(f32::to_bits),
                        "{d:?}"
                    );
                    for a in 0..3 {
                        assert_eq!(ray.enters_upper(a), d[a].is_sign_negative(), "{d:?} axis {a}");
                        assert_eq!(ray.enters_upper(a), ray.inv[a] < 0.0, "{d:?} axis {a}");
                    }
                    // obvhs' code where no component is −0.0 (there it tests d < 0).
                    if !d.to_array().iter().any(|c| *c == 0.0 && c.is_sign_negative()) {
                        let bvh = obvhs::cwbvh::CwBvh::default();
                        assert_eq!(ray.oct_inv4, bvh.new_traversal(d).oct_inv4, "{d:?}");
                    }
                }
            }
        }
    }
}
