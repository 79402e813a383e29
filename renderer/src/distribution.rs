//! Piecewise-constant 1D and 2D distributions for importance sampling tabulated functions (pbrt-v4
//! §A.4 `PiecewiseConstant1D/2D`): sample a continuous point in [0,1)² with density proportional to the
//! table, and evaluate that density.

/// What one 1D table is built into: per bin (CDF at its start, density), plus one entry for the
/// CDF's end; the guide table; the integral.
struct Built {
    entries: Vec<[f32; 2]>,
    guide: Vec<u32>,
    integral: f32,
}

/// Builds the tables of `func` (non-negative; an all-zero table becomes uniform). Each entry holds
/// the CDF at the bin's start next to the bin's density, so the bin a search lands on costs one
/// cache line, not one per array (sampling an environment map is a few cache misses deep).
fn build(func: &[f32]) -> Built {
    let n = func.len().max(1);
    let func: Vec<f32> = if func.is_empty() {
        vec![1.0]
    } else {
        func.iter().map(|&f| if f.is_finite() && f > 0.0 { f } else { 0.0 }).collect()
    };
    let mut cdf = vec![0.0f64; n + 1];
    for i in 0..n {
        cdf[i + 1] = cdf[i] + func[i] as f64 / n as f64;
    }
    let integral = cdf[n];
    let (func, cdf): (Vec<f32>, Vec<f32>) = if integral > 0.0 {
        (func, cdf.iter().map(|&c| (c / integral) as f32).collect())
    } else {
        (vec![1.0; n], (0..=n).map(|i| i as f32 / n as f32).collect())
    };
    // An all-zero table samples uniformly (density 1) but reports its true integral, 0: a 2D
    // table's all-zero row must weigh nothing in the marginal. (It used to report 1, which gave
    // the rows MIS compensation zeroes out a share of the environment's light samples.)
    let density_scale = if integral > 0.0 { integral as f32 } else { 1.0 };
    let g = guide_size(n);
    let guide = (0..=g).map(|k| cdf.partition_point(|&c| c <= k as f32 / g as f32) as u32).collect();
    let entries = (0..=n).map(|i| [cdf[i], if i < n { func[i] / density_scale } else { 0.0 }]).collect();
    Built { entries, guide, integral: integral as f32 }
}

/// The guide table's size G for a table of `n` bins (it has G + 1 entries): `n` rounded up to a
/// power of two, at most 2^20. With a slot per bin, a u's search range is a bin or two wherever
/// the function is bright (a bright bin spans several slots), which is where samples land; half
/// as many slots (the size until the fortieth round, docs/performance-journal.md) left a binary search of a
/// few steps, each a dependent load (envlit: 0.950 and 0.975 of the time in two series of
/// alternating renders, 0.3 % fewer instructions). The guide is 4 bytes a bin beside the
/// entries' 8.
fn guide_size(n: usize) -> usize {
    n.next_power_of_two().min(1 << 20)
}

/// A 1D table as sampling sees it: `n + 1` entries (CDF at the bin's start, density) and the
/// guide table (Chen & Asau 1974, "On Generating Random Variates from an Empirical
/// Distribution"): `guide[k]` = the number of CDF entries ≤ k/G, for k in 0..=G, G a power of
/// two. A u in [k/G, (k+1)/G) has its answer between `guide[k]` and `guide[k+1]`, so the binary
/// search runs over those few entries instead of the whole CDF (an environment map's row has
/// thousands; the search was 16 % of an environment-lit render). Same answer as the whole
/// search, always: k/G is exact in f32 and the answer is monotone in u.
#[derive(Clone, Copy)]
struct Table<'a> {
    entries: &'a [[f32; 2]],
    guide: &'a [u32],
}

impl Table<'_> {
    fn bins(&self) -> usize {
        self.entries.len() - 1
    }

    /// The number of CDF entries ≤ u (a search of the whole CDF), through the guide table.
    #[inline]
    fn entries_at_most(&self, u: f32) -> usize {
        let (lo, hi) = self.search_range(u);
        self.entries_at_most_in(u, lo, hi)
    }

    /// Where [`Self::entries_at_most`] searches: the guide's two entries around u (the whole CDF
    /// for a u outside [0, 1)). The first of a sample's dependent loads (`sample_batch`).
    #[inline(always)]
    fn search_range(&self, u: f32) -> (usize, usize) {
        self.range_of_slot(self.guide_slot(u))
    }

    /// [`Self::search_range`] given u's [`Self::guide_slot`].
    #[inline(always)]
    fn range_of_slot(&self, k: Option<usize>) -> (usize, usize) {
        match k {
            Some(k) => (self.guide[k] as usize, self.guide[k + 1] as usize),
            None => (0, self.entries.len()),
        }
    }

    /// The guide entry k whose pair [`Self::search_range`] reads for u (entries k and k + 1);
    /// None for a u outside [0, 1), which searches the whole CDF.
    #[inline(always)]
    fn guide_slot(&self, u: f32) -> Option<usize> {
        if !(0.0..1.0).contains(&u) {
            return None;
        }
        let g = self.guide.len() - 1;
        // u·G is in [0, G] (G ≤ 2^20): its truncation as a u32 is the same integer as a usize,
        // without the unsigned 64-bit conversion's range fix-ups (x86-64 has none native).
        Some(((u * g as f32) as u32 as usize).min(g - 1))
    }

    /// [`Self::entries_at_most`] given its [`Self::search_range`].
    #[inline(always)]
    fn entries_at_most_in(&self, u: f32, lo: usize, hi: usize) -> usize {
        lo + self.entries[lo..hi].partition_point(|e| e[0] <= u)
    }

    /// Returns (x in [0,1), pdf(x), bin).
    #[inline]
    fn sample(&self, u: f32) -> (f32, f32, usize) {
        self.sample_at(u, self.entries_at_most(u))
    }

    /// [`Self::sample`] given [`Self::entries_at_most`]`(u)`.
    #[inline(always)]
    fn sample_at(&self, u: f32, at_most: usize) -> (f32, f32, usize) {
        let n = self.bins();
        // Largest i with cdf[i] <= u.
        let i = match at_most {
            0 => 0,
            k => (k - 1).min(n - 1),
        };
        let ([c0, pdf], c1) = (self.entries[i], self.entries[i + 1][0]);
        let width = c1 - c0;
        let du = if width > 0.0 { ((u - c0) / width).clamp(0.0, 1.0) } else { 0.5 };
        let x = ((i as f32 + du) / n as f32).min(1.0 - f32::EPSILON);
        (x, pdf, i)
    }

    /// Density at x in [0,1).
    #[inline]
    fn pdf(&self, x: f32) -> f32 {
        self.entries[self.bin(x)][1]
    }

    /// The bin [`Self::pdf`] reads for x.
    #[inline(always)]
    fn bin(&self, x: f32) -> usize {
        let n = self.bins();
        // As u32: the same integer for any x (both saturate; n is far below 2^32), cheaper.
        ((x * n as f32) as u32 as usize).min(n - 1)
    }
}

#[derive(Clone, Debug)]
pub struct Distribution1D {
    entries: Vec<[f32; 2]>,
    guide: Vec<u32>,
}

impl Distribution1D {
    /// `func` must be non-negative; an all-zero table becomes uniform.
    pub fn new(func: &[f32]) -> Self {
        let Built { entries, guide, .. } = build(func);
        Distribution1D { entries, guide }
    }

    fn table(&self) -> Table<'_> {
        Table { entries: &self.entries, guide: &self.guide }
    }

    pub fn len(&self) -> usize {
        self.entries.len() - 1
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Returns (x in [0,1), pdf(x), bin).
    pub fn sample(&self, u: f32) -> (f32, f32, usize) {
        self.table().sample(u)
    }

    /// Density at x in [0,1).
    pub fn pdf(&self, x: f32) -> f32 {
        self.table().pdf(x)
    }
}

/// How many samples [`Distribution2D::sample_batch`] takes a step at a time.
pub const BATCH: usize = 8;

/// f(u, v) tabulated on `nu × nv` cells (rows are v), sampled as marginal in v then conditional in u.
/// The rows' tables sit back to back in two flat arrays (row r's at r·(nu+1) and r·(G+1)), so
/// reaching a row is arithmetic, not another pointer to follow.
#[derive(Clone, Debug)]
pub struct Distribution2D {
    nu: usize,
    nv: usize,
    row_entries: Vec<[f32; 2]>,
    row_guides: Vec<u32>,
    guide_len: usize,
    marginal: Distribution1D,
}

impl Distribution2D {
    pub fn new(func: &[f32], nu: usize, nv: usize) -> Self {
        let (nu, nv) = (nu.max(1), nv.max(1));
        let mut row_entries = Vec::with_capacity(nv * (nu + 1));
        let mut row_guides = Vec::new();
        let mut rows = Vec::with_capacity(nv);
        // Every row has nu bins, so the same guide length.
        let guide_len = guide_size(nu) + 1;
        let zeros = vec![0.0; nu];
        for v in 0..nv {
            // A short table's missing rows are all zero (uniform), so every row has nu bins.
            let b = build(func.get(v * nu..(v + 1) * nu).unwrap_or(&zeros));
            debug_assert_eq!(b.guide.len(), guide_len);
            row_entries.extend_from_slice(&b.entries);
            row_guides.extend_from_slice(&b.guide);
            rows.push(b.integral);
        }
        Distribution2D { nu, nv, row_entries, row_guides, guide_len, marginal: Distribution1D::new(&rows) }
    }

    fn row(&self, r: usize) -> Table<'_> {
        Table {
            entries: &self.row_entries[r * (self.nu + 1)..(r + 1) * (self.nu + 1)],
            guide: &self.row_guides[r * self.guide_len..(r + 1) * self.guide_len],
        }
    }

    /// [`Self::sample`] of each of `us` into `out`, the same numbers, its dependent loads taken a
    /// step at a time across [`BATCH`] samples (the marginal and the row's guide entries for all,
    /// then each row's search): an environment map's rows are megabytes, so each step is a cache
    /// miss, and one sample's misses follow one another while different samples' can overlap,
    /// but only when their loads are issued close together rather than a whole sample apart.
    ///
    /// Each step first asks the cache for the lines the next one reads (the guide entries, then
    /// the CDF entries at both ends of each search): a step's loop over eight samples is longer
    /// than the processor's window, so without the prefetches its last samples' loads were only
    /// issued once its first ones had arrived.
    pub fn sample_batch(&self, us: &[[f32; 2]], out: &mut [([f32; 2], f32)]) {
        let n = us.len().min(out.len());
        for (us, out) in us[..n].chunks(BATCH).zip(out[..n].chunks_mut(BATCH)) {
            // Per sample: its v and density, its row's table and the guide slot of its u, made
            // once here and read by the steps below (made again at each step, they cost envlit
            // 1.1 % of its instructions: callgrind, 64×48, 16 spp, 180.66 → 178.74 M).
            let empty = Table { entries: &[], guide: &[] };
            let mut rows = [(0f32, 0f32, empty, None); BATCH];
            for (u, r) in us.iter().zip(&mut rows) {
                let (v, pdf_v, row) = self.marginal.sample(u[1]);
                let t = self.row(row);
                let k = t.guide_slot(u[0]);
                if let Some(k) = k {
                    crate::accel::prefetch(&t.guide[k]);
                }
                *r = (v, pdf_v, t, k);
            }
            let mut ranges = [(0usize, 0usize); BATCH];
            for (&(_, _, t, k), range) in rows.iter().zip(&mut ranges) {
                let (lo, hi) = t.range_of_slot(k);
                for e in [lo, hi.max(lo + 1) - 1] {
                    t.entries.get(e).map(crate::accel::prefetch);
                }
                *range = (lo, hi);
            }
            for (((u, &(v, pdf_v, t, _)), &(lo, hi)), o) in us.iter().zip(&rows).zip(&ranges).zip(out) {
                let (x, pdf_u, _) = t.sample_at(u[0], t.entries_at_most_in(u[0], lo, hi));
                *o = ([x, v], pdf_u * pdf_v);
            }
        }
    }

    /// Returns ((u, v), pdf) with pdf relative to the unit square.
    pub fn sample(&self, u: [f32; 2]) -> ([f32; 2], f32) {
        let (v, pdf_v, row) = self.marginal.sample(u[1]);
        let (x, pdf_u, _) = self.row(row).sample(u[0]);
        ([x, v], pdf_u * pdf_v)
    }

    pub fn pdf(&self, uv: [f32; 2]) -> f32 {
        self.row_at(uv[1]).pdf(uv[0]) * self.marginal.pdf(uv[1])
    }

    /// The row [`Self::pdf`] reads at v.
    #[inline(always)]
    fn row_at(&self, v: f32) -> Table<'_> {
        self.row(((v * self.nv as f32) as u32 as usize).min(self.nv - 1))
    }

    /// Asks the cache for the row entry [`Self::pdf`]`(uv)` reads (the marginal is small enough
    /// to stay cached).
    #[inline(always)]
    pub fn prefetch_pdf(&self, uv: [f32; 2]) {
        let t = self.row_at(uv[1]);
        crate::accel::prefetch(&t.entries[t.bin(uv[0])]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 2D batch of any length is each sample's own `sample`, bit for bit: more samples than
    /// one step's [`BATCH`], random and at the square's edges (1 itself takes the whole-table
    /// search).
    #[test]
    fn batch_of_any_length_equals_single_samples() {
        let (nu, nv) = (40usize, 9usize);
        let func: Vec<f32> = (0..nu * nv).map(|i| if i % 7 == 0 { 0.0 } else { (i % 13) as f32 }).collect();
        let d = Distribution2D::new(&func, nu, nv);
        let mut us: Vec<[f32; 2]> =
            (0..100u64).map(|i| [crate::sampler::hash_unit(2 * i), crate::sampler::hash_unit(2 * i + 1)]).collect();
        us.extend([[0.0, 0.0], [1.0, 0.5], [0.5, 1.0], [1.0 - f32::EPSILON / 2.0, 1.0]]);
        let mut out = vec![([f32::NAN; 2], f32::NAN); us.len()];
        d.sample_batch(&us, &mut out);
        for (u, o) in us.iter().zip(&out) {
            let (uv, pdf) = d.sample(*u);
            assert_eq!((o.0.map(f32::to_bits), o.1.to_bits()), (uv.map(f32::to_bits), pdf.to_bits()), "u {u:?}");
        }
    }

    /// The guide has a slot per bin: on a bright stretch (here a uniform table, every bin bright)
    /// each slot's search range holds one CDF entry, so a sample there costs no search at all;
    /// a peaked table's samples mostly land in ranges of one or two entries. (Half as many
    /// slots gave two entries a slot on the uniform table.)
    #[test]
    fn guide_slots_narrow_bright_searches_to_one_entry() {
        for n in [8usize, 64, 1000, 1024] {
            let d = Distribution1D::new(&vec![1.0; n]);
            let t = d.table();
            let g = t.guide.len() - 1;
            assert!(g >= n, "n {n}: {g} slots");
            for k in 0..g {
                let (lo, hi) = t.range_of_slot(Some(k));
                assert!(hi - lo <= 1, "n {n}, slot {k}: range {lo}..{hi}");
            }
        }
        // A peaked table: a uniform u's expected range is short.
        let func: Vec<f32> = (0..1024).map(|i| if (500..520).contains(&i) { 1000.0 } else { 0.1 }).collect();
        let d = Distribution1D::new(&func);
        let t = d.table();
        let m = 4096;
        let total: usize = (0..m)
            .map(|i| {
                let (lo, hi) = t.search_range((i as f32 + 0.5) / m as f32);
                hi - lo
            })
            .sum();
        assert!(total as f64 / m as f64 <= 1.5, "mean range {}", total as f64 / m as f64);
    }

    #[test]
    fn sample_and_pdf_agree_and_integrate_to_one() {
        let d = Distribution1D::new(&[0.0, 1.0, 3.0, 0.0, 4.0]);
        let n = 100_000;
        let mut hist = [0usize; 5];
        for k in 0..n {
            let (x, p, i) = d.sample((k as f32 + 0.5) / n as f32);
            assert!((p - d.pdf(x)).abs() < 1e-6, "x {x}");
            hist[i] += 1;
        }
        assert_eq!(hist[0], 0);
        assert_eq!(hist[3], 0);
        assert!((hist[4] as f32 / n as f32 - 0.5).abs() < 1e-3);
        let integral: f32 = (0..1000).map(|i| d.pdf((i as f32 + 0.5) / 1000.0) / 1000.0).sum();
        assert!((integral - 1.0).abs() < 1e-4);
        let z = Distribution1D::new(&[0.0, 0.0]);
        assert_eq!(z.pdf(0.3), 1.0);
    }

    #[test]
    fn two_d_pdf_matches_the_table() {
        let f = [1.0, 2.0, 0.0, 5.0, 1.0, 1.0];
        let d = Distribution2D::new(&f, 3, 2);
        let total: f32 = f.iter().sum::<f32>() / 6.0;
        assert!((d.pdf([0.5, 0.75]) - 1.0 / total).abs() < 1e-5);
        assert!((d.pdf([0.1, 0.25]) - 1.0 / total).abs() < 1e-5);
        let (uv, p) = d.sample([0.9, 0.9]);
        assert!((p - d.pdf(uv)).abs() < 1e-5);
    }

    /// A row of zeros gets no samples and density 0, however many rows are zero (MIS compensation
    /// zeroes whole rows of an environment map). An all-zero row used to enter the marginal with
    /// weight 1, as if it were uniform: here that row drew 1/(1 + 2/3) = 60 % of the samples.
    #[test]
    fn zero_rows_weigh_nothing() {
        let f = [0.0, 0.0, 0.0, 1.0, 0.0, 1.0];
        let d = Distribution2D::new(&f, 3, 2);
        for k in 0..1000 {
            let u = [crate::sampler::hash_unit(2 * k), crate::sampler::hash_unit(2 * k + 1)];
            let (uv, p) = d.sample(u);
            assert!(uv[1] >= 0.5, "a sample in the zero row: {uv:?}");
            assert!(p > 0.0 && (p - d.pdf(uv)).abs() < 1e-5, "{uv:?}: {p} vs {}", d.pdf(uv));
        }
        assert_eq!(d.pdf([0.5, 0.25]), 0.0);
        // All rows zero: uniform over the square.
        let z = Distribution2D::new(&[0.0; 6], 3, 2);
        assert!((z.pdf([0.1, 0.9]) - 1.0).abs() < 1e-6 && (z.pdf([0.9, 0.1]) - 1.0).abs() < 1e-6);
    }

    /// The guide table finds what a search of the whole CDF finds, for every u of a fine grid,
    /// every CDF entry and its neighbours, on peaked, flat and sparse tables.
    #[test]
    fn guide_table_answers_as_the_whole_search() {
        let u = crate::sampler::hash_unit;
        let tables: Vec<Vec<f32>> = vec![
            vec![1.0],
            vec![0.0, 0.0, 3.0],
            (0..1000).map(|i| if i == 517 { 1e6 } else { u(i) }).collect(), // a sun
            (0..4096).map(|i| if i % 97 == 0 { u(i) } else { 0.0 }).collect(),
            (0..333).map(|i| (i as f32 * 0.1).sin().max(0.0) * 10.0).collect(),
        ];
        for f in &tables {
            let d = Distribution1D::new(f);
            let mut us: Vec<f32> = (0..100_000).map(|k| k as f32 / 100_000.0).collect();
            for e in &d.entries {
                let c = e[0];
                us.extend([c, f32::from_bits(c.to_bits().saturating_sub(1)), f32::from_bits(c.to_bits() + 1)]);
            }
            us.extend([0.0, 1.0 - f32::EPSILON, 1.0, -0.0, -1e-30, 2.0, f32::NAN]);
            for u in us {
                let whole = d.entries.partition_point(|e| e[0] <= u);
                assert_eq!(d.table().entries_at_most(u), whole, "u = {u} ({} bins)", f.len());
            }
        }
    }
}
