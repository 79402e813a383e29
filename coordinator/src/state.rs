//! The coordinator's scheduling and merging state machine, free of I/O so it can be reasoned about
//! (and tested) on its own. A job is planned as tiles × passes (`WorkUnit`s); results are folded per
//! tile in pass order — the determinism rule of ARCHITECTURE.md — so the final image is bit-identical
//! to `tessera render` whatever the number of workers, arrival order or retries.

use renderer::budget::{self, StopReason};
use renderer::film::{PartialSums, Rect};
use renderer::noise;
use renderer::RenderSettings;
use std::collections::{BTreeMap, HashMap, HashSet};
use std::ops::Range;

/// Side of the square tiles jobs are cut into: the renderer's, so that adaptive sampling makes the
/// same per-tile decisions locally and on the farm.
pub use renderer::budget::TILE;
/// A worker whose leases expire this many times on one job is not given that job again.
pub const MAX_WORKER_FAILURES: u32 = 3;

#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum JobState {
    Queued,
    Running,
    Done,
    Failed,
    Cancelled,
}

impl JobState {
    pub fn as_str(&self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Done => "done",
            JobState::Failed => "failed",
            JobState::Cancelled => "cancelled",
        }
    }
    pub fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "queued" => JobState::Queued,
            "running" => JobState::Running,
            "done" => JobState::Done,
            "failed" => JobState::Failed,
            "cancelled" => JobState::Cancelled,
            _ => return None,
        })
    }
    pub fn is_final(&self) -> bool {
        matches!(self, JobState::Done | JobState::Failed | JobState::Cancelled)
    }
}

/// What a user asked for: immutable once submitted.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct JobSpec {
    pub name: String,
    pub scene_hash: String,
    pub settings: RenderSettings,
    pub priority: i32,
    /// What the scene is rendered without (optional extensions), as `tessera render` reports it.
    #[serde(default)]
    pub warnings: Vec<String>,
    /// The shot (a job of several frames) this job is one frame of (`settings.frame`); None for a
    /// single image. A shot is its frame jobs: each has its own tiles, passes, budgets, noise and
    /// EXR, exactly as `tessera render --frame N` would make it.
    #[serde(default)]
    pub shot: Option<String>,
}

/// A unit handed to a worker and not yet returned.
#[derive(Clone, Debug, PartialEq)]
struct Lease {
    worker: String,
    deadline_ms: i64,
}

/// One tile × pass of a job, as handed to a worker.
#[derive(Clone, Debug, PartialEq)]
pub struct WorkUnit {
    pub unit_id: String,
    pub job_id: String,
    pub scene_hash: String,
    /// The job's settings as JSON, serialised once per job (not per unit).
    pub settings_json: std::sync::Arc<str>,
    pub scene_size: u64,
    pub rect: Rect,
    pub samples: Range<u32>,
    pub deadline_ms: i64,
}

/// A job's plan and progress. Units are not materialised: unit `pass × tiles + tile` is pending
/// when its tile still plans that pass and nobody holds or has returned it. This keeps a budgeted
/// job (whose sample cap may be 65536) as small as a fixed one.
pub struct Job {
    pub id: String,
    pub spec: JobSpec,
    pub state: JobState,
    pub error: Option<String>,
    pub submitted_ms: i64,
    pub started_ms: Option<i64>,
    pub finished_ms: Option<i64>,
    pub tiles: Vec<Rect>,
    /// Per tile: the folded accumulation and how many passes it holds.
    pub tile_sums: Vec<PartialSums>,
    pub folded: Vec<u32>,
    /// Per tile: the passes it will hold when done. Starts at the sample cap's pass count; shrinks
    /// to `folded` when the tile meets its noise target, and to the passes already started when the
    /// time budget closes the job.
    pub planned: Vec<u32>,
    /// Per tile: results that arrived before an earlier pass.
    waiting: Vec<BTreeMap<u32, PartialSums>>,
    /// Per tile: passes leased and not yet returned.
    leases: Vec<BTreeMap<u32, Lease>>,
    /// Per tile: passes whose lease expired and nobody holds now, with the worker that held it:
    /// only that worker may still heartbeat or return them (a late result is still good work).
    lapsed: Vec<BTreeMap<u32, String>>,
    /// Per tile: the noise estimate of its folded sums, kept current at every fold so that job
    /// listings never walk the pixels.
    tile_noise: Vec<noise::NoiseEstimate>,
    /// Per tile: stopped before the cap because it met its noise target (kept at each fold, so it
    /// survives the accumulation being released).
    converged: Vec<bool>,
    /// The settings as sent to workers, serialised once.
    pub settings_json: std::sync::Arc<str>,
    /// Size of the scene bundle in bytes (workers are told it with each unit).
    pub scene_size: u64,
    /// Set while the finished image is being encoded and stored outside the farm lock.
    pub finishing: bool,
    /// The last storage failure while finishing (retried by the tick; nothing is lost meanwhile).
    pub finish_error: Option<String>,
    /// After a failed finish, not before this time (ms).
    pub finish_retry_ms: i64,
    /// Passes of which at least one unit was leased: the boundary a time budget stops at.
    started_passes: u32,
    /// Set when the time budget closed the job.
    budget_spent: bool,
    pub bad_workers: HashSet<String>,
    failures: HashMap<String, u32>,
    /// Scheduling round-robin: when this job last got a unit.
    last_served: u64,
    /// Workers that have been given a unit of this job (the job's log names each once).
    pub workers_seen: HashSet<String>,
    /// When the last point of the convergence curve was logged (ms).
    pub last_progress_ms: i64,
}

impl Job {
    pub fn new(id: String, spec: JobSpec, submitted_ms: i64) -> Self {
        let s = &spec.settings;
        let tiles = Rect::tiles(s.width, s.height, TILE);
        let n = tiles.len();
        let unknown = noise::NoiseEstimate { rel_mse: f64::INFINITY, rel_error: f64::INFINITY, spp_min: 0, spp_max: 0 };
        Job {
            id,
            lapsed: vec![BTreeMap::new(); n],
            converged: vec![false; n],
            tile_noise: vec![unknown; n],
            settings_json: serde_json::to_string(s).unwrap_or_default().into(),
            scene_size: 0,
            finishing: false,
            finish_error: None,
            finish_retry_ms: 0,
            // Storage is allocated at a tile's first fold: a queued job costs no image memory.
            tile_sums: tiles.iter().map(|t| PartialSums::unallocated(*t)).collect(),
            folded: vec![0; n],
            planned: vec![s.pass_count(); n],
            waiting: vec![BTreeMap::new(); n],
            leases: vec![BTreeMap::new(); n],
            started_passes: 0,
            budget_spent: false,
            tiles,
            spec,
            state: JobState::Queued,
            error: None,
            submitted_ms,
            started_ms: None,
            finished_ms: None,
            bad_workers: HashSet::new(),
            failures: HashMap::new(),
            last_served: 0,
            workers_seen: HashSet::new(),
            last_progress_ms: 0,
        }
    }

    /// Restores folded progress (after a coordinator restart). A tile that had met its noise
    /// target is recognised as such again: the decision is a function of its sums.
    pub fn restore_tile(&mut self, tile: usize, folded: u32, sums: PartialSums) {
        if tile >= self.tiles.len() || sums.rect != self.tiles[tile] || folded > self.planned[tile] {
            return;
        }
        self.folded[tile] = folded;
        self.tile_sums[tile] = sums;
        self.tile_noise[tile] = noise::estimate(&self.tile_sums[tile]);
        if !budget::tile_needs_more(&self.spec.settings, &self.tile_sums[tile], folded) {
            self.planned[tile] = folded;
            self.converged[tile] = folded < self.spec.settings.pass_count();
        }
        self.started_passes = self.started_passes.max(folded);
    }

    /// Units planned so far (shrinks as tiles converge).
    pub fn unit_count(&self) -> usize {
        self.planned.iter().map(|&p| p as usize).sum()
    }

    pub fn units_done(&self) -> usize {
        self.folded.iter().map(|&f| f as usize).sum()
    }

    pub fn units_leased(&self) -> usize {
        self.leases.iter().map(BTreeMap::len).sum()
    }

    /// Tiles that stopped before the sample cap because they met the noise target.
    pub fn tiles_converged(&self) -> usize {
        self.converged.iter().filter(|&&c| c).count()
    }

    /// Pixel-samples folded into the image so far, and planned in total.
    pub fn samples_progress(&self) -> (u64, u64) {
        let s = &self.spec.settings;
        let (mut done, mut total) = (0u64, 0u64);
        for (t, rect) in self.tiles.iter().enumerate() {
            done += s.samples_after(self.folded[t]) as u64 * rect.pixels() as u64;
            total += s.samples_after(self.planned[t]) as u64 * rect.pixels() as u64;
        }
        (done, total)
    }

    pub fn is_complete(&self) -> bool {
        self.folded == self.planned
    }

    /// Why the job stopped (or will stop, with what is planned now).
    pub fn stop_reason(&self) -> StopReason {
        if self.state == JobState::Cancelled {
            StopReason::Cancelled
        } else if self.budget_spent {
            StopReason::TimeBudget
        } else if self.planned.iter().any(|&p| p < self.spec.settings.pass_count()) {
            StopReason::NoiseTarget
        } else {
            StopReason::SampleCount
        }
    }

    fn unit_id(&self, pass: u32, tile: usize) -> String {
        format!("{}/{}", self.id, pass as u64 * self.tiles.len() as u64 + tile as u64)
    }

    /// The image so far: every tile's folded accumulation placed in the full frame.
    pub fn image(&self) -> PartialSums {
        let s = &self.spec.settings;
        let mut img = PartialSums::new(Rect { x0: 0, y0: 0, width: s.width, height: s.height });
        for t in self.tile_sums.iter().filter(|t| t.is_allocated()) {
            // Tiles come from Rect::tiles of this very image, so they always fit (a released job's
            // tiles are empty and skipped).
            let _ = img.merge_tile(t);
        }
        img
    }

    /// The image's estimated noise (see `renderer::noise`); `None` before every pixel has two samples.
    /// Combined from the per-tile estimates kept at each fold (pixel-weighted), so it costs one step
    /// per tile, not per pixel.
    pub fn noise(&self) -> Option<noise::NoiseEstimate> {
        let (mut total, mut n) = (0.0f64, 0usize);
        let (mut spp_min, mut spp_max) = (u32::MAX, 0u32);
        for (t, e) in self.tiles.iter().zip(&self.tile_noise) {
            total += e.rel_mse * t.pixels() as f64;
            n += t.pixels();
            spp_min = spp_min.min(e.spp_min);
            spp_max = spp_max.max(e.spp_max);
        }
        let rel_mse = total / n.max(1) as f64;
        rel_mse.is_finite().then(|| noise::NoiseEstimate { rel_mse, rel_error: rel_mse.sqrt(), spp_min, spp_max })
    }

    /// The per-tile noise estimates (kept current at each fold).
    pub fn tile_noise(&self) -> &[noise::NoiseEstimate] {
        &self.tile_noise
    }

    /// Pixels of the image (what its accumulation costs, at 36 bytes each).
    pub fn pixels(&self) -> u64 {
        self.spec.settings.width as u64 * self.spec.settings.height as u64
    }

    /// True when some tile holds samples.
    pub fn has_samples(&self) -> bool {
        self.tile_sums.iter().any(PartialSums::is_allocated)
    }

    /// Drops the accumulation of a job that reached a final state (its image and preview are stored
    /// by then, its checkpoints are on disk): memory follows work in flight, not jobs ever
    /// submitted. Every final state is released, so "final" is "released".
    pub fn release(&mut self) {
        for t in &mut self.tile_sums {
            *t = PartialSums::unallocated(t.rect);
        }
        for t in 0..self.tiles.len() {
            self.waiting[t].clear();
            self.leases[t].clear();
            self.lapsed[t].clear();
        }
    }

    /// Closes the job at the passes already started when another pass would not fit in its time
    /// budget (`budget::may_start_pass`, timed from the first lease). Returns whether it did.
    fn close_if_budget_spent(&mut self, now_ms: i64) -> bool {
        let (Some(started), Some(_)) = (self.started_ms, self.spec.settings.time_budget) else { return false };
        if self.budget_spent {
            return false;
        }
        let elapsed = (now_ms - started).max(0) as f64 / 1000.0;
        if budget::may_start_pass(&self.spec.settings, elapsed, self.started_passes) {
            return false;
        }
        self.budget_spent = true;
        for t in 0..self.tiles.len() {
            self.planned[t] = self.planned[t].min(self.started_passes.max(self.folded[t]));
            self.drop_beyond_plan(t);
        }
        true
    }

    fn drop_beyond_plan(&mut self, t: usize) {
        let plan = self.planned[t];
        self.leases[t].retain(|&p, _| p < plan);
        self.waiting[t].retain(|&p, _| p < plan);
        self.lapsed[t].retain(|&p, _| p < plan);
    }

    /// True when `worker` may return or heartbeat pass `pass` of tile `t`: it holds the lease, or
    /// held it until it expired and nobody has taken it since.
    fn may_return(&self, worker: &str, t: usize, pass: u32) -> bool {
        match self.leases[t].get(&pass) {
            Some(l) => l.worker == worker,
            None => self.lapsed[t].get(&pass).is_some_and(|w| w == worker),
        }
    }

    /// The next unit in pass-major order: the lowest pending pass of any tile, tiles in order.
    /// With a noise target a tile runs at most one pass ahead of what it has folded, so little work
    /// is wasted on tiles that turn out to have converged.
    fn next_pending(&self) -> Option<(u32, usize)> {
        let lookahead = if self.spec.settings.noise_target.is_some() { 1 } else { u32::MAX };
        let mut best: Option<(u32, usize)> = None;
        for t in 0..self.tiles.len() {
            let mut p = self.folded[t];
            while p < self.planned[t] && (self.leases[t].contains_key(&p) || self.waiting[t].contains_key(&p)) {
                p += 1;
            }
            if p < self.planned[t] && p - self.folded[t] <= lookahead && best.is_none_or(|(bp, _)| p < bp) {
                best = Some((p, t));
            }
        }
        best
    }

    /// Splits a unit index into (pass, tile).
    fn locate(&self, idx: u64) -> Option<(u32, usize)> {
        let n = self.tiles.len() as u64;
        let pass = u32::try_from(idx / n).ok()?;
        (pass < self.spec.settings.pass_count()).then_some((pass, (idx % n) as usize))
    }
}

/// A tile's folded state, taken before a merge (see `Farm::snapshot_tile`).
pub struct TileSnapshot {
    job: String,
    tile: usize,
    folded: u32,
    planned: u32,
    sums: PartialSums,
    noise: noise::NoiseEstimate,
    converged: bool,
}

/// Why a submitted result was not merged.
#[derive(Debug, PartialEq)]
pub enum SubmitOutcome {
    /// Folded (or queued behind an earlier pass); `tiles_changed` need checkpointing.
    Merged { tiles_changed: Vec<usize>, job_complete: bool },
    /// The unit was already merged (a duplicate from a retried lease): dropped.
    Duplicate,
    /// The job is gone, cancelled or finished, or the unit's tile no longer needs the pass (it met
    /// its noise target, or the time budget closed the job).
    Stale,
    /// The result is malformed; the worker is now on the job's bad list and the unit is re-queued.
    Rejected(String),
    /// The caller does not hold the unit's lease (a forged or misdirected result): refused, and
    /// the honest holder keeps its lease.
    NotLeased(String),
}

#[derive(Default)]
pub struct Farm {
    pub jobs: BTreeMap<String, Job>,
    serve_counter: u64,
    /// Most image pixels of running jobs at once (`--max-pixels-in-flight`; 0: no limit). A queued
    /// job starts only while it fits beside the running ones (or when nothing runs), so the
    /// coordinator's accumulation memory (36 bytes a pixel) is bounded by this, not by the queue.
    pub max_pixels_in_flight: u64,
    /// Most frames of one shot running at once (`TESSERA_MAX_FRAMES_IN_FLIGHT`; 0: no limit).
    /// With frames scheduled in order this bounds a shot's memory to a few accumulations, whatever
    /// its length; finished frames are on disk.
    pub max_frames_in_flight: usize,
    /// The job each worker was last given: a worker stays on the frame whose posed scene it holds.
    worker_job: HashMap<String, String>,
}

impl Farm {
    pub fn add_job(&mut self, job: Job) {
        self.jobs.insert(job.id.clone(), job);
    }

    /// Picks the next unit for `worker`: highest priority first; among jobs of that priority, the
    /// one served longest ago (round-robin), older submissions first on ties; within a job, the
    /// first pending unit in pass-major order. A job whose time budget allows no further pass is
    /// closed at its started passes instead (see `finished_jobs`).
    pub fn lease(&mut self, worker: &str, now_ms: i64, lease_ms: i64) -> Option<WorkUnit> {
        let running: u64 = self.jobs.values().filter(|j| j.state == JobState::Running).map(Job::pixels).sum();
        let limit = self.max_pixels_in_flight;
        // Frames of a shot: how many run, and when the shot was last served (round-robin is
        // between shots and single jobs, not between one shot's frames).
        let mut shot_running: HashMap<String, usize> = HashMap::new();
        let mut shot_served: HashMap<String, u64> = HashMap::new();
        for j in self.jobs.values() {
            if let Some(shot) = &j.spec.shot {
                if j.state == JobState::Running {
                    *shot_running.entry(shot.clone()).or_default() += 1;
                }
                let e = shot_served.entry(shot.clone()).or_default();
                *e = (*e).max(j.last_served);
            }
        }
        let frames_limit = self.max_frames_in_flight;
        let current = self.worker_job.get(worker).cloned();
        let mut candidates: Vec<&mut Job> = self
            .jobs
            .values_mut()
            .filter(|j| !j.state.is_final() && !j.bad_workers.contains(worker) && j.next_pending().is_some())
            .filter(|j| j.state != JobState::Queued || limit == 0 || running == 0 || running + j.pixels() <= limit)
            .filter(|j| {
                j.state != JobState::Queued
                    || frames_limit == 0
                    || j.spec.shot.as_ref().is_none_or(|s| shot_running.get(s).copied().unwrap_or(0) < frames_limit)
            })
            .collect();
        let served = |j: &Job| j.spec.shot.as_ref().and_then(|s| shot_served.get(s).copied()).unwrap_or(j.last_served);
        // Priority; then the job or shot served longest ago; within a shot, the frame this worker
        // holds first (its posed scene is loaded), then frames in order (a sequence can be
        // reviewed while the rest renders); then submission order.
        candidates.sort_by(|a, b| {
            b.spec
                .priority
                .cmp(&a.spec.priority)
                .then(served(a).cmp(&served(b)))
                .then_with(|| {
                    let same_shot = a.spec.shot.is_some() && a.spec.shot == b.spec.shot;
                    if !same_shot {
                        return std::cmp::Ordering::Equal;
                    }
                    let mine = |j: &Job| current.as_deref() != Some(j.id.as_str());
                    mine(a).cmp(&mine(b)).then(a.spec.settings.frame.cmp(&b.spec.settings.frame))
                })
                .then(a.submitted_ms.cmp(&b.submitted_ms))
                .then(a.id.cmp(&b.id))
        });
        for job in candidates {
            let Some((pass, tile)) = job.next_pending() else { continue };
            if pass >= job.started_passes && job.close_if_budget_spent(now_ms) {
                continue;
            }
            self.serve_counter += 1;
            job.last_served = self.serve_counter;
            let deadline_ms = now_ms + lease_ms;
            job.leases[tile].insert(pass, Lease { worker: worker.to_string(), deadline_ms });
            job.lapsed[tile].remove(&pass);
            job.started_passes = job.started_passes.max(pass + 1);
            if job.state == JobState::Queued {
                job.state = JobState::Running;
                job.started_ms = Some(now_ms);
            }
            if job.spec.shot.is_some() {
                self.worker_job.insert(worker.to_string(), job.id.clone());
            }
            return Some(WorkUnit {
                unit_id: job.unit_id(pass, tile),
                job_id: job.id.clone(),
                scene_hash: job.spec.scene_hash.clone(),
                settings_json: job.settings_json.clone(),
                scene_size: job.scene_size,
                rect: job.tiles[tile],
                samples: job.spec.settings.pass_range(pass),
                deadline_ms,
            });
        }
        None
    }

    /// Unfinished jobs whose every tile holds its planned passes (closed by a time budget between
    /// results, or restored complete): the caller writes their images.
    pub fn finished_jobs(&self, now_ms: i64) -> Vec<String> {
        self.jobs
            .values()
            .filter(|j| !j.state.is_final() && !j.finishing && j.is_complete() && now_ms >= j.finish_retry_ms)
            .map(|j| j.id.clone())
            .collect()
    }

    /// The folded state of the tile a unit belongs to, to undo a merge whose checkpoint could not
    /// be written (so memory never gets ahead of disk).
    pub fn snapshot_tile(&self, unit_id: &str) -> Option<TileSnapshot> {
        let (job_id, idx) = Self::parse_unit(unit_id)?;
        let job = self.jobs.get(job_id)?;
        let (_, tile) = job.locate(idx)?;
        Some(TileSnapshot {
            job: job_id.to_string(),
            tile,
            folded: job.folded[tile],
            planned: job.planned[tile],
            sums: job.tile_sums[tile].clone(),
            noise: job.tile_noise[tile],
            converged: job.converged[tile],
        })
    }

    /// Undoes a merge: the tile returns to the snapshot; the passes folded since are pending again
    /// (they will be leased and rendered anew: the same bits, by the determinism rule).
    pub fn restore_snapshot(&mut self, snap: TileSnapshot) {
        let Some(job) = self.jobs.get_mut(&snap.job) else { return };
        let t = snap.tile;
        if t >= job.tiles.len() {
            return;
        }
        job.folded[t] = snap.folded;
        job.planned[t] = snap.planned;
        job.tile_sums[t] = snap.sums;
        job.tile_noise[t] = snap.noise;
        job.converged[t] = snap.converged;
        job.waiting[t].retain(|&p, _| p >= snap.folded);
    }

    fn parse_unit(unit_id: &str) -> Option<(&str, u64)> {
        let (job, idx) = unit_id.rsplit_once('/')?;
        Some((job, idx.parse().ok()?))
    }

    /// Extends a lease. Returns the new deadline, or None when the worker should stop (job
    /// cancelled or finished, unit already merged or no longer needed, or leased to someone else).
    pub fn heartbeat(&mut self, worker: &str, unit_id: &str, now_ms: i64, lease_ms: i64) -> Option<i64> {
        let (job_id, idx) = Self::parse_unit(unit_id)?;
        let job = self.jobs.get_mut(job_id)?;
        if job.state.is_final() {
            return None;
        }
        let (pass, t) = job.locate(idx)?;
        if pass < job.folded[t] || pass >= job.planned[t] || job.waiting[t].contains_key(&pass) {
            return None;
        }
        let deadline_ms = now_ms + lease_ms;
        match job.leases[t].get_mut(&pass) {
            Some(l) if l.worker == worker => {
                l.deadline_ms = deadline_ms;
                Some(deadline_ms)
            }
            Some(_) => None,
            // Our lease expired but nobody else took the unit yet: take it back. Anyone else (a
            // worker that never held it) gets nothing.
            None if job.lapsed[t].get(&pass).is_some_and(|w| w == worker) => {
                job.lapsed[t].remove(&pass);
                job.leases[t].insert(pass, Lease { worker: worker.to_string(), deadline_ms });
                Some(deadline_ms)
            }
            None => None,
        }
    }

    /// Returns expired leases to the queue and counts them against their workers. Returns the
    /// (job, worker) pairs whose leases expired.
    pub fn expire(&mut self, now_ms: i64) -> Vec<(String, String)> {
        let mut expired = Vec::new();
        // A job in a final state holds no leases that matter (cancelled units are not "expired").
        for job in self.jobs.values_mut().filter(|j| !j.state.is_final()) {
            for t in 0..job.leases.len() {
                let gone: Vec<u32> =
                    job.leases[t].iter().filter(|(_, l)| l.deadline_ms < now_ms).map(|(&p, _)| p).collect();
                for p in gone {
                    let Some(lease) = job.leases[t].remove(&p) else { continue };
                    job.lapsed[t].insert(p, lease.worker.clone());
                    let n = job.failures.entry(lease.worker.clone()).or_insert(0);
                    *n += 1;
                    if *n >= MAX_WORKER_FAILURES {
                        job.bad_workers.insert(lease.worker.clone());
                    }
                    expired.push((job.id.clone(), lease.worker));
                }
            }
        }
        expired
    }

    /// The expected rect and sample range of a unit, for validating a result's header before its
    /// payload is read.
    pub fn unit_shape(&self, unit_id: &str) -> Option<(Rect, Range<u32>)> {
        let (job_id, idx) = Self::parse_unit(unit_id)?;
        let job = self.jobs.get(job_id)?;
        let (pass, tile) = job.locate(idx)?;
        Some((job.tiles[tile], job.spec.settings.pass_range(pass)))
    }

    /// Validates and merges a unit's result, received at `now_ms` (so that a time budget can close
    /// the job at the pass boundary this result completes).
    pub fn submit(
        &mut self,
        worker: &str,
        unit_id: &str,
        sums: Result<PartialSums, String>,
        now_ms: i64,
    ) -> SubmitOutcome {
        let Some((job_id, idx)) = Self::parse_unit(unit_id) else { return SubmitOutcome::Stale };
        let Some(job) = self.jobs.get_mut(job_id) else { return SubmitOutcome::Stale };
        let Some((pass, tile)) = job.locate(idx) else { return SubmitOutcome::Stale };
        if job.state.is_final() {
            return SubmitOutcome::Stale;
        }
        if pass < job.folded[tile] || job.waiting[tile].contains_key(&pass) {
            return SubmitOutcome::Duplicate;
        }
        if pass >= job.planned[tile] {
            return SubmitOutcome::Stale;
        }
        if !job.may_return(worker, tile, pass) {
            let holder = job.leases[tile].get(&pass).map(|l| l.worker.clone());
            let lapsed = job.lapsed[tile].get(&pass).cloned();
            return SubmitOutcome::NotLeased(match (holder, lapsed) {
                (Some(h), _) => format!("unit {unit_id} is leased to worker {h}, not to {worker}"),
                (None, Some(h)) => format!("unit {unit_id} was leased to worker {h} (expired), not to {worker}"),
                (None, None) => format!("unit {unit_id} was never leased to worker {worker}"),
            });
        }
        let expected = job.spec.settings.pass_range(pass).len() as u32;
        let checked = sums.and_then(|s| {
            if s.rect != job.tiles[tile] {
                return Err(format!("result covers {:?}, the unit is {:?}", s.rect, job.tiles[tile]));
            }
            s.validate(expected)?;
            Ok(s)
        });
        let sums = match checked {
            Ok(s) => s,
            Err(e) => {
                job.bad_workers.insert(worker.to_string());
                if job.leases[tile].get(&pass).is_some_and(|l| l.worker == worker) {
                    job.leases[tile].remove(&pass);
                }
                return SubmitOutcome::Rejected(e);
            }
        };
        job.leases[tile].remove(&pass);
        job.lapsed[tile].remove(&pass);
        job.waiting[tile].insert(pass, sums);
        let mut changed = false;
        while job.folded[tile] < job.planned[tile] {
            let Some(next) = job.waiting[tile].remove(&job.folded[tile]) else { break };
            // Folding in pass order: determinism rule 3 (from zeros, as `render` does).
            if !job.tile_sums[tile].is_allocated() {
                job.tile_sums[tile] = PartialSums::new(job.tiles[tile]);
            }
            let _ = job.tile_sums[tile].merge(&next);
            job.folded[tile] += 1;
            changed = true;
            job.tile_noise[tile] = noise::estimate(&job.tile_sums[tile]);
            // Adaptive sampling: the decision depends on this tile's folded sums alone.
            if !budget::tile_needs_more(&job.spec.settings, &job.tile_sums[tile], job.folded[tile]) {
                job.planned[tile] = job.folded[tile];
                job.converged[tile] = job.folded[tile] < job.spec.settings.pass_count();
            }
        }
        job.drop_beyond_plan(tile);
        // A completed pass boundary is where a time budget may close the job.
        if job.folded.iter().zip(&job.planned).all(|(&f, &p)| f >= job.started_passes.min(p)) {
            job.close_if_budget_spent(now_ms);
        }
        let complete = job.is_complete();
        SubmitOutcome::Merged { tiles_changed: if changed { vec![tile] } else { Vec::new() }, job_complete: complete }
    }

    pub fn cancel(&mut self, job_id: &str, now_ms: i64) -> Option<&Job> {
        let job = self.jobs.get_mut(job_id)?;
        if !job.state.is_final() {
            job.state = JobState::Cancelled;
            job.finished_ms = Some(now_ms);
        }
        Some(job)
    }

    /// The units each worker holds now (job id, unit id), for the workers' listing.
    pub fn units_held(&self) -> HashMap<String, Vec<(String, String)>> {
        let mut out: HashMap<String, Vec<(String, String)>> = HashMap::new();
        for job in self.jobs.values().filter(|j| !j.state.is_final()) {
            for (t, leases) in job.leases.iter().enumerate() {
                for (&pass, l) in leases {
                    out.entry(l.worker.clone()).or_default().push((job.id.clone(), job.unit_id(pass, t)));
                }
            }
        }
        out
    }

    /// Unfinished jobs, a shot counting once.
    pub fn queued_jobs(&self) -> usize {
        let mut shots = HashSet::new();
        self.jobs
            .values()
            .filter(|j| !j.state.is_final())
            .filter(|j| j.spec.shot.as_ref().is_none_or(|s| shots.insert(s.clone())))
            .count()
    }

    /// The frame jobs of shot `id`, in frame order.
    pub fn shot_frames(&self, id: &str) -> Vec<&Job> {
        let mut v: Vec<&Job> = self.jobs.values().filter(|j| j.spec.shot.as_deref() == Some(id)).collect();
        v.sort_by_key(|j| j.spec.settings.frame);
        v
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use renderer::math::Vec3;

    fn job(id: &str, priority: i32, t: i64) -> Job {
        let settings = RenderSettings { width: 40, height: 20, spp: 8, pass_spp: 4, ..RenderSettings::default() };
        Job::new(
            id.into(),
            JobSpec { name: id.into(), scene_hash: "h".into(), settings, priority, warnings: Vec::new(), shot: None },
            t,
        )
    }

    fn sums(rect: Rect, n: u32, v: f32) -> PartialSums {
        let mut p = PartialSums::new(rect);
        for i in 0..rect.pixels() {
            for _ in 0..n {
                p.add_sample(i, Vec3::splat(v));
            }
        }
        p
    }

    /// Frame `frame` of shot `shot`: a 40×20 image (2 tiles of 32 px) × 2 passes = 4 units.
    fn frame_job(shot: &str, frame: u32) -> Job {
        let mut j = job(&format!("{shot}-f{frame}"), 0, 0);
        j.spec.shot = Some(shot.into());
        j.spec.settings.frame = frame;
        j
    }

    #[test]
    fn a_shot_runs_frames_in_order_keeps_workers_on_their_frame_and_bounds_frames_in_flight() {
        let mut f = Farm { max_frames_in_flight: 2, ..Farm::default() };
        // Added out of order: order comes from the frame number, not from insertion.
        for frame in [3, 0, 2, 1] {
            f.add_job(frame_job("s", frame));
        }
        let frame_of = |u: &WorkUnit| u.job_id.rsplit("-f").next().and_then(|n| n.parse::<u32>().ok());
        // Worker a takes frame 0's four units, then b is sent to frame 1 (frame 0 has none left).
        let a: Vec<_> = (0..4).map(|_| f.lease("a", 0, 1000).and_then(|u| frame_of(&u))).collect();
        assert_eq!(a, vec![Some(0); 4]);
        assert_eq!(f.lease("b", 0, 1000).and_then(|u| frame_of(&u)), Some(1));
        // Two frames run: frame 2 may not start until one finishes, whoever asks.
        for w in ["b", "b", "b"] {
            assert_eq!(f.lease(w, 0, 1000).and_then(|u| frame_of(&u)), Some(1));
        }
        assert!(f.lease("c", 0, 1000).is_none(), "a third frame in flight");
        // A worker on a frame stays on it while it has units: after frame 2 and 3 open up, a worker
        // that last had frame 3 keeps getting frame 3 before frame 2.
        f.jobs.get_mut("s-f0").unwrap().state = JobState::Done;
        f.jobs.get_mut("s-f1").unwrap().state = JobState::Done;
        assert_eq!(f.lease("d", 0, 1000).and_then(|u| frame_of(&u)), Some(2));
        f.worker_job.insert("e".into(), "s-f3".into());
        f.jobs.get_mut("s-f3").unwrap().state = JobState::Running;
        assert_eq!(f.lease("e", 0, 1000).and_then(|u| frame_of(&u)), Some(3));
        assert_eq!(f.lease("d", 0, 1000).and_then(|u| frame_of(&u)), Some(2));
        // A shot counts as one queued job.
        assert_eq!(f.queued_jobs(), 1);
    }

    #[test]
    fn priority_then_round_robin() {
        let mut f = Farm::default();
        f.add_job(job("a", 0, 1));
        f.add_job(job("b", 0, 2));
        f.add_job(job("c", 5, 3));
        let order: Vec<String> = (0..6).map(|_| f.lease("w", 0, 1000).unwrap().job_id).collect();
        // c has 2 tiles × 2 passes = 4 units at priority 5, then a and b alternate.
        assert_eq!(order, ["c", "c", "c", "c", "a", "b"]);
    }

    #[test]
    fn out_of_order_results_fold_in_pass_order_and_duplicates_are_dropped() {
        let mut f = Farm::default();
        f.add_job(job("a", 0, 1));
        let units: Vec<WorkUnit> = (0..4).map(|_| f.lease("w", 0, 1000).unwrap()).collect();
        // Tile 0, pass 1 first: waits for pass 0.
        let u = &units[2];
        assert_eq!(
            f.submit("w", &u.unit_id, Ok(sums(u.rect, 4, 2.0)), 0),
            SubmitOutcome::Merged { tiles_changed: vec![], job_complete: false }
        );
        let u = &units[0];
        assert_eq!(
            f.submit("w", &u.unit_id, Ok(sums(u.rect, 4, 1.0)), 0),
            SubmitOutcome::Merged { tiles_changed: vec![0], job_complete: false }
        );
        assert_eq!(f.jobs["a"].folded[0], 2);
        assert_eq!(f.submit("w2", &u.unit_id, Ok(sums(u.rect, 4, 1.0)), 0), SubmitOutcome::Duplicate);
        for u in [&units[1], &units[3]] {
            f.submit("w", &u.unit_id, Ok(sums(u.rect, 4, 1.0)), 0);
        }
        assert!(f.jobs["a"].is_complete());
        assert_eq!(f.jobs["a"].tile_sums[0].sum_rgb[0][0], 4.0 + 8.0);
    }

    #[test]
    fn results_and_heartbeats_need_the_lease() {
        let mut f = Farm::default();
        f.add_job(job("a", 0, 1));
        let u = f.lease("honest", 0, 1000).unwrap();
        // Finding 3 of issue 11: a registered worker returned tiles it never leased, and a
        // heartbeat on a unit nobody leased granted a lease.
        let forged = f.submit("mallory", &u.unit_id, Ok(sums(u.rect, 4, 9.0)), 0);
        assert!(matches!(forged, SubmitOutcome::NotLeased(ref m) if m.contains("honest")), "{forged:?}");
        let never = "a/3"; // pass 1 of tile 1: nobody holds it
        assert!(matches!(
            f.submit("mallory", never, Ok(sums(f.jobs["a"].tiles[1], 4, 9.0)), 0),
            SubmitOutcome::NotLeased(_)
        ));
        assert_eq!(f.heartbeat("mallory", never, 0, 1000), None);
        assert_eq!(f.heartbeat("mallory", &u.unit_id, 0, 1000), None);
        assert!(!f.jobs["a"].bad_workers.contains("honest"));
        // The honest holder is unaffected and merges.
        assert!(matches!(f.submit("honest", &u.unit_id, Ok(sums(u.rect, 4, 1.0)), 0), SubmitOutcome::Merged { .. }));
        // After an expiry only the previous holder may take a lapsed unit back.
        let v = f.lease("slow", 0, 10).unwrap();
        f.expire(100);
        assert_eq!(f.heartbeat("mallory", &v.unit_id, 100, 1000), None);
        assert!(f.heartbeat("slow", &v.unit_id, 100, 1000).is_some());
    }

    #[test]
    fn pixels_in_flight_bound_the_jobs_that_start() {
        let mut f = Farm { max_pixels_in_flight: 1000, ..Farm::default() };
        f.add_job(job("a", 0, 1)); // 40 × 20 = 800 pixels
        f.add_job(job("b", 0, 2));
        assert_eq!(f.lease("w", 0, 1000).unwrap().job_id, "a");
        // b would make 1600 pixels in flight: it waits while a runs.
        for _ in 0..3 {
            assert_eq!(f.lease("w", 0, 1000).unwrap().job_id, "a");
        }
        assert!(f.lease("w", 0, 1000).is_none());
        f.cancel("a", 0);
        assert_eq!(f.lease("w", 0, 1000).unwrap().job_id, "b");
        // Nothing running: even a job over the limit starts (alone).
        let mut g = Farm { max_pixels_in_flight: 10, ..Farm::default() };
        g.add_job(job("c", 0, 1));
        assert!(g.lease("w", 0, 1000).is_some());
    }

    #[test]
    fn bad_results_blacklist_the_worker_and_requeue_the_unit() {
        let mut f = Farm::default();
        f.add_job(job("a", 0, 1));
        let units: Vec<WorkUnit> = (0..3).map(|_| f.lease("liar", 0, 1000).unwrap()).collect();
        let mut bad = sums(units[0].rect, 4, 1.0);
        bad.sum_rgb[3][1] = f64::NAN;
        assert!(matches!(f.submit("liar", &units[0].unit_id, Ok(bad), 0), SubmitOutcome::Rejected(_)));
        let wrong = sums(Rect { x0: 0, y0: 0, width: 3, height: 3 }, 4, 1.0);
        assert!(matches!(f.submit("liar", &units[1].unit_id, Ok(wrong), 0), SubmitOutcome::Rejected(_)));
        let short = sums(units[2].rect, 3, 1.0);
        assert!(matches!(f.submit("liar", &units[2].unit_id, Ok(short), 0), SubmitOutcome::Rejected(_)));
        // Its rejected unit is no longer its own: trying again is refused as not leased.
        let u = &units[0];
        assert!(matches!(f.submit("liar", &u.unit_id, Ok(sums(u.rect, 4, 1.0)), 0), SubmitOutcome::NotLeased(_)));
        assert!(f.jobs["a"].bad_workers.contains("liar"));
        assert!(f.lease("liar", 0, 1000).is_none(), "a bad worker gets no more units of the job");
        let again = f.lease("honest", 0, 1000).unwrap();
        assert_eq!(again.unit_id, u.unit_id, "the rejected unit is handed out again");
    }

    #[test]
    fn expired_leases_return_to_the_queue() {
        let mut f = Farm::default();
        f.add_job(job("a", 0, 1));
        let u = f.lease("dead", 0, 1000).unwrap();
        assert!(f.expire(500).is_empty());
        assert_eq!(f.expire(1001), vec![("a".to_string(), "dead".to_string())]);
        assert_eq!(f.lease("alive", 1001, 1000).unwrap().unit_id, u.unit_id);
    }

    /// Sums whose pixel `i` alternates between `lo` and `hi` over `n` samples.
    fn noisy(rect: Rect, n: u32, lo: f32, hi: f32) -> PartialSums {
        let mut p = PartialSums::new(rect);
        for i in 0..rect.pixels() {
            for k in 0..n {
                p.add_sample(i, Vec3::splat(if k % 2 == 0 { lo } else { hi }));
            }
        }
        p
    }

    fn budget_job(id: &str, noise_target: Option<f64>, time_budget: Option<f64>) -> Job {
        let settings = RenderSettings {
            width: 64,
            height: 32,
            spp: 64,
            pass_spp: 8,
            noise_target,
            min_spp: 16,
            time_budget,
            ..RenderSettings::default()
        };
        Job::new(
            id.into(),
            JobSpec {
                name: id.into(),
                scene_hash: "h".into(),
                settings,
                priority: 0,
                warnings: Vec::new(),
                shot: None,
            },
            0,
        )
    }

    /// Plays a noise-target job to the end, returning results in `order` within each round of
    /// leases; the tile values make tile 0 quiet and tile 1 noisy.
    fn play(order_reversed: bool, workers: usize) -> Job {
        let mut f = Farm::default();
        f.add_job(budget_job("a", Some(0.05), None));
        let mut rounds = 0;
        while f.jobs["a"].state != JobState::Done && rounds < 100 {
            rounds += 1;
            let mut units: Vec<(String, WorkUnit)> =
                (0..workers).filter_map(|w| f.lease(&format!("w{w}"), 0, 1000).map(|u| (format!("w{w}"), u))).collect();
            if order_reversed {
                units.reverse();
            }
            if units.is_empty() {
                break;
            }
            for (w, u) in &units {
                let n = u.samples.len() as u32;
                let sums = if u.rect.x0 == 0 { noisy(u.rect, n, 0.99, 1.01) } else { noisy(u.rect, n, 0.0, 2.0) };
                if let SubmitOutcome::Merged { job_complete: true, .. } = f.submit(w, &u.unit_id, Ok(sums), 0) {
                    f.jobs.get_mut("a").unwrap().state = JobState::Done;
                }
            }
        }
        f.jobs.remove("a").unwrap()
    }

    #[test]
    fn noise_target_stops_quiet_tiles_early_whatever_the_worker_count() {
        let one = play(false, 1);
        assert_eq!(one.state, JobState::Done);
        // Quiet tile: stops at min_spp (2 passes of 8); noisy tile: runs to the cap (8 passes).
        assert_eq!(one.folded, vec![2, 8]);
        assert_eq!(one.planned, one.folded);
        assert_eq!(one.stop_reason(), StopReason::NoiseTarget);
        assert_eq!(one.tiles_converged(), 1);
        for (reversed, workers) in [(true, 3), (false, 5), (true, 2)] {
            let other = play(reversed, workers);
            assert_eq!(other.folded, one.folded, "{workers} workers");
            assert_eq!(other.tile_sums, one.tile_sums, "{workers} workers");
        }
    }

    #[test]
    fn results_for_passes_a_converged_tile_no_longer_needs_are_stale() {
        let mut f = Farm::default();
        f.add_job(budget_job("a", Some(0.05), None));
        // Lookahead of one pass: tile 0 gets passes 0 and 1, tile 1 too, then nothing more.
        let units: Vec<WorkUnit> = std::iter::from_fn(|| f.lease("w", 0, 1000)).collect();
        assert_eq!(units.len(), 4);
        for u in &units {
            f.submit("w", &u.unit_id, Ok(noisy(u.rect, 8, 1.0, 1.0)), 0);
        }
        // Both tiles are flat: done at min_spp (16 = 2 passes).
        assert!(f.jobs["a"].is_complete());
        let job = f.jobs.get_mut("a").unwrap();
        job.planned[0] = 1; // as if the tile had converged after one pass
        let late = f.jobs["a"].unit_id(1, 0);
        assert_eq!(f.submit("w", &late, Ok(noisy(units[0].rect, 8, 1.0, 1.0)), 0), SubmitOutcome::Duplicate);
        let beyond = f.jobs["a"].unit_id(3, 0);
        assert_eq!(f.submit("w", &beyond, Ok(noisy(units[0].rect, 8, 1.0, 1.0)), 0), SubmitOutcome::Stale);
        assert_eq!(f.submit("w", "a/999999999", Ok(noisy(units[0].rect, 8, 1.0, 1.0)), 0), SubmitOutcome::Stale);
    }

    #[test]
    fn time_budget_closes_the_job_at_the_started_pass() {
        let mut f = Farm::default();
        f.add_job(budget_job("a", None, Some(1.0)));
        let first: Vec<WorkUnit> = (0..2).map(|_| f.lease("w", 0, 10_000).unwrap()).collect();
        // The first pass is done at 300 ms: 300 + 300 fits in 1 s, so pass 1 starts.
        for u in &first {
            f.submit("w", &u.unit_id, Ok(noisy(u.rect, 8, 1.0, 2.0)), 300);
        }
        let second = f.lease("w", 300, 10_000).unwrap();
        assert_eq!(second.samples, 8..16);
        // At 700 ms with 2 passes started, a third (≈ 350 ms) would end past 1 s: no new pass, and
        // the other tile's pass 1 still runs.
        let other = f.lease("w", 700, 10_000).unwrap();
        assert_eq!(other.samples, 8..16);
        assert!(f.lease("w", 700, 10_000).is_none(), "the budget is spent");
        f.submit("w", &second.unit_id, Ok(noisy(second.rect, 8, 1.0, 2.0)), 800);
        let out = f.submit("w", &other.unit_id, Ok(noisy(other.rect, 8, 1.0, 2.0)), 900);
        assert_eq!(out, SubmitOutcome::Merged { tiles_changed: vec![1], job_complete: true });
        let job = &f.jobs["a"];
        assert_eq!(job.folded, vec![2, 2], "every tile holds the same whole passes");
        assert_eq!(job.stop_reason(), StopReason::TimeBudget);
        assert_eq!(job.samples_progress().0, 64 * 32 * 16);
    }
}
