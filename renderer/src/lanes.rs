//! Eight f32 lanes on one AVX register: the numbers of [`crate::spmd`]'s eight paths side by side.
//!
//! Every operation is the IEEE operation the scalar code does on each lane (no fused multiply-add,
//! comparisons with Rust's NaN semantics, `max` and `min` with the operand order that makes
//! `f32::max`'s NaN answer), so a lane's result is the scalar code's bit for bit when the scalar
//! code's operations are written in the same order.

#![cfg(all(target_arch = "x86_64", target_feature = "avx2"))]

use std::arch::x86_64::*;
use std::ops::{Add, BitAnd, BitOr, Div, Mul, Neg, Not, Sub};

use crate::math::Vec3;
use crate::spmd::LANES;

/// Eight f32 lanes.
#[derive(Clone, Copy)]
pub struct F8(pub __m256);

/// Eight lane masks (all ones or all zeros per lane), kept in a float register for the blends.
#[derive(Clone, Copy)]
pub struct M8(pub __m256);

// SAFETY (for every `unsafe` block in this file): the file is only compiled with AVX2 enabled
// (`cfg` above), so the AVX/AVX2 intrinsics are available; loads and stores go through arrays of
// exactly eight lanes.

/// A lane-by-lane comparison with the predicate Rust's operator has (ordered: false with a NaN,
/// but for `!=`).
macro_rules! cmp {
    ($name:ident, $pred:ident, $doc:expr) => {
        #[doc = $doc]
        #[inline(always)]
        pub fn $name(self, o: F8) -> M8 {
            M8(unsafe { _mm256_cmp_ps::<$pred>(self.0, o.0) })
        }
    };
}

impl F8 {
    #[inline(always)]
    pub fn splat(x: f32) -> F8 {
        F8(unsafe { _mm256_set1_ps(x) })
    }
    #[inline(always)]
    pub fn zero() -> F8 {
        F8(unsafe { _mm256_setzero_ps() })
    }
    #[inline(always)]
    pub fn from_array(a: [f32; LANES]) -> F8 {
        F8(unsafe { _mm256_loadu_ps(a.as_ptr()) })
    }
    #[inline(always)]
    pub fn to_array(self) -> [f32; LANES] {
        let mut a = [0.0; LANES];
        unsafe { _mm256_storeu_ps(a.as_mut_ptr(), self.0) };
        a
    }
    #[inline(always)]
    pub fn sqrt(self) -> F8 {
        F8(unsafe { _mm256_sqrt_ps(self.0) })
    }
    #[inline(always)]
    pub fn abs(self) -> F8 {
        F8(unsafe { _mm256_andnot_ps(_mm256_set1_ps(-0.0), self.0) })
    }
    /// `f32::max(self, other)` for a finite `other`: a NaN `self` gives `other` (vmaxps returns
    /// its second operand when either is NaN), in one instruction. Unlike `f32::max`, −0 against
    /// +0 gives +0: for operands that cannot be −0 when `other` is ±0 ([`F8::max`] otherwise).
    #[inline(always)]
    pub fn max_finite(self, other: F8) -> F8 {
        F8(unsafe { _mm256_max_ps(self.0, other.0) })
    }
    /// `f32::max(self, other)` exactly: equal operands (±0) give `self`, a NaN gives the other.
    #[inline(always)]
    pub fn max(self, other: F8) -> F8 {
        // vmaxps(a, b) is `a > b ? a : b`: `other > self ? other : self`, then NaN `self` fixed.
        let m = F8(unsafe { _mm256_max_ps(other.0, self.0) });
        select(self.ne(self), other, m)
    }
    /// `f32::min(self, other)` exactly: equal operands (±0) give `self`, a NaN gives the other.
    #[inline(always)]
    pub fn min(self, other: F8) -> F8 {
        let m = F8(unsafe { _mm256_min_ps(other.0, self.0) });
        select(self.ne(self), other, m)
    }
    /// glam's `Vec3::min` per coordinate, `if self < other { self } else { other }` (a NaN gives
    /// `other`): vminps exactly.
    #[inline(always)]
    pub fn glam_min(self, other: F8) -> F8 {
        F8(unsafe { _mm256_min_ps(self.0, other.0) })
    }
    /// `f32::clamp(self, lo, hi)`: `lo` where `self < lo`, then `hi` where `self > hi`; a NaN
    /// stays NaN. vmaxps(lo, x) is `lo > x ? lo : x`, vminps(hi, x) is `hi < x ? hi : x`.
    #[inline(always)]
    pub fn clamp(self, lo: F8, hi: F8) -> F8 {
        F8(unsafe { _mm256_min_ps(hi.0, _mm256_max_ps(lo.0, self.0)) })
    }
    /// `f32::round`: to the nearest integer, halves away from zero (not the even rounding of
    /// vroundps's nearest mode). `x − trunc(x)` is exact, so its comparison with ½ is too.
    #[inline(always)]
    pub fn round(self) -> F8 {
        let t = F8(unsafe { _mm256_round_ps::<{ _MM_FROUND_TO_ZERO | _MM_FROUND_NO_EXC }>(self.0) });
        select((self - t).abs().ge(F8::splat(0.5)), t + self.sign_one(), t)
    }
    /// 1.0 with the sign of each lane (`f32::copysign(1.0, x)`).
    #[inline(always)]
    pub fn sign_one(self) -> F8 {
        unsafe {
            let sign = _mm256_and_ps(self.0, _mm256_set1_ps(-0.0));
            F8(_mm256_or_ps(sign, _mm256_set1_ps(1.0)))
        }
    }
    cmp!(lt, _CMP_LT_OQ, "`<`");
    cmp!(le, _CMP_LE_OQ, "`<=`");
    cmp!(gt, _CMP_GT_OQ, "`>`");
    cmp!(ge, _CMP_GE_OQ, "`>=`");
    cmp!(eq, _CMP_EQ_OQ, "`==`");
    cmp!(ne, _CMP_NEQ_UQ, "`!=` as Rust has it: true for NaN");
    /// Lanes that are neither infinite nor NaN.
    #[inline(always)]
    pub fn is_finite(self) -> M8 {
        self.abs().lt(F8::splat(f32::INFINITY))
    }
    /// `f32::to_bits` per lane, then `as i32` arithmetic: `self`'s bits moved by `delta` ulps.
    #[inline(always)]
    pub fn add_to_bits(self, delta: I8) -> F8 {
        F8(unsafe { _mm256_castsi256_ps(_mm256_add_epi32(_mm256_castps_si256(self.0), delta.0)) })
    }
    /// `x as i32` for lanes within i32's range (truncation toward zero).
    #[inline(always)]
    pub fn to_i32_in_range(self) -> I8 {
        I8(unsafe { _mm256_cvttps_epi32(self.0) })
    }
}

/// Eight i32 lanes.
#[derive(Clone, Copy)]
pub struct I8(pub __m256i);

impl Neg for I8 {
    type Output = I8;
    /// Wrapping, as `i32`'s negation in a release build.
    #[inline(always)]
    fn neg(self) -> I8 {
        I8(unsafe { _mm256_sub_epi32(_mm256_setzero_si256(), self.0) })
    }
}

impl I8 {
    #[inline(always)]
    pub fn splat(x: i32) -> I8 {
        I8(unsafe { _mm256_set1_epi32(x) })
    }
    /// `self & o`, lane by lane.
    #[inline(always)]
    pub fn and(self, o: I8) -> I8 {
        I8(unsafe { _mm256_and_si256(self.0, o.0) })
    }
    /// `==`, lane by lane.
    #[inline(always)]
    pub fn eq(self, o: I8) -> M8 {
        M8(unsafe { _mm256_castsi256_ps(_mm256_cmpeq_epi32(self.0, o.0)) })
    }
    /// Lane by lane, `a` where `m` is set, else `b`.
    #[inline(always)]
    pub fn select(m: M8, a: I8, b: I8) -> I8 {
        unsafe { I8(_mm256_castps_si256(_mm256_blendv_ps(_mm256_castsi256_ps(b.0), _mm256_castsi256_ps(a.0), m.0))) }
    }
}

impl M8 {
    /// A mask from the low eight bits of `bits` (lane k: bit k).
    #[inline(always)]
    pub fn from_bits(bits: u32) -> M8 {
        unsafe {
            let lane = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
            let b = _mm256_and_si256(_mm256_set1_epi32(bits as i32), lane);
            M8(_mm256_castsi256_ps(_mm256_cmpeq_epi32(b, lane)))
        }
    }
    /// Lane k's flag as bit k.
    #[inline(always)]
    pub fn bits(self) -> u32 {
        unsafe { _mm256_movemask_ps(self.0) as u32 }
    }
    #[inline(always)]
    pub fn any(self) -> bool {
        self.bits() != 0
    }
    /// Lane by lane, `a` where `m` is set, else `b`.
    #[inline(always)]
    pub fn select(m: M8, a: M8, b: M8) -> M8 {
        M8(unsafe { _mm256_blendv_ps(b.0, a.0, m.0) })
    }
    /// `self != o`, lane by lane (exclusive or).
    #[inline(always)]
    pub fn xor(self, o: M8) -> M8 {
        M8(unsafe { _mm256_xor_ps(self.0, o.0) })
    }
    #[inline(always)]
    pub fn and_not(self, o: M8) -> M8 {
        M8(unsafe { _mm256_andnot_ps(o.0, self.0) })
    }
}

impl BitAnd for M8 {
    type Output = M8;
    #[inline(always)]
    fn bitand(self, o: M8) -> M8 {
        M8(unsafe { _mm256_and_ps(self.0, o.0) })
    }
}

impl BitOr for M8 {
    type Output = M8;
    #[inline(always)]
    fn bitor(self, o: M8) -> M8 {
        M8(unsafe { _mm256_or_ps(self.0, o.0) })
    }
}

impl Not for M8 {
    type Output = M8;
    #[inline(always)]
    fn not(self) -> M8 {
        M8(unsafe { _mm256_xor_ps(self.0, _mm256_castsi256_ps(_mm256_set1_epi32(-1))) })
    }
}

/// Lane by lane, `a` where `m` is set, else `b`.
#[inline(always)]
pub fn select(m: M8, a: F8, b: F8) -> F8 {
    F8(unsafe { _mm256_blendv_ps(b.0, a.0, m.0) })
}

macro_rules! binop {
    ($t:ident, $f:ident, $i:ident) => {
        impl $t for F8 {
            type Output = F8;
            #[inline(always)]
            fn $f(self, o: F8) -> F8 {
                F8(unsafe { $i(self.0, o.0) })
            }
        }
    };
}
binop!(Add, add, _mm256_add_ps);
binop!(Sub, sub, _mm256_sub_ps);
binop!(Mul, mul, _mm256_mul_ps);
binop!(Div, div, _mm256_div_ps);

impl Neg for F8 {
    type Output = F8;
    #[inline(always)]
    fn neg(self) -> F8 {
        F8(unsafe { _mm256_xor_ps(self.0, _mm256_set1_ps(-0.0)) })
    }
}

// `V8::from_lanes` and `to_lanes` read and write eight `Vec3`s as 24 consecutive floats.
const _: () = assert!(std::mem::size_of::<[Vec3; LANES]>() == 24 * std::mem::size_of::<f32>());

/// Eight 3-vectors, one coordinate a register. Operations follow glam's `Vec3` component by
/// component (its `dot` is `(x·x + y·y) + z·z`).
#[derive(Clone, Copy)]
pub struct V8 {
    pub x: F8,
    pub y: F8,
    pub z: F8,
}

impl V8 {
    #[inline(always)]
    pub fn splat(v: Vec3) -> V8 {
        V8 { x: F8::splat(v.x), y: F8::splat(v.y), z: F8::splat(v.z) }
    }
    #[inline(always)]
    pub fn zero() -> V8 {
        V8 { x: F8::zero(), y: F8::zero(), z: F8::zero() }
    }
    /// Eight vectors side by side, lane k the k-th: the 24 floats loaded as six halves and
    /// sorted into coordinates by five shuffles (the AoS-to-SoA transpose of Intel's "3D Vector
    /// Normalization Using 256-Bit Intel AVX", 2011). Picked out one coordinate at a time, the
    /// compiler moved the floats one by one (24 loads and inserts); the kernel transposes some
    /// twenty times a bounce. The same bits as [`Self::from_lanes_scalar`] (a test compares).
    #[inline(always)]
    pub fn from_lanes(v: &[Vec3; LANES]) -> V8 {
        // SAFETY: `[Vec3; 8]` is 24 consecutive f32 (glam's `Vec3` is `repr(C)` x, y, z, with no
        // padding: asserted below), so every 4-float load lies inside `v`.
        unsafe {
            let p = v.as_ptr() as *const f32;
            let half = |i: usize| _mm_loadu_ps(p.add(4 * i));
            // [x0 y0 z0 x1 | x4 y4 z4 x5], [y1 z1 x2 y2 | y5 z5 x6 y6], [z2 x3 y3 z3 | z6 x7 y7 z7]
            let m03 = _mm256_insertf128_ps::<1>(_mm256_castps128_ps256(half(0)), half(3));
            let m14 = _mm256_insertf128_ps::<1>(_mm256_castps128_ps256(half(1)), half(4));
            let m25 = _mm256_insertf128_ps::<1>(_mm256_castps128_ps256(half(2)), half(5));
            // [x2 y2 x3 y3 | x6 y6 x7 y7] and [y0 z0 y1 z1 | y4 z4 y5 z5]
            let xy = _mm256_shuffle_ps::<0b10_01_11_10>(m14, m25);
            let yz = _mm256_shuffle_ps::<0b01_00_10_01>(m03, m14);
            V8 {
                x: F8(_mm256_shuffle_ps::<0b10_00_11_00>(m03, xy)),
                y: F8(_mm256_shuffle_ps::<0b11_01_10_00>(yz, xy)),
                z: F8(_mm256_shuffle_ps::<0b11_00_11_01>(yz, m25)),
            }
        }
    }

    /// Eight vectors side by side from registers that each hold one as (x, y, z, ·)
    /// ([`xyz_register`]): four lane pairs joined, then unpacked and shuffled into coordinates
    /// (eleven shuffles). Why not [`Self::from_lanes`] on an array of `Vec3` filled lane by lane:
    /// its 16-byte loads each span two lanes' 12-byte stores, which a core cannot forward from
    /// its store buffer (the load waits for the stores to reach the cache); a register a lane is
    /// stored and loaded whole. Measured: 0.3 % fewer instructions on the Cornell box, the same
    /// bits; the stall itself could not be counted on the hosts we had (no hardware counters).
    #[inline(always)]
    pub fn from_registers(v: &[__m128; LANES]) -> V8 {
        unsafe {
            let pair = |a: usize| _mm256_insertf128_ps::<1>(_mm256_castps128_ps256(v[a]), v[a + 4]);
            // [x0 y0 z0 · | x4 y4 z4 ·] and so on.
            let (v04, v15, v26, v37) = (pair(0), pair(1), pair(2), pair(3));
            // [x0 x1 y0 y1 | x4 x5 y4 y5], [z0 z1 · · | z4 z5 · ·], the same for lanes 2, 3, 6, 7.
            let (lo01, hi01) = (_mm256_unpacklo_ps(v04, v15), _mm256_unpackhi_ps(v04, v15));
            let (lo23, hi23) = (_mm256_unpacklo_ps(v26, v37), _mm256_unpackhi_ps(v26, v37));
            V8 {
                x: F8(_mm256_shuffle_ps::<0b01_00_01_00>(lo01, lo23)),
                y: F8(_mm256_shuffle_ps::<0b11_10_11_10>(lo01, lo23)),
                z: F8(_mm256_shuffle_ps::<0b01_00_01_00>(hi01, hi23)),
            }
        }
    }

    /// [`Self::from_lanes`] a coordinate at a time: the reference.
    pub fn from_lanes_scalar(v: &[Vec3; LANES]) -> V8 {
        V8 { x: F8::from_array(v.map(|v| v.x)), y: F8::from_array(v.map(|v| v.y)), z: F8::from_array(v.map(|v| v.z)) }
    }

    /// The lanes as eight vectors: [`Self::from_lanes`]' transpose run backwards (six shuffles,
    /// three lane swaps, three stores). The same bits as [`Self::to_lanes_scalar`].
    #[inline(always)]
    pub fn to_lanes(self) -> [Vec3; LANES] {
        let mut out = [Vec3::ZERO; LANES];
        self.store_lanes(&mut out);
        out
    }

    /// [`Self::to_lanes`] into `out` in place: three stores where the caller's vectors live, not
    /// a local array copied there (which, for a slice of eight or fewer, LLVM makes a call to
    /// `memcpy`: 0.7 % of a veach render, the camera rays' directions).
    #[inline(always)]
    pub fn store_lanes(self, out: &mut [Vec3; LANES]) {
        // SAFETY: as in `from_lanes`: the three 8-float stores fill `out`'s 24 floats exactly.
        unsafe {
            let (x, y, z) = (self.x.0, self.y.0, self.z.0);
            // [x0 x2 y0 y2 | x4 x6 y4 y6], [y1 y3 z1 z3 | …], [z0 z2 x1 x3 | …]
            let rxy = _mm256_shuffle_ps::<0b10_00_10_00>(x, y);
            let ryz = _mm256_shuffle_ps::<0b11_01_11_01>(y, z);
            let rzx = _mm256_shuffle_ps::<0b11_01_10_00>(z, x);
            // [x0 y0 z0 x1 | x4 y4 z4 x5], [y1 z1 x2 y2 | y5 z5 x6 y6], [z2 x3 y3 z3 | z6 x7 y7 z7]
            let r03 = _mm256_shuffle_ps::<0b10_00_10_00>(rxy, rzx);
            let r14 = _mm256_shuffle_ps::<0b11_01_10_00>(ryz, rxy);
            let r25 = _mm256_shuffle_ps::<0b11_01_11_01>(rzx, ryz);
            let p = out.as_mut_ptr() as *mut f32;
            _mm256_storeu_ps(p, _mm256_permute2f128_ps::<0x20>(r03, r14));
            _mm256_storeu_ps(p.add(8), _mm256_permute2f128_ps::<0x30>(r25, r03));
            _mm256_storeu_ps(p.add(16), _mm256_permute2f128_ps::<0x31>(r14, r25));
        }
    }

    /// [`Self::to_lanes`] a lane at a time: the reference.
    pub fn to_lanes_scalar(self) -> [Vec3; LANES] {
        let (x, y, z) = (self.x.to_array(), self.y.to_array(), self.z.to_array());
        std::array::from_fn(|k| Vec3::new(x[k], y[k], z[k]))
    }
    #[inline(always)]
    pub fn dot(self, o: V8) -> F8 {
        self.x * o.x + self.y * o.y + self.z * o.z
    }
    /// glam's `cross`: (y·z' − y'·z, z·x' − z'·x, x·y' − x'·y).
    #[inline(always)]
    pub fn cross(self, o: V8) -> V8 {
        V8 { x: self.y * o.z - o.y * self.z, y: self.z * o.x - o.z * self.x, z: self.x * o.y - o.x * self.y }
    }
    #[inline(always)]
    pub fn scale(self, s: F8) -> V8 {
        V8 { x: self.x * s, y: self.y * s, z: self.z * s }
    }
    /// `Vec3 != Vec3::ZERO`: some coordinate not zero (NaN included).
    #[inline(always)]
    pub fn ne_zero(self) -> M8 {
        let z = F8::zero();
        self.x.ne(z) | self.y.ne(z) | self.z.ne(z)
    }
    #[inline(always)]
    pub fn is_finite(self) -> M8 {
        self.x.is_finite() & self.y.is_finite() & self.z.is_finite()
    }
    /// glam's `max_element` for non-NaN lanes: `x.max(y.max(z))`.
    #[inline(always)]
    pub fn max_element(self) -> F8 {
        F8(unsafe { _mm256_max_ps(self.x.0, _mm256_max_ps(self.y.0, self.z.0)) })
    }
    /// glam's `min_element`: `min(x, min(y, z))` with its `a < b ? a : b`.
    #[inline(always)]
    pub fn min_element(self) -> F8 {
        self.x.glam_min(self.y.glam_min(self.z))
    }
    /// glam's `Vec3::min` and `Vec3::max`, coordinate by coordinate.
    #[inline(always)]
    pub fn glam_min(self, o: V8) -> V8 {
        V8 { x: self.x.glam_min(o.x), y: self.y.glam_min(o.y), z: self.z.glam_min(o.z) }
    }
    /// (glam's max, `if self > other { self } else { other }`, is vmaxps: [`F8::max_finite`].)
    #[inline(always)]
    pub fn glam_max(self, o: V8) -> V8 {
        V8 { x: self.x.max_finite(o.x), y: self.y.max_finite(o.y), z: self.z.max_finite(o.z) }
    }
    #[inline(always)]
    pub fn select(m: M8, a: V8, b: V8) -> V8 {
        V8 { x: select(m, a.x, b.x), y: select(m, a.y, b.y), z: select(m, a.z, b.z) }
    }
}

impl Div<F8> for V8 {
    type Output = V8;
    #[inline(always)]
    fn div(self, s: F8) -> V8 {
        V8 { x: self.x / s, y: self.y / s, z: self.z / s }
    }
}

impl Mul for V8 {
    type Output = V8;
    #[inline(always)]
    fn mul(self, o: V8) -> V8 {
        V8 { x: self.x * o.x, y: self.y * o.y, z: self.z * o.z }
    }
}

impl Add for V8 {
    type Output = V8;
    #[inline(always)]
    fn add(self, o: V8) -> V8 {
        V8 { x: self.x + o.x, y: self.y + o.y, z: self.z + o.z }
    }
}

impl Sub for V8 {
    type Output = V8;
    #[inline(always)]
    fn sub(self, o: V8) -> V8 {
        V8 { x: self.x - o.x, y: self.y - o.y, z: self.z - o.z }
    }
}

impl Neg for V8 {
    type Output = V8;
    #[inline(always)]
    fn neg(self) -> V8 {
        V8 { x: -self.x, y: -self.y, z: -self.z }
    }
}

/// `v` as (x, y, z, 0) in an SSE register: an 8-byte and a 4-byte load and an insert, reading
/// exactly `v`'s 12 bytes (a 16-byte load would read past the last vector of an array).
#[inline(always)]
pub fn xyz_register(v: &Vec3) -> __m128 {
    unsafe {
        // `_mm_loadl_epi64` reads unaligned (a `Vec3` is 4-byte aligned).
        let xy = _mm_castsi128_ps(_mm_loadl_epi64((v as *const Vec3).cast()));
        // z (source element 0, bits 7–6) into element 2 (bits 5–4); element 3 zeroed (bit 3).
        _mm_insert_ps::<0b0010_1000>(xy, _mm_load_ss(&v.z))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The transposes move every float to its place: distinct bit patterns (NaNs, ±0, ∞ among
    /// them) in every position, through both directions and back, and from one register a lane.
    #[test]
    fn transposes_are_the_coordinate_at_a_time_ones() {
        let specials = [f32::NAN, -0.0, 0.0, f32::INFINITY, f32::NEG_INFINITY, f32::MIN_POSITIVE, -1.5];
        for round in 0..64u32 {
            let v: [Vec3; LANES] = std::array::from_fn(|k| {
                let c = |j: u32| {
                    let i = 3 * k as u32 + j;
                    match (i + round) % 11 {
                        s if (s as usize) < specials.len() && round % 2 == 1 => specials[s as usize],
                        _ => (i * 1000 + round) as f32 + 0.25,
                    }
                };
                Vec3::new(c(0), c(1), c(2))
            });
            let (fast, slow) = (V8::from_lanes(&v), V8::from_lanes_scalar(&v));
            let regs = V8::from_registers(&v.each_ref().map(xyz_register));
            for (a, b) in [(fast.x, slow.x), (fast.y, slow.y), (fast.z, slow.z)] {
                assert_eq!(a.to_array().map(f32::to_bits), b.to_array().map(f32::to_bits), "round {round}");
            }
            for (a, b) in [(regs.x, slow.x), (regs.y, slow.y), (regs.z, slow.z)] {
                assert_eq!(a.to_array().map(f32::to_bits), b.to_array().map(f32::to_bits), "round {round}");
            }
            let bits = |a: [Vec3; LANES]| a.map(|v| v.to_array().map(f32::to_bits));
            assert_eq!(bits(fast.to_lanes()), bits(slow.to_lanes_scalar()), "round {round}");
            assert_eq!(bits(fast.to_lanes()), bits(v), "round {round}");
        }
    }
}
