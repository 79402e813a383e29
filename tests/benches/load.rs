//! Coordinator under load (not a test): `cargo bench -p tessera-cli --bench load`.
//!
//! 32 simulated workers (tokio tasks speaking gRPC) lease units and return valid synthetic partial
//! sums at once, while 50 REST clients poll the job list and single jobs, for `SECONDS` (default
//! 20). Two 2048² jobs (8192 units of 32×32 × 16 spp). Reports the lease latency (p50, p99, max),
//! units merged, REST latency and the coordinator's peak resident memory (VmHWM).
//! `TESSERA_BIN=/path/to/other/tessera` measures another build with the same harness (issue 11's
//! before/after).

use proto::v1::*;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tessera_tests::worker;
use tessera_tests::*;

fn pct(v: &mut [f64], p: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * p).round() as usize]
}

fn vm_hwm_mb(pid: u32) -> f64 {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    s.lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse::<f64>().ok())
        .unwrap_or(0.0)
        / 1024.0
}

fn main() {
    let seconds: u64 = std::env::var("SECONDS").ok().and_then(|v| v.parse().ok()).unwrap_or(20);
    let farm = Farm::start("load", &[("TESSERA_MAX_SIDE", "8192"), ("TESSERA_LOG", "warn")]);
    let glb = std::fs::read(repo_root().join("scenes/cornell/cornell.glb")).expect("cornell");
    let mut jobs = Vec::new();
    for _ in 0..2 {
        let (st, body) = post_job(
            &farm.url,
            None,
            &[("c.glb", &glb)],
            r#"{"spp": 32, "pass_spp": 16, "width": 2048, "height": 2048}"#,
        );
        assert_eq!(st, 201, "{body}");
        jobs.push(body["id"].as_str().unwrap().to_string());
    }
    let pid = farm.coordinator.as_ref().unwrap().pid();
    let stop = Arc::new(AtomicBool::new(false));
    let lease_ms = Arc::new(Mutex::new(Vec::<f64>::new()));
    let rest_ms = Arc::new(Mutex::new(Vec::<f64>::new()));
    let merged = Arc::new(std::sync::atomic::AtomicU64::new(0));

    // 50 REST clients.
    let clients: Vec<_> = (0..50)
        .map(|k| {
            let (url, stop, rest_ms, job) = (farm.url.clone(), stop.clone(), rest_ms.clone(), jobs[k % 2].clone());
            std::thread::spawn(move || {
                let agent: ureq::Agent = ureq::Agent::config_builder()
                    .http_status_as_error(false)
                    .timeout_global(Some(Duration::from_secs(60)))
                    .build()
                    .into();
                let mut n = 0;
                while !stop.load(Ordering::Relaxed) {
                    let path = if n % 2 == 0 { "/api/v1/jobs".to_string() } else { format!("/api/v1/jobs/{job}") };
                    let t = Instant::now();
                    if let Ok(mut r) = agent.get(&format!("{url}{path}")).call() {
                        let _ = r.body_mut().read_to_vec();
                    }
                    rest_ms.lock().unwrap().push(t.elapsed().as_secs_f64() * 1e3);
                    n += 1;
                    std::thread::sleep(Duration::from_millis(100));
                }
            })
        })
        .collect();

    // 32 simulated workers.
    let rt = tokio::runtime::Runtime::new().unwrap();
    let t0 = Instant::now();
    rt.block_on(async {
        let mut tasks = Vec::new();
        for _ in 0..32 {
            let (url, stop, lease_ms, merged) = (farm.url.clone(), stop.clone(), lease_ms.clone(), merged.clone());
            tasks.push(tokio::spawn(async move {
                let Ok((mut client, id)) = worker::connect(&url, None).await else { return };
                while !stop.load(Ordering::Relaxed) {
                    let t = Instant::now();
                    let Ok(reply) = client.lease(LeaseRequest { worker_id: id.clone(), wait_ms: 1000 }).await else {
                        break;
                    };
                    lease_ms.lock().unwrap().push(t.elapsed().as_secs_f64() * 1e3);
                    let Some(u) = reply.into_inner().unit else { continue };
                    let (header, payload) = synthetic_result(&id, &u, 0.5);
                    if worker::submit(&mut client, header, payload).await.is_ok_and(|r| r.accepted) {
                        merged.fetch_add(1, Ordering::Relaxed);
                    }
                }
            }));
        }
        tokio::time::sleep(Duration::from_secs(seconds)).await;
        stop.store(true, Ordering::Relaxed);
        for t in tasks {
            let _ = t.await;
        }
    });
    for c in clients {
        let _ = c.join();
    }
    let elapsed = t0.elapsed().as_secs_f64();
    let mut l = lease_ms.lock().unwrap().clone();
    let mut r = rest_ms.lock().unwrap().clone();
    println!(
        "load: {} s, 32 workers + 50 REST clients: leases {} (p50 {:.1} ms, p99 {:.1} ms, max {:.1} ms), units merged {} ({:.0}/s), REST requests {} (p50 {:.1} ms, p99 {:.1} ms), coordinator peak RSS {:.0} MB",
        seconds,
        l.len(),
        pct(&mut l, 0.5),
        pct(&mut l, 0.99),
        pct(&mut l, 1.0),
        merged.load(Ordering::Relaxed),
        merged.load(Ordering::Relaxed) as f64 / elapsed,
        r.len(),
        pct(&mut r, 0.5),
        pct(&mut r, 0.99),
        vm_hwm_mb(pid)
    );
}
