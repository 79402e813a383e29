//! A bounding-volume hierarchy over lights for many-light sampling: each node bounds its lights'
//! positions, total power and emission directions (a cone), and a light is chosen by walking down the
//! tree, picking a child in proportion to an importance estimate for the shading point (pbrt-v4
//! §12.6.3 `BVHLightSampler` and `LightBounds::Importance`; Conty & Kulla 2018, "Importance Sampling of
//! Many Lights with Adaptive Tree Splitting"). `pmf()` retraces the same walk, so MIS can ask for
//! the probability of any light at any point.

use crate::math::{Vec3, PI};

/// Spatial and directional bounds of one or more lights.
#[derive(Clone, Copy, Debug)]
pub struct LightBounds {
    pub min: Vec3,
    pub max: Vec3,
    /// Emitted power (luminance).
    pub phi: f32,
    /// Emission cone: axis, cos of its spread θo, and cos of the falloff θe beyond it.
    pub w: Vec3,
    pub cos_theta_o: f32,
    pub cos_theta_e: f32,
    pub two_sided: bool,
}

#[inline]
fn safe_sqrt(x: f32) -> f32 {
    x.max(0.0).sqrt()
}

/// a·b with fused multiply-adds, z(y(x)): `(a.z · b.z + (a.y · b.y + a.x · b.x))`, each sum
/// rounded once with its product. [`Family::importance_avx`]'s `dot` is the same three
/// operations (VMULPS, then two VFMADD231PS), so the lanes keep the reference's bits. A fused
/// multiply-add is one IEEE operation, exactly rounded on every x86-64-v3 CPU (and `mul_add`
/// without the instruction), so the determinism rule holds across vendors.
#[inline(always)]
fn dot_fma(a: Vec3, b: Vec3) -> f32 {
    a.z.mul_add(b.z, a.y.mul_add(b.y, a.x * b.x))
}

/// Rotates `v` about the unit axis `k` by `angle` (Rodrigues).
fn rotate(v: Vec3, k: Vec3, angle: f32) -> Vec3 {
    let (s, c) = angle.sin_cos();
    v * c + k.cross(v) * s + k * k.dot(v) * (1.0 - c)
}

impl LightBounds {
    /// Union of two bounds (cones merged as in pbrt-v4 `DirectionCone::Union`).
    pub fn union(a: &LightBounds, b: &LightBounds) -> LightBounds {
        if a.phi == 0.0 {
            return *b;
        }
        if b.phi == 0.0 {
            return *a;
        }
        let (w, cos_theta_o) = {
            let (ta, tb) = (a.cos_theta_o.clamp(-1.0, 1.0).acos(), b.cos_theta_o.clamp(-1.0, 1.0).acos());
            let td = a.w.dot(b.w).clamp(-1.0, 1.0).acos();
            if (td + tb).min(PI) <= ta {
                (a.w, a.cos_theta_o)
            } else if (td + ta).min(PI) <= tb {
                (b.w, b.cos_theta_o)
            } else {
                let to = (ta + td + tb) / 2.0;
                let axis = a.w.cross(b.w);
                if to >= PI || axis.length_squared() < 1e-12 {
                    (a.w, -1.0)
                } else {
                    (rotate(a.w, axis.normalize(), to - ta).normalize(), to.cos())
                }
            }
        };
        LightBounds {
            min: a.min.min(b.min),
            max: a.max.max(b.max),
            phi: a.phi + b.phi,
            w,
            cos_theta_o,
            cos_theta_e: a.cos_theta_e.min(b.cos_theta_e),
            two_sided: a.two_sided || b.two_sided,
        }
    }

    pub fn centroid(&self) -> Vec3 {
        (self.min + self.max) * 0.5
    }

    /// Conservative estimate of the light these bounds can send to `p` (on a surface with normal `n`,
    /// if given): power / distance², reduced by the angle between the cone and `p`.
    ///
    /// pbrt-v4's `LightBounds::Importance`, written for a short chain of dependent operations:
    /// the walk waits on each level's importances before it can pick the next node, so their
    /// latency, not their count, is what a sample costs (`WideNode`). Every sine and cosine of an
    /// angle at `p` is kept multiplied by d = |p − c| (cos θw·d = w·v, sin θw·d = √(d² − (w·v)²),
    /// cos θb·d = √(d² − r²), sin θb·d = r), so none of them waits on d itself: pbrt's chain of
    /// normalising v (a square root, then a division), then √(1 − cos²) (a second square root)
    /// becomes one square root straight from d² and w·v, and the one division, 1/d², runs beside
    /// it. cos θp, a product of two such d-scaled factors, is d² times itself and is scaled back
    /// by that 1/d², which φ · min(1/d², 2/diagonal) (pbrt's d² is max(d², diagonal/2)) uses too.
    /// The comparisons pbrt makes on cosines compare the d-scaled ones: θw ≤ θo (inside the
    /// emission cone) is w·v > cos θo·d, tested squared with signs kept, (w·v)|w·v| > cos θo|cos θo|·d².
    /// Every product that feeds a sum is fused with it (`mul_add`, VFMADD): the dot products,
    /// d² − (w·v)², d² − r² (whose sign is then the inside test), and the angle sums: 13 fewer
    /// operations a family with a normal, 9 without, on the ports sixteen interleaved walks
    /// share (`LightTree::walks`), and each sum rounded once instead of twice.
    pub fn importance(&self, p: Vec3, n: Option<Vec3>) -> f32 {
        let pc = self.centroid();
        let half_diag = (self.max - self.min).length() / 2.0;
        let inv_half_diag = 1.0 / half_diag;
        let v = p - pc;
        let dist2 = dot_fma(v, v);
        // From here on, cos_w, sin_w, cos_b, cos_x, sin_x and cos_i, sin_i are the d-scaled
        // values (cos θw·d and so on); cos_p and the normal's factor are plain cosines again.
        let inv_dist2 = 1.0 / dist2;
        // f32::min returns its other operand for a NaN (as VMINPS its second).
        let phi_d2 = self.phi * inv_dist2.min(inv_half_diag);
        let mut cos_w = dot_fma(self.w, v);
        if self.two_sided {
            cos_w = cos_w.abs();
        }
        let sin_w = safe_sqrt((-cos_w).mul_add(cos_w, dist2));
        // Angle θb subtended by the bounds' bounding sphere (radius r) as seen from p: cos θb·d
        // = √(d² − r²), d² − r² rounded once, so p is inside the sphere exactly when it is ≤ 0.
        let cos_b2 = (-half_diag).mul_add(half_diag, dist2);
        let inside = cos_b2 <= 0.0;
        let cos_b = safe_sqrt(cos_b2);
        let cos_o = self.cos_theta_o;
        let sin_o = safe_sqrt(1.0 - cos_o * cos_o);
        let in_cone = cos_w * cos_w.abs() > cos_o * cos_o.abs() * dist2;
        // θx = max(0, θw − θo), its cosine and sine (d-scaled) where θw > θo.
        let cos_x = cos_w.mul_add(cos_o, sin_w * sin_o);
        let sin_x = sin_w.mul_add(cos_o, -(cos_w * sin_o));
        // cos θp = cos(max(0, θx − θb)): 1 inside the cone or the bounds, or where θx ≤ θb.
        let cos_p =
            if in_cone || inside || cos_x > cos_b { 1.0 } else { cos_x.mul_add(cos_b, sin_x * half_diag) * inv_dist2 };
        if cos_p <= self.cos_theta_e {
            return 0.0;
        }
        let mut importance = phi_d2 * cos_p;
        if let Some(n) = n {
            // cos(max(0, θi − θb)), θi the angle between n (either side) and p − c.
            let cos_i = dot_fma(n, v).abs();
            let sin_i = safe_sqrt((-cos_i).mul_add(cos_i, dist2));
            importance *=
                if inside || cos_i > cos_b { 1.0 } else { cos_i.mul_add(cos_b, sin_i * half_diag) * inv_dist2 };
        }
        if importance.is_finite() {
            importance.max(0.0)
        } else {
            0.0
        }
    }
}

/// The bounds of a wide node's (up to eight) children as the eight lanes of vectors (unused lanes
/// are zero bounds, whose importance is 0), with what `importance` derives from bounds alone
/// (centroid, half diagonal and its reciprocal, sin θo) computed once, by the same operations.
/// [`Family::importance`] runs `LightBounds::importance` on all lanes at once (AVX), operation for
/// operation, so every lane is the one-at-a-time reference's number, bit for bit (a test checks it
/// on random points, normals and bounds): one evaluation per level of the walk.
#[derive(Clone, Copy, Debug, Default)]
#[repr(C, align(32))]
struct Family {
    c: [[f32; 8]; 3],
    w: [[f32; 8]; 3],
    half_diag: [f32; 8],
    inv_half_diag: [f32; 8],
    phi: [f32; 8],
    cos_o: [f32; 8],
    sin_o: [f32; 8],
    cos_e: [f32; 8],
    /// The sign bit (−0.0) in a two-sided lane, 0 in a one-sided one: AND-NOT with it is the
    /// reference's `abs()` of w·v where the bounds are two-sided, in one operation.
    two_sided: [u32; 8],
}

impl Family {
    fn new(lanes: &[LightBounds]) -> Self {
        debug_assert!(lanes.len() <= WIDTH);
        let mut f = Family::default();
        for (l, x) in lanes.iter().enumerate() {
            let c = x.centroid();
            let diag = (x.max - x.min).length();
            for k in 0..3 {
                f.c[k][l] = c[k];
                f.w[k][l] = x.w[k];
            }
            f.half_diag[l] = diag / 2.0;
            f.inv_half_diag[l] = 1.0 / f.half_diag[l];
            f.phi[l] = x.phi;
            f.cos_o[l] = x.cos_theta_o;
            f.sin_o[l] = safe_sqrt(1.0 - x.cos_theta_o * x.cos_theta_o);
            f.cos_e[l] = x.cos_theta_e;
            f.two_sided[l] = if x.two_sided { (-0.0f32).to_bits() } else { 0 };
        }
        f
    }

    /// The importance of every lane's bounds at `p` (normal `n`): see `LightBounds::importance`,
    /// whose steps these are, in the same order.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
    #[inline]
    fn importance(&self, p: Vec3, n: Option<Vec3>) -> [f32; 8] {
        let mut out = [0f32; 8];
        // SAFETY: AVX2 is enabled at compile time; every load reads a 32-byte-aligned [f32; 8],
        // the store writes the eight floats of `out`.
        unsafe { std::arch::x86_64::_mm256_storeu_ps(out.as_mut_ptr(), self.importance_avx(p, n)) };
        out
    }

    #[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
    #[inline(always)]
    unsafe fn importance_avx(&self, p: Vec3, n: Option<Vec3>) -> std::arch::x86_64::__m256 {
        use std::arch::x86_64::*;
        let splat = _mm256_set1_ps;
        let n = n.map(|n| [splat(n.x), splat(n.y), splat(n.z)]);
        importance_lanes(self, [splat(p.x), splat(p.y), splat(p.z)], n)
    }
}

/// Light bounds in the eight lanes of AVX registers, as [`importance_lanes`] reads them, each
/// read where it is used (a family's loads stay memory operands of the arithmetic, as the
/// walks' sixteen interleaved evaluations want): a family's eight children, each lane its own
/// bounds ([`Family`]), or one child in every lane ([`SlotLanes`]).
#[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
trait BoundsLanes {
    /// Field `f` of the bounds, as eight lanes.
    fn lanes(&self, f: fn(&Family) -> &[f32; 8]) -> std::arch::x86_64::__m256;
    /// The sign bit (−0.0) in a two-sided lane, 0 in a one-sided one (as `Family::two_sided`).
    fn two_sided(&self) -> std::arch::x86_64::__m256;
}

#[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
impl BoundsLanes for Family {
    #[inline(always)]
    fn lanes(&self, f: fn(&Family) -> &[f32; 8]) -> std::arch::x86_64::__m256 {
        // SAFETY: AVX is enabled at compile time; every field is a 32-byte-aligned [f32; 8].
        unsafe { std::arch::x86_64::_mm256_load_ps(f(self).as_ptr()) }
    }
    #[inline(always)]
    fn two_sided(&self) -> std::arch::x86_64::__m256 {
        use std::arch::x86_64::*;
        // SAFETY: as above; `two_sided` is a 32-byte-aligned [u32; 8].
        unsafe { _mm256_castsi256_ps(_mm256_load_si256(self.two_sided.as_ptr() as *const __m256i)) }
    }
}

/// One slot of a family in every lane: what [`importance_lanes`] needs to evaluate one light
/// (or node) at eight points, [`LightTree::root_lanes`]'s transposed evaluation.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
struct SlotLanes<'a> {
    family: &'a Family,
    slot: usize,
}

#[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
impl BoundsLanes for SlotLanes<'_> {
    #[inline(always)]
    fn lanes(&self, f: fn(&Family) -> &[f32; 8]) -> std::arch::x86_64::__m256 {
        // SAFETY: AVX is enabled at compile time.
        unsafe { std::arch::x86_64::_mm256_set1_ps(f(self.family)[self.slot]) }
    }
    #[inline(always)]
    fn two_sided(&self) -> std::arch::x86_64::__m256 {
        // SAFETY: as above.
        unsafe { std::arch::x86_64::_mm256_set1_ps(f32::from_bits(self.family.two_sided[self.slot])) }
    }
}

/// The root's choice at eight points ([`LightTree::root_lanes`]), lane for lane: the count of
/// running sums not above u · total (the slot, where below 8) and the slot's share; the lanes
/// with a choice (`ok`) and those past the last slot (`past`), which [`RootLanes::past_choice`]
/// finishes from the importances and totals.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
struct RootLanes {
    below: std::arch::x86_64::__m256i,
    prob: std::arch::x86_64::__m256,
    ok: u32,
    past: u32,
    imp: [std::arch::x86_64::__m256; WIDTH],
    total: std::arch::x86_64::__m256,
}

#[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
impl RootLanes {
    /// `chosen`'s slot and share for lane `k`, one of `past` (whose total is above 0: `past` is
    /// within `ok`), from its importances and total.
    fn past_choice(&self, k: usize) -> Option<(usize, f32)> {
        debug_assert!(self.past & self.ok & (1 << k) != 0);
        let mut lanes = [[0f32; 8]; WIDTH + 1];
        for (row, x) in lanes.iter_mut().zip(self.imp.iter().chain([&self.total])) {
            // SAFETY: AVX is enabled at compile time; an unaligned store of eight lanes.
            unsafe { std::arch::x86_64::_mm256_storeu_ps(row.as_mut_ptr(), *x) };
        }
        last_with_importance(&std::array::from_fn(|s| lanes[s][k]), lanes[WIDTH][k])
    }
}

/// `LightBounds::importance`, lane by lane, of bounds `b` at points `p` (normals `n`): whether
/// the lanes hold eight bounds at one point or one bounds at eight points, every lane takes the
/// reference's steps in its order, so every lane is its number bit for bit
/// (`family_importance_equals_one_at_a_time` checks both forms on random points, normals and
/// bounds).
#[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
#[inline(always)]
unsafe fn importance_lanes(
    b: &impl BoundsLanes,
    p: [std::arch::x86_64::__m256; 3],
    n: Option<[std::arch::x86_64::__m256; 3]>,
) -> std::arch::x86_64::__m256 {
    use std::arch::x86_64::*;
    let splat = _mm256_set1_ps;
    let (zero, one) = (_mm256_setzero_ps(), splat(1.0));
    // safe_sqrt: max(x, 0) first (VMAXPS returns its second operand for a NaN, as f32::max does).
    let safe_sqrt = |x: __m256| _mm256_sqrt_ps(_mm256_max_ps(x, zero));
    let select = |m: __m256, a: __m256, b: __m256| _mm256_blendv_ps(b, a, m);
    // `dot_fma`: z·z + (y·y + x·x), each sum fused with its product.
    let dot = |ax: __m256, ay: __m256, az: __m256, bx: __m256, by: __m256, bz: __m256| {
        _mm256_fmadd_ps(az, bz, _mm256_fmadd_ps(ay, by, _mm256_mul_ps(ax, bx)))
    };
    let gt = |a: __m256, b: __m256| _mm256_cmp_ps::<_CMP_GT_OQ>(a, b);
    let (vx, vy, vz) = (
        _mm256_sub_ps(p[0], b.lanes(|f| &f.c[0])),
        _mm256_sub_ps(p[1], b.lanes(|f| &f.c[1])),
        _mm256_sub_ps(p[2], b.lanes(|f| &f.c[2])),
    );
    let dist2 = dot(vx, vy, vz, vx, vy, vz);
    let half_diag = b.lanes(|f| &f.half_diag);
    let inv_dist2 = _mm256_div_ps(one, dist2);
    let abs = |x: __m256| _mm256_andnot_ps(splat(-0.0), x);
    // VMINPS returns its second operand for a NaN, as f32::min returns the other one.
    let phi_d2 = _mm256_mul_ps(b.lanes(|f| &f.phi), _mm256_min_ps(inv_dist2, b.lanes(|f| &f.inv_half_diag)));
    let cos_w = dot(b.lanes(|f| &f.w[0]), b.lanes(|f| &f.w[1]), b.lanes(|f| &f.w[2]), vx, vy, vz);
    let cos_w = _mm256_andnot_ps(b.two_sided(), cos_w);
    // −(a·b) + c rounded once (VFNMADD) is (−a).mul_add(b, c).
    let sin_w = safe_sqrt(_mm256_fnmadd_ps(cos_w, cos_w, dist2));
    let cos_b2 = _mm256_fnmadd_ps(half_diag, half_diag, dist2);
    let inside = _mm256_cmp_ps::<_CMP_LE_OQ>(cos_b2, zero);
    let cos_b = safe_sqrt(cos_b2);
    let (sin_o, cos_o) = (b.lanes(|f| &f.sin_o), b.lanes(|f| &f.cos_o));
    let in_cone = gt(_mm256_mul_ps(cos_w, abs(cos_w)), _mm256_mul_ps(_mm256_mul_ps(cos_o, abs(cos_o)), dist2));
    let cos_x = _mm256_fmadd_ps(cos_w, cos_o, _mm256_mul_ps(sin_w, sin_o));
    let sin_x = _mm256_fmsub_ps(sin_w, cos_o, _mm256_mul_ps(cos_w, sin_o));
    // cos(max(0, θa − θb)) from d-scaled sines and cosines, 1 where θa ≤ θb or inside.
    let cos_sub = |sa: __m256, ca: __m256, clamped: __m256| {
        let unclamped = _mm256_fmadd_ps(ca, cos_b, _mm256_mul_ps(sa, half_diag));
        select(_mm256_or_ps(clamped, gt(ca, cos_b)), one, _mm256_mul_ps(unclamped, inv_dist2))
    };
    let cos_p = cos_sub(sin_x, cos_x, _mm256_or_ps(in_cone, inside));
    let lit = gt(cos_p, b.lanes(|f| &f.cos_e));
    let mut imp = _mm256_mul_ps(phi_d2, cos_p);
    if let Some(n) = n {
        let cos_i = abs(dot(n[0], n[1], n[2], vx, vy, vz));
        let sin_i = safe_sqrt(_mm256_fnmadd_ps(cos_i, cos_i, dist2));
        imp = _mm256_mul_ps(imp, cos_sub(sin_i, cos_i, inside));
    }
    // `is_finite` then max(·, 0): below +∞ (false for a NaN), and VMAXPS returns its second
    // operand, 0, for a NaN; −∞ is below +∞ and its max with 0 is 0, as the reference's.
    let finite = _mm256_cmp_ps::<_CMP_LT_OQ>(imp, splat(f32::INFINITY));
    _mm256_and_ps(_mm256_and_ps(lit, finite), _mm256_max_ps(imp, zero))
}

/// Children a node of the walked tree holds: one AVX family of eight lanes.
const WIDTH: usize = 8;
/// Marks a child slot that is a light (its index in the low bits), not a node.
const LIGHT: u32 = 1 << 31;
/// Deeper than any tree `build` makes (its binary tree over < 2³¹ lights, split at medians, is
/// at most 32 levels deep, and collapsing only shortens paths); `pmf` keeps one factor per level.
const MAX_DEPTH: usize = 40;
/// Walks [`LightTree::sample_batch`] interleaves (more are taken this many at a time): a
/// path batch's worth (`accel::MAX_BATCH`).
pub const MAX_WALKS: usize = 16;

/// A node of the binary tree `build` splits first, before collapsing it into [`WideNode`]s.
struct BinaryNode {
    bounds: LightBounds,
    /// Interior: index of the first child (the second follows). Leaf: the light index.
    index: u32,
    leaf: bool,
    /// Lights below.
    lights: u32,
}

/// A node of the tree as walked: up to eight children (lights or nodes), whose bounds are the
/// lanes of one family, so choosing among them is one AVX evaluation and one pass over eight
/// numbers. It is the binary tree collapsed three levels at a time (see `collapse`): about
/// a third of the levels, and no chain of divisions per binary level (a profile of
/// `scenes/sphere_light`, 2208 emissive triangles, had the binary walk at 35 % of the render,
/// most of it waiting on `u / p` and `a / (a + b)` one level after another).
#[derive(Clone, Copy, Debug)]
#[repr(C, align(32))]
struct WideNode {
    family: Family,
    /// `LIGHT | light index` or a node index; slots `count..` are unused.
    child: [u32; WIDTH],
    count: u32,
}

pub struct LightTree {
    nodes: Vec<WideNode>,
    /// The children's bounds of each node, for the one-at-a-time reference.
    child_bounds: Vec<[LightBounds; WIDTH]>,
    /// Evaluate children one at a time with `LightBounds::importance` (the reference the family
    /// evaluation is held to, bit for bit); off except in tests.
    scalar_reference: bool,
    /// For each light: its node and slot.
    leaf_of: Vec<(u32, u8)>,
    /// For each node: its parent and slot there (root: u32::MAX).
    parent: Vec<(u32, u8)>,
}

/// The running sums of a node's importances, `running[i]` = imp[0] + … + imp[i], added as a
/// three-step scan (the total is three additions deep, not seven: the walk waits on it at every
/// level). Each sum only adds non-negative terms to the one before, so they never decrease, and
/// a slot of importance 0 repeats the sum before it exactly (x + 0 = x): what `choose` relies on.
/// `choose` and `pmf` both take the total from here, so they see the same probabilities.
#[inline]
fn running_sums(imp: &[f32; WIDTH]) -> [f32; WIDTH] {
    let [x0, x1, x2, x3, x4, x5, x6, x7] = *imp;
    let (s01, s23, s45, s67) = (x0 + x1, x2 + x3, x4 + x5, x6 + x7);
    let s03 = s01 + s23;
    let s46 = s45 + x6;
    [x0, s01, s01 + x2, s03, s03 + x4, s03 + s45, s03 + s46, s03 + (s45 + s67)]
}

/// Picks a slot in proportion to `imp` with `u` ∈ [0, 1): (slot, its probability, `u` rescaled
/// to [0, 1) within the slot's share, so the levels below stay stratified). None when every
/// importance is 0.
///
/// The slot is the first whose running sum exceeds `t = u · total`, found by counting the running
/// sums that do not (they rise with the slot, and a slot of importance 0 never adds to them, so
/// it is never the first to exceed `t`): compares and a count the compiler vectorises, where a loop
/// that stopped at the slot mispredicted its exit once a level (the walk's slot is random). Same
/// slot and numbers as that loop over the same sums, bit for bit (`choose_matches_running_search`).
#[inline]
fn choose(imp: &[f32; WIDTH], u: f32) -> Option<(usize, f32, f32)> {
    let running = running_sums(imp);
    let total = running[WIDTH - 1];
    if total.is_nan() || total <= 0.0 {
        return None;
    }
    let t = u * total;
    let below: usize = running.iter().map(|&r| (!(t < r)) as usize).sum();
    chosen(imp, &running, t, below)
}

/// What `choose` and `choose_avx` return once they have the running sums (total last) and
/// `below`, the count of running sums not above `t = u · total`: that slot, its probability and
/// `u` rescaled within its share.
#[inline(always)]
fn chosen(imp: &[f32; WIDTH], running: &[f32; WIDTH], t: f32, below: usize) -> Option<(usize, f32, f32)> {
    let total = running[WIDTH - 1];
    if below < WIDTH {
        let x = imp[below];
        let before = if below == 0 { 0.0 } else { running[below - 1] };
        return Some((below, x / total, ((t - before) / x).clamp(0.0, 1.0 - f32::EPSILON)));
    }
    let (last, prob) = last_with_importance(imp, total)?;
    Some((last, prob, 1.0 - f32::EPSILON))
}

/// `chosen`'s slot where rounding left t at or past the sum: the last slot that has any
/// importance, and its share of `total`.
#[inline(always)]
fn last_with_importance(imp: &[f32; WIDTH], total: f32) -> Option<(usize, f32)> {
    let last = imp.iter().rposition(|&x| x > 0.0)?;
    Some((last, imp[last] / total))
}

/// `choose` on importances still in an AVX register, as the walk has them: the running sums by
/// three shuffle-and-add steps, each lane the same two numbers added as in `running_sums`
/// ([x0, s01, x2, s23, …], then lanes 2–3 and 6–7 add s01 and s45, then lanes 4–7 add s03; a
/// lane with nothing to add adds +0, which leaves a non-negative sum unchanged), the slot by a
/// compare, a mask and a bit count; the slot's share then comes from `chosen`, as `choose`'s
/// does. Same slot, probability and rescaled `u` as `choose`, bit for bit
/// (`choose_matches_running_search`); what it saves, on the path from one level's node to the
/// next (the slot), is what `choose` compiled to there: the importances stored and reloaded as
/// eight scalars, ten scalar additions and the lane inserts that rebuilt a vector for the compare.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
#[inline(always)]
unsafe fn choose_avx(imp: std::arch::x86_64::__m256, u: f32) -> Option<(usize, f32, f32)> {
    use std::arch::x86_64::*;
    let zero = _mm256_setzero_ps();
    // [x0, x0 + x1, x2, x2 + x3, x4, x4 + x5, x6, x6 + x7]
    let pairs = _mm256_add_ps(imp, _mm256_blend_ps::<0b1010_1010>(zero, _mm256_permute_ps::<0b10_10_00_00>(imp)));
    // Lanes 2–3 add lane 1 (s01), lanes 6–7 add lane 5 (s45).
    let halves = _mm256_add_ps(pairs, _mm256_blend_ps::<0b1100_1100>(zero, _mm256_permute_ps::<0b01_01_00_00>(pairs)));
    // Lanes 4–7 add lane 3 (s03): lane 3 of each half broadcast, the low half's moved up.
    let s03 = _mm256_permute_ps::<0b11_11_11_11>(halves);
    let running = _mm256_add_ps(halves, _mm256_permute2f128_ps::<0x08>(s03, s03));
    let total = _mm_cvtss_f32(_mm_permute_ps::<0b11_11_11_11>(_mm256_extractf128_ps::<1>(running)));
    if total.is_nan() || total <= 0.0 {
        return None;
    }
    let t = u * total;
    // !(t < r) in every lane: NLT, true for a NaN as `choose`'s negation is.
    let not_below = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_NLT_UQ>(_mm256_set1_ps(t), running));
    // The slot's share is off the path to the next node (only the rescaled u waits on it), so
    // the lanes go through memory to the scalar code `choose` ends with.
    let (mut imp_lanes, mut running_lanes) = ([0f32; WIDTH], [0f32; WIDTH]);
    _mm256_storeu_ps(imp_lanes.as_mut_ptr(), imp);
    _mm256_storeu_ps(running_lanes.as_mut_ptr(), running);
    chosen(&imp_lanes, &running_lanes, t, not_below.count_ones() as usize)
}

impl LightTree {
    /// Builds the tree over `lights` (light index = position): a binary tree split at the median
    /// of the longest centroid axis, collapsed into nodes of up to eight children.
    pub fn build(lights: &[LightBounds]) -> Option<Self> {
        if lights.is_empty() || lights.len() >= LIGHT as usize {
            return None;
        }
        let binary = Self::build_binary(lights);
        let mut tree = LightTree {
            nodes: Vec::with_capacity(lights.len() / 4 + 1),
            child_bounds: Vec::with_capacity(lights.len() / 4 + 1),
            scalar_reference: false,
            leaf_of: vec![(0, 0); lights.len()],
            parent: Vec::with_capacity(lights.len() / 4 + 1),
        };
        tree.collapse(&binary, 0, (u32::MAX, 0));
        Some(tree)
    }

    fn build_binary(lights: &[LightBounds]) -> Vec<BinaryNode> {
        let mut nodes = Vec::with_capacity(2 * lights.len());
        let mut idx: Vec<u32> = (0..lights.len() as u32).collect();
        nodes.push(BinaryNode { bounds: lights[0], index: 0, leaf: true, lights: 1 });
        // (node, range in idx)
        let mut work = vec![(0usize, 0usize, lights.len())];
        while let Some((node, lo, hi)) = work.pop() {
            let mut b = lights[idx[lo] as usize];
            for &i in &idx[lo + 1..hi] {
                b = LightBounds::union(&b, &lights[i as usize]);
            }
            if hi - lo == 1 {
                nodes[node] = BinaryNode { bounds: b, index: idx[lo], leaf: true, lights: 1 };
                continue;
            }
            let (mut cmin, mut cmax) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
            for &i in &idx[lo..hi] {
                let c = lights[i as usize].centroid();
                cmin = cmin.min(c);
                cmax = cmax.max(c);
            }
            let ext = cmax - cmin;
            let axis = if ext.x >= ext.y && ext.x >= ext.z {
                0
            } else if ext.y >= ext.z {
                1
            } else {
                2
            };
            let mid = (lo + hi) / 2;
            idx[lo..hi].select_nth_unstable_by(mid - lo, |a, b| {
                lights[*a as usize].centroid()[axis].total_cmp(&lights[*b as usize].centroid()[axis])
            });
            let first = nodes.len();
            for _ in 0..2 {
                nodes.push(BinaryNode { bounds: b, index: 0, leaf: true, lights: 1 });
            }
            nodes[node] = BinaryNode { bounds: b, index: first as u32, leaf: false, lights: (hi - lo) as u32 };
            work.push((first, lo, mid));
            work.push((first + 1, mid, hi));
        }
        nodes
    }

    /// Makes a wide node of binary node `b` (a leaf only when it is the root, one light): its
    /// children opened, then repeatedly the open entry with the most lights replaced in place by
    /// its two children, up to eight entries. In-place keeps the children in the binary tree's
    /// depth-first order, so neighbouring `u` still pick neighbouring lights (what Sobol
    /// stratifies over the emitters). Returns the new node's index.
    fn collapse(&mut self, binary: &[BinaryNode], b: usize, parent: (u32, u8)) -> u32 {
        let mut entries: Vec<usize> = match binary[b].leaf {
            true => vec![b],
            false => vec![binary[b].index as usize, binary[b].index as usize + 1],
        };
        while entries.len() < WIDTH {
            let open = entries
                .iter()
                .enumerate()
                .filter(|(_, &e)| !binary[e].leaf)
                .max_by_key(|(k, &e)| (binary[e].lights, std::cmp::Reverse(*k)));
            let Some((k, &e)) = open else { break };
            let first = binary[e].index as usize;
            entries.splice(k..=k, [first, first + 1]);
        }
        let at = self.nodes.len() as u32;
        let bounds: Vec<LightBounds> = entries.iter().map(|&e| binary[e].bounds).collect();
        let mut child_bounds = [bounds[0]; WIDTH];
        child_bounds[..bounds.len()].copy_from_slice(&bounds);
        self.nodes.push(WideNode { family: Family::new(&bounds), child: [0; WIDTH], count: entries.len() as u32 });
        self.child_bounds.push(child_bounds);
        self.parent.push(parent);
        for (slot, &e) in entries.iter().enumerate() {
            let child = if binary[e].leaf {
                self.leaf_of[binary[e].index as usize] = (at, slot as u8);
                LIGHT | binary[e].index
            } else {
                self.collapse(binary, e, (at, slot as u8))
            };
            self.nodes[at as usize].child[slot] = child;
        }
        at
    }

    /// Makes the walk evaluate each child alone with `LightBounds::importance` (tests compare).
    pub fn set_scalar_reference(&mut self, on: bool) {
        self.scalar_reference = on;
    }

    /// The importances at `p` of node `at`'s children (0 in unused slots).
    #[inline]
    fn importances(&self, at: usize, p: Vec3, n: Option<Vec3>) -> [f32; WIDTH] {
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
        if !self.scalar_reference {
            return self.nodes[at].family.importance(p, n);
        }
        let mut imp = [0.0; WIDTH];
        let count = self.nodes[at].count as usize;
        for (x, b) in imp.iter_mut().zip(&self.child_bounds[at][..count]) {
            *x = b.importance(p, n);
        }
        imp
    }

    /// Chooses a light for point `p`: (light index, probability).
    pub fn sample(&self, p: Vec3, n: Option<Vec3>, u: f32) -> Option<(usize, f32)> {
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
        if !self.scalar_reference {
            // SAFETY: AVX2 is enabled at compile time; the family's loads are 32-byte aligned.
            return self.walk(u, |at, u| unsafe { choose_avx(self.nodes[at].family.importance_avx(p, n), u) });
        }
        self.walk(u, |at, u| choose(&self.importances(at, p, n), u))
    }

    /// The root's choice (`choose` on its children's importances) at eight shading points at once,
    /// the points in the lanes (`p[k]`, normal `n[k]`, number `u[k]`). Walked one point at a
    /// time, each point costs an evaluation of the root's family (its eight children at one
    /// point) and a choice among its lanes by shuffles (`choose_avx`); here each child is
    /// evaluated at the eight points at once, and the running sums, the count of those not
    /// above `u · total` and the slot's share are the same additions, compares and division
    /// lane for lane, so every lane's slot and share are `choose`'s bit for bit. (For the
    /// many-node trees' walks the same at their root cost more than it saved: many_lights
    /// 85.15 → 87.31 M instructions, docs/performance-journal.md's thirty-fifth round.)
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
    #[inline(always)]
    fn root_lanes(&self, p: &[Vec3; 8], n: &[Vec3; 8], u: &[f32; 8]) -> RootLanes {
        use std::arch::x86_64::*;
        let node = &self.nodes[0];
        let count = (node.count as usize).min(WIDTH);
        // Eight lanes from `f(0) … f(7)`.
        fn lanes(f: impl Fn(usize) -> f32) -> __m256 {
            let a: [f32; 8] = std::array::from_fn(f);
            // SAFETY: AVX is enabled at compile time; an unaligned load of eight floats.
            unsafe { _mm256_loadu_ps(a.as_ptr()) }
        }
        let points = [lanes(|k| p[k].x), lanes(|k| p[k].y), lanes(|k| p[k].z)];
        let normals = [lanes(|k| n[k].x), lanes(|k| n[k].y), lanes(|k| n[k].z)];
        // SAFETY (this block's intrinsics): AVX2 and FMA are enabled at compile time.
        unsafe {
            let mut imp = [_mm256_setzero_ps(); WIDTH];
            for (slot, x) in imp.iter_mut().enumerate().take(count) {
                *x = importance_lanes(&SlotLanes { family: &node.family, slot }, points, Some(normals));
            }
            // `running_sums`' additions, each lane its own point's.
            let add = |a, b| _mm256_add_ps(a, b);
            let [x0, x1, x2, x3, x4, x5, x6, x7] = imp;
            let (s01, s23, s45, s67) = (add(x0, x1), add(x2, x3), add(x4, x5), add(x6, x7));
            let s03 = add(s01, s23);
            let s46 = add(s45, x6);
            let running =
                [x0, s01, add(s01, x2), s03, add(s03, x4), add(s03, s45), add(s03, s46), add(s03, add(s45, s67))];
            let total = running[WIDTH - 1];
            // `choose`: t = u · total, and the count of running sums not above it (!(t < r), true
            // for a NaN, as NLT is), each compare's all-ones lane subtracted as −1.
            let t = _mm256_mul_ps(lanes(|k| u[k]), total);
            let mut below = _mm256_setzero_si256();
            for r in running {
                below = _mm256_sub_epi32(below, _mm256_castps_si256(_mm256_cmp_ps::<_CMP_NLT_UQ>(t, r)));
            }
            // `chosen`: the slot's importance over the total, where the count is a slot.
            let mut x = _mm256_setzero_ps();
            for (s, &xs) in imp.iter().enumerate() {
                let here = _mm256_castsi256_ps(_mm256_cmpeq_epi32(below, _mm256_set1_epi32(s as i32)));
                x = _mm256_blendv_ps(x, xs, here);
            }
            let prob = _mm256_div_ps(x, total);
            // Lanes with no choice: total not above 0 (or NaN); lanes whose count ran past the
            // last slot (u · total rounded up to a subnormal total) take `chosen`'s fallback.
            let ok = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_GT_OQ>(total, _mm256_setzero_ps())) as u32;
            let past =
                _mm256_movemask_ps(_mm256_castsi256_ps(_mm256_cmpeq_epi32(below, _mm256_set1_epi32(WIDTH as i32))))
                    as u32
                    & ok;
            RootLanes { below, prob, ok, past, imp, total }
        }
    }

    /// [`Self::sample`] of a one-node tree ([`Self::is_one_node`]) at eight shading points at
    /// once (`p[k]`, normal `n[k]`, number `u[k]`; the answer into `out[k]` for every lane): the
    /// root's choice for the eight together ([`Self::root_lanes`]: one evaluation per light,
    /// four for `scenes/sphere_lights`' bulbs, where one point at a time evaluated eight lights
    /// for each), then the walk's one step down, also lane for lane. Every lane's answer is
    /// [`Self::sample`]'s bit for bit (`root_lanes_choose_what_single_walks_choose`).
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
    pub fn sample_root_lanes(&self, p: &[Vec3; 8], n: &[Vec3; 8], u: &[f32; 8], out: &mut [Option<(usize, f32)>; 8]) {
        use std::arch::x86_64::*;
        debug_assert!(self.is_one_node());
        let root = self.root_lanes(p, n, u);
        // SAFETY (this block's intrinsics): AVX2 is enabled at compile time; the child slots are
        // read as one unaligned load of eight u32.
        let (light, prob, chose) = unsafe {
            // The walk's step down (`descend`): pmf = 1 · prob, the slot's child, an answer where
            // that child is a light (in a one-node tree every child is) and pmf > 0.
            let child = _mm256_loadu_si256(self.nodes[0].child.as_ptr() as *const __m256i);
            let child = _mm256_permutevar8x32_epi32(child, root.below);
            let is_light = _mm256_cmpeq_epi32(_mm256_srli_epi32::<31>(child), _mm256_set1_epi32(1));
            let positive = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_GT_OQ>(root.prob, _mm256_setzero_ps()));
            let (mut light, mut prob) = ([0u32; 8], [0f32; 8]);
            _mm256_storeu_si256(
                light.as_mut_ptr() as *mut __m256i,
                _mm256_and_si256(child, _mm256_set1_epi32(!LIGHT as i32)),
            );
            _mm256_storeu_ps(prob.as_mut_ptr(), root.prob);
            let answered = _mm256_movemask_ps(_mm256_castsi256_ps(_mm256_and_si256(is_light, positive))) as u32;
            (light, prob, answered & root.ok & !root.past)
        };
        for (k, answer) in out.iter_mut().enumerate() {
            *answer = match root.past & (1 << k) {
                0 => (chose & (1 << k) != 0).then_some((light[k] as usize, prob[k])),
                _ => root.past_choice(k).and_then(|(slot, prob)| {
                    let mut pmf = 1.0;
                    self.descend(0, slot, prob, &mut pmf).err().flatten()
                }),
            };
        }
    }

    /// Whether the tree is a single node (eight lights or fewer): a walk is then one level, with
    /// no chain for a batch to interleave, so `LightSet::select_batch` walks such a tree one
    /// point at a time rather than through [`Self::sample_batch`].
    pub fn is_one_node(&self) -> bool {
        self.nodes.len() == 1
    }

    /// [`Self::sample`] for up to [`MAX_WALKS`] shading points at once (point `k` is `p[k]`, `n[k]`,
    /// `u[k]`, its light into `out[k]`): the walks go down a level each in turn, so one walk's
    /// chain of dependent steps (a level's importances, the running sums, the slot, the next
    /// node) overlaps the others' instead of waiting alone. A walk is a chain of latencies, not
    /// of work: `scenes/sphere_light`'s profile had `sample` at 22 % of the render. Each walk
    /// takes the steps it takes alone, so each answer is [`Self::sample`]'s bit for bit.
    pub fn sample_batch(&self, p: &[Vec3], n: &[Option<Vec3>], u: &[f32], out: &mut [Option<(usize, f32)>]) {
        let count = p.len().min(n.len()).min(u.len()).min(out.len());
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
        if !self.scalar_reference {
            for s in (0..count).step_by(MAX_WALKS) {
                let e = (s + MAX_WALKS).min(count);
                // SAFETY: AVX2 is enabled at compile time; the families' loads are 32-byte aligned.
                unsafe { self.walks(&p[s..e], &n[s..e], &u[s..e], &mut out[s..e]) };
            }
            return;
        }
        for k in 0..count {
            out[k] = self.sample(p[k], n[k], u[k]);
        }
    }

    /// Up to [`MAX_WALKS`] walks (`p.len()`, all slices that long) into `out`, a level of each
    /// in turn, each taking the steps [`Self::sample`] takes. (Only the AVX2 build walks in
    /// batches.)
    ///
    /// A level goes in two passes over the live walks: every walk's importances at its node
    /// first, then every walk's choice and step down. A level's chain (the node's loads, the
    /// importances with their division and square roots, the running sums, the slot, the child's
    /// index) is long, some 85 cycles by its instructions' latencies; evaluated and chosen in one
    /// iteration per walk, a walk cost 120 ns of 16 interleaved against 156 ns alone (`cargo
    /// bench --bench light_tree`, 2208 lights, Zen 3): the core's window held few chains at once.
    /// In the first pass the evaluations share nothing, so it overlaps as many as the window
    /// holds: 91 ns a walk. Each walk still takes the steps it takes alone.
    ///
    /// # Safety
    /// AVX2 must be available (it is enabled at compile time where this is compiled).
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
    #[inline(always)]
    unsafe fn walks(&self, p: &[Vec3], n: &[Option<Vec3>], u: &[f32], out: &mut [Option<(usize, f32)>]) {
        use std::arch::x86_64::{__m256, _mm256_setzero_ps};
        let count = p.len().min(n.len()).min(u.len()).min(out.len()).min(MAX_WALKS);
        // The walks' state in arrays of MAX_WALKS, indexed by `k & LAST` (k < count ≤
        // MAX_WALKS, so the mask changes nothing): the compiler sees every index in bounds
        // and drops the checks a level's two passes paid for each walk.
        const LAST: usize = MAX_WALKS - 1;
        let (mut at, mut pmf, mut rest) = ([0usize; MAX_WALKS], [1.0f32; MAX_WALKS], [0f32; MAX_WALKS]);
        let (mut points, mut normals) = ([Vec3::ZERO; MAX_WALKS], [Vec3::ZERO; MAX_WALKS]);
        let mut found = [None; MAX_WALKS];
        let mut live = [0u8; MAX_WALKS];
        for k in 0..count {
            (rest[k], points[k], normals[k]) = (u[k], p[k], n[k].unwrap_or(Vec3::ZERO));
            live[k] = k as u8;
        }
        // Shading points have normals: then the family's evaluation is the one with a normal,
        // chosen once for the batch rather than asked at every level of every walk.
        let with_normals = n[..count].iter().all(Option::is_some);
        let mut imp: [__m256; MAX_WALKS] = [_mm256_setzero_ps(); MAX_WALKS];
        let mut alive = count;
        while alive > 0 {
            for j in 0..alive {
                let k = live[j & LAST] as usize & LAST;
                let family = &self.nodes[at[k]].family;
                // SAFETY: AVX2 (the caller's contract); the family's loads are 32-byte aligned.
                imp[j & LAST] = unsafe {
                    match with_normals {
                        true => family.importance_avx(points[k], Some(normals[k])),
                        false => family.importance_avx(points[k], n.get(k).copied().flatten()),
                    }
                };
            }
            let mut still = 0;
            for j in 0..alive {
                let k = live[j & LAST] as usize & LAST;
                // SAFETY: as above.
                let Some((slot, prob, r)) = (unsafe { choose_avx(imp[j & LAST], rest[k]) }) else {
                    found[k] = None;
                    continue;
                };
                rest[k] = r;
                match self.descend(at[k], slot, prob, &mut pmf[k]) {
                    Err(answer) => found[k] = answer,
                    Ok(child) => {
                        at[k] = child;
                        live[still & LAST] = k as u8;
                        still += 1;
                    }
                }
            }
            alive = still;
        }
        out[..count].copy_from_slice(&found[..count]);
    }

    /// The walk from the root: `pick(node, u)` chooses a slot of `node` (slot, probability,
    /// rescaled u) and the walk follows it to a light, multiplying the probabilities.
    #[inline(always)]
    fn walk(&self, mut u: f32, pick: impl Fn(usize, f32) -> Option<(usize, f32, f32)>) -> Option<(usize, f32)> {
        let (mut at, mut pmf) = (0usize, 1.0f32);
        loop {
            let (slot, prob, rest) = pick(at, u)?;
            u = rest;
            match self.descend(at, slot, prob, &mut pmf) {
                Ok(child) => at = child,
                Err(found) => return found,
            }
        }
    }

    /// A walk's step down from node `at` through `slot`, chosen with probability `prob` (folded
    /// into `pmf`): `Ok` the child node to go on from, or `Err` the walk's answer, at a light
    /// (None when its probability came to 0).
    #[inline(always)]
    fn descend(&self, at: usize, slot: usize, prob: f32, pmf: &mut f32) -> Result<usize, Option<(usize, f32)>> {
        *pmf *= prob;
        match self.nodes[at].child[slot] {
            c if c & LIGHT != 0 => Err((*pmf > 0.0).then_some(((c & !LIGHT) as usize, *pmf))),
            c => Ok(c as usize),
        }
    }

    /// The nodes on the walk to `light` and its slot in each, from its own node up to the root
    /// (nothing for an index that is not a tree light): what `pmf` evaluates, and `levels` counts.
    fn ancestors(&self, light: usize) -> impl Iterator<Item = (u32, u8)> + '_ {
        let first = self.leaf_of.get(light).copied();
        std::iter::successors(first, |&(at, _)| Some(self.parent[at as usize]).filter(|&(up, _)| up != u32::MAX))
    }

    /// How many nodes a walk to `light` visits (its node's depth, the root's being 1): the number
    /// of family evaluations `sample` makes when it picks that light, and `pmf` makes for it.
    /// 0 for an index that is not a tree light.
    pub fn levels(&self, light: usize) -> usize {
        self.ancestors(light).count()
    }

    /// Probability that `sample(p, n, ·)` picks `light`: the same factors, multiplied in the same
    /// order (root first), so it is `sample`'s number bit for bit.
    pub fn pmf(&self, p: Vec3, n: Option<Vec3>, light: usize) -> f32 {
        let mut factors = [0f32; MAX_DEPTH];
        let mut depth = 0;
        for (at, slot) in self.ancestors(light) {
            let imp = self.importances(at as usize, p, n);
            let total = running_sums(&imp)[WIDTH - 1];
            let x = imp[slot as usize];
            if total.is_nan() || total <= 0.0 || x <= 0.0 || depth == MAX_DEPTH {
                return 0.0;
            }
            factors[depth] = x / total;
            depth += 1;
        }
        if depth == 0 {
            return 0.0;
        }
        factors[..depth].iter().rev().product()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tri_light(c: Vec3, normal: Vec3, phi: f32) -> LightBounds {
        LightBounds {
            min: c - Vec3::splat(0.05),
            max: c + Vec3::splat(0.05),
            phi,
            w: normal,
            cos_theta_o: 1.0,
            cos_theta_e: 0.0,
            two_sided: false,
        }
    }

    #[test]
    fn pmf_sums_to_one_and_matches_sampling_frequencies() {
        let mut lights = Vec::new();
        for i in 0..37 {
            let a = i as f32 * 0.7;
            lights.push(tri_light(
                Vec3::new(a.cos() * 3.0, 2.0 + (i % 5) as f32 * 0.3, a.sin() * 3.0),
                -Vec3::Y,
                1.0 + (i % 7) as f32,
            ));
        }
        let tree = LightTree::build(&lights).unwrap();
        for p in [Vec3::ZERO, Vec3::new(2.5, 0.0, 0.3), Vec3::new(0.0, 1.0, -2.0)] {
            let n = Some(Vec3::Y);
            let total: f32 = (0..lights.len()).map(|l| tree.pmf(p, n, l)).sum();
            assert!((total - 1.0).abs() < 1e-4, "pmf sums to {total}");
            let m = 200_000;
            let mut counts = vec![0usize; lights.len()];
            for k in 0..m {
                let (l, pmf) = tree.sample(p, n, (k as f32 + 0.5) / m as f32).unwrap();
                assert_eq!(pmf.to_bits(), tree.pmf(p, n, l).to_bits(), "sample and pmf agree bit for bit");
                counts[l] += 1;
            }
            for (l, &c) in counts.iter().enumerate() {
                let f = c as f32 / m as f32;
                assert!((f - tree.pmf(p, n, l)).abs() < 2e-3, "light {l}: {f} vs {}", tree.pmf(p, n, l));
            }
        }
    }

    /// The search `choose` replaced: walk the slots, stop at the first whose running sum exceeds t.
    fn choose_by_search(imp: &[f32; WIDTH], u: f32) -> Option<(usize, f32, f32)> {
        let running = running_sums(imp);
        let total = running[WIDTH - 1];
        if total.is_nan() || total <= 0.0 {
            return None;
        }
        let t = u * total;
        let mut last = None;
        for (i, &x) in imp.iter().enumerate() {
            if x > 0.0 {
                let before = if i == 0 { 0.0 } else { running[i - 1] };
                if t < running[i] {
                    return Some((i, x / total, ((t - before) / x).clamp(0.0, 1.0 - f32::EPSILON)));
                }
                last = Some(i);
            }
        }
        last.map(|i| (i, imp[i] / total, 1.0 - f32::EPSILON))
    }

    /// `choose` picks the slot the running search picks, with the same probability and rescaled
    /// `u` bit for bit, and so does `choose_avx` (the walk's): random importances with zeros,
    /// ties, tiny and huge values, and `u` at 0, just below 1 and at the slot boundaries.
    #[test]
    fn choose_matches_running_search() {
        let h = crate::sampler::hash_unit;
        let bits = |r: Option<(usize, f32, f32)>| r.map(|(s, p, u)| (s, p.to_bits(), u.to_bits()));
        let mut picked = [0usize; WIDTH];
        for k in 0..200_000u64 {
            let mut imp = [0f32; WIDTH];
            for (i, x) in imp.iter_mut().enumerate() {
                let r = h(k * 16 + i as u64);
                *x = match (k + i as u64) % 6 {
                    0 => 0.0,
                    1 => r * 1e-30,
                    2 => r * 1e30,
                    3 => 1.0,
                    _ => r,
                };
            }
            if k % 97 == 0 {
                imp = [0.0; WIDTH];
            }
            let running = running_sums(&imp);
            let total = running[WIDTH - 1];
            let u = match k % 5 {
                0 => 0.0,
                1 => 1.0 - f32::EPSILON / 2.0,
                // A slot boundary: t lands on a running sum.
                2 if total > 0.0 && k % 8 > 0 => running[(k % 8) as usize - 1] / total,
                _ => h(k * 16 + 9),
            };
            let sequential: f32 = imp.iter().sum();
            assert!((total - sequential).abs() <= 1e-6 * sequential, "{imp:?}: total {running:?}");
            for i in 1..WIDTH {
                assert!(running[i] >= running[i - 1], "{imp:?}: running sums {running:?} decrease");
                assert!(imp[i] > 0.0 || running[i] == running[i - 1], "{imp:?}: a 0 moved the sum {running:?}");
            }
            let (got, want) = (choose(&imp, u), choose_by_search(&imp, u));
            assert_eq!(bits(got), bits(want), "importances {imp:?}, u {u}");
            #[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
            {
                // SAFETY: AVX2 is enabled at compile time; the load reads imp's eight floats.
                let avx = unsafe { choose_avx(std::arch::x86_64::_mm256_loadu_ps(imp.as_ptr()), u) };
                assert_eq!(bits(avx), bits(got), "AVX choose: importances {imp:?}, u {u}");
            }
            if let Some((s, ..)) = got {
                picked[s] += 1;
            }
        }
        assert!(picked.iter().all(|&c| c > 1000), "every slot picked: {picked:?}");
    }

    /// `sample_batch` gives each point `sample`'s answer, bit for bit: batches of 1 to 40 (more
    /// than `MAX_WALKS`, so walks go in groups), points with and without a normal (and every
    /// batch again with a normal at each point, the form the kernel's batches take), points every
    /// light faces away from (None) among the rest, and trees deep enough for walks to end at
    /// different levels.
    /// `sample_root_lanes` (one light at eight points per evaluation) against `sample` (eight
    /// lights at one point) on one-node trees of 1 to 8 lights, bit for bit: lit and unlit points,
    /// points inside a light's bounds, and the numbers at the ends of [0, 1).
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
    #[test]
    fn root_lanes_choose_what_single_walks_choose() {
        let h = |j: usize| crate::sampler::hash_unit(j as u64);
        let (mut none, mut some, mut past_last, mut slots_seen) = (0, 0, 0, std::collections::HashSet::new());
        // Subnormal powers make subnormal totals, where u · total can round up to the total
        // itself: the count then runs past the last slot, `chosen`'s fallback.
        // And one bright light among subnormal ones (`bright`): where u = 0 picks a faint one, its
        // share x / total underflows to 0, and `descend` answers None.
        let configs = (1..=WIDTH).map(|c| (c, 1.0, None)).chain([(3, 1e-41, None), (8, 1e-41, None)]);
        let mut underflows = 0;
        for (count, phi, bright) in configs.chain((0..4).map(|b| (4, 1e-41, Some(b)))) {
            let lights: Vec<_> = (0..count)
                .map(|i| {
                    let down = if i % 3 == 0 { Vec3::new(0.3, -1.0, 0.2).normalize() } else { -Vec3::Y };
                    let c = Vec3::new(i as f32 - 3.0, 2.0 + 0.1 * i as f32, 0.5 * i as f32);
                    let phi = if bright == Some(i) { 1e6 } else { phi };
                    let mut b = tri_light(c, down, phi * (0.5 + i as f32));
                    b.two_sided = i == 5;
                    b
                })
                .collect();
            let tree = LightTree::build(&lights).unwrap();
            assert!(tree.is_one_node());
            for batch in 0..200 {
                let at = |k: usize| 1000 * count + 16 * batch + k;
                let p: [Vec3; 8] = std::array::from_fn(|k| match at(k) % 9 {
                    0 => Vec3::new(h(at(k)), 50.0, h(at(k) + 1)), // above every light: unlit
                    1 => lights[k % count].centroid(),            // inside a light's bounds
                    _ => Vec3::new(h(at(k)) * 8.0 - 4.0, h(at(k) + 1) * 3.0, h(at(k) + 2) * 6.0 - 3.0),
                });
                let n: [Vec3; 8] =
                    std::array::from_fn(|k| Vec3::new(h(at(k) + 3) - 0.5, 1.0, h(at(k) + 4) - 0.5).normalize());
                let u: [f32; 8] = std::array::from_fn(|k| match at(k) % 13 {
                    0 => 0.0,
                    1 => 1.0 - f32::EPSILON / 2.0,
                    _ => h(at(k) + 5),
                });
                let mut out = [Some((usize::MAX, -1.0)); 8];
                tree.sample_root_lanes(&p, &n, &u, &mut out);
                for k in 0..8 {
                    let alone = tree.sample(p[k], Some(n[k]), u[k]);
                    let bits = |x: Option<(usize, f32)>| x.map(|(l, pmf)| (l, pmf.to_bits()));
                    assert_eq!(bits(out[k]), bits(alone), "{count} lights, batch {batch}, lane {k}");
                    match alone {
                        Some((l, _)) => (some += 1, slots_seen.insert((count, l))),
                        None => (none += 1, false),
                    };
                    // Where the fallback chose, the probability is the last lit slot's share.
                    past_last += (phi < 1.0 && bright.is_none() && u[k] > 0.99999 && alone.is_some()) as usize;
                    let lit = tree.importances(0, p[k], Some(n[k])).iter().any(|&x| x > 0.0);
                    underflows += (bright.is_some() && u[k] == 0.0 && lit && alone.is_none()) as usize;
                }
            }
        }
        assert!(
            none > 50 && some > 5000 && past_last > 10 && underflows > 0 && slots_seen.len() == 36,
            "{none} unlit, {some} lit, {past_last} near 1 with subnormal totals, {underflows} shares underflowed, {} \
             picks: the test lost its cases",
            slots_seen.len()
        );
    }

    #[test]
    fn batched_walks_choose_what_single_walks_choose() {
        let mut lights = Vec::new();
        for i in 0..300 {
            let a = i as f32 * 0.37;
            // Facing down, most straight down, some tilted.
            let down = if i % 3 == 0 { Vec3::new(0.3, -1.0, 0.2).normalize() } else { -Vec3::Y };
            let y = 2.0 + (i % 11) as f32 * 0.2;
            lights.push(tri_light(Vec3::new(a.cos() * (1.0 + a), y, a.sin() * 2.0), down, 0.5 + (i % 7) as f32));
        }
        let tree = LightTree::build(&lights).unwrap();
        let point = |k: usize| {
            let h = |j: usize| crate::sampler::hash_unit((7 * k + j) as u64);
            // Every fifth point lies far above the lights, which all face down: none lights it.
            if k % 5 == 4 {
                (Vec3::new(h(0), 50.0, h(1)), Some(Vec3::Y), h(2))
            } else {
                let n = (!k.is_multiple_of(4)).then(|| Vec3::new(h(3) - 0.5, 1.0, h(4) - 0.5).normalize());
                (Vec3::new(h(0) * 8.0 - 4.0, h(1) * 3.0, h(5) * 6.0 - 3.0), n, h(2))
            }
        };
        let (mut none, mut some) = (0, 0);
        for count in [1, 2, 3, 7, MAX_WALKS, MAX_WALKS + 1, 40] {
            let pts: Vec<_> = (0..count).map(|k| point(count * 100 + k)).collect();
            let p: Vec<_> = pts.iter().map(|x| x.0).collect();
            let n: Vec<_> = pts.iter().map(|x| x.1).collect();
            let u: Vec<_> = pts.iter().map(|x| x.2).collect();
            // Each batch as drawn (some points without a normal: the walks ask per point) and with
            // a normal at every point (the kernel's batches: the evaluation chosen once).
            let n_all: Vec<_> = n.iter().map(|x| Some(x.unwrap_or(Vec3::Y))).collect();
            for n in [&n, &n_all] {
                let mut out = vec![Some((usize::MAX, -1.0)); count];
                tree.sample_batch(&p, n, &u, &mut out);
                for k in 0..count {
                    let alone = tree.sample(p[k], n[k], u[k]);
                    assert_eq!(
                        out[k].map(|(l, pmf)| (l, pmf.to_bits())),
                        alone.map(|(l, pmf)| (l, pmf.to_bits())),
                        "batch of {count}, point {k}"
                    );
                    if alone.is_some() {
                        some += 1
                    } else {
                        none += 1
                    }
                }
            }
        }
        assert!(none > 5 && some > 50, "{none} unlit and {some} lit points: the test lost its cases");
    }

    #[test]
    fn lights_facing_away_get_no_samples_and_near_lights_more() {
        let p = Vec3::ZERO;
        let near_far = LightTree::build(&[
            tri_light(Vec3::new(0.0, 1.0, 0.0), -Vec3::Y, 1.0),
            tri_light(Vec3::new(0.0, 10.0, 0.0), -Vec3::Y, 1.0),
        ])
        .unwrap();
        assert!(
            near_far.pmf(p, Some(Vec3::Y), 0) > 10.0 * near_far.pmf(p, Some(Vec3::Y), 1),
            "the near light dominates"
        );
        let away = LightTree::build(&[
            tri_light(Vec3::new(0.0, 1.0, 0.0), -Vec3::Y, 1.0),
            tri_light(Vec3::new(0.5, 2.0, 0.0), Vec3::Y, 50.0),
        ])
        .unwrap();
        assert_eq!(away.pmf(p, Some(Vec3::Y), 1), 0.0, "a one-sided light facing away");
        assert_eq!(away.pmf(p, Some(Vec3::Y), 0), 1.0);
    }

    /// The family (AVX) importance of both children equals `LightBounds::importance` of each, bit
    /// for bit, and so do whole walks (`sample`, `pmf`), over random bounds of every kind.
    #[test]
    fn family_importance_equals_one_at_a_time() {
        let u = crate::sampler::hash_unit;
        let v = |i: u64| Vec3::new(u(i), u(i + 1), u(i + 2)) * 2.0 - 1.0;
        let mut lights = Vec::new();
        for i in 0..300u64 {
            let c = v(20 * i) * 4.0;
            let ext = match i % 4 {
                0 => Vec3::ZERO, // a point light's bounds
                1 => Vec3::splat(0.01),
                _ => (v(20 * i + 3) + 1.0) * 0.5,
            };
            let w = v(20 * i + 6).normalize_or(Vec3::Y);
            lights.push(LightBounds {
                min: c - ext,
                max: c + ext,
                phi: u(20 * i + 9) * 10.0,
                w,
                cos_theta_o: if i % 5 == 0 { -1.0 } else { u(20 * i + 10) * 2.0 - 1.0 },
                cos_theta_e: if i % 3 == 0 { 0.0 } else { u(20 * i + 11) - 1.0 },
                two_sided: i % 7 == 0,
            });
        }
        let mut tree = LightTree::build(&lights).unwrap();
        let (mut compared, mut nonzero, mut slot_compared) = (0usize, 0usize, 0usize);
        for k in 0..2000u64 {
            let p = if k % 50 == 0 { lights[k as usize % 300].centroid() } else { v(7 * k + 100_000) * 5.0 };
            let n = (k % 3 != 0).then(|| v(7 * k + 200_000).normalize_or(Vec3::Z));
            for (i, node) in tree.nodes.iter().enumerate() {
                let lanes = tree.importances(i, p, n);
                for (slot, &x) in lanes.iter().enumerate() {
                    let s = match slot < node.count as usize {
                        true => tree.child_bounds[i][slot].importance(p, n),
                        false => 0.0,
                    };
                    // Equal as numbers (0 and −0 alike) and as bits where non-zero.
                    assert!(x == s && (x == 0.0 || x.to_bits() == s.to_bits()), "node {i} slot {slot}: {x} vs {s}");
                    compared += 1;
                    nonzero += (s > 0.0) as usize;
                }
            }
            // The slot form: one child at eight points (this one and seven more), each lane the
            // reference's number at its point.
            #[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
            if let Some(n) = n {
                use std::arch::x86_64::*;
                let pts: [Vec3; 8] =
                    std::array::from_fn(|i| if i == 0 { p } else { v(7 * k + 300_000 + 3 * i as u64) * 5.0 });
                let lanes = |f: &dyn Fn(Vec3) -> f32| {
                    let a: [f32; 8] = std::array::from_fn(|i| f(pts[i]));
                    // SAFETY: AVX is enabled at compile time; an unaligned load of eight floats.
                    unsafe { _mm256_loadu_ps(a.as_ptr()) }
                };
                let at = [lanes(&|q| q.x), lanes(&|q| q.y), lanes(&|q| q.z)];
                // SAFETY: as above.
                let normal = unsafe { [_mm256_set1_ps(n.x), _mm256_set1_ps(n.y), _mm256_set1_ps(n.z)] };
                for (i, node) in tree.nodes.iter().enumerate() {
                    for slot in 0..node.count as usize {
                        let mut out = [0f32; 8];
                        // SAFETY: AVX2 and FMA are enabled at compile time; an unaligned store.
                        unsafe {
                            let x = importance_lanes(&SlotLanes { family: &node.family, slot }, at, Some(normal));
                            _mm256_storeu_ps(out.as_mut_ptr(), x);
                        }
                        for (lane, &x) in out.iter().enumerate() {
                            let s = tree.child_bounds[i][slot].importance(pts[lane], Some(n));
                            assert!(
                                x == s && (x == 0.0 || x.to_bits() == s.to_bits()),
                                "slot form: node {i} slot {slot} lane {lane}"
                            );
                            slot_compared += 1;
                        }
                    }
                }
            }
            let uu = u(7 * k + 5);
            let family = (tree.sample(p, n, uu), (0..300).map(|l| tree.pmf(p, n, l).to_bits()).collect::<Vec<_>>());
            tree.set_scalar_reference(true);
            let scalar = (tree.sample(p, n, uu), (0..300).map(|l| tree.pmf(p, n, l).to_bits()).collect::<Vec<_>>());
            tree.set_scalar_reference(false);
            assert_eq!(family.0.map(|(l, q)| (l, q.to_bits())), scalar.0.map(|(l, q)| (l, q.to_bits())), "point {k}");
            assert_eq!(family.1, scalar.1, "point {k}");
        }
        assert!(compared > 500_000 && nonzero > compared / 4, "{compared} compared, {nonzero} non-zero");
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
        assert!(slot_compared > 500_000, "{slot_compared} compared in the slot form");
    }

    /// pbrt-v4's `LightBounds::Importance`, step for step as it is written there (normalise
    /// p − c, √(1 − cos²) for every sine), in f64: what `LightBounds::importance`'s d-scaled
    /// rearrangement must equal.
    fn pbrt_importance(b: &LightBounds, p: Vec3, n: Option<Vec3>) -> (f64, f64) {
        let f = |v: Vec3| [v.x as f64, v.y as f64, v.z as f64];
        let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let sqrt0 = |x: f64| x.max(0.0).sqrt();
        let cos_sub = |sa: f64, ca: f64, sb: f64, cb: f64| if ca > cb { 1.0 } else { ca * cb + sa * sb };
        let sin_sub = |sa: f64, ca: f64, sb: f64, cb: f64| if ca > cb { 0.0 } else { sa * cb - ca * sb };
        let (lo, hi, p) = (f(b.min), f(b.max), f(p));
        let pc = [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, (lo[2] + hi[2]) / 2.0];
        let v = [p[0] - pc[0], p[1] - pc[1], p[2] - pc[2]];
        let diag = [hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]];
        let r = dot(diag, diag).sqrt() / 2.0;
        let d2 = dot(v, v);
        let len = d2.sqrt();
        let wi = [v[0] / len, v[1] / len, v[2] / len];
        let mut cos_w = dot(f(b.w), wi);
        if b.two_sided {
            cos_w = cos_w.abs();
        }
        let sin_w = sqrt0(1.0 - cos_w * cos_w);
        let cos_b = if d2 < r * r { -1.0 } else { sqrt0(1.0 - r * r / d2) };
        let sin_b = sqrt0(1.0 - cos_b * cos_b);
        let cos_o = b.cos_theta_o as f64;
        let sin_o = sqrt0(1.0 - cos_o * cos_o);
        let cos_x = cos_sub(sin_w, cos_w, sin_o, cos_o);
        let sin_x = sin_sub(sin_w, cos_w, sin_o, cos_o);
        let cos_p = cos_sub(sin_x, cos_x, sin_b, cos_b);
        let mut importance = b.phi as f64 * cos_p / d2.max(r);
        if let Some(n) = n {
            let cos_i = dot(wi, f(n)).abs();
            importance *= cos_sub(sqrt0(1.0 - cos_i * cos_i), cos_i, sin_b, cos_b);
        }
        // The culling test's margin: how far cos θp is from the cut at cos θe.
        (if cos_p <= b.cos_theta_e as f64 { 0.0 } else { importance.max(0.0) }, cos_p - b.cos_theta_e as f64)
    }

    /// `LightBounds::importance` (whose d-scaled steps the AVX family repeats bit for bit) is
    /// pbrt-v4's bound: within f32 rounding of the literal f64 steps on random bounds of every
    /// kind (cones from a ray to the full sphere, two-sided, points inside the bounds, normals
    /// and none), and zero exactly where pbrt's is, away from the cut's edge.
    #[test]
    fn importance_is_pbrts_bound() {
        let u = crate::sampler::hash_unit;
        let v = |i: u64| Vec3::new(u(i), u(i + 1), u(i + 2)) * 2.0 - 1.0;
        let (mut checked, mut lit, mut culled) = (0usize, 0usize, 0usize);
        for i in 0..200_000u64 {
            let c = v(20 * i) * 4.0;
            let ext = match i % 4 {
                0 => Vec3::ZERO,
                1 => Vec3::splat(0.01),
                _ => (v(20 * i + 3) + 1.0) * 0.5,
            };
            let b = LightBounds {
                min: c - ext,
                max: c + ext,
                phi: 0.1 + u(20 * i + 9) * 10.0,
                w: v(20 * i + 6).normalize_or(Vec3::Y),
                // A full sphere, a triangle's cone (its normal alone), or anything between.
                cos_theta_o: match i % 5 {
                    0 => -1.0,
                    1 => 1.0,
                    _ => u(20 * i + 10) * 2.0 - 1.0,
                },
                cos_theta_e: if i % 3 == 0 { 0.0 } else { u(20 * i + 11) - 1.0 },
                two_sided: i % 7 == 0,
            };
            let p = v(20 * i + 12) * 5.0;
            let n = (i % 3 != 0).then(|| v(20 * i + 15).normalize_or(Vec3::Z));
            let (want, margin) = pbrt_importance(&b, p, n);
            if margin.abs() < 1e-3 {
                continue; // at the cut, f32 rounding may fall either side
            }
            let got = b.importance(p, n) as f64;
            // Errors are relative to the unculled power / distance² (a cosine factor near 0 has
            // an absolute error of about √ε from √(d² − (w·v)²)).
            let d2 = (p - b.centroid()).length_squared() as f64;
            let scale = b.phi as f64 / d2.max(((b.max - b.min).length() / 2.0) as f64);
            assert!((got - want).abs() <= 2e-3 * scale, "bounds {b:?}, p {p}, n {n:?}: {got} vs pbrt {want}");
            assert_eq!(got == 0.0, want == 0.0, "bounds {b:?}, p {p}, n {n:?}: {got} vs pbrt {want}");
            checked += 1;
            lit += (want > 0.0) as usize;
            culled += (want == 0.0) as usize;
        }
        assert!(checked > 190_000 && lit > checked / 3 && culled > checked / 20, "{checked} {lit} {culled}");
    }

    /// The node sizes (416 bytes a family, 480 a node); and the collapse: every light in exactly
    /// one slot, 2–8 children a node, and about a third of the binary depth.
    #[test]
    fn nodes_hold_every_light_once_in_few_levels() {
        assert_eq!(std::mem::size_of::<Family>(), 416);
        assert_eq!(std::mem::size_of::<WideNode>(), 480);
        for n in [2usize, 3, 7, 8, 9, 63, 64, 65, 1000, 2208] {
            let lights: Vec<LightBounds> = (0..n)
                .map(|i| {
                    tri_light(Vec3::new((i as f32 * 0.37).sin() * 5.0, i as f32 * 0.01, (i % 17) as f32), -Vec3::Y, 1.0)
                })
                .collect();
            let tree = LightTree::build(&lights).unwrap();
            let mut seen = vec![0usize; n];
            let mut depth = vec![1usize; tree.nodes.len()];
            for (i, node) in tree.nodes.iter().enumerate() {
                assert!((2..=WIDTH).contains(&(node.count as usize)), "{n} lights: node {i} has {}", node.count);
                for (slot, &c) in node.child[..node.count as usize].iter().enumerate() {
                    if c & LIGHT != 0 {
                        seen[(c & !LIGHT) as usize] += 1;
                        assert_eq!(tree.leaf_of[(c & !LIGHT) as usize], (i as u32, slot as u8));
                        assert_eq!(tree.levels((c & !LIGHT) as usize), depth[i], "{n} lights: a walk's levels");
                    } else {
                        assert_eq!(tree.parent[c as usize], (i as u32, slot as u8));
                        depth[c as usize] = depth[i] + 1;
                    }
                }
            }
            assert!(seen.iter().all(|&s| s == 1), "{n} lights: each in one slot");
            assert_eq!(tree.levels(n), 0, "{n} lights: an index past the lights has no walk");
            let max_depth = depth.into_iter().max().unwrap_or(0);
            let binary_depth = (n as f64).log2().ceil() as usize;
            assert!(max_depth <= binary_depth.div_ceil(3) + 1, "{n} lights: {max_depth} levels");
        }
    }
}
