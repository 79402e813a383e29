//! `tessera bench convergence`: what each technique buys. For every scene of a suite and every
//! technique switch (integrator, sampler, light sampler, environment sampling) it renders at
//! spp 1, 2, 4, … while the next render fits in a time cap, and records wall time, the true relMSE
//! against a converged reference (Mitsuba 3 where one is committed, else a long Tessera render), the
//! estimated relMSE (the render's own noise estimate, so its accuracy is measured too) and the
//! efficiency 1 / (relMSE × time). The reference's own noise (its variance channel, same metric) is
//! subtracted from the measured relMSE; points within 4× of it are kept in the CSV but marked
//! unresolved and left out of plots and tables. Writes `convergence.csv`, one PNG per scene (error and efficiency
//! against time, log-log, one panel per switch) and `summary.md` (relMSE of every switch value at the
//! same time, interpolated log-log between measured points).

use crate::render_cmd::init_threads;
use anyhow::{anyhow, bail, Context, Result};
use clap::Args;
use renderer::environment::EnvironmentSettings;
use renderer::image_io::{read_exr, FinalImage};
use renderer::{Counters, RenderSettings, Scene};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The built-in suite: scene name (under `scenes/<name>/<name>.gltf`) and the environment map it is
/// lit by (as in `scenes/references/make_references.py`).
const SUITE: &[(&str, Option<&str>)] =
    &[("cornell", None), ("veach", None), ("envlit", Some("env/sunset.exr")), ("many_lights", None), ("glass", None)];

#[derive(Args, Debug)]
pub struct ConvergenceArgs {
    /// Further scene files (.gltf/.glb) to measure besides the suite.
    pub scenes: Vec<PathBuf>,
    /// Suite scenes to run, comma-separated (cornell, veach, envlit, many_lights, glass), or "none".
    #[arg(long, value_delimiter = ',', default_value = "cornell,veach,envlit,many_lights,glass")]
    pub suite: Vec<String>,
    /// The repository's scenes/ directory (the suite, its environment maps and references/).
    #[arg(long, default_value = "scenes")]
    pub scenes_dir: PathBuf,
    /// Longest single render of a ladder, seconds: spp doubles while the next render is predicted
    /// to take at most this long.
    #[arg(long, default_value_t = 4.0)]
    pub time_cap: f64,
    /// Technique switches to measure, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "integrator,sampler,light_sampler,env_sampling")]
    pub switches: Vec<String>,
    /// Renders per ladder point (different seeds); time and error are medians.
    #[arg(long, default_value_t = 1)]
    pub runs: usize,
    /// Output directory (CSV, PNG plots, summary.md, long references of scenes without one).
    #[arg(short, long, default_value = "convergence")]
    pub out: PathBuf,
    /// Samples per pixel of the Tessera reference rendered for a scene without a committed one.
    #[arg(long, default_value_t = 2048)]
    pub reference_spp: u32,
    /// Image size for scene files without a committed reference (the suite uses its references').
    #[arg(long, default_value_t = 128)]
    pub width: u32,
    #[arg(long, default_value_t = 96)]
    pub height: u32,
    #[arg(long)]
    pub threads: Option<usize>,
}

/// One technique configuration: the defaults with one switch set to one value.
#[derive(Clone, Debug)]
struct Technique {
    switch: &'static str,
    value: &'static str,
}

impl Technique {
    fn apply(&self, s: &mut RenderSettings) -> Result<()> {
        match self.switch {
            "integrator" => s.integrator = self.value.parse().map_err(anyhow::Error::msg)?,
            "sampler" => s.sampler = self.value.parse().map_err(anyhow::Error::msg)?,
            "light_sampler" => s.light_sampler = self.value.parse().map_err(anyhow::Error::msg)?,
            "env_sampling" => s.environment.sampling = self.value == "on",
            other => bail!("unknown switch '{other}' (expected integrator, sampler, light_sampler, env_sampling)"),
        }
        Ok(())
    }
}

/// Every switch and its values (the first is not necessarily the default).
const SWITCHES: &[(&str, &[&str])] = &[
    ("integrator", &["mis", "nee", "bsdf"]),
    ("sampler", &["sobol", "independent"]),
    ("light_sampler", &["uniform", "power", "tree"]),
    ("env_sampling", &["on", "off"]),
];

fn techniques(switches: &[String], has_env: bool) -> Result<Vec<Technique>> {
    let mut out = Vec::new();
    for sw in switches {
        let Some(&(switch, values)) = SWITCHES.iter().find(|(name, _)| name == sw) else {
            bail!("unknown switch '{sw}' (expected integrator, sampler, light_sampler, env_sampling)");
        };
        // Without an environment there is nothing for env_sampling to switch.
        if switch != "env_sampling" || has_env {
            out.extend(values.iter().map(|&value| Technique { switch, value }));
        }
    }
    Ok(out)
}

/// One measured point of a ladder.
#[derive(Clone, Copy, Debug)]
struct Point {
    spp: u32,
    seconds: f64,
    /// relMSE of the render itself: measured against the reference, less the reference's own
    /// expected relMSE (E[(x − r)²] = var x + var r + bias²).
    rel_mse: f64,
    /// As measured against the reference.
    raw_rel_mse: f64,
    est_rel_mse: f64,
    /// Whether `rel_mse` stands clear of the reference's own noise (≥ ¼ of it); below that the
    /// difference of two noisy numbers says little, and the point is left out of plots and tables.
    resolved: bool,
}

impl Point {
    fn efficiency(&self) -> f64 {
        1.0 / (self.rel_mse * self.seconds)
    }
}

/// The resolved points of a ladder.
fn resolved(points: &[Point]) -> Vec<Point> {
    points.iter().copied().filter(|p| p.resolved).collect()
}

/// A scene to measure and what it is compared with.
struct Subject {
    name: String,
    path: PathBuf,
    environment: EnvironmentSettings,
    /// Directory environment map paths are relative to.
    base: PathBuf,
    width: u32,
    height: u32,
    reference: Vec<[f32; 3]>,
    reference_kind: String,
    /// The reference's own expected relMSE, from its variance channel (same metric).
    reference_rel_mse: f64,
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => v[n / 2],
        n => 0.5 * (v[n / 2 - 1] + v[n / 2]),
    }
}

/// A reference's size, RGB pixels and own expected relMSE (from its `variance` channel).
fn reference_of(path: &Path) -> Result<(u32, u32, Vec<[f32; 3]>, f64)> {
    let e = read_exr(path)?;
    let ch = |c: &str| e.channel(c).ok_or_else(|| anyhow!("{}: no {c} channel", path.display()));
    let (r, g, b, v) = (ch("R")?, ch("G")?, ch("B")?, ch("variance")?);
    let rgb: Vec<[f32; 3]> = (0..r.len()).map(|i| [r[i], g[i], b[i]]).collect();
    let own = rgb
        .iter()
        .zip(v)
        .map(|(p, v)| {
            let y = renderer::math::luminance(renderer::math::Vec3::from(*p)) as f64;
            *v as f64 / (y * y + renderer::noise::REL_MSE_FLOOR)
        })
        .filter(|x| x.is_finite())
        .sum::<f64>()
        / rgb.len().max(1) as f64;
    Ok((e.width, e.height, rgb, own))
}

fn load(path: &Path) -> Result<Scene> {
    renderer::gltf_loader::load(path).with_context(|| format!("loading {}", path.display()))
}

fn subjects(a: &ConvergenceArgs) -> Result<Vec<Subject>> {
    let mut out = Vec::new();
    for name in a.suite.iter().filter(|n| n.as_str() != "none") {
        let Some((_, env)) = SUITE.iter().find(|(n, _)| n == name) else {
            bail!("'{name}' is not in the suite (cornell, veach, envlit, many_lights, glass)");
        };
        let reference = a.scenes_dir.join("references").join(format!("{name}.exr"));
        let (width, height, rgb, own) = reference_of(&reference).with_context(|| {
            format!("the suite needs {} (run from the repository root or pass --scenes-dir)", reference.display())
        })?;
        out.push(Subject {
            name: name.clone(),
            path: a.scenes_dir.join(name).join(format!("{name}.gltf")),
            environment: EnvironmentSettings { map: env.map(str::to_string), ..Default::default() },
            base: a.scenes_dir.clone(),
            width,
            height,
            reference: rgb,
            reference_kind: "Mitsuba 3 scalar_rgb".into(),
            reference_rel_mse: own,
        });
    }
    for path in &a.scenes {
        let name = path.file_stem().map_or("scene".into(), |s| s.to_string_lossy().to_string());
        let committed = a.scenes_dir.join("references").join(format!("{name}.exr"));
        let (width, height, reference, kind, own) = if committed.exists() {
            let (w, h, rgb, own) = reference_of(&committed)?;
            (w, h, rgb, "Mitsuba 3 scalar_rgb".to_string(), own)
        } else {
            let mut scene = load(path)?;
            let settings = RenderSettings {
                width: a.width,
                height: a.height,
                spp: a.reference_spp,
                seed: 999_983,
                ..Default::default()
            };
            settings.validate().map_err(anyhow::Error::msg)?;
            scene.prepare(&settings, Path::new("."))?;
            eprintln!("{name}: rendering a {}-spp Tessera reference (no committed one)", a.reference_spp);
            let r = renderer::render(&scene, &settings, &Counters::default());
            let img = FinalImage::from_sums(&r.image);
            let file = a.out.join(format!("{name}-reference.exr"));
            img.write_exr(&file, &renderer::image_io::standard_attributes(&settings, &r.image, r.stop, &[]))?;
            let own = renderer::noise::estimate(&r.image).rel_mse;
            (a.width, a.height, img.rgb, format!("Tessera mis {} spp", a.reference_spp), own)
        };
        out.push(Subject {
            name,
            path: path.clone(),
            environment: EnvironmentSettings::default(),
            base: PathBuf::from("."),
            width,
            height,
            reference,
            reference_kind: kind,
            reference_rel_mse: own,
        });
    }
    Ok(out)
}

/// Renders the ladder spp = 1, 2, 4, … of one configuration.
fn ladder(scene: &Scene, settings: &RenderSettings, subject: &Subject, a: &ConvergenceArgs) -> Result<Vec<Point>> {
    let mut points = Vec::new();
    let mut spp = 1u32;
    loop {
        let (mut times, mut errors, mut estimates) = (Vec::new(), Vec::new(), Vec::new());
        for run in 0..a.runs.max(1) {
            let s = RenderSettings { spp, pass_spp: 16, seed: run as u64, ..settings.clone() };
            let t = Instant::now();
            let r = renderer::render(scene, &s, &Counters::default());
            times.push(t.elapsed().as_secs_f64());
            let rgb = FinalImage::from_sums(&r.image).rgb;
            errors.push(
                renderer::noise::rel_mse_against(&rgb, &subject.reference)
                    .ok_or_else(|| anyhow!("{}: image and reference sizes differ", subject.name))?,
            );
            estimates.push(renderer::noise::estimate(&r.image).rel_mse);
        }
        let raw = median(errors);
        let floor = subject.reference_rel_mse;
        let rel_mse = raw - floor;
        let p = Point {
            spp,
            seconds: median(times),
            rel_mse,
            raw_rel_mse: raw,
            est_rel_mse: median(estimates),
            resolved: rel_mse > 0.0 && rel_mse >= 0.25 * floor,
        };
        points.push(p);
        if 2.0 * p.seconds > a.time_cap || spp >= 1 << 16 {
            return Ok(points);
        }
        spp *= 2;
    }
}

/// log-log interpolation of relMSE at time `t` (None outside the measured range).
fn error_at(points: &[Point], t: f64) -> Option<f64> {
    points.windows(2).find(|w| w[0].seconds <= t && t <= w[1].seconds).map(|w| {
        let (t0, t1) = (w[0].seconds.ln(), w[1].seconds.ln());
        let f = if t1 > t0 { (t.ln() - t0) / (t1 - t0) } else { 0.0 };
        (w[0].rel_mse.ln() * (1.0 - f) + w[1].rel_mse.ln() * f).exp()
    })
}

type Measurements = Vec<(Technique, Vec<Point>)>;

pub fn run(a: ConvergenceArgs) -> Result<()> {
    init_threads(a.threads)?;
    if a.time_cap.is_nan() || a.time_cap <= 0.0 {
        bail!("--time-cap must be positive");
    }
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let subjects = subjects(&a)?;
    let mut csv = String::from(
        "scene,switch,value,spp,seconds,rel_mse,est_rel_mse,efficiency,reference,raw_rel_mse,reference_rel_mse,resolved\n",
    );
    let mut summary = format!(
        "# Convergence: relMSE against time per technique switch\n\nMade by `tessera bench convergence` (time cap {} s, {} run(s) per point, {} threads). relMSE is against the reference named per scene; equal-time columns interpolate log-log between measured points. The estimate/true column is the render's own noise estimate divided by its true error at the largest spp.\n",
        a.time_cap,
        a.runs,
        rayon::current_num_threads()
    );
    for subject in &subjects {
        let mut scene = load(&subject.path)?;
        let techniques = techniques(&a.switches, subject.environment.map.is_some())?;
        // The defaults are every switch's baseline: render each distinct configuration once.
        let mut cache: BTreeMap<String, Vec<Point>> = BTreeMap::new();
        let mut measured: Measurements = Vec::new();
        for t in &techniques {
            let mut settings = RenderSettings {
                width: subject.width,
                height: subject.height,
                environment: subject.environment.clone(),
                ..Default::default()
            };
            t.apply(&mut settings)?;
            let key = serde_json::to_string(&settings)?;
            let points = match cache.get(&key) {
                Some(p) => p.clone(),
                None => {
                    scene.prepare(&settings, &subject.base)?;
                    let p = ladder(&scene, &settings, subject, &a)?;
                    let last = p.last().copied();
                    eprintln!(
                        "{} {}={}: up to {} spp in {:.2}s, relMSE {:.3e}",
                        subject.name,
                        t.switch,
                        t.value,
                        last.map_or(0, |p| p.spp),
                        last.map_or(0.0, |p| p.seconds),
                        last.map_or(f64::NAN, |p| p.rel_mse)
                    );
                    cache.insert(key, p.clone());
                    p
                }
            };
            for p in &points {
                let est = if p.est_rel_mse.is_finite() { format!("{:.6e}", p.est_rel_mse) } else { String::new() };
                writeln!(
                    csv,
                    "{},{},{},{},{:.6},{:.6e},{},{:.6e},{},{:.6e},{:.6e},{}",
                    subject.name,
                    t.switch,
                    t.value,
                    p.spp,
                    p.seconds,
                    p.rel_mse,
                    est,
                    p.efficiency(),
                    subject.reference_kind,
                    p.raw_rel_mse,
                    subject.reference_rel_mse,
                    p.resolved
                )?;
            }
            measured.push((t.clone(), points));
        }
        write_summary(&mut summary, subject, &measured)?;
        let png = a.out.join(format!("{}.png", subject.name));
        plot(&png, subject, &measured)?;
        eprintln!("{} -> {}", subject.name, png.display());
    }
    std::fs::write(a.out.join("convergence.csv"), &csv)?;
    std::fs::write(a.out.join("summary.md"), &summary)?;
    println!("{summary}");
    eprintln!("wrote {}/convergence.csv, summary.md and one PNG per scene", a.out.display());
    Ok(())
}

fn write_summary(out: &mut String, subject: &Subject, measured: &Measurements) -> Result<()> {
    writeln!(
        out,
        "\n## {} ({}×{}, reference: {}, its own relMSE {:.2e}, subtracted)\n\n| switch | value | equal time | relMSE at equal time | efficiency 1/(relMSE·s) | largest spp | relMSE there | estimate/true |\n|---|---|---|---|---|---|---|---|",
        subject.name, subject.width, subject.height, subject.reference_kind, subject.reference_rel_mse
    )?;
    let mut switches: Vec<&str> = measured.iter().map(|(t, _)| t.switch).collect();
    switches.dedup();
    for sw in switches {
        let group: Vec<(&Technique, Vec<Point>)> =
            measured.iter().filter(|(t, _)| t.switch == sw).map(|(t, p)| (t, resolved(p))).collect();
        // The longest time every value of the switch reached.
        let t_eq = group.iter().map(|(_, p)| p.last().map_or(0.0, |p| p.seconds)).fold(f64::INFINITY, f64::min);
        for (t, points) in &group {
            let Some(last) = points.last() else { continue };
            let at = error_at(points, t_eq);
            writeln!(
                out,
                "| {} | {} | {:.2} s | {} | {} | {} | {:.3e} | {} |",
                t.switch,
                t.value,
                t_eq,
                at.map_or("-".into(), |e| format!("{e:.3e}")),
                at.map_or("-".into(), |e| format!("{:.3e}", 1.0 / (e * t_eq))),
                last.spp,
                last.rel_mse,
                if last.est_rel_mse.is_finite() {
                    format!("{:.2}", last.est_rel_mse / last.rel_mse)
                } else {
                    "-".into()
                }
            )?;
        }
    }
    Ok(())
}

static FONT: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");

fn plot_err<E: std::fmt::Debug>(e: E) -> anyhow::Error {
    anyhow!("plotting failed: {e:?}")
}

/// One PNG per scene: relMSE (top) and efficiency (bottom) against time, log-log, a panel per switch.
fn plot(path: &Path, subject: &Subject, measured: &Measurements) -> Result<()> {
    use plotters::prelude::*;
    static REGISTER: std::sync::Once = std::sync::Once::new();
    REGISTER.call_once(|| {
        let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, FONT);
    });
    let mut switches: Vec<&str> = measured.iter().map(|(t, _)| t.switch).collect();
    switches.dedup();
    let cols = switches.len().max(1);
    let root = BitMapBackend::new(path, (420 * cols as u32, 760)).into_drawing_area();
    root.fill(&WHITE).map_err(plot_err)?;
    let root = root
        .titled(&format!("{} — relMSE and efficiency against render time", subject.name), ("sans-serif", 22))
        .map_err(plot_err)?;
    let areas = root.split_evenly((2, cols));
    for (c, sw) in switches.iter().enumerate() {
        let group: Vec<(&Technique, Vec<Point>)> =
            measured.iter().filter(|(t, _)| t.switch == *sw).map(|(t, p)| (t, resolved(p))).collect();
        for row in 0..2 {
            let value = |p: &Point| if row == 0 { p.rel_mse } else { p.efficiency() };
            let pts: Vec<(f64, f64)> = group
                .iter()
                .flat_map(|(_, ps)| ps.iter().map(|p| (p.seconds, value(p))))
                .filter(|(x, y)| *x > 0.0 && *y > 0.0 && y.is_finite())
                .collect();
            if pts.is_empty() {
                continue;
            }
            let (x0, x1) = pts.iter().fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.0), b.max(p.0)));
            let (y0, y1) = pts.iter().fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.1), b.max(p.1)));
            let mut chart = ChartBuilder::on(&areas[row * cols + c])
                .caption(
                    format!("{sw}: {}", if row == 0 { "relMSE" } else { "efficiency 1/(relMSE·s)" }),
                    ("sans-serif", 16),
                )
                .margin(10)
                .x_label_area_size(32)
                .y_label_area_size(60)
                .build_cartesian_2d((x0 * 0.8..x1 * 1.25).log_scale(), (y0 * 0.8..y1 * 1.25).log_scale())
                .map_err(plot_err)?;
            chart
                .configure_mesh()
                .x_desc("render time, s")
                .x_labels(6)
                .y_labels(6)
                .light_line_style(WHITE)
                .label_style(("sans-serif", 12))
                .y_label_formatter(&|v| format!("{v:.0e}"))
                .x_label_formatter(&|v| format!("{v:.2}"))
                .draw()
                .map_err(plot_err)?;
            for (k, (t, ps)) in group.iter().enumerate() {
                let color = Palette99::pick(k).to_rgba();
                let line: Vec<(f64, f64)> = ps
                    .iter()
                    .map(|p| (p.seconds, value(p)))
                    .filter(|(x, y)| *x > 0.0 && *y > 0.0 && y.is_finite())
                    .collect();
                chart
                    .draw_series(LineSeries::new(line.clone(), color.stroke_width(2)))
                    .map_err(plot_err)?
                    .label(t.value)
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], color.stroke_width(2)));
                chart.draw_series(line.iter().map(|p| Circle::new(*p, 3, color.filled()))).map_err(plot_err)?;
            }
            chart
                .configure_series_labels()
                .position(if row == 0 { SeriesLabelPosition::UpperRight } else { SeriesLabelPosition::LowerRight })
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .label_font(("sans-serif", 13))
                .draw()
                .map_err(plot_err)?;
        }
    }
    root.present().map_err(plot_err)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use renderer::light::LightSamplerKind;
    use renderer::sampler::SamplerKind;
    use renderer::IntegratorKind;

    #[test]
    fn interpolation_is_log_log_and_bounded() {
        let p = |seconds, rel_mse| Point {
            spp: 1,
            seconds,
            rel_mse,
            raw_rel_mse: rel_mse,
            est_rel_mse: f64::NAN,
            resolved: true,
        };
        let pts = [p(1.0, 1.0), p(4.0, 0.25)];
        // relMSE ∝ 1/t: at t = 2, 0.5.
        assert!((error_at(&pts, 2.0).unwrap() - 0.5).abs() < 1e-12);
        assert!(error_at(&pts, 8.0).is_none());
        assert_eq!(median(vec![3.0, 1.0, 2.0]), 2.0);
        let techniques = techniques(&["integrator".into(), "env_sampling".into()], false).unwrap();
        assert_eq!(techniques.len(), 3, "no environment: env_sampling has nothing to switch");
        assert!(super::techniques(&["colour".into()], false).is_err());
        let mut s = RenderSettings::default();
        Technique { switch: "sampler", value: "independent" }.apply(&mut s).unwrap();
        assert_eq!(s.sampler, SamplerKind::Independent);
        Technique { switch: "light_sampler", value: "tree" }.apply(&mut s).unwrap();
        assert_eq!(s.light_sampler, LightSamplerKind::Tree);
        Technique { switch: "integrator", value: "bsdf" }.apply(&mut s).unwrap();
        assert_eq!(s.integrator, IntegratorKind::Bsdf);
    }
}
