//! Tessera's coordinator. One address serves the REST API (`/api/v1`), the web page (`/`), Prometheus
//! metrics (`/metrics`) and the workers' gRPC service, multiplexed by HTTP version and content type,
//! so workers and clients are given the same URL.
//!
//! Modules: `state` (scheduling and merging, no I/O), `store` (SQLite persistence), `grpc` (the
//! worker protocol), `rest` (the user API), `web` (the page).

pub mod grpc;
pub mod rest;
pub mod state;
pub mod store;
pub mod tls;
mod web;

use state::{Farm, Job, JobState};
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
}

/// Counters exported on /metrics.
#[derive(Default)]
pub struct Metrics {
    pub units_merged: u64,
    pub units_rejected: u64,
    pub units_expired: u64,
    pub merge_seconds_sum: f64,
    pub samples_merged: u64,
}

pub struct Shared {
    pub config: Config,
    pub farm: Mutex<Farm>,
    pub store: Mutex<Store>,
    pub workers: Mutex<HashMap<String, WorkerInfo>>,
    pub metrics: Mutex<Metrics>,
    /// Wakes long-polling `Lease` calls when work appears.
    pub work_available: tokio::sync::Notify,
    pub started: std::time::Instant,
}

pub fn now_ms() -> i64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_millis() as i64).unwrap_or(0)
}

/// Locks a mutex, recovering the data if a panicking thread poisoned it (the state stays usable:
/// every mutation is completed before anything that could panic).
pub fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Shared {
    /// Opens the store and restores every job from it.
    pub fn open(config: Config) -> Result<Arc<Self>, store::StoreError> {
        let store = Store::open(&config.data_dir)?;
        let mut farm = Farm::default();
        for job in store.load_jobs()? {
            if !job.state.is_final() {
                tracing::info!(job = %job.id, done = job.units_done(), total = job.unit_count(), "resuming job from checkpoint");
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
            started: std::time::Instant::now(),
        }))
    }

    /// Writes the final EXR of a completed job and marks it done.
    pub fn finish_job(&self, job: &mut Job) {
        let sums = job.image();
        let image = renderer::image_io::FinalImage::from_sums(&sums);
        match image.exr_bytes(&renderer::image_io::standard_attributes(&job.spec.settings, &sums, job.stop_reason())) {
            Ok(bytes) => {
                job.state = JobState::Done;
                job.finished_ms = Some(now_ms());
                if let Err(e) = lock(&self.store).finish_job(job, &bytes) {
                    tracing::error!(job = %job.id, error = %e, "cannot store the finished image");
                    job.state = JobState::Failed;
                    job.error = Some(format!("cannot store the finished image: {e}"));
                }
            }
            Err(e) => {
                job.state = JobState::Failed;
                job.error = Some(format!("cannot encode the EXR: {e}"));
                let _ = lock(&self.store).update_job_state(job);
            }
        }
        tracing::info!(job = %job.id, state = job.state.as_str(), "job finished");
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
            let expired = {
                let mut farm = lock(&s.farm);
                // Jobs a time budget closed between results have nothing left to wait for.
                for id in farm.finished_jobs() {
                    if let Some(job) = farm.jobs.get_mut(&id) {
                        s.finish_job(job);
                    }
                }
                farm.expire(now_ms())
            };
            if !expired.is_empty() {
                lock(&s.metrics).units_expired += expired.len() as u64;
                for (job, worker) in &expired {
                    tracing::warn!(%job, %worker, "lease expired: unit returned to the queue");
                }
                s.work_available.notify_waiters();
            }
        }
    });
    let app = rest::router(shared.clone()).merge(grpc::router(shared.clone()));
    tracing::info!(addr = %listener.local_addr()?, tls = tls.is_some(), "coordinator listening (REST, web, gRPC)");
    if let Some(cfg) = tls {
        axum::serve(tls::TlsListener { inner: listener, acceptor: tokio_rustls::TlsAcceptor::from(cfg) }, app).await?;
        return Ok(());
    }
    // TCP_NODELAY: a streamed result (header, then data) would otherwise stall ~40 ms per unit
    // on Nagle's algorithm meeting delayed ACKs.
    use axum::serve::ListenerExt;
    let listener = listener.tap_io(|tcp| {
        let _ = tcp.set_nodelay(true);
    });
    axum::serve(listener, app).await?;
    Ok(())
}
