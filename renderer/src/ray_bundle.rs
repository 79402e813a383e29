//! Rays from one origin whose directions lie close together (a pixel's camera rays), bounded as
//! a whole: a box none of them can enter is found with one interval test instead of one slab
//! test a ray (interval arithmetic over the bundle's directions, after Boulos et al. 2006,
//! "Geometric and arithmetic culling methods for entire ray packets"; Wald et al. 2007, "SIMD
//! ray stream tracing").
//!
//! What it is for: a pixel's camera rays walk the BVH's nodes once for all eight
//! ([`crate::accel::Accel::intersect_bundle`]): the leaves it lets through are the ones each ray
//! tests, and a pixel whose rays all miss the scene (a background) is answered by that walk
//! alone. So the test has to be conservative, never exact: a box some ray of the bundle enters,
//! by exact arithmetic or by the one-ray walk's rounding, must pass it.

#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
use crate::lanes::{select, F8};
use crate::math::Vec3;

/// One to eight directions, one register per axis (lane l: direction l; lanes past them repeat
/// the first): a pixel's camera rays as [`RayBundle::from_lanes`] and
/// [`crate::triangle::RayLanes8::from_lanes`] read them, transposed once for both.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[derive(Clone, Copy)]
pub struct Directions8 {
    pub xyz: [std::arch::x86_64::__m256; 3],
}

#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
impl Directions8 {
    /// None for no directions or more than eight.
    #[inline(always)]
    pub fn new(d: &[Vec3]) -> Option<Self> {
        let first = *d.first()?;
        if d.len() > 8 {
            return None;
        }
        let mut rows = [[0f32; 8]; 3];
        let [xs, ys, zs] = &mut rows;
        for (l, ((x, y), z)) in xs.iter_mut().zip(ys.iter_mut()).zip(zs.iter_mut()).enumerate() {
            let v = d.get(l).copied().unwrap_or(first);
            (*x, *y, *z) = (v.x, v.y, v.z);
        }
        // SAFETY: AVX is enabled at compile time; each row is eight floats.
        Some(Directions8 { xyz: rows.map(|r| unsafe { std::arch::x86_64::_mm256_loadu_ps(r.as_ptr()) }) })
    }
}

/// A bundle's origin and, per axis, what bounds its rays' distances to planes across that axis.
#[derive(Clone, Copy, Debug)]
pub struct RayBundle {
    axes: [Option<BundleAxis>; 3],
}

/// One axis of a [`RayBundle`] whose direction components all have one sign.
#[derive(Clone, Copy, Debug)]
pub struct BundleAxis {
    /// The origin's coordinate.
    origin: f32,
    /// +1 or −1: the components' sign.
    sign: f32,
    /// 1 / the least and 1 / the greatest component magnitude.
    inv_least: f32,
    inv_most: f32,
    /// [`WIDEN`] · |origin|: the origin's part of every plane's outward move.
    origin_margin: f32,
}

/// Relative widening of every box before the interval test: each plane p moves outward by
/// 1e-4 · (|p| + |origin|). The one-ray walk's distances are within a few ulps (relative ~1e-7
/// of |p − origin|) of exact and its planes are rounded outward, and this test's own roundings
/// are as small, so every box that walk can enter stays inside this test's answer by a wide
/// margin.
const WIDEN: f32 = 1e-4;

impl RayBundle {
    /// The bundle of rays from `origin` along `directions`; None when it is empty or a value is
    /// not finite (the one-ray walk's own answer for those is left to it). The reference
    /// [`Self::from_lanes`], the form `Accel::intersect_bundle` builds, is held to.
    pub fn new(origin: Vec3, directions: &[Vec3]) -> Option<Self> {
        let first = *directions.first()?;
        if !directions.iter().all(|d| d.is_finite()) {
            return None;
        }
        let (mut lo, mut hi) = (first, first);
        for &d in directions {
            lo = lo.min(d);
            hi = hi.max(d);
        }
        Self::from_range(origin, lo, hi)
    }

    /// [`Self::new`] for up to eight directions held one register per axis: the same bundle (the
    /// least and greatest of finite numbers do not depend on the order they are taken in; of a
    /// +0 and a −0 either may come out, and both leave the axis unbounded alike).
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[inline(always)]
    pub fn from_lanes(origin: Vec3, d: &Directions8) -> Option<Self> {
        let (lo, hi) = d.range()?;
        Self::from_range(origin, lo, hi)
    }

    /// [`Self::from_lanes`] for the directions of `d` and, where given, of `more` too: the
    /// bundle of up to sixteen rays (the same bundle as [`Self::new`] of them all, for the
    /// reason `from_lanes` gives).
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[inline(always)]
    pub fn from_lanes2(origin: Vec3, d: &Directions8, more: Option<&Directions8>) -> Option<Self> {
        let (mut lo, mut hi) = d.range()?;
        if let Some(more) = more {
            let (l, h) = more.range()?;
            (lo, hi) = (lo.min(l), hi.max(h));
        }
        Self::from_range(origin, lo, hi)
    }
}

#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
impl Directions8 {
    /// The least and greatest component on each axis; None where one is not finite.
    #[inline(always)]
    fn range(&self) -> Option<(Vec3, Vec3)> {
        use std::arch::x86_64::*;
        let d = self;
        // SAFETY: AVX is enabled at compile time.
        unsafe {
            let inf = _mm256_set1_ps(f32::INFINITY);
            let abs = |x: __m256| _mm256_andnot_ps(_mm256_set1_ps(-0.0), x);
            let finite = |x: __m256| _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LT_OQ>(abs(x), inf)) == 0xff;
            if !d.xyz.iter().all(|&x| finite(x)) {
                return None;
            }
            // The least and greatest lane: halves, then pairs, then neighbours.
            let reduce = |x: __m256, f: unsafe fn(__m256, __m256) -> __m256| {
                let x = f(x, _mm256_permute2f128_ps::<1>(x, x));
                let x = f(x, _mm256_permute_ps::<0b01_00_11_10>(x));
                _mm256_cvtss_f32(f(x, _mm256_permute_ps::<0b10_11_00_01>(x)))
            };
            let [x, y, z] = d.xyz;
            let lo = Vec3::new(reduce(x, _mm256_min_ps), reduce(y, _mm256_min_ps), reduce(z, _mm256_min_ps));
            let hi = Vec3::new(reduce(x, _mm256_max_ps), reduce(y, _mm256_max_ps), reduce(z, _mm256_max_ps));
            Some((lo, hi))
        }
    }
}

impl RayBundle {
    /// The bundle whose directions' components lie in `lo`..`hi` (finite).
    fn from_range(origin: Vec3, lo: Vec3, hi: Vec3) -> Option<Self> {
        if !origin.is_finite() {
            return None;
        }
        let axis = |a: usize| {
            // Components of both signs, or one the walk's safe inverse replaces by ±1/ε
            // (`node_ray::safe_inverse`), leave the axis unbounded.
            let (sign, least, most) = if lo[a] > 2.0 * f32::EPSILON {
                (1.0, lo[a], hi[a])
            } else if hi[a] < -2.0 * f32::EPSILON {
                (-1.0, -hi[a], -lo[a])
            } else {
                return None;
            };
            let origin_margin = WIDEN * origin[a].abs();
            Some(BundleAxis { origin: origin[a], sign, inv_least: 1.0 / least, inv_most: 1.0 / most, origin_margin })
        };
        Some(RayBundle { axes: [axis(0), axis(1), axis(2)] })
    }

    /// Axis `a`, or None where it bounds nothing.
    #[inline(always)]
    pub fn axis(&self, a: usize) -> Option<BundleAxis> {
        self.axes[a]
    }

    /// False only when no ray of the bundle can enter the box `lo`..`hi` at a distance ≥ 0 (the
    /// one box at a time form of `WideNode::bundle_mask`, and its reference in tests).
    pub fn may_enter(&self, lo: [f32; 3], hi: [f32; 3]) -> bool {
        let (mut enter, mut leave) = (0f32, f32::INFINITY);
        for a in 0..3 {
            let Some(ax) = self.axes[a] else { continue };
            let (e, l) = ax.span(lo[a], hi[a]);
            enter = enter.max(e);
            leave = leave.min(l);
        }
        lo[0] <= hi[0] && enter <= leave
    }
}

impl BundleAxis {
    /// The earliest entry into and the latest exit from the slab `lo`..`hi` (widened by
    /// [`WIDEN`]) over the bundle's rays along this axis.
    ///
    /// With every component positive, magnitudes in [m, M], a ray enters the slab at (lo − o)/d
    /// and leaves at (hi − o)/d; the earliest entry over the bundle is (lo − o)/M for lo − o ≥ 0,
    /// else (lo − o)/m, and the latest exit (hi − o)/m for hi − o ≥ 0, else (hi − o)/M (mirrored
    /// for negative components). A ray that enters a box has its largest entry at most its
    /// smallest exit, so the largest earliest entry is at most the smallest latest exit: a box
    /// that fails that test is entered by no ray.
    #[inline(always)]
    pub fn span(&self, lo: f32, hi: f32) -> (f32, f32) {
        let lo = lo - (WIDEN * lo.abs() + self.origin_margin);
        let hi = hi + (WIDEN * hi.abs() + self.origin_margin);
        let (near, far) =
            if self.sign > 0.0 { (lo - self.origin, hi - self.origin) } else { (self.origin - hi, self.origin - lo) };
        let earliest = if near >= 0.0 { near * self.inv_most } else { near * self.inv_least };
        let latest = if far >= 0.0 { far * self.inv_least } else { far * self.inv_most };
        (earliest, latest)
    }

    /// [`Self::span`] of eight slabs at once, the same operations lane by lane.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[inline(always)]
    pub fn span8(&self, lo: F8, hi: F8) -> (F8, F8) {
        let (widen, margin, o) = (F8::splat(WIDEN), F8::splat(self.origin_margin), F8::splat(self.origin));
        let lo = lo - (widen * lo.abs() + margin);
        let hi = hi + (widen * hi.abs() + margin);
        let (near, far) = if self.sign > 0.0 { (lo - o, hi - o) } else { (o - hi, o - lo) };
        let (least, most) = (F8::splat(self.inv_least), F8::splat(self.inv_most));
        let zero = F8::zero();
        let earliest = select(near.ge(zero), near * most, near * least);
        let latest = select(far.ge(zero), far * least, far * most);
        (earliest, latest)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampler::hash_unit;

    /// The interval test against each ray's own slab test in f64: whenever one ray of a bundle
    /// enters a box, the bundle may enter it; and it does cull (most boxes away from the bundle
    /// fail it), so the test is not trivially true.
    #[test]
    fn a_box_any_ray_enters_passes_and_others_mostly_fail() {
        let (mut entered, mut culled, mut missed_by_all) = (0, 0, 0);
        for i in 0..20_000u64 {
            let u = |k: u64| hash_unit(64 * i + k);
            let origin = [u(0) * 4.0 - 2.0, u(1) * 4.0 - 2.0, u(2) * 4.0 - 2.0];
            // A pixel's worth of spread (or a wide one every fourth bundle).
            let spread = if i % 4 == 0 { 0.5 } else { 0.01 };
            let c = [u(40) * 6.0 - 3.0, u(41) * 6.0 - 3.0, u(42) * 6.0 - 3.0];
            // Aimed near the box's centre, so that bundles graze, enter and pass it.
            let axis = [0, 1, 2].map(|a| c[a] - origin[a] + u(3 + a as u64) - 0.5);
            let dirs: Vec<[f32; 3]> =
                (0..8).map(|k| [0, 1, 2].map(|a| axis[a] + spread * (u(6 + 3 * k + a as u64) - 0.5))).collect();
            let h = [u(43) * 0.5, u(44) * 0.5, u(45) * 0.5];
            let (lo, hi) = ([c[0] - h[0], c[1] - h[1], c[2] - h[2]], [c[0] + h[0], c[1] + h[1], c[2] + h[2]]);
            let Some(bundle) =
                RayBundle::new(Vec3::from(origin), &dirs.iter().map(|&d| Vec3::from(d)).collect::<Vec<_>>())
            else {
                continue;
            };
            let any = dirs.iter().any(|d| {
                let (mut t0, mut t1) = (0f64, f64::INFINITY);
                for a in 0..3 {
                    let inv = 1.0 / d[a] as f64;
                    let (x, y) = ((lo[a] as f64 - origin[a] as f64) * inv, (hi[a] as f64 - origin[a] as f64) * inv);
                    t0 = t0.max(x.min(y));
                    t1 = t1.min(x.max(y));
                }
                t0 <= t1
            });
            let may = bundle.may_enter(lo, hi);
            if any {
                assert!(may, "bundle {i}: a ray enters {lo:?}..{hi:?} but the bundle test says none can");
                entered += 1;
            } else {
                missed_by_all += 1;
                culled += !may as usize;
            }
        }
        assert!(entered > 500, "{entered} boxes entered");
        assert!(culled * 10 > missed_by_all * 8, "culled {culled} of {missed_by_all} boxes no ray enters");
    }

    /// Directions of mixed sign, or a component the walk's safe inverse would replace, bound
    /// nothing on that axis; non-finite values give no bundle.
    #[test]
    fn unboundable_axes_constrain_nothing() {
        let b =
            RayBundle::new(Vec3::ZERO, &[Vec3::from([1.0, 0.5, 1.0]), Vec3::from([1.0, -0.5, 1.0])]).expect("finite");
        assert!(b.axes[1].is_none() && b.axes[0].is_some());
        let b = RayBundle::new(Vec3::ZERO, &[Vec3::from([1.0, 1e-9, 1.0])]).expect("finite");
        assert!(b.axes[1].is_none());
        assert!(RayBundle::new(Vec3::ZERO, &[Vec3::from([f32::NAN, 1.0, 1.0])]).is_none());
        assert!(RayBundle::new(Vec3::from([f32::INFINITY, 0.0, 0.0]), &[Vec3::from([1.0, 1.0, 1.0])]).is_none());
        assert!(RayBundle::new(Vec3::ZERO, &[]).is_none());
        // Behind the origin: a ray along +x cannot enter a box at x < 0.
        let b = RayBundle::new(Vec3::ZERO, &[Vec3::from([1.0, 0.01, 0.01])]).expect("finite");
        assert!(!b.may_enter([-3.0, -1.0, -1.0], [-2.0, 1.0, 1.0]));
        assert!(b.may_enter([2.0, -1.0, -1.0], [3.0, 1.0, 1.0]));
    }

    /// `from_lanes` builds `new`'s bundle, bit for bit, from one to eight directions held a
    /// register per axis, and `from_lanes2` from nine to sixteen in two: every sign, zero and tiny components, near-ties; and refuses a NaN or
    /// an infinity in any lane, or an origin that is not finite, as `new` does.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[test]
    fn lanes_bundle_is_the_slice_bundle() {
        let u = |k: u64| hash_unit(k);
        let bits = |b: Option<RayBundle>| {
            b.map(|b| {
                b.axes
                    .map(|a| a.map(|a| [a.origin, a.sign, a.inv_least, a.inv_most, a.origin_margin].map(f32::to_bits)))
            })
        };
        let mut built = 0;
        for i in 0..20_000u64 {
            // One to eight directions (one register), then nine to sixteen (two: `from_lanes2`).
            let n = 1 + (i % 16) as usize;
            let origin = Vec3::new(u(i * 64) * 20.0 - 10.0, u(i * 64 + 1) * 4.0, -u(i * 64 + 2) * 8.0);
            let mut dirs: Vec<Vec3> = (0..n as u64)
                .map(|l| {
                    let c = |j: u64| match (i + j) % 9 {
                        0 => 0.0,
                        1 => -0.0,
                        2 => 1e-9,
                        _ => u(i * 64 + 3 + 3 * l + j) * 2.0 - 0.9,
                    };
                    Vec3::new(c(0), c(1), c(2))
                })
                .collect();
            let origin = if i % 211 == 0 { Vec3::new(f32::INFINITY, 0.0, 0.0) } else { origin };
            if i % 101 == 0 {
                dirs[n - 1].y = if i % 2 == 0 { f32::NAN } else { f32::NEG_INFINITY };
            }
            let want = RayBundle::new(origin, &dirs);
            let (first, rest) = dirs.split_at(n.min(8));
            let got = match Directions8::new(first) {
                Some(d) if rest.is_empty() => RayBundle::from_lanes(origin, &d),
                Some(d) => Directions8::new(rest).and_then(|more| RayBundle::from_lanes2(origin, &d, Some(&more))),
                None => None,
            };
            assert_eq!(bits(got), bits(want), "bundle {i}: {dirs:?} from {origin:?}");
            built += want.is_some() as usize;
        }
        assert!(built > 15_000, "{built} bundles built");
    }
}
