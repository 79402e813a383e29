//! Helpers for the farm's integration tests: run the real `tessera` binary as coordinator, workers
//! and client on loopback with ephemeral ports, and kill or restart them.

pub use renderer;
pub use worker;
pub use {proto, rusqlite};

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// The `tessera` binary built alongside these tests (target/<profile>/tessera).
pub fn tessera_bin() -> PathBuf {
    // Benchmarks may measure another build (e.g. the previous release) in the same harness.
    if let Some(b) = std::env::var_os("TESSERA_BIN") {
        return PathBuf::from(b);
    }
    let exe = std::env::current_exe().expect("test executable path");
    let dir = exe.parent().and_then(Path::parent).expect("target dir");
    let bin = dir.join("tessera");
    assert!(
        bin.exists(),
        "{} not built: these tests run as tests of tessera-cli (`cargo test --workspace --release`)",
        bin.display()
    );
    bin
}

pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// A free TCP port on 127.0.0.1.
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").and_then(|l| l.local_addr()).map(|a| a.port()).expect("ephemeral port")
}

/// A child process killed when dropped.
pub struct Proc {
    pub child: Child,
    pub name: String,
}

impl Proc {
    pub fn kill9(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
    pub fn pid(&self) -> u32 {
        self.child.id()
    }
    /// Sends a signal by name (`STOP`, `CONT`) with kill(1).
    pub fn signal(&self, sig: &str) {
        let ok = Command::new("kill").arg(format!("-{sig}")).arg(self.pid().to_string()).status().map(|s| s.success());
        assert!(matches!(ok, Ok(true)), "kill -{sig} {} failed", self.pid());
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        self.kill9();
    }
}

pub struct Farm {
    pub url: String,
    pub port: u16,
    pub data_dir: PathBuf,
    pub env: Vec<(String, String)>,
    pub coordinator: Option<Proc>,
    pub workers: Vec<Proc>,
    pub tmp: PathBuf,
}

pub fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("tessera-test-{name}-{}-{}", std::process::id(), free_port()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

impl Farm {
    /// Starts a coordinator (lease 1.5 s so tests see expiry quickly) with extra env vars.
    pub fn start(name: &str, env: &[(&str, &str)]) -> Farm {
        let port = free_port();
        let tmp = temp_dir(name);
        let scheme = if env.iter().any(|(k, _)| *k == "TESSERA_TLS_CERT") { "https" } else { "http" };
        let mut f = Farm {
            url: format!("{scheme}://127.0.0.1:{port}"),
            port,
            data_dir: tmp.join("data"),
            env: env.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect(),
            coordinator: None,
            workers: Vec::new(),
            tmp,
        };
        f.start_coordinator();
        f
    }

    pub fn start_coordinator(&mut self) {
        let log = std::fs::File::create(self.tmp.join(format!("coordinator-{}.log", free_port()))).expect("log");
        let child = Command::new(tessera_bin())
            .args(["coordinator", "--listen", &format!("127.0.0.1:{}", self.port), "--data-dir"])
            .arg(&self.data_dir)
            .args(["--lease-seconds", "1.5"])
            .args(if self.env.iter().any(|(k, _)| k == "TESSERA_MAX_SIDE") {
                &[][..]
            } else {
                &["--max-side", "4096"][..]
            })
            .envs(self.env.iter().map(|(k, v)| (k.as_str(), v.as_str())))
            .env("TESSERA_LOG", "info")
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .expect("start coordinator");
        self.coordinator = Some(Proc { child, name: "coordinator".into() });
        let t = Instant::now();
        while t.elapsed() < Duration::from_secs(20) {
            if std::net::TcpStream::connect(("127.0.0.1", self.port)).is_ok() {
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        panic!("coordinator did not come up on {}", self.url);
    }

    pub fn start_worker(&mut self, threads: usize) -> usize {
        let log = std::fs::File::create(self.tmp.join(format!("worker-{}.log", self.workers.len()))).expect("log");
        let child = Command::new(tessera_bin())
            .args(["worker", "--coordinator", &self.url, "--threads", &threads.to_string()])
            .args(["--name", &format!("worker{}", self.workers.len()), "--cache-dir"])
            .arg(self.tmp.join(format!("cache-{}", self.workers.len())))
            .envs(self.env.iter().map(|(k, v)| (k.as_str(), v.as_str())))
            .env("TESSERA_LOG", "info")
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .expect("start worker");
        self.workers.push(Proc { child, name: format!("worker{}", self.workers.len()) });
        self.workers.len() - 1
    }

    /// Waits until `n` workers have registered (so a test's work is spread as it expects).
    pub fn wait_workers(&self, n: usize) {
        poll(Duration::from_secs(30), || {
            let (code, out, _) = self.cli(&["workers"]);
            (code == 0 && out.lines().skip(1).count() >= n)
                .then_some(())
                .ok_or_else(|| format!("{n} workers did not register"))
        });
    }

    /// Worker `i`'s entry in `GET /workers` (workers are started as `worker{i}`).
    pub fn worker(&self, i: usize) -> Result<Value, String> {
        let w = self.api("/workers")?;
        let name = format!("worker{i}");
        let me = w["workers"].as_array().into_iter().flatten().find(|x| x["name"] == name.as_str());
        me.cloned().ok_or_else(|| format!("{name} is not listed: {w}"))
    }

    /// The units the coordinator says worker `i` holds now.
    pub fn units_held_by(&self, i: usize) -> Result<usize, String> {
        Ok(self.worker(i)?["current_units"].as_array().map_or(0, |u| u.len()))
    }

    /// Kills worker `i` with SIGKILL at a moment it holds a lease, so a test of lease expiry cannot
    /// race the worker's own result. Polling and then killing can: a unit returned between the
    /// poll and the kill leaves the dead worker holding nothing (it happened in CI). So the worker
    /// is frozen first (SIGSTOP: no more results or heartbeats), and killed only if, once anything
    /// it had already sent has been taken in, the coordinator still counts a unit as its;
    /// otherwise it is thawed and tried again once it holds one.
    pub fn kill_worker_holding_a_lease(&mut self, i: usize) {
        let t = Instant::now();
        loop {
            self.workers[i].signal("STOP");
            std::thread::sleep(Duration::from_millis(300));
            if self.units_held_by(i).unwrap_or(0) > 0 {
                self.workers[i].kill9();
                return;
            }
            self.workers[i].signal("CONT");
            assert!(t.elapsed() < Duration::from_secs(60), "worker{i} never held a lease when frozen");
            poll(Duration::from_secs(30), || match self.units_held_by(i)? {
                0 => Err(format!("worker{i} holds no unit")),
                _ => Ok(()),
            });
        }
    }

    /// Runs the CLI against this farm; returns (exit code, stdout, stderr).
    pub fn cli(&self, args: &[&str]) -> (i32, String, String) {
        let out = Command::new(tessera_bin())
            .args(args)
            .env("TESSERA_COORDINATOR", &self.url)
            .envs(self.env.iter().map(|(k, v)| (k.as_str(), v.as_str())))
            .output()
            .expect("run tessera");
        (
            out.status.code().unwrap_or(-1),
            String::from_utf8_lossy(&out.stdout).into_owned(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    }

    /// `GET /api/v1{path}` as JSON (no token: test farms run without one); the error as text,
    /// for `poll`.
    pub fn api(&self, path: &str) -> Result<Value, String> {
        ureq::get(&format!("{}/api/v1{path}", self.url))
            .call()
            .map_err(|e| format!("GET {path}: {e}"))?
            .into_body()
            .read_json()
            .map_err(|e| format!("GET {path}: {e}"))
    }

    pub fn job(&self, id: &str) -> Value {
        let (code, out, err) = self.cli(&["status", id]);
        assert_eq!(code, 0, "status failed: {err}");
        serde_json::from_str(&out).expect("status JSON")
    }

    /// Waits until `pred(job)` holds, or panics after `timeout`.
    pub fn wait_job(&self, id: &str, timeout: Duration, pred: impl Fn(&Value) -> bool) -> Value {
        poll(timeout, || {
            let j = self.job(id);
            if pred(&j) {
                Ok(j)
            } else {
                Err(format!("job {id} did not reach the expected state: {j}"))
            }
        })
    }
}

/// Calls `f` every 50 ms until it succeeds; panics with its last error after `timeout`.
pub fn poll<T>(timeout: Duration, mut f: impl FnMut() -> Result<T, String>) -> T {
    let t = Instant::now();
    loop {
        match f() {
            Ok(v) => return v,
            Err(e) if t.elapsed() >= timeout => panic!("after {timeout:?}: {e}"),
            Err(_) => std::thread::sleep(Duration::from_millis(50)),
        }
    }
}

/// Renders locally with the CLI and returns the EXR bytes.
pub fn local_render(scene: &Path, args: &[&str], out: &Path) -> Vec<u8> {
    let status = Command::new(tessera_bin())
        .arg("render")
        .arg(scene)
        .arg("-o")
        .arg(out)
        .args(args)
        .stderr(Stdio::null())
        .status()
        .expect("tessera render");
    assert!(status.success());
    std::fs::read(out).expect("local EXR")
}

/// POSTs a multipart job submission by hand (so tests can send what the CLI never would).
pub fn post_job(url: &str, token: Option<&str>, files: &[(&str, &[u8])], settings: &str) -> (u16, Value) {
    let b = "xTESSERAx";
    let mut body = Vec::new();
    for (name, data) in files {
        body.extend_from_slice(
            format!("--{b}\r\nContent-Disposition: form-data; name=\"scene\"; filename=\"{name}\"\r\n\r\n").as_bytes(),
        );
        body.extend_from_slice(data);
        body.extend_from_slice(b"\r\n");
    }
    body.extend_from_slice(
        format!("--{b}\r\nContent-Disposition: form-data; name=\"settings\"\r\n\r\n{settings}\r\n--{b}--\r\n")
            .as_bytes(),
    );
    let agent: ureq::Agent = ureq::Agent::config_builder().http_status_as_error(false).build().into();
    let mut req =
        agent.post(&format!("{url}/api/v1/jobs")).header("Content-Type", &format!("multipart/form-data; boundary={b}"));
    if let Some(t) = token {
        req = req.header("Authorization", &format!("Bearer {t}"));
    }
    let mut resp = req.send(&body[..]).expect("request");
    let status = resp.status().as_u16();
    let text = resp.body_mut().read_to_string().unwrap_or_default();
    (status, serde_json::from_str(&text).unwrap_or(Value::String(text)))
}

/// A valid result for `unit` as `worker` would return it: every pixel holds the unit's samples of
/// radiance `value` (for tests and benchmarks that speak the worker protocol directly).
pub fn synthetic_result(worker: &str, unit: &proto::v1::WorkUnit, value: f32) -> (proto::v1::ResultHeader, Vec<u8>) {
    let r = unit.rect.unwrap_or_default();
    let rect = renderer::film::Rect { x0: r.x0, y0: r.y0, width: r.width, height: r.height };
    let mut sums = renderer::film::PartialSums::new(rect);
    for i in 0..rect.pixels() {
        for _ in unit.sample_start..unit.sample_end {
            sums.add_sample(i, renderer::math::Vec3::splat(value));
        }
    }
    let payload = sums.encode();
    let header = proto::v1::ResultHeader {
        worker_id: worker.into(),
        unit_id: unit.unit_id.clone(),
        rect: Some(r),
        sample_start: unit.sample_start,
        sample_end: unit.sample_end,
        payload_size: payload.len() as u64,
    };
    (header, payload)
}
