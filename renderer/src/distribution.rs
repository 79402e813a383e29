//! Piecewise-constant 1D and 2D distributions for importance sampling tabulated functions (pbrt-v4
//! §A.4 `PiecewiseConstant1D/2D`): sample a continuous point in [0,1)² with density proportional to the
//! table, and evaluate that density.

#[derive(Clone, Debug)]
pub struct Distribution1D {
    func: Vec<f32>,
    /// CDF with `func.len() + 1` entries, cdf[0] = 0, cdf[n] = 1.
    cdf: Vec<f32>,
    integral: f32,
}

impl Distribution1D {
    /// `func` must be non-negative; an all-zero table becomes uniform.
    pub fn new(func: &[f32]) -> Self {
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
        let (func, cdf) = if integral > 0.0 {
            (func, cdf.iter().map(|&c| (c / integral) as f32).collect())
        } else {
            (vec![1.0; n], (0..=n).map(|i| i as f32 / n as f32).collect())
        };
        Distribution1D { func, cdf, integral: if integral > 0.0 { integral as f32 } else { 1.0 } }
    }

    pub fn len(&self) -> usize {
        self.func.len()
    }

    pub fn is_empty(&self) -> bool {
        self.func.is_empty()
    }

    pub fn integral(&self) -> f32 {
        self.integral
    }

    /// Returns (x in [0,1), pdf(x), bin).
    pub fn sample(&self, u: f32) -> (f32, f32, usize) {
        let n = self.func.len();
        // Largest i with cdf[i] <= u.
        let i = match self.cdf.partition_point(|&c| c <= u) {
            0 => 0,
            k => (k - 1).min(n - 1),
        };
        let width = self.cdf[i + 1] - self.cdf[i];
        let du = if width > 0.0 { ((u - self.cdf[i]) / width).clamp(0.0, 1.0) } else { 0.5 };
        let x = ((i as f32 + du) / n as f32).min(1.0 - f32::EPSILON);
        (x, self.func[i] / self.integral, i)
    }

    /// Density at x in [0,1).
    pub fn pdf(&self, x: f32) -> f32 {
        let n = self.func.len();
        let i = ((x * n as f32) as usize).min(n - 1);
        self.func[i] / self.integral
    }
}

/// f(u, v) tabulated on `nu × nv` cells (rows are v), sampled as marginal in v then conditional in u.
#[derive(Clone, Debug)]
pub struct Distribution2D {
    conditional: Vec<Distribution1D>,
    marginal: Distribution1D,
}

impl Distribution2D {
    pub fn new(func: &[f32], nu: usize, nv: usize) -> Self {
        let conditional: Vec<Distribution1D> =
            (0..nv).map(|v| Distribution1D::new(&func[v * nu..(v + 1) * nu])).collect();
        let rows: Vec<f32> = conditional.iter().map(|c| c.integral()).collect();
        Distribution2D { marginal: Distribution1D::new(&rows), conditional }
    }

    /// Returns ((u, v), pdf) with pdf relative to the unit square.
    pub fn sample(&self, u: [f32; 2]) -> ([f32; 2], f32) {
        let (v, pdf_v, row) = self.marginal.sample(u[1]);
        let (x, pdf_u, _) = self.conditional[row].sample(u[0]);
        ([x, v], pdf_u * pdf_v)
    }

    pub fn pdf(&self, uv: [f32; 2]) -> f32 {
        let nv = self.conditional.len();
        let row = ((uv[1] * nv as f32) as usize).min(nv - 1);
        self.conditional[row].pdf(uv[0]) * self.marginal.pdf(uv[1])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
