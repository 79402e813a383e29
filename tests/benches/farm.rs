//! Farm benchmarks (not tests): `cargo bench -p tessera-cli --bench farm`.
//!
//! 1. Overhead: the same Cornell job rendered by `tessera render --threads 2` and by a coordinator
//!    with two 1-thread workers (submit → EXR downloaded), median of several runs each, alternating.
//! 2. Merge throughput: simulated workers (tokio tasks speaking gRPC) lease units and return valid
//!    precomputed partial sums at once; reports units merged per second by the coordinator.

use proto::v1::*;
use std::time::{Duration, Instant};
use tessera_tests::*;
use tessera_tests::{renderer, worker};

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() {
    let runs: usize = std::env::var("RUNS").ok().and_then(|v| v.parse().ok()).unwrap_or(5);
    let scene = repo_root().join("scenes/cornell/cornell.gltf");
    let args = ["--spp", "128", "--width", "256", "--height", "256"];

    let mut farm = Farm::start("bench", &[]);
    farm.start_worker(1);
    farm.start_worker(1);
    std::thread::sleep(Duration::from_millis(500));
    let (mut local, mut remote) = (Vec::new(), Vec::new());
    for r in 0..runs {
        let out = farm.tmp.join(format!("local{r}.exr"));
        let t = Instant::now();
        let ok = std::process::Command::new(tessera_bin())
            .arg("render")
            .arg(&scene)
            .arg("-o")
            .arg(&out)
            .args(args)
            .args(["--threads", "2"])
            .stderr(std::process::Stdio::null())
            .status()
            .unwrap()
            .success();
        assert!(ok);
        local.push(t.elapsed().as_secs_f64());
        let out = farm.tmp.join(format!("farm{r}.exr"));
        let t = Instant::now();
        let mut a = vec!["submit", scene.to_str().unwrap(), "--wait", "-o", out.to_str().unwrap()];
        a.extend_from_slice(&args);
        let (code, _, err) = farm.cli(&a);
        assert_eq!(code, 0, "{err}");
        remote.push(t.elapsed().as_secs_f64());
        println!("run {}: local {:.3}s, farm {:.3}s", r + 1, local[r], remote[r]);
    }
    let (l, f) = (median(local), median(remote));
    println!("overhead: Cornell 256x256 128 spp; tessera render --threads 2: median {l:.3}s; coordinator + 2 workers x 1 thread: median {f:.3}s; farm/local = {:.3}", f / l);
    drop(farm);

    // Merge throughput.
    let farm = Farm::start("bench-merge", &[]);
    let glb = std::fs::read(repo_root().join("scenes/cornell/cornell.glb")).unwrap();
    let (got, job) = post_job(&farm.url, None, &[("c.glb", &glb)], r#"{"spp": 64, "width": 2048, "height": 1024}"#);
    assert_eq!(got, 201, "{job}");
    let total = job["progress"]["units_total"].as_u64().unwrap() as usize;
    let sim = 32;
    let rt = tokio::runtime::Runtime::new().unwrap();
    let url = farm.url.clone();
    let t = Instant::now();
    let merged: usize = rt.block_on(async move {
        let mut tasks = Vec::new();
        for _ in 0..sim {
            let url = url.clone();
            tasks.push(tokio::spawn(async move {
                let (mut client, wid) = worker::connect(&url, None).await.expect("connect");
                let mut n = 0usize;
                loop {
                    let Some(unit) = client
                        .lease(LeaseRequest { worker_id: wid.clone(), wait_ms: 200 })
                        .await
                        .expect("lease")
                        .into_inner()
                        .unit
                    else {
                        break;
                    };
                    let r = unit.rect.unwrap();
                    let rect = renderer::film::Rect { x0: r.x0, y0: r.y0, width: r.width, height: r.height };
                    let mut sums = renderer::film::PartialSums::new(rect);
                    let k = unit.sample_end - unit.sample_start;
                    for i in 0..rect.pixels() {
                        sums.sum_rgb[i] = [k as f64 * 0.5; 3];
                        sums.sum_lum_sq[i] = k as f64 * 0.25;
                        sums.count[i] = k;
                    }
                    let payload = sums.encode();
                    let header = ResultHeader {
                        worker_id: wid.clone(),
                        unit_id: unit.unit_id,
                        rect: Some(r),
                        sample_start: unit.sample_start,
                        sample_end: unit.sample_end,
                        payload_size: payload.len() as u64,
                    };
                    if worker::submit(&mut client, header, payload).await.expect("submit").accepted {
                        n += 1;
                    }
                }
                n
            }));
        }
        let mut sum = 0;
        for t in tasks {
            sum += t.await.unwrap();
        }
        sum
    });
    let secs = t.elapsed().as_secs_f64();
    println!("merge throughput: {merged}/{total} units (32x32 px, 16 spp each) from {sim} simulated workers in {secs:.3}s = {:.0} units/s ({:.1} Mpixel-passes/s)", merged as f64 / secs, merged as f64 * 1024.0 / secs / 1e6);
    let j = farm.job(job["id"].as_str().unwrap());
    println!("job state after the load: {}", j["state"]);
}
