//! Bad input and lying workers: every bad request gets the right status and a message naming the
//! problem, a worker whose results fail validation is rejected and listed as bad, its unit is
//! re-leased, and the coordinator keeps serving (the job still completes bit-identically).

use proto::v1::*;
use std::time::Duration;
use tessera_tests::*;
use tessera_tests::{renderer, worker};

fn cornell_bytes() -> Vec<u8> {
    std::fs::read(repo_root().join("scenes/cornell/cornell.glb")).unwrap()
}

/// The Cornell box's JSON with its first primitive's POSITION accessor index set to `index`.
fn cornell_gltf_with_position(index: u32) -> Vec<u8> {
    let text = std::fs::read_to_string(repo_root().join("scenes/cornell/cornell.gltf")).unwrap();
    let mut json: serde_json::Value = serde_json::from_str(&text).unwrap();
    json["meshes"][0]["primitives"][0]["attributes"]["POSITION"] = index.into();
    serde_json::to_vec(&json).unwrap()
}

#[test]
fn bad_requests_get_clear_4xx_answers_and_the_coordinator_keeps_serving() {
    let farm = Farm::start("bad-input", &[("TESSERA_TOKEN", "let-me-in"), ("TESSERA_WORKER_SECRET", "workers-only")]);
    let tok = Some("let-me-in");
    let glb = cornell_bytes();
    type Case<'a> = (&'a str, Option<&'a str>, Vec<(&'a str, Vec<u8>)>, &'a str, u16, &'a str);
    let cases: Vec<Case> = vec![
        ("missing token", None, vec![("c.glb", glb.clone())], "{}", 401, "token"),
        ("wrong token", Some("guess"), vec![("c.glb", glb.clone())], "{}", 401, "token"),
        ("garbage glb", tok, vec![("bad.glb", b"this is not a glb at all".to_vec())], "{}", 422, "bad.glb"),
        ("truncated glb", tok, vec![("cut.glb", glb[..glb.len() / 3].to_vec())], "{}", 422, "cut.glb"),
        ("unknown settings field", tok, vec![("c.glb", glb.clone())], r#"{"spp": 4, "colour": "red"}"#, 400, "colour"),
        ("malformed settings", tok, vec![("c.glb", glb.clone())], "{spp:", 400, "settings JSON"),
        ("spp 0", tok, vec![("c.glb", glb.clone())], r#"{"spp": 0}"#, 422, "settings.spp"),
        (
            "resolution over the limit",
            tok,
            vec![("c.glb", glb.clone())],
            r#"{"width": 5000, "height": 100}"#,
            422,
            "limit of 4096",
        ),
        ("no scene file", tok, vec![("notes.txt", b"hi".to_vec())], "{}", 422, ".gltf or .glb"),
        ("escaping file name", tok, vec![("c.glb", glb.clone()), ("../evil.bin", vec![1])], "{}", 422, "not allowed"),
        // The gltf crate's validation panicked on it (a 500 from the coordinator's loading task).
        (
            "POSITION accessor out of range",
            tok,
            vec![("refs.gltf", cornell_gltf_with_position(999))],
            "{}",
            422,
            "POSITION",
        ),
    ];
    for (what, token, files, settings, status, needle) in cases {
        let files: Vec<(&str, &[u8])> = files.iter().map(|(n, d)| (*n, d.as_slice())).collect();
        let (got, body) = post_job(&farm.url, token, &files, settings);
        assert_eq!(got, status, "{what}: {body}");
        let msg = body["error"].as_str().unwrap_or_default();
        assert!(msg.contains(needle), "{what}: message '{msg}' should mention '{needle}'");
    }
    // Unknown job, and the CLI's exit codes for refusals and unreachable coordinators.
    let (code, _, err) = farm.cli(&["status", "nope"]);
    assert_eq!(code, 4, "{err}");
    assert!(err.contains("no job 'nope'"), "{err}");
    let (code, _, err) =
        Farm { url: format!("http://127.0.0.1:{}", free_port()), ..Farm::start("unreachable", &[]) }.cli(&["list"]);
    assert_eq!(code, 3, "{err}");

    // Workers: wrong secret and wrong protocol version are refused with the right gRPC status.
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let e = worker::connect(&farm.url, Some("wrong")).await.err().unwrap_or_else(|| panic!("wrong secret refused"));
        assert_eq!(e.code(), tonic::Code::Unauthenticated, "{e}");
        let e = worker::connect(&farm.url, None).await.err().unwrap_or_else(|| panic!("missing secret refused"));
        assert_eq!(e.code(), tonic::Code::Unauthenticated, "{e}");
        let channel = tonic::transport::Channel::from_shared(farm.url.clone()).unwrap().connect().await.unwrap();
        let mut raw = farm_client::FarmClient::with_interceptor(channel, |mut r: tonic::Request<()>| {
            r.metadata_mut().insert("authorization", "Bearer workers-only".parse().unwrap());
            Ok(r)
        });
        let e = raw
            .register(RegisterRequest { version: "0.0.0".into(), protocol: 999, cores: 1, name: "old".into() })
            .await
            .err()
            .unwrap_or_else(|| panic!("old protocol refused"));
        assert_eq!(e.code(), tonic::Code::FailedPrecondition);
        assert!(e.message().contains("incompatible"), "{}", e.message());
    });

    // Still serving: a good job is accepted.
    let (got, body) = post_job(&farm.url, tok, &[("c.glb", &glb)], r#"{"spp": 4, "width": 32, "height": 32}"#);
    assert_eq!(got, 201, "{body}");
}

/// Malformed query strings and a POST that is not multipart are refused like every other request:
/// 400 with a JSON `{"error"}` naming what is wrong. axum's own answers were plain text (found
/// by schemathesis against `openapi.json`, which now documents the 400s).
#[test]
fn malformed_queries_and_bodies_get_json_errors() {
    let farm = Farm::start("bad-queries", &[("TESSERA_TOKEN", "let-me-in")]);
    let agent: ureq::Agent = ureq::Agent::config_builder().http_status_as_error(false).build().into();
    let cases = [
        ("GET", "/api/v1/jobs/nope/preview.png?width=wide", "width"),
        ("GET", "/api/v1/jobs/nope/preview.png?width=99999999999", "width"),
        ("GET", "/api/v1/jobs/nope/preview.png?exposure=bright", "exposure"),
        ("GET", "/api/v1/jobs/nope/events?after=soon", "after"),
        ("POST", "/api/v1/jobs", "boundary"),
    ];
    for (method, path, needle) in cases {
        let url = format!("{}{path}", farm.url);
        let auth = "Bearer let-me-in";
        let resp = match method {
            "POST" => agent.post(&url).header("Authorization", auth).send(&b"spp=4"[..]),
            _ => agent.get(&url).header("Authorization", auth).call(),
        };
        let mut resp = resp.expect("request");
        let ctype = resp.headers().get("content-type").and_then(|v| v.to_str().ok()).unwrap_or("").to_string();
        let text = resp.body_mut().read_to_string().unwrap_or_default();
        assert_eq!(resp.status().as_u16(), 400, "{method} {path}: {text}");
        assert!(ctype.starts_with("application/json"), "{method} {path}: content type {ctype}: {text}");
        let body: serde_json::Value = serde_json::from_str(&text).unwrap_or_default();
        let msg = body["error"].as_str().unwrap_or_default();
        assert!(msg.contains(needle), "{method} {path}: '{text}' should name '{needle}'");
    }
}

#[test]
fn a_lying_worker_is_rejected_and_listed_and_the_job_still_completes_identically() {
    let mut farm = Farm::start("liar", &[]);
    let glb = cornell_bytes();
    let (got, job) = post_job(&farm.url, None, &[("c.glb", &glb)], r#"{"spp": 32, "width": 64, "height": 64}"#);
    assert_eq!(got, 201, "{job}");
    let id = job["id"].as_str().unwrap().to_string();
    let rt = tokio::runtime::Runtime::new().unwrap();
    let liars = rt.block_on(async {
        let mut liars = Vec::new();
        for lie in ["nan", "wrong-size", "wrong-count"] {
            let (mut client, wid) = worker::connect(&farm.url, None).await.expect("connect");
            let unit = client
                .lease(LeaseRequest { worker_id: wid.clone(), wait_ms: 2000 })
                .await
                .unwrap()
                .into_inner()
                .unit
                .expect("a unit");
            let r = unit.rect.unwrap();
            let rect = renderer::film::Rect { x0: r.x0, y0: r.y0, width: r.width, height: r.height };
            let n = unit.sample_end - unit.sample_start;
            let mut sums = renderer::film::PartialSums::new(rect);
            for i in 0..rect.pixels() {
                for _ in 0..n {
                    sums.add_sample(i, renderer::math::Vec3::splat(0.5));
                }
            }
            let payload = match lie {
                "nan" => {
                    sums.sum_rgb[7][0] = f64::NAN;
                    sums.encode()
                }
                "wrong-size" => sums.encode()[..100].to_vec(),
                _ => {
                    sums.count[0] += 1;
                    sums.encode()
                }
            };
            let header = ResultHeader {
                worker_id: wid.clone(),
                unit_id: unit.unit_id.clone(),
                rect: Some(r),
                sample_start: unit.sample_start,
                sample_end: unit.sample_end,
                payload_size: payload.len() as u64,
            };
            let e = worker::submit(&mut client, header, payload)
                .await
                .err()
                .unwrap_or_else(|| panic!("{lie}: the lie was accepted"));
            assert_eq!(e.code(), tonic::Code::InvalidArgument, "{lie}: {e}");
            assert!(e.message().contains("rejected"), "{lie}: {}", e.message());
            // The liar gets no more units of this job.
            let next = client.lease(LeaseRequest { worker_id: wid.clone(), wait_ms: 300 }).await.unwrap().into_inner();
            assert!(next.unit.is_none(), "{lie}: a bad worker must not get more units of the job");
            liars.push(wid);
        }
        liars
    });
    let j = farm.job(&id);
    for l in &liars {
        assert!(
            j["bad_workers"].as_array().unwrap().iter().any(|b| b == l.as_str()),
            "{l} not listed as bad: {}",
            j["bad_workers"]
        );
    }
    farm.start_worker(2);
    farm.wait_job(&id, Duration::from_secs(120), |j| j["state"] == "done");
    let out = farm.tmp.join("liar.exr");
    assert_eq!(farm.cli(&["download", &id, "-o", out.to_str().unwrap()]).0, 0);
    let local = local_render(
        &repo_root().join("scenes/cornell/cornell.glb"),
        &["--spp", "32", "--width", "64", "--height", "64"],
        &farm.tmp.join("local.exr"),
    );
    assert!(std::fs::read(&out).unwrap() == local, "the job's image must not contain the lies");
}
