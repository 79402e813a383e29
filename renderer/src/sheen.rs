//! KHR_materials_sheen: the "Charlie" sheen lobe of cloth-like fuzz layered over the base material.
//!
//! ```text
//! f_sheen = sheenColor · D_charlie(h) · V_charlie(wo, wi)
//! D_charlie(h) = (2 + 1/α) · sin(θh)^(1/α) / (2π),      α = sheenRoughness²
//! V_charlie = 1 / ((1 + Λ(cos θo) + Λ(cos θi)) · 4 cos θo cos θi)
//! f = f_sheen + (1 − max(sheenColor) · E(cos θo, α)) · f_base
//! ```
//! References: Estevez & Kulla 2017, "Production Friendly Microfacet Sheen BRDF" (D and the fitted Λ);
//! the KHR_materials_sheen specification (layering and albedo scaling with the directional albedo E
//! of the sheen lobe with white color). E is tabulated once per process by numerical integration of
//! exactly the `eval` below, so the layered BSDF conserves energy to the table's accuracy
//! (the furnace test in `tests/furnace.rs` checks it).
//!
//! Sampling: cosine-weighted hemisphere (the lobe is broad; its peak is at grazing angles where a
//! cosine distribution is weakest, but its contribution there is scaled by cos θi too).

use crate::math::{cosine_hemisphere_pdf, sample_cosine_hemisphere, Vec2, Vec3, PI};
use std::sync::OnceLock;

/// Smallest sheen roughness used: below it the Charlie distribution is a spike at grazing half
/// vectors that no sampling strategy here resolves (Filament clamps likewise).
pub const MIN_SHEEN_ROUGHNESS: f32 = 0.07;

/// The sheen layer at one shading point.
#[derive(Clone, Copy, Debug)]
pub struct Sheen {
    pub color: Vec3,
    /// sheenRoughness, clamped to [MIN_SHEEN_ROUGHNESS, 1].
    pub roughness: f32,
}

impl Sheen {
    pub fn new(color: Vec3, roughness: f32) -> Self {
        let r = if roughness.is_finite() { roughness.clamp(MIN_SHEEN_ROUGHNESS, 1.0) } else { 1.0 };
        Sheen { color: color.clamp(Vec3::ZERO, Vec3::ONE), roughness: r }
    }

    #[inline]
    fn alpha(&self) -> f32 {
        self.roughness * self.roughness
    }

    /// D_charlie(h) (Estevez & Kulla 2017, eq. 2).
    #[inline]
    fn d(alpha: f32, h: Vec3) -> f32 {
        let inv = 1.0 / alpha;
        let sin2 = (1.0 - h.z * h.z).max(0.0);
        (2.0 + inv) * sin2.powf(0.5 * inv) / (2.0 * PI)
    }

    /// Λ(cos θ) from the fitted curve of Estevez & Kulla 2017 (§3), interpolated in (1 − α)².
    #[inline]
    fn lambda(alpha: f32, cos: f32) -> f32 {
        let l = |x: f32| {
            let t = (1.0 - alpha) * (1.0 - alpha);
            let lerp = |a0: f32, a1: f32| a0 + (a1 - a0) * t;
            let (a, b, c, d, e) = (
                lerp(21.5473, 25.3245),
                lerp(3.82987, 3.32435),
                lerp(0.19823, 0.16801),
                lerp(-1.97760, -1.27393),
                lerp(-4.32054, -4.85967),
            );
            a / (1.0 + b * x.max(1e-6).powf(c)) + d * x + e
        };
        let cos = cos.abs();
        if cos < 0.5 {
            l(cos).exp()
        } else {
            (2.0 * l(0.5) - l(1.0 - cos)).exp()
        }
    }

    /// The white (sheenColor = 1) lobe D·V at directions in the upper hemisphere.
    #[inline]
    fn white(alpha: f32, wo: Vec3, wi: Vec3) -> f32 {
        if wo.z <= 0.0 || wi.z <= 0.0 {
            return 0.0;
        }
        Self::white_given(alpha, wo, wi, Self::lambda(alpha, wo.z), Self::lambda(alpha, wi.z))
    }

    /// [`Self::white`] given Λ(cos θo) and Λ(cos θi) (pure functions of `alpha` and each
    /// direction's cosine, so the albedo table's integration works each out once per direction
    /// instead of once per pair: the same numbers).
    #[inline]
    fn white_given(alpha: f32, wo: Vec3, wi: Vec3, lambda_o: f32, lambda_i: f32) -> f32 {
        if wo.z <= 0.0 || wi.z <= 0.0 {
            return 0.0;
        }
        let h = (wo + wi).normalize_or_zero();
        if h == Vec3::ZERO {
            return 0.0;
        }
        // Clamped to 1 as the Khronos sample renderer does: the fitted Λ is not exact at grazing angles.
        let v = (1.0 / ((1.0 + lambda_o + lambda_i) * 4.0 * wo.z * wi.z)).min(1.0);
        let f = Self::d(alpha, h) * v;
        if f.is_finite() {
            f
        } else {
            0.0
        }
    }

    /// The lobe, scaled down where its directional albedo would exceed 1 (at grazing angles and low
    /// roughness the fitted masking term lets the Charlie lobe reflect more than it receives; this
    /// renormalisation is this renderer's choice, so that no sheen can create energy).
    pub fn eval(&self, wo: Vec3, wi: Vec3) -> Vec3 {
        let e = albedo_table().lookup(wo.z, self.roughness);
        self.color * (Self::white(self.alpha(), wo, wi) / e.max(1.0))
    }

    pub fn pdf(&self, _wo: Vec3, wi: Vec3) -> f32 {
        if wi.z <= 0.0 {
            return 0.0;
        }
        cosine_hemisphere_pdf(wi.z)
    }

    pub fn sample(&self, u: Vec2) -> Vec3 {
        sample_cosine_hemisphere(u)
    }

    /// Directional albedo of the (renormalised) white lobe seen from cos θo = `mu`.
    pub fn albedo(&self, mu: f32) -> f32 {
        albedo_table().lookup(mu, self.roughness).min(1.0)
    }

    /// The factor the layers below are scaled by: 1 − max(sheenColor)·E(cos θo).
    pub fn scaling(&self, mu: f32) -> f32 {
        (1.0 - self.color.max_element() * self.albedo(mu)).clamp(0.0, 1.0)
    }
}

const TABLE_MU: usize = 32;
const TABLE_R: usize = 32;

struct AlbedoTable {
    e: Vec<f32>,
}

impl AlbedoTable {
    fn roughness_at(j: usize) -> f32 {
        MIN_SHEEN_ROUGHNESS + (1.0 - MIN_SHEEN_ROUGHNESS) * j as f32 / (TABLE_R - 1) as f32
    }

    /// μ = t² on a uniform t grid: finer near grazing, where E changes fastest.
    fn mu_at(i: usize) -> f32 {
        (i as f32 / (TABLE_MU - 1) as f32).powi(2).max(1e-4)
    }

    /// E(μo, r) = ∫ f cos θi dωi by the midpoint rule in (cos θi, φ); the lobe is symmetric in φ.
    ///
    /// Built when a scene with sheen is first prepared (the light choice's pilot shades it), so its
    /// time is every such render's: the 32 × 32 entries' 4.2 M lobe values took 0.22 s of a
    /// one-thread `tessera render` of `scenes/blender/materials.glb` when each value worked out
    /// both Λ and the direction's sine and cosine again. Those depend on one direction each, so
    /// they are worked out once per direction here, and the roughness rows are integrated in
    /// parallel: every term is the same number, summed in the same order
    /// ([`AlbedoTable::build_reference`] in the tests holds it to the plain loop's bits).
    fn build() -> Self {
        use rayon::prelude::*;
        let (n_mu, n_phi) = (64usize, 64usize);
        // φ over [0, π] (doubled below); its cosine and sine are each row's.
        let phis: Vec<(f32, f32)> = (0..n_phi)
            .map(|b| {
                let phi = PI * (b as f32 + 0.5) / n_phi as f32;
                (phi.cos(), phi.sin())
            })
            .collect();
        let rows: Vec<Vec<f32>> = (0..TABLE_R)
            .into_par_iter()
            .map(|j| {
                let alpha = Self::roughness_at(j).powi(2);
                // Per incoming cosine: s, μi = s² (points concentrated near the horizon, where the
                // lobe peaks), sin θi and Λ(μi).
                let incoming: Vec<(f32, f32, f32, f32)> = (0..n_mu)
                    .map(|a| {
                        let s = (a as f32 + 0.5) / n_mu as f32;
                        let mu_i = s * s;
                        (s, mu_i, (1.0 - mu_i * mu_i).max(0.0).sqrt(), Sheen::lambda(alpha, mu_i))
                    })
                    .collect();
                (0..TABLE_MU)
                    .map(|i| {
                        let mu_o = Self::mu_at(i);
                        let wo = Vec3::new((1.0 - mu_o * mu_o).max(0.0).sqrt(), 0.0, mu_o);
                        let lambda_o = Sheen::lambda(alpha, mu_o);
                        let mut sum = 0.0f64;
                        for &(s, mu_i, sin_i, lambda_i) in &incoming {
                            for &(cos_phi, sin_phi) in &phis {
                                let wi = Vec3::new(sin_i * cos_phi, sin_i * sin_phi, mu_i);
                                // dω = dμ dφ, dμ = 2 s ds; φ over [0, π] doubled.
                                let f = Sheen::white_given(alpha, wo, wi, lambda_o, lambda_i);
                                sum += (f * mu_i * 2.0 * s) as f64;
                            }
                        }
                        (sum * (1.0 / n_mu as f64) * (PI as f64 / n_phi as f64) * 2.0) as f32
                    })
                    .collect()
            })
            .collect();
        AlbedoTable { e: rows.concat() }
    }

    fn lookup(&self, mu: f32, roughness: f32) -> f32 {
        let x = (mu.clamp(0.0, 1.0).sqrt() * (TABLE_MU - 1) as f32).min((TABLE_MU - 1) as f32 - 1e-4);
        let y = ((roughness - MIN_SHEEN_ROUGHNESS) / (1.0 - MIN_SHEEN_ROUGHNESS) * (TABLE_R - 1) as f32)
            .clamp(0.0, (TABLE_R - 1) as f32 - 1e-4);
        let (i, j) = (x as usize, y as usize);
        let (fx, fy) = (x - i as f32, y - j as f32);
        let at = |i: usize, j: usize| self.e[j * TABLE_MU + i];
        let top = at(i, j) * (1.0 - fx) + at(i + 1, j) * fx;
        let bottom = at(i, j + 1) * (1.0 - fx) + at(i + 1, j + 1) * fx;
        top * (1.0 - fy) + bottom * fy
    }
}

fn albedo_table() -> &'static AlbedoTable {
    static TABLE: OnceLock<AlbedoTable> = OnceLock::new();
    TABLE.get_or_init(AlbedoTable::build)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn charlie_d_is_normalized() {
        // ∫ D(h) cos θh dω = 1.
        for r in [MIN_SHEEN_ROUGHNESS, 0.3, 0.6, 1.0] {
            let alpha = r * r;
            let n = 20000;
            let mut sum = 0.0f64;
            for i in 0..n {
                let mu = (i as f32 + 0.5) / n as f32;
                let sin = (1.0 - mu * mu).sqrt();
                sum += (Sheen::d(alpha, Vec3::new(sin, 0.0, mu)) * mu) as f64 * 2.0 * PI as f64 / n as f64;
            }
            assert!((sum - 1.0).abs() < 0.01, "roughness {r}: {sum}");
        }
    }

    impl AlbedoTable {
        /// The table as it was first written: every lobe value by [`Sheen::white`], one row
        /// after another.
        fn build_reference() -> Self {
            let (n_mu, n_phi) = (64usize, 64usize);
            let mut e = vec![0.0f32; TABLE_MU * TABLE_R];
            for j in 0..TABLE_R {
                let alpha = Self::roughness_at(j).powi(2);
                for i in 0..TABLE_MU {
                    let mu_o = Self::mu_at(i);
                    let wo = Vec3::new((1.0 - mu_o * mu_o).max(0.0).sqrt(), 0.0, mu_o);
                    let mut sum = 0.0f64;
                    for a in 0..n_mu {
                        let s = (a as f32 + 0.5) / n_mu as f32;
                        let mu_i = s * s;
                        let sin_i = (1.0 - mu_i * mu_i).max(0.0).sqrt();
                        for b in 0..n_phi {
                            let phi = PI * (b as f32 + 0.5) / n_phi as f32;
                            let wi = Vec3::new(sin_i * phi.cos(), sin_i * phi.sin(), mu_i);
                            sum += (Sheen::white(alpha, wo, wi) * mu_i * 2.0 * s) as f64;
                        }
                    }
                    e[j * TABLE_MU + i] = (sum * (1.0 / n_mu as f64) * (PI as f64 / n_phi as f64) * 2.0) as f32;
                }
            }
            AlbedoTable { e }
        }
    }

    #[test]
    fn albedo_table_is_the_plain_integration_bit_for_bit() {
        let (fast, plain) = (AlbedoTable::build(), AlbedoTable::build_reference());
        assert_eq!(fast.e.len(), plain.e.len());
        for (k, (a, b)) in fast.e.iter().zip(&plain.e).enumerate() {
            assert_eq!(
                a.to_bits(),
                b.to_bits(),
                "entry {k} (roughness row {}, μ column {}): {a} against {b}",
                k / TABLE_MU,
                k % TABLE_MU
            );
        }
    }

    #[test]
    fn albedo_is_below_one_and_finite() {
        for r in [MIN_SHEEN_ROUGHNESS, 0.5, 1.0] {
            for mu in [0.0f32, 0.01, 0.5, 1.0] {
                let e = Sheen::new(Vec3::ONE, r).albedo(mu);
                assert!(e.is_finite() && (0.0..=1.0).contains(&e), "r {r} mu {mu}: {e}");
            }
        }
    }
}
