//! The REST API (`/api/v1`, JSON, bearer token), the web page, `/metrics` and the OpenAPI document.

use crate::service::ServiceError;
use crate::state::{Job, JobSpec, JobState};
use crate::{lock, now_ms, Shared};
use axum::body::Bytes;
use axum::extract::multipart::MultipartRejection;
use axum::extract::{DefaultBodyLimit, FromRequestParts, Multipart, Path, Query, State};
use axum::http::request::Parts;
use axum::http::{header, StatusCode};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use renderer::bundle::SceneBundle;
use renderer::image_io::FinalImage;
use renderer::settings_request::{SceneFacts, SettingsLimits, SettingsRequest};
use serde_json::{json, Value};
use sha2::Digest;
use std::sync::Arc;

pub const OPENAPI: &str = include_str!("openapi.json");

/// Most tiles of all a shot's frames together: every frame job is planned when the shot is
/// submitted (about 250 bytes a tile before it starts), so this bounds a shot's bookkeeping.
pub const MAX_SHOT_TILES: u64 = 4_000_000;

type S = State<Arc<Shared>>;

/// An API error: a status and a message naming what is wrong.
pub struct ApiError(StatusCode, String);

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        (self.0, Json(json!({ "error": self.1 }))).into_response()
    }
}

fn err(status: StatusCode, msg: impl Into<String>) -> ApiError {
    ApiError(status, msg.into())
}

/// An axum extractor (`Path`, `Query`) whose refusal is answered as every other refusal is: 400
/// and a JSON `{"error"}` naming what is wrong, e.g. the query parameter that does not parse or a
/// path segment that is not UTF-8. axum's own answers are plain text, which a client that reads
/// `error` from every refusal cannot show (found by schemathesis against `openapi.json`).
struct ApiExtract<E>(E);

impl<E, St> FromRequestParts<St> for ApiExtract<E>
where
    E: FromRequestParts<St>,
    E::Rejection: std::fmt::Display,
    St: Send + Sync,
{
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &St) -> Result<Self, ApiError> {
        E::from_request_parts(parts, state)
            .await
            .map(ApiExtract)
            .map_err(|e| err(StatusCode::BAD_REQUEST, e.to_string()))
    }
}

pub fn router(shared: Arc<Shared>) -> Router {
    let limit = shared.config.limits.max_upload_bytes;
    let api = Router::new()
        .route("/jobs", post(submit).get(list_jobs))
        .route("/jobs/{id}", get(get_job).delete(delete_job))
        .route("/jobs/{id}/cancel", post(cancel_job))
        .route("/jobs/{id}/image.exr", get(download))
        .route("/jobs/{id}/preview.png", get(preview))
        .route("/jobs/{id}/events", get(job_events))
        .route("/jobs/{id}/resubmit", post(resubmit_job))
        .route("/events", get(live_events))
        .route("/jobs/{id}/frames/{frame}", get(frame_image))
        .route("/jobs/{id}/frames.tar", get(frames_archive))
        .route("/workers", get(list_workers))
        .route("/workers/{id}/drain", post(drain_worker))
        .route("/workers/{id}/resume", post(resume_worker))
        .layer(axum::middleware::from_fn_with_state(shared.clone(), auth))
        .layer(axum::middleware::from_fn_with_state(shared.clone(), upload_guard))
        .layer(DefaultBodyLimit::max(limit));
    Router::new()
        .route("/", get(|| async { Html(crate::web::PAGE) }))
        .route("/api/v1/openapi.json", get(|| async { ([(header::CONTENT_TYPE, "application/json")], OPENAPI) }))
        .route("/metrics", get(metrics))
        .route("/healthz", get(|| async { "ok" }))
        .nest("/api/v1", api)
        .with_state(shared)
}

/// Answer for any path that is neither REST, the page, metrics nor the workers' gRPC service.
pub async fn not_found(uri: axum::http::Uri) -> ApiError {
    err(StatusCode::NOT_FOUND, format!("no such resource: {}", uri.path()))
}

/// Refuses an upload whose declared length is over the limit before any of it is read, and bounds
/// the time a request may take (a client trickling its body cannot hold a connection forever).
async fn upload_guard(State(s): S, req: axum::extract::Request, next: axum::middleware::Next) -> Response {
    let limit = s.config.limits.max_upload_bytes;
    let declared =
        req.headers().get(header::CONTENT_LENGTH).and_then(|v| v.to_str().ok()).and_then(|v| v.parse::<u64>().ok());
    if let Some(n) = declared.filter(|&n| n > limit as u64 + 64 * 1024) {
        return err(
            StatusCode::PAYLOAD_TOO_LARGE,
            format!("upload of {n} bytes exceeds the limit of {limit} bytes (TESSERA_MAX_UPLOAD_MB)"),
        )
        .into_response();
    }
    match tokio::time::timeout(REQUEST_TIMEOUT, next.run(req)).await {
        Ok(r) => r,
        Err(_) => {
            err(StatusCode::REQUEST_TIMEOUT, format!("request not completed within {} s", REQUEST_TIMEOUT.as_secs()))
                .into_response()
        }
    }
}

/// Longest a REST request (an upload included) may take.
pub const REQUEST_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(600);

async fn auth(State(s): S, req: axum::extract::Request, next: axum::middleware::Next) -> Response {
    if let Some(token) = &s.config.token {
        let given = req
            .headers()
            .get(header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.strip_prefix("Bearer "));
        if given != Some(token.as_str()) {
            return err(StatusCode::UNAUTHORIZED, "missing or wrong bearer token (TESSERA_TOKEN)").into_response();
        }
    }
    next.run(req).await
}

async fn submit(
    State(s): S,
    form: Result<Multipart, MultipartRejection>,
) -> Result<(StatusCode, Json<Value>), ApiError> {
    // Not multipart, or no boundary: refused in JSON like the rest (as `ApiExtract` does for the
    // extractors of a request's parts; axum's own answer is plain text).
    let mut form = form.map_err(|e| err(StatusCode::BAD_REQUEST, e.to_string()))?;
    let limits = s.config.limits.clone();
    if lock(&s.farm).queued_jobs() >= limits.max_queued_jobs {
        return Err(err(
            StatusCode::TOO_MANY_REQUESTS,
            format!("the queue holds the maximum of {} unfinished jobs", limits.max_queued_jobs),
        ));
    }
    let mut files: Vec<(String, Vec<u8>)> = Vec::new();
    let mut settings = SettingsRequest::default();
    let mut total = 0usize;
    let mut env_map: Option<String> = None;
    loop {
        let field = match form.next_field().await {
            Ok(Some(f)) => f,
            Ok(None) => break,
            Err(e) => {
                let status = if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
                    StatusCode::PAYLOAD_TOO_LARGE
                } else {
                    StatusCode::BAD_REQUEST
                };
                let msg = if status == StatusCode::PAYLOAD_TOO_LARGE {
                    format!("upload exceeds the limit of {} bytes", limits.max_upload_bytes)
                } else {
                    format!("bad multipart body: {e}")
                };
                return Err(err(status, msg));
            }
        };
        let name = field.name().unwrap_or("").to_string();
        match name.as_str() {
            "scene" => {
                let (file_name, data) = file_part(field, "scene", limits.max_upload_bytes).await?;
                total += data.len();
                files.push((file_name, data));
            }
            "settings" => {
                let text = field.text().await.map_err(|e| err(StatusCode::BAD_REQUEST, format!("settings: {e}")))?;
                settings = serde_json::from_str(&text)
                    .map_err(|e| err(StatusCode::BAD_REQUEST, format!("settings JSON: {e}")))?;
            }
            "env" => {
                let (file_name, data) = file_part(field, "env", limits.max_upload_bytes).await?;
                total += data.len();
                let name = format!("env/{}", file_name.rsplit('/').next().unwrap_or("map"));
                env_map = Some(name.clone());
                files.push((name, data));
            }
            other => {
                return Err(err(
                    StatusCode::BAD_REQUEST,
                    format!("unknown form field '{other}' (expected scene, settings, env)"),
                ))
            }
        }
    }
    if total > limits.max_upload_bytes {
        return Err(err(
            StatusCode::PAYLOAD_TOO_LARGE,
            format!("upload of {total} bytes exceeds the limit of {} bytes", limits.max_upload_bytes),
        ));
    }
    let main = files
        .iter()
        .find(|(n, _)| n.to_ascii_lowercase().ends_with(".gltf") || n.to_ascii_lowercase().ends_with(".glb"))
        .map(|(n, _)| n.clone())
        .ok_or_else(|| err(StatusCode::UNPROCESSABLE_ENTITY, "no .gltf or .glb file among the 'scene' parts"))?;
    let bundle = SceneBundle { main, files };
    bundle.validate().map_err(|e| err(StatusCode::UNPROCESSABLE_ENTITY, e))?;

    // Farm-level fields first: they need no scene.
    let (name, priority) = settings.job_fields().map_err(|e| err(StatusCode::UNPROCESSABLE_ENTITY, e.to_string()))?;
    // Check the scene loads here, so a broken file is refused now rather than failing on workers.
    let dir = s.config.data_dir.join("tmp").join(format!("upload-{}", crate::new_id("u")));
    let b = bundle.clone();
    let d = dir.clone();
    // The probe reads the map to refuse a broken one; it builds no sampling table (sampling off,
    // so MIS compensation, the `false` below, has nothing to change).
    let env_probe = renderer::environment::EnvironmentSettings {
        map: env_map.clone(),
        color: None,
        sampling: false,
        ..Default::default()
    };
    let loaded = tokio::task::spawn_blocking(move || -> Result<(Vec<Option<f32>>, Vec<String>), String> {
        let main = b.unpack(&d).map_err(|e| format!("cannot unpack the scene: {e}"))?;
        let strip = |e: String| e.replace(&format!("{}/", d.display()), "");
        let mut scene = renderer::gltf_loader::load(&main).map_err(|e| strip(e.to_string()))?;
        scene.attach_environment(&env_probe, &d, false).map_err(|e| strip(e.to_string()))?;
        Ok((scene.cameras.iter().map(|c| c.aspect_ratio).collect(), scene.warnings.clone()))
    })
    .await
    .map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()));
    let _ = std::fs::remove_dir_all(&dir);
    let (aspects, warnings) = loaded?.map_err(|e| err(StatusCode::UNPROCESSABLE_ENTITY, e))?;
    let facts = SceneFacts {
        cameras: aspects.len(),
        aspect: match settings.camera {
            Some(c) => aspects.get(c as usize).copied().flatten(),
            None => aspects.first().copied().flatten(),
        },
    };
    let farm_limits = SettingsLimits { max_side: limits.max_side, max_spp: limits.max_spp };
    let rs = settings
        .resolve(facts, env_map, farm_limits)
        .map_err(|e| err(StatusCode::UNPROCESSABLE_ENTITY, e.to_string()))?;
    let encoded = bundle.encode();
    let hash = hex::encode(sha2::Sha256::digest(&encoded));
    let spec = JobSpec {
        name: name.unwrap_or_else(|| bundle.main.clone()),
        scene_hash: hash,
        settings: rs,
        priority,
        warnings,
        shot: None,
    };
    // `frames` makes a shot: one frame job per frame (even for a single frame, so that the
    // frame's EXR is at /frames/N.exr like every other).
    let frames = match &settings.frames {
        Some(_) => Some(settings.frame_range().map_err(|e| err(StatusCode::UNPROCESSABLE_ENTITY, e.to_string()))?),
        None => None,
    };
    if let Some(f) = frames {
        let tiles =
            renderer::film::Rect::tiles(spec.settings.width, spec.settings.height, renderer::budget::TILE).len();
        if f.count() as u64 * tiles as u64 > MAX_SHOT_TILES {
            return Err(err(
                StatusCode::UNPROCESSABLE_ENTITY,
                format!("settings.frames: {} frames of {tiles} tiles is over this farm's {MAX_SHOT_TILES} tiles a shot: split the shot", f.count()),
            ));
        }
    }
    let shared = s.clone();
    let id = tokio::task::spawn_blocking(move || match frames {
        Some(f) => shared.submit_shot(spec, f, &encoded),
        None => shared.submit_job(spec, &encoded),
    })
    .await
    .map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?
    .map_err(service_err)?;
    let body = entity_json(&lock(&s.farm), &id, false).unwrap_or(Value::Null);
    Ok((StatusCode::CREATED, Json(body)))
}

/// The HTTP answer to a refused service call.
fn service_err(e: ServiceError) -> ApiError {
    let status = StatusCode::from_u16(e.status()).unwrap_or(StatusCode::INTERNAL_SERVER_ERROR);
    err(status, e.to_string())
}

/// A file part of the upload: its file name and bytes (bounded by the body limit layer).
async fn file_part(
    field: axum::extract::multipart::Field<'_>,
    part: &str,
    limit: usize,
) -> Result<(String, Vec<u8>), ApiError> {
    let file_name = field
        .file_name()
        .map(str::to_string)
        .ok_or_else(|| err(StatusCode::BAD_REQUEST, format!("a '{part}' part needs a file name")))?;
    let data = field.bytes().await.map_err(|e| {
        err(StatusCode::PAYLOAD_TOO_LARGE, format!("upload failed or exceeds the limit of {limit} bytes: {e}"))
    })?;
    Ok((file_name, data.to_vec()))
}

fn job_json(j: &Job) -> Value {
    let (done, total) = j.samples_progress();
    let now = now_ms();
    let s = &j.spec.settings;
    let elapsed_ms = j.started_ms.map(|st| j.finished_ms.unwrap_or(now) - st);
    let mut fraction = if total > 0 { done as f64 / total as f64 } else { 0.0 };
    // A noise target: the samples planned are only a cap (65536 by default), so count each tile's
    // progress towards the target instead (the measure `tessera render` shows too).
    if s.noise_target.is_some() && !j.state.is_final() {
        let (mut acc, mut px) = (0.0f64, 0.0f64);
        for (i, (r, e)) in j.tiles.iter().zip(j.tile_noise()).enumerate() {
            let finished = j.folded[i] >= j.planned[i];
            acc += renderer::budget::tile_progress(s, j.folded[i], finished, e.rel_error) * r.pixels() as f64;
            px += r.pixels() as f64;
        }
        if px > 0.0 {
            fraction = fraction.max(acc / px);
        }
    }
    let mut eta_s = None;
    if let (Some(e), false) = (elapsed_ms, j.state.is_final()) {
        (fraction, eta_s) = renderer::budget::fraction_and_eta(s, fraction, e as f64 / 1000.0);
    }
    let noise = j.noise();
    let worst = j
        .tiles
        .iter()
        .zip(j.tile_noise())
        .filter(|(_, e)| e.rel_mse.is_finite())
        .max_by(|a, b| a.1.rel_mse.total_cmp(&b.1.rel_mse))
        .map(|(r, e)| (*r, *e));
    json!({
        "id": j.id,
        "name": j.spec.name,
        "state": j.state.as_str(),
        "error": j.error.clone().or_else(|| j.finish_error.clone()),
        "warnings": j.spec.warnings,
        "priority": j.spec.priority,
        "scene_hash": j.spec.scene_hash,
        "submitted_ms": j.submitted_ms,
        "started_ms": j.started_ms,
        "finished_ms": j.finished_ms,
        "elapsed_s": elapsed_ms.map(|e| e as f64 / 1000.0),
        "eta_s": eta_s,
        "progress": {
            "samples_done": done, "samples_total": total, "fraction": fraction,
            "units_done": j.units_done(), "units_leased": j.units_leased(), "units_total": j.unit_count(),
            "spp_min": noise.map(|n| n.spp_min), "spp_max": noise.map(|n| n.spp_max),
            "spp_mean": done as f64 / (s.width as f64 * s.height as f64),
        },
        "noise": {
            "estimated_rel_mse": noise.map(|n| n.rel_mse),
            "estimated_rel_error": noise.map(|n| n.rel_error),
            "worst_tile": worst.map(|(r, e)| json!({ "x0": r.x0, "y0": r.y0, "width": r.width, "height": r.height, "rel_error": e.rel_error, "spp": e.spp_max })),
        },
        "budget": {
            "time_budget_s": s.time_budget, "noise_target": s.noise_target, "min_spp": s.min_spp, "spp_cap": s.spp,
            "tiles_converged": j.tiles_converged(), "tiles": j.tiles.len(), "stop": j.stop_reason().as_str(),
        },
        "techniques": { "integrator": s.integrator, "mis_heuristic": s.mis_heuristic, "sampler": s.sampler, "light_sampler": s.light_sampler, "filter": s.filter },
        "settings": s,
        "bad_workers": j.bad_workers.iter().collect::<Vec<_>>(),
        // Changes whenever the preview would: clients fetch the preview only when it did.
        "preview_version": format!("{}-{}-{}", j.state.as_str(), j.units_done(), j.finished_ms.unwrap_or(0)),
    })
}

/// Per-tile noise of a job (only on the single-job resource: a large image has thousands of tiles).
fn tiles_json(j: &Job) -> Value {
    let tiles: Vec<Value> = j
        .tiles
        .iter()
        .zip(j.tile_noise())
        .zip(j.folded.iter().zip(&j.planned))
        .map(|((r, e), (f, p))| {
            json!({
                "x0": r.x0, "y0": r.y0, "width": r.width, "height": r.height,
                "spp": e.spp_max, "passes_done": f, "passes_planned": p,
                "rel_error": e.rel_error.is_finite().then_some(e.rel_error),
            })
        })
        .collect();
    Value::Array(tiles)
}

/// A shot: its frames' states, progress and noise, aggregated, and a line per frame.
fn shot_json(id: &str, frames: &[&Job]) -> Value {
    let Some(first) = frames.first() else { return Value::Null };
    let per: Vec<Value> = frames.iter().map(|j| job_json(j)).collect();
    let count = |st: JobState| frames.iter().filter(|j| j.state == st).count();
    let (done, failed, cancelled, running) =
        (count(JobState::Done), count(JobState::Failed), count(JobState::Cancelled), count(JobState::Running));
    let state = if done == frames.len() {
        "done"
    } else if failed > 0 && running == 0 {
        "failed"
    } else if cancelled > 0 && running == 0 && cancelled + done + failed == frames.len() {
        "cancelled"
    } else if running > 0 || done > 0 {
        "running"
    } else {
        "queued"
    };
    let fraction =
        per.iter().map(|v| v["progress"]["fraction"].as_f64().unwrap_or(0.0)).sum::<f64>() / per.len() as f64;
    let started = frames.iter().filter_map(|j| j.started_ms).min();
    let finished = (state == "done").then(|| frames.iter().filter_map(|j| j.finished_ms).max()).flatten();
    let elapsed_ms = started.map(|s| finished.unwrap_or(now_ms()) - s);
    let eta_s = match elapsed_ms {
        Some(e) if fraction > 0.0 && state == "running" => Some(e as f64 / 1000.0 * (1.0 - fraction) / fraction),
        _ => None,
    };
    let worst = per
        .iter()
        .filter_map(|v| v["noise"]["estimated_rel_error"].as_f64())
        .fold(None, |m: Option<f64>, x| Some(m.map_or(x, |m| m.max(x))));
    let s = &first.spec.settings;
    json!({
        "id": id,
        "kind": "shot",
        "name": first.spec.name.rsplit_once(" frame ").map_or(first.spec.name.as_str(), |(n, _)| n),
        "state": state,
        "warnings": first.spec.warnings,
        "priority": first.spec.priority,
        "scene_hash": first.spec.scene_hash,
        "submitted_ms": first.submitted_ms,
        "started_ms": started,
        "finished_ms": finished,
        "elapsed_s": elapsed_ms.map(|e| e as f64 / 1000.0),
        "eta_s": eta_s,
        "frames": {
            "first": frames.first().map(|j| j.spec.settings.frame), "last": frames.last().map(|j| j.spec.settings.frame),
            "count": frames.len(), "done": done, "running": running, "failed": failed, "cancelled": cancelled,
        },
        "progress": { "fraction": fraction, "frames_done": done, "frames_total": frames.len() },
        "noise": { "worst_frame_rel_error": worst },
        "settings": s,
        "frame_jobs": per.iter().zip(frames).map(|(v, j)| json!({
            "frame": j.spec.settings.frame, "id": j.id, "state": v["state"], "progress": v["progress"]["fraction"],
            "elapsed_s": v["elapsed_s"], "estimated_rel_error": v["noise"]["estimated_rel_error"],
            "spp_mean": v["progress"]["spp_mean"], "stop": v["budget"]["stop"],
        })).collect::<Vec<_>>(),
    })
}

/// A job or a shot by id (with per-tile noise for a single job when `detail`).
fn entity_json(farm: &crate::state::Farm, id: &str, detail: bool) -> Option<Value> {
    if let Some(job) = farm.jobs.get(id) {
        let mut body = job_json(job);
        body["kind"] = json!("job");
        if detail {
            body["noise"]["tiles"] = tiles_json(job);
        }
        return Some(body);
    }
    let frames = farm.shot_frames(id);
    (!frames.is_empty()).then(|| shot_json(id, &frames))
}

async fn list_jobs(State(s): S) -> Json<Value> {
    Json(jobs_list(&s))
}

/// The job list (`GET /jobs`, and the `jobs` event of `GET /events`).
fn jobs_list(s: &Shared) -> Value {
    let farm = lock(&s.farm);
    // Single jobs, and each shot once (its frames are listed inside it).
    let mut out = Vec::new();
    let mut shots = std::collections::BTreeSet::new();
    for j in farm.jobs.values() {
        match &j.spec.shot {
            None => {
                let mut v = job_json(j);
                v["kind"] = json!("job");
                out.push(v);
            }
            Some(shot) => {
                if shots.insert(shot.clone()) {
                    out.push(shot_json(shot, &farm.shot_frames(shot)));
                }
            }
        }
    }
    json!({ "jobs": out })
}

async fn get_job(State(s): S, ApiExtract(Path(id)): ApiExtract<Path<String>>) -> Result<Json<Value>, ApiError> {
    let farm = lock(&s.farm);
    entity_json(&farm, &id, true).map(Json).ok_or_else(|| err(StatusCode::NOT_FOUND, format!("no job '{id}'")))
}

/// `GET /jobs/{id}/frames/{n}.exr`: one finished frame of a shot (frame 0 of a single job too).
async fn frame_image(
    State(s): S,
    ApiExtract(Path((id, file))): ApiExtract<Path<(String, String)>>,
) -> Result<Response, ApiError> {
    let n: u32 = file
        .strip_suffix(".exr")
        .and_then(|n| n.parse().ok())
        .ok_or_else(|| err(StatusCode::NOT_FOUND, format!("'{file}': frames are at frames/<number>.exr")))?;
    let job_id = {
        let farm = lock(&s.farm);
        let job = match farm.jobs.get(&id) {
            Some(j) if j.spec.settings.frame == n => Some(j),
            Some(_) => None,
            None => farm.shot_frames(&id).into_iter().find(|j| j.spec.settings.frame == n),
        };
        job.map(|j| j.id.clone()).ok_or_else(|| err(StatusCode::NOT_FOUND, format!("'{id}' has no frame {n}")))?
    };
    download(State(s), ApiExtract(Path(job_id))).await
}

/// `GET /jobs/{id}/frames.tar`: every finished frame of a shot as `frame.NNNN.exr` in one tar,
/// streamed a frame at a time (a long shot never sits in memory whole).
async fn frames_archive(State(s): S, ApiExtract(Path(id)): ApiExtract<Path<String>>) -> Result<Response, ApiError> {
    let frames: Vec<(u32, String)> = {
        let farm = lock(&s.farm);
        let list = farm.shot_frames(&id);
        if list.is_empty() {
            return Err(err(StatusCode::NOT_FOUND, format!("no shot '{id}'")));
        }
        list.iter().filter(|j| j.state == JobState::Done).map(|j| (j.spec.settings.frame, j.id.clone())).collect()
    };
    let (tx, rx) = tokio::sync::mpsc::channel::<Result<Bytes, std::io::Error>>(2);
    let shared = s.clone();
    tokio::task::spawn_blocking(move || {
        for (frame, job) in frames {
            let exr = match lock(&shared.store).image(&job) {
                Ok(Some(b)) => b,
                Ok(None) => continue,
                Err(e) => {
                    let _ = tx.blocking_send(Err(std::io::Error::other(e.to_string())));
                    return;
                }
            };
            let mut h = tar::Header::new_ustar();
            if h.set_path(format!("frame.{frame:04}.exr")).is_err() {
                continue;
            }
            h.set_size(exr.len() as u64);
            h.set_mode(0o644);
            h.set_cksum();
            let pad = (512 - exr.len() % 512) % 512;
            let mut chunk = Vec::with_capacity(512 + exr.len() + pad);
            chunk.extend_from_slice(h.as_bytes());
            chunk.extend_from_slice(&exr);
            chunk.resize(chunk.len() + pad, 0);
            if tx.blocking_send(Ok(Bytes::from(chunk))).is_err() {
                return;
            }
        }
        let _ = tx.blocking_send(Ok(Bytes::from(vec![0u8; 1024])));
    });
    let body = axum::body::Body::from_stream(tokio_stream::wrappers::ReceiverStream::new(rx));
    Ok((
        [
            (header::CONTENT_TYPE, "application/x-tar"),
            (header::CONTENT_DISPOSITION, "attachment; filename=\"frames.tar\""),
        ],
        body,
    )
        .into_response())
}

async fn cancel_job(State(s): S, ApiExtract(Path(id)): ApiExtract<Path<String>>) -> Result<Json<Value>, ApiError> {
    let ids = s.jobs_named(&id);
    if ids.is_empty() {
        return Err(err(StatusCode::NOT_FOUND, format!("no job '{id}'")));
    }
    let shared = s.clone();
    tokio::task::spawn_blocking(move || ids.iter().try_for_each(|i| shared.cancel_job(i)))
        .await
        .map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?
        .map_err(service_err)?;
    s.work_available.notify_waiters();
    let body =
        entity_json(&lock(&s.farm), &id, false).ok_or_else(|| err(StatusCode::NOT_FOUND, format!("no job '{id}'")))?;
    Ok(Json(body))
}

/// `DELETE /jobs/{id}`: removes the job and its data (cancelling it first if it still runs).
async fn delete_job(State(s): S, ApiExtract(Path(id)): ApiExtract<Path<String>>) -> Result<Json<Value>, ApiError> {
    let ids = s.jobs_named(&id);
    if ids.is_empty() {
        return Err(err(StatusCode::NOT_FOUND, format!("no job '{id}'")));
    }
    let shared = s.clone();
    tokio::task::spawn_blocking(move || {
        ids.iter().try_for_each(|i| {
            shared.cancel_job(i)?;
            shared.delete_job(i)
        })
    })
    .await
    .map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?
    .map_err(service_err)?;
    Ok(Json(json!({ "id": id, "deleted": true })))
}

async fn download(State(s): S, ApiExtract(Path(id)): ApiExtract<Path<String>>) -> Result<Response, ApiError> {
    let state = {
        let farm = lock(&s.farm);
        if !farm.jobs.contains_key(&id) && !farm.shot_frames(&id).is_empty() {
            return Err(err(
                StatusCode::CONFLICT,
                format!("'{id}' is a shot: its frames are at /frames/<n>.exr, all of them at /frames.tar"),
            ));
        }
        farm.jobs
            .get(&id)
            .map(|j| j.state.clone())
            .ok_or_else(|| err(StatusCode::NOT_FOUND, format!("no job '{id}'")))?
    };
    if state != JobState::Done {
        return Err(err(
            StatusCode::CONFLICT,
            format!("job '{id}' is {}, not done: no image yet (the preview is at /preview.png)", state.as_str()),
        ));
    }
    let shared = s.clone();
    let i = id.clone();
    let exr = tokio::task::spawn_blocking(move || lock(&shared.store).image(&i))
        .await
        .map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?
        .map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?
        .ok_or_else(|| err(StatusCode::NOT_FOUND, "image missing"))?;
    Ok(([(header::CONTENT_TYPE, "image/x-exr")], Bytes::from(exr)).into_response())
}

/// `preview.png?exposure=E&width=W`: exposure in stops (−20..20, default 0), and the largest
/// width wanted (the image is shrunk by a whole factor to fit; default: full size).
#[derive(serde::Deserialize)]
struct PreviewQuery {
    exposure: Option<f32>,
    width: Option<u32>,
}

async fn preview(
    State(s): S,
    ApiExtract(Path(id)): ApiExtract<Path<String>>,
    ApiExtract(Query(q)): ApiExtract<Query<PreviewQuery>>,
) -> Result<Response, ApiError> {
    let exposure = q.exposure.unwrap_or(0.0);
    if !(-20.0..=20.0).contains(&exposure) {
        return Err(err(
            StatusCode::UNPROCESSABLE_ENTITY,
            format!("exposure {exposure}: must be within -20..20 stops"),
        ));
    }
    if q.width == Some(0) {
        return Err(err(StatusCode::UNPROCESSABLE_ENTITY, "width 0: must be at least 1"));
    }
    // A running job's image is copied out under the lock and encoded outside it; a finished one's
    // preview was stored when it finished (its accumulation is no longer in memory): at another
    // exposure or size it is made from the stored EXR.
    let (image, done) = {
        let farm = lock(&s.farm);
        let job = farm.jobs.get(&id).ok_or_else(|| err(StatusCode::NOT_FOUND, format!("no job '{id}'")))?;
        ((!job.state.is_final()).then(|| job.image()), job.state == JobState::Done)
    };
    let shared = s.clone();
    let png = tokio::task::spawn_blocking(move || -> Result<Vec<u8>, ApiError> {
        let internal = |e: String| err(StatusCode::INTERNAL_SERVER_ERROR, e);
        let encode = |img: FinalImage| {
            let img = match q.width {
                Some(w) => img.downscaled(w),
                None => img,
            };
            img.png_bytes(exposure).map_err(internal)
        };
        match image {
            Some(img) => encode(FinalImage::from_sums(&img)),
            None if done && (exposure != 0.0 || q.width.is_some()) => {
                let exr = lock(&shared.store)
                    .image(&id)
                    .map_err(|e| internal(e.to_string()))?
                    .ok_or_else(|| err(StatusCode::NOT_FOUND, format!("job '{id}' has no stored image")))?;
                encode(FinalImage::from_exr_bytes(&exr).map_err(internal)?)
            }
            None => lock(&shared.store)
                .preview(&id)
                .map_err(|e| internal(e.to_string()))?
                .ok_or_else(|| err(StatusCode::NOT_FOUND, format!("job '{id}' has no stored preview"))),
        }
    })
    .await
    .map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))??;
    Ok(([(header::CONTENT_TYPE, "image/png")], Bytes::from(png)).into_response())
}

/// `GET /jobs/{id}/events?after=SEQ`: the job's log, oldest first (at most 1000 a call; page on
/// with `after` = the last `seq`). For a shot, every frame's log, each event naming its frame job.
#[derive(serde::Deserialize)]
struct EventsQuery {
    after: Option<i64>,
}

async fn job_events(
    State(s): S,
    ApiExtract(Path(id)): ApiExtract<Path<String>>,
    ApiExtract(Query(q)): ApiExtract<Query<EventsQuery>>,
) -> Result<Json<Value>, ApiError> {
    let ids = s.jobs_named(&id);
    if ids.is_empty() {
        return Err(err(StatusCode::NOT_FOUND, format!("no job '{id}'")));
    }
    let shared = s.clone();
    let after = q.after.unwrap_or(0);
    let events = tokio::task::spawn_blocking(move || -> Result<Vec<Value>, ApiError> {
        let store = lock(&shared.store);
        let mut out = Vec::new();
        for job in &ids {
            for e in
                store.events(job, after, 1000).map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?
            {
                let mut v = serde_json::to_value(&e).unwrap_or(Value::Null);
                v["job"] = json!(job);
                out.push(v);
            }
        }
        out.sort_by_key(|v| v["seq"].as_i64().unwrap_or(0));
        out.truncate(1000);
        Ok(out)
    })
    .await
    .map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))??;
    Ok(Json(json!({ "events": events })))
}

/// `POST /jobs/{id}/resubmit`: a new job with the same scene, settings and priority (retry a
/// failed job, render a cancelled one again, or repeat a finished one under a new seed by editing
/// nothing: the settings are copied as they are, so the result is the same image).
async fn resubmit_job(
    State(s): S,
    ApiExtract(Path(id)): ApiExtract<Path<String>>,
) -> Result<(StatusCode, Json<Value>), ApiError> {
    let spec = {
        let farm = lock(&s.farm);
        match farm.jobs.get(&id) {
            Some(j) => j.spec.clone(),
            None if !farm.shot_frames(&id).is_empty() => {
                return Err(err(
                    StatusCode::CONFLICT,
                    format!(
                        "'{id}' is a shot: resubmit its frame jobs ({id}-f<n>) one by one, or submit the shot again"
                    ),
                ))
            }
            None => return Err(err(StatusCode::NOT_FOUND, format!("no job '{id}'"))),
        }
    };
    let spec = JobSpec { shot: None, ..spec };
    let shared = s.clone();
    let hash = spec.scene_hash.clone();
    let new_id = tokio::task::spawn_blocking(move || -> Result<String, ApiError> {
        let scene = lock(&shared.store)
            .scene(&hash)
            .map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?
            .ok_or_else(|| err(StatusCode::GONE, "the job's scene is no longer stored"))?;
        shared.submit_job(spec, &scene).map_err(service_err)
    })
    .await
    .map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))??;
    s.event(&new_id, "resubmitted", &format!("a copy of {id}"));
    Ok((StatusCode::CREATED, Json(json!({ "id": new_id, "resubmitted_from": id }))))
}

/// What `GET /events` streams: each list (as `GET /jobs` and `GET /workers` return it) with a
/// version that grows when it is republished.
#[derive(Clone, Default)]
pub struct LiveLists {
    pub jobs: (u64, Arc<str>),
    pub workers: (u64, Arc<str>),
}

/// Makes the lists `GET /events` streams, once a second and once for all its clients (none are
/// made while nobody listens). A list is republished when it changed — the fields that change with
/// the clock alone do not count — and at least every 15 s, which is also how a client that went
/// away is noticed.
pub async fn publish_live_lists(s: Arc<Shared>) {
    // Without the fields that change with the clock alone.
    fn steady(mut v: Value, list: &str, clock: &[&str]) -> Value {
        for item in v[list].as_array_mut().into_iter().flatten() {
            if let Some(o) = item.as_object_mut() {
                for f in clock {
                    o.remove(*f);
                }
            }
        }
        v
    }
    let mut last = [Value::Null, Value::Null];
    let mut tick = tokio::time::interval(std::time::Duration::from_secs(1));
    for n in 0u64.. {
        tick.tick().await;
        if s.live.receiver_count() == 0 {
            last = [Value::Null, Value::Null];
            continue;
        }
        let mut lists = s.live.borrow().clone();
        // Each list: its name (the key of its array), the list now, its clock fields, its slot.
        type Feed<'a> = (&'static str, Value, &'static [&'static str], &'a mut (u64, Arc<str>));
        let feeds: [Feed; 2] = [
            ("jobs", jobs_list(&s), &["elapsed_s", "eta_s"], &mut lists.jobs),
            ("workers", workers_list(&s), &["seconds_since_seen", "last_seen_ms"], &mut lists.workers),
        ];
        let mut changed = false;
        for ((name, value, clock, slot), last) in feeds.into_iter().zip(&mut last) {
            let now = steady(value.clone(), name, clock);
            if n.is_multiple_of(15) || now != *last {
                *last = now;
                *slot = (slot.0 + 1, value.to_string().into());
                changed = true;
            }
        }
        if changed {
            s.live.send_replace(lists);
        }
    }
}

/// Most clients of `GET /events` at once (each holds a connection; more get 503).
pub const MAX_EVENT_STREAMS: usize = 64;

/// `GET /events`: server-sent events for pages that stay open. A `jobs` event carries what
/// `GET /jobs` returns and a `workers` event what `GET /workers` returns, each sent when it changed
/// (see [`publish_live_lists`]). The page then downloads a preview only when a job's
/// `preview_version` changed, instead of polling everything.
async fn live_events(State(s): S) -> Result<Response, ApiError> {
    use axum::response::sse::{Event, KeepAlive, Sse};
    use std::sync::atomic::Ordering;
    static STREAMS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    if STREAMS.fetch_add(1, Ordering::SeqCst) >= MAX_EVENT_STREAMS {
        STREAMS.fetch_sub(1, Ordering::SeqCst);
        return Err(err(
            StatusCode::SERVICE_UNAVAILABLE,
            format!("{MAX_EVENT_STREAMS} event streams are open: poll GET /jobs instead"),
        ));
    }
    let (tx, rx) = tokio::sync::mpsc::channel::<Result<Event, std::convert::Infallible>>(4);
    let mut lists = s.live.subscribe();
    tokio::spawn(async move {
        struct Release;
        impl Drop for Release {
            fn drop(&mut self) {
                STREAMS.fetch_sub(1, Ordering::SeqCst);
            }
        }
        let _release = Release;
        let mut sent = [0u64; 2];
        loop {
            let now = lists.borrow_and_update().clone();
            for ((name, (version, data)), sent) in
                [("jobs", now.jobs), ("workers", now.workers)].into_iter().zip(&mut sent)
            {
                if version > *sent {
                    *sent = version;
                    if tx.send(Ok(Event::default().event(name).data(&*data))).await.is_err() {
                        return;
                    }
                }
            }
            if lists.changed().await.is_err() {
                return;
            }
        }
    });
    let stream = tokio_stream::wrappers::ReceiverStream::new(rx);
    Ok(Sse::new(stream).keep_alive(KeepAlive::default()).into_response())
}

/// A worker's state: `offline` when not seen for three lease periods (it died or lost the
/// network; its units are re-leased), `draining` when an operator stopped giving it work, `busy`
/// while it holds units, else `idle`.
fn worker_state(seconds_since_seen: f64, lease_s: f64, draining: bool, holds: bool) -> &'static str {
    if seconds_since_seen > 3.0 * lease_s {
        "offline"
    } else if draining {
        "draining"
    } else if holds {
        "busy"
    } else {
        "idle"
    }
}

async fn list_workers(State(s): S) -> Json<Value> {
    Json(workers_list(&s))
}

/// The worker list (`GET /workers`, and the `workers` event of `GET /events`).
fn workers_list(s: &Shared) -> Value {
    let now = now_ms();
    let held = lock(&s.farm).units_held();
    let lease_s = s.config.lease.as_secs_f64();
    let workers = lock(&s.workers);
    let mut list: Vec<Value> = workers
        .values()
        .map(|w| {
            let mut v = serde_json::to_value(w).unwrap_or(Value::Null);
            let since = (now - w.last_seen_ms) as f64 / 1000.0;
            let units = held.get(&w.id).cloned().unwrap_or_default();
            v["seconds_since_seen"] = json!(since);
            v["state"] = json!(worker_state(since, lease_s, w.draining, !units.is_empty()));
            v["current_job"] = json!(units.first().map(|(j, _)| j.clone()));
            v["current_units"] = json!(units.iter().map(|(_, u)| u.clone()).collect::<Vec<_>>());
            v
        })
        .collect();
    list.sort_by(|a, b| a["id"].as_str().cmp(&b["id"].as_str()));
    json!({ "workers": list })
}

/// `POST /workers/{id}/drain` and `/resume`: stop (or restart) giving a worker new units; what it
/// holds it finishes.
fn set_draining(s: &Shared, id: &str, draining: bool) -> Result<Json<Value>, ApiError> {
    let mut workers = lock(&s.workers);
    let w = workers.get_mut(id).ok_or_else(|| err(StatusCode::NOT_FOUND, format!("no worker '{id}'")))?;
    w.draining = draining;
    tracing::info!(worker = %id, draining, "worker drain changed");
    Ok(Json(json!({ "id": id, "draining": draining })))
}

async fn drain_worker(State(s): S, ApiExtract(Path(id)): ApiExtract<Path<String>>) -> Result<Json<Value>, ApiError> {
    set_draining(&s, &id, true)
}

async fn resume_worker(State(s): S, ApiExtract(Path(id)): ApiExtract<Path<String>>) -> Result<Json<Value>, ApiError> {
    let r = set_draining(&s, &id, false);
    s.work_available.notify_waiters();
    r
}

/// A job's share of the queue depth: its pending units, at most two passes over its tiles. A
/// noise-target job plans its whole sample cap (up to 65536 spp) but stops long before; counting
/// that as work would scale a farm to its maximum for one small job.
fn queue_depth(pending: usize, tiles: usize) -> usize {
    pending.min(2 * tiles)
}

async fn metrics(State(s): S) -> Response {
    let mut out = String::new();
    let farm = lock(&s.farm);
    for state in ["queued", "running", "done", "failed", "cancelled"] {
        let n = farm.jobs.values().filter(|j| j.state.as_str() == state).count();
        out += &format!("tessera_jobs{{state=\"{state}\"}} {n}\n");
    }
    let (mut leased, mut done, mut total, mut depth) = (0, 0, 0, 0);
    for j in farm.jobs.values().filter(|j| !j.state.is_final()) {
        leased += j.units_leased();
        done += j.units_done();
        total += j.unit_count();
        depth += queue_depth(j.unit_count().saturating_sub(j.units_done() + j.units_leased()), j.tiles.len());
    }
    drop(farm);
    out += &format!("# HELP tessera_queue_depth Units workers could take now (per job at most two passes' worth: a noise-target job's sample cap is not work). The autoscaling signal.\n# TYPE tessera_queue_depth gauge\ntessera_queue_depth {depth}\n");
    out += &format!("tessera_units{{state=\"leased\"}} {leased}\ntessera_units{{state=\"done\"}} {done}\ntessera_units{{state=\"pending\"}} {}\n", total - done - leased);
    let now = now_ms();
    let live = lock(&s.workers).values().filter(|w| now - w.last_seen_ms < 60_000).count();
    out += &format!("tessera_workers {live}\n");
    let m = lock(&s.metrics);
    let up = s.started.elapsed().as_secs_f64().max(1e-3);
    out += &format!(
        "tessera_units_merged_total {}\ntessera_units_rejected_total {}\ntessera_leases_expired_total {}\ntessera_samples_merged_total {}\ntessera_samples_per_second {:.1}\ntessera_merge_seconds_sum {:.6}\ntessera_merge_seconds_count {}\ntessera_results_refused_not_leased_total {}\ntessera_heartbeats_refused_total {}\ntessera_storage_errors_total {}\n",
        m.units_merged, m.units_rejected, m.units_expired, m.samples_merged, m.samples_merged as f64 / up, m.merge_seconds_sum, m.units_merged,
        m.results_forged, m.heartbeats_refused, m.storage_errors
    );
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], out).into_response()
}

#[cfg(test)]
mod tests {
    use renderer::settings_request::{SettingsRequest, FIELDS};
    use serde_json::Value;

    /// A request with every field set, to list the schema's field names.
    fn full_request() -> SettingsRequest {
        serde_json::from_str(
            r#"{"name":"n","priority":1,"spp":1,"width":1,"height":1,"camera":0,"integrator":"mis","mis_heuristic":"power",
               "sampler":"sobol","seed":1,"max_depth":1,"rr_depth":1,"filter":"box","env_color":[1,1,1],"env_strength":1,
               "env_rotate":0,"env_sampling":true,"light_sampler":"auto","pass_spp":1,"time_budget":1,"noise_target":0.1,"min_spp":2,
               "frames":"0-3","fps":24,"animation":"walk"}"#,
        )
        .expect("every field")
    }

    /// A noise-target job's progress counts tiles that met the target as done, not the 1/4 of their
    /// sample cap they used (issue 14: "ETA 14 700 s and a bar near 0 %" for a 75 s job).
    #[test]
    fn noise_target_progress_counts_converged_tiles() {
        use crate::state::{Job, JobSpec, JobState};
        use renderer::film::{PartialSums, Rect};
        let settings = renderer::RenderSettings {
            width: 64,
            height: 32,
            spp: 64,
            pass_spp: 16,
            min_spp: 2,
            noise_target: Some(0.05),
            ..Default::default()
        };
        let spec =
            JobSpec { name: "n".into(), scene_hash: "h".into(), settings, priority: 0, warnings: vec![], shot: None };
        let mut job = Job::new("j".into(), spec, 0);
        job.state = JobState::Running;
        job.started_ms = Some(super::now_ms() - 10_000);
        // Tile 0: one pass of a noiseless constant: it meets the target at once. Tile 1: nothing yet.
        let rect = Rect { x0: 0, y0: 0, width: 32, height: 32 };
        let mut sums = PartialSums::new(rect);
        for i in 0..rect.pixels() {
            for _ in 0..16 {
                sums.add_sample(i, renderer::math::Vec3::splat(0.5));
            }
        }
        job.restore_tile(0, 1, sums);
        let (done, total) = job.samples_progress();
        let v = super::job_json(&job);
        let fraction = v["progress"]["fraction"].as_f64().expect("fraction");
        assert!((done as f64 / total as f64 - 0.2).abs() < 1e-9, "{done}/{total}");
        assert!((fraction - 0.5).abs() < 1e-9, "half the pixels met the target: {fraction}");
        assert!(v["eta_s"].as_f64().expect("eta") < 11.0, "{v}");
    }

    #[test]
    fn queue_depth_counts_at_most_two_passes_a_job() {
        assert_eq!(super::queue_depth(5, 16), 5);
        assert_eq!(super::queue_depth(65536 * 16, 16), 32);
        assert_eq!(super::queue_depth(0, 16), 0);
    }

    /// The OpenAPI document's settings schema is checked against the one settings schema
    /// (renderer/src/settings_request.rs): same fields, same bounds, same defaults.
    #[test]
    fn openapi_settings_match_the_settings_schema() {
        let doc: Value = serde_json::from_str(super::OPENAPI).expect("openapi.json parses");
        let props = doc["components"]["schemas"]["Settings"]["properties"].as_object().expect("Settings properties");
        let full = serde_json::to_value(full_request()).expect("encodes");
        let mut ours: Vec<&String> = full.as_object().expect("object").keys().collect();
        let mut theirs: Vec<&String> = props.keys().collect();
        ours.sort();
        theirs.sort();
        assert_eq!(ours, theirs, "OpenAPI settings properties differ from SettingsRequest's fields");
        for f in FIELDS {
            let p = &props[f.name];
            assert_eq!(p["minimum"].as_f64(), Some(f.min), "{}: minimum", f.name);
            assert_eq!(p["maximum"].as_f64(), Some(f.max), "{}: maximum", f.name);
            assert_eq!(p.get("default").and_then(Value::as_f64), f.default, "{}: default", f.name);
        }
    }

    /// Every token-guarded operation documents its 401, and every one with a query parameter its
    /// 400 (`ApiExtract`), each with the JSON error body the coordinator sends.
    #[test]
    fn openapi_documents_the_refusals_every_route_can_give() {
        let doc: Value = serde_json::from_str(super::OPENAPI).expect("openapi.json parses");
        let error = serde_json::json!({ "application/json": { "schema": { "$ref": "#/components/schemas/Error" } } });
        for (path, ops) in doc["paths"].as_object().expect("paths") {
            for (method, op) in ops.as_object().expect("operations").iter().filter(|(m, _)| *m != "parameters") {
                let responses = &op["responses"];
                if !path.ends_with("openapi.json") {
                    assert_eq!(responses["401"]["content"], error, "{method} {path}: 401");
                }
                let queries = op["parameters"].as_array().into_iter().flatten().filter(|p| p["in"] == "query");
                if queries.count() > 0 {
                    assert_eq!(responses["400"]["content"], error, "{method} {path}: 400");
                }
            }
        }
    }
}
