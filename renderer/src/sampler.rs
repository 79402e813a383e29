//! Sample generation. A sample value is a pure function of (seed, pixel, sample index, dimension):
//! no state is carried between samples, so any split of the sample range across threads, tiles,
//! calls or machines reproduces exactly the same numbers (the determinism rule in ARCHITECTURE.md).

use crate::math::Vec2;

#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SamplerKind {
    /// Owen-scrambled Sobol (Burley 2020, via `sobol_burley`), padded in 4D sets, decorrelated per
    /// pixel by seeding the shuffle/scramble with a pixel hash.
    Sobol,
    /// Independent uniform numbers from a counter-based PCG32 step.
    Independent,
}

crate::named_choices!(SamplerKind, "sampler", { "sobol" => SamplerKind::Sobol, "independent" => SamplerKind::Independent });

/// The dimension layout of one path. Fixing it (rather than drawing dimensions in call order) keeps
/// each decision on the same Sobol dimension at every sample, which is what stratification needs,
/// and keeps 2D decisions inside one 4D set.
pub mod dims {
    /// Pixel-filter offset (2D).
    pub const FILM: u32 = 0;
    /// First dimension of bounce `b` is `BOUNCE_BASE + BOUNCE_STRIDE * b`.
    pub const BOUNCE_BASE: u32 = 4;
    pub const BOUNCE_STRIDE: u32 = 8;
    /// Offsets inside a bounce.
    pub const BSDF_DIR: u32 = 0; // 2D
    pub const BSDF_LOBE: u32 = 2;
    pub const RUSSIAN_ROULETTE: u32 = 3;
    pub const LIGHT_POS: u32 = 4; // 2D
    pub const LIGHT_SELECT: u32 = 6;
    pub const SPARE: u32 = 7;
}

/// Sampler for one (pixel, sample index). `repr(C)`: [`get_4d_pair_each_lanes`] gathers
/// `pixel_seed` and `index` (at bytes 4 and 8 of its 12) for eight lanes at once.
#[derive(Clone, Copy, Debug)]
#[repr(C)]
pub struct PixelSample {
    kind: SamplerKind,
    pixel_seed: u32,
    index: u32,
}

// The layout the eight-lane gathers read.
const _: () = assert!(
    std::mem::size_of::<PixelSample>() == 12
        && std::mem::offset_of!(PixelSample, pixel_seed) == 4
        && std::mem::offset_of!(PixelSample, index) == 8
);

impl PixelSample {
    pub fn new(kind: SamplerKind, seed: u64, pixel: (u32, u32), index: u32) -> Self {
        let pixel_seed = hash_u64(seed ^ hash_u64(((pixel.0 as u64) << 32) | pixel.1 as u64)) as u32;
        PixelSample { kind, pixel_seed, index }
    }

    /// The sampler of sample `index` of the same pixel: `new` with that index, without hashing
    /// the pixel again (its seed does not depend on the index).
    #[inline(always)]
    pub fn at(&self, index: u32) -> Self {
        PixelSample { index, ..*self }
    }

    /// The Sobol seed of 4D set `set` for this pixel and sample. sobol_burley supports 2^16
    /// samples per seed: higher blocks of samples get a fresh seed.
    #[inline]
    fn sobol_seed(&self, set: u32) -> u32 {
        hash_u32(self.pixel_seed ^ set_hash(set, self.index >> 16))
    }

    /// Dimensions `4·set … 4·set + 3` at once (one SIMD Owen-scrambled Sobol evaluation).
    #[inline]
    pub fn get_4d(&self, set: u32) -> [f32; 4] {
        match self.kind {
            SamplerKind::Sobol => sobol_4d(self.index & 0xffff, self.sobol_seed(set)),
            SamplerKind::Independent => {
                // One PCG32 stream per (pixel, sample), seeded by their hash; the 4D set picks the
                // stream's increment, so sets are independent streams and values within a set are
                // consecutive outputs of one stream.
                let mut rng = Pcg32::new(hash_u64((self.pixel_seed as u64) << 32 | self.index as u64), set as u64);
                [rng.next_unit(), rng.next_unit(), rng.next_unit(), rng.next_unit()]
            }
        }
    }

    /// [`Self::get_4d`] of two sets at once, the same numbers bit for bit: for Sobol the two
    /// scrambles run as the eight lanes of one AVX2 evaluation ([`sobol_4d_pair`]) instead of two
    /// four-lane ones, and the reversed index is shared. A bounce draws its BSDF and light sets
    /// together.
    #[inline(always)]
    pub fn get_4d_pair(&self, set_a: u32, set_b: u32) -> ([f32; 4], [f32; 4]) {
        match self.kind {
            SamplerKind::Sobol => sobol_4d_pair(self.index & 0xffff, self.sobol_seed(set_a), self.sobol_seed(set_b)),
            SamplerKind::Independent => (self.get_4d(set_a), self.get_4d(set_b)),
        }
    }

    /// Uniform number in [0, 1) for dimension `dim`.
    #[inline]
    pub fn get_1d(&self, dim: u32) -> f32 {
        self.get_4d(dim / 4)[(dim % 4) as usize]
    }

    /// Two dimensions (`dim`, `dim + 1`); `dim` is even in the fixed layout so both stay in one
    /// Sobol 4D set and are jointly stratified.
    #[inline]
    pub fn get_2d(&self, dim: u32) -> Vec2 {
        let v = self.get_4d(dim / 4);
        let k = (dim % 4) as usize;
        Vec2::new(v[k], v[(k + 1) % 4])
    }
}

/// `sobol_burley::sample_4d(index, 0, seed)`, bit for bit, with the Sobol matrix product done by
/// two table lookups instead of the crate's loop over the index bits (up to 16 iterations with a
/// data-dependent branch, 18 % of a Cornell-box render's time in `perf`). The generator is linear
/// over GF(2): x(a ⊕ b) = x(a) ⊕ x(b), so the contributions of the reversed index's two bytes,
/// tabulated once (2 × 256 × 16 bytes), XOR to the loop's result. The scrambles are the crate's
/// own functions (`sobol_burley::parts`), so only the order of the work differs.
/// (Burley 2020, "Practical Hash-based Owen Scrambling", JCGT 9(4).)
#[inline]
pub fn sobol_4d(index: u32, seed: u32) -> [f32; 4] {
    use sobol_burley::parts::{hash_int4, owen_scramble_int4_rev};
    debug_assert!(index < 1 << 16);
    let sobol = sobol_int4_rev(index.reverse_bits(), seed).into();
    owen_scramble_int4_rev(sobol, hash_int4(dimension_scrambles(seed).into())).reverse_bits().to_f32_norm()
}

/// The Sobol points (reversed bits, before the dimensions' scramble) of the Owen-scrambled
/// reversed index `index_rev` for `seed`: the matrix product by the byte tables.
#[inline(always)]
fn sobol_int4_rev(index_rev: u32, seed: u32) -> [u32; 4] {
    use sobol_burley::parts::{hash, owen_scramble_rev};
    let rev = owen_scramble_rev(index_rev, hash(seed ^ 0x79c6_8e4a));
    let tables = &SOBOL_BYTE_TABLES;
    let (hi, lo) = (tables[1][(rev >> 24) as usize], tables[0][((rev >> 16) & 0xff) as usize]);
    [hi[0] ^ lo[0], hi[1] ^ lo[1], hi[2] ^ lo[2], hi[3] ^ lo[3]]
}

/// The crate's per-dimension scramble values for dimension set 0 (hashed before use).
#[inline(always)]
fn dimension_scrambles(seed: u32) -> [u32; 4] {
    let s = seed.wrapping_mul(0x9c8f_2d3b);
    DIMENSION_SCRAMBLES.map(|c| s ^ c)
}

/// What [`dimension_scrambles`] xors into its seed's product for each of the four dimensions.
const DIMENSION_SCRAMBLES: [u32; 4] = [0x912f_69ba, 0x174f_18ab, 0x691e_72ca, 0xb40c_c1b8];

/// [`sobol_4d`] for two seeds: `(sobol_4d(index, seed_a), sobol_4d(index, seed_b))` bit for bit.
/// The per-seed index scramble and table lookups stay scalar; the scramble of the eight
/// dimensions, their bit reversal and the conversion to floats are the crate's `Int4` operations
/// (`hash_int4`, `owen_scramble_int4_rev`, `Int4::reverse_bits`, `Int4::to_f32_norm`), written out
/// on eight lanes. A test compares it with two `sobol_4d` calls over every index.
#[inline(always)]
pub fn sobol_4d_pair(index: u32, seed_a: u32, seed_b: u32) -> ([f32; 4], [f32; 4]) {
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    {
        debug_assert!(index < 1 << 16);
        let index_rev = index.reverse_bits();
        let (a, b) = (sobol_int4_rev(index_rev, seed_a), sobol_int4_rev(index_rev, seed_b));
        let (sa, sb) = (dimension_scrambles(seed_a), dimension_scrambles(seed_b));
        let lanes = [a[0], a[1], a[2], a[3], b[0], b[1], b[2], b[3]];
        let scramble = [sa[0], sa[1], sa[2], sa[3], sb[0], sb[1], sb[2], sb[3]];
        // SAFETY: AVX2 is enabled at compile time; loads and stores are unaligned.
        let out = unsafe { owen_reverse_to_f32_avx2(lanes, scramble) };
        ([out[0], out[1], out[2], out[3]], [out[4], out[5], out[6], out[7]])
    }
    #[cfg(not(all(target_arch = "x86_64", target_feature = "avx2")))]
    {
        (sobol_4d(index, seed_a), sobol_4d(index, seed_b))
    }
}

/// Eight samples' own pairs of sets at once, dimension-major: `a[i][k]` and `b[i][k]` are
/// dimension i of `samplers[k].get_4d_pair(sets_a[k], sets_b[k])`, bit for bit. The samples may
/// be of any pixels, blocks and bounces: the SPMD kernel's lanes run paths of a stream of pixels
/// and refill as paths end (`spmd::radiance8`), so their bounces differ. Each lane's two set
/// seeds are scalar hashes; the index scramble, the dimensions' scramble hashes and scrambles,
/// the bit reversal and the conversion to floats run across the lanes, and each dimension lands
/// in the lane order the kernel's registers want. False, with nothing written, unless every
/// sampler is Sobol.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[inline(always)]
pub(crate) fn get_4d_pair_each_lanes(
    samplers: &[PixelSample; 8],
    sets_a: &[u32; 8],
    sets_b: &[u32; 8],
    a: &mut [[f32; 8]; 4],
    b: &mut [[f32; 8]; 4],
) -> bool {
    if samplers.iter().any(|s| s.kind != SamplerKind::Sobol) {
        return false;
    }
    // `sobol_seed`'s hash inputs eight lanes at once: each sampler's pixel seed and index
    // gathered, and the set hashes gathered from their table where every lane's sample lies in
    // block 0 and both sets are tabulated (a bounce below 127), else looked up lane by lane.
    // SAFETY: AVX2 is enabled at compile time; loads and stores are unaligned. The gathers read
    // `samplers[k]`'s `pixel_seed` and `index` (`PixelSample` is `repr(C)`: a one-byte kind and
    // its padding, then the two u32 at bytes 4 and 8 of 12), and the table at indices checked to
    // be below its length.
    unsafe {
        use std::arch::x86_64::*;
        let load = |x: &[u32; 8]| _mm256_loadu_si256(x.as_ptr() as *const __m256i);
        let words = samplers.as_ptr() as *const i32;
        let lane = _mm256_setr_epi32(0, 3, 6, 9, 12, 15, 18, 21);
        let pixel = _mm256_i32gather_epi32::<4>(words.add(1), lane);
        let full = _mm256_i32gather_epi32::<4>(words.add(2), lane);
        let index = _mm256_and_si256(full, _mm256_set1_epi32(0xffff));
        let (sa, sb) = (load(sets_a), load(sets_b));
        // Each lane's larger set, with its block above bit 8 (a block is 16 bits): below
        // SET_HASHES (256) in every lane exactly where every set is tabulated and every block 0.
        let blocks = _mm256_slli_epi32::<8>(_mm256_srli_epi32::<16>(full));
        let key = _mm256_or_si256(_mm256_max_epu32(sa, sb), blocks);
        const _: () = assert!(SET_HASHES == 256);
        let tabulated = _mm256_testz_si256(key, _mm256_set1_epi32(!0xff)) != 0;
        let (ha, hb) = if tabulated {
            let table = SET_HASH_TABLE.as_ptr() as *const i32;
            (_mm256_i32gather_epi32::<4>(table, sa), _mm256_i32gather_epi32::<4>(table, sb))
        } else {
            let (mut set_a, mut set_b) = ([0u32; 8], [0u32; 8]);
            for k in 0..8 {
                let block = samplers[k].index >> 16;
                (set_a[k], set_b[k]) = (set_hash(sets_a[k], block), set_hash(sets_b[k], block));
            }
            (load(&set_a), load(&set_b))
        };
        let seed = |h: __m256i| hash_u32_avx2(_mm256_xor_si256(pixel, h));
        let mut idx = [0u32; 8];
        _mm256_storeu_si256(idx.as_mut_ptr() as *mut __m256i, index);
        sobol_lanes_avx2(idx, [seed(ha), seed(hb)], [a, b])
    };
    true
}

/// [`hash_u32`] on eight lanes: `hash_u64` (SplitMix64's finalizer) of each zero-extended lane,
/// four 64-bit lanes a register, its low 32 bits. AVX2 has no 64-bit multiply; each is three
/// 32×32→64 ones (`a·k mod 2^64 = a_lo·k_lo + (a_hi·k_lo + a_lo·k_hi)·2^32`).
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[inline(always)]
unsafe fn hash_u32_avx2(x: std::arch::x86_64::__m256i) -> std::arch::x86_64::__m256i {
    use std::arch::x86_64::*;
    let splat = |k: u64| _mm256_set1_epi64x(k as i64);
    let mul = |a: __m256i, k: u64| {
        let (k_lo, k_hi) = (splat(k & 0xffff_ffff), splat(k >> 32));
        let cross = _mm256_add_epi64(_mm256_mul_epu32(_mm256_srli_epi64::<32>(a), k_lo), _mm256_mul_epu32(a, k_hi));
        _mm256_add_epi64(_mm256_mul_epu32(a, k_lo), _mm256_slli_epi64::<32>(cross))
    };
    let hash = |x: __m256i| {
        let x = _mm256_add_epi64(x, splat(0x9e37_79b9_7f4a_7c15));
        let x = mul(_mm256_xor_si256(x, _mm256_srli_epi64::<30>(x)), 0xbf58_476d_1ce4_e5b9);
        let x = mul(_mm256_xor_si256(x, _mm256_srli_epi64::<27>(x)), 0x94d0_49bb_1331_11eb);
        _mm256_xor_si256(x, _mm256_srli_epi64::<31>(x))
    };
    let lo = hash(_mm256_cvtepu32_epi64(_mm256_castsi256_si128(x)));
    let hi = hash(_mm256_cvtepu32_epi64(_mm256_extracti128_si256::<1>(x)));
    // The low halves of the eight 64-bit results, back in lane order.
    let even = _mm256_setr_epi32(0, 2, 4, 6, 0, 2, 4, 6);
    let (lo, hi) = (_mm256_permutevar8x32_epi32(lo, even), _mm256_permutevar8x32_epi32(hi, even));
    _mm256_blend_epi32::<0xf0>(lo, hi)
}

/// Up to eight samples of one pixel at once, one set, dimension-major: `out[i][k]` is dimension i
/// of `samplers[k].get_4d(set)` bit for bit (lanes past `samplers.len()` repeat sample 0). False,
/// with nothing written, unless every sampler is Sobol with the same pixel and the same 2^16
/// block, so the eight share their seed: a pixel's camera rays (`render::camera_rays8`).
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[inline(always)]
pub(crate) fn get_4d_lanes(samplers: &[PixelSample], set: u32, out: &mut [[f32; 8]; 4]) -> bool {
    let Some((first, index)) = lane_indices(samplers) else { return false };
    // SAFETY: AVX2 is enabled at compile time; loads and stores are unaligned.
    unsafe { sobol_lanes_avx2(index, [std::arch::x86_64::_mm256_set1_epi32(first.sobol_seed(set) as i32)], [out]) };
    true
}

/// The first of up to eight samplers that share their seeds (all Sobol, one pixel, one 2^16
/// block), whose seeds serve them all, and their Sobol indices (lanes past the samplers repeat
/// the first); None when they do not share them.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[inline(always)]
fn lane_indices(samplers: &[PixelSample]) -> Option<(&PixelSample, [u32; 8])> {
    let first = samplers.first()?;
    let same = |s: &PixelSample| {
        s.kind == SamplerKind::Sobol && s.pixel_seed == first.pixel_seed && s.index >> 16 == first.index >> 16
    };
    if samplers.len() > 8 || !samplers.iter().all(same) {
        return None;
    }
    let mut index = [first.index & 0xffff; 8];
    for (i, s) in index.iter_mut().zip(samplers) {
        *i = s.index & 0xffff;
    }
    Some((first, index))
}

/// [`get_4d_pair_each_lanes`]' arithmetic: `sobol_4d(index[k], seeds[s]'s lane k)` for the eight
/// lanes k into `out[s]`, dimension-major.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[inline(always)]
unsafe fn sobol_lanes_avx2<const N: usize>(
    index: [u32; 8],
    seeds: [std::arch::x86_64::__m256i; N],
    out: [&mut [[f32; 8]; 4]; N],
) {
    use std::arch::x86_64::*;
    let splat = |x: u32| _mm256_set1_epi32(x as i32);
    let index_rev = reverse_bits_avx2(_mm256_loadu_si256(index.as_ptr() as *const __m256i));
    for (seed, out) in seeds.into_iter().zip(out) {
        // `sobol_int4_rev`: the index scramble, then the table rows.
        let rev = owen_scramble_rev_avx2(index_rev, hash_avx2(_mm256_xor_si256(seed, splat(0x79c6_8e4a))));
        let mut rev_lanes = [0u32; 8];
        _mm256_storeu_si256(rev_lanes.as_mut_ptr() as *mut __m256i, rev);
        let tables = &SOBOL_BYTE_TABLES;
        let row = |k: usize| {
            let r = rev_lanes[k];
            let (hi, lo) = (&tables[1][(r >> 24) as usize], &tables[0][((r >> 16) & 0xff) as usize]);
            _mm_xor_si128(
                _mm_loadu_si128(hi.as_ptr() as *const __m128i),
                _mm_loadu_si128(lo.as_ptr() as *const __m128i),
            )
        };
        // Lane k's four dimensions in row k; rows k and k + 4 share a register, then a 4×4
        // transpose in each half leaves dimension j of lanes 0–7 in `dim[j]`.
        let r = |k: usize| _mm256_set_m128i(row(k + 4), row(k));
        let (r0, r1, r2, r3) = (r(0), r(1), r(2), r(3));
        let (t0, t1) = (_mm256_unpacklo_epi32(r0, r1), _mm256_unpackhi_epi32(r0, r1));
        let (t2, t3) = (_mm256_unpacklo_epi32(r2, r3), _mm256_unpackhi_epi32(r2, r3));
        let dim = [
            _mm256_unpacklo_epi64(t0, t2),
            _mm256_unpackhi_epi64(t0, t2),
            _mm256_unpacklo_epi64(t1, t3),
            _mm256_unpackhi_epi64(t1, t3),
        ];
        // Each dimension's scramble (`hash_int4(dimension_scrambles(seed))`).
        let scramble = _mm256_mullo_epi32(seed, splat(0x9c8f_2d3b));
        for (j, x) in dim.into_iter().enumerate() {
            let h = hash_avx2(_mm256_xor_si256(scramble, splat(DIMENSION_SCRAMBLES[j])));
            let f = to_f32_norm_avx2(reverse_bits_avx2(owen_scramble_rev_avx2(x, h)));
            _mm256_storeu_ps(out[j].as_mut_ptr(), f);
        }
    }
}

/// `sobol_burley::parts::owen_scramble_rev` on eight lanes, lane i scrambled by `h`'s lane i.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[inline(always)]
unsafe fn owen_scramble_rev_avx2(
    x: std::arch::x86_64::__m256i,
    h: std::arch::x86_64::__m256i,
) -> std::arch::x86_64::__m256i {
    use std::arch::x86_64::*;
    let splat = |x: u32| _mm256_set1_epi32(x as i32);
    let mul = |a: __m256i, k: __m256i| _mm256_mullo_epi32(a, k);
    let xor = |a: __m256i, b: __m256i| _mm256_xor_si256(a, b);
    let mut x = xor(x, mul(x, splat(0x3d20_adea)));
    x = _mm256_add_epi32(x, h);
    x = mul(x, _mm256_or_si256(_mm256_srli_epi32::<16>(h), splat(1)));
    x = xor(x, mul(x, splat(0x0552_6c56)));
    xor(x, mul(x, splat(0x53a2_2864)))
}

/// `u32::reverse_bits` on eight lanes (`Int4::reverse_bits`: swap halves, bytes, nibbles, pairs,
/// bits).
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[inline(always)]
unsafe fn reverse_bits_avx2(x: std::arch::x86_64::__m256i) -> std::arch::x86_64::__m256i {
    use std::arch::x86_64::*;
    let swap = |x: __m256i, mask: u32, shift: __m128i| {
        let m = _mm256_set1_epi32(mask as i32);
        _mm256_or_si256(
            _mm256_and_si256(_mm256_srl_epi32(x, shift), m),
            _mm256_sll_epi32(_mm256_and_si256(x, m), shift),
        )
    };
    let x = swap(x, 0x5555_5555, _mm_cvtsi32_si128(1));
    let x = swap(x, 0x3333_3333, _mm_cvtsi32_si128(2));
    let x = swap(x, 0x0f0f_0f0f, _mm_cvtsi32_si128(4));
    let x = swap(x, 0x00ff_00ff, _mm_cvtsi32_si128(8));
    _mm256_or_si256(_mm256_srli_epi32::<16>(x), _mm256_slli_epi32::<16>(x))
}

/// `sobol_burley::parts::hash_int4` (skeeto's hash-prospector hash) on eight lanes.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[inline(always)]
unsafe fn hash_avx2(n: std::arch::x86_64::__m256i) -> std::arch::x86_64::__m256i {
    use std::arch::x86_64::*;
    let splat = |x: u32| _mm256_set1_epi32(x as i32);
    let mut h = _mm256_xor_si256(n, splat(0xe6fe_3beb));
    h = _mm256_xor_si256(h, _mm256_srli_epi32::<16>(h));
    h = _mm256_mullo_epi32(h, splat(0x7feb_352d));
    h = _mm256_xor_si256(h, _mm256_srli_epi32::<15>(h));
    h = _mm256_mullo_epi32(h, splat(0x846c_a68b));
    _mm256_xor_si256(h, _mm256_srli_epi32::<16>(h))
}

/// `Int4::to_f32_norm` on eight lanes: the top 23 bits as a float in [0, 1).
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[inline(always)]
unsafe fn to_f32_norm_avx2(x: std::arch::x86_64::__m256i) -> std::arch::x86_64::__m256 {
    use std::arch::x86_64::*;
    _mm256_sub_ps(
        _mm256_castsi256_ps(_mm256_or_si256(_mm256_srli_epi32::<9>(x), _mm256_set1_epi32(0x3f80_0000))),
        _mm256_set1_ps(1.0),
    )
}

/// `owen_scramble_int4_rev(n, hash_int4(scramble)).reverse_bits().to_f32_norm()` of
/// `sobol_burley::parts` on eight lanes (wrapping multiplies, logical shifts, as `Int4`'s).
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[inline(always)]
unsafe fn owen_reverse_to_f32_avx2(n: [u32; 8], scramble: [u32; 8]) -> [f32; 8] {
    use std::arch::x86_64::*;
    let h = hash_avx2(_mm256_loadu_si256(scramble.as_ptr() as *const __m256i));
    // owen_scramble_int4_rev(n, h), Int4::reverse_bits, Int4::to_f32_norm
    let x = owen_scramble_rev_avx2(_mm256_loadu_si256(n.as_ptr() as *const __m256i), h);
    let f = to_f32_norm_avx2(reverse_bits_avx2(x));
    let mut out = [0f32; 8];
    _mm256_storeu_ps(out.as_mut_ptr(), f);
    out
}

/// `hash_u32(set · 0x9e3779b9 ⊕ block · 0x85ebca6b)`, the part of a 4D set's seed shared by every
/// pixel: read from a table for the first [`SET_HASHES`] sets of block 0 (every sample below 2^16
/// and every bounce below 127), computed otherwise. Each `get_4d` is a chain of three hashes
/// before its scramble can start; the table takes one off the chain.
#[inline]
fn set_hash(set: u32, block: u32) -> u32 {
    match SET_HASH_TABLE.get(set as usize) {
        Some(&h) if block == 0 => h,
        _ => hash_u32(set.wrapping_mul(0x9e37_79b9) ^ block.wrapping_mul(0x85eb_ca6b)),
    }
}

/// Sets [`set_hash`] tabulates.
const SET_HASHES: usize = 256;

/// Worked out at compile time: a lazily built table would cost a check of its initialisation on
/// every read.
static SET_HASH_TABLE: [u32; SET_HASHES] = {
    let mut t = [0u32; SET_HASHES];
    let mut set = 0;
    while set < SET_HASHES {
        t[set] = hash_u32((set as u32).wrapping_mul(0x9e37_79b9));
        set += 1;
    }
    t
};

include!(concat!(env!("OUT_DIR"), "/sobol_byte_tables.rs"));

/// Maps 32 random bits to [0, 1) with 24 bits of precision (never returns 1.0).
#[inline]
fn u32_to_unit(x: u32) -> f32 {
    (x >> 8) as f32 * (1.0 / 16_777_216.0)
}

/// PCG32 (O'Neill 2014, `pcg32_random_r` with XSH-RR output).
struct Pcg32 {
    state: u64,
    inc: u64,
}

impl Pcg32 {
    const MUL: u64 = 6_364_136_223_846_793_005;

    /// `pcg32_srandom_r(seed, stream)`.
    #[inline]
    fn new(seed: u64, stream: u64) -> Self {
        let mut r = Pcg32 { state: 0, inc: (stream << 1) | 1 };
        r.next_u32();
        r.state = r.state.wrapping_add(seed);
        r.next_u32();
        r
    }

    #[inline]
    fn next_u32(&mut self) -> u32 {
        let old = self.state;
        self.state = old.wrapping_mul(Self::MUL).wrapping_add(self.inc);
        let xorshifted = (((old >> 18) ^ old) >> 27) as u32;
        xorshifted.rotate_right((old >> 59) as u32)
    }

    #[inline]
    fn next_unit(&mut self) -> f32 {
        u32_to_unit(self.next_u32())
    }
}

/// SplitMix64 finalizer: a well-mixed 64-bit hash.
#[inline]
pub const fn hash_u64(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9e37_79b9_7f4a_7c15);
    x = (x ^ (x >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    x ^ (x >> 31)
}

/// A uniform number in [0, 1) from the top 24 bits of `hash_u64(x)` (every such float exactly).
#[inline]
pub fn hash_unit(x: u64) -> f32 {
    (hash_u64(x) >> 40) as f32 / (1u64 << 24) as f32
}

#[inline]
const fn hash_u32(x: u32) -> u32 {
    hash_u64(x as u64) as u32
}

#[cfg(test)]
mod tests {
    /// The eight-lane bit reversal is `u32::reverse_bits` on every lane: single bits, all ones,
    /// every byte value in every byte position, and hashed words.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[test]
    fn eight_lane_bit_reversal_is_reverse_bits() {
        use std::arch::x86_64::*;
        let mut words: Vec<u32> = (0..32).map(|b| 1u32 << b).chain([0, u32::MAX, 0x8000_0001]).collect();
        words.extend((0..256u32).flat_map(|v| (0..4).map(move |p| v << (8 * p))));
        words.extend((0..4096u64).map(|k| super::hash_u32(k as u32) ^ (k as u32).rotate_left(7)));
        for chunk in words.chunks(8) {
            let mut lanes = [0u32; 8];
            lanes[..chunk.len()].copy_from_slice(chunk);
            let mut got = [0u32; 8];
            // SAFETY: AVX2 is enabled at compile time; unaligned loads and stores of eight u32.
            unsafe {
                let r = super::reverse_bits_avx2(_mm256_loadu_si256(lanes.as_ptr() as *const __m256i));
                _mm256_storeu_si256(got.as_mut_ptr() as *mut __m256i, r);
            }
            for (x, y) in lanes.iter().zip(got) {
                assert_eq!(y, x.reverse_bits(), "{x:#010x}");
            }
        }
    }

    #[test]
    fn table_sobol_equals_the_crate_bit_for_bit() {
        // Every index of the 2^16 the crate supports, for a few seeds (0, all ones, hashes).
        for seed in [0u32, 1, 0xffff_ffff, 0x9e37_79b9, super::hash_u32(42)] {
            for i in 0..1u32 << 16 {
                let (a, b) = (super::sobol_4d(i, seed), sobol_burley::sample_4d(i, 0, seed));
                assert!(
                    a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()),
                    "index {i} seed {seed}: {a:?} vs {b:?}"
                );
            }
        }
    }

    use super::*;

    /// The paired evaluation is two single ones, bit for bit: every index of a block for a few
    /// seed pairs, and through `PixelSample` for both kinds, in block 0 and past it.
    #[test]
    fn paired_sets_equal_two_single_ones() {
        let seeds = [(0u32, 1u32), (0xffff_ffff, 0), (hash_u32(7), hash_u32(8)), (0x9e37_79b9, 0x9e37_79b9)];
        for (a, b) in seeds {
            for i in 0..1u32 << 16 {
                let (pa, pb) = sobol_4d_pair(i, a, b);
                let bits = |v: [f32; 4]| v.map(f32::to_bits);
                assert_eq!((bits(pa), bits(pb)), (bits(sobol_4d(i, a)), bits(sobol_4d(i, b))), "index {i}");
            }
        }
        for kind in [SamplerKind::Sobol, SamplerKind::Independent] {
            for index in [0u32, 1, 77, 65_535, 65_536, 200_001] {
                let s = PixelSample::new(kind, 3, (5, 9), index);
                for set in [0u32, 1, 2, 9, 254, 255, 256, 300] {
                    let (a, b) = s.get_4d_pair(set, set + 1);
                    assert_eq!(a.map(f32::to_bits), s.get_4d(set).map(f32::to_bits));
                    assert_eq!(b.map(f32::to_bits), s.get_4d(set + 1).map(f32::to_bits));
                }
            }
        }
    }

    /// A pixel's samples drawn eight lanes at once for one set are each sample's own set, bit for
    /// bit: runs of one to eight consecutive and scattered indices, in block 0 and past it, sets
    /// inside and past the hash table; and the lanes refuse samplers that do not share their seed.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[test]
    fn one_pixels_lanes_equal_each_sample_alone() {
        let mut checked = 0;
        for (seed, pixel) in [(0u64, (0u32, 0u32)), (3, (5, 9)), (u64::MAX, (4095, 17))] {
            for start in [0u32, 1, 8, 61, 65_530, 65_536, 131_071, 200_001] {
                for n in 1..=8u32 {
                    for stride in [1u32, 3, 977] {
                        let pixel_sampler = PixelSample::new(SamplerKind::Sobol, seed, pixel, 0);
                        let samplers: Vec<PixelSample> = (0..n)
                            .map(|k| pixel_sampler.at(start + k * stride))
                            .filter(|s| s.index >> 16 == start >> 16)
                            .collect();
                        for set in [0u32, 1, 2, 9, 254, 255, 256, 300] {
                            let mut one = [[0f32; 8]; 4];
                            assert!(get_4d_lanes(&samplers, set, &mut one), "one pixel, one block");
                            for (k, s) in samplers.iter().enumerate() {
                                // `at` is `new` with that index.
                                let alone = PixelSample::new(SamplerKind::Sobol, seed, pixel, s.index).get_4d(set);
                                for i in 0..4 {
                                    assert_eq!(one[i][k].to_bits(), alone[i].to_bits(), "set {set} lane {k} dim {i}");
                                }
                                checked += 1;
                            }
                        }
                    }
                }
            }
        }
        assert!(checked > 10_000, "{checked}");
        let s = |kind, pixel, index| PixelSample::new(kind, 3, pixel, index);
        let sobol = SamplerKind::Sobol;
        let refused = |samplers: &[PixelSample]| {
            let mut c = [[7f32; 8]; 4];
            !get_4d_lanes(samplers, 0, &mut c) && c == [[7f32; 8]; 4]
        };
        assert!(refused(&[]));
        assert!(refused(&[s(sobol, (1, 1), 0), s(sobol, (1, 2), 1)]));
        assert!(refused(&[s(sobol, (1, 1), 65_535), s(sobol, (1, 1), 65_536)]));
        assert!(refused(&[s(SamplerKind::Independent, (1, 1), 0)]));
        assert!(refused(&[s(sobol, (1, 1), 0); 9]));
        assert!(!refused(&[s(sobol, (1, 1), 0); 8]));
    }

    /// Eight samples of different pixels, blocks and bounces drawn at once are each sample's own
    /// pair of sets, bit for bit (the kernel's lanes after refills), for sets inside and past the
    /// hash table; a lane of the independent sampler makes the call refuse, writing nothing.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[test]
    fn each_lanes_own_sets_equal_each_sample_alone() {
        let mut checked = 0;
        let indices = [0u32, 1, 7, 61, 65_535, 65_536, 131_071, 200_001, 3, 40_000];
        let sets = [0u32, 1, 2, 9, 254, 255, 256, 300, 5, 77, 129];
        // Rounds of three kinds: lanes mixed inside and past the table (and block 0 or not); every
        // lane inside it and in block 0 (the set hashes gathered from the table); the same with
        // one lane moved past it, by its set or its block.
        for round in 0..600u32 {
            let mut samplers = [PixelSample::new(SamplerKind::Sobol, 0, (0, 0), 0); 8];
            let (mut sets_a, mut sets_b) = ([0u32; 8], [0u32; 8]);
            for k in 0..8 {
                let r = hash_u32(round * 8 + k as u32);
                let seed = [0u64, 3, u64::MAX][(r % 3) as usize];
                let pixel = ((r >> 4) % 4096, (r >> 16) % 64);
                let mut index = indices[((r >> 8) as usize) % indices.len()];
                sets_a[k] = sets[((r >> 12) as usize) % sets.len()];
                sets_b[k] = sets_a[k] + 1 + (r >> 28);
                if round % 3 != 0 {
                    (index, sets_a[k]) = (index & 0xffff, sets_a[k] % 239);
                    sets_b[k] = sets_a[k] + 1 + (r >> 28);
                    if round % 3 == 2 && k == (round as usize / 3) % 8 {
                        if round % 2 == 0 {
                            sets_b[k] = 256 + (r >> 28);
                        } else {
                            index |= 1 << 16;
                        }
                    }
                }
                samplers[k] = PixelSample::new(SamplerKind::Sobol, seed, pixel, index);
            }
            let (mut a, mut b) = ([[0f32; 8]; 4], [[0f32; 8]; 4]);
            assert!(get_4d_pair_each_lanes(&samplers, &sets_a, &sets_b, &mut a, &mut b));
            for (k, s) in samplers.iter().enumerate() {
                let (ea, eb) = (s.get_4d(sets_a[k]), s.get_4d(sets_b[k]));
                for i in 0..4 {
                    assert_eq!(a[i][k].to_bits(), ea[i].to_bits(), "round {round} lane {k} dim {i}");
                    assert_eq!(b[i][k].to_bits(), eb[i].to_bits(), "round {round} lane {k} dim {i}");
                }
                checked += 1;
            }
        }
        assert_eq!(checked, 4800);
        let mut samplers = [PixelSample::new(SamplerKind::Sobol, 3, (1, 1), 0); 8];
        samplers[5] = PixelSample::new(SamplerKind::Independent, 3, (1, 1), 0);
        let (mut a, mut b) = ([[7f32; 8]; 4], [[7f32; 8]; 4]);
        assert!(!get_4d_pair_each_lanes(&samplers, &[0; 8], &[1; 8], &mut a, &mut b));
        assert!(a == [[7f32; 8]; 4] && b == a);
    }

    /// The eight-lane `hash_u32` is the scalar one on every lane, for inputs at the edges of
    /// the 32-bit range and hashes between.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[test]
    fn eight_lane_hash_equals_the_scalar_one() {
        use std::arch::x86_64::*;
        let edges = [0u32, 1, 2, 0x7fff_ffff, 0x8000_0000, 0xffff_fffe, u32::MAX, 0x9e37_79b9];
        for round in 0..1000u32 {
            let x: [u32; 8] = if round == 0 { edges } else { std::array::from_fn(|k| hash_u32(round * 8 + k as u32)) };
            let mut got = [0u32; 8];
            // SAFETY: AVX2 is enabled at compile time; loads and stores are unaligned.
            unsafe {
                let h = hash_u32_avx2(_mm256_loadu_si256(x.as_ptr() as *const __m256i));
                _mm256_storeu_si256(got.as_mut_ptr() as *mut __m256i, h);
            }
            assert_eq!(got, x.map(hash_u32), "inputs {x:?}");
        }
    }

    /// The tabulated set hashes are the formula's, inside the table and past it, in block 0
    /// and in later blocks (samples from 2^16 on).
    #[test]
    fn set_hash_table_equals_the_formula() {
        for block in 0..3u32 {
            for set in 0..SET_HASHES as u32 + 40 {
                let formula = hash_u32(set.wrapping_mul(0x9e37_79b9) ^ block.wrapping_mul(0x85eb_ca6b));
                assert_eq!(set_hash(set, block), formula, "set {set} block {block}");
            }
        }
    }

    #[test]
    fn values_are_in_unit_interval_and_pure() {
        for kind in [SamplerKind::Sobol, SamplerKind::Independent] {
            for i in 0..64 {
                for d in 0..40 {
                    let a = PixelSample::new(kind, 7, (3, 5), i).get_1d(d);
                    let b = PixelSample::new(kind, 7, (3, 5), i).get_1d(d);
                    assert_eq!(a.to_bits(), b.to_bits());
                    assert!((0.0..1.0).contains(&a));
                }
            }
        }
    }

    #[test]
    fn sobol_is_stratified_per_pixel_and_differs_between_pixels() {
        // The first 16 Sobol points of one dimension fall one per 1/16 stratum.
        let mut seen = [false; 16];
        for i in 0..16 {
            let v = PixelSample::new(SamplerKind::Sobol, 1, (10, 20), i).get_1d(5);
            seen[(v * 16.0) as usize] = true;
        }
        assert!(seen.iter().all(|&s| s));
        let a = PixelSample::new(SamplerKind::Sobol, 1, (10, 20), 0).get_1d(0);
        let b = PixelSample::new(SamplerKind::Sobol, 1, (11, 20), 0).get_1d(0);
        assert_ne!(a, b);
    }

    #[test]
    fn independent_mean_and_variance_are_uniform() {
        let n = 200_000u32;
        let (mut s, mut s2) = (0.0f64, 0.0f64);
        for i in 0..n {
            let v = PixelSample::new(SamplerKind::Independent, 3, (1, 2), i).get_1d(9) as f64;
            s += v;
            s2 += v * v;
        }
        let mean = s / n as f64;
        let var = s2 / n as f64 - mean * mean;
        assert!((mean - 0.5).abs() < 0.005, "mean {mean}");
        assert!((var - 1.0 / 12.0).abs() < 0.002, "var {var}");
    }
}
