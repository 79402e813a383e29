//! Environment lighting: a lat-long radiance map (OpenEXR or Radiance .hdr) or a uniform color, with
//! importance sampling of (luminance − mean) × sin θ (pbrt-v4 §12.5 `ImageInfiniteLight`, with
//! its MIS compensation: see `from_texels`).
//!
//! Mapping (glTF coordinates, +Y up; what Blender shows after importing the glTF with the same world
//! texture, and Mitsuba's `envmap` with `to_world = rotate(Y, 90°)`): for a unit world direction d,
//! `u = 0.5 + atan2(d.z, d.x) / 2π`, `v = 0.5 − asin(d.y) / π`, (u, v) = (0, 0) the image's top-left.
//! `--env-rotate θ` turns the environment by θ about +Y: a lookup first rotates d by −θ.

use crate::distribution::Distribution2D;
use crate::error::RenderError;
use crate::math::{luminance, sin_cos_azimuth, Vec2, Vec3, PI};
use glam::Vec3A;
use std::path::Path;

/// The solid-angle density of a uniform environment's samples (the whole sphere).
const UNIFORM_PDF: f32 = 1.0 / (4.0 * PI);

/// Largest environment map side accepted.
pub const MAX_ENV_SIDE: usize = 16384;

pub struct Environment {
    width: usize,
    height: usize,
    /// Linear RGB radiance × strength, row-major, top row first. A uniform environment is 1×1.
    texels: Texels,
    uniform: bool,
    /// (cos, sin) of the rotation about +Y.
    rot: (f32, f32),
    /// None when importance sampling is off.
    distribution: Option<Distribution2D>,
    /// Average radiance over the sphere (luminance), for light-selection power.
    pub mean_luminance: f32,
}

/// An environment map's texels: as f16 when every channel of every texel is exactly an f16 (a
/// half-float EXR's are; both maps under scenes/env are), else as f32. The values are the same
/// either way (f16 → f32 is exact), so are the images; the half copy is 8 bytes a texel instead
/// of 12, and a row's texel and its right neighbour are one 16-byte load. The map is the part of
/// an environment-lit render that misses cache (scenes/envlit's 1024×512 map: 6 MB of f32 texels
/// against a core's 1 MB of L2; `Environment::eval_uv` was 7 % of its time in `perf`, most of
/// it on the texel loads).
enum Texels {
    Full(Vec<Vec3>),
    /// R, G, B and a zero, as f16 bits.
    Half(Vec<[u16; 4]>),
}

impl Texels {
    /// The half copy when every value survives it bit for bit (`load` has replaced NaN and
    /// infinite inputs with 0; a product with the strength that overflows to infinity is an f16
    /// too).
    fn new(texels: Vec<Vec3>) -> Self {
        let half = |x: f32| {
            let h = half::f16::from_f32(x);
            (h.to_f32().to_bits() == x.to_bits()).then_some(h.to_bits())
        };
        match texels.iter().map(|t| Some([half(t.x)?, half(t.y)?, half(t.z)?, 0])).collect() {
            Some(h) => Texels::Half(h),
            None => Texels::Full(texels),
        }
    }

    #[inline(always)]
    fn get(&self, i: usize) -> Vec3 {
        match self {
            Texels::Full(t) => t[i],
            Texels::Half(t) => half_texel(&t[i]).into(),
        }
    }
}

/// One texel of a half copy as f32 lanes (R, G, B).
#[inline(always)]
fn half_texel(&[r, g, b, _]: &[u16; 4]) -> Vec3A {
    let f = |x: u16| half::f16::from_bits(x).to_f32();
    Vec3A::new(f(r), f(g), f(b))
}

/// Texels `i` and `j` of a half copy as f32 lanes (R, G, B, 0). With F16C (x86-64-v3) a row's
/// neighbours `j = i + 1` are one 16-byte load and one conversion.
#[inline(always)]
fn half_pair(t: &[[u16; 4]], i: usize, j: usize) -> (Vec3A, Vec3A) {
    #[cfg(all(target_arch = "x86_64", target_feature = "f16c", target_feature = "avx"))]
    {
        use std::arch::x86_64::*;
        if j == i + 1 && j < t.len() {
            // SAFETY: F16C and AVX are enabled at compile time; `i` and `i + 1` are in bounds
            // (checked above), so the 16 bytes read are theirs; unaligned load.
            unsafe {
                let v = _mm256_cvtph_ps(_mm_loadu_si128(t.as_ptr().add(i) as *const __m128i));
                return (_mm256_castps256_ps128(v).into(), _mm256_extractf128_ps::<1>(v).into());
            }
        }
    }
    (half_texel(&t[i]), half_texel(&t[j]))
}

/// A world direction's place on an environment map: the direction in the map's frame and its
/// (u, v), found once by [`Environment::map_point`] for a prefetch and the lookup after it.
#[derive(Clone, Copy, Debug, Default)]
pub struct MapPoint {
    dm: Vec3,
    uv: Vec2,
}

/// Settings of the environment: a map file or a uniform color, scaled and rotated.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EnvironmentSettings {
    /// Lat-long map file (`.exr` or `.hdr`); for farm jobs, the name of the uploaded file.
    pub map: Option<String>,
    /// Uniform radiance, used when there is no map.
    pub color: Option<[f32; 3]>,
    pub strength: f32,
    pub rotate_deg: f32,
    /// Importance-sample the map for next-event estimation (off: only BSDF sampling finds it).
    pub sampling: bool,
}

impl Default for EnvironmentSettings {
    fn default() -> Self {
        EnvironmentSettings { map: None, color: None, strength: 1.0, rotate_deg: 0.0, sampling: true }
    }
}

impl EnvironmentSettings {
    pub fn is_active(&self) -> bool {
        self.map.is_some() || self.color.is_some()
    }
}

/// Direction → (u, v) in [0,1)² before rotation. The arctangent and arcsine are polynomial
/// ([`atan2`]); libm's arctangent (`atanf` in `perf`) was 1.9 % of an environment-lit render
/// (scenes/envlit).
#[inline]
fn dir_to_uv(d: Vec3) -> Vec2 {
    let y = d.y.clamp(-1.0, 1.0);
    let u = 0.5 + atan2(d.z, d.x) / (2.0 * PI);
    // asin y = atan2(y, √(1 − y²)), the square root's argument as (1 − y)(1 + y), exact near ±1.
    let v = 0.5 - atan2(y, ((1.0 - y) * (1.0 + y)).sqrt()) / PI;
    Vec2::new(u.rem_euclid(1.0), v.clamp(0.0, 1.0))
}

/// (u, v) → direction before rotation, by the polynomial [`sin_cos_azimuth`] (libm's `sincosf`
/// was another 1.9 % of scenes/envlit).
#[inline]
fn uv_to_dir(uv: Vec2) -> Vec3 {
    let phi = (uv.x - 0.5) * 2.0 * PI;
    let theta_lat = (0.5 - uv.y) * PI; // latitude: asin(d.y)
    let (sl, cl) = sin_cos_azimuth(theta_lat);
    let (sp, cp) = sin_cos_azimuth(phi);
    Vec3::new(cl * cp, sl, cl * sp)
}

/// atan2(y, x) in [−π, π]: the ratio of the smaller to the larger magnitude (in [0, 1]), its
/// arctangent by Cephes' `atanf` (Moshier 1989: reduced about tan(π/8) and its polynomial, peak
/// relative error about 2e-7), then the octant and quadrant from the magnitudes and signs.
/// atan2(0, 0) is 0, as libm's for +0.
#[inline]
fn atan2(y: f32, x: f32) -> f32 {
    let (ax, ay) = (x.abs(), y.abs());
    let (lo, hi) = if ay > ax { (ax, ay) } else { (ay, ax) };
    let t = if hi > 0.0 { lo / hi } else { 0.0 };
    // atan t for t in [0, 1]: above tan(π/8), atan t = π/4 + atan((t − 1)/(t + 1)).
    let (base, r) = if t > 0.414_213_57 { (PI / 4.0, (t - 1.0) / (t + 1.0)) } else { (0.0, t) };
    let z = r * r;
    let a = base + (((8.053_744_5e-2 * z - 1.387_768_6e-1) * z + 1.997_771_1e-1) * z - 3.333_295e-1) * z * r + r;
    let a = if ay > ax { PI / 2.0 - a } else { a };
    let a = if x < 0.0 { PI - a } else { a };
    if y < 0.0 {
        -a
    } else {
        a
    }
}

impl Environment {
    pub fn uniform(color: Vec3, sampling: bool) -> Self {
        Self::from_texels(1, 1, vec![color], true, 0.0, sampling, false)
    }

    /// Loads a lat-long map. `strength` scales it, `rotate_deg` turns it about +Y; `sampling`
    /// importance-samples it for NEE, with MIS compensation (`from_texels`) if `mis_compensation`.
    pub fn load(
        path: &Path,
        strength: f32,
        rotate_deg: f32,
        sampling: bool,
        mis_compensation: bool,
    ) -> Result<Self, RenderError> {
        let err = |message: String| RenderError::Read { path: path.into(), message };
        let ext = path.extension().map(|e| e.to_string_lossy().to_ascii_lowercase()).unwrap_or_default();
        let (w, h, rgb) = match ext.as_str() {
            "exr" => read_exr_rgb(path)?,
            "hdr" => {
                let reader = image::ImageReader::open(path)
                    .map_err(|e| err(e.to_string()))?
                    .with_guessed_format()
                    .map_err(|e| err(e.to_string()))?;
                let (w, h) = reader.into_dimensions().map_err(|e| err(e.to_string()))?;
                if w as usize > MAX_ENV_SIDE || h as usize > MAX_ENV_SIDE {
                    return Err(err(format!("{w}x{h} exceeds the limit of {MAX_ENV_SIDE} per side")));
                }
                let img = image::ImageReader::open(path)
                    .map_err(|e| err(e.to_string()))?
                    .with_guessed_format()
                    .map_err(|e| err(e.to_string()))?
                    .decode()
                    .map_err(|e| err(e.to_string()))?;
                let f = img.to_rgb32f();
                (w as usize, h as usize, f.pixels().map(|p| Vec3::new(p.0[0], p.0[1], p.0[2])).collect())
            }
            other => return Err(err(format!("unsupported environment map format '.{other}' (use .exr or .hdr)"))),
        };
        if w < 2 || h < 1 {
            return Err(err(format!("a {w}x{h} environment map is too small")));
        }
        if !(strength.is_finite() && strength >= 0.0) {
            return Err(err(format!("strength {strength} must be a finite non-negative number")));
        }
        let texels: Vec<Vec3> =
            rgb.into_iter().map(|c| if c.is_finite() { c.max(Vec3::ZERO) * strength } else { Vec3::ZERO }).collect();
        Ok(Self::from_texels(w, h, texels, false, rotate_deg, sampling, mis_compensation))
    }

    fn from_texels(
        width: usize,
        height: usize,
        texels: Vec<Vec3>,
        uniform: bool,
        rotate_deg: f32,
        sampling: bool,
        mis_compensation: bool,
    ) -> Self {
        let r = rotate_deg.to_radians();
        // Sampling weight per texel: the largest luminance in its 3×3 neighbourhood (bilinear lookups
        // reach into neighbours, so a texel next to a bright one must count as bright), less the
        // map's mean radiance, × sin θ of the row: MIS compensation (Karlík, Šik, Vévoda, Skřivan &
        // Křivánek 2019, "MIS Compensation: Optimizing Sampling Techniques in Multiple Importance
        // Sampling", §5.1). Under MIS, BSDF sampling already finds the map's dim, smooth part well;
        // spending light samples there only dilutes them. Subtracting the mean sends them to what
        // stands out (sun, windows, bright sky). On `scenes/envlit` (a sunset map: brightest texel
        // channel 6248, mean over texels and channels 0.46) the image's relMSE at 64 spp drops
        // from 4.70e-3 to 1.76e-3 at the same time (`bench_peers.py --variants none --runs 5
        // envlit`).
        //
        // Directions below the mean get density 0, so next-event estimation never samples them and
        // the MIS integrator gives BSDF-sampled hits there full weight (the light pdf is 0). Only
        // with `mis_compensation` (the scene's integrator is MIS: `Scene::prepare`): the NEE
        // integrator has no BSDF strategy to leave them to. (It counts BSDF-sampled hits wherever
        // the map's pdf is 0 all the same, `integrator.rs`.) A map with nothing above its mean
        // (uniform) keeps a uniform table (`Distribution2D` of all zeros).
        // sin θ at each row's centre: the solid angle a texel of the row covers, up to a constant.
        let row_sin: Vec<f32> = (0..height).map(|y| ((y as f32 + 0.5) / height as f32 * PI).sin()).collect();
        let lum: Vec<f32> = texels.iter().map(|&t| luminance(t)).collect();
        let texels = Texels::new(texels);
        let (mut mean, mut wsum) = (0.0f64, 0.0f64);
        for (i, &l) in lum.iter().enumerate() {
            let sin_theta = row_sin[i / width];
            mean += l as f64 * sin_theta as f64;
            wsum += sin_theta as f64;
        }
        let mean_luminance = if wsum > 0.0 { (mean / wsum) as f32 } else { 0.0 };
        // The table only where it is sampled (a uniform map is sampled without one).
        let distribution = (sampling && !uniform).then(|| {
            let sin_of = |i: usize| row_sin[i / width];
            let peak = |i: usize| {
                let (x, y) = (i % width, i / width);
                let mut m = 0.0f32;
                for dy in -1i64..=1 {
                    let yy = (y as i64 + dy).clamp(0, height as i64 - 1) as usize;
                    for dx in -1i64..=1 {
                        let xx = (x as i64 + dx).rem_euclid(width as i64) as usize;
                        m = m.max(lum[yy * width + xx]);
                    }
                }
                m
            };
            let weights: Vec<f32> = if mis_compensation {
                (0..lum.len()).map(|i| (peak(i) - mean_luminance).max(0.0) * sin_of(i)).collect()
            } else {
                // Without compensation (the NEE integrator, which has no BSDF strategy to leave
                // the dim part to), a small floor keeps every direction's density positive.
                let weights: Vec<f32> = (0..lum.len()).map(|i| peak(i) * sin_of(i)).collect();
                let floor = 1e-3 * weights.iter().map(|&w| w as f64).sum::<f64>() as f32 / weights.len().max(1) as f32;
                weights.iter().enumerate().map(|(i, &w)| w + floor.max(1e-12) * sin_of(i)).collect()
            };
            Distribution2D::new(&weights, width, height)
        });
        Environment { width, height, texels, uniform, rot: (r.cos(), r.sin()), distribution, mean_luminance }
    }

    /// World direction → map direction (undo the rotation).
    #[inline]
    fn to_map(&self, d: Vec3) -> Vec3 {
        let (c, s) = self.rot;
        // R_y(−θ), the inverse of `to_world`.
        Vec3::new(c * d.x - s * d.z, d.y, s * d.x + c * d.z)
    }

    /// R_y(θ), right-handed about +Y (as Mitsuba's `rotate([0, 1, 0], θ)`): +Z turns towards +X.
    #[inline]
    fn to_world(&self, d: Vec3) -> Vec3 {
        let (c, s) = self.rot;
        Vec3::new(c * d.x + s * d.z, d.y, -s * d.x + c * d.z)
    }

    /// Radiance arriving from direction `d` (unit, pointing away from the scene), bilinear. Texel
    /// columns are centred at u = (x + ½)/W (the map wraps in u); rows run pole to pole, row y at
    /// v = y/(H − 1) — the lookup Mitsuba 3's `envmap` makes (checked to 1e-6 on 1500 random
    /// directions), so references from it compare texel for texel.
    pub fn eval(&self, d: Vec3) -> Vec3 {
        self.eval_at(self.map_point(d))
    }

    /// [`Self::eval`] and [`Self::pdf`] of one direction, its (u, v) found once (an escaped path
    /// weighed by MIS needs both; the arctangent and arcsine were a visible share of an
    /// environment-lit render).
    pub fn eval_pdf(&self, d: Vec3) -> (Vec3, f32) {
        self.eval_pdf_at(self.map_point(d))
    }

    /// Where the world direction `d` falls on the map (nothing to find on a uniform one).
    #[inline]
    pub fn map_point(&self, d: Vec3) -> MapPoint {
        if self.uniform {
            return MapPoint { dm: d, uv: Vec2::ZERO };
        }
        let dm = self.to_map(d);
        MapPoint { dm, uv: dir_to_uv(dm) }
    }

    /// [`Self::eval`] of the direction `p` was found for.
    pub fn eval_at(&self, p: MapPoint) -> Vec3 {
        if self.uniform {
            return self.texels.get(0);
        }
        self.eval_uv(p.uv)
    }

    /// [`Self::eval_pdf`] of the direction `p` was found for.
    pub fn eval_pdf_at(&self, p: MapPoint) -> (Vec3, f32) {
        if self.uniform {
            return (self.texels.get(0), UNIFORM_PDF);
        }
        (self.eval_uv(p.uv), self.pdf_map(p.dm, p.uv))
    }

    /// Asks the cache for what [`Self::eval_pdf_at`]`(p)` reads: the map's texels and the
    /// distribution's rows are megabytes, and a lookup's miss is more than the arithmetic around
    /// it can hide. One lookup after another, each lane waited for its own miss; asking for every
    /// lane's lines first and then looking them up (`spmd::radiance8`'s escape) lets the misses
    /// overlap. Always inlined: a change elsewhere in the renderer once tipped LLVM into calling
    /// it, and envlit's render took 0.6 % more instructions (callgrind, 64×48, 16 spp).
    #[inline(always)]
    pub fn prefetch(&self, p: &MapPoint) {
        if self.uniform {
            return;
        }
        self.prefetch_uv(p.uv);
        if let Some(dist) = &self.distribution {
            dist.prefetch_pdf([p.uv.x, p.uv.y]);
        }
    }

    /// The four texels of a bilinear lookup at map coordinates `uv` and the weights of the right
    /// and lower ones: columns xa, xb and rows ya, yb. [`Self::eval_uv`] reads them and
    /// [`Self::prefetch_uv`] asks the cache for them, so both find the same texels.
    #[inline(always)]
    fn corners(&self, uv: Vec2) -> ([usize; 4], f32, f32) {
        let x = uv.x * self.width as f32 - 0.5;
        let y = (uv.y * (self.height - 1) as f32).clamp(0.0, (self.height - 1) as f32);
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        // x0 is in −1 ..= width − 1 (u < 1); wrap without an integer division (two of them were
        // most of this function's own time). The `min` only guards a u that rounding put at 1.
        // As u32 (both conversions saturate; a side is at most MAX_ENV_SIDE): the same integers.
        let xa = if x0 < 0.0 { self.width - 1 } else { (x0 as u32 as usize).min(self.width - 1) };
        let xb = if xa + 1 == self.width { 0 } else { xa + 1 };
        let ya = y0 as u32 as usize;
        let yb = (ya + 1).min(self.height - 1);
        ([xa, xb, ya, yb], fx, fy)
    }

    /// The bilinear lookup of [`Self::eval`] at map coordinates `uv` (u in [0, 1), v in [0, 1]).
    fn eval_uv(&self, uv: Vec2) -> Vec3 {
        let ([xa, xb, ya, yb], fx, fy) = self.corners(uv);
        // The same products and sums per channel, in the same order, from either storage.
        let (gx, gy) = (1.0 - fx, 1.0 - fy);
        let blend = |a: Vec3A, b: Vec3A, c: Vec3A, d: Vec3A| (a * gx + b * fx) * gy + (c * gx + d * fx) * fy;
        let w = self.width;
        match &self.texels {
            Texels::Full(t) => {
                let t = |x: usize, y: usize| Vec3A::from(t[y * w + x]);
                blend(t(xa, ya), t(xb, ya), t(xa, yb), t(xb, yb)).into()
            }
            Texels::Half(t) => {
                let (a, b) = half_pair(t, ya * w + xa, ya * w + xb);
                let (c, d) = half_pair(t, yb * w + xa, yb * w + xb);
                blend(a, b, c, d).into()
            }
        }
    }

    /// Asks the cache for the texels [`Self::eval_uv`]`(uv)` reads.
    #[inline(always)]
    fn prefetch_uv(&self, uv: Vec2) {
        let ([xa, xb, ya, yb], ..) = self.corners(uv);
        let w = self.width;
        for i in [ya * w + xa, ya * w + xb, yb * w + xa, yb * w + xb] {
            match &self.texels {
                Texels::Full(t) => t.get(i).map(crate::accel::prefetch),
                Texels::Half(t) => t.get(i).map(crate::accel::prefetch),
            };
        }
    }

    pub fn is_sampled(&self) -> bool {
        self.uniform || self.distribution.is_some()
    }

    /// Samples a direction: returns (world direction, radiance, solid-angle pdf).
    pub fn sample(&self, u: Vec2) -> Option<(Vec3, Vec3, f32)> {
        if self.uniform {
            let z = 1.0 - 2.0 * u.x;
            let r = (1.0 - z * z).max(0.0).sqrt();
            let phi = 2.0 * PI * u.y;
            let d = Vec3::new(r * phi.cos(), r * phi.sin(), z);
            return Some((d, self.texels.get(0), UNIFORM_PDF));
        }
        let dist = self.distribution.as_ref()?;
        let (uv, map_pdf) = dist.sample([u.x, u.y]);
        self.sampled(uv, map_pdf)
    }

    /// [`Self::sample`] of each of `us` into `out`, the same answers: the distribution's searches
    /// a step at a time across the samples (`Distribution2D::sample_batch`), then each sample's
    /// texels, so the cache misses of different samples overlap.
    pub fn sample_batch(&self, us: &[Vec2], out: &mut [Option<(Vec3, Vec3, f32)>]) {
        let n = us.len().min(out.len());
        let dist = match &self.distribution {
            Some(d) if !self.uniform => d,
            _ => {
                for (u, o) in us[..n].iter().zip(&mut out[..n]) {
                    *o = self.sample(*u);
                }
                return;
            }
        };
        for s in (0..n).step_by(crate::distribution::BATCH) {
            let e = (s + crate::distribution::BATCH).min(n);
            let mut q = [[0f32; 2]; crate::distribution::BATCH];
            for (q, u) in q.iter_mut().zip(&us[s..e]) {
                *q = [u.x, u.y];
            }
            let mut found = [([0f32; 2], 0f32); crate::distribution::BATCH];
            dist.sample_batch(&q[..e - s], &mut found[..e - s]);
            // Every sample's texels asked for before any is read, so their misses overlap.
            for &(uv, _) in &found[..e - s] {
                self.prefetch_uv(Vec2::new(uv[0], uv[1]));
            }
            for (o, &(uv, map_pdf)) in out[s..e].iter_mut().zip(&found) {
                *o = self.sampled(uv, map_pdf);
            }
        }
    }

    /// The end of [`Self::sample`] once the distribution has given the map point `uv` and its
    /// density over the unit square.
    #[inline(always)]
    fn sampled(&self, uv: [f32; 2], map_pdf: f32) -> Option<(Vec3, Vec3, f32)> {
        let d_map = uv_to_dir(Vec2::new(uv[0], uv[1]));
        let cos_lat = (1.0 - d_map.y * d_map.y).max(0.0).sqrt();
        if map_pdf <= 0.0 || cos_lat <= 0.0 {
            return None;
        }
        // dω = 2π² sin θ du dv with sin θ (polar) = cos(latitude).
        let pdf = map_pdf / (2.0 * PI * PI * cos_lat);
        // Radiance at the sampled (u, v) itself, not at the direction turned back into (u, v).
        Some((self.to_world(d_map), self.eval_uv(Vec2::new(uv[0], uv[1])), pdf))
    }

    /// Solid-angle pdf of `sample()` producing direction `d`.
    pub fn pdf(&self, d: Vec3) -> f32 {
        if self.uniform {
            return UNIFORM_PDF;
        }
        let p = self.map_point(d);
        self.pdf_map(p.dm, p.uv)
    }

    /// [`Self::pdf`] of the map direction `dm` at its coordinates `uv`.
    fn pdf_map(&self, dm: Vec3, uv: Vec2) -> f32 {
        let Some(dist) = &self.distribution else { return 0.0 };
        let cos_lat = (1.0 - dm.y * dm.y).max(0.0).sqrt();
        if cos_lat <= 0.0 {
            return 0.0;
        }
        dist.pdf([uv.x, uv.y]) / (2.0 * PI * PI * cos_lat)
    }
}

/// Reads R, G, B of an EXR's first layer, refusing compressions the reader cannot decode by name.
fn read_exr_rgb(path: &Path) -> Result<(usize, usize, Vec<Vec3>), RenderError> {
    let err = |message: String| RenderError::Read { path: path.into(), message };
    let meta =
        crate::image_io::decoder_guard(|| exr::meta::MetaData::read_from_file(path, false).map_err(|e| e.to_string()))
            .map_err(err)?;
    let header = meta.headers.first().ok_or_else(|| err("no image layer".into()))?;
    let size = header.layer_size;
    if size.width() > MAX_ENV_SIDE || size.height() > MAX_ENV_SIDE {
        return Err(err(format!("{}x{} exceeds the limit of {MAX_ENV_SIDE} per side", size.width(), size.height())));
    }
    use exr::compression::Compression as C;
    let supported = matches!(
        header.compression,
        C::Uncompressed | C::RLE | C::ZIP1 | C::ZIP16 | C::PIZ | C::PXR24 | C::B44 | C::B44A
    );
    if !supported {
        return Err(err(format!(
            "the EXR uses {:?} compression, which this reader cannot decode; convert it to PIZ or ZIP (e.g. `oiiotool in.exr --compression piz -o out.exr`)",
            header.compression
        )));
    }
    let c = crate::image_io::read_exr(path)?;
    let (r, g, b) = match (c.channel("R"), c.channel("G"), c.channel("B")) {
        (Some(r), Some(g), Some(b)) => (r, g, b),
        _ => return Err(err("the EXR has no R, G, B channels".into())),
    };
    Ok((c.width as usize, c.height as usize, (0..r.len()).map(|i| Vec3::new(r[i], g[i], b[i])).collect()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The polynomial arctangent, arcsine, sine and cosine of the mapping agree with libm's
    /// (each (u, v) within 3e-7, 1/3000 of a 1024-wide map's texel; measured 6e-8), over directions
    /// everywhere and at the seam, axes and poles.
    #[test]
    fn polynomial_mapping_matches_libm() {
        let libm_uv = |d: Vec3| {
            let u = 0.5 + d.z.atan2(d.x) / (2.0 * PI);
            let v = 0.5 - d.y.clamp(-1.0, 1.0).asin() / PI;
            Vec2::new(u.rem_euclid(1.0), v.clamp(0.0, 1.0))
        };
        let mut dirs: Vec<Vec3> = Vec::new();
        for i in 0..200 {
            for j in 0..100 {
                let (phi, z) = (i as f32 / 200.0 * 2.0 * PI, j as f32 / 99.0 * 2.0 - 1.0);
                let r = (1.0 - z * z).max(0.0).sqrt();
                dirs.push(Vec3::new(r * phi.cos(), z, r * phi.sin()));
            }
        }
        for d in [Vec3::X, -Vec3::X, Vec3::Y, -Vec3::Y, Vec3::Z, -Vec3::Z, Vec3::new(-1.0, 0.0, -1e-7)] {
            dirs.push(d.normalize());
        }
        let mut worst = 0.0f32;
        for d in dirs {
            let (a, b) = (dir_to_uv(d), libm_uv(d));
            // u wraps: 0 and just below 1 are the same place.
            let du = (a.x - b.x).abs().min(1.0 - (a.x - b.x).abs());
            // At a pole every u is the same point.
            let du = if d.y.abs() > 0.999_999 { 0.0 } else { du };
            worst = worst.max(du).max((a.y - b.y).abs());
        }
        assert!(worst < 3e-7, "worst (u, v) difference {worst:e}");
        let mut worst = 0.0f32;
        for i in 0..=1000 {
            for j in 0..=100 {
                let uv = Vec2::new(i as f32 / 1000.0, j as f32 / 100.0);
                let (phi, lat) = ((uv.x - 0.5) * 2.0 * PI, (0.5 - uv.y) * PI);
                let libm = Vec3::new(lat.cos() * phi.cos(), lat.sin(), lat.cos() * phi.sin());
                worst = worst.max((uv_to_dir(uv) - libm).abs().max_element());
            }
        }
        assert!(worst < 3.0 * f32::EPSILON, "worst direction difference {worst:e}");
    }

    #[test]
    fn mapping_round_trips_and_follows_the_convention() {
        for d in [Vec3::X, Vec3::Z, -Vec3::X, Vec3::new(0.3, 0.8, -0.5).normalize()] {
            let back = uv_to_dir(dir_to_uv(d));
            assert!((back - d).length() < 1e-5, "{d:?} -> {back:?}");
        }
        // +Y is the top row, +X the horizontal centre, +Z a quarter to the right.
        assert!(dir_to_uv(Vec3::Y).y < 1e-6);
        assert!((dir_to_uv(Vec3::X) - Vec2::new(0.5, 0.5)).length() < 1e-6);
        assert!((dir_to_uv(Vec3::Z) - Vec2::new(0.75, 0.5)).length() < 1e-6);
    }

    /// The wrap in u without integer division reads the texels the modulo arithmetic read, at the
    /// seam (u = 0, u just below 1, the half texel either side) and everywhere between.
    #[test]
    fn bilinear_wrap_equals_the_modulo_lookup() {
        let (w, h) = (8usize, 5usize);
        let texels: Vec<Vec3> = (0..w * h).map(|i| Vec3::new(i as f32, (i * i % 13) as f32, 1.0)).collect();
        let env = Environment::from_texels(w, h, texels.clone(), false, 0.0, false, false);
        let modulo = |uv: Vec2| {
            let x = uv.x * w as f32 - 0.5;
            let y = (uv.y * (h - 1) as f32).clamp(0.0, (h - 1) as f32);
            let (x0, y0) = (x.floor(), y.floor());
            let (fx, fy) = (x - x0, y - y0);
            let xa = (x0 as i64).rem_euclid(w as i64) as usize;
            let xb = (xa + 1) % w;
            let (ya, yb) = (y0 as usize, (y0 as usize + 1).min(h - 1));
            let t = |x: usize, y: usize| texels[y * w + x];
            (t(xa, ya) * (1.0 - fx) + t(xb, ya) * fx) * (1.0 - fy) + (t(xa, yb) * (1.0 - fx) + t(xb, yb) * fx) * fy
        };
        let mut us: Vec<f32> = (0..=400).map(|i| i as f32 / 400.0).filter(|&u| u < 1.0).collect();
        us.extend([0.0, 1.0 - f32::EPSILON / 2.0, 0.5 / w as f32, 1.0 - 0.5 / w as f32, 1e-9]);
        for &u in &us {
            for v in [0.0, 0.1, 0.5, 0.77, 1.0] {
                let uv = Vec2::new(u, v);
                assert_eq!(env.eval_uv(uv), modulo(uv), "u {u}, v {v}");
            }
        }
    }

    /// Sampling a batch gives each sample's own answer, bit for bit: a map with dark rows and
    /// bright texels, sampled (with and without MIS compensation, rotated) at random and at the
    /// edges of the unit square (0, just under 1, and 1 itself, which takes the whole-table
    /// search), in batches of 1 to 19 (past `distribution::BATCH`).
    #[test]
    fn batched_samples_are_each_samples_own() {
        let (w, h) = (64usize, 32usize);
        let texels: Vec<Vec3> = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let bright = if (x * 7 + y * 3) % 29 == 0 { 500.0 } else { 0.3 };
                Vec3::new(bright * (1.0 + (x % 5) as f32), bright, if y < 4 { 0.0 } else { 1.0 })
            })
            .collect();
        let mut us: Vec<Vec2> = (0..300u64)
            .map(|i| Vec2::new(crate::sampler::hash_unit(2 * i), crate::sampler::hash_unit(2 * i + 1)))
            .collect();
        for a in [0.0, 1.0 - f32::EPSILON / 2.0, 1.0] {
            for b in [0.0, 0.5, 1.0 - f32::EPSILON / 2.0, 1.0] {
                us.push(Vec2::new(a, b));
            }
        }
        let bits = |o: Option<(Vec3, Vec3, f32)>| {
            o.map(|(d, l, p)| (d.to_array().map(f32::to_bits), l.to_array().map(f32::to_bits), p.to_bits()))
        };
        for (compensate, rotation) in [(false, 0.0), (true, 0.0), (true, 75.0)] {
            let env = Environment::from_texels(w, h, texels.clone(), false, rotation, true, compensate);
            assert!(env.is_sampled());
            let mut sampled = 0;
            for batch in 1..20usize {
                for chunk in us.chunks(batch) {
                    let mut out = vec![Some((Vec3::NAN, Vec3::NAN, f32::NAN)); chunk.len()];
                    env.sample_batch(chunk, &mut out);
                    for (u, o) in chunk.iter().zip(&out) {
                        assert_eq!(bits(*o), bits(env.sample(*u)), "u {u:?}, batch {batch}");
                        sampled += usize::from(o.is_some());
                    }
                }
            }
            assert!(sampled > 19 * 250, "{sampled}");
        }
    }

    /// A map whose values are all f16 is stored half (and one with a value that is not, full), and
    /// its bilinear lookups give the f32 copy's values bit for bit, the wrap seam and the
    /// neighbour-pair load included.
    #[test]
    fn half_texels_are_kept_when_exact_and_look_up_as_f32() {
        let (w, h) = (16usize, 9usize);
        // Multiples of 1/64 below 2^10, and a few large values: all exact in f16.
        let texels: Vec<Vec3> = (0..w * h)
            .map(|i| {
                Vec3::new((i % 97) as f32 / 64.0, (i * 7 % 31) as f32 * 3.0, if i % 11 == 0 { 6144.0 } else { 0.25 })
            })
            .collect();
        let half = Environment::from_texels(w, h, texels.clone(), false, 0.0, true, true);
        assert!(matches!(half.texels, Texels::Half(_)));
        let full = Environment {
            texels: Texels::Full(texels.clone()),
            ..Environment::from_texels(w, h, texels.clone(), false, 0.0, true, true)
        };
        for i in 0..=300 {
            for j in 0..=40 {
                let uv = Vec2::new(i as f32 / 301.0, j as f32 / 40.0);
                let (a, b) = (half.eval_uv(uv), full.eval_uv(uv));
                assert_eq!(
                    (a.x.to_bits(), a.y.to_bits(), a.z.to_bits()),
                    (b.x.to_bits(), b.y.to_bits(), b.z.to_bits()),
                    "uv {uv:?}"
                );
            }
        }
        let mut inexact = texels;
        inexact[5].y = 0.1;
        let env = Environment::from_texels(w, h, inexact, false, 0.0, true, true);
        assert!(matches!(env.texels, Texels::Full(_)), "0.1 is not an f16");
    }

    #[test]
    fn asymmetric_map_lookups_and_rotation() {
        // 8×5 map: texel (x, y) holds x + 10 y, so every lookup says where it landed.
        let (w, h) = (8usize, 5usize);
        let texels: Vec<Vec3> = (0..w * h).map(|i| Vec3::splat((i % w) as f32 + 10.0 * (i / w) as f32)).collect();
        let env = Environment::from_texels(w, h, texels.clone(), false, 0.0, true, true);
        let centre = |x: usize, y: usize| uv_to_dir(Vec2::new((x as f32 + 0.5) / w as f32, y as f32 / (h - 1) as f32));
        // Row 0 is the north pole itself: every column meets there (u = ½ by convention).
        assert!((env.eval(Vec3::Y).x - 3.5).abs() < 1e-3, "{:?}", env.eval(Vec3::Y));
        for (x, y) in [(0, 1), (5, 1), (7, 3), (2, 2)] {
            let v = env.eval(centre(x, y)).x;
            assert!((v - (x as f32 + 10.0 * y as f32)).abs() < 1e-3, "texel ({x},{y}) read {v}");
        }
        // The top rows are up (+Y), and +Z is three quarters across (u = 0.75 → column 6).
        assert!(centre(3, 1).y > 0.0 && centre(3, 3).y < 0.0);
        let d = centre(6, 1);
        assert!(d.z > 0.9 * (1.0 - d.y * d.y).sqrt(), "{d:?}");
        // Rotating by +90° about +Y (right-handed) carries the texel that was at +Z over to +X.
        let rotated = Environment::from_texels(w, h, texels, false, 90.0, true, true);
        let plus_z = centre(6, 1);
        let plus_x = Vec3::new(plus_z.z, plus_z.y, -plus_z.x);
        assert!(
            (rotated.eval(plus_x) - env.eval(plus_z)).length() < 1e-3,
            "{:?} vs {:?}",
            rotated.eval(plus_x),
            env.eval(plus_z)
        );
    }

    /// A lookup through [`Environment::map_point`] (the escape's prefetch, then the lookup)
    /// agrees with what sampling that direction returned: radiance and pdf, uniform and mapped,
    /// rotated, compensated or not (the sample's (u, v) against the direction's, through the
    /// mapping and back, so within rounding). It is bit for bit what `eval` and `pdf` give (they
    /// go through the same map point). A prefetch anywhere, non-finite directions included,
    /// stays inside the tables.
    #[test]
    fn map_point_lookups_are_the_direct_lookups() {
        let (w, h) = (8usize, 5usize);
        let texels: Vec<Vec3> = (0..w * h).map(|i| Vec3::new(i as f32, (i * i % 11) as f32, 0.5)).collect();
        let maps = [
            Environment::from_texels(w, h, texels.clone(), false, 0.0, true, true),
            Environment::from_texels(w, h, texels.clone(), false, 37.0, true, false),
            Environment::from_texels(w, h, texels, false, 0.0, false, false),
            Environment::from_texels(1, 1, vec![Vec3::new(0.25, 0.5, 2.0)], true, 0.0, true, false),
        ];
        let mut dirs: Vec<Vec3> = (0..400u64)
            .map(|i| {
                let (a, b) = (crate::sampler::hash_unit(2 * i), crate::sampler::hash_unit(2 * i + 1));
                uv_to_dir(Vec2::new(a, b))
            })
            .collect();
        dirs.extend([Vec3::Y, -Vec3::Y, -Vec3::X, Vec3::new(-1.0, 0.0, -1e-7).normalize(), Vec3::Z]);
        for (m, env) in maps.iter().enumerate() {
            for &d in &dirs {
                let p = env.map_point(d);
                env.prefetch(&p);
                let bits = |v: Vec3| v.to_array().map(f32::to_bits);
                assert_eq!(bits(env.eval_at(p)), bits(env.eval(d)), "map {m}, {d:?}");
                let ((le, pdf), (le_direct, pdf_direct)) = (env.eval_pdf_at(p), (env.eval(d), env.pdf(d)));
                assert_eq!((bits(le), pdf.to_bits()), (bits(le_direct), pdf_direct.to_bits()), "map {m}, {d:?}");
            }
            for d in [Vec3::NAN, Vec3::INFINITY, Vec3::new(f32::NEG_INFINITY, 0.0, 1.0), Vec3::ZERO] {
                env.prefetch(&env.map_point(d));
            }
            let mut sampled = 0;
            for i in 0..400u64 {
                let u = Vec2::new(crate::sampler::hash_unit(2 * i + 7), crate::sampler::hash_unit(2 * i + 8));
                let Some((d, le, pdf)) = env.sample(u) else { continue };
                let (le_at, pdf_at) = env.eval_pdf_at(env.map_point(d));
                let close = |a: f32, b: f32| (a - b).abs() <= 1e-3 * a.abs().max(b.abs()) + 1e-4;
                assert!(close(pdf, pdf_at), "map {m}, u {u:?}: sampled pdf {pdf}, looked up {pdf_at}");
                assert!(
                    (0..3).all(|c| close(le[c], le_at[c])),
                    "map {m}, u {u:?}: sampled {le:?}, looked up {le_at:?}"
                );
                sampled += 1;
            }
            assert!(sampled > 300 || !env.is_sampled(), "map {m}: {sampled} samples");
        }
    }
}
