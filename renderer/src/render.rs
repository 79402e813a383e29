//! Rendering a tile over a sample range into [`PartialSums`], and a whole image by passes.

use crate::film::{PartialSums, Rect};
use crate::integrator::radiance;
use crate::math::Vec2;
use crate::sampler::{dims, PixelSample};
use crate::scene::Scene;
use crate::settings::{PixelFilter, RenderSettings};
use rayon::prelude::*;
use std::ops::Range;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

/// Live counters a caller may watch while rendering (progress bars, rays/s, metrics).
#[derive(Default, Debug)]
pub struct Counters {
    /// Pixel samples finished.
    pub samples: AtomicU64,
    /// Rays traced (camera, bounce and shadow rays).
    pub rays: AtomicU64,
    /// Samples whose estimate was not finite and was replaced by zero (should stay 0).
    pub nonfinite: AtomicU64,
    /// Set to stop `render` at the next pass boundary (the image stays unbiased).
    pub cancel: AtomicBool,
}

/// Samples a filter offset from the pixel centre, in pixels (filter importance sampling).
#[inline]
fn filter_offset(filter: PixelFilter, u: Vec2) -> Vec2 {
    match filter {
        PixelFilter::Box => u - Vec2::splat(0.5),
        PixelFilter::Tent => {
            let tent = |x: f32| {
                if x < 0.5 {
                    (2.0 * x).sqrt() - 1.0
                } else {
                    1.0 - (2.0 - 2.0 * x).sqrt()
                }
            };
            Vec2::new(tent(u.x), tent(u.y))
        }
    }
}

/// Renders samples `samples` of every pixel in `rect`. The result for a pixel is the in-order f64
/// sum, starting from zero, of its samples' radiance: independent of threads, tile shapes and of
/// whatever else is rendered in the same call.
pub fn render_tile(scene: &Scene, settings: &RenderSettings, rect: Rect, samples: Range<u32>) -> PartialSums {
    render_tile_counted(scene, settings, rect, samples, &Counters::default())
}

pub fn render_tile_counted(
    scene: &Scene,
    settings: &RenderSettings,
    rect: Rect,
    samples: Range<u32>,
    counters: &Counters,
) -> PartialSums {
    let camera = scene
        .camera(settings.camera)
        .unwrap_or_else(|_| crate::camera::Camera::framing(scene.bounds.0, scene.bounds.1));
    let (w, h) = (settings.width, settings.height);
    let pixels: Vec<([f64; 3], f64, u32)> = (0..rect.pixels())
        .into_par_iter()
        .map(|i| {
            let x = rect.x0 + (i as u32 % rect.width);
            let y = rect.y0 + (i as u32 / rect.width);
            let (mut rgb, mut lum_sq) = ([0.0f64; 3], 0.0f64);
            let mut rays = 0u64;
            let mut bad = 0u64;
            for s in samples.clone() {
                let sampler = PixelSample::new(settings.sampler, settings.seed, (x, y), s);
                let film = Vec2::new(x as f32 + 0.5, y as f32 + 0.5)
                    + filter_offset(settings.filter, sampler.get_2d(dims::FILM));
                let d = camera.ray_direction(film, w, h);
                let mut l = radiance(scene, settings, camera.origin, d, &sampler, &mut rays);
                if !l.is_finite() {
                    bad += 1;
                    l = crate::math::Vec3::ZERO;
                }
                // Same arithmetic as PartialSums::add_sample, in sample order (determinism rule 2).
                rgb[0] += l.x as f64;
                rgb[1] += l.y as f64;
                rgb[2] += l.z as f64;
                let y = crate::math::luminance(l) as f64;
                lum_sq += y * y;
            }
            counters.rays.fetch_add(rays, Ordering::Relaxed);
            counters.samples.fetch_add(samples.len() as u64, Ordering::Relaxed);
            if bad > 0 {
                counters.nonfinite.fetch_add(bad, Ordering::Relaxed);
            }
            (rgb, lum_sq, samples.len() as u32)
        })
        .collect();
    let mut out = PartialSums::new(rect);
    for (i, (rgb, lsq, n)) in pixels.into_iter().enumerate() {
        out.sum_rgb[i] = rgb;
        out.sum_lum_sq[i] = lsq;
        out.count[i] = n;
    }
    out
}

/// Tile side used by the local renderer (any value gives the same image).
pub const LOCAL_TILE: u32 = 32;

/// Renders the whole image pass by pass: each pass is rendered into per-tile sums starting from
/// zero and folded into the image in pass order (the determinism rule). `on_pass` sees the image
/// after each pass. Stops after the current pass when `counters.cancel` is set; returns the image and
/// the number of samples per pixel it holds.
pub fn render(
    scene: &Scene,
    settings: &RenderSettings,
    counters: &Counters,
    mut on_pass: impl FnMut(&PartialSums),
) -> (PartialSums, u32) {
    let full = Rect { x0: 0, y0: 0, width: settings.width, height: settings.height };
    let mut image = PartialSums::new(full);
    let tiles = Rect::tiles(settings.width, settings.height, LOCAL_TILE);
    let mut done = 0;
    for pass in settings.passes() {
        if counters.cancel.load(Ordering::Relaxed) {
            break;
        }
        let sums: Vec<PartialSums> =
            tiles.par_iter().map(|t| render_tile_counted(scene, settings, *t, pass.clone(), counters)).collect();
        for s in &sums {
            // Tiles are disjoint, so every pixel receives exactly one addition per pass.
            image.merge_tile(s).expect("local tiles lie inside the image");
        }
        done = pass.end;
        on_pass(&image);
    }
    (image, done)
}
