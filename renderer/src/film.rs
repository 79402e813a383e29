//! Partial radiance sums: the currency of the farm. A tile's `PartialSums` over a sample range holds,
//! per pixel, the f64 sum of RGB radiance, the f64 sum of squared luminance and the sample count.
//! Merging is elementwise addition; the *order* of merges is fixed by the determinism rule
//! (ARCHITECTURE.md), which is what makes a distributed image bit-identical to a local one.

use crate::math::Vec3;
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Rect {
    pub x0: u32,
    pub y0: u32,
    pub width: u32,
    pub height: u32,
}

impl Rect {
    pub fn pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// Splits a `width × height` image into tiles of at most `size × size`, row-major.
    pub fn tiles(width: u32, height: u32, size: u32) -> Vec<Rect> {
        let size = size.max(1);
        let mut out = Vec::new();
        for y0 in (0..height).step_by(size as usize) {
            for x0 in (0..width).step_by(size as usize) {
                out.push(Rect { x0, y0, width: size.min(width - x0), height: size.min(height - y0) });
            }
        }
        out
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PartialSums {
    pub rect: Rect,
    /// Per pixel, row-major within `rect`.
    pub sum_rgb: Vec<[f64; 3]>,
    pub sum_lum_sq: Vec<f64>,
    pub count: Vec<u32>,
}

impl PartialSums {
    pub fn new(rect: Rect) -> Self {
        let n = rect.pixels();
        PartialSums { rect, sum_rgb: vec![[0.0; 3]; n], sum_lum_sq: vec![0.0; n], count: vec![0; n] }
    }

    /// Sums for `rect` that hold no storage yet (a queued or finished farm job's tile): memory
    /// follows work in flight. `is_allocated` tells them apart; merging needs `new`.
    pub fn unallocated(rect: Rect) -> Self {
        PartialSums { rect, sum_rgb: Vec::new(), sum_lum_sq: Vec::new(), count: Vec::new() }
    }

    /// True when the per-pixel storage exists (see `unallocated`).
    pub fn is_allocated(&self) -> bool {
        self.count.len() == self.rect.pixels()
    }

    /// Adds one sample to pixel `i` (index within the rect).
    #[inline]
    pub fn add_sample(&mut self, i: usize, l: Vec3) {
        let s = &mut self.sum_rgb[i];
        s[0] += l.x as f64;
        s[1] += l.y as f64;
        s[2] += l.z as f64;
        let y = crate::math::luminance(l) as f64;
        self.sum_lum_sq[i] += y * y;
        self.count[i] += 1;
    }

    /// Elementwise `self += other` (same rect).
    pub fn merge(&mut self, other: &PartialSums) -> Result<(), String> {
        if self.rect != other.rect {
            return Err(format!("cannot merge sums of {:?} into {:?}", other.rect, self.rect));
        }
        let lengths = |s: &PartialSums| (s.sum_rgb.len(), s.sum_lum_sq.len(), s.count.len());
        if lengths(self) != lengths(other) {
            return Err(format!("cannot merge sums of {:?} pixels into {:?}", lengths(other), lengths(self)));
        }
        // Zipped rather than indexed: no bounds check a value, and the additions vectorise (each
        // pixel's sum still gains `other`'s in one addition, so the bits are the same). A tile's
        // pass is folded this way at every pass: 2.7 % of a depth-0 veach render's `perf`
        // samples when indexed.
        for (a, b) in self.sum_rgb.iter_mut().zip(&other.sum_rgb) {
            for c in 0..3 {
                a[c] += b[c];
            }
        }
        for (a, b) in self.sum_lum_sq.iter_mut().zip(&other.sum_lum_sq) {
            *a += b;
        }
        for (a, b) in self.count.iter_mut().zip(&other.count) {
            *a += b;
        }
        Ok(())
    }

    /// Adds a tile's sums into this (larger) rect at the tile's position.
    pub fn merge_tile(&mut self, tile: &PartialSums) -> Result<(), String> {
        let (r, t) = (self.rect, tile.rect);
        if t.x0 < r.x0 || t.y0 < r.y0 || t.x0 + t.width > r.x0 + r.width || t.y0 + t.height > r.y0 + r.height {
            return Err(format!("tile {t:?} lies outside {r:?}"));
        }
        for ty in 0..t.height {
            for tx in 0..t.width {
                let src = (ty * t.width + tx) as usize;
                let dst = ((t.y0 - r.y0 + ty) * r.width + (t.x0 - r.x0 + tx)) as usize;
                for c in 0..3 {
                    self.sum_rgb[dst][c] += tile.sum_rgb[src][c];
                }
                self.sum_lum_sq[dst] += tile.sum_lum_sq[src];
                self.count[dst] += tile.count[src];
            }
        }
        Ok(())
    }

    /// Validates sums received from elsewhere: sizes match the rect, values finite and non-negative,
    /// every pixel holds exactly `expected_count` samples.
    pub fn validate(&self, expected_count: u32) -> Result<(), String> {
        let n = self.rect.pixels();
        if self.sum_rgb.len() != n || self.sum_lum_sq.len() != n || self.count.len() != n {
            return Err(format!(
                "{} pixels expected for {:?}, got {}/{}/{}",
                n,
                self.rect,
                self.sum_rgb.len(),
                self.sum_lum_sq.len(),
                self.count.len()
            ));
        }
        for i in 0..n {
            let s = self.sum_rgb[i];
            if !s.iter().chain(std::iter::once(&self.sum_lum_sq[i])).all(|v| v.is_finite() && *v >= 0.0) {
                return Err(format!("pixel {i} holds a non-finite or negative sum"));
            }
            if self.count[i] != expected_count {
                return Err(format!("pixel {i} holds {} samples, expected {expected_count}", self.count[i]));
            }
        }
        Ok(())
    }

    /// Mean radiance of pixel `i`.
    pub fn mean(&self, i: usize) -> [f32; 3] {
        let n = self.count[i].max(1) as f64;
        let s = self.sum_rgb[i];
        [(s[0] / n) as f32, (s[1] / n) as f32, (s[2] / n) as f32]
    }

    /// Variance of the mean luminance of pixel `i` (unbiased sample variance / n); infinite when
    /// fewer than two samples make it unknowable.
    pub fn variance_of_mean(&self, i: usize) -> f32 {
        let n = self.count[i] as f64;
        if n < 2.0 {
            return f32::INFINITY;
        }
        let s = self.sum_rgb[i];
        let mean = (0.2126 * s[0] + 0.7152 * s[1] + 0.0722 * s[2]) / n;
        let var = ((self.sum_lum_sq[i] - n * mean * mean) / (n - 1.0)).max(0.0);
        (var / n) as f32
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiles_cover_image_exactly_once() {
        let tiles = Rect::tiles(70, 33, 16);
        let mut hits = vec![0u8; 70 * 33];
        for t in &tiles {
            for y in t.y0..t.y0 + t.height {
                for x in t.x0..t.x0 + t.width {
                    hits[(y * 70 + x) as usize] += 1;
                }
            }
        }
        assert!(hits.iter().all(|&h| h == 1));
    }

    #[test]
    fn variance_of_mean_matches_definition() {
        let mut p = PartialSums::new(Rect { x0: 0, y0: 0, width: 1, height: 1 });
        for v in [1.0f32, 2.0, 3.0, 6.0] {
            p.add_sample(0, Vec3::splat(v));
        }
        // Luminance of grey v is v (weights sum to 1); sample variance of {1,2,3,6} is 14/3.
        let expect = 14.0 / 3.0 / 4.0;
        assert!((p.variance_of_mean(0) as f64 - expect).abs() < 1e-5);
        assert_eq!(p.mean(0), [3.0, 3.0, 3.0]);
    }

    /// Merging adds each pixel's sums and counts (the same additions as one pixel at a time), and
    /// sums whose vectors do not fit their rect (a malformed message's) are refused with an error,
    /// not a panic, leaving the target as it was.
    #[test]
    fn merge_adds_pixel_by_pixel_and_refuses_misshapen_sums() {
        let rect = Rect { x0: 2, y0: 1, width: 3, height: 2 };
        let (mut a, mut b) = (PartialSums::new(rect), PartialSums::new(rect));
        for i in 0..6 {
            a.add_sample(i, Vec3::new(0.1 * i as f32, 1e-7, 3.0));
            b.add_sample(i, Vec3::new(1.0 / (i + 1) as f32, 2.5, 1e9));
            b.add_sample(i, Vec3::splat(0.3));
        }
        let before = a.clone();
        a.merge(&b).expect("same rect");
        for i in 0..6 {
            for c in 0..3 {
                assert_eq!(a.sum_rgb[i][c].to_bits(), (before.sum_rgb[i][c] + b.sum_rgb[i][c]).to_bits());
            }
            assert_eq!(a.sum_lum_sq[i].to_bits(), (before.sum_lum_sq[i] + b.sum_lum_sq[i]).to_bits());
            assert_eq!(a.count[i], 3);
        }
        let merged = a.clone();
        let mut short = b.clone();
        short.sum_lum_sq.pop();
        assert!(a.merge(&short).is_err());
        let mut long = b.clone();
        long.count.push(1);
        assert!(a.merge(&long).is_err());
        assert_eq!((a.sum_rgb, a.sum_lum_sq, a.count), (merged.sum_rgb, merged.sum_lum_sq, merged.count));
    }

    #[test]
    fn validate_rejects_bad_sums() {
        let mut p = PartialSums::new(Rect { x0: 0, y0: 0, width: 2, height: 1 });
        p.add_sample(0, Vec3::ONE);
        p.add_sample(1, Vec3::ONE);
        assert!(p.validate(1).is_ok());
        assert!(p.validate(2).is_err());
        let mut q = p.clone();
        q.sum_rgb[1][0] = f64::NAN;
        assert!(q.validate(1).is_err());
        let mut r = p.clone();
        r.count.pop();
        assert!(r.validate(1).is_err());
    }
}

/// Bytes per pixel in the wire encoding of [`PartialSums`]: three f64 sums, the f64 sum of squared
/// luminance, the u32 count.
pub const ENCODED_PIXEL_BYTES: usize = 36;

impl PartialSums {
    /// Little-endian encoding of the per-pixel data (the rect travels separately).
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.rect.pixels() * ENCODED_PIXEL_BYTES);
        for i in 0..self.rect.pixels() {
            for c in self.sum_rgb[i] {
                out.extend_from_slice(&c.to_le_bytes());
            }
            out.extend_from_slice(&self.sum_lum_sq[i].to_le_bytes());
            out.extend_from_slice(&self.count[i].to_le_bytes());
        }
        out
    }

    /// Decodes sums for `rect`; the length must match exactly (checked before allocating).
    pub fn decode(rect: Rect, bytes: &[u8]) -> Result<Self, String> {
        let n = rect.pixels();
        let expected = n.checked_mul(ENCODED_PIXEL_BYTES).ok_or("rect too large")?;
        if bytes.len() != expected {
            return Err(format!(
                "{} bytes of sums for a {}x{} rect, expected {expected}",
                bytes.len(),
                rect.width,
                rect.height
            ));
        }
        let mut p = PartialSums::new(rect);
        let f = |b: &[u8]| f64::from_le_bytes(b.try_into().unwrap_or([0; 8]));
        for (i, px) in bytes.chunks_exact(ENCODED_PIXEL_BYTES).enumerate() {
            p.sum_rgb[i] = [f(&px[0..8]), f(&px[8..16]), f(&px[16..24])];
            p.sum_lum_sq[i] = f(&px[24..32]);
            p.count[i] = u32::from_le_bytes(px[32..36].try_into().unwrap_or([0; 4]));
        }
        Ok(p)
    }
}

#[cfg(test)]
mod wire_tests {
    use super::*;

    #[test]
    fn encode_decode_round_trip_is_bit_exact() {
        let mut p = PartialSums::new(Rect { x0: 3, y0: 4, width: 5, height: 2 });
        for i in 0..10 {
            p.add_sample(i, Vec3::new(0.1 * i as f32, 1e-30, 3e20));
        }
        let e = p.encode();
        assert_eq!(PartialSums::decode(p.rect, &e).unwrap(), p);
        assert!(PartialSums::decode(p.rect, &e[1..]).is_err());
        assert!(PartialSums::decode(Rect { x0: 0, y0: 0, width: u32::MAX, height: u32::MAX }, &e).is_err());
    }
}
