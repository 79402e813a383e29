//! The REST API (`/api/v1`, JSON, bearer token), the web page, `/metrics` and the OpenAPI document.

use crate::state::{Job, JobSpec, JobState};
use crate::{lock, now_ms, Shared};
use axum::body::Bytes;
use axum::extract::{DefaultBodyLimit, Multipart, Path, State};
use axum::http::{header, StatusCode};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use renderer::bundle::SceneBundle;
use renderer::image_io::FinalImage;
use renderer::sampler::SamplerKind;
use renderer::{IntegratorKind, MisHeuristic, PixelFilter, RenderSettings};
use serde_json::{json, Value};
use sha2::Digest;
use std::sync::Arc;

pub const OPENAPI: &str = include_str!("openapi.json");

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

pub fn router(shared: Arc<Shared>) -> Router {
    let limit = shared.config.limits.max_upload_bytes;
    let api = Router::new()
        .route("/jobs", post(submit).get(list_jobs))
        .route("/jobs/{id}", get(get_job).delete(cancel_job))
        .route("/jobs/{id}/cancel", post(cancel_job))
        .route("/jobs/{id}/image.exr", get(download))
        .route("/jobs/{id}/preview.png", get(preview))
        .route("/workers", get(list_workers))
        .layer(axum::middleware::from_fn_with_state(shared.clone(), auth))
        .layer(DefaultBodyLimit::max(limit));
    Router::new()
        .route("/", get(|| async { Html(crate::web::PAGE) }))
        .route("/api/v1/openapi.json", get(|| async { ([(header::CONTENT_TYPE, "application/json")], OPENAPI) }))
        .route("/metrics", get(metrics))
        .route("/healthz", get(|| async { "ok" }))
        .nest("/api/v1", api)
        .with_state(shared)
}

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

/// Render settings a client may send; unknown fields are refused.
#[derive(serde::Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct SubmitSettings {
    name: Option<String>,
    priority: Option<i32>,
    spp: Option<u32>,
    width: Option<u32>,
    height: Option<u32>,
    camera: Option<usize>,
    integrator: Option<IntegratorKind>,
    mis_heuristic: Option<MisHeuristic>,
    sampler: Option<SamplerKind>,
    seed: Option<u64>,
    max_depth: Option<u32>,
    rr_depth: Option<u32>,
    filter: Option<PixelFilter>,
    env_color: Option<[f32; 3]>,
    env_strength: Option<f32>,
    env_rotate: Option<f32>,
    env_sampling: Option<bool>,
    light_sampler: Option<renderer::light::LightSamplerKind>,
    pass_spp: Option<u32>,
    /// Seconds; with it (or a noise target) `spp` is a cap, by default the farm's spp limit.
    time_budget: Option<f64>,
    /// Relative standard error each tile must reach (adaptive sampling).
    noise_target: Option<f64>,
    min_spp: Option<u32>,
}

async fn submit(State(s): S, mut form: Multipart) -> Result<(StatusCode, Json<Value>), ApiError> {
    let limits = s.config.limits.clone();
    if lock(&s.farm).queued_jobs() >= limits.max_queued_jobs {
        return Err(err(
            StatusCode::TOO_MANY_REQUESTS,
            format!("the queue holds the maximum of {} unfinished jobs", limits.max_queued_jobs),
        ));
    }
    let mut files: Vec<(String, Vec<u8>)> = Vec::new();
    let mut settings = SubmitSettings::default();
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

    // Check the scene loads here, so a broken file is refused now rather than failing on workers.
    let dir = s.config.data_dir.join("tmp").join(format!("upload-{}-{}", now_ms(), std::process::id()));
    let b = bundle.clone();
    let d = dir.clone();
    let env_default = renderer::environment::EnvironmentSettings::default();
    let environment = renderer::environment::EnvironmentSettings {
        map: env_map,
        color: settings.env_color,
        strength: settings.env_strength.unwrap_or(env_default.strength),
        rotate_deg: settings.env_rotate.unwrap_or(env_default.rotate_deg),
        sampling: settings.env_sampling.unwrap_or(env_default.sampling),
    };
    let env = environment.clone();
    let loaded = tokio::task::spawn_blocking(move || -> Result<Option<f32>, String> {
        let main = b.unpack(&d).map_err(|e| format!("cannot unpack the scene: {e}"))?;
        let strip = |e: String| e.replace(&format!("{}/", d.display()), "");
        let mut scene = renderer::gltf_loader::load(&main).map_err(|e| strip(e.to_string()))?;
        scene.attach_environment(&env, &d).map_err(|e| strip(e.to_string()))?;
        Ok(scene.camera(None).ok().and_then(|c| c.aspect_ratio))
    })
    .await
    .map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
    let _ = std::fs::remove_dir_all(&dir);
    let aspect = loaded.map_err(|e| err(StatusCode::UNPROCESSABLE_ENTITY, e))?;

    let d = RenderSettings::default();
    let (width, height) = renderer::settings::image_size(aspect, settings.width, settings.height);
    let rs = RenderSettings {
        width,
        height,
        spp: settings.spp.unwrap_or(if settings.time_budget.is_some() || settings.noise_target.is_some() {
            limits.max_spp.min(renderer::budget::BUDGET_SPP_CAP)
        } else {
            d.spp
        }),
        pass_spp: settings.pass_spp.unwrap_or(d.pass_spp),
        integrator: settings.integrator.unwrap_or(d.integrator),
        mis_heuristic: settings.mis_heuristic.unwrap_or(d.mis_heuristic),
        sampler: settings.sampler.unwrap_or(d.sampler),
        seed: settings.seed.unwrap_or(d.seed),
        max_depth: settings.max_depth.unwrap_or(d.max_depth),
        rr_depth: settings.rr_depth.unwrap_or(d.rr_depth),
        camera: settings.camera,
        filter: settings.filter.unwrap_or(d.filter),
        environment,
        light_sampler: settings.light_sampler.unwrap_or(d.light_sampler),
        noise_target: settings.noise_target,
        min_spp: settings.min_spp.unwrap_or(d.min_spp),
        time_budget: settings.time_budget,
    };
    rs.validate().map_err(|e| err(StatusCode::UNPROCESSABLE_ENTITY, e))?;
    if rs.width > limits.max_side || rs.height > limits.max_side {
        return Err(err(
            StatusCode::UNPROCESSABLE_ENTITY,
            format!("resolution {}x{} exceeds this farm's limit of {} per side", rs.width, rs.height, limits.max_side),
        ));
    }
    if rs.spp > limits.max_spp {
        return Err(err(
            StatusCode::UNPROCESSABLE_ENTITY,
            format!("spp {} exceeds this farm's limit of {}", rs.spp, limits.max_spp),
        ));
    }
    let encoded = bundle.encode();
    let hash = hex::encode(sha2::Sha256::digest(&encoded));
    let id = format!("j{}", now_ms());
    let id = {
        let farm = lock(&s.farm);
        let mut id = id;
        while farm.jobs.contains_key(&id) {
            id.push('x');
        }
        id
    };
    let spec = JobSpec {
        name: settings.name.unwrap_or_else(|| bundle.main.clone()),
        scene_hash: hash,
        settings: rs,
        priority: settings.priority.unwrap_or(0),
    };
    let job = Job::new(id.clone(), spec, now_ms());
    {
        let store = lock(&s.store);
        store
            .put_scene(&job.spec.scene_hash, &encoded)
            .map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
        store.put_job(&job).map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
    }
    let body = job_json(&job);
    lock(&s.farm).add_job(job);
    s.work_available.notify_waiters();
    tracing::info!(job = %id, "job submitted");
    Ok((StatusCode::CREATED, Json(body)))
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
    let mut eta_s = match (elapsed_ms, j.state.is_final()) {
        (Some(e), false) if fraction > 0.0 => Some(e as f64 / 1000.0 * (1.0 - fraction) / fraction),
        _ => None,
    };
    // A time budget bounds the job: progress is at least the budget's share spent.
    if let (Some(b), Some(e), false) = (s.time_budget, elapsed_ms, j.state.is_final()) {
        let spent = e as f64 / 1000.0;
        fraction = fraction.max((spent / b).min(1.0));
        eta_s = Some(eta_s.unwrap_or(f64::INFINITY).min((b - spent).max(0.0)));
    }
    let noise = j.noise();
    let worst = renderer::noise::worst(&j.tile_sums);
    json!({
        "id": j.id,
        "name": j.spec.name,
        "state": j.state.as_str(),
        "error": j.error,
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
    })
}

/// Per-tile noise of a job (only on the single-job resource: a large image has thousands of tiles).
fn tiles_json(j: &Job) -> Value {
    let tiles: Vec<Value> = j
        .tile_sums
        .iter()
        .zip(j.folded.iter().zip(&j.planned))
        .map(|(t, (f, p))| {
            let e = renderer::noise::estimate(t);
            json!({
                "x0": t.rect.x0, "y0": t.rect.y0, "width": t.rect.width, "height": t.rect.height,
                "spp": e.spp_max, "passes_done": f, "passes_planned": p,
                "rel_error": e.rel_error.is_finite().then_some(e.rel_error),
            })
        })
        .collect();
    Value::Array(tiles)
}

async fn list_jobs(State(s): S) -> Json<Value> {
    let farm = lock(&s.farm);
    Json(json!({ "jobs": farm.jobs.values().map(job_json).collect::<Vec<_>>() }))
}

async fn get_job(State(s): S, Path(id): Path<String>) -> Result<Json<Value>, ApiError> {
    let farm = lock(&s.farm);
    let job = farm.jobs.get(&id).ok_or_else(|| err(StatusCode::NOT_FOUND, format!("no job '{id}'")))?;
    let mut body = job_json(job);
    body["noise"]["tiles"] = tiles_json(job);
    Ok(Json(body))
}

async fn cancel_job(State(s): S, Path(id): Path<String>) -> Result<Json<Value>, ApiError> {
    let mut farm = lock(&s.farm);
    let job = farm.cancel(&id, now_ms()).ok_or_else(|| err(StatusCode::NOT_FOUND, format!("no job '{id}'")))?;
    let body = job_json(job);
    if job.state == JobState::Cancelled {
        let _ = lock(&s.store).update_job_state(job);
    }
    Ok(Json(body))
}

async fn download(State(s): S, Path(id): Path<String>) -> Result<Response, ApiError> {
    let state = lock(&s.farm)
        .jobs
        .get(&id)
        .map(|j| j.state.clone())
        .ok_or_else(|| err(StatusCode::NOT_FOUND, format!("no job '{id}'")))?;
    if state != JobState::Done {
        return Err(err(
            StatusCode::CONFLICT,
            format!("job '{id}' is {}, not done: no image yet (the preview is at /preview.png)", state.as_str()),
        ));
    }
    let exr = lock(&s.store)
        .image(&id)
        .map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?
        .ok_or_else(|| err(StatusCode::NOT_FOUND, "image missing"))?;
    Ok(([(header::CONTENT_TYPE, "image/x-exr")], Bytes::from(exr)).into_response())
}

async fn preview(State(s): S, Path(id): Path<String>) -> Result<Response, ApiError> {
    let img = {
        let farm = lock(&s.farm);
        let job = farm.jobs.get(&id).ok_or_else(|| err(StatusCode::NOT_FOUND, format!("no job '{id}'")))?;
        FinalImage::from_sums(&job.image())
    };
    let png = img.png_bytes(0.0).map_err(|e| err(StatusCode::INTERNAL_SERVER_ERROR, e))?;
    Ok(([(header::CONTENT_TYPE, "image/png")], Bytes::from(png)).into_response())
}

async fn list_workers(State(s): S) -> Json<Value> {
    let now = now_ms();
    let workers = lock(&s.workers);
    let mut list: Vec<Value> = workers
        .values()
        .map(|w| {
            let mut v = serde_json::to_value(w).unwrap_or(Value::Null);
            v["seconds_since_seen"] = json!((now - w.last_seen_ms) as f64 / 1000.0);
            v
        })
        .collect();
    list.sort_by(|a, b| a["id"].as_str().cmp(&b["id"].as_str()));
    Json(json!({ "workers": list }))
}

async fn metrics(State(s): S) -> Response {
    let mut out = String::new();
    let farm = lock(&s.farm);
    for state in ["queued", "running", "done", "failed", "cancelled"] {
        let n = farm.jobs.values().filter(|j| j.state.as_str() == state).count();
        out += &format!("tessera_jobs{{state=\"{state}\"}} {n}\n");
    }
    let (mut leased, mut done, mut total) = (0, 0, 0);
    for j in farm.jobs.values().filter(|j| !j.state.is_final()) {
        leased += j.units_leased();
        done += j.units_done();
        total += j.unit_count();
    }
    drop(farm);
    out += &format!("tessera_units{{state=\"leased\"}} {leased}\ntessera_units{{state=\"done\"}} {done}\ntessera_units{{state=\"pending\"}} {}\n", total - done - leased);
    let now = now_ms();
    let live = lock(&s.workers).values().filter(|w| now - w.last_seen_ms < 60_000).count();
    out += &format!("tessera_workers {live}\n");
    let m = lock(&s.metrics);
    let up = s.started.elapsed().as_secs_f64().max(1e-3);
    out += &format!(
        "tessera_units_merged_total {}\ntessera_units_rejected_total {}\ntessera_leases_expired_total {}\ntessera_samples_merged_total {}\ntessera_samples_per_second {:.1}\ntessera_merge_seconds_sum {:.6}\ntessera_merge_seconds_count {}\n",
        m.units_merged, m.units_rejected, m.units_expired, m.samples_merged, m.samples_merged as f64 / up, m.merge_seconds_sum, m.units_merged
    );
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], out).into_response()
}
