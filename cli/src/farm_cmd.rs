//! `tessera coordinator` and `tessera worker`.

use anyhow::{Context, Result};
use clap::Args;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

#[derive(Args, Debug)]
pub struct CoordinatorArgs {
    /// Address for REST, the web page and gRPC (one port).
    #[arg(long, default_value = "127.0.0.1:7878", env = "TESSERA_LISTEN")]
    pub listen: std::net::SocketAddr,
    /// Where jobs, scenes, checkpoints and images are kept.
    #[arg(long, default_value = "tessera-data", env = "TESSERA_DATA_DIR")]
    pub data_dir: PathBuf,
    /// Seconds a work unit stays leased without a heartbeat.
    #[arg(long, default_value_t = 10.0, env = "TESSERA_LEASE_SECONDS")]
    pub lease_seconds: f64,
    /// Largest upload accepted, in MiB.
    #[arg(long, default_value_t = 512, env = "TESSERA_MAX_UPLOAD_MB")]
    pub max_upload_mb: usize,
    /// Largest image side accepted.
    #[arg(long, default_value_t = 8192, env = "TESSERA_MAX_SIDE")]
    pub max_side: u32,
    /// Largest spp accepted.
    #[arg(long, default_value_t = 65536, env = "TESSERA_MAX_SPP")]
    pub max_spp: u32,
    /// Most unfinished jobs held at once.
    #[arg(long, default_value_t = 256, env = "TESSERA_MAX_QUEUED_JOBS")]
    pub max_queued_jobs: usize,
    /// PEM certificate chain: serve HTTPS and gRPC over TLS (with --tls-key).
    #[arg(long, env = "TESSERA_TLS_CERT", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// PEM private key for --tls-cert.
    #[arg(long, env = "TESSERA_TLS_KEY", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    /// Most connections served at once (REST, web and workers); more are closed on arrival.
    #[arg(long, default_value_t = 512, env = "TESSERA_MAX_CONNECTIONS")]
    pub max_connections: usize,
    /// Largest size of the coordinator's database in MiB (writes beyond it are answered like a full
    /// disk: 507, nothing stored is lost). Default: as large as the disk allows.
    #[arg(long, env = "TESSERA_MAX_DB_MB")]
    pub max_db_mb: Option<u64>,
    /// Most image pixels of running jobs at once: a queued job starts only while it fits beside the
    /// running ones (or when none runs). The coordinator holds 36 bytes a pixel in flight, so the
    /// default 2^28 (268 Mpx, e.g. four 8192² frames) bounds that at 9.7 GB. 0: no limit.
    #[arg(long, default_value_t = 1 << 28, env = "TESSERA_MAX_PIXELS_IN_FLIGHT")]
    pub max_pixels_in_flight: u64,
    /// Most frames of one shot rendering at once (frames are handed out in order; finished frames
    /// are on disk, so a 240-frame shot holds at most this many accumulations). 0: no limit.
    #[arg(long, default_value_t = 4, env = "TESSERA_MAX_FRAMES_IN_FLIGHT")]
    pub max_frames_in_flight: usize,
    /// Seconds a client has to send a request's headers (HTTP/1).
    #[arg(long, default_value_t = 10.0, env = "TESSERA_HEADER_TIMEOUT_SECONDS")]
    pub header_timeout_seconds: f64,
}

pub fn coordinator(a: CoordinatorArgs) -> Result<()> {
    let token = std::env::var("TESSERA_TOKEN").ok().filter(|t| !t.is_empty());
    let worker_secret = std::env::var("TESSERA_WORKER_SECRET").ok().filter(|t| !t.is_empty());
    if !(a.lease_seconds > 0.0 && a.lease_seconds < 86400.0) {
        anyhow::bail!("--lease-seconds must be between 0 and 86400");
    }
    tracing::info!(listen = %a.listen, data_dir = %a.data_dir.display(), "coordinator starting");
    let config = coordinator::Config {
        listen: a.listen,
        data_dir: a.data_dir,
        token,
        worker_secret,
        limits: coordinator::Limits {
            max_upload_bytes: a.max_upload_mb << 20,
            max_side: a.max_side,
            max_spp: a.max_spp,
            max_queued_jobs: a.max_queued_jobs,
        },
        lease: std::time::Duration::from_secs_f64(a.lease_seconds),
        tls: a.tls_cert.zip(a.tls_key),
        conn: coordinator::conn::ConnLimits {
            max_connections: a.max_connections.max(1),
            header_read_timeout: std::time::Duration::from_secs_f64(a.header_timeout_seconds.clamp(0.1, 3600.0)),
            ..Default::default()
        },
        max_db_bytes: a.max_db_mb.map(|m| m << 20),
        max_pixels_in_flight: a.max_pixels_in_flight,
        max_frames_in_flight: a.max_frames_in_flight,
    };
    let rt = tokio::runtime::Runtime::new().context("cannot start the async runtime")?;
    rt.block_on(async move {
        tokio::select! {
            r = coordinator::serve(config) => r.map_err(|e| anyhow::anyhow!("{e}")),
            _ = shutdown_signal() => { tracing::info!("coordinator stopping"); Ok(()) }
        }
    })
}

async fn shutdown_signal() {
    #[cfg(unix)]
    {
        let mut term = match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(s) => s,
            Err(_) => return std::future::pending().await,
        };
        tokio::select! { _ = term.recv() => {}, _ = tokio::signal::ctrl_c() => {} }
    }
    #[cfg(not(unix))]
    let _ = tokio::signal::ctrl_c().await;
}

#[derive(Args, Debug)]
pub struct WorkerArgs {
    /// Coordinator URL, e.g. http://127.0.0.1:7878.
    #[arg(long, env = "TESSERA_COORDINATOR")]
    pub coordinator: String,
    /// Render threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Name shown in `tessera workers`.
    #[arg(long)]
    pub name: Option<String>,
    /// Scene cache directory.
    #[arg(long, env = "TESSERA_CACHE_DIR")]
    pub cache_dir: Option<PathBuf>,
    /// Scene cache size limit in MiB.
    #[arg(long, default_value_t = 4096)]
    pub cache_limit_mb: u64,
}

pub fn worker(a: WorkerArgs) -> Result<()> {
    let name = a.name.unwrap_or_else(|| {
        format!("{}-{}", std::env::var("HOSTNAME").unwrap_or_else(|_| "worker".into()), std::process::id())
    });
    let config = worker::WorkerConfig {
        coordinator: a.coordinator,
        secret: std::env::var("TESSERA_WORKER_SECRET").ok().filter(|t| !t.is_empty()),
        ca_cert: match std::env::var("TESSERA_CA_CERT").ok().filter(|p| !p.is_empty()) {
            Some(p) => Some(std::fs::read(&p).with_context(|| format!("TESSERA_CA_CERT {p}"))?),
            None => None,
        },
        threads: a.threads,
        cache_dir: a
            .cache_dir
            .unwrap_or_else(|| std::env::temp_dir().join(format!("tessera-cache-{}", std::process::id()))),
        name,
        cache_limit_bytes: a.cache_limit_mb << 20,
    };
    let stop = Arc::new(AtomicBool::new(false));
    let rt = tokio::runtime::Runtime::new().context("cannot start the async runtime")?;
    rt.block_on(async move {
        let s = stop.clone();
        tokio::spawn(async move {
            shutdown_signal().await;
            tracing::info!("stopping after the current unit");
            s.store(true, Ordering::Relaxed);
        });
        worker::run(config, stop).await.map_err(anyhow::Error::from)
    })
}
