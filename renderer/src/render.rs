//! Rendering a tile over a sample range into [`PartialSums`], and a whole image by passes.

use crate::accel::MAX_BATCH;
use crate::film::{PartialSums, Rect};
use crate::integrator::{radiance, radiance_batch};
use crate::math::{Vec2, Vec3};
use crate::sampler::{dims, PixelSample};
use crate::scene::Scene;
use crate::settings::{PixelFilter, RenderSettings};
use rayon::prelude::*;
use std::ops::Range;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Instant;

use crate::budget;
pub use crate::budget::{StopReason, TILE};
use crate::noise::NoiseEstimate;

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
    /// After each pass: the image's estimated relative error (`f64` bits; 0 until every pixel has
    /// two samples). For progress displays; the result's own estimate is the one to report.
    pub rel_error_bits: AtomicU64,
    /// After each pass: the fraction of the work done (`f64` bits), the same measure the farm
    /// reports: samples done of those planned, and under a noise target each unfinished tile
    /// counts (target / error)², at most 0.99 (relative MSE falls as 1/spp).
    pub progress_bits: AtomicU64,
}

impl Counters {
    /// The estimated relative error after the last pass (None before it is known).
    pub fn rel_error(&self) -> Option<f64> {
        let e = f64::from_bits(self.rel_error_bits.load(Ordering::Relaxed));
        (e > 0.0 && e.is_finite()).then_some(e)
    }

    /// The fraction of the work done after the last pass (0 before the first).
    pub fn progress(&self) -> f64 {
        f64::from_bits(self.progress_bits.load(Ordering::Relaxed))
    }
}

/// The error and progress `Counters` reports after a pass, from each tile's noise estimate (kept
/// by `render`, made once per pass for the tiles that pass changed): pixel-weighted relative MSE
/// over the tiles, and per tile [`budget::tile_progress`].
fn pass_report(
    settings: &RenderSettings,
    tiles: &[(PartialSums, u32)],
    noise: &[NoiseEstimate],
    active: &[usize],
) -> (f64, f64) {
    let (mut mse, mut frac, mut px) = (0.0f64, 0.0f64, 0.0f64);
    let mut still = vec![false; tiles.len()];
    for &t in active {
        still[t] = true;
    }
    for (t, ((sums, folded), e)) in tiles.iter().zip(noise).enumerate() {
        let n = sums.rect.pixels() as f64;
        mse += e.rel_mse * n;
        px += n;
        frac += budget::tile_progress(settings, *folded, !still[t], e.rel_error) * n;
    }
    let px = px.max(1.0);
    ((mse / px).sqrt(), frac / px)
}

/// One pixel's sums over its samples in a tile, and the non-finite samples it met.
#[derive(Default)]
struct PixelSums {
    rgb: [f64; 3],
    lum_sq: f64,
    bad: u64,
}

impl PixelSums {
    /// Adds one sample (a non-finite one as zero, counted). Same arithmetic as
    /// `PartialSums::add_sample`, in sample order (determinism rule 2).
    #[inline(always)]
    fn add(&mut self, l: crate::math::Vec3) {
        let l = if l.is_finite() {
            l
        } else {
            self.bad += 1;
            crate::math::Vec3::ZERO
        };
        self.rgb[0] += l.x as f64;
        self.rgb[1] += l.y as f64;
        self.rgb[2] += l.z as f64;
        let y = crate::math::luminance(l) as f64;
        self.lum_sq += y * y;
    }
}

/// Sample `s` of pixel (x, y): its sample generator and camera ray direction.
#[inline(always)]
fn camera_ray(
    settings: &RenderSettings,
    raster: &crate::camera::Raster,
    (x, y): (u32, u32),
    s: u32,
) -> (PixelSample, crate::math::Vec3) {
    let sampler = PixelSample::new(settings.sampler, settings.seed, (x, y), s);
    let film = Vec2::new(x as f32 + 0.5, y as f32 + 0.5) + filter_offset(settings.filter, sampler.get_2d(dims::FILM));
    (sampler, raster.direction(film))
}

/// [`camera_ray`] for samples `first .. first + n` (n ≤ 8) of a pixel (`pixel_sampler`: its
/// sampler of any index) at once, for the SPMD kernel: the film dimensions of the eight samples
/// drawn together (`sampler::get_4d_lanes`), the filter offsets and directions eight-wide, each
/// lane in `camera_ray`'s operations (same bits; `spmd.rs`' tests compare whole images).
/// Samples that do not share their Sobol seeds (a 2^16 block boundary, the independent sampler)
/// take `camera_ray` one at a time.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[inline(always)]
fn camera_rays8(
    settings: &RenderSettings,
    raster: &crate::camera::Raster,
    (x, y): (u32, u32),
    pixel_sampler: &PixelSample,
    first: u32,
    samplers: &mut [PixelSample],
    dirs: &mut [Vec3],
) {
    use crate::lanes::{select, F8};
    let n = samplers.len().min(dirs.len()).min(crate::spmd::LANES);
    for (k, s) in samplers[..n].iter_mut().enumerate() {
        *s = pixel_sampler.at(first + k as u32);
    }
    let mut u = [[0f32; 8]; 4];
    if !crate::sampler::get_4d_lanes(&samplers[..n], dims::FILM / 4, &mut u) {
        for k in 0..n {
            (samplers[k], dirs[k]) = camera_ray(settings, raster, (x, y), first + k as u32);
        }
        return;
    }
    let d = (dims::FILM % 4) as usize;
    let (ux, uy) = (F8::from_array(u[d]), F8::from_array(u[(d + 1) % 4]));
    let (half, one, two) = (F8::splat(0.5), F8::splat(1.0), F8::splat(2.0));
    // `filter_offset`, eight-wide.
    let offset = |u: F8| match settings.filter {
        PixelFilter::Box => u - half,
        PixelFilter::Tent => select(u.lt(half), (two * u).sqrt() - one, one - (two - two * u).sqrt()),
    };
    let fx = F8::splat(x as f32 + 0.5) + offset(ux);
    let fy = F8::splat(y as f32 + 0.5) + offset(uy);
    let d = raster.directions8(fx, fy);
    match <&mut [Vec3; crate::spmd::LANES]>::try_from(&mut dirs[..n]) {
        Ok(all) => d.store_lanes(all),
        Err(_) => dirs[..n].copy_from_slice(&d.to_lanes()[..n]),
    }
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
    let raster = camera.raster(settings.width, settings.height);
    let batches = scene.batches_paths();
    // The kernel's lanes where it renders the scene (`spmd`), else sixteen paths a batch where
    // it pays (`radiance_batch`), else one at a time: the same sums all three ways.
    let lanes = scene.lanes(settings);
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    if let Some(materials) = lanes {
        let (sums, rays, bad) =
            kernel_pixels(scene, materials, settings, &raster, camera.origin, rect, samples.clone());
        count(counters, rect, &samples, rays, bad);
        return sums;
    }
    let width = if lanes.is_none() && batches { MAX_BATCH } else { 1 };
    // Per pixel: its sums, its sample count, and the rays traced and non-finite samples met, which
    // go to the shared counters once per tile rather than once per pixel (threads adding to the
    // same atomics contend for their cache line).
    let pixels: Vec<PixelResult> = (0..rect.pixels())
        .into_par_iter()
        .map(|i| {
            let x = rect.x0 + (i as u32 % rect.width);
            let y = rect.y0 + (i as u32 / rect.width);
            let mut rays = 0u64;
            let mut sums = PixelSums::default();
            let mut s = samples.start;
            if width > 1 {
                // `width` samples' paths at a time, added in sample order: the same sums as one
                // at a time. A batch leaves a pixel's last sample to the single path (a batch of
                // one is that path with bookkeeping).
                let (mut samplers, mut dirs, mut l) = (
                    [PixelSample::new(settings.sampler, settings.seed, (x, y), 0); MAX_BATCH],
                    [Vec3::ZERO; MAX_BATCH],
                    [Vec3::ZERO; MAX_BATCH],
                );
                while s + 1 < samples.end {
                    let n = ((samples.end - s) as usize).min(width);
                    for k in 0..n {
                        (samplers[k], dirs[k]) = camera_ray(settings, &raster, (x, y), s + k as u32);
                    }
                    let (dirs, samplers, l) = (&dirs[..n], &samplers[..n], &mut l[..n]);
                    radiance_batch(scene, settings, camera.origin, dirs, samplers, &mut rays, l);
                    for lk in l.iter() {
                        sums.add(*lk);
                    }
                    s += n as u32;
                }
            }
            for s in s..samples.end {
                let (sampler, d) = camera_ray(settings, &raster, (x, y), s);
                sums.add(radiance(scene, settings, camera.origin, d, &sampler, &mut rays));
            }
            (sums, rays)
        })
        .collect();
    tile_sums(rect, samples, pixels, counters)
}

/// One pixel's result in a tile: its sums and rays traced (which go to the shared counters once
/// per tile rather than once per pixel: threads adding to the same atomics contend for their
/// cache line).
type PixelResult = (PixelSums, u64);

/// A tile's sums from its pixels' results (row-major), each of `samples.len()` samples, the
/// counters updated once.
fn tile_sums(rect: Rect, samples: Range<u32>, pixels: Vec<PixelResult>, counters: &Counters) -> PartialSums {
    let mut out = PartialSums::new(rect);
    let (mut rays, mut bad) = (0u64, 0u64);
    for (i, (PixelSums { rgb, lum_sq, bad: b }, r)) in pixels.into_iter().enumerate() {
        out.sum_rgb[i] = rgb;
        out.sum_lum_sq[i] = lum_sq;
        out.count[i] = samples.len() as u32;
        rays += r;
        bad += b;
    }
    count(counters, rect, &samples, rays, bad);
    out
}

/// A tile's rays, samples and non-finite samples into the shared counters, once a tile.
fn count(counters: &Counters, rect: Rect, samples: &Range<u32>, rays: u64, bad: u64) {
    counters.rays.fetch_add(rays, Ordering::Relaxed);
    counters.samples.fetch_add(samples.len() as u64 * rect.pixels() as u64, Ordering::Relaxed);
    if bad > 0 {
        counters.nonfinite.fetch_add(bad, Ordering::Relaxed);
    }
}

/// The pixels one task of the kernel streams through its lanes: sixteen pixels of sixteen
/// samples (a pass's default) fill one stream ([`crate::spmd::STREAM`]).
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
const STREAM_PIXELS: usize = 16;

/// [`render_tile_counted`]'s pixels through the SPMD kernel: each task takes [`STREAM_PIXELS`]
/// pixels, lays their samples' camera rays out pixel by pixel (eight at a time:
/// `camera_rays8`) in streams of up to [`crate::spmd::STREAM`] paths, and adds each path's
/// radiance to its pixel in sample order, so the sums are the one-path-at-a-time sums. Also
/// returns the rays traced and the non-finite samples met, for the counters.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
fn kernel_pixels(
    scene: &Scene,
    materials: &crate::spmd::LaneTable,
    settings: &RenderSettings,
    raster: &crate::camera::Raster,
    origin: Vec3,
    rect: Rect,
    samples: Range<u32>,
) -> (PartialSums, u64, u64) {
    use crate::spmd::{LANES, STREAM};
    // A thread's stream buffers (camera ray directions, samplers, each path's pixel as an offset
    // into the group, radiance), made once per thread rather than once per group.
    let buffers = || {
        let sampler = PixelSample::new(settings.sampler, settings.seed, (0, 0), 0);
        (vec![Vec3::ZERO; STREAM], vec![sampler; STREAM], vec![0u8; STREAM], vec![Vec3::ZERO; STREAM])
    };
    // Each group's sums written where the tile's sums hold them: no vector a group, joined into
    // one for the tile and copied into the sums (at a tile a pass, that was 66 allocations and
    // two copies of the tile's results). The counters' totals are sums of integers, the same in
    // any order.
    let mut out = PartialSums::new(rect);
    let (rays, bad) = out
        .sum_rgb
        .par_chunks_mut(STREAM_PIXELS)
        .zip(out.sum_lum_sq.par_chunks_mut(STREAM_PIXELS))
        .enumerate()
        .map_init(buffers, |(dirs, samplers, owner, l), (g, (sum_rgb, sum_lum_sq))| {
            let first = g * STREAM_PIXELS;
            let group = first..first + sum_rgb.len();
            let mut sums: [PixelSums; STREAM_PIXELS] = Default::default();
            let mut rays = 0u64;
            let mut fill = 0;
            let mut run = |dirs: &[Vec3], samplers: &[PixelSample], owner: &[u8], l: &mut [Vec3]| {
                let l = &mut l[..dirs.len()];
                // The kernel's build with the per-lane hit detail only where the scene has some.
                if materials.hit_detail {
                    crate::spmd::radiance8::<true>(scene, materials, settings, origin, dirs, samplers, &mut rays, l);
                } else {
                    crate::spmd::radiance8::<false>(scene, materials, settings, origin, dirs, samplers, &mut rays, l);
                }
                for (l, &o) in l.iter().zip(owner) {
                    sums[o as usize].add(*l);
                }
            };
            for i in group.clone() {
                let (x, y) = (rect.x0 + (i as u32 % rect.width), rect.y0 + (i as u32 / rect.width));
                let sampler = PixelSample::new(settings.sampler, settings.seed, (x, y), 0);
                let mut s = samples.start;
                while s < samples.end {
                    let m = ((samples.end - s) as usize).min(LANES).min(STREAM - fill);
                    let span = fill..fill + m;
                    camera_rays8(
                        settings,
                        raster,
                        (x, y),
                        &sampler,
                        s,
                        &mut samplers[span.clone()],
                        &mut dirs[span.clone()],
                    );
                    owner[span].fill((i - first) as u8);
                    (fill, s) = (fill + m, s + m as u32);
                    if fill == STREAM {
                        run(dirs, samplers, owner, l);
                        fill = 0;
                    }
                }
            }
            if fill > 0 {
                run(&dirs[..fill], &samplers[..fill], &owner[..fill], l);
            }
            let mut bad = 0;
            for ((rgb, lum_sq), s) in sum_rgb.iter_mut().zip(sum_lum_sq.iter_mut()).zip(sums) {
                (*rgb, *lum_sq, bad) = (s.rgb, s.lum_sq, bad + s.bad);
            }
            (rays, bad)
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    out.count.fill(samples.len() as u32);
    (out, rays, bad)
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
    // Each tile's noise, re-estimated only when a pass changed it (for the progress display).
    let unknown = NoiseEstimate { rel_mse: f64::INFINITY, rel_error: f64::INFINITY, spp_min: 0, spp_max: 0 };
    let mut noise = vec![unknown; rects.len()];
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
        // Each tile's pass folded into the tile as soon as it is rendered, not once every tile's
        // is: the pass's sums are freed where they were made and the next tile's reuse that
        // memory. Held until the pass ended, a whole image of them was freed at once, and glibc
        // gives the free space at a heap's top back to the kernel above 128 KiB: every pass
        // took fresh pages, each a page fault and a page of zeroes (`perf record`, depth-0 veach,
        // 256×192, 256 spp, one thread: `clear_page_erms` 5.5 %, page faults under
        // `Vec::from_iter` 3.7 % and `realloc` 1.4 %, with `kernel_pixels`' own vectors).
        // (`active` stays in ascending order: it starts so and is only ever `retain`ed.)
        let is_active = |t: &usize| active.binary_search(t).is_ok();
        tiles.par_iter_mut().zip(noise.par_iter_mut()).enumerate().filter(|(t, _)| is_active(t)).for_each(
            |(t, ((tile, folded), noise))| {
                let sums = render_tile_counted(scene, settings, rects[t], range.clone(), counters);
                tile.merge(&sums).expect("a tile's pass has the tile's rect");
                *folded += 1;
                *noise = crate::noise::estimate(tile);
            },
        );
        passes += 1;
        active.retain(|&t| budget::tile_needs_more(settings, &tiles[t].0, tiles[t].1));
        let (rel_error, progress) = pass_report(settings, &tiles, &noise, &active);
        counters.rel_error_bits.store(if rel_error.is_finite() { rel_error.to_bits() } else { 0 }, Ordering::Relaxed);
        counters.progress_bits.store(progress.to_bits(), Ordering::Relaxed);
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

#[cfg(test)]
mod tests {
    use super::pass_report;
    use crate::film::{PartialSums, Rect};
    use crate::math::Vec3;
    use crate::settings::RenderSettings;

    /// A 2×1 tile whose pixels hold samples 0.5 ± d: relative error known in closed form.
    fn tile(x0: u32, spp: u32, d: f32) -> PartialSums {
        let mut t = PartialSums::new(Rect { x0, y0: 0, width: 2, height: 1 });
        for i in 0..2 {
            for k in 0..spp {
                let v = if k % 2 == 0 { 0.5 + d } else { 0.5 - d };
                t.add_sample(i, Vec3::new(v, v, v));
            }
        }
        t
    }

    #[test]
    fn progress_counts_finished_tiles_whole_and_others_by_their_error() {
        let settings =
            RenderSettings { spp: 1024, pass_spp: 16, noise_target: Some(0.01), ..RenderSettings::default() };
        let (noisy, quiet) = (tile(0, 32, 0.2), tile(2, 32, 0.0));
        let e = crate::noise::estimate(&noisy).rel_error;
        let tiles = vec![(noisy, 2), (quiet, 2)];
        let noise: Vec<_> = tiles.iter().map(|(t, _)| crate::noise::estimate(t)).collect();
        // Tile 1 stopped (met the target); tile 0 is at error e: (0.01 / e)² of the way.
        let (err, frac) = pass_report(&settings, &tiles, &noise, &[0]);
        let expect = 0.5 * (0.01 / e).powi(2).clamp(2.0 / 64.0, 0.99) + 0.5;
        assert!((frac - expect).abs() < 1e-12, "{frac} vs {expect}");
        assert!((err - (e * e / 2.0).sqrt()).abs() < 1e-9, "pixel-weighted: {err} vs {e}");
        // Without a target, progress is the samples done.
        let fixed = RenderSettings { noise_target: None, ..settings };
        let (_, frac) = pass_report(&fixed, &tiles, &noise, &[0, 1]);
        assert!((frac - 2.0 / 64.0).abs() < 1e-12, "{frac}");
    }
}
