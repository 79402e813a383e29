//! `tessera render`: load a scene, render it with all cores, write EXR (+ optional PNG preview).

use anyhow::{bail, Context, Result};
use clap::Args;
use renderer::image_io::FinalImage;
use renderer::sampler::SamplerKind;
use renderer::settings_request::{SceneFacts, SettingsLimits, SettingsRequest};
use renderer::{Counters, IntegratorKind, MisHeuristic, PixelFilter, RenderSettings, Scene};
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

/// The Cornell box shipped inside the binary, rendered when no scene is given.
pub const EMBEDDED_CORNELL: &[u8] = include_bytes!("../../scenes/cornell/cornell.gltf");

/// Flags shared by every command that describes a render (render, bench, submit). They carry no
/// defaults of their own: they become a `renderer::settings_request::SettingsRequest`, which owns
/// every default and bound (the one settings schema), and `tessera submit` sends that same request.
#[derive(Args, Clone, Debug)]
pub struct RenderFlags {
    /// Samples per pixel (default 64). With --time-budget or --noise-target: the cap (default 65536).
    #[arg(long)]
    pub spp: Option<u64>,
    /// Stop at the last whole pass that fits in this many seconds of rendering (the image stays
    /// unbiased: every pixel gets the same passes).
    #[arg(long, value_name = "SECONDS")]
    pub time_budget: Option<f64>,
    /// Keep adding passes to each 32×32 tile until its estimated relative standard error is at most
    /// REL (e.g. 0.02): noisy tiles get more samples than quiet ones.
    #[arg(long, value_name = "REL")]
    pub noise_target: Option<f64>,
    /// With --noise-target: samples every pixel gets before its tile may stop (default 32).
    #[arg(long)]
    pub min_spp: Option<u64>,
    /// Image width (default: 640, or from --height and the camera's aspect ratio).
    #[arg(long)]
    pub width: Option<u64>,
    /// Image height (default: from the width and the camera's aspect ratio).
    #[arg(long)]
    pub height: Option<u64>,
    /// Index of the glTF camera to render through (default: the first, or a framing view).
    #[arg(long)]
    pub camera: Option<u64>,
    /// Light transport: mis (NEE + BSDF sampling, the default), nee, or bsdf (BSDF sampling only).
    #[arg(long)]
    pub integrator: Option<IntegratorKind>,
    /// MIS weighting: power (default) or balance heuristic.
    #[arg(long)]
    pub mis_heuristic: Option<MisHeuristic>,
    /// Sample generator: sobol (Owen-scrambled, the default) or independent (PCG).
    #[arg(long)]
    pub sampler: Option<SamplerKind>,
    /// Seed of every random decision (default 0).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Maximum number of bounces (0 = emission only, 1 = direct lighting; default 64).
    #[arg(long)]
    pub max_depth: Option<u64>,
    /// Bounce from which Russian roulette may end paths (default 5); it plays only on paths whose
    /// throughput has fallen below 1/4.
    #[arg(long)]
    pub rr_depth: Option<u64>,
    /// Pixel filter, importance-sampled: box (default) or tent.
    #[arg(long)]
    pub filter: Option<PixelFilter>,
    /// Samples per pass, the unit of accumulation (part of the image's identity: see ARCHITECTURE.md;
    /// default 16).
    #[arg(long)]
    pub pass_spp: Option<u64>,
    /// Environment map: lat-long OpenEXR or Radiance .hdr.
    #[arg(long)]
    pub env: Option<PathBuf>,
    /// Uniform environment radiance R,G,B (when there is no --env).
    #[arg(long, value_parser = parse_rgb)]
    pub env_color: Option<[f64; 3]>,
    /// Multiplier of the environment's radiance (default 1).
    #[arg(long)]
    pub env_strength: Option<f64>,
    /// Rotation of the environment about +Y, degrees (right-handed; default 0).
    #[arg(long, allow_negative_numbers = true)]
    pub env_rotate: Option<f64>,
    /// Light selection for NEE: auto (the best of the three as measured by a pilot run; default),
    /// uniform, power, or tree (light BVH: power, distance, orientation).
    #[arg(long)]
    pub light_sampler: Option<renderer::light::LightSamplerKind>,
    /// How KHR_lights_punctual intensities are read: auto (default: files from Blender's exporter as
    /// blender, others as gltf), gltf (candela and lux as they are), or blender (÷ 683: the watts
    /// Blender had, so the image matches Cycles).
    #[arg(long)]
    pub light_units: Option<renderer::punctual::LightUnits>,
    /// Importance-sample the environment for NEE: on (default) or off (only BSDF sampling finds it).
    #[arg(long, value_parser = ["on", "off"])]
    pub env_sampling: Option<String>,
    /// Frames of an animated scene: A-B or A-B:STEP (output names: see -o); frame N is at N/fps s.
    #[arg(long, value_name = "A-B[:STEP]", conflicts_with = "frame")]
    pub frames: Option<String>,
    /// One frame of an animated scene (default 0).
    #[arg(long, value_name = "N")]
    pub frame: Option<u64>,
    /// Frames per second of the animation (default 24, Blender's: its frame f is Tessera's frame f).
    #[arg(long)]
    pub fps: Option<f64>,
    /// The glTF animation that plays, by name or index (default: all of them together, as
    /// Blender's exporter writes one animation per object).
    #[arg(long, value_name = "NAME|INDEX")]
    pub animation: Option<String>,
}

fn parse_rgb(s: &str) -> Result<[f64; 3], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|x| x.trim().parse::<f64>().map_err(|_| format!("'{x}' is not a number")))
        .collect::<Result<_, _>>()?;
    match v[..] {
        [r, g, b] if v.iter().all(|x| x.is_finite() && *x >= 0.0) => Ok([r, g, b]),
        _ => Err(format!("expected R,G,B (three non-negative numbers), got '{s}'")),
    }
}

impl RenderFlags {
    /// The request these flags make (what `tessera submit` sends; `settings` resolves it locally).
    pub fn request(&self) -> SettingsRequest {
        SettingsRequest {
            spp: self.spp,
            width: self.width,
            height: self.height,
            camera: self.camera,
            integrator: self.integrator,
            mis_heuristic: self.mis_heuristic,
            sampler: self.sampler,
            seed: self.seed,
            max_depth: self.max_depth,
            rr_depth: self.rr_depth,
            filter: self.filter,
            env_color: self.env_color,
            env_strength: self.env_strength,
            env_rotate: self.env_rotate,
            env_sampling: self.env_sampling.as_deref().map(|v| v == "on"),
            light_sampler: self.light_sampler,
            light_units: self.light_units,
            pass_spp: self.pass_spp,
            time_budget: self.time_budget,
            noise_target: self.noise_target,
            min_spp: self.min_spp,
            frames: self.frames.clone().or(self.frame.map(|f| f.to_string())),
            fps: self.fps,
            animation: self.animation.clone(),
            ..SettingsRequest::default()
        }
    }

    /// Settings for `scene`: the request resolved against the scene's cameras (same code as the farm).
    pub fn settings(&self, scene: &Scene) -> Result<RenderSettings> {
        let camera = self.camera.map(|c| usize::try_from(c).unwrap_or(usize::MAX));
        let facts =
            SceneFacts { cameras: scene.cameras.len(), aspect: scene.camera(camera).ok().and_then(|c| c.aspect_ratio) };
        let env_map = self.env.as_ref().map(|p| p.to_string_lossy().into_owned());
        Ok(self.request().resolve(facts, env_map, SettingsLimits::default())?)
    }
}

#[derive(Args, Debug)]
pub struct RenderArgs {
    /// Scene file (.glb or .gltf). Without it, the built-in Cornell box is rendered.
    pub scene: Option<PathBuf>,
    /// Output OpenEXR file. For several frames, a pattern: its run of # is the zero-padded frame
    /// number (shot.####.exr); without #, .NNNN goes before the extension.
    #[arg(short, long, default_value = "render.exr")]
    pub output: PathBuf,
    #[command(flatten)]
    pub flags: RenderFlags,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Also write a tone-mapped sRGB PNG preview here.
    #[arg(long)]
    pub preview: Option<PathBuf>,
    /// Preview exposure in stops.
    #[arg(long, default_value_t = 0.0)]
    pub exposure: f32,
}

/// "64" for a uniform sample count, "32..512 (mean 97.3)" for an adaptive one.
pub fn spp_text(min: u32, max: u32, mean: f64) -> String {
    if min == max {
        format!("{max}")
    } else {
        format!("{min}..{max} (mean {mean:.1})")
    }
}

pub fn load_scene(path: Option<&Path>) -> Result<Scene> {
    match path {
        Some(p) => Ok(renderer::gltf_loader::load(p)?),
        None => Ok(renderer::gltf_loader::load_from_bytes(Path::new("<built-in cornell.gltf>"), EMBEDDED_CORNELL)?),
    }
}

pub fn init_threads(threads: Option<usize>) -> Result<()> {
    if let Some(t) = threads {
        if t == 0 {
            bail!("--threads must be at least 1");
        }
        rayon::ThreadPoolBuilder::new().num_threads(t).build_global().context("cannot start the thread pool")?;
    }
    Ok(())
}

pub fn run(args: RenderArgs) -> Result<()> {
    init_threads(args.threads)?;
    let t0 = Instant::now();
    let mut scene = load_scene(args.scene.as_deref())?;
    for w in &scene.warnings {
        eprintln!("warning: {w}");
    }
    let settings = args.flags.settings(&scene)?;
    let frames = args.flags.request().frame_range()?;
    scene.prepare(&settings, Path::new("."))?;
    let load_time = t0.elapsed();
    let pattern = args.output.to_string_lossy().into_owned();
    // One frame keeps the name as given (unless it is a pattern); a sequence numbers every frame.
    let numbered = frames.count() > 1 || pattern.contains('#');
    if frames.count() > 1 && !scene.is_animated() {
        eprintln!("warning: the scene has no animation: every frame is the same image");
    }
    for frame in frames.iter() {
        let settings = RenderSettings { frame, ..settings.clone() };
        scene.set_frame(&settings, frame)?;
        let output =
            if numbered { PathBuf::from(renderer::frames::frame_path(&pattern, frame)) } else { args.output.clone() };
        let preview = args.preview.as_ref().map(|p| {
            if numbered {
                PathBuf::from(renderer::frames::frame_path(&p.to_string_lossy(), frame))
            } else {
                p.clone()
            }
        });
        if numbered {
            eprintln!("frame {frame}:");
        }
        // A sequence's folder (shots/shot.####.exr) is made if it does not exist.
        if let Some(dir) = output.parent().filter(|d| !d.as_os_str().is_empty() && !d.exists()) {
            std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
        }
        render_frame(&scene, &settings, &output, preview.as_deref(), args.exposure, load_time.as_secs_f64())?;
    }
    Ok(())
}

/// Renders the scene as posed, writes the EXR (and preview), reports time and noise.
fn render_frame(
    scene: &Scene,
    settings: &RenderSettings,
    output: &Path,
    preview: Option<&Path>,
    exposure: f32,
    load_time: f64,
) -> Result<()> {
    let counters = Counters::default();
    let pixels = settings.width as u64 * settings.height as u64;
    // Progress in thousandths, for every budget: samples for a fixed count, the renderer's own
    // measure (tiles converging towards the target) for a noise target, time for a time budget.
    let bar = indicatif::ProgressBar::new(1000);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{spinner} [{elapsed_precise}] {bar:30} {percent:>3}% {msg}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let start = Instant::now();
    let done = std::sync::atomic::AtomicBool::new(false);
    // The render time is taken when the render returns, not when the progress thread (which waits
    // 100 ms between updates) has noticed; and the render wakes it, so the process does not wait
    // out the rest of its 100 ms either (it did: every render and every frame of `--frames` ended
    // 0–100 ms late, 50 ms on average).
    let (result, elapsed) = std::thread::scope(|s| {
        let progress = s.spawn(|| {
            while !done.load(Ordering::Relaxed) {
                let samples = counters.samples.load(Ordering::Relaxed);
                let secs = start.elapsed().as_secs_f64().max(1e-3);
                let rays = counters.rays.load(Ordering::Relaxed) as f64 / secs;
                let work = match settings.noise_target {
                    Some(_) => counters.progress(),
                    None => samples as f64 / (pixels.max(1) as f64 * settings.spp as f64),
                };
                let (fraction, eta) = renderer::budget::fraction_and_eta(settings, work, secs);
                bar.set_position((fraction * 1000.0) as u64);
                bar.set_message(format!(
                    "{:.1}/{} spp (mean/cap) | {:.2} Msamples/s | {:.2} Mrays/s | rel. error {}{} | ETA {}",
                    samples as f64 / pixels.max(1) as f64,
                    settings.spp,
                    samples as f64 / secs / 1e6,
                    rays / 1e6,
                    counters.rel_error().map_or("-".into(), |e| format!("{e:.2e}")),
                    settings.noise_target.map_or(String::new(), |t| format!(" (target {t})")),
                    eta.filter(|e| e.is_finite()).map_or("-".into(), |e| format!("{e:.0} s"))
                ));
                // Woken early (or spuriously) by the render's end: the loop checks `done`.
                std::thread::park_timeout(Duration::from_millis(100));
            }
        });
        let result = renderer::render(scene, settings, &counters);
        let elapsed = start.elapsed().as_secs_f64();
        done.store(true, Ordering::Relaxed);
        progress.thread().unpark();
        (result, elapsed)
    });
    bar.finish_and_clear();
    let image = &result.image;
    let final_image = FinalImage::from_sums(image);
    let attrs = renderer::image_io::standard_attributes(settings, image, result.stop, &scene.warnings);
    final_image.write_exr(output, &attrs)?;
    if let Some(p) = preview {
        final_image.write_png(p, exposure)?;
    }
    let samples = counters.samples.load(Ordering::Relaxed);
    let rays = counters.rays.load(Ordering::Relaxed) as f64;
    let nonfinite = counters.nonfinite.load(Ordering::Relaxed);
    let noise = renderer::noise::estimate(image);
    eprintln!(
        "rendered {}x{} at {} spp in {:.3}s (scene load {:.3}s): {:.3} Mpaths/s, {:.3} Mrays/s -> {}",
        settings.width,
        settings.height,
        spp_text(noise.spp_min, noise.spp_max, samples as f64 / pixels.max(1) as f64),
        elapsed,
        load_time,
        samples as f64 / elapsed / 1e6,
        rays / elapsed / 1e6,
        output.display()
    );
    let worst = renderer::noise::worst(result.tiles.iter().map(|(t, _)| t));
    eprintln!(
        "estimated noise: relative error {:.3e} (relMSE {:.3e}); worst tile {}; stopped by {}",
        noise.rel_error,
        noise.rel_mse,
        worst.map_or("-".into(), |(r, e)| format!("{:.3e} at ({}, {})", e.rel_error, r.x0, r.y0)),
        result.stop.as_str()
    );
    if nonfinite > 0 {
        tracing::warn!(nonfinite, "samples with non-finite radiance were replaced by zero");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Wrapper {
        #[command(flatten)]
        flags: RenderFlags,
    }

    /// Every field of the one settings schema has a flag, and flags carry no defaults of their own
    /// (so `tessera render`, `tessera submit` and the farm resolve the same defaults).
    #[test]
    fn flags_cover_the_settings_schema_and_default_nothing() {
        let all = Wrapper::try_parse_from([
            "t",
            "--spp",
            "8",
            "--width",
            "16",
            "--height",
            "8",
            "--camera",
            "0",
            "--integrator",
            "nee",
            "--mis-heuristic",
            "balance",
            "--sampler",
            "independent",
            "--seed",
            "3",
            "--max-depth",
            "4",
            "--rr-depth",
            "2",
            "--filter",
            "tent",
            "--env-color",
            "1,1,1",
            "--env-strength",
            "2",
            "--env-rotate",
            "-30",
            "--env-sampling",
            "off",
            "--light-units",
            "blender",
            "--light-sampler",
            "tree",
            "--pass-spp",
            "4",
            "--time-budget",
            "5",
            "--noise-target",
            "0.1",
            "--min-spp",
            "4",
            "--frames",
            "1-3",
            "--fps",
            "30",
            "--animation",
            "walk",
        ])
        .expect("parses");
        let v = serde_json::to_value(all.flags.request()).expect("encodes");
        let given: Vec<&str> = v.as_object().expect("object").keys().map(String::as_str).collect();
        assert!(given.contains(&"light_units"));
        for f in renderer::settings_request::FIELDS {
            assert!(f.name == "priority" || given.contains(&f.name), "no flag for settings.{}", f.name);
        }
        let none = Wrapper::try_parse_from(["t"]).expect("parses");
        assert_eq!(none.flags.request(), SettingsRequest::default());
    }
}
