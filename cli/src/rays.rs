//! `tessera bench rays`: the ray-query engine alone, on one thread — BVH build time, closest-hit
//! and occlusion rays per second for incoherent rays on a dense mesh — for each accelerator
//! (obvhs' CWBVH with decompressed and with compressed nodes, and the own BVH2), so they can be set beside Embree on the same workload
//! (`scenes/references/bench_embree.py` reads what `--dump` writes and runs Embree 4 on it).
//!
//! The default workload is the one the per-core-speed issue names: rays starting at random points
//! inside a subdivided unit icosphere (level 8: 1 310 720 triangles) in uniformly random
//! directions, so every ray hits and neighbouring rays share nothing. `--scene` takes a glTF
//! scene instead, with rays leaving its surfaces as a path tracer's bounce and shadow rays do.
//! Under obvhs' rows, "paired", "batch of 4" and "batch of 16" rows: the same rays two, four and
//! `accel::MAX_BATCH` at a time with their walks interleaved (`Accel::intersect_batch` and `occluded_batch`,
//! which renders use above `accel::BATCH_RAYS_ABOVE` triangles).

use crate::bench::median;
use anyhow::{Context, Result};
use clap::Args;
use renderer::accel::{Accel, AccelKind};
use renderer::math::Vec3;
use renderer::mesh::{Mesh, Triangle};
use renderer::scene::Scene;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Args, Debug)]
pub struct RaysArgs {
    /// Icosphere subdivision level: 20·4^level triangles (7: 327 680; 8: 1 310 720).
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u32).range(0..=9))]
    pub level: u32,
    /// Number of rays per timed run.
    #[arg(long, default_value_t = 1_000_000, value_parser = clap::value_parser!(u32).range(1..=100_000_000))]
    pub rays: u32,
    /// Timed runs per query (after one warm-up); the median is reported.
    #[arg(long, default_value_t = 5)]
    pub runs: usize,
    /// Write the workload and Tessera's hit distances (raw little-endian f32 arrays) into this
    /// folder: vertices.f32 (triangles × 3 × xyz), origins.f32, directions.f32, t_closest.f32
    /// (infinite for a ray that hits nothing); with `--scene`, also the occlusion rays'
    /// shadow_directions.f32 and shadow_tmax.f32 (they start at the same origins).
    #[arg(long)]
    pub dump: Option<PathBuf>,
    /// A glTF scene instead of the icosphere, with a path tracer's kind of rays: each starts just
    /// off a random point of a random triangle (area-weighted), the closest-hit ray in a
    /// cosine-distributed direction on the side the triangle faces, the occlusion ray toward a
    /// random point of another random triangle, stopping just short of it.
    #[arg(long)]
    pub scene: Option<PathBuf>,
    /// Only this accelerator: obvhs, obvhs-compressed or own (default: all three). With
    /// `--no-batches`, a run times one walk alone, so two builds can be alternated quickly.
    #[arg(long)]
    pub accel: Option<AccelKind>,
    /// Leave out the batched rows ("paired", "batch of 4", "batch of 16").
    #[arg(long)]
    pub no_batches: bool,
}

impl RaysArgs {
    /// The accelerators to time, in the table's order.
    fn kinds(&self) -> Vec<AccelKind> {
        let all = [AccelKind::Obvhs, AccelKind::ObvhsCompressed, AccelKind::Own];
        all.into_iter().filter(|k| self.accel.is_none_or(|a| a == *k)).collect()
    }
}

/// The `--scene` workload: one origin per ray, its closest-hit direction, and its occlusion ray's
/// direction and length.
struct SurfaceRays {
    origins: Vec<Vec3>,
    dirs: Vec<Vec3>,
    shadow: Vec<(Vec3, f32)>,
}

fn surface_rays(scene: &Scene, n: u32) -> Result<SurfaceRays> {
    let mesh = &scene.mesh;
    let u = renderer::sampler::hash_unit;
    let areas: Vec<f32> = (0..mesh.triangles.len() as u32).map(|i| mesh.area(i)).collect();
    let cdf: Vec<f64> = areas
        .iter()
        .scan(0.0f64, |acc, &a| {
            *acc += a as f64;
            Some(*acc)
        })
        .collect();
    let total = cdf.last().copied().unwrap_or(0.0);
    anyhow::ensure!(total > 0.0, "the scene has no triangle with an area");
    let pick = |x: f32| cdf.partition_point(|&c| c < x as f64 * total).min(cdf.len() - 1) as u32;
    // A point of triangle `tri` from two uniform numbers (the square's upper half folded in).
    let point = |tri: u32, a: f32, b: f32| {
        let (a, b) = if a + b > 1.0 { (1.0 - a, 1.0 - b) } else { (a, b) };
        mesh.surface_point(tri, a, b)
    };
    let (mut origins, mut dirs, mut shadow) = (Vec::new(), Vec::new(), Vec::new());
    for i in 0..n as u64 {
        let k = 16 * i;
        let sp = point(pick(u(k)), u(k + 1), u(k + 2));
        // Leaving the triangle as the renderer's paths do.
        let o = scene.spawn_origin(sp.p, sp.ng, sp.plane_error);
        let local = renderer::math::sample_cosine_hemisphere(renderer::math::Vec2::new(u(k + 3), u(k + 4)));
        let d = renderer::math::Frame::from_normal(sp.ng).to_world(local);
        let target = point(pick(u(k + 5)), u(k + 6), u(k + 7)).p;
        let to = target - o;
        let len = to.length();
        origins.push(o);
        dirs.push(d);
        shadow.push(if len > 0.0 { (to / len, len * (1.0 - 1e-3)) } else { (Vec3::Z, 0.0) });
    }
    Ok(SurfaceRays { origins, dirs, shadow })
}

/// `bench rays --scene`: Mrays/s of each accelerator on [`surface_rays`].
fn run_scene(a: &RaysArgs, path: &Path) -> Result<()> {
    let scene = renderer::gltf_loader::load(path).with_context(|| format!("cannot load {}", path.display()))?;
    let mesh = &scene.mesh;
    let SurfaceRays { origins, dirs, shadow } = surface_rays(&scene, a.rays)?;
    let (shadow_dirs, shadow_tmax): (Vec<Vec3>, Vec<f32>) = shadow.iter().copied().unzip();
    let batched = Batched { origins: &origins, dirs: &dirs, shadow_dirs: &shadow_dirs, shadow_tmax: &shadow_tmax };
    println!(
        "{}: {} triangles | {} rays off its surfaces | 1 thread | median of {} runs",
        path.display(),
        mesh.triangles.len(),
        a.rays,
        a.runs
    );
    println!("{:<16} {:>10} {:>16} {:>16}", "accel", "build s", "closest Mrays/s", "occluded Mrays/s");
    let mut closest_t = Vec::new();
    for (nth, kind) in a.kinds().into_iter().enumerate() {
        let t = Instant::now();
        let accel = Accel::build_with(mesh, kind);
        let build = t.elapsed().as_secs_f64();
        let (mut closest, mut occluded) = (Vec::new(), Vec::new());
        // Each ray's closest-hit distance (infinite: none), as the icosphere's `run` keeps them.
        let mut ts = vec![f32::INFINITY; origins.len()];
        for run in 0..=a.runs {
            let t = Instant::now();
            for (i, (o, d)) in origins.iter().zip(&dirs).enumerate() {
                ts[i] = accel.intersect(*o, *d, f32::INFINITY).map_or(f32::INFINITY, |h| h.t);
            }
            let secs = t.elapsed().as_secs_f64();
            let t = Instant::now();
            let blocked = origins.iter().zip(&shadow).filter(|(o, (d, len))| accel.occluded(**o, *d, *len)).count();
            let secs_occ = t.elapsed().as_secs_f64();
            if run > 0 {
                closest.push(origins.len() as f64 / secs / 1e6);
                occluded.push(origins.len() as f64 / secs_occ / 1e6);
            }
            std::hint::black_box(blocked);
        }
        let hits = ts.iter().filter(|t| t.is_finite()).count();
        println!(
            "{:<16} {:>10.3} {:>16.3} {:>16.3}  ({hits} closest hits)",
            kind.name(),
            build,
            median(closest),
            median(occluded)
        );
        if kind == AccelKind::Obvhs && !a.no_batches {
            batched.print(&accel, a.runs);
        }
        // The dump's distances: the first accelerator's (obvhs' unless `--accel` chose another).
        if nth == 0 {
            closest_t = ts;
        }
    }
    if let Some(dir) = &a.dump {
        dump(dir, mesh, &origins, &dirs, &closest_t)?;
        write_f32s(&dir.join("shadow_directions.f32"), shadow_dirs.iter().flat_map(|v| v.to_array()))?;
        write_f32s(&dir.join("shadow_tmax.f32"), shadow_tmax.iter().copied())?;
    }
    Ok(())
}

/// `--dump`'s files common to both workloads (see [`RaysArgs::dump`]).
fn dump(dir: &Path, mesh: &Mesh, origins: &[Vec3], dirs: &[Vec3], closest_t: &[f32]) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    write_f32s(
        &dir.join("vertices.f32"),
        (0..mesh.triangles.len() as u32).flat_map(|i| mesh.vertices(i)).flat_map(|v| v.to_array()),
    )?;
    write_f32s(&dir.join("origins.f32"), origins.iter().flat_map(|v| v.to_array()))?;
    write_f32s(&dir.join("directions.f32"), dirs.iter().flat_map(|v| v.to_array()))?;
    write_f32s(&dir.join("t_closest.f32"), closest_t.iter().copied())?;
    println!("workload written to {}", dir.display());
    Ok(())
}

/// The rows under an accelerator's for rays traced `k` at a time with their walks interleaved
/// (`Accel::intersect_batch` and `occluded_batch`, what renders of large scenes use): median
/// Mrays/s of `runs` timed runs after a warm-up that also checks every batch's answers against
/// each ray alone.
struct Batched<'a> {
    origins: &'a [Vec3],
    dirs: &'a [Vec3],
    /// The occlusion rays (from `origins`): directions and lengths.
    shadow_dirs: &'a [Vec3],
    shadow_tmax: &'a [f32],
}

impl Batched<'_> {
    fn print(&self, accel: &Accel, runs: usize) {
        for k in [2, 4, renderer::accel::MAX_BATCH] {
            self.print_row(accel, runs, k);
        }
    }

    fn print_row(&self, accel: &Accel, runs: usize, k: usize) {
        let Batched { origins, dirs, shadow_dirs, shadow_tmax } = *self;
        let batches = origins.len() / k;
        let (mut closest, mut occluded, mut same) = (Vec::new(), Vec::new(), true);
        let (mut h, mut blocked) = (vec![None; k], vec![false; k]);
        for run in 0..=runs {
            let t = Instant::now();
            let mut found = 0usize;
            for i in (0..k * batches).step_by(k) {
                accel.intersect_batch(&origins[i..i + k], &dirs[i..i + k], f32::INFINITY, &mut h);
                found += h.iter().filter(|h| h.is_some()).count();
                if run == 0 {
                    for (j, hj) in h.iter().enumerate() {
                        let alone = accel.intersect(origins[i + j], dirs[i + j], f32::INFINITY);
                        same &= alone.map(|h| (h.t, h.triangle)) == hj.map(|h| (h.t, h.triangle));
                    }
                }
            }
            let secs = t.elapsed().as_secs_f64();
            let t = Instant::now();
            for i in (0..k * batches).step_by(k) {
                accel.occluded_batch(&origins[i..i + k], &shadow_dirs[i..i + k], &shadow_tmax[i..i + k], &mut blocked);
                found += blocked.iter().filter(|b| **b).count();
                if run == 0 {
                    for (j, bj) in blocked.iter().enumerate() {
                        same &= accel.occluded(origins[i + j], shadow_dirs[i + j], shadow_tmax[i + j]) == *bj;
                    }
                }
            }
            let secs_occ = t.elapsed().as_secs_f64();
            if run > 0 {
                closest.push((k * batches) as f64 / secs / 1e6);
                occluded.push((k * batches) as f64 / secs_occ / 1e6);
            }
            std::hint::black_box(found);
        }
        let name = if k == 2 { "  paired".to_string() } else { format!("  batch of {k}") };
        println!(
            "{:<16} {:>10} {:>16.3} {:>16.3}  (same hits as one at a time: {same})",
            name,
            "",
            median(closest),
            median(occluded)
        );
    }
}

/// The workload's rays: origins uniform in the ball of radius 0.5, directions uniform on the
/// sphere, from a counter-based hash so every run (and the dump) sees the same rays.
fn rays(n: u32) -> (Vec<Vec3>, Vec<Vec3>) {
    let u = renderer::sampler::hash_unit;
    let mut origins = Vec::with_capacity(n as usize);
    let mut dirs = Vec::with_capacity(n as usize);
    for i in 0..n as u64 {
        let k = i * 8;
        // Direction: z uniform in [−1, 1], azimuth uniform (Archimedes).
        let z = 1.0 - 2.0 * u(k);
        let phi = std::f32::consts::TAU * u(k + 1);
        let r = (1.0 - z * z).max(0.0).sqrt();
        dirs.push(Vec3::new(r * phi.cos(), r * phi.sin(), z));
        // Origin: a uniform direction times radius 0.5·∛u.
        let z = 1.0 - 2.0 * u(k + 2);
        let phi = std::f32::consts::TAU * u(k + 3);
        let r = (1.0 - z * z).max(0.0).sqrt();
        let rad = 0.5 * u(k + 4).cbrt();
        origins.push(Vec3::new(r * phi.cos(), r * phi.sin(), z) * rad);
    }
    (origins, dirs)
}

fn write_f32s(path: &Path, values: impl Iterator<Item = f32>) -> Result<()> {
    let mut w = std::io::BufWriter::new(
        std::fs::File::create(path).with_context(|| format!("cannot create {}", path.display()))?,
    );
    for v in values {
        w.write_all(&v.to_le_bytes())?;
    }
    w.flush().with_context(|| format!("cannot write {}", path.display()))
}

pub fn run(a: RaysArgs) -> Result<()> {
    if let Some(path) = &a.scene {
        return run_scene(&a, path);
    }
    let (positions, faces) = renderer::testing::icosphere(a.level);
    let mesh = Mesh {
        triangles: faces.iter().map(|&v| Triangle { v, material: 0, flags: 0 }).collect(),
        positions,
        ..Mesh::default()
    };
    let (origins, dirs) = rays(a.rays);
    let shadow_tmax = vec![10.0; origins.len()];
    let batched = Batched { origins: &origins, dirs: &dirs, shadow_dirs: &dirs, shadow_tmax: &shadow_tmax };
    println!(
        "icosphere level {}: {} triangles | {} incoherent rays from inside | 1 thread | median of {} runs",
        a.level,
        mesh.triangles.len(),
        a.rays,
        a.runs
    );
    println!("{:<16} {:>10} {:>16} {:>16}", "accel", "build s", "closest Mrays/s", "occluded Mrays/s");
    let mut closest_t: Vec<f32> = Vec::new();
    for (nth, kind) in a.kinds().into_iter().enumerate() {
        let t = Instant::now();
        let accel = Accel::build_with(&mesh, kind);
        let build = t.elapsed().as_secs_f64();
        let (mut closest, mut occluded) = (Vec::new(), Vec::new());
        let mut misses = 0usize;
        let mut ts = vec![f32::INFINITY; origins.len()];
        for run in 0..=a.runs {
            let t = Instant::now();
            for (i, (o, d)) in origins.iter().zip(&dirs).enumerate() {
                ts[i] = accel.intersect(*o, *d, f32::INFINITY).map_or(f32::INFINITY, |h| h.t);
            }
            let secs = t.elapsed().as_secs_f64();
            let t = Instant::now();
            let mut blocked = 0usize;
            for (o, d) in origins.iter().zip(&dirs) {
                blocked += accel.occluded(*o, *d, 10.0) as usize;
            }
            let secs_occ = t.elapsed().as_secs_f64();
            misses = origins.len() - blocked;
            if run > 0 {
                closest.push(origins.len() as f64 / secs / 1e6);
                occluded.push(origins.len() as f64 / secs_occ / 1e6);
            }
        }
        let lost = ts.iter().filter(|t| !t.is_finite()).count();
        println!(
            "{:<16} {:>10.3} {:>16.3} {:>16.3}{}",
            kind.name(),
            build,
            median(closest),
            median(occluded),
            if lost + misses > 0 {
                format!("  ({lost} closest / {misses} occlusion rays escaped)")
            } else {
                String::new()
            }
        );
        if (kind == AccelKind::Obvhs || kind == AccelKind::ObvhsCompressed) && !a.no_batches {
            batched.print(&accel, a.runs);
        }
        if nth == 0 {
            closest_t = ts;
        }
    }
    if let Some(dir) = &a.dump {
        dump(dir, &mesh, &origins, &dirs, &closest_t)?;
    }
    Ok(())
}
