//! The coordinator's scheduling and merging state machine, free of I/O so it can be reasoned about
//! (and tested) on its own. A job is planned as tiles × passes (`WorkUnit`s); results are folded per
//! tile in pass order — the determinism rule of ARCHITECTURE.md — so the final image is bit-identical
//! to `tessera render` whatever the number of workers, arrival order or retries.

use renderer::film::{PartialSums, Rect};
use renderer::RenderSettings;
use std::collections::{BTreeMap, HashMap, HashSet};
use std::ops::Range;

/// Side of the square tiles jobs are cut into (any value gives the same image).
pub const TILE: u32 = 32;
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
}

#[derive(Clone, Debug, PartialEq)]
enum UnitState {
    Pending,
    Leased {
        worker: String,
        deadline_ms: i64,
    },
    /// The result arrived (it may still wait for earlier passes before it is folded).
    Received,
}

/// One tile × pass of a job, as handed to a worker.
#[derive(Clone, Debug, PartialEq)]
pub struct WorkUnit {
    pub unit_id: String,
    pub job_id: String,
    pub scene_hash: String,
    pub settings: RenderSettings,
    pub rect: Rect,
    pub samples: Range<u32>,
    pub deadline_ms: i64,
}

pub struct Job {
    pub id: String,
    pub spec: JobSpec,
    pub state: JobState,
    pub error: Option<String>,
    pub submitted_ms: i64,
    pub started_ms: Option<i64>,
    pub finished_ms: Option<i64>,
    pub tiles: Vec<Rect>,
    pub passes: Vec<Range<u32>>,
    /// Per tile: the folded accumulation and how many passes it holds.
    pub tile_sums: Vec<PartialSums>,
    pub folded: Vec<u32>,
    /// Per tile: results that arrived before an earlier pass.
    waiting: Vec<BTreeMap<u32, PartialSums>>,
    units: Vec<UnitState>,
    pub bad_workers: HashSet<String>,
    failures: HashMap<String, u32>,
    /// Scheduling round-robin: when this job last got a unit.
    last_served: u64,
}

/// Unit index = pass × tiles + tile: pass-major, so the whole image refines pass by pass.
impl Job {
    pub fn new(id: String, spec: JobSpec, submitted_ms: i64) -> Self {
        let s = &spec.settings;
        let tiles = Rect::tiles(s.width, s.height, TILE);
        let passes: Vec<Range<u32>> = s.passes().collect();
        let n = tiles.len() * passes.len();
        Job {
            id,
            tile_sums: tiles.iter().map(|t| PartialSums::new(*t)).collect(),
            folded: vec![0; tiles.len()],
            waiting: vec![BTreeMap::new(); tiles.len()],
            units: vec![UnitState::Pending; n],
            tiles,
            passes,
            spec,
            state: JobState::Queued,
            error: None,
            submitted_ms,
            started_ms: None,
            finished_ms: None,
            bad_workers: HashSet::new(),
            failures: HashMap::new(),
            last_served: 0,
        }
    }

    /// Restores folded progress (after a coordinator restart): units of folded passes are done.
    pub fn restore_tile(&mut self, tile: usize, folded: u32, sums: PartialSums) {
        if tile >= self.tiles.len() || sums.rect != self.tiles[tile] || folded as usize > self.passes.len() {
            return;
        }
        self.folded[tile] = folded;
        self.tile_sums[tile] = sums;
        for p in 0..folded as usize {
            let idx = p * self.tiles.len() + tile;
            self.units[idx] = UnitState::Received;
        }
    }

    pub fn unit_count(&self) -> usize {
        self.units.len()
    }

    pub fn units_done(&self) -> usize {
        self.folded.iter().map(|&f| f as usize).sum()
    }

    pub fn units_leased(&self) -> usize {
        self.units.iter().filter(|u| matches!(u, UnitState::Leased { .. })).count()
    }

    /// Pixel-samples folded into the image so far, and in total.
    pub fn samples_progress(&self) -> (u64, u64) {
        let mut done = 0u64;
        for (t, &f) in self.folded.iter().enumerate() {
            let spp: u64 = self.passes[..f as usize].iter().map(|r| r.len() as u64).sum();
            done += spp * self.tiles[t].pixels() as u64;
        }
        let total = self.spec.settings.spp as u64 * self.spec.settings.width as u64 * self.spec.settings.height as u64;
        (done, total)
    }

    pub fn is_complete(&self) -> bool {
        self.folded.iter().all(|&f| f as usize == self.passes.len())
    }

    fn unit_id(&self, idx: usize) -> String {
        format!("{}/{}", self.id, idx)
    }

    /// The image so far: every tile's folded accumulation placed in the full frame.
    pub fn image(&self) -> PartialSums {
        let s = &self.spec.settings;
        let mut img = PartialSums::new(Rect { x0: 0, y0: 0, width: s.width, height: s.height });
        for t in &self.tile_sums {
            // Tiles come from Rect::tiles of this very image, so they always fit.
            let _ = img.merge_tile(t);
        }
        img
    }

    /// Estimated relative MSE of the image from its variance buffer: mean over pixels of
    /// var(mean) / (mean² + 0.01), the expectation of the relMSE `equal_time.py` measures.
    pub fn estimated_rel_mse(&self) -> Option<f64> {
        let mut sum = 0.0;
        let mut n = 0usize;
        for t in &self.tile_sums {
            for i in 0..t.rect.pixels() {
                if t.count[i] < 2 {
                    continue;
                }
                let m = t.mean(i);
                let y = renderer::math::luminance(renderer::math::Vec3::from(m)) as f64;
                sum += t.variance_of_mean(i) as f64 / (y * y + 0.01);
                n += 1;
            }
        }
        (n > 0).then(|| sum / n as f64)
    }
}

/// Why a submitted result was not merged.
#[derive(Debug, PartialEq)]
pub enum SubmitOutcome {
    /// Folded (or queued behind an earlier pass); `tiles_changed` need checkpointing.
    Merged { tiles_changed: Vec<usize>, job_complete: bool },
    /// The unit was already merged (a duplicate from a retried lease): dropped.
    Duplicate,
    /// The job is gone, cancelled or finished.
    Stale,
    /// The result is malformed; the worker is now on the job's bad list and the unit is re-queued.
    Rejected(String),
}

#[derive(Default)]
pub struct Farm {
    pub jobs: BTreeMap<String, Job>,
    serve_counter: u64,
}

impl Farm {
    pub fn add_job(&mut self, job: Job) {
        self.jobs.insert(job.id.clone(), job);
    }

    /// Picks the next unit for `worker`: highest priority first; among jobs of that priority, the
    /// one served longest ago (round-robin), older submissions first on ties; within a job, the
    /// first pending unit in pass-major order.
    pub fn lease(&mut self, worker: &str, now_ms: i64, lease_ms: i64) -> Option<WorkUnit> {
        let mut candidates: Vec<&mut Job> = self
            .jobs
            .values_mut()
            .filter(|j| !j.state.is_final() && !j.bad_workers.contains(worker) && j.units.contains(&UnitState::Pending))
            .collect();
        candidates.sort_by(|a, b| {
            b.spec
                .priority
                .cmp(&a.spec.priority)
                .then(a.last_served.cmp(&b.last_served))
                .then(a.submitted_ms.cmp(&b.submitted_ms))
                .then(a.id.cmp(&b.id))
        });
        let job = candidates.into_iter().next()?;
        let idx = job.units.iter().position(|u| *u == UnitState::Pending)?;
        self.serve_counter += 1;
        job.last_served = self.serve_counter;
        let deadline_ms = now_ms + lease_ms;
        job.units[idx] = UnitState::Leased { worker: worker.to_string(), deadline_ms };
        if job.state == JobState::Queued {
            job.state = JobState::Running;
            job.started_ms = Some(now_ms);
        }
        let (pass, tile) = (idx / job.tiles.len(), idx % job.tiles.len());
        Some(WorkUnit {
            unit_id: job.unit_id(idx),
            job_id: job.id.clone(),
            scene_hash: job.spec.scene_hash.clone(),
            settings: job.spec.settings.clone(),
            rect: job.tiles[tile],
            samples: job.passes[pass].clone(),
            deadline_ms,
        })
    }

    fn parse_unit(unit_id: &str) -> Option<(&str, usize)> {
        let (job, idx) = unit_id.rsplit_once('/')?;
        Some((job, idx.parse().ok()?))
    }

    /// Extends a lease. Returns the new deadline, or None when the worker should stop (job
    /// cancelled or finished, unit already merged, or leased to someone else).
    pub fn heartbeat(&mut self, worker: &str, unit_id: &str, now_ms: i64, lease_ms: i64) -> Option<i64> {
        let (job_id, idx) = Self::parse_unit(unit_id)?;
        let job = self.jobs.get_mut(job_id)?;
        if job.state.is_final() {
            return None;
        }
        match job.units.get_mut(idx)? {
            UnitState::Leased { worker: w, deadline_ms } if w == worker => {
                *deadline_ms = now_ms + lease_ms;
                Some(*deadline_ms)
            }
            // Our lease expired but nobody else took the unit yet: take it back.
            u @ UnitState::Pending => {
                *u = UnitState::Leased { worker: worker.to_string(), deadline_ms: now_ms + lease_ms };
                Some(now_ms + lease_ms)
            }
            _ => None,
        }
    }

    /// Returns expired leases to the queue and counts them against their workers. Returns the
    /// (job, worker) pairs whose leases expired.
    pub fn expire(&mut self, now_ms: i64) -> Vec<(String, String)> {
        let mut expired = Vec::new();
        for job in self.jobs.values_mut() {
            for u in job.units.iter_mut() {
                if let UnitState::Leased { worker, deadline_ms } = u {
                    if *deadline_ms < now_ms {
                        expired.push((job.id.clone(), worker.clone()));
                        let n = job.failures.entry(worker.clone()).or_insert(0);
                        *n += 1;
                        if *n >= MAX_WORKER_FAILURES {
                            job.bad_workers.insert(worker.clone());
                        }
                        *u = UnitState::Pending;
                    }
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
        if idx >= job.units.len() {
            return None;
        }
        Some((job.tiles[idx % job.tiles.len()], job.passes[idx / job.tiles.len()].clone()))
    }

    /// Validates and merges a unit's result.
    pub fn submit(&mut self, worker: &str, unit_id: &str, sums: Result<PartialSums, String>) -> SubmitOutcome {
        let Some((job_id, idx)) = Self::parse_unit(unit_id) else { return SubmitOutcome::Stale };
        let Some(job) = self.jobs.get_mut(job_id) else { return SubmitOutcome::Stale };
        if job.state.is_final() || idx >= job.units.len() {
            return SubmitOutcome::Stale;
        }
        if job.units[idx] == UnitState::Received {
            return SubmitOutcome::Duplicate;
        }
        let (pass, tile) = (idx / job.tiles.len(), idx % job.tiles.len());
        let expected = job.passes[pass].len() as u32;
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
                if matches!(&job.units[idx], UnitState::Leased { worker: w, .. } if w == worker) {
                    job.units[idx] = UnitState::Pending;
                }
                return SubmitOutcome::Rejected(e);
            }
        };
        job.units[idx] = UnitState::Received;
        job.waiting[tile].insert(pass as u32, sums);
        let mut changed = false;
        while let Some(next) = job.waiting[tile].remove(&job.folded[tile]) {
            // Folding in pass order: determinism rule 3.
            let _ = job.tile_sums[tile].merge(&next);
            job.folded[tile] += 1;
            changed = true;
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

    pub fn queued_jobs(&self) -> usize {
        self.jobs.values().filter(|j| !j.state.is_final()).count()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use renderer::math::Vec3;

    fn job(id: &str, priority: i32, t: i64) -> Job {
        let settings = RenderSettings { width: 40, height: 20, spp: 8, pass_spp: 4, ..RenderSettings::default() };
        Job::new(id.into(), JobSpec { name: id.into(), scene_hash: "h".into(), settings, priority }, t)
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
            f.submit("w", &u.unit_id, Ok(sums(u.rect, 4, 2.0))),
            SubmitOutcome::Merged { tiles_changed: vec![], job_complete: false }
        );
        let u = &units[0];
        assert_eq!(
            f.submit("w", &u.unit_id, Ok(sums(u.rect, 4, 1.0))),
            SubmitOutcome::Merged { tiles_changed: vec![0], job_complete: false }
        );
        assert_eq!(f.jobs["a"].folded[0], 2);
        assert_eq!(f.submit("w2", &u.unit_id, Ok(sums(u.rect, 4, 1.0))), SubmitOutcome::Duplicate);
        for u in [&units[1], &units[3]] {
            f.submit("w", &u.unit_id, Ok(sums(u.rect, 4, 1.0)));
        }
        assert!(f.jobs["a"].is_complete());
        assert_eq!(f.jobs["a"].tile_sums[0].sum_rgb[0][0], 4.0 + 8.0);
    }

    #[test]
    fn bad_results_blacklist_the_worker_and_requeue_the_unit() {
        let mut f = Farm::default();
        f.add_job(job("a", 0, 1));
        let u = f.lease("liar", 0, 1000).unwrap();
        let mut bad = sums(u.rect, 4, 1.0);
        bad.sum_rgb[3][1] = f64::NAN;
        assert!(matches!(f.submit("liar", &u.unit_id, Ok(bad)), SubmitOutcome::Rejected(_)));
        let wrong = sums(Rect { x0: 0, y0: 0, width: 3, height: 3 }, 4, 1.0);
        assert!(matches!(f.submit("liar", &u.unit_id, Ok(wrong)), SubmitOutcome::Rejected(_)));
        let short = sums(u.rect, 3, 1.0);
        assert!(matches!(f.submit("liar", &u.unit_id, Ok(short)), SubmitOutcome::Rejected(_)));
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
}
