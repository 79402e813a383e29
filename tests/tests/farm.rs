//! The farm end to end: coordinator and worker processes on loopback, driven through the CLI.
//! Results must be bit-identical to `tessera render` whatever happens to the workers or the
//! coordinator.

use std::time::Duration;
use tessera_tests::*;

const SETTINGS: &[&str] = &["--width", "96", "--height", "96", "--spp"];

fn cornell() -> std::path::PathBuf {
    repo_root().join("scenes/cornell/cornell.gltf")
}

fn submit(farm: &Farm, spp: &str) -> String {
    let scene = cornell();
    let mut args = vec!["submit", scene.to_str().unwrap()];
    args.extend_from_slice(SETTINGS);
    args.push(spp);
    let (code, out, err) = farm.cli(&args);
    assert_eq!(code, 0, "submit failed: {err}");
    out.trim().to_string()
}

fn download_and_compare(farm: &Farm, id: &str, name: &str, spp: &str) {
    let out = farm.tmp.join(format!("{name}.exr"));
    let (code, _, err) = farm.cli(&["download", id, "-o", out.to_str().unwrap()]);
    assert_eq!(code, 0, "download failed: {err}");
    let mut args = SETTINGS.to_vec();
    args.push(spp);
    let local = local_render(&cornell(), &args, &farm.tmp.join(format!("{name}-local.exr")));
    let remote = std::fs::read(&out).unwrap();
    assert!(
        remote == local,
        "{name}: the farm's EXR differs from tessera render's ({} vs {} bytes)",
        remote.len(),
        local.len()
    );
}

#[test]
fn two_workers_give_the_local_image_bit_for_bit() {
    let mut farm = Farm::start("two-workers", &[]);
    farm.start_worker(1);
    farm.start_worker(1);
    farm.wait_workers(2);
    let scene = cornell();
    let out = farm.tmp.join("farm.exr");
    let mut args = vec!["submit", scene.to_str().unwrap(), "--wait", "-o", out.to_str().unwrap()];
    args.extend_from_slice(SETTINGS);
    args.push("64");
    let (code, stdout, err) = farm.cli(&args);
    assert_eq!(code, 0, "submit --wait failed: {err}");
    assert!(err.contains("spp (mean), estimated relative error"), "no summary line: {err}");
    let mut local_args = SETTINGS.to_vec();
    local_args.push("64");
    let local = local_render(&scene, &local_args, &farm.tmp.join("local.exr"));
    assert!(std::fs::read(&out).unwrap() == local, "farm EXR differs from the local render");
    // Both workers took part.
    let (_, workers, _) = farm.cli(&["workers"]);
    let busy = workers
        .lines()
        .skip(1)
        .filter(|l| l.split_whitespace().nth(3).and_then(|n| n.parse::<u32>().ok()).unwrap_or(0) > 0)
        .count();
    assert_eq!(busy, 2, "both workers should have rendered units:\n{workers}");
    let j = farm.job(stdout.trim());
    assert_eq!(j["state"], "done");
    assert!(j["noise"]["estimated_rel_error"].as_f64().unwrap() > 0.0);
    // `status --summary`: one line on stdout instead of the JSON.
    let (code, line, err) = farm.cli(&["status", "--summary", stdout.trim()]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(line.lines().count(), 1, "{line}");
    assert!(line.contains("done: 100%") && line.contains("spp 64 "), "{line}");
    // A preview at the size it is shown, and brighter at +2 stops (made from the stored EXR).
    let png = |q: &str| {
        let bytes = ureq::get(&format!("{}/api/v1/jobs/{}/preview.png{q}", farm.url, stdout.trim()))
            .call()
            .unwrap()
            .into_body()
            .read_to_vec()
            .unwrap();
        let img = image::load_from_memory(&bytes).unwrap().to_rgb8();
        let mean = img.pixels().map(|p| p.0.iter().map(|&c| c as f64).sum::<f64>()).sum::<f64>() / img.len() as f64;
        (img.width(), mean)
    };
    let (full_w, full_mean) = png("");
    let (small_w, small_mean) = png("?width=20");
    let (_, bright_mean) = png("?exposure=2");
    assert!(small_w <= 20 && small_w < full_w, "{small_w} vs {full_w}");
    assert!((small_mean - full_mean).abs() < 0.05 * full_mean + 2.0, "{small_mean} vs {full_mean}");
    assert!(bright_mean > 1.3 * full_mean, "{bright_mean} vs {full_mean}");
    let bad = ureq::get(&format!("{}/api/v1/jobs/{}/preview.png?exposure=99", farm.url, stdout.trim())).call();
    assert!(matches!(bad, Err(ureq::Error::StatusCode(422))), "{bad:?}");
    // Resubmit: a new job, same scene and settings, the same image.
    let r: serde_json::Value = ureq::post(&format!("{}/api/v1/jobs/{}/resubmit", farm.url, stdout.trim()))
        .send_empty()
        .unwrap()
        .into_body()
        .read_json()
        .unwrap();
    let again = r["id"].as_str().unwrap().to_string();
    assert_ne!(again, stdout.trim());
    farm.wait_job(&again, Duration::from_secs(60), |j| j["state"] == "done");
    let out2 = farm.tmp.join("again.exr");
    assert_eq!(farm.cli(&["download", &again, "-o", out2.to_str().unwrap()]).0, 0);
    assert!(std::fs::read(&out2).unwrap() == local, "the resubmitted job's EXR differs");
    // Live updates: the event stream opens with the job list and the workers.
    let resp = ureq::get(&format!("{}/api/v1/events", farm.url)).call().unwrap();
    assert!(resp.headers().get("content-type").unwrap().to_str().unwrap().starts_with("text/event-stream"));
    let mut reader = resp.into_body().into_reader();
    let mut got = Vec::new();
    let mut buf = [0u8; 4096];
    while !(String::from_utf8_lossy(&got).contains("event: workers")) {
        let n = std::io::Read::read(&mut reader, &mut buf).unwrap();
        assert!(n > 0, "the event stream ended");
        got.extend_from_slice(&buf[..n]);
    }
    let text = String::from_utf8_lossy(&got);
    assert!(text.contains("event: jobs") && text.contains(&again), "{text}");
}

#[test]
fn a_killed_worker_units_are_re_leased() {
    let mut farm = Farm::start("kill-worker", &[]);
    let doomed = farm.start_worker(1);
    farm.start_worker(1);
    farm.wait_workers(2);
    // The kill waits until both workers are at work, and freezes the doomed one until it is seen
    // holding a lease (`kill_worker_holding_a_lease`), so it dies holding one.
    let scene = cornell();
    let mut args = vec!["submit", scene.to_str().unwrap()];
    args.extend_from_slice(SETTINGS);
    args.extend_from_slice(&["256", "--pass-spp", "64"]);
    let (code, out, err) = farm.cli(&args);
    assert_eq!(code, 0, "submit failed: {err}");
    let id = out.trim().to_string();
    farm.wait_job(&id, Duration::from_secs(60), |j| {
        j["progress"]["units_done"].as_u64().unwrap_or(0) >= 2
            && j["progress"]["units_leased"].as_u64().unwrap_or(0) == 2
    });
    farm.kill_worker_holding_a_lease(doomed);
    // The dead worker is listed as offline (not "last seen N s" forever), the live one is not.
    poll(Duration::from_secs(30), || {
        let (d, l) = (farm.worker(doomed)?["state"].clone(), farm.worker(1 - doomed)?["state"].clone());
        if d == "offline" && l != "offline" {
            Ok(())
        } else {
            Err(format!("worker states: dead {d}, live {l}"))
        }
    });
    let j = farm.wait_job(&id, Duration::from_secs(180), |j| j["state"] == "done");
    assert_eq!(j["progress"]["units_done"], j["progress"]["units_total"]);
    let metrics = ureq::get(&format!("{}/metrics", farm.url)).call().unwrap().into_body().read_to_string().unwrap();
    let expired: u64 = metrics
        .lines()
        .find(|l| l.starts_with("tessera_leases_expired_total"))
        .and_then(|l| l.split_whitespace().nth(1)?.parse().ok())
        .unwrap_or(0);
    assert!(expired >= 1, "the dead worker's lease must have expired and been re-leased:\n{metrics}");
    // The job's log tells what happened: both workers joined, the dead one's lease expired, the
    // error fell as samples came in, and the job finished.
    let ev = farm.api(&format!("/jobs/{id}/events")).unwrap();
    let events = ev["events"].as_array().unwrap();
    let kinds: Vec<&str> = events.iter().map(|e| e["kind"].as_str().unwrap()).collect();
    assert_eq!(kinds.first(), Some(&"submitted"), "{kinds:?}");
    assert_eq!(kinds.last(), Some(&"done"), "{kinds:?}");
    assert_eq!(kinds.iter().filter(|k| **k == "worker_joined").count(), 2, "{kinds:?}");
    let lapsed = events.iter().find(|e| e["kind"] == "lease_expired").expect("a lease_expired event");
    assert!(lapsed["detail"].as_str().unwrap().contains(&format!("worker{doomed}-")), "{lapsed}");
    let curve: Vec<(f64, f64)> = events
        .iter()
        .filter(|e| e["kind"] == "progress")
        .map(|e| {
            let p: serde_json::Value = serde_json::from_str(e["detail"].as_str().unwrap()).unwrap();
            (p["spp_mean"].as_f64().unwrap(), p["rel_error"].as_f64().unwrap_or(f64::INFINITY))
        })
        .collect();
    assert!(curve.len() >= 2, "{curve:?}");
    let (first, last) = (curve[0], curve[curve.len() - 1]);
    assert!(last.0 == 256.0 && last.1 < first.1, "the curve must end at 256 spp with less error: {curve:?}");
    let out = farm.tmp.join("kill-worker.exr");
    assert_eq!(farm.cli(&["download", &id, "-o", out.to_str().unwrap()]).0, 0);
    let mut local_args = SETTINGS.to_vec();
    local_args.extend_from_slice(&["256", "--pass-spp", "64"]);
    let local = local_render(&cornell(), &local_args, &farm.tmp.join("kill-worker-local.exr"));
    assert!(std::fs::read(&out).unwrap() == local, "farm EXR differs after a worker was killed");
}

#[test]
fn a_restarted_coordinator_finishes_from_its_checkpoint() {
    let mut farm = Farm::start("restart", &[]);
    farm.start_worker(1);
    farm.start_worker(1);
    let id = submit(&farm, "64");
    let before =
        farm.wait_job(&id, Duration::from_secs(60), |j| j["progress"]["units_done"].as_u64().unwrap_or(0) >= 6);
    if let Some(c) = farm.coordinator.as_mut() {
        c.kill9();
    }
    farm.start_coordinator();
    let after = farm.job(&id);
    assert!(
        after["state"] == "done"
            || after["progress"]["units_done"].as_u64().unwrap() >= before["progress"]["units_done"].as_u64().unwrap(),
        "checkpointed progress was lost: {before} -> {after}"
    );
    farm.wait_job(&id, Duration::from_secs(120), |j| j["state"] == "done");
    download_and_compare(&farm, &id, "restart", "64");
}

#[test]
fn tls_carries_rest_and_grpc_on_one_port() {
    let dir = temp_dir("tls-certs");
    let ck = rcgen::generate_simple_self_signed(vec!["localhost".to_string(), "127.0.0.1".to_string()])
        .expect("self-signed certificate");
    let (cert, key) = (dir.join("cert.pem"), dir.join("key.pem"));
    std::fs::write(&cert, ck.cert.pem()).unwrap();
    std::fs::write(&key, ck.signing_key.serialize_pem()).unwrap();
    let (c, k) = (cert.to_str().unwrap(), key.to_str().unwrap());
    let mut farm = Farm::start(
        "tls",
        &[("TESSERA_TLS_CERT", c), ("TESSERA_TLS_KEY", k), ("TESSERA_CA_CERT", c), ("TESSERA_WORKER_SECRET", "s3cret")],
    );
    assert!(farm.url.starts_with("https://"));
    farm.start_worker(2);
    let id = submit(&farm, "32");
    farm.wait_job(&id, Duration::from_secs(120), |j| j["state"] == "done");
    download_and_compare(&farm, &id, "tls", "32");
    // The port does not speak plaintext HTTP.
    let plain = ureq::get(&format!("http://127.0.0.1:{}/healthz", farm.port)).call();
    assert!(plain.is_err(), "plaintext must not be served on a TLS port");
    // And a client that does not trust the certificate is refused.
    let out = std::process::Command::new(tessera_bin())
        .args(["list", "--coordinator", &farm.url])
        .env_remove("TESSERA_CA_CERT")
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(3), "{}", String::from_utf8_lossy(&out.stderr));
}

#[test]
fn an_environment_map_travels_with_the_job() {
    let mut farm = Farm::start("env", &[]);
    farm.start_worker(2);
    let scene = repo_root().join("scenes/envlit/envlit.gltf");
    let env = repo_root().join("scenes/env/sunset.exr");
    let args = ["--env", env.to_str().unwrap(), "--env-rotate", "40", "--spp", "16", "--width", "64", "--height", "48"];
    let out = farm.tmp.join("env.exr");
    let mut submit = vec!["submit", scene.to_str().unwrap(), "--wait", "-o", out.to_str().unwrap()];
    submit.extend_from_slice(&args);
    let (code, _, err) = farm.cli(&submit);
    assert_eq!(code, 0, "{err}");
    let local = local_render(&scene, &args, &farm.tmp.join("env-local.exr"));
    assert!(std::fs::read(&out).unwrap() == local, "the farm's env-lit EXR differs from tessera render's");
}

/// A worker keeps the scene it prepared between units, but only for jobs that prepare it the same
/// way: the same Blender export read with two light-unit settings, one after the other on one
/// worker, gives each job its own local image (the cache key once left the light units out).
#[test]
fn a_cached_scene_serves_only_jobs_that_prepare_it_alike() {
    let mut farm = Farm::start("prepare-key", &[]);
    farm.start_worker(2);
    let scene = repo_root().join("scenes/blender/lights.glb");
    for units in ["blender", "gltf"] {
        let args = ["--light-units", units, "--spp", "4", "--width", "48", "--height", "36"];
        let out = farm.tmp.join(format!("farm-{units}.exr"));
        let mut submit = vec!["submit", scene.to_str().unwrap(), "--wait", "-o", out.to_str().unwrap()];
        submit.extend_from_slice(&args);
        let (code, _, err) = farm.cli(&submit);
        assert_eq!(code, 0, "{err}");
        let local = local_render(&scene, &args, &farm.tmp.join(format!("local-{units}.exr")));
        assert!(
            std::fs::read(&out).unwrap() == local,
            "light units {units}: the farm's EXR differs from tessera render's"
        );
    }
}

/// Budgets on the farm. A noise target gives the local image bit for bit (each tile's stopping
/// decision depends on its own sums only), with fewer samples on quiet tiles. A time budget ends
/// at a whole pass of the image: the pixels equal the fixed-spp render of the sample count reached.
#[test]
fn budgets_give_the_local_image_and_stop_where_they_say() {
    let mut farm = Farm::start("budgets", &[]);
    farm.start_worker(1);
    farm.start_worker(1);
    farm.wait_workers(2);
    let scene = cornell();
    let adaptive = ["--width", "96", "--height", "96", "--spp", "512", "--pass-spp", "8"];
    let adaptive: Vec<&str> = adaptive.iter().copied().chain(["--noise-target", "0.05", "--min-spp", "16"]).collect();
    let out = farm.tmp.join("adaptive.exr");
    let mut args = vec!["submit", scene.to_str().unwrap(), "--wait", "-o", out.to_str().unwrap()];
    args.extend_from_slice(&adaptive);
    let (code, stdout, err) = farm.cli(&args);
    assert_eq!(code, 0, "submit --wait failed: {err}");
    let local = local_render(&scene, &adaptive, &farm.tmp.join("adaptive-local.exr"));
    assert!(std::fs::read(&out).unwrap() == local, "noise-target farm EXR differs from the local render");
    let j = farm.job(stdout.trim());
    assert_eq!(j["budget"]["stop"], "noise_target", "{j}");
    assert!(j["budget"]["tiles_converged"].as_u64().unwrap() > 0, "{j}");
    assert!(j["progress"]["spp_min"].as_u64().unwrap() < j["progress"]["spp_max"].as_u64().unwrap(), "{j}");
    assert!(j["noise"]["estimated_rel_error"].as_f64().unwrap() <= 0.05, "{j}");
    assert_eq!(j["noise"]["tiles"].as_array().unwrap().len(), 9);
    let exr = renderer::image_io::read_exr(&out).unwrap();
    let attr = exr.tessera.unwrap();
    let rel: f64 = renderer::image_io::attribute_field(&attr, "rel_error").unwrap().parse().unwrap();
    assert!((rel - j["noise"]["estimated_rel_error"].as_f64().unwrap()).abs() <= 1e-4 * rel, "{attr}");

    let timed = ["--width", "96", "--height", "96", "--pass-spp", "4", "--time-budget", "1.5"];
    let out = farm.tmp.join("timed.exr");
    let mut args = vec!["submit", scene.to_str().unwrap(), "--wait", "-o", out.to_str().unwrap()];
    args.extend_from_slice(&timed);
    let (code, stdout, err) = farm.cli(&args);
    assert_eq!(code, 0, "submit --wait failed: {err}");
    let j = farm.job(stdout.trim());
    assert_eq!(j["budget"]["stop"], "time_budget", "{j}");
    let exr = renderer::image_io::read_exr(&out).unwrap();
    let spp = exr.channel("spp").unwrap().to_vec();
    assert!(spp.iter().all(|&s| s == spp[0]) && spp[0] >= 4.0, "every pixel holds the same whole passes");
    let n = (spp[0] as u32).to_string();
    let fixed = ["--width", "96", "--height", "96", "--pass-spp", "4", "--spp", &n];
    let fixed_path = farm.tmp.join("timed-local.exr");
    local_render(&scene, &fixed, &fixed_path);
    let local = renderer::image_io::read_exr(&fixed_path).unwrap();
    for c in ["R", "G", "B", "variance", "spp"] {
        assert!(exr.channel(c) == local.channel(c), "channel {c} differs from the {n}-spp render");
    }
    println!("time budget 1.5 s on 2 workers: {n} spp, elapsed {}", j["elapsed_s"]);
}

/// A shot (issue 13): frames 0–3 of an animated scene (a moving emitter, a moving camera) on two
/// workers, one killed while both hold units: every frame's EXR — per frame and in the archive — is
/// byte-identical to `tessera render --frames 0-3`.
#[test]
fn a_shot_on_two_workers_one_killed_gives_the_local_frames_byte_for_byte() {
    let mut farm = Farm::start("shot", &[("TESSERA_MAX_FRAMES_IN_FLIGHT", "2")]);
    let doomed = farm.start_worker(1);
    farm.start_worker(1);
    farm.wait_workers(2);
    let scene = repo_root().join("scenes/animation/moving_light.gltf");
    // Enough work that units are still left for the doomed worker once it is thawed: at 128 spp
    // the eight-lane kernel (`spmd.rs`) finished the shot between two of
    // `kill_worker_holding_a_lease`'s tries (CI, "worker0 holds no unit").
    let common = ["--width", "64", "--height", "64", "--spp", "512", "--pass-spp", "32", "--max-depth", "3"];
    let mut args = vec!["submit", scene.to_str().unwrap(), "--frames", "0-3"];
    args.extend_from_slice(&common);
    let (code, out, err) = farm.cli(&args);
    assert_eq!(code, 0, "submit failed: {err}");
    let shot = out.trim().to_string();
    let j = farm.job(&shot);
    assert_eq!(j["kind"], "shot", "{j}");
    assert_eq!(j["frames"]["count"], 4);
    // Kill a worker while both hold units.
    let children: Vec<String> =
        j["frame_jobs"].as_array().unwrap().iter().map(|f| f["id"].as_str().unwrap().to_string()).collect();
    poll(Duration::from_secs(60), || {
        let leased: u64 = children.iter().map(|c| farm.job(c)["progress"]["units_leased"].as_u64().unwrap_or(0)).sum();
        if leased >= 2 {
            Ok(())
        } else {
            Err(format!("{leased} units leased"))
        }
    });
    farm.kill_worker_holding_a_lease(doomed);
    let j = farm.wait_job(&shot, Duration::from_secs(240), |j| j["state"] == "done");
    assert_eq!(j["frames"]["done"], 4, "{j}");
    // Per-frame download through the CLI, as a frame pattern.
    let pattern = farm.tmp.join("farm/shot.####.exr");
    let (code, _, err) = farm.cli(&["download", &shot, "-o", pattern.to_str().unwrap()]);
    assert_eq!(code, 0, "download failed: {err}");
    // The same frames locally.
    let local = farm.tmp.join("local/shot.####.exr");
    let mut args = vec!["render", scene.to_str().unwrap(), "--frames", "0-3", "-o", local.to_str().unwrap()];
    args.extend_from_slice(&common);
    let st = std::process::Command::new(tessera_bin()).args(&args).output().expect("local render");
    assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));
    let archive = ureq::get(&format!("{}/api/v1/jobs/{shot}/frames.tar", farm.url))
        .call()
        .expect("archive")
        .into_body()
        .read_to_vec()
        .expect("archive bytes");
    for f in 0..4u32 {
        let name = format!("shot.{f:04}.exr");
        let remote = std::fs::read(farm.tmp.join("farm").join(&name)).expect("farm frame");
        let mine = std::fs::read(farm.tmp.join("local").join(&name)).expect("local frame");
        assert!(remote == mine, "frame {f}: the farm's EXR differs from tessera render --frames");
        // In the archive: a ustar entry frame.NNNN.exr holding the same bytes.
        let entry = format!("frame.{f:04}.exr");
        let at = archive.windows(entry.len()).position(|w| w == entry.as_bytes()).expect("frame in the archive");
        assert!(archive[at + 512..at + 512 + mine.len()] == mine[..], "frame {f}: archive bytes differ");
    }
}

/// Issue 14: a drained worker gets no new units until it is resumed; ids start with the worker's name.
#[test]
fn a_drained_worker_takes_no_units_until_resumed() {
    let mut farm = Farm::start("drain", &[]);
    farm.start_worker(1);
    farm.wait_workers(1);
    let w = farm.api("/workers").unwrap();
    let id = w["workers"][0]["id"].as_str().unwrap().to_string();
    assert!(id.starts_with("worker0-"), "{id}");
    let (code, table, err) = farm.cli(&["workers", "--drain", &id]);
    assert_eq!(code, 0, "{err}");
    assert!(table.contains("draining"), "{table}");
    let job = submit(&farm, "16");
    std::thread::sleep(Duration::from_millis(2500));
    let j = farm.job(&job);
    assert_eq!(j["progress"]["units_done"], 0, "a drained worker rendered: {j}");
    let (code, _, err) = farm.cli(&["workers", "--drain", "nosuchworker"]);
    assert_ne!(code, 0, "draining an unknown worker must fail");
    assert!(err.contains("nosuchworker") || err.contains("404") || err.contains("no such"), "{err}");
    // A job cancelled while `submit --wait` waits for it: the waiter says so, with a reason.
    let scene = cornell();
    let out = farm.tmp.join("cancelled.exr");
    let (code, err) = std::thread::scope(|sc| {
        let waiter = sc.spawn(|| {
            let mut args = vec!["submit", scene.to_str().unwrap(), "--wait", "-o", out.to_str().unwrap()];
            args.extend_from_slice(SETTINGS);
            args.push("16");
            farm.cli(&args)
        });
        let other = poll(Duration::from_secs(20), || {
            let list = farm.api("/jobs")?;
            list["jobs"]
                .as_array()
                .into_iter()
                .flatten()
                .filter_map(|j| j["id"].as_str())
                .find(|j| *j != job)
                .map(str::to_string)
                .ok_or_else(|| "the waiter's job is not listed yet".to_string())
        });
        ureq::post(&format!("{}/api/v1/jobs/{other}/cancel", farm.url)).send_empty().unwrap();
        let (code, _, err) = waiter.join().unwrap();
        (code, err)
    });
    assert_eq!(code, 5, "{err}");
    assert!(err.contains("cancelled (tessera cancel, DELETE or the web page) at 0.0 spp"), "{err}");
    ureq::post(&format!("{}/api/v1/workers/{id}/resume", farm.url)).send_empty().unwrap();
    farm.wait_job(&job, Duration::from_secs(60), |j| j["state"] == "done");
}
