//! The farm under hostile and unlucky conditions (issue 11): each numbered finding of the issue is a
//! test here, against real processes on loopback.

use proto::v1::*;
use std::io::{Read, Write};
use std::time::{Duration, Instant};
use tessera_tests::*;
use tessera_tests::{proto, rusqlite, worker};

fn cornell() -> Vec<u8> {
    std::fs::read(repo_root().join("scenes/cornell/cornell.glb")).expect("cornell.glb")
}

fn http(url: &str, method: &str, path: &str, token: Option<&str>) -> (u16, String, Vec<u8>) {
    let agent: ureq::Agent = ureq::Agent::config_builder().http_status_as_error(false).build().into();
    let full = format!("{url}{path}");
    let mut resp = match method {
        "DELETE" => {
            let mut r = agent.delete(&full);
            if let Some(t) = token {
                r = r.header("Authorization", &format!("Bearer {t}"));
            }
            r.call()
        }
        _ => {
            let mut r = agent.get(&full);
            if let Some(t) = token {
                r = r.header("Authorization", &format!("Bearer {t}"));
            }
            r.call()
        }
    }
    .expect("request");
    let ctype = resp.headers().get("content-type").and_then(|v| v.to_str().ok()).unwrap_or("").to_string();
    let mut body = Vec::new();
    let _ = resp.body_mut().as_reader().read_to_end(&mut body);
    (resp.status().as_u16(), ctype, body)
}

/// Finding 1: settings that would overflow, be negative or name a missing camera are refused with
/// a 422 naming the field, and the coordinator restarts cleanly afterwards.
#[test]
fn bad_settings_are_refused_by_field_and_cannot_brick_the_farm() {
    let mut farm = Farm::start("hostile-settings", &[]);
    let glb = cornell();
    let huge_name = format!(r#"{{"name": "{}"}}"#, "x".repeat(10 << 20));
    let cases = [
        (r#"{"env_strength": 1e39}"#.to_string(), "env_strength"),
        (r#"{"env_strength": -1}"#.to_string(), "env_strength"),
        (r#"{"time_budget": 1e-300}"#.to_string(), "time_budget"),
        (r#"{"camera": 5}"#.to_string(), "camera"),
        (r#"{"env_color": [1, 1e39, 1]}"#.to_string(), "env_color"),
        (huge_name, "name"),
    ];
    for (settings, field) in &cases {
        let (status, body) = post_job(&farm.url, None, &[("c.glb", &glb)], settings);
        let msg = body["error"].as_str().unwrap_or_default().to_string();
        assert_eq!(status, 422, "{field}: {msg}");
        assert!(msg.contains(&format!("settings.{field}")), "{field}: {msg}");
    }
    // Issue 12's policy on the farm: an optional extension the renderer does not model is a warning
    // on the job (and in its EXR), not a refusal.
    let gltf = std::fs::read_to_string(repo_root().join("scenes/cornell/cornell.gltf")).expect("cornell.gltf");
    let gltf = gltf.replacen("\"extensionsUsed\": [", "\"extensionsUsed\": [\"KHR_materials_iridescence\", ", 1);
    assert!(gltf.contains("KHR_materials_iridescence"));
    let (status, body) = post_job(&farm.url, None, &[("c.gltf", gltf.as_bytes())], r#"{"spp": 1, "width": 8}"#);
    assert_eq!(status, 201, "{body}");
    assert!(body["warnings"][0].as_str().unwrap_or_default().contains("KHR_materials_iridescence"), "{body}");
    // NaN is not JSON: refused as malformed.
    let (status, _) = post_job(&farm.url, None, &[("c.glb", &glb)], r#"{"env_strength": NaN}"#);
    assert_eq!(status, 400);
    // Nothing bad was stored: a restart comes up and serves.
    let (ok, _) =
        post_job(&farm.url, None, &[("c.glb", &glb)], r#"{"spp": 4, "width": 16, "height": 16, "env_strength": 1e6}"#);
    assert_eq!(ok, 201);
    farm.coordinator.as_mut().unwrap().kill9();
    farm.start_coordinator();
    let (code, out, err) = farm.cli(&["list"]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(out.lines().skip(1).count(), 2, "{out}");
}

/// Finding 2: 300 parallel submissions with a queue limit of 100: exactly 100 are accepted, each
/// with its own id naming its own job; the rest get 429.
#[test]
fn parallel_submissions_get_distinct_ids_and_exactly_the_queue_limit() {
    let farm = Farm::start("hostile-parallel", &[("TESSERA_MAX_QUEUED_JOBS", "100")]);
    let glb = cornell();
    let next = std::sync::atomic::AtomicUsize::new(0);
    let results: Vec<(usize, u16, serde_json::Value)> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..16)
            .map(|_| {
                let (url, glb, next) = (&farm.url, &glb, &next);
                s.spawn(move || {
                    let mut out = Vec::new();
                    loop {
                        let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        if i >= 300 {
                            return out;
                        }
                        let settings = format!(r#"{{"name": "client-{i}", "spp": 1, "width": 8, "height": 8}}"#);
                        let (st, body) = post_job(url, None, &[("c.glb", glb)], &settings);
                        out.push((i, st, body));
                    }
                })
            })
            .collect();
        handles.into_iter().flat_map(|h| h.join().expect("thread")).collect()
    });
    assert_eq!(results.len(), 300);
    let accepted: Vec<&(usize, u16, serde_json::Value)> = results.iter().filter(|r| r.1 == 201).collect();
    assert_eq!(accepted.len(), 100, "exactly the queue limit is accepted");
    assert!(results.iter().all(|r| r.1 == 201 || r.1 == 429), "only 201 or 429");
    let mut ids: Vec<&str> = accepted.iter().map(|r| r.2["id"].as_str().unwrap()).collect();
    ids.sort();
    ids.dedup();
    assert_eq!(ids.len(), 100, "ids are distinct");
    for (i, _, body) in &accepted {
        let id = body["id"].as_str().unwrap();
        let j = farm.job(id);
        assert_eq!(j["name"], format!("client-{i}"), "id {id} names the job its client submitted");
    }
}

/// Finding 3: results and heartbeats from a worker that does not hold the lease are refused (and
/// counted); 500 concurrent registrations get 500 distinct ids.
#[test]
fn forged_results_and_foreign_heartbeats_are_refused() {
    let farm = Farm::start("hostile-forge", &[("TESSERA_WORKER_SECRET", "s3")]);
    let (st, body) =
        post_job(&farm.url, None, &[("c.glb", &cornell())], r#"{"spp": 8, "pass_spp": 4, "width": 64, "height": 32}"#);
    assert_eq!(st, 201, "{body}");
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let (mut alice, alice_id) = worker::connect(&farm.url, Some("s3")).await.expect("alice");
        let (mut mallory, mallory_id) = worker::connect(&farm.url, Some("s3")).await.expect("mallory");
        assert_ne!(alice_id, mallory_id);
        let unit = alice
            .lease(LeaseRequest { worker_id: alice_id.clone(), wait_ms: 2000 })
            .await
            .expect("lease")
            .into_inner()
            .unit
            .expect("a unit");
        // The same valid sums, headed as `worker` returning unit `unit_id`.
        let result = |worker: &str, unit_id: &str| {
            let (mut header, payload) = synthetic_result(worker, &unit, 1.0);
            header.unit_id = unit_id.into();
            (header, payload)
        };
        // Mallory returns Alice's unit: refused, and Alice keeps her lease.
        let (h, p) = result(&mallory_id, &unit.unit_id);
        let e = worker::submit(&mut mallory, h, p).await.expect_err("refused");
        assert_eq!(e.code(), tonic::Code::PermissionDenied, "{e}");
        assert!(e.message().contains(&alice_id), "{}", e.message());
        // Mallory heartbeats it: no lease granted.
        let hb = mallory
            .heartbeat(HeartbeatRequest { worker_id: mallory_id.clone(), unit_id: unit.unit_id.clone() })
            .await
            .expect("heartbeat answered")
            .into_inner();
        assert!(!hb.keep_going, "a foreign heartbeat must not grant a lease");
        // A unit nobody leased (the last pass of the same tile): refused too.
        let never = format!("{}/{}", unit.job_id, 2 + 1);
        let (h, p) = result(&mallory_id, &never);
        let e = worker::submit(&mut mallory, h, p).await.expect_err("refused");
        assert_eq!(e.code(), tonic::Code::PermissionDenied, "{e}");
        let hb = mallory
            .heartbeat(HeartbeatRequest { worker_id: mallory_id.clone(), unit_id: never })
            .await
            .unwrap()
            .into_inner();
        assert!(!hb.keep_going);
        // Alice's honest result is merged.
        let (h, p) = result(&alice_id, &unit.unit_id);
        let reply = worker::submit(&mut alice, h, p).await.expect("merged");
        assert!(reply.accepted, "{}", reply.message);

        // 500 registrations at once: 500 distinct ids.
        let regs = (0..500).map(|_| {
            let url = farm.url.clone();
            tokio::spawn(async move { worker::connect(&url, Some("s3")).await.map(|(_, id)| id) })
        });
        let mut ids = Vec::new();
        for r in regs {
            ids.push(r.await.expect("task").expect("registered"));
        }
        ids.sort();
        ids.dedup();
        assert_eq!(ids.len(), 500);
    });
    let (_, _, metrics) = http(&farm.url, "GET", "/metrics", None);
    let metrics = String::from_utf8_lossy(&metrics);
    assert!(metrics.contains("tessera_results_refused_not_leased_total 2"), "{metrics}");
    assert!(metrics.contains("tessera_heartbeats_refused_total 2"), "{metrics}");
}

/// Finding 6: a corrupt job row quarantines that job; a corrupt image blob is refused by its
/// checksum; the rest of the farm starts and serves.
#[test]
fn corrupt_rows_and_blobs_are_quarantined_and_the_rest_is_served() {
    let mut farm = Farm::start("hostile-corrupt", &[]);
    let glb = cornell();
    let submit = |name: &str| {
        let settings = format!(r#"{{"name": "{name}", "spp": 4, "width": 16, "height": 16}}"#);
        let (st, body) = post_job(&farm.url, None, &[("c.glb", &glb)], &settings);
        assert_eq!(st, 201, "{body}");
        body["id"].as_str().unwrap().to_string()
    };
    let (a, b, c) = (submit("a"), submit("b"), submit("c"));
    farm.start_worker(1);
    for id in [&a, &b, &c] {
        farm.wait_job(id, Duration::from_secs(60), |j| j["state"] == "done");
    }
    farm.coordinator.as_mut().unwrap().kill9();
    {
        let db = rusqlite::Connection::open(farm.data_dir.join("tessera.db")).expect("db");
        db.execute("UPDATE jobs SET spec = '{not json' WHERE id = ?1", [&a]).unwrap();
        let mut exr: Vec<u8> = db.query_row("SELECT exr FROM images WHERE job_id = ?1", [&b], |r| r.get(0)).unwrap();
        let mid = exr.len() / 2;
        exr[mid] ^= 0x40;
        db.execute("UPDATE images SET exr = ?2 WHERE job_id = ?1", rusqlite::params![&b, exr]).unwrap();
    }
    farm.start_coordinator();
    let (code, _, _) = http(&farm.url, "GET", "/healthz", None);
    assert_eq!(code, 200);
    let ja = farm.job(&a);
    assert_eq!(ja["state"], "failed", "{ja}");
    assert!(ja["error"].as_str().unwrap_or_default().contains("quarantined"), "{ja}");
    let (code, _, body) = http(&farm.url, "GET", &format!("/api/v1/jobs/{b}/image.exr"), None);
    assert_eq!(code, 500);
    assert!(String::from_utf8_lossy(&body).contains("SHA-256"), "{}", String::from_utf8_lossy(&body));
    let (code, ctype, body) = http(&farm.url, "GET", &format!("/api/v1/jobs/{c}/image.exr"), None);
    assert_eq!((code, ctype.as_str()), (200, "image/x-exr"));
    assert!(body.len() > 100);
    // A finished job's preview comes from disk (its accumulation left memory).
    let (code, ctype, _) = http(&farm.url, "GET", &format!("/api/v1/jobs/{c}/preview.png"), None);
    assert_eq!((code, ctype.as_str()), (200, "image/png"));
    let (st, _) = post_job(&farm.url, None, &[("c.glb", &glb)], r#"{"spp": 1, "width": 8, "height": 8}"#);
    assert_eq!(st, 201, "still accepting work");
}

/// Finding 6: a full disk (the database's size cap, which fails exactly like one) is answered 507
/// naming it, and nothing stored before is lost, across a restart too.
#[test]
fn a_full_disk_is_answered_507_and_nothing_is_lost() {
    let mut farm = Farm::start("hostile-full", &[("TESSERA_MAX_DB_MB", "2")]);
    let glb = cornell();
    let mut accepted = Vec::new();
    let mut refused = None;
    for k in 0..40u32 {
        // Each job brings its own 200 kB file, so scenes do not deduplicate.
        let pad: Vec<u8> =
            (0..200_000u32).map(|i| (i.wrapping_mul(2_654_435_761).wrapping_add(k) >> 13) as u8).collect();
        let (st, body) =
            post_job(&farm.url, None, &[("c.glb", &glb), ("pad.bin", &pad)], r#"{"spp": 1, "width": 8, "height": 8}"#);
        match st {
            201 => accepted.push(body["id"].as_str().unwrap().to_string()),
            507 => {
                refused = Some(body);
                break;
            }
            other => panic!("unexpected {other}: {body}"),
        }
    }
    let refused = refused.expect("the cap is reached within 40 jobs");
    assert!(refused["error"].as_str().unwrap_or_default().contains("full"), "{refused}");
    assert!(accepted.len() >= 3, "{} jobs fit", accepted.len());
    farm.coordinator.as_mut().unwrap().kill9();
    farm.start_coordinator();
    for id in &accepted {
        assert_eq!(farm.job(id)["state"], "queued", "{id}");
    }
    let (code, out, _) = farm.cli(&["list"]);
    assert_eq!(code, 0);
    assert_eq!(out.lines().skip(1).count(), accepted.len());
}

/// Finding 5: 300 half-sent requests do not starve anyone: /healthz answers within 1 s, and the
/// half-open connections are cut after the header timeout. Unknown paths are 404, not gRPC.
#[test]
fn half_open_connections_do_not_starve_the_coordinator() {
    let farm = Farm::start("hostile-conns", &[("TESSERA_HEADER_TIMEOUT_SECONDS", "2")]);
    let mut socks = Vec::new();
    for _ in 0..300 {
        let mut s = std::net::TcpStream::connect(("127.0.0.1", farm.port)).expect("connect");
        s.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n").expect("half a request");
        socks.push(s);
    }
    let t = Instant::now();
    let (code, _, _) = http(&farm.url, "GET", "/healthz", None);
    let took = t.elapsed();
    assert_eq!(code, 200);
    assert!(took < Duration::from_secs(1), "healthz took {took:?} with 300 half-open connections");
    // After the header timeout the server has closed them (read ends).
    std::thread::sleep(Duration::from_secs(3));
    let mut closed = 0;
    for s in &mut socks {
        s.set_read_timeout(Some(Duration::from_millis(200))).unwrap();
        let mut buf = [0u8; 256];
        loop {
            match s.read(&mut buf) {
                Ok(0) => {
                    closed += 1;
                    break;
                }
                Ok(_) => continue,
                Err(_) => break,
            }
        }
    }
    assert_eq!(closed, 300, "half-open connections are closed after the header timeout");
    let (code, ctype, _) = http(&farm.url, "GET", "/no/such/path", None);
    assert_eq!(code, 404);
    assert!(ctype.starts_with("application/json"), "{ctype}");
    // Finding 4: a 600 MB upload is refused on its Content-Length, before any of it is read.
    let mut s = std::net::TcpStream::connect(("127.0.0.1", farm.port)).expect("connect");
    s.write_all(b"POST /api/v1/jobs HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\nContent-Length: 629145600\r\n\r\n")
        .expect("headers");
    s.set_read_timeout(Some(Duration::from_secs(2))).unwrap();
    let mut buf = [0u8; 512];
    let n = s.read(&mut buf).expect("an answer before any body byte was sent");
    let head = String::from_utf8_lossy(&buf[..n]);
    assert!(head.starts_with("HTTP/1.1 413"), "{head}");
}

fn rss_kb(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .unwrap_or(0)
}

/// Finding 4: three 8192² jobs, queued then cancelled, cost no image memory (accumulation is
/// allocated when a tile is first folded and dropped when a job ends); DELETE removes a job.
#[test]
fn huge_queued_and_cancelled_jobs_hold_no_memory_and_delete_removes_them() {
    let farm = Farm::start("hostile-memory", &[("TESSERA_MAX_SIDE", "8192")]);
    let glb = cornell();
    let mut ids = Vec::new();
    for _ in 0..3 {
        let (st, body) = post_job(&farm.url, None, &[("c.glb", &glb)], r#"{"spp": 16, "width": 8192, "height": 8192}"#);
        assert_eq!(st, 201, "{body}");
        ids.push(body["id"].as_str().unwrap().to_string());
    }
    let pid = farm.coordinator.as_ref().unwrap().pid();
    let (code, _, _) = http(&farm.url, "GET", "/api/v1/jobs", None);
    assert_eq!(code, 200);
    let queued = rss_kb(pid);
    for id in &ids {
        let (code, out, err) = farm.cli(&["cancel", id]);
        assert_eq!(code, 0, "{out}{err}");
    }
    let (code, _, _) = http(&farm.url, "GET", "/api/v1/jobs", None);
    assert_eq!(code, 200);
    let cancelled = rss_kb(pid);
    eprintln!("coordinator RSS with three 8192² jobs: queued {} MB, cancelled {} MB", queued / 1024, cancelled / 1024);
    assert!(queued < 300 * 1024 && cancelled < 300 * 1024, "RSS {queued} kB / {cancelled} kB");
    let (code, _, body) = http(&farm.url, "DELETE", &format!("/api/v1/jobs/{}", ids[0]), None);
    assert_eq!(code, 200, "{}", String::from_utf8_lossy(&body));
    let (code, _, _) = http(&farm.url, "GET", &format!("/api/v1/jobs/{}", ids[0]), None);
    assert_eq!(code, 404);
}

/// Finding 7: with a wrong token a large submission reports the 401 (exit 4), not a broken pipe;
/// a negative priority is accepted as `--priority -1`.
#[test]
fn the_client_reports_refusals_and_takes_negative_priorities() {
    let farm = Farm::start("hostile-client", &[("TESSERA_TOKEN", "right")]);
    let dir = temp_dir("hostile-client-scene");
    let big = dir.join("big.glb");
    let mut glb = cornell();
    glb.extend(std::iter::repeat_n(0u8, 6 << 20)); // trailing bytes: a 6 MB upload
    std::fs::write(&big, &glb).unwrap();
    let mut wrong = Farm {
        url: farm.url.clone(),
        env: vec![("TESSERA_TOKEN".into(), "wrong".into())],
        ..Farm::start("hostile-client-2", &[])
    };
    wrong.coordinator.as_mut().unwrap().kill9();
    let (code, _, err) = wrong.cli(&["submit", big.to_str().unwrap()]);
    assert_eq!(code, 4, "{err}");
    assert!(err.contains("401"), "{err}");
    let (code, out, err) = farm.cli(&[
        "submit",
        repo_root().join("scenes/cornell/cornell.glb").to_str().unwrap(),
        "--priority",
        "-1",
        "--spp",
        "1",
        "--width",
        "8",
    ]);
    assert_eq!(code, 0, "{out}{err}");
}
