//! Walker/Vose alias table: O(1) sampling of a discrete distribution (Vose 1991; pbrt-v4 §A.1).

#[derive(Clone, Debug, Default)]
pub struct AliasTable {
    bins: Vec<Bin>,
}

#[derive(Clone, Copy, Debug)]
struct Bin {
    /// Probability of keeping this bin when it is chosen uniformly.
    q: f32,
    /// The pmf of this index, stored so that `pmf()` is exact.
    p: f32,
    alias: u32,
}

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
        let i = (x as usize).min(n - 1);
        let up = (x - i as f32).min(1.0 - f32::EPSILON);
        let idx = if up < self.bins[i].q { i } else { self.bins[i].alias as usize };
        (idx, self.bins[idx].p)
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

    #[test]
    fn rejects_all_zero_and_non_finite() {
        assert!(AliasTable::new(&[0.0, f32::NAN, -1.0]).is_none());
        assert!(AliasTable::new(&[]).is_none());
    }
}
