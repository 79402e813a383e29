//! The coordinator's service layer: the operations REST and gRPC handlers call (submit, cancel,
//! delete, lease, accept a result), each owning its locking and persistence, so handlers stay thin
//! adapters that translate requests and errors.
//!
//! Lock order (never take an earlier lock while holding a later one): `farm` → `store` → `workers`
//! → `metrics`. Slow work (scene parsing, EXR encoding, image blobs) happens outside `farm`.

use crate::state::{Job, JobSpec};
use crate::store::StoreError;
use crate::{lock, now_ms, Shared};

/// Why an operation was refused; `status()` is its HTTP status.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    #[error("the queue holds the maximum of {0} unfinished jobs")]
    QueueFull(usize),
    #[error("no job '{0}'")]
    NoJob(String),
    #[error("{0}")]
    Conflict(String),
    #[error("storage: {0}")]
    Storage(#[from] StoreError),
}

impl ServiceError {
    pub fn status(&self) -> u16 {
        match self {
            ServiceError::QueueFull(_) => 429,
            ServiceError::NoJob(_) => 404,
            ServiceError::Conflict(_) => 409,
            ServiceError::Storage(e) if e.is_disk_full() => 507,
            ServiceError::Storage(_) => 503,
        }
    }
}

impl Shared {
    /// Stores the scene (deduplicated by hash) and the job, and queues it. The queue limit is
    /// checked under the farm lock together with the insert, so concurrent submissions cannot
    /// overshoot it; the id is fresh (`new_id`) and the row insert fails rather than replace on a
    /// clash, in which case another id is drawn.
    pub fn submit_job(&self, spec: JobSpec, scene: &[u8]) -> Result<String, ServiceError> {
        // The (large) scene blob first, without the farm lock: a duplicate upload is a no-op.
        lock(&self.store).put_scene(&spec.scene_hash, scene)?;
        let mut farm = lock(&self.farm);
        let max = self.config.limits.max_queued_jobs;
        if farm.queued_jobs() >= max {
            return Err(ServiceError::QueueFull(max));
        }
        let mut tries = 0;
        let job = loop {
            let id = crate::new_id("j");
            if farm.jobs.contains_key(&id) {
                continue;
            }
            let mut job = Job::new(id, spec.clone(), now_ms());
            job.scene_size = scene.len() as u64;
            match lock(&self.store).insert_job(&job) {
                Ok(()) => break job,
                Err(e) if e.is_conflict() && tries < 8 => tries += 1,
                Err(e) => return Err(e.into()),
            }
        };
        let id = job.id.clone();
        tracing::info!(job = %id, name = %job.spec.name, width = job.spec.settings.width, height = job.spec.settings.height, "job submitted");
        self.event(&id, "submitted", &submitted_detail(&job));
        farm.add_job(job);
        drop(farm);
        self.work_available.notify_waiters();
        Ok(id)
    }

    /// Submits a shot: one frame job per frame of `frames` (ids `<shot>-f<frame>`), each the job
    /// `tessera render --frame N` would be. All are stored before any is scheduled; if storing one
    /// fails, the ones stored are removed again.
    pub fn submit_shot(
        &self,
        spec: JobSpec,
        frames: renderer::frames::FrameRange,
        scene: &[u8],
    ) -> Result<String, ServiceError> {
        lock(&self.store).put_scene(&spec.scene_hash, scene)?;
        let mut farm = lock(&self.farm);
        let max = self.config.limits.max_queued_jobs;
        if farm.queued_jobs() >= max {
            return Err(ServiceError::QueueFull(max));
        }
        let shot = loop {
            let id = crate::new_id("s");
            if !farm.jobs.keys().any(|k| k.starts_with(&id)) {
                break id;
            }
        };
        let mut jobs = Vec::with_capacity(frames.count() as usize);
        for frame in frames.iter() {
            let mut settings = spec.settings.clone();
            settings.frame = frame;
            let child = JobSpec {
                name: format!("{} frame {frame}", spec.name),
                settings,
                shot: Some(shot.clone()),
                ..spec.clone()
            };
            let mut job = Job::new(format!("{shot}-f{frame}"), child, now_ms());
            job.scene_size = scene.len() as u64;
            if let Err(e) = lock(&self.store).insert_job(&job) {
                for j in &jobs {
                    let j: &Job = j;
                    let _ = lock(&self.store).delete_job(&j.id, None);
                }
                return Err(e.into());
            }
            jobs.push(job);
        }
        tracing::info!(shot = %shot, name = %spec.name, frames = %frames, "shot submitted");
        for job in jobs {
            self.event(
                &job.id,
                "submitted",
                &format!("frame {} of shot {shot}: {}", job.spec.settings.frame, submitted_detail(&job)),
            );
            farm.add_job(job);
        }
        drop(farm);
        self.work_available.notify_waiters();
        Ok(shot)
    }

    /// The jobs an id names: the job itself, or every frame job of a shot.
    pub fn jobs_named(&self, id: &str) -> Vec<String> {
        let farm = lock(&self.farm);
        if farm.jobs.contains_key(id) {
            return vec![id.to_string()];
        }
        farm.shot_frames(id).iter().map(|j| j.id.clone()).collect()
    }

    /// Removes a job and everything stored for it (scene blobs stay while another job uses them).
    pub fn delete_job(&self, id: &str) -> Result<(), ServiceError> {
        let mut farm = lock(&self.farm);
        let job = farm.jobs.get(id).ok_or_else(|| ServiceError::NoJob(id.to_string()))?;
        let hash = job.spec.scene_hash.clone();
        let still_used = farm.jobs.values().any(|j| j.id != id && j.spec.scene_hash == hash);
        lock(&self.store).delete_job(id, (!still_used).then_some(hash.as_str()))?;
        farm.jobs.remove(id);
        drop(farm);
        tracing::info!(job = %id, "job deleted");
        Ok(())
    }
}

impl Shared {
    /// Appends to a job's event log (served by `GET /jobs/{id}/events`). Best effort: a log line
    /// that cannot be stored is logged and dropped, never a reason to refuse work.
    pub fn event(&self, job_id: &str, kind: &str, detail: &str) {
        if let Err(e) = lock(&self.store).add_event(job_id, now_ms(), kind, detail) {
            tracing::warn!(job = %job_id, %kind, error = %e, "cannot store a job event");
        }
    }

    /// As `event`, for ids that come from a worker: only jobs the farm has get a log (a forged
    /// unit id must not create rows). Takes the farm lock: not for callers that hold it.
    pub fn event_if_known(&self, job_id: &str, kind: &str, detail: &str) {
        if lock(&self.farm).jobs.contains_key(job_id) {
            self.event(job_id, kind, detail);
        }
    }
}

/// The job a unit id (`<job>/<pass>/<tile>`-like, job first) belongs to.
fn job_of(unit_id: &str) -> &str {
    unit_id.split('/').next().unwrap_or(unit_id)
}

/// What the log says of a new job: its size and budget.
fn submitted_detail(job: &Job) -> String {
    let s = &job.spec.settings;
    let budget = match (s.noise_target, s.time_budget) {
        (Some(t), _) => format!("noise target {t} (min {} spp, cap {} spp)", s.min_spp, s.spp),
        (None, Some(b)) => format!("time budget {b} s (cap {} spp)", s.spp),
        (None, None) => format!("{} spp", s.spp),
    };
    let integrator =
        serde_json::to_value(s.integrator).ok().and_then(|v| v.as_str().map(str::to_string)).unwrap_or_default();
    format!("{}×{}, {budget}, {integrator} integrator, priority {}", s.width, s.height, job.spec.priority)
}

/// A point of the job's convergence curve (JSON: seconds since start, mean spp, estimated
/// relative error, units done), at most every 2 s, or every 1 % of the elapsed time for long jobs
/// (so a day-long job logs a few hundred points), and always at completion.
fn progress_point(job: &mut Job, now: i64, force: bool) -> Option<String> {
    let started = job.started_ms?;
    let gap = 2000.max((now - started) / 100);
    if !force && now - job.last_progress_ms < gap {
        return None;
    }
    job.last_progress_ms = now;
    let (done, _) = job.samples_progress();
    let noise = job.noise();
    Some(
        serde_json::json!({
            "t_s": (now - started) as f64 / 1000.0,
            "spp_mean": done as f64 / job.pixels().max(1) as f64,
            "rel_error": noise.map(|n| n.rel_error).filter(|e| e.is_finite()),
            "units_done": job.units_done(),
        })
        .to_string(),
    )
}

/// What happened to a worker's result (the gRPC reply is made from it).
pub enum ResultReply {
    Merged,
    Dropped(&'static str),
}

/// Why a result was refused.
#[derive(Debug, thiserror::Error)]
pub enum ResultError {
    /// Malformed: the worker is on the job's bad list now.
    #[error("result rejected: {0}")]
    Invalid(String),
    /// The caller does not hold the unit's lease.
    #[error("result refused: {0}")]
    NotLeased(String),
    /// The checkpoint could not be written: nothing was merged, the unit will be leased again.
    #[error("result not merged: the coordinator cannot store it ({0}); the unit will be leased again")]
    Storage(StoreError),
}

impl Shared {
    /// Validates and merges a result, checkpoints the tiles it changed (undoing the merge if that
    /// fails, so memory never gets ahead of disk), and finishes the job when it is complete.
    pub fn accept_result(
        &self,
        worker: &str,
        unit_id: &str,
        sums: Result<renderer::PartialSums, String>,
        pixel_samples: u64,
    ) -> Result<ResultReply, ResultError> {
        use crate::state::SubmitOutcome;
        let t = std::time::Instant::now();
        let mut farm = lock(&self.farm);
        let snapshot = farm.snapshot_tile(unit_id);
        let outcome = farm.submit(worker, unit_id, sums, now_ms());
        let complete = match outcome {
            SubmitOutcome::Merged { tiles_changed, job_complete } => {
                let job_id = unit_id.rsplit_once('/').map(|(j, _)| j.to_string()).unwrap_or_default();
                if let Some(job) = farm.jobs.get(&job_id) {
                    let store = lock(&self.store);
                    let mut failed = None;
                    for &tile in &tiles_changed {
                        if let Err(e) = store.put_tile(&job.id, tile, job.folded[tile], &job.tile_sums[tile]) {
                            failed = Some(e);
                            break;
                        }
                    }
                    if failed.is_none() && job.started_ms.is_some() {
                        if let Err(e) = store.update_job_state(job) {
                            tracing::warn!(job = %job.id, error = %e, "cannot save the job's state (kept in memory)");
                        }
                    }
                    drop(store);
                    if failed.is_none() {
                        if let Some(point) =
                            farm.jobs.get_mut(&job_id).and_then(|j| progress_point(j, now_ms(), job_complete))
                        {
                            self.event(&job_id, "progress", &point);
                        }
                    }
                    if let Some(e) = failed {
                        tracing::error!(job = %job_id, unit = %unit_id, error = %e, "checkpoint failed: merge undone");
                        if let Some(snap) = snapshot {
                            farm.restore_snapshot(snap);
                        }
                        drop(farm);
                        lock(&self.metrics).storage_errors += 1;
                        self.work_available.notify_waiters();
                        return Err(ResultError::Storage(e));
                    }
                }
                job_complete.then_some(job_id)
            }
            SubmitOutcome::Duplicate => return Ok(ResultReply::Dropped("unit already merged: result dropped")),
            SubmitOutcome::Stale => return Ok(ResultReply::Dropped("job finished or cancelled: result dropped")),
            SubmitOutcome::NotLeased(why) => {
                drop(farm);
                tracing::warn!(%worker, unit = %unit_id, %why, "result from a worker without the lease refused");
                self.event_if_known(job_of(unit_id), "result_refused", &format!("unit {unit_id} from {worker}: {why}"));
                lock(&self.metrics).results_forged += 1;
                return Err(ResultError::NotLeased(why));
            }
            SubmitOutcome::Rejected(why) => {
                drop(farm);
                tracing::warn!(%worker, unit = %unit_id, %why, "result rejected; worker put on the job's bad list");
                self.event_if_known(
                    job_of(unit_id),
                    "result_rejected",
                    &format!("unit {unit_id} from {worker}: {why}; the worker is barred from this job"),
                );
                lock(&self.metrics).units_rejected += 1;
                if let Some(w) = lock(&self.workers).get_mut(worker) {
                    w.units_rejected += 1;
                }
                self.work_available.notify_waiters();
                return Err(ResultError::Invalid(why));
            }
        };
        drop(farm);
        {
            let mut m = lock(&self.metrics);
            m.units_merged += 1;
            m.samples_merged += pixel_samples;
            m.merge_seconds_sum += t.elapsed().as_secs_f64();
        }
        if let Some(w) = lock(&self.workers).get_mut(worker) {
            w.units_done += 1;
        }
        if let Some(id) = complete {
            self.finish_job(&id);
        }
        Ok(ResultReply::Merged)
    }

    /// Writes the final EXR and preview of a completed job and marks it done, then drops its
    /// accumulation from memory. Encoding and the blob write happen outside the farm lock. If
    /// storing fails (disk full), the job stays running with its accumulation and checkpoints, and
    /// the tick tries again: nothing is lost.
    pub fn finish_job(&self, id: &str) {
        let (image, settings, stop, warnings) = {
            let mut farm = lock(&self.farm);
            let Some(job) = farm.jobs.get_mut(id) else { return };
            if job.state.is_final() || job.finishing || !job.is_complete() {
                return;
            }
            job.finishing = true;
            (job.image(), job.spec.settings.clone(), job.stop_reason(), job.spec.warnings.clone())
        };
        let encoded = renderer::image_io::FinalImage::from_sums(&image);
        let exr = encoded.exr_bytes(&renderer::image_io::standard_attributes(&settings, &image, stop, &warnings));
        let png = encoded.png_bytes(0.0).unwrap_or_default();
        drop(image);
        let finished_ms = now_ms();
        let stored = match &exr {
            Ok(bytes) => lock(&self.store).finish_job(id, bytes, &png, finished_ms).map_err(|e| e.to_string()),
            Err(e) => Err(format!("cannot encode the EXR: {e}")),
        };
        let mut farm = lock(&self.farm);
        let Some(job) = farm.jobs.get_mut(id) else { return };
        job.finishing = false;
        match (stored, exr.is_ok()) {
            (Ok(()), _) => {
                job.state = crate::state::JobState::Done;
                job.finished_ms = Some(finished_ms);
                job.finish_error = None;
                let (spp, error) = match job.noise() {
                    Some(n) if n.spp_min == n.spp_max => (n.spp_min.to_string(), format!("{:.4}", n.rel_error)),
                    Some(n) => (format!("{}..{}", n.spp_min, n.spp_max), format!("{:.4}", n.rel_error)),
                    None => ("-".into(), "-".into()),
                };
                let detail = format!(
                    "done in {:.1} s: {spp} spp, estimated relative error {error}, stopped by {}",
                    job.started_ms.map_or(0.0, |st| (finished_ms - st) as f64 / 1000.0),
                    stop.as_str()
                );
                job.release();
                tracing::info!(job = %id, "job done");
                self.event(id, "done", &detail);
            }
            (Err(e), true) => {
                tracing::error!(job = %id, error = %e, "cannot store the finished image; will retry");
                self.event(id, "storage_error", &format!("cannot store the finished image ({e}); retrying in 10 s"));
                job.finish_error = Some(format!("cannot store the finished image ({e}); retrying"));
                job.finish_retry_ms = now_ms() + 10_000;
                lock(&self.metrics).storage_errors += 1;
            }
            (Err(e), false) => {
                job.state = crate::state::JobState::Failed;
                job.error = Some(e.clone());
                job.finished_ms = Some(finished_ms);
                job.release();
                if let Err(se) = lock(&self.store).update_job_state(job) {
                    tracing::error!(job = %id, error = %se, "cannot save the failed state");
                }
                tracing::error!(job = %id, error = %e, "job failed");
                self.event(id, "failed", &e);
            }
        }
    }

    /// Cancels a job: its state is saved, its accumulation becomes a stored preview and leaves
    /// memory (the checkpoints stay on disk until the job is deleted).
    pub fn cancel_job(&self, id: &str) -> Result<(), ServiceError> {
        let image = {
            let mut farm = lock(&self.farm);
            let job = farm.jobs.get(id).ok_or_else(|| ServiceError::NoJob(id.to_string()))?;
            if job.state.is_final() {
                return Ok(());
            }
            let before = (job.state.clone(), job.finished_ms);
            farm.cancel(id, now_ms());
            let job = farm.jobs.get_mut(id).ok_or_else(|| ServiceError::NoJob(id.to_string()))?;
            // The cancellation counts once it is stored (memory never gets ahead of disk).
            if let Err(e) = lock(&self.store).update_job_state(job) {
                (job.state, job.finished_ms) = before;
                return Err(e.into());
            }
            // A job cancelled before any sample has nothing to preview (and a huge one would
            // otherwise allocate its whole frame just to say so).
            let image = job.has_samples().then(|| job.image());
            job.release();
            image
        };
        if let Some(image) = image {
            let png = renderer::image_io::FinalImage::from_sums(&image).png_bytes(0.0).unwrap_or_default();
            drop(image);
            lock(&self.store).put_preview(id, &png)?;
        }
        tracing::info!(job = %id, "job cancelled");
        self.event(id, "cancelled", "cancelled by the user");
        Ok(())
    }
}
