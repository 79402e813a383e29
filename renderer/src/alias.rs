//! Walker/Vose alias table: O(1) sampling of a discrete distribution (Vose 1991; pbrt-v4 §A.1).

#[derive(Clone, Debug, Default)]
pub struct AliasTable {
    bins: Vec<Bin>,
}

/// `repr(C)`: [`AliasTable::sample_lanes`] gathers the fields at offsets 0, 4 and 8.
#[derive(Clone, Copy, Debug)]
#[repr(C)]
struct Bin {
    /// Probability of keeping this bin when it is chosen uniformly.
    q: f32,
    /// The pmf of this index, stored so that `pmf()` is exact.
    p: f32,
    alias: u32,
}

// The layout `AliasTable::sample_lanes` gathers.
const _: () = assert!(
    std::mem::size_of::<Bin>() == 12
        && std::mem::offset_of!(Bin, q) == 0
        && std::mem::offset_of!(Bin, p) == 4
        && std::mem::offset_of!(Bin, alias) == 8
);

impl AliasTable {
    /// Builds the table from non-negative weights. Returns None when no weight is positive and finite.
    pub fn new(weights: &[f32]) -> Option<Self> {
        let clean: Vec<f64> = weights.iter().map(|&w| if w.is_finite() && w > 0.0 { w as f64 } else { 0.0 }).collect();
        let total: f64 = clean.iter().sum();
        if !(total > 0.0) || clean.len() > u32::MAX as usize {
            return None;
        }
        let n = clean.len();
        let mut bins: Vec<Bin> = clean.iter().map(|&w| Bin { q: 0.0, p: (w / total) as f32, alias: 0 }).collect();
        let scaled: Vec<f64> = clean.iter().map(|&w| w / total * n as f64).collect();
        let mut q = scaled.clone();
        let (mut small, mut large): (Vec<usize>, Vec<usize>) = (0..n).partition(|&i| scaled[i] < 1.0);
        while let (Some(&s), Some(&l)) = (small.last(), large.last()) {
            small.pop();
            bins[s].q = q[s] as f32;
            bins[s].alias = l as u32;
            q[l] = (q[l] + q[s]) - 1.0;
            if q[l] < 1.0 {
                large.pop();
                small.push(l);
            }
        }
        for i in small.into_iter().chain(large) {
            bins[i].q = 1.0;
            bins[i].alias = i as u32;
        }
        Some(AliasTable { bins })
    }

    pub fn len(&self) -> usize {
        self.bins.len()
    }

    pub fn is_empty(&self) -> bool {
        self.bins.is_empty()
    }

    /// Samples an index with one uniform number; returns (index, pmf).
    #[inline]
    pub fn sample(&self, u: f32) -> (usize, f32) {
        let n = self.bins.len();
        let x = u * n as f32;
        // Through u32 (both conversions saturate; n is far below 2^32): the same integer, without
        // the unsigned 64-bit conversion's range fix-ups, which x86-64 does not have natively.
        let i = (x as u32 as usize).min(n - 1);
        let up = (x - i as u32 as f32).min(1.0 - f32::EPSILON);
        let idx = if up < self.bins[i].q { i } else { self.bins[i].alias as usize };
        (idx, self.bins[idx].p)
    }

    /// [`Self::sample`] for each of `u` (up to eight) into `out`, eight lanes at once, bit for
    /// bit: the same multiply, truncation, subtraction and minimum lane by lane, each bin's
    /// fields gathered. A number outside [0, 1) (which no sampler gives) and a table of 2^24 bins
    /// or more (where an index no longer converts to f32 exactly) go through `sample`. Why: the
    /// kernel chooses a light for each of its lanes at every bounce, and one at a time each choice
    /// paid a call, the bin's bounds checks and a branch on the kept or aliased bin.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    pub fn sample_lanes(&self, u: &[f32], out: &mut [(usize, f32)]) {
        let count = u.len().min(out.len()).min(8);
        let (mut ua, mut all) = ([0f32; 8], [(0, 0.0); 8]);
        ua[..count].copy_from_slice(&u[..count]);
        self.sample_eight(&ua, &mut all);
        out[..count].copy_from_slice(&all[..count]);
    }

    /// [`Self::sample_lanes`] for exactly eight numbers, inlined: the SPMD kernel's form, whose
    /// lanes are eight (a slice of unknown length cost it a call, two copies of unknown length
    /// and about 200 instructions a choice of eight: callgrind, Cornell).
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[inline(always)]
    pub fn sample_eight(&self, ua: &[f32; 8], out: &mut [(usize, f32); 8]) {
        use std::arch::x86_64::*;
        let n = self.bins.len();
        if n == 0 || n >= 1 << 24 {
            for k in 0..8 {
                out[k] = self.sample(ua[k]);
            }
            return;
        }
        let (mut idx, mut p) = ([0i32; 8], [0f32; 8]);
        // SAFETY: AVX2 is enabled at compile time. Every gathered index is a bin's field: `i` is
        // at most n − 1 in every lane (the unsigned minimum also catches the truncation's
        // 0x8000_0000 for NaN and the wrap of a negative), an alias is a bin index
        // (`AliasTable::new`), and `Bin` is `repr(C)` (q, p, alias at 0, 4, 8).
        let valid = unsafe {
            let uv = _mm256_loadu_ps(ua.as_ptr());
            let valid = _mm256_and_ps(
                _mm256_cmp_ps::<_CMP_GE_OQ>(uv, _mm256_setzero_ps()),
                _mm256_cmp_ps::<_CMP_LT_OQ>(uv, _mm256_set1_ps(1.0)),
            );
            let x = _mm256_mul_ps(uv, _mm256_set1_ps(n as f32));
            let i = _mm256_min_epu32(_mm256_cvttps_epi32(x), _mm256_set1_epi32(n as i32 - 1));
            let up = _mm256_min_ps(_mm256_sub_ps(x, _mm256_cvtepi32_ps(i)), _mm256_set1_ps(1.0 - f32::EPSILON));
            let base = self.bins.as_ptr() as *const f32;
            let three = _mm256_set1_epi32(3);
            let i3 = _mm256_mullo_epi32(i, three);
            let q = _mm256_i32gather_ps::<4>(base, i3);
            let alias = _mm256_i32gather_epi32::<4>(base as *const i32, _mm256_add_epi32(i3, _mm256_set1_epi32(2)));
            let keep = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_LT_OQ>(up, q));
            let chosen = _mm256_blendv_epi8(alias, i, keep);
            let pmf = _mm256_i32gather_ps::<4>(
                base,
                _mm256_add_epi32(_mm256_mullo_epi32(chosen, three), _mm256_set1_epi32(1)),
            );
            _mm256_storeu_si256(idx.as_mut_ptr().cast(), chosen);
            _mm256_storeu_ps(p.as_mut_ptr(), pmf);
            _mm256_movemask_ps(valid) as u32
        };
        for k in 0..8 {
            out[k] = (idx[k] as usize, p[k]);
        }
        if valid != 0xff {
            for k in 0..8 {
                if valid & (1 << k) == 0 {
                    out[k] = self.sample(ua[k]);
                }
            }
        }
    }

    #[inline]
    pub fn pmf(&self, i: usize) -> f32 {
        self.bins.get(i).map_or(0.0, |b| b.p)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frequencies_match_pmf() {
        let w = [1.0, 0.0, 3.0, 0.5, 10.0, 1e-3];
        let t = AliasTable::new(&w).unwrap();
        let n = 1_000_000;
        let mut counts = [0usize; 6];
        for k in 0..n {
            let u = (k as f32 + 0.5) / n as f32;
            let (i, p) = t.sample(u);
            assert!((p - t.pmf(i)).abs() < 1e-7);
            counts[i] += 1;
        }
        let total: f32 = w.iter().sum();
        for i in 0..6 {
            let expect = w[i] / total;
            let got = counts[i] as f32 / n as f32;
            assert!((got - expect).abs() < 1e-3, "bin {i}: {got} vs {expect}");
        }
        assert_eq!(counts[1], 0);
    }

    /// Eight at a time, the same index and pmf bits as one at a time: numbers spread over [0, 1),
    /// at and around every bin's edges and the kept/aliased split, 0 and the largest below 1,
    /// and numbers no sampler gives (1, NaN, negative, ∞); tables of 1 to 200 bins.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[test]
    fn lanes_sample_as_one_at_a_time() {
        let mut compared = 0;
        for n in [1usize, 2, 3, 5, 8, 13, 64, 200] {
            let w: Vec<f32> =
                (0..n).map(|i| ((i * 7919 % 13) as f32 + 0.5) * if i % 4 == 0 { 10.0 } else { 1.0 }).collect();
            let t = AliasTable::new(&w).expect("positive weights");
            let mut us = vec![0.0, 1.0 - f32::EPSILON / 2.0, 1.0, -0.0, -0.25, f32::NAN, f32::INFINITY];
            for b in 0..n {
                let edge = b as f32 / n as f32;
                let split = (b as f32 + t.bins[b].q) / n as f32;
                for v in [edge, split] {
                    us.extend([v, f32::from_bits(v.to_bits() + 1), f32::from_bits(v.to_bits().saturating_sub(1))]);
                }
            }
            us.extend((0..997).map(|k| (k as f32 * 0.618_034).fract()));
            for chunk in us.chunks(7).chain(us.chunks(8)).chain(us.chunks(3)) {
                let mut got = [(0usize, 0f32); 8];
                t.sample_lanes(chunk, &mut got);
                for (k, &u) in chunk.iter().enumerate() {
                    // `sample` itself on numbers it is given by samplers; outside [0, 1) only
                    // that the lanes give what it gives (it does not panic there either).
                    let want = t.sample(u);
                    assert_eq!((got[k].0, got[k].1.to_bits()), (want.0, want.1.to_bits()), "n {n} u {u:e}");
                    compared += 1;
                }
            }
        }
        assert!(compared > 10_000, "{compared}");
    }

    #[test]
    fn rejects_all_zero_and_non_finite() {
        assert!(AliasTable::new(&[0.0, f32::NAN, -1.0]).is_none());
        assert!(AliasTable::new(&[]).is_none());
    }
}
