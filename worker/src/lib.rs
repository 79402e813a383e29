//! Tessera's worker: registers with a coordinator, leases work units (tile × pass), fetches scenes
//! by content hash into a size-limited cache, renders with all cores, heartbeats while rendering and
//! streams the partial sums back. It reconnects with backoff when the coordinator goes away and, on
//! shutdown, finishes and returns the unit it holds before exiting.

use proto::v1::farm_client::FarmClient;
use proto::v1::*;
use renderer::bundle::SceneBundle;
use renderer::film::{PartialSums, Rect as FilmRect};
use renderer::{RenderSettings, Scene};
use sha2::Digest;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;
use tonic::{Code, Request, Status};

#[derive(Debug, thiserror::Error)]
pub enum WorkerError {
    #[error("coordinator refused this worker: {0}")]
    Refused(String),
    #[error("invalid coordinator URL '{0}'")]
    BadUrl(String),
    #[error("{0}")]
    Other(String),
}

#[derive(Clone, Debug)]
pub struct WorkerConfig {
    pub coordinator: String,
    pub secret: Option<String>,
    pub threads: Option<usize>,
    pub name: String,
    pub cache_dir: PathBuf,
    /// Scene cache size limit; the least recently used scenes are evicted past it.
    pub cache_limit_bytes: u64,
    /// PEM CA certificate to trust for an `https://` coordinator (else the webpki roots).
    pub ca_cert: Option<Vec<u8>>,
}

/// A channel to the coordinator, over TLS when the URL is `https://`.
async fn open_channel(url: &str, ca_cert: Option<&[u8]>) -> Result<Channel, String> {
    let mut endpoint = Channel::from_shared(url.to_string()).map_err(|_| format!("invalid coordinator URL '{url}'"))?;
    if url.starts_with("https://") {
        let mut tls = tonic::transport::ClientTlsConfig::new().with_webpki_roots();
        if let Some(pem) = ca_cert {
            tls = tls.ca_certificate(tonic::transport::Certificate::from_pem(pem));
        }
        endpoint = endpoint.tls_config(tls).map_err(|e| e.to_string())?;
    }
    endpoint.tcp_nodelay(true).connect().await.map_err(|e| e.to_string())
}

type Client = FarmClient<InterceptedService<Channel, Auth>>;

#[derive(Clone)]
pub struct Auth(Option<tonic::metadata::MetadataValue<tonic::metadata::Ascii>>);

impl tonic::service::Interceptor for Auth {
    fn call(&mut self, mut req: Request<()>) -> Result<Request<()>, Status> {
        if let Some(v) = &self.0 {
            req.metadata_mut().insert("authorization", v.clone());
        }
        Ok(req)
    }
}

/// Runs until `stop` is set (then finishes the unit in hand) or the coordinator refuses us.
pub async fn run(config: WorkerConfig, stop: Arc<AtomicBool>) -> Result<(), WorkerError> {
    let pool = Arc::new(
        rayon::ThreadPoolBuilder::new()
            .num_threads(config.threads.unwrap_or(0))
            .build()
            .map_err(|e| WorkerError::Other(e.to_string()))?,
    );
    let auth = Auth(match &config.secret {
        Some(s) => Some(
            format!("Bearer {s}")
                .parse()
                .map_err(|_| WorkerError::Other("the worker secret has characters not allowed in a header".into()))?,
        ),
        None => None,
    });
    std::fs::create_dir_all(&config.cache_dir)
        .map_err(|e| WorkerError::Other(format!("cache dir {}: {e}", config.cache_dir.display())))?;
    let mut backoff = Duration::from_millis(200);
    let mut loaded: Option<(String, Arc<Scene>)> = None;
    while !stop.load(Ordering::Relaxed) {
        if Channel::from_shared(config.coordinator.clone()).is_err() {
            return Err(WorkerError::BadUrl(config.coordinator.clone()));
        }
        let channel = match open_channel(&config.coordinator, config.ca_cert.as_deref()).await {
            Ok(c) => c,
            Err(e) => {
                tracing::warn!(error = %e, retry_in = ?backoff, "cannot reach the coordinator");
                tokio::time::sleep(backoff).await;
                backoff = (backoff * 2).min(Duration::from_secs(5));
                continue;
            }
        };
        let mut client = FarmClient::with_interceptor(channel, auth.clone()).max_decoding_message_size(64 << 20);
        match session(&config, &mut client, pool.clone(), &stop, &mut loaded).await {
            Ok(()) => return Ok(()),
            Err(s) if s.code() == Code::FailedPrecondition || s.code() == Code::Unauthenticated => {
                return Err(WorkerError::Refused(s.message().to_string()))
            }
            Err(s) => {
                tracing::warn!(error = %s.message(), code = ?s.code(), "lost the coordinator; reconnecting");
                tokio::time::sleep(backoff).await;
                backoff = (backoff * 2).min(Duration::from_secs(5));
            }
        }
    }
    Ok(())
}

/// One connection's worth of work: register, then lease and render until stopped or disconnected.
async fn session(
    config: &WorkerConfig,
    client: &mut Client,
    pool: Arc<rayon::ThreadPool>,
    stop: &AtomicBool,
    loaded: &mut Option<(String, Arc<Scene>)>,
) -> Result<(), Status> {
    let reg = client
        .register(RegisterRequest {
            version: env!("CARGO_PKG_VERSION").into(),
            protocol: proto::PROTOCOL_VERSION,
            cores: pool.current_num_threads() as u32,
            name: config.name.clone(),
        })
        .await?
        .into_inner();
    tracing::info!(worker = %reg.worker_id, "registered");
    let lease_ms = reg.lease_ms.max(1000) as u64;
    let mut settings_by_job: std::collections::HashMap<String, RenderSettings> = std::collections::HashMap::new();
    while !stop.load(Ordering::Relaxed) {
        let reply = match client.lease(LeaseRequest { worker_id: reg.worker_id.clone(), wait_ms: 2000 }).await {
            Ok(r) => r.into_inner(),
            // The coordinator restarted and forgot us: register again.
            Err(s) if s.code() == Code::NotFound => return Err(Status::unavailable("coordinator forgot this worker")),
            Err(s) => return Err(s),
        };
        let Some(unit) = reply.unit else { continue };
        // Settings come with a job's first unit of this registration; later units name the job.
        let settings: RenderSettings = if unit.settings_json.is_empty() {
            match settings_by_job.get(&unit.job_id) {
                Some(s) => s.clone(),
                None => {
                    return Err(Status::unavailable(format!("no settings for job {}: registering again", unit.job_id)))
                }
            }
        } else {
            match serde_json::from_str(&unit.settings_json) {
                Ok(s) => {
                    if settings_by_job.len() >= 256 {
                        settings_by_job.clear();
                        // The coordinator will not send them again to this registration.
                        return Err(Status::unavailable("settings cache full: registering again"));
                    }
                    settings_by_job.insert(unit.job_id.clone(), s);
                    settings_by_job[&unit.job_id].clone()
                }
                Err(e) => {
                    tracing::error!(unit = %unit.unit_id, error = %e, "bad settings in the unit");
                    continue;
                }
            }
        };
        let scene = match scene_for(config, client, &reg.worker_id, &unit, &settings, loaded).await {
            Ok(s) => s,
            Err(e) => {
                tracing::error!(unit = %unit.unit_id, error = %e, "cannot load the unit's scene; leaving the unit to expire");
                continue;
            }
        };
        let Some(r) = unit.rect else { continue };
        let rect = FilmRect { x0: r.x0, y0: r.y0, width: r.width, height: r.height };
        let samples = unit.sample_start..unit.sample_end;
        if settings.validate().is_err()
            || samples.end <= samples.start
            || rect.width == 0
            || rect.height == 0
            || rect.x0 + rect.width > settings.width
            || rect.y0 + rect.height > settings.height
        {
            tracing::error!(unit = %unit.unit_id, "malformed unit");
            continue;
        }

        // Render on the thread pool while heartbeating.
        let t = std::time::Instant::now();
        let (p, sc, st, sm) = (pool.clone(), scene.clone(), settings.clone(), samples.clone());
        let mut render = tokio::task::spawn_blocking(move || p.install(|| renderer::render_tile(&sc, &st, rect, sm)));
        let mut beat = tokio::time::interval(Duration::from_millis(lease_ms / 3));
        beat.tick().await;
        let sums: PartialSums = loop {
            tokio::select! {
                r = &mut render => break r.map_err(|e| Status::internal(e.to_string()))?,
                _ = beat.tick() => {
                    let hb = client.heartbeat(HeartbeatRequest { worker_id: reg.worker_id.clone(), unit_id: unit.unit_id.clone() }).await?.into_inner();
                    if !hb.keep_going {
                        tracing::info!(unit = %unit.unit_id, "coordinator no longer needs this unit");
                    }
                }
            }
        };
        let payload = sums.encode();
        let header = ResultHeader {
            worker_id: reg.worker_id.clone(),
            unit_id: unit.unit_id.clone(),
            rect: Some(r),
            sample_start: samples.start,
            sample_end: samples.end,
            payload_size: payload.len() as u64,
        };
        match submit(client, header, payload).await {
            Ok(reply) => {
                tracing::info!(unit = %unit.unit_id, seconds = t.elapsed().as_secs_f64(), accepted = reply.accepted, message = %reply.message, "unit done");
            }
            // The lease went to someone else, the result was refused, or the coordinator could
            // not store it (it re-leases the unit): this unit is over, the session is not.
            Err(s) if matches!(s.code(), Code::PermissionDenied | Code::InvalidArgument | Code::Unavailable) => {
                tracing::warn!(unit = %unit.unit_id, code = ?s.code(), error = %s.message(), "result not merged");
            }
            Err(s) => return Err(s),
        }
    }
    Ok(())
}

/// Streams a result: the header, then the payload in 1 MiB chunks.
pub async fn submit(client: &mut Client, header: ResultHeader, payload: Vec<u8>) -> Result<SubmitReply, Status> {
    let mut chunks = vec![ResultChunk { part: Some(result_chunk::Part::Header(header)) }];
    chunks.extend(payload.chunks(1 << 20).map(|c| ResultChunk { part: Some(result_chunk::Part::Data(c.to_vec())) }));
    Ok(client.submit_result(tokio_stream::iter(chunks)).await?.into_inner())
}

/// Connects and registers, for tools and tests that speak the protocol directly.
pub async fn connect(url: &str, secret: Option<&str>) -> Result<(Client, String), Status> {
    let channel = open_channel(url, None).await.map_err(Status::unavailable)?;
    let auth = Auth(
        secret
            .map(|s| format!("Bearer {s}").parse())
            .transpose()
            .map_err(|_| Status::invalid_argument("bad secret"))?,
    );
    let mut client = FarmClient::with_interceptor(channel, auth);
    let reg = client
        .register(RegisterRequest {
            version: env!("CARGO_PKG_VERSION").into(),
            protocol: proto::PROTOCOL_VERSION,
            cores: 1,
            name: "probe".into(),
        })
        .await?
        .into_inner();
    Ok((client, reg.worker_id))
}

/// The unit's scene: from memory, from the disk cache, or fetched from the coordinator.
async fn scene_for(
    config: &WorkerConfig,
    client: &mut Client,
    worker_id: &str,
    unit: &WorkUnit,
    settings: &RenderSettings,
    loaded: &mut Option<(String, Arc<Scene>)>,
) -> Result<Arc<Scene>, String> {
    // The loaded scene depends on the bundle and on what `prepare` reads from the settings; an
    // animated scene also on the frame (and fps, animation), which a re-pose changes in place:
    // a worker kept on a shot's frames loads and prepares once (the scheduler keeps it there).
    let key = format!("{} {}", unit.scene_hash, Scene::prepare_key(settings));
    let pose = (settings.frame, settings.fps.to_bits(), settings.animation.clone());
    if let Some((k, s)) = loaded.as_ref() {
        if *k == key {
            if s.pose_key() == Some(&pose) || !s.is_animated() {
                return Ok(s.clone());
            }
            // Another frame of the same scene: re-pose it (nothing else holds it between units).
            if let Some((k, s)) = loaded.take() {
                if let Ok(mut scene) = Arc::try_unwrap(s) {
                    let st = settings.clone();
                    let scene = tokio::task::spawn_blocking(move || -> Result<Scene, String> {
                        scene.set_frame(&st, st.frame).map_err(|e| e.to_string())?;
                        Ok(scene)
                    })
                    .await
                    .map_err(|e| e.to_string())??;
                    let scene = Arc::new(scene);
                    *loaded = Some((k, scene.clone()));
                    return Ok(scene);
                }
            }
        }
    }
    if unit.scene_hash.len() != 64 || !unit.scene_hash.bytes().all(|b| b.is_ascii_hexdigit()) {
        return Err(format!("bad scene hash '{}'", unit.scene_hash));
    }
    let dir = config.cache_dir.join(&unit.scene_hash);
    let marker = dir.join(".complete");
    if !marker.exists() {
        if unit.scene_size > config.cache_limit_bytes {
            return Err(format!(
                "scene of {} bytes exceeds the cache limit of {} bytes",
                unit.scene_size, config.cache_limit_bytes
            ));
        }
        let mut stream = client
            .fetch_scene(FetchSceneRequest { worker_id: worker_id.into(), scene_hash: unit.scene_hash.clone() })
            .await
            .map_err(|e| e.message().to_string())?
            .into_inner();
        let mut data = Vec::new();
        while let Some(chunk) = stream.message().await.map_err(|e| e.message().to_string())? {
            if chunk.total_size > config.cache_limit_bytes || data.len() + chunk.data.len() > chunk.total_size as usize
            {
                return Err("scene stream larger than announced or than the cache limit".into());
            }
            data.extend_from_slice(&chunk.data);
        }
        let got = hex::encode(sha2::Sha256::digest(&data));
        if got != unit.scene_hash {
            return Err(format!("scene content hash {got} does not match {}", unit.scene_hash));
        }
        let bundle = SceneBundle::decode(&data)?;
        let _ = std::fs::remove_dir_all(&dir);
        bundle.unpack(&dir).map_err(|e| e.to_string())?;
        std::fs::write(dir.join(".main"), &bundle.main).map_err(|e| e.to_string())?;
        std::fs::write(&marker, b"").map_err(|e| e.to_string())?;
        evict(&config.cache_dir, config.cache_limit_bytes, &unit.scene_hash);
    }
    let main = std::fs::read_to_string(dir.join(".main")).map_err(|e| e.to_string())?;
    let path = dir.join(main.trim());
    let st = settings.clone();
    let scene = tokio::task::spawn_blocking(move || -> Result<Scene, String> {
        let mut scene = renderer::gltf_loader::load(&path).map_err(|e| e.to_string())?;
        scene.prepare(&st, &dir).map_err(|e| e.to_string())?;
        scene.set_frame(&st, st.frame).map_err(|e| e.to_string())?;
        Ok(scene)
    })
    .await
    .map_err(|e| e.to_string())??;
    let scene = Arc::new(scene);
    *loaded = Some((key, scene.clone()));
    Ok(scene)
}

fn dir_size(p: &std::path::Path) -> u64 {
    std::fs::read_dir(p).map_or(0, |rd| {
        rd.flatten()
            .map(|e| match e.metadata() {
                Ok(m) if m.is_dir() => dir_size(&e.path()),
                Ok(m) => m.len(),
                Err(_) => 0,
            })
            .sum()
    })
}

/// Removes the least recently written cached scenes until the cache fits its limit.
fn evict(cache: &std::path::Path, limit: u64, keep: &str) {
    let Ok(rd) = std::fs::read_dir(cache) else { return };
    let mut entries: Vec<(std::time::SystemTime, PathBuf, u64)> = rd
        .flatten()
        .filter(|e| e.file_name().to_string_lossy() != keep)
        .filter_map(|e| Some((e.metadata().ok()?.modified().ok()?, e.path(), dir_size(&e.path()))))
        .collect();
    let mut total: u64 = entries.iter().map(|e| e.2).sum::<u64>() + dir_size(&cache.join(keep));
    entries.sort();
    for (_, path, size) in entries {
        if total <= limit {
            break;
        }
        let _ = std::fs::remove_dir_all(&path);
        total -= size;
    }
}
