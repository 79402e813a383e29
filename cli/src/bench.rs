//! `tessera bench`: paths/s and rays/s on a scene, median over several runs.

use crate::render_cmd::{init_threads, load_scene, RenderFlags};
use anyhow::Result;
use clap::Args;
use renderer::Counters;
use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::time::Instant;

#[derive(Args, Debug)]
#[command(args_conflicts_with_subcommands = true)]
pub struct BenchArgs {
    #[command(subcommand)]
    pub what: Option<BenchKind>,
    /// Scene file (default: the built-in Cornell box).
    pub scene: Option<PathBuf>,
    /// Number of timed runs (after one warm-up).
    #[arg(long, default_value_t = 5)]
    pub runs: usize,
    #[command(flatten)]
    pub flags: RenderFlags,
    #[arg(long)]
    pub threads: Option<usize>,
    /// Ray-query structure: obvhs (CWBVH, nodes decompressed up to 65 536 triangles; default),
    /// obvhs-compressed (CWBVH with compressed nodes at every size) or own (binned-SAH BVH2); the
    /// last two for comparison.
    #[arg(long, default_value = "obvhs")]
    pub accel: renderer::accel::AccelKind,
}

#[derive(clap::Subcommand, Debug)]
pub enum BenchKind {
    /// Error against time for every technique switch over a scene suite: CSV, PNG plots, summary.
    Convergence(crate::convergence::ConvergenceArgs),
    /// Production size: a 10⁴-instance scene of a 10⁵-triangle mesh and 10⁷ unique triangles —
    /// load, BVH build, memory and a short render.
    Scale(crate::scale::ScaleArgs),
    /// The ray-query engine alone on one thread: BVH build time and closest-hit / occlusion
    /// Mrays/s for incoherent rays inside a dense icosphere, for each accelerator (`--dump`
    /// writes the workload for scenes/references/bench_embree.py).
    Rays(crate::rays::RaysArgs),
}

/// Median (the mean of the two middle values for an even count; NaN for none).
pub(crate) fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n == 0 {
        return f64::NAN;
    }
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

pub fn run(args: BenchArgs) -> Result<()> {
    match args.what {
        Some(BenchKind::Convergence(a)) => return crate::convergence::run(a),
        Some(BenchKind::Scale(a)) => {
            init_threads(args.threads)?;
            return crate::scale::run(a);
        }
        Some(BenchKind::Rays(a)) => return crate::rays::run(a),
        None => {}
    }
    init_threads(args.threads)?;
    let mut scene = load_scene(args.scene.as_deref())?;
    let t = Instant::now();
    scene.use_accel(args.accel);
    let build = t.elapsed().as_secs_f64();
    let settings = args.flags.settings(&scene)?;
    scene.prepare(&settings, std::path::Path::new("."))?;
    let paths = settings.width as f64 * settings.height as f64 * settings.spp as f64;
    println!(
        "scene {} | {}x{} {} spp | integrator {:?} sampler {:?} | {} threads | accel {:?} built in {:.3}s",
        args.scene.as_ref().map_or("built-in cornell".to_string(), |p| p.display().to_string()),
        settings.width,
        settings.height,
        settings.spp,
        settings.integrator,
        settings.sampler,
        rayon::current_num_threads(),
        args.accel,
        build
    );
    let (mut times, mut path_rates, mut ray_rates) = (Vec::new(), Vec::new(), Vec::new());
    for run in 0..=args.runs {
        let counters = Counters::default();
        let t = Instant::now();
        renderer::render(&scene, &settings, &counters);
        let secs = t.elapsed().as_secs_f64();
        let rays = counters.rays.load(Ordering::Relaxed) as f64;
        if run == 0 {
            println!("warm-up: {secs:.3}s");
            continue;
        }
        println!("run {run}: {secs:.3}s  {:.3} Mpaths/s  {:.3} Mrays/s", paths / secs / 1e6, rays / secs / 1e6);
        times.push(secs);
        path_rates.push(paths / secs);
        ray_rates.push(rays / secs);
    }
    println!(
        "median: {:.3}s  {:.3} Mpaths/s  {:.3} Mrays/s",
        median(times),
        median(path_rates) / 1e6,
        median(ray_rates) / 1e6
    );
    Ok(())
}
