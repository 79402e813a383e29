//! The workers' gRPC service (`proto/tessera.proto`): register, lease (long-poll), fetch scene,
//! heartbeat, submit result. Every call must carry the worker secret.

use crate::service::{ResultError, ResultReply};
use crate::{lock, now_ms, Shared, WorkerInfo};
use proto::v1::farm_server::{Farm, FarmServer};
use proto::v1::*;
use renderer::film::{PartialSums, Rect as FilmRect, ENCODED_PIXEL_BYTES};
use std::sync::Arc;
use std::time::Duration;
use tokio_stream::StreamExt;
use tonic::{Request, Response, Status, Streaming};

/// Scene bundles are streamed in chunks of this size.
const CHUNK: usize = 1 << 20;
/// Longest long-poll a worker may ask for.
const MAX_WAIT_MS: u32 = 30_000;

pub fn router(shared: Arc<Shared>) -> axum::Router {
    let secret = shared.config.worker_secret.clone();
    let check = move |req: Request<()>| -> Result<Request<()>, Status> {
        if let Some(secret) = &secret {
            let given = req
                .metadata()
                .get("authorization")
                .and_then(|v| v.to_str().ok())
                .and_then(|v| v.strip_prefix("Bearer "));
            if given != Some(secret.as_str()) {
                return Err(Status::unauthenticated("worker secret missing or wrong (TESSERA_WORKER_SECRET)"));
            }
        }
        Ok(req)
    };
    let svc = FarmServer::with_interceptor(FarmService { shared }, check);
    // Only the service's own paths are gRPC: anything else is the REST router's 404.
    axum::Router::new().route_service("/tessera.v1.Farm/{*method}", svc)
}

struct FarmService {
    shared: Arc<Shared>,
}

fn to_proto_rect(r: FilmRect) -> Rect {
    Rect { x0: r.x0, y0: r.y0, width: r.width, height: r.height }
}

impl FarmService {
    fn touch(&self, worker_id: &str) -> Result<(), Status> {
        match lock(&self.shared.workers).get_mut(worker_id) {
            Some(w) => {
                w.last_seen_ms = now_ms();
                Ok(())
            }
            None => Err(Status::not_found(format!("unknown worker '{worker_id}': register first"))),
        }
    }
}

#[tonic::async_trait]
impl Farm for FarmService {
    async fn register(&self, req: Request<RegisterRequest>) -> Result<Response<RegisterReply>, Status> {
        let r = req.into_inner();
        if r.protocol != proto::PROTOCOL_VERSION {
            return Err(Status::failed_precondition(format!(
                "worker protocol {} (tessera {}) is incompatible with this coordinator's protocol {} (tessera {}): run the same tessera version",
                r.protocol,
                r.version,
                proto::PROTOCOL_VERSION,
                env!("CARGO_PKG_VERSION")
            )));
        }
        let name: String = r.name.chars().take(64).collect();
        // The id starts with the name the worker was given (URL-safe part of it), so `tessera
        // workers` and the logs say which machine is which; the suffix keeps registrations apart.
        let stem: String =
            name.chars().filter(|c| c.is_ascii_alphanumeric() || *c == '-' || *c == '_').take(32).collect();
        let id = if stem.is_empty() { crate::new_id("w") } else { format!("{stem}-{}", crate::new_id("w")) };
        tracing::info!(worker = %id, %name, cores = r.cores, version = %r.version, "worker registered");
        lock(&self.shared.workers).insert(
            id.clone(),
            WorkerInfo {
                id: id.clone(),
                name,
                version: r.version.chars().take(32).collect(),
                cores: r.cores,
                registered_ms: now_ms(),
                last_seen_ms: now_ms(),
                units_done: 0,
                units_rejected: 0,
                draining: false,
                settings_sent: Default::default(),
            },
        );
        Ok(Response::new(RegisterReply { worker_id: id, lease_ms: self.shared.config.lease.as_millis() as u32 }))
    }

    async fn lease(&self, req: Request<LeaseRequest>) -> Result<Response<LeaseReply>, Status> {
        let r = req.into_inner();
        self.touch(&r.worker_id)?;
        let deadline = tokio::time::Instant::now() + Duration::from_millis(r.wait_ms.min(MAX_WAIT_MS) as u64);
        loop {
            // Register interest before looking, so a notification between the look and the wait is not lost.
            let notified = self.shared.work_available.notified();
            // A drained worker is told "nothing yet" until it is resumed.
            let draining = lock(&self.shared.workers).get(&r.worker_id).is_some_and(|w| w.draining);
            let unit = if draining {
                None
            } else {
                let mut farm = lock(&self.shared.farm);
                let unit = farm.lease(&r.worker_id, now_ms(), self.shared.config.lease.as_millis() as i64);
                // The job's log names each worker once, at its first unit.
                if let Some(job) = unit.as_ref().and_then(|u| farm.jobs.get_mut(&u.job_id)) {
                    if job.workers_seen.len() < 4096 && job.workers_seen.insert(r.worker_id.clone()) {
                        self.shared.event(&job.id, "worker_joined", &format!("{} took its first unit", r.worker_id));
                    }
                }
                unit
            };
            if let Some(u) = unit {
                // Settings travel once per job and registration: the worker keeps them by job id.
                let first = lock(&self.shared.workers).get_mut(&r.worker_id).is_some_and(|w| {
                    if w.settings_sent.len() > 4096 {
                        w.settings_sent.clear();
                    }
                    w.settings_sent.insert(u.job_id.clone())
                });
                let settings_json = if first { u.settings_json.to_string() } else { String::new() };
                return Ok(Response::new(LeaseReply {
                    unit: Some(WorkUnit {
                        unit_id: u.unit_id,
                        job_id: u.job_id,
                        scene_hash: u.scene_hash,
                        scene_size: u.scene_size,
                        settings_json,
                        rect: Some(to_proto_rect(u.rect)),
                        sample_start: u.samples.start,
                        sample_end: u.samples.end,
                        lease_deadline_unix_ms: u.deadline_ms,
                    }),
                }));
            }
            if tokio::time::timeout_at(deadline, notified).await.is_err() {
                return Ok(Response::new(LeaseReply { unit: None }));
            }
        }
    }

    type FetchSceneStream = std::pin::Pin<Box<dyn tokio_stream::Stream<Item = Result<SceneChunk, Status>> + Send>>;

    async fn fetch_scene(&self, req: Request<FetchSceneRequest>) -> Result<Response<Self::FetchSceneStream>, Status> {
        let r = req.into_inner();
        self.touch(&r.worker_id)?;
        // Read (and checked against its hash) outside the farm lock; a corrupt blob is an error.
        let shared = self.shared.clone();
        let hash = r.scene_hash.clone();
        let data = tokio::task::spawn_blocking(move || lock(&shared.store).scene(&hash))
            .await
            .map_err(|e| Status::internal(e.to_string()))?
            .map_err(|e| Status::data_loss(e.to_string()))?
            .ok_or_else(|| Status::not_found(format!("no scene with hash {}", r.scene_hash)))?;
        let total = data.len() as u64;
        let chunks: Vec<Result<SceneChunk, Status>> =
            data.chunks(CHUNK).map(|c| Ok(SceneChunk { total_size: total, data: c.to_vec() })).collect();
        Ok(Response::new(Box::pin(tokio_stream::iter(chunks))))
    }

    async fn heartbeat(&self, req: Request<HeartbeatRequest>) -> Result<Response<HeartbeatReply>, Status> {
        let r = req.into_inner();
        self.touch(&r.worker_id)?;
        let deadline = lock(&self.shared.farm).heartbeat(
            &r.worker_id,
            &r.unit_id,
            now_ms(),
            self.shared.config.lease.as_millis() as i64,
        );
        if deadline.is_none() {
            lock(&self.shared.metrics).heartbeats_refused += 1;
        }
        Ok(Response::new(HeartbeatReply {
            keep_going: deadline.is_some(),
            lease_deadline_unix_ms: deadline.unwrap_or(0),
        }))
    }

    async fn submit_result(&self, req: Request<Streaming<ResultChunk>>) -> Result<Response<SubmitReply>, Status> {
        let mut stream = req.into_inner();
        let header = match stream.next().await {
            Some(Ok(ResultChunk { part: Some(result_chunk::Part::Header(h)) })) => h,
            Some(Err(e)) => return Err(e),
            _ => return Err(Status::invalid_argument("a result must start with its header")),
        };
        self.touch(&header.worker_id)?;
        let (rect, samples) = lock(&self.shared.farm)
            .unit_shape(&header.unit_id)
            .ok_or_else(|| Status::not_found(format!("unknown unit '{}'", header.unit_id)))?;
        // Bound the payload by what the unit can legitimately produce before reading any of it.
        let expected = rect.pixels() * ENCODED_PIXEL_BYTES;
        let mut payload = Vec::with_capacity(expected.min(header.payload_size as usize));
        let mut too_long = false;
        while let Some(chunk) = stream.next().await {
            match chunk?.part {
                Some(result_chunk::Part::Data(d)) => {
                    if payload.len() + d.len() > expected {
                        too_long = true;
                        break;
                    }
                    payload.extend_from_slice(&d);
                }
                _ => return Err(Status::invalid_argument("only data chunks may follow the header")),
            }
        }
        let claimed = header.rect.map(|r| FilmRect { x0: r.x0, y0: r.y0, width: r.width, height: r.height });
        let sums = if too_long {
            Err(format!("payload exceeds the {expected} bytes a {}x{} tile can hold", rect.width, rect.height))
        } else if claimed != Some(rect) || header.sample_start != samples.start || header.sample_end != samples.end {
            Err(format!(
                "result header {:?} {}..{} does not match the unit {:?} {:?}",
                claimed, header.sample_start, header.sample_end, rect, samples
            ))
        } else {
            PartialSums::decode(rect, &payload)
        };
        let pixel_samples = rect.pixels() as u64 * samples.len() as u64;
        let shared = self.shared.clone();
        let (worker, unit) = (header.worker_id.clone(), header.unit_id.clone());
        // Merging, checkpointing and possibly finishing the job (EXR encoding) block: off the runtime.
        let outcome = tokio::task::spawn_blocking(move || shared.accept_result(&worker, &unit, sums, pixel_samples))
            .await
            .map_err(|e| Status::internal(e.to_string()))?;
        let reply = match outcome {
            Ok(ResultReply::Merged) => SubmitReply { accepted: true, message: "merged".into() },
            Ok(ResultReply::Dropped(why)) => SubmitReply { accepted: false, message: why.into() },
            Err(e @ ResultError::NotLeased(_)) => return Err(Status::permission_denied(e.to_string())),
            Err(e @ ResultError::Invalid(_)) => return Err(Status::invalid_argument(e.to_string())),
            Err(e @ ResultError::Storage(_)) => return Err(Status::unavailable(e.to_string())),
        };
        Ok(Response::new(reply))
    }
}
