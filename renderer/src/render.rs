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
use std::time::Instant;

use crate::budget;
pub use crate::budget::{StopReason, TILE};

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

/// What [`render`] produced.
#[derive(Debug)]
pub struct Rendered {
    /// The image: every tile's sums, folded in pass order.
    pub image: PartialSums,
    /// Per tile (row-major [`Rect::tiles`] of side [`TILE`]): its sums and how many passes it holds.
    pub tiles: Vec<(PartialSums, u32)>,
    /// Passes of the whole image that were started (the largest per-tile pass count).
    pub passes: u32,
    pub stop: StopReason,
}

impl Rendered {
    /// Largest samples per pixel of any tile.
    pub fn spp_max(&self, settings: &RenderSettings) -> u32 {
        settings.samples_after(self.passes)
    }
}

/// Renders the whole image pass by pass: each pass renders every tile that still needs samples
/// into sums starting from zero, folded into the tile in pass order (the determinism rule). Stops
/// when every tile has its samples (sample count or noise target, [`budget::tile_needs_more`]),
/// when the time budget allows no further pass ([`budget::may_start_pass`]), or after the current
/// pass when `counters.cancel` is set.
pub fn render(scene: &Scene, settings: &RenderSettings, counters: &Counters) -> Rendered {
    let start = Instant::now();
    let full = Rect { x0: 0, y0: 0, width: settings.width, height: settings.height };
    let rects = Rect::tiles(settings.width, settings.height, TILE);
    let mut tiles: Vec<(PartialSums, u32)> = rects.iter().map(|r| (PartialSums::new(*r), 0)).collect();
    let mut active: Vec<usize> = (0..rects.len()).collect();
    let mut stop = StopReason::SampleCount;
    let mut passes = 0;
    while !active.is_empty() {
        if counters.cancel.load(Ordering::Relaxed) {
            stop = StopReason::Cancelled;
            break;
        }
        if !budget::may_start_pass(settings, start.elapsed().as_secs_f64(), passes) {
            stop = StopReason::TimeBudget;
            break;
        }
        let range = settings.pass_range(passes);
        let sums: Vec<PartialSums> = active
            .par_iter()
            .map(|&t| render_tile_counted(scene, settings, rects[t], range.clone(), counters))
            .collect();
        passes += 1;
        for (&t, s) in active.iter().zip(&sums) {
            let (tile, folded) = &mut tiles[t];
            tile.merge(s).expect("a tile's pass has the tile's rect");
            *folded += 1;
        }
        active.retain(|&t| budget::tile_needs_more(settings, &tiles[t].0, tiles[t].1));
    }
    if stop == StopReason::SampleCount && tiles.iter().any(|(_, f)| *f < settings.pass_count()) {
        stop = StopReason::NoiseTarget;
    }
    let mut image = PartialSums::new(full);
    for (t, _) in &tiles {
        image.merge_tile(t).expect("tiles lie inside the image");
    }
    Rendered { image, tiles, passes, stop }
}
