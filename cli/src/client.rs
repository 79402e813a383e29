//! The farm's command-line client: `submit`, `status`, `list`, `cancel`, `download`, `workers`.
//!
//! Exit codes (for scripts): 0 success; 1 local error (bad file, bad flag value); 2 usage error
//! (from the argument parser); 3 coordinator unreachable; 4 request refused by the coordinator
//! (the message says why: 400/401/404/409/413/422/429); 5 the job failed or was cancelled while
//! `--wait`ing.

use crate::render_cmd::RenderFlags;
use clap::Args;
use renderer::settings_request::SettingsRequest;
use serde_json::Value;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// An error with the exit code a script should see.
#[derive(Debug)]
pub struct CliError {
    pub code: u8,
    pub message: String,
}

impl std::fmt::Display for CliError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.message)
    }
}

impl std::error::Error for CliError {}

fn fail(code: u8, message: impl Into<String>) -> anyhow::Error {
    CliError { code, message: message.into() }.into()
}

#[derive(Args, Debug, Clone)]
pub struct Conn {
    /// Coordinator URL.
    #[arg(long, env = "TESSERA_COORDINATOR", default_value = "http://127.0.0.1:7878")]
    pub coordinator: String,
}

struct Api {
    base: String,
    token: Option<String>,
    agent: ureq::Agent,
}

impl Api {
    fn new(c: &Conn) -> anyhow::Result<Self> {
        let mut cfg =
            ureq::Agent::config_builder().http_status_as_error(false).timeout_global(Some(Duration::from_secs(600)));
        // An https coordinator with a private CA: trust the PEM certificate in TESSERA_CA_CERT.
        if let Some(path) = std::env::var("TESSERA_CA_CERT").ok().filter(|p| !p.is_empty()) {
            let pem = std::fs::read(&path).map_err(|e| fail(1, format!("TESSERA_CA_CERT {path}: {e}")))?;
            let cert =
                ureq::tls::Certificate::from_pem(&pem).map_err(|e| fail(1, format!("TESSERA_CA_CERT {path}: {e}")))?;
            cfg = cfg.tls_config(
                ureq::tls::TlsConfig::builder().root_certs(ureq::tls::RootCerts::new_with_certs(&[cert])).build(),
            );
        }
        let agent: ureq::Agent = cfg.build().into();
        Ok(Api {
            base: c.coordinator.trim_end_matches('/').to_string(),
            token: std::env::var("TESSERA_TOKEN").ok().filter(|t| !t.is_empty()),
            agent,
        })
    }

    fn auth<B>(&self, r: ureq::RequestBuilder<B>) -> ureq::RequestBuilder<B> {
        match &self.token {
            Some(t) => r.header("Authorization", &format!("Bearer {t}")),
            None => r,
        }
    }

    fn check(
        &self,
        r: Result<ureq::http::Response<ureq::Body>, ureq::Error>,
    ) -> anyhow::Result<ureq::http::Response<ureq::Body>> {
        let mut resp = r.map_err(|e| fail(3, format!("cannot reach the coordinator at {}: {e}", self.base)))?;
        let status = resp.status();
        if status.is_success() {
            return Ok(resp);
        }
        let body = resp.body_mut().read_to_string().unwrap_or_default();
        let msg = serde_json::from_str::<Value>(&body)
            .ok()
            .and_then(|v| v["error"].as_str().map(str::to_string))
            .unwrap_or(body);
        Err(fail(4, format!("coordinator refused ({}): {msg}", status.as_u16())))
    }

    fn get_json(&self, path: &str) -> anyhow::Result<Value> {
        let mut r = self.check(self.auth(self.agent.get(&format!("{}/api/v1{path}", self.base))).call())?;
        r.body_mut().read_json().map_err(|e| fail(3, format!("bad reply from the coordinator: {e}")))
    }

    fn get_bytes(&self, path: &str) -> anyhow::Result<Vec<u8>> {
        let mut r = self.check(self.auth(self.agent.get(&format!("{}/api/v1{path}", self.base))).call())?;
        let mut v = Vec::new();
        r.body_mut().as_reader().read_to_end(&mut v).map_err(|e| fail(3, format!("download failed: {e}")))?;
        Ok(v)
    }

    fn post_json(&self, path: &str) -> anyhow::Result<Value> {
        let mut r = self.check(self.auth(self.agent.post(&format!("{}/api/v1{path}", self.base))).send_empty())?;
        r.body_mut().read_json().map_err(|e| fail(3, format!("bad reply from the coordinator: {e}")))
    }
}

#[derive(Args, Debug)]
pub struct SubmitArgs {
    /// Scene file (.gltf with its sibling files, or .glb).
    pub scene: PathBuf,
    #[command(flatten)]
    pub flags: RenderFlags,
    /// Higher runs first (-1000..=1000; negative values may be written `--priority -1`).
    #[arg(long, default_value_t = 0, allow_negative_numbers = true)]
    pub priority: i32,
    /// Wait for the job, with a progress bar, then download the EXR.
    #[arg(long)]
    pub wait: bool,
    /// Where `--wait` writes the EXR.
    #[arg(short, long, default_value = "render.exr")]
    pub output: PathBuf,
    #[command(flatten)]
    pub conn: Conn,
}

/// The files a scene needs: the scene file, and for `.gltf` the relative buffer and image URIs.
fn scene_files(scene: &Path) -> anyhow::Result<Vec<(String, Vec<u8>)>> {
    let data = std::fs::read(scene).map_err(|e| fail(1, format!("{}: {e}", scene.display())))?;
    let name = scene
        .file_name()
        .map(|n| n.to_string_lossy().to_string())
        .ok_or_else(|| fail(1, format!("{}: not a file", scene.display())))?;
    let mut files = vec![(name.clone(), data.clone())];
    if name.to_ascii_lowercase().ends_with(".gltf") {
        let doc: Value =
            serde_json::from_slice(&data).map_err(|e| fail(1, format!("{}: not valid JSON: {e}", scene.display())))?;
        let dir = scene.parent().unwrap_or(Path::new("."));
        let uris = ["buffers", "images"]
            .iter()
            .flat_map(|k| doc[*k].as_array().cloned().unwrap_or_default())
            .filter_map(|v| v["uri"].as_str().map(str::to_string));
        for uri in uris {
            if uri.starts_with("data:") || files.iter().any(|(n, _)| *n == uri) {
                continue;
            }
            let rel = uri.replace("%20", " ");
            if !renderer::bundle::valid_name(&rel) {
                return Err(fail(1, format!("{}: URI '{uri}' leaves the scene's folder", scene.display())));
            }
            let bytes =
                std::fs::read(dir.join(&rel)).map_err(|e| fail(1, format!("{}: {e}", dir.join(&rel).display())))?;
            files.push((rel, bytes));
        }
    }
    Ok(files)
}

fn multipart(files: &[(String, Vec<u8>)], env: Option<&(String, Vec<u8>)>, settings: &Value) -> (String, Vec<u8>) {
    let boundary = format!(
        "tessera-{:016x}",
        std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos() as u64).unwrap_or(7)
    );
    let mut body = Vec::new();
    for (name, data) in files {
        body.extend_from_slice(format!("--{boundary}\r\nContent-Disposition: form-data; name=\"scene\"; filename=\"{}\"\r\nContent-Type: application/octet-stream\r\n\r\n", name.replace('"', "")).as_bytes());
        body.extend_from_slice(data);
        body.extend_from_slice(b"\r\n");
    }
    if let Some((name, data)) = env {
        let head = format!(
            "--{boundary}\r\nContent-Disposition: form-data; name=\"env\"; filename=\"{}\"\r\n\r\n",
            name.replace('"', "")
        );
        body.extend_from_slice(head.as_bytes());
        body.extend_from_slice(data);
        body.extend_from_slice(b"\r\n");
    }
    body.extend_from_slice(format!("--{boundary}\r\nContent-Disposition: form-data; name=\"settings\"\r\nContent-Type: application/json\r\n\r\n{settings}\r\n--{boundary}--\r\n").as_bytes());
    (format!("multipart/form-data; boundary={boundary}"), body)
}

pub fn submit(a: SubmitArgs) -> anyhow::Result<()> {
    let files = scene_files(&a.scene)?;
    let f = &a.flags;
    let request = SettingsRequest { priority: Some(a.priority as i64), ..f.request() };
    let settings = serde_json::to_value(&request).map_err(|e| fail(1, format!("settings: {e}")))?;
    let env = match &f.env {
        Some(p) => {
            let data = std::fs::read(p).map_err(|e| fail(1, format!("{}: {e}", p.display())))?;
            let name = p.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_else(|| "env.exr".into());
            Some((name, data))
        }
        None => None,
    };
    let api = Api::new(&a.conn)?;
    // Ask a cheap authenticated question first: a wrong token is then a clear 401 (exit 4), not a
    // broken pipe halfway through a large upload that the coordinator refused unread.
    api.get_json("/workers")?;
    let (ctype, body) = multipart(&files, env.as_ref(), &settings);
    let mut r = api.check(
        api.auth(api.agent.post(&format!("{}/api/v1/jobs", api.base))).header("Content-Type", &ctype).send(&body[..]),
    )?;
    let job: Value = r.body_mut().read_json().map_err(|e| fail(3, format!("bad reply: {e}")))?;
    let id = job["id"].as_str().unwrap_or_default().to_string();
    for w in job["warnings"].as_array().into_iter().flatten() {
        eprintln!("warning: {}", w.as_str().unwrap_or_default());
    }
    if !a.wait {
        println!("{id}");
        return Ok(());
    }
    eprintln!("submitted {id}");
    let bar = indicatif::ProgressBar::new(1000);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{spinner} [{elapsed_precise}] {bar:30} {percent:>3}% {msg}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    // Samples per second over the whole wait so far (the farm's rate, all workers together).
    let waited = std::time::Instant::now();
    let mut first_samples: Option<f64> = None;
    loop {
        let j = api.get_json(&format!("/jobs/{id}"))?;
        let frac = j["progress"]["fraction"].as_f64().unwrap_or(0.0);
        let samples = j["progress"]["samples_done"].as_f64().unwrap_or(0.0);
        let base = *first_samples.get_or_insert(samples);
        let rate = (samples - base) / waited.elapsed().as_secs_f64().max(1e-3);
        bar.set_position((frac * 1000.0) as u64);
        if j["kind"] == "shot" {
            bar.set_message(format!(
                "{} frames {}/{} | worst frame rel. error {}",
                j["state"].as_str().unwrap_or("?"),
                j["frames"]["done"],
                j["frames"]["count"],
                j["noise"]["worst_frame_rel_error"].as_f64().map_or("-".into(), |e| format!("{e:.2e}"))
            ));
        } else {
            bar.set_message(format!(
                "{} | {:.1} spp (mean) | {:.2} Msamples/s | rel. error {}{} | ETA {}",
                j["state"].as_str().unwrap_or("?"),
                j["progress"]["spp_mean"].as_f64().unwrap_or(0.0),
                rate / 1e6,
                j["noise"]["estimated_rel_error"].as_f64().map_or("-".into(), |e| format!("{e:.2e}")),
                j["budget"]["noise_target"].as_f64().map_or(String::new(), |t| format!(" (target {t})")),
                j["eta_s"].as_f64().map_or("-".into(), |e| format!("{e:.0} s"))
            ));
        }
        match j["state"].as_str() {
            Some("done") => break,
            Some("failed") | Some("cancelled") => {
                bar.abandon();
                let reason = match (j["state"].as_str(), j["error"].as_str()) {
                    (_, Some(e)) if !e.is_empty() => e.to_string(),
                    (Some("cancelled"), _) => format!(
                        "cancelled (tessera cancel, DELETE or the web page) at {:.1} spp (mean); the image so far is at /api/v1/jobs/{id}/preview.png",
                        j["progress"]["spp_mean"].as_f64().unwrap_or(0.0)
                    ),
                    _ => "no reason given".into(),
                };
                return Err(fail(5, format!("job {id} {}: {reason}", j["state"].as_str().unwrap_or("?"))));
            }
            _ => std::thread::sleep(Duration::from_millis(300)),
        }
    }
    bar.finish_and_clear();
    let written = fetch_images(&api, &id, &a.output)?;
    // The summary: time, samples and noise, as `tessera render` reports them.
    let j = api.get_json(&format!("/jobs/{id}"))?;
    let num = |v: &Value| v.as_f64().map_or("-".to_string(), |e| format!("{e:.3e}"));
    if j["kind"] == "shot" {
        eprintln!(
            "shot {id} done in {:.1} s: {} frames, worst frame estimated relative error {}",
            j["elapsed_s"].as_f64().unwrap_or(0.0),
            j["frames"]["count"],
            num(&j["noise"]["worst_frame_rel_error"])
        );
    } else {
        eprintln!(
            "job {id} done in {:.1} s: {:.1} spp (mean), estimated relative error {}, stopped by {}",
            j["elapsed_s"].as_f64().unwrap_or(0.0),
            j["progress"]["spp_mean"].as_f64().unwrap_or(0.0),
            num(&j["noise"]["estimated_rel_error"]),
            j["budget"]["stop"].as_str().unwrap_or("?")
        );
    }
    eprintln!("job {id} done -> {}", written.join(", "));
    println!("{id}");
    Ok(())
}

/// Downloads a job's image to `output`, or every finished frame of a shot to `output` as a frame
/// pattern (`shot.####.exr`; without #, .NNNN before the extension). Returns the files written.
fn fetch_images(api: &Api, id: &str, output: &std::path::Path) -> anyhow::Result<Vec<String>> {
    let j = api.get_json(&format!("/jobs/{id}"))?;
    let write = |path: &std::path::Path, bytes: Vec<u8>| -> anyhow::Result<()> {
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty() && !d.exists()) {
            std::fs::create_dir_all(dir).map_err(|e| fail(1, format!("{}: {e}", dir.display())))?;
        }
        std::fs::write(path, bytes).map_err(|e| fail(1, format!("{}: {e}", path.display())))
    };
    if j["kind"] != "shot" {
        let exr = api.get_bytes(&format!("/jobs/{id}/image.exr"))?;
        write(output, exr)?;
        return Ok(vec![output.display().to_string()]);
    }
    let pattern = output.to_string_lossy().into_owned();
    let mut written = Vec::new();
    for f in j["frame_jobs"].as_array().cloned().unwrap_or_default() {
        let Some(n) = f["frame"].as_u64() else { continue };
        if f["state"] != "done" {
            eprintln!("frame {n}: {} (not downloaded)", f["state"].as_str().unwrap_or("?"));
            continue;
        }
        let exr = api.get_bytes(&format!("/jobs/{id}/frames/{n}.exr"))?;
        let path = std::path::PathBuf::from(renderer::frames::frame_path(&pattern, n as u32));
        write(&path, exr)?;
        written.push(path.display().to_string());
    }
    Ok(written)
}

#[derive(Args, Debug)]
pub struct JobArgs {
    pub job: String,
    #[command(flatten)]
    pub conn: Conn,
}

#[derive(Args, Debug)]
pub struct StatusArgs {
    pub job: String,
    /// One summary line on stdout instead of the job's JSON (whose per-tile noise can run to
    /// thousands of lines).
    #[arg(long)]
    pub summary: bool,
    #[command(flatten)]
    pub conn: Conn,
}

pub fn status(a: StatusArgs) -> anyhow::Result<()> {
    let j = Api::new(&a.conn)?.get_json(&format!("/jobs/{}", a.job))?;
    if !a.summary {
        println!("{}", serde_json::to_string_pretty(&j).unwrap_or_default());
    }
    let line = |s: String| {
        if a.summary {
            println!("{s}");
        } else {
            // The headline on stderr, so that scripts reading the JSON on stdout are unaffected.
            eprintln!("{s}");
        }
    };
    if j["kind"] == "shot" {
        line(format!(
            "{} {}: {:.0}% | frames {}/{} done, {} running | worst frame estimated relative error {}",
            a.job,
            j["state"].as_str().unwrap_or("?"),
            100.0 * j["progress"]["fraction"].as_f64().unwrap_or(0.0),
            j["frames"]["done"],
            j["frames"]["count"],
            j["frames"]["running"],
            j["noise"]["worst_frame_rel_error"].as_f64().map_or("-".to_string(), |e| format!("{e:.3e}"))
        ));
        return Ok(());
    }
    let num = |v: &Value| v.as_f64().map_or("-".to_string(), |e| format!("{e:.3e}"));
    // A job cancelled before any sample has no spp range: say "-", not "null..null".
    let spp = match (j["progress"]["spp_min"].as_u64(), j["progress"]["spp_max"].as_u64()) {
        (Some(lo), Some(hi)) if lo == hi => format!("{hi}"),
        (Some(lo), Some(hi)) => format!("{lo}..{hi}"),
        _ => "-".to_string(),
    };
    line(format!(
        "{} {}: {:.0}% | spp {spp} | estimated relative error {} (worst tile {}) | stop: {}",
        a.job,
        j["state"].as_str().unwrap_or("?"),
        100.0 * j["progress"]["fraction"].as_f64().unwrap_or(0.0),
        num(&j["noise"]["estimated_rel_error"]),
        num(&j["noise"]["worst_tile"]["rel_error"]),
        j["budget"]["stop"].as_str().unwrap_or("?")
    ));
    Ok(())
}

pub fn cancel(a: JobArgs) -> anyhow::Result<()> {
    let j = Api::new(&a.conn)?.post_json(&format!("/jobs/{}/cancel", a.job))?;
    println!("{} {}", a.job, j["state"].as_str().unwrap_or("?"));
    Ok(())
}

#[derive(Args, Debug)]
pub struct DownloadArgs {
    pub job: String,
    /// Output EXR; for a shot, a frame pattern (shot.####.exr) every finished frame is written to.
    #[arg(short, long)]
    pub output: PathBuf,
    #[command(flatten)]
    pub conn: Conn,
}

pub fn download(a: DownloadArgs) -> anyhow::Result<()> {
    let api = Api::new(&a.conn)?;
    for f in fetch_images(&api, &a.job, &a.output)? {
        eprintln!("{f}");
    }
    Ok(())
}

#[derive(Args, Debug)]
pub struct ListArgs {
    #[command(flatten)]
    pub conn: Conn,
}

pub fn list(a: ListArgs) -> anyhow::Result<()> {
    let v = Api::new(&a.conn)?.get_json("/jobs")?;
    println!("{:<16} {:<10} {:>7} {:>9} {:>10}  name", "id", "state", "done", "elapsed", "rel.err");
    for j in v["jobs"].as_array().cloned().unwrap_or_default() {
        println!(
            "{:<16} {:<10} {:>6.1}% {:>8.1}s {:>10}  {}",
            j["id"].as_str().unwrap_or(""),
            j["state"].as_str().unwrap_or(""),
            100.0 * j["progress"]["fraction"].as_f64().unwrap_or(0.0),
            j["elapsed_s"].as_f64().unwrap_or(0.0),
            j["noise"]["estimated_rel_error"].as_f64().map_or("-".into(), |e| format!("{e:.2e}")),
            j["name"].as_str().unwrap_or("")
        );
    }
    Ok(())
}

#[derive(Args, Debug)]
pub struct WorkersArgs {
    #[command(flatten)]
    pub conn: Conn,
    /// Stop giving this worker new units (the units it holds finish), then list the workers.
    #[arg(long, value_name = "WORKER_ID", conflicts_with = "resume")]
    pub drain: Option<String>,
    /// Give a drained worker units again, then list the workers.
    #[arg(long, value_name = "WORKER_ID")]
    pub resume: Option<String>,
}

pub fn workers(a: WorkersArgs) -> anyhow::Result<()> {
    let api = Api::new(&a.conn)?;
    if let Some(id) = &a.drain {
        api.post_json(&format!("/workers/{id}/drain"))?;
        eprintln!("worker {id} draining: it takes no new units");
    }
    if let Some(id) = &a.resume {
        api.post_json(&format!("/workers/{id}/resume"))?;
        eprintln!("worker {id} resumed");
    }
    let v = api.get_json("/workers")?;
    let rows: Vec<[String; 8]> = v["workers"]
        .as_array()
        .cloned()
        .unwrap_or_default()
        .iter()
        .map(|w| {
            [
                w["id"].as_str().unwrap_or("").to_string(),
                w["name"].as_str().unwrap_or("").to_string(),
                w["cores"].to_string(),
                w["units_done"].to_string(),
                w["units_rejected"].to_string(),
                format!("{:.0}s", w["seconds_since_seen"].as_f64().unwrap_or(0.0)),
                w["state"].as_str().unwrap_or("?").to_string(),
                w["current_job"].as_str().unwrap_or("-").to_string(),
            ]
        })
        .collect();
    let head = ["id", "name", "cores", "done", "rejected", "last seen", "state", "job"];
    // Columns as wide as their widest cell, so long ids and names keep the table aligned.
    let width: Vec<usize> =
        (0..8).map(|c| rows.iter().map(|r| r[c].chars().count()).chain([head[c].len()]).max().unwrap_or(0)).collect();
    let print = |r: [&str; 8]| {
        println!(
            "{:<w0$}  {:<w1$}  {:>w2$}  {:>w3$}  {:>w4$}  {:>w5$}  {:<w6$}  {}",
            r[0],
            r[1],
            r[2],
            r[3],
            r[4],
            r[5],
            r[6],
            r[7],
            w0 = width[0],
            w1 = width[1],
            w2 = width[2],
            w3 = width[3],
            w4 = width[4],
            w5 = width[5],
            w6 = width[6]
        )
    };
    print(head);
    for r in &rows {
        print([&r[0], &r[1], &r[2], &r[3], &r[4], &r[5], &r[6], &r[7]]);
    }
    Ok(())
}
