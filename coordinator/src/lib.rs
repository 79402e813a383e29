//! Tessera's coordinator. One address serves the REST API (`/api/v1`), the web page (`/`), Prometheus
//! metrics (`/metrics`) and the workers' gRPC service, multiplexed by HTTP version and content type,
//! so workers and clients are given the same URL.
//!
//! Modules: `state` (scheduling and merging, no I/O), `store` (SQLite persistence), `grpc` (the
//! worker protocol), `rest` (the user API), `web` (the page).

pub mod conn;
pub mod grpc;
pub mod rest;
pub mod service;
pub mod state;
pub mod store;
pub mod tls;
mod web;

use state::Farm;
use std::collections::HashMap;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use store::Store;

/// Limits on what clients may ask for; each violation is answered with a 4xx naming the limit.
#[derive(Clone, Debug)]
pub struct Limits {
    pub max_upload_bytes: usize,
    pub max_side: u32,
    pub max_spp: u32,
    pub max_queued_jobs: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Limits { max_upload_bytes: 512 << 20, max_side: 8192, max_spp: 1 << 16, max_queued_jobs: 256 }
    }
}

#[derive(Clone, Debug)]
pub struct Config {
    pub listen: SocketAddr,
    pub data_dir: PathBuf,
    /// Bearer token required by the REST API (`TESSERA_TOKEN`); None leaves it open.
    pub token: Option<String>,
    /// Shared secret required from workers (`TESSERA_WORKER_SECRET`); None accepts any worker.
    pub worker_secret: Option<String>,
    pub limits: Limits,
    /// How long a lease lasts without a heartbeat.
    pub lease: Duration,
    /// PEM certificate chain and private key: serve HTTPS (and gRPC over TLS) instead of plain HTTP.
    pub tls: Option<(PathBuf, PathBuf)>,
    /// Connection cap and timeouts.
    pub conn: conn::ConnLimits,
    /// Largest database size (`TESSERA_MAX_DB_MB`); None: as large as the disk allows.
    pub max_db_bytes: Option<u64>,
    /// Most pixels of running jobs at once (`TESSERA_MAX_PIXELS_IN_FLIGHT`; 0: no limit).
    pub max_pixels_in_flight: u64,
    /// Most frames of one shot running at once (`TESSERA_MAX_FRAMES_IN_FLIGHT`; 0: no limit).
    pub max_frames_in_flight: usize,
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct WorkerInfo {
    pub id: String,
    pub name: String,
    pub version: String,
    pub cores: u32,
    pub registered_ms: i64,
    pub last_seen_ms: i64,
    pub units_done: u64,
    pub units_rejected: u64,
    /// Drained by an operator: it keeps what it holds but is given no new units.
    pub draining: bool,
    /// Jobs whose settings this registration was sent (they travel once per job).
    #[serde(skip)]
    pub settings_sent: std::collections::HashSet<String>,
}

/// Counters exported on /metrics.
#[derive(Default)]
pub struct Metrics {
    pub units_merged: u64,
    pub units_rejected: u64,
    pub units_expired: u64,
    pub merge_seconds_sum: f64,
    pub samples_merged: u64,
    /// Results and heartbeats refused because the caller did not hold the lease.
    pub results_forged: u64,
    pub heartbeats_refused: u64,
    /// Storage failures (a result not merged, an image not stored: all retried).
    pub storage_errors: u64,
}

pub struct Shared {
    pub config: Config,
    pub farm: Mutex<Farm>,
    pub store: Mutex<Store>,
    pub workers: Mutex<HashMap<String, WorkerInfo>>,
    pub metrics: Mutex<Metrics>,
    /// Wakes long-polling `Lease` calls when work appears.
    pub work_available: tokio::sync::Notify,
    /// The job and worker lists `GET /events` streams, made once for all its clients
    /// (`rest::publish_live_lists`).
    pub live: tokio::sync::watch::Sender<rest::LiveLists>,
    pub started: std::time::Instant,
}

/// An identifier that cannot collide: `prefix` and 16 hex digits of a hash of a process-wide
/// counter, the time and the process id, keyed by the OS-seeded `RandomState` (so neither
/// guessable from the submission time nor repeated across restarts). Job rows are inserted without
/// replace, so a clash could only ever make an insert fail and retry.
pub fn new_id(prefix: &str) -> String {
    use std::hash::BuildHasher;
    static COUNTER: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let n = COUNTER.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let t = SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_nanos()).unwrap_or(0);
    let h = std::collections::hash_map::RandomState::new().hash_one((n, t, std::process::id()));
    format!("{prefix}{h:016x}")
}

pub fn now_ms() -> i64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_millis() as i64).unwrap_or(0)
}

/// Locks a mutex, recovering the data if a panicking thread poisoned it (the state stays usable:
/// every mutation is completed before anything that could panic).
pub fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// A worker not heard from for this long is dropped from the registry (it re-registers if alive).
pub const WORKER_FORGET_MS: i64 = 10 * 60 * 1000;

impl Shared {
    /// Forgets workers not seen for `WORKER_FORGET_MS` (their leases expired long before).
    pub fn prune_workers(&self, now: i64) {
        lock(&self.workers).retain(|id, w| {
            let keep = now - w.last_seen_ms < WORKER_FORGET_MS;
            if !keep {
                tracing::info!(worker = %id, name = %w.name, "worker forgotten (not seen for 10 minutes)");
            }
            keep
        });
    }

    /// Opens the store and restores every job from it.
    pub fn open(config: Config) -> Result<Arc<Self>, store::StoreError> {
        let store = Store::open(&config.data_dir, config.max_db_bytes)?;
        let mut farm = Farm::default();
        farm.max_pixels_in_flight = config.max_pixels_in_flight;
        farm.max_frames_in_flight = config.max_frames_in_flight;
        for job in store.load_jobs()? {
            if !job.state.is_final() {
                tracing::info!(job = %job.id, done = job.units_done(), total = job.unit_count(), "resuming job from checkpoint");
                let detail = format!(
                    "coordinator restarted: resumed from the checkpoint with {} of {} units",
                    job.units_done(),
                    job.unit_count()
                );
                if let Err(e) = store.add_event(&job.id, now_ms(), "resumed", &detail) {
                    tracing::warn!(job = %job.id, error = %e, "cannot store a job event");
                }
            }
            farm.add_job(job);
        }
        Ok(Arc::new(Shared {
            config,
            farm: Mutex::new(farm),
            store: Mutex::new(store),
            workers: Mutex::new(HashMap::new()),
            metrics: Mutex::new(Metrics::default()),
            work_available: tokio::sync::Notify::new(),
            live: tokio::sync::watch::Sender::new(rest::LiveLists::default()),
            started: std::time::Instant::now(),
        }))
    }
}

/// Runs the coordinator until the process is stopped.
pub async fn serve(config: Config) -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
    let listener = tokio::net::TcpListener::bind(config.listen).await?;
    serve_on(listener, config).await
}

pub async fn serve_on(
    listener: tokio::net::TcpListener,
    config: Config,
) -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
    if config.token.is_none() {
        tracing::warn!("TESSERA_TOKEN is not set: the REST API accepts anyone who can reach it");
    }
    if config.worker_secret.is_none() {
        tracing::warn!("TESSERA_WORKER_SECRET is not set: any worker may join");
    }
    let tls = match &config.tls {
        Some((cert, key)) => Some(tls::server_config(cert, key)?),
        None => None,
    };
    let shared = Shared::open(config)?;
    // Lease expiry: units of dead, partitioned or slow workers go back to the queue.
    let s = shared.clone();
    tokio::spawn(async move {
        let mut tick = tokio::time::interval(Duration::from_millis(250));
        loop {
            tick.tick().await;
            // Jobs a time budget closed between results (or whose image could not be stored
            // yet) have nothing left to wait for: finish them, outside the farm lock.
            let finished = lock(&s.farm).finished_jobs(now_ms());
            for id in finished {
                s.finish_job(&id);
            }
            let expired = lock(&s.farm).expire(now_ms());
            s.prune_workers(now_ms());
            if !expired.is_empty() {
                lock(&s.metrics).units_expired += expired.len() as u64;
                for (job, worker) in &expired {
                    tracing::warn!(%job, %worker, "lease expired: unit returned to the queue");
                    let detail = format!(
                        "a unit's lease held by {worker} expired (no heartbeat for {} s): returned to the queue",
                        s.config.lease.as_secs_f64()
                    );
                    s.event(job, "lease_expired", &detail);
                }
                s.work_available.notify_waiters();
            }
        }
    });
    tokio::spawn(rest::publish_live_lists(shared.clone()));
    let app = rest::router(shared.clone()).merge(grpc::router(shared.clone())).fallback(rest::not_found);
    tracing::info!(addr = %listener.local_addr()?, tls = tls.is_some(), max_connections = shared.config.conn.max_connections, "coordinator listening (REST, web, gRPC)");
    let acceptor = tls.map(tokio_rustls::TlsAcceptor::from);
    conn::serve(listener, acceptor, app, shared.config.conn).await?;
    Ok(())
}
