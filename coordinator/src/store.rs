//! Persistence in SQLite (`<data-dir>/tessera.db`): scenes by content hash, jobs, per-tile checkpoints
//! of the folded accumulation, and finished images. Every write is a transaction, so a crash leaves
//! either the old checkpoint or the new one, never a torn one; in-flight units are simply re-leased
//! after a restart.

use crate::state::{Job, JobSpec, JobState};
use renderer::film::PartialSums;
use rusqlite::{params, Connection, OptionalExtension};
use std::path::Path;

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("database: {0}")]
    Sql(#[from] rusqlite::Error),
    #[error("stored data is corrupt: {0}")]
    Corrupt(String),
}

impl StoreError {
    /// The disk (or the database's size limit) is full: HTTP 507.
    pub fn is_disk_full(&self) -> bool {
        matches!(self, StoreError::Sql(rusqlite::Error::SqliteFailure(e, _)) if e.code == rusqlite::ErrorCode::DiskFull)
    }

    /// A row with this key exists already (an insert that must not replace).
    pub fn is_conflict(&self) -> bool {
        matches!(self, StoreError::Sql(rusqlite::Error::SqliteFailure(e, _)) if e.code == rusqlite::ErrorCode::ConstraintViolation)
    }
}

fn sha256_hex(data: &[u8]) -> String {
    use sha2::Digest;
    hex::encode(sha2::Sha256::digest(data))
}

pub struct Store {
    db: Connection,
}

/// Most events stored per job (about 100 bytes each).
pub const MAX_EVENTS_PER_JOB: usize = 5000;

/// One line of a job's log: what happened to it (`kind`: submitted, worker_joined, lease_expired,
/// result_rejected, result_refused, progress, done, failed, cancelled, resumed, storage_error,
/// log_full) with a human-readable `detail` (for `progress`, JSON: `t_s`, `spp_mean`,
/// `rel_error`, `units_done`).
#[derive(Debug, Clone, serde::Serialize)]
pub struct StoredEvent {
    pub seq: i64,
    pub t_ms: i64,
    pub kind: String,
    pub detail: String,
}

impl Store {
    /// Opens (or creates) the database in `dir`. `max_bytes` caps its size (`TESSERA_MAX_DB_MB`):
    /// beyond it writes fail as on a full disk (SQLITE_FULL), which the farm answers with 507 and
    /// survives without losing what is stored.
    pub fn open(dir: &Path, max_bytes: Option<u64>) -> Result<Self, StoreError> {
        std::fs::create_dir_all(dir)
            .map_err(|e| StoreError::Corrupt(format!("cannot create {}: {e}", dir.display())))?;
        let db = Connection::open(dir.join("tessera.db"))?;
        db.execute_batch(
            "PRAGMA journal_mode=WAL;
             PRAGMA synchronous=NORMAL;
             CREATE TABLE IF NOT EXISTS scenes (hash TEXT PRIMARY KEY, data BLOB NOT NULL);
             CREATE TABLE IF NOT EXISTS jobs (
                 id TEXT PRIMARY KEY, spec TEXT NOT NULL, state TEXT NOT NULL, error TEXT,
                 submitted_ms INTEGER NOT NULL, started_ms INTEGER, finished_ms INTEGER);
             CREATE TABLE IF NOT EXISTS tiles (
                 job_id TEXT NOT NULL, tile INTEGER NOT NULL, folded INTEGER NOT NULL, sums BLOB NOT NULL,
                 PRIMARY KEY (job_id, tile));
             CREATE TABLE IF NOT EXISTS images (job_id TEXT PRIMARY KEY, exr BLOB NOT NULL);
             CREATE TABLE IF NOT EXISTS previews (job_id TEXT PRIMARY KEY, png BLOB NOT NULL);
             CREATE TABLE IF NOT EXISTS events (
                 seq INTEGER PRIMARY KEY AUTOINCREMENT, job_id TEXT NOT NULL, t_ms INTEGER NOT NULL,
                 kind TEXT NOT NULL, detail TEXT NOT NULL);
             CREATE INDEX IF NOT EXISTS events_by_job ON events (job_id, seq);",
        )?;
        // Databases made before checksums: add the column (old images stay unchecked).
        let has_sha: bool = db.prepare("SELECT 1 FROM pragma_table_info('images') WHERE name = 'sha256'")?.exists([])?;
        if !has_sha {
            db.execute_batch("ALTER TABLE images ADD COLUMN sha256 TEXT")?;
        }
        if let Some(max) = max_bytes {
            let page: i64 = db.query_row("PRAGMA page_size", [], |r| r.get(0))?;
            let pages = (max / page.max(512) as u64).max(1);
            db.query_row(&format!("PRAGMA max_page_count = {pages}"), [], |_| Ok(()))?;
        }
        Ok(Store { db })
    }

    /// Stores a scene bundle unless one with the same hash is already there (deduplication).
    pub fn put_scene(&self, hash: &str, data: &[u8]) -> Result<(), StoreError> {
        self.db.execute("INSERT OR IGNORE INTO scenes (hash, data) VALUES (?1, ?2)", params![hash, data])?;
        Ok(())
    }

    /// A scene bundle, checked against its hash (its name): a corrupted blob is an error, never
    /// sent to workers.
    pub fn scene(&self, hash: &str) -> Result<Option<Vec<u8>>, StoreError> {
        let data: Option<Vec<u8>> =
            self.db.query_row("SELECT data FROM scenes WHERE hash = ?1", params![hash], |r| r.get(0)).optional()?;
        match data {
            Some(d) if sha256_hex(&d) != hash => {
                Err(StoreError::Corrupt(format!("scene {hash}: stored bytes do not match their SHA-256")))
            }
            d => Ok(d),
        }
    }

    /// The size of a stored scene, without reading it.
    pub fn scene_size(&self, hash: &str) -> Result<Option<u64>, StoreError> {
        Ok(self
            .db
            .query_row("SELECT length(data) FROM scenes WHERE hash = ?1", params![hash], |r| r.get::<_, i64>(0))
            .optional()?
            .map(|n| n as u64))
    }

    /// Inserts a new job; fails (`is_conflict`) rather than replace a job with the same id.
    pub fn insert_job(&self, job: &Job) -> Result<(), StoreError> {
        let spec = serde_json::to_string(&job.spec).map_err(|e| StoreError::Corrupt(e.to_string()))?;
        self.db.execute(
            "INSERT INTO jobs (id, spec, state, error, submitted_ms, started_ms, finished_ms) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7)",
            params![job.id, spec, job.state.as_str(), job.error, job.submitted_ms, job.started_ms, job.finished_ms],
        )?;
        Ok(())
    }

    pub fn update_job_state(&self, job: &Job) -> Result<(), StoreError> {
        self.db.execute(
            "UPDATE jobs SET state = ?2, error = ?3, started_ms = ?4, finished_ms = ?5 WHERE id = ?1",
            params![job.id, job.state.as_str(), job.error, job.started_ms, job.finished_ms],
        )?;
        Ok(())
    }

    /// Checkpoints one tile's folded accumulation.
    pub fn put_tile(&self, job_id: &str, tile: usize, folded: u32, sums: &PartialSums) -> Result<(), StoreError> {
        self.db.execute(
            "INSERT OR REPLACE INTO tiles (job_id, tile, folded, sums) VALUES (?1, ?2, ?3, ?4)",
            params![job_id, tile as i64, folded as i64, sums.encode()],
        )?;
        Ok(())
    }

    /// Stores the finished EXR (with its SHA-256) and preview and marks the job done, in one
    /// transaction: after a failure (disk full) the job and its checkpoints are as they were.
    pub fn finish_job(&mut self, id: &str, exr: &[u8], png: &[u8], finished_ms: i64) -> Result<(), StoreError> {
        let tx = self.db.transaction()?;
        tx.execute(
            "INSERT OR REPLACE INTO images (job_id, exr, sha256) VALUES (?1, ?2, ?3)",
            params![id, exr, sha256_hex(exr)],
        )?;
        tx.execute("INSERT OR REPLACE INTO previews (job_id, png) VALUES (?1, ?2)", params![id, png])?;
        tx.execute(
            "UPDATE jobs SET state = 'done', error = NULL, finished_ms = ?2 WHERE id = ?1",
            params![id, finished_ms],
        )?;
        tx.execute("DELETE FROM tiles WHERE job_id = ?1", params![id])?;
        tx.commit()?;
        Ok(())
    }

    /// A job's final EXR, checked against the SHA-256 stored with it.
    pub fn image(&self, job_id: &str) -> Result<Option<Vec<u8>>, StoreError> {
        let row: Option<(Vec<u8>, Option<String>)> = self
            .db
            .query_row("SELECT exr, sha256 FROM images WHERE job_id = ?1", params![job_id], |r| {
                Ok((r.get(0)?, r.get(1)?))
            })
            .optional()?;
        match row {
            Some((exr, Some(sum))) if sha256_hex(&exr) != sum => {
                Err(StoreError::Corrupt(format!("image of job {job_id}: stored bytes do not match their SHA-256")))
            }
            row => Ok(row.map(|r| r.0)),
        }
    }

    pub fn put_preview(&self, job_id: &str, png: &[u8]) -> Result<(), StoreError> {
        self.db.execute("INSERT OR REPLACE INTO previews (job_id, png) VALUES (?1, ?2)", params![job_id, png])?;
        Ok(())
    }

    pub fn preview(&self, job_id: &str) -> Result<Option<Vec<u8>>, StoreError> {
        Ok(self.db.query_row("SELECT png FROM previews WHERE job_id = ?1", params![job_id], |r| r.get(0)).optional()?)
    }

    /// Deletes a job with its checkpoints, image and preview, and the scene `scene` if given (the
    /// caller knows no other job uses it), in one transaction.
    pub fn delete_job(&mut self, id: &str, scene: Option<&str>) -> Result<(), StoreError> {
        let tx = self.db.transaction()?;
        for table in ["tiles", "images", "previews", "events"] {
            tx.execute(&format!("DELETE FROM {table} WHERE job_id = ?1"), params![id])?;
        }
        tx.execute("DELETE FROM jobs WHERE id = ?1", params![id])?;
        if let Some(h) = scene {
            tx.execute("DELETE FROM scenes WHERE hash = ?1", params![h])?;
        }
        tx.commit()?;
        Ok(())
    }

    /// Appends an event to a job's log, unless the log already holds `MAX_EVENTS_PER_JOB` (a
    /// worker failing in a loop must not fill the disk; the last event says the log is full).
    pub fn add_event(&self, job_id: &str, t_ms: i64, kind: &str, detail: &str) -> Result<(), StoreError> {
        let n: i64 =
            self.db.query_row("SELECT COUNT(*) FROM events WHERE job_id = ?1", params![job_id], |r| r.get(0))?;
        let cap = MAX_EVENTS_PER_JOB as i64;
        let (kind, detail) = match n {
            n if n < cap - 1 => (kind, detail),
            n if n == cap - 1 => ("log_full", "the event log is full: later events are not stored"),
            _ => return Ok(()),
        };
        self.db.execute(
            "INSERT INTO events (job_id, t_ms, kind, detail) VALUES (?1, ?2, ?3, ?4)",
            params![job_id, t_ms, kind, detail],
        )?;
        Ok(())
    }

    /// A job's events after sequence number `after`, oldest first, at most `limit`.
    pub fn events(&self, job_id: &str, after: i64, limit: usize) -> Result<Vec<StoredEvent>, StoreError> {
        let mut stmt = self.db.prepare(
            "SELECT seq, t_ms, kind, detail FROM events WHERE job_id = ?1 AND seq > ?2 ORDER BY seq LIMIT ?3",
        )?;
        let rows = stmt.query_map(params![job_id, after, limit as i64], |r| {
            Ok(StoredEvent { seq: r.get(0)?, t_ms: r.get(1)?, kind: r.get(2)?, detail: r.get(3)? })
        })?;
        Ok(rows.collect::<Result<_, _>>()?)
    }

    /// Every job, with unfinished ones restored to their checkpointed progress. A row that cannot be
    /// read (bad JSON, unknown state, corrupt checkpoint) does not stop the coordinator: the job is
    /// quarantined, i.e. loaded as failed with the reason (and saved so), and the others are served.
    pub fn load_jobs(&self) -> Result<Vec<Job>, StoreError> {
        let mut stmt =
            self.db.prepare("SELECT id, spec, state, error, submitted_ms, started_ms, finished_ms FROM jobs")?;
        let rows = stmt.query_map([], |r| {
            Ok((
                r.get::<_, String>(0)?,
                r.get::<_, String>(1)?,
                r.get::<_, String>(2)?,
                r.get::<_, Option<String>>(3)?,
                r.get::<_, i64>(4)?,
                r.get::<_, Option<i64>>(5)?,
                r.get::<_, Option<i64>>(6)?,
            ))
        })?;
        let mut jobs = Vec::new();
        let mut quarantined = Vec::new();
        for row in rows {
            let (id, spec, state, error, submitted, started, finished) = match row {
                Ok(r) => r,
                Err(e) => {
                    tracing::error!(error = %e, "a job row cannot be read at all: skipped");
                    continue;
                }
            };
            match self.load_job(&id, &spec, &state, error, submitted, started, finished) {
                Ok(job) => jobs.push(job),
                Err(why) => {
                    tracing::error!(job = %id, %why, "stored job is corrupt: quarantined (marked failed)");
                    let mut job = Job::new(id.clone(), quarantine_spec(&spec), submitted);
                    job.state = JobState::Failed;
                    job.error = Some(format!("quarantined at start: stored data is corrupt ({why})"));
                    job.finished_ms = finished.or(Some(submitted));
                    job.release();
                    quarantined.push((id, job.error.clone()));
                    jobs.push(job);
                }
            }
        }
        drop(stmt);
        for (id, error) in quarantined {
            if let Err(e) =
                self.db.execute("UPDATE jobs SET state = 'failed', error = ?2 WHERE id = ?1", params![id, error])
            {
                tracing::warn!(job = %id, error = %e, "cannot save the quarantine");
            }
        }
        Ok(jobs)
    }

    #[allow(clippy::too_many_arguments)] // one job row's columns
    fn load_job(
        &self,
        id: &str,
        spec: &str,
        state: &str,
        error: Option<String>,
        submitted: i64,
        started: Option<i64>,
        finished: Option<i64>,
    ) -> Result<Job, String> {
        let spec: JobSpec = serde_json::from_str(spec).map_err(|e| format!("spec: {e}"))?;
        spec.settings.validate().map_err(|e| format!("settings: {e}"))?;
        let mut job = Job::new(id.to_string(), spec, submitted);
        job.state = JobState::parse(state).ok_or_else(|| format!("state '{state}'"))?;
        job.error = error;
        job.started_ms = started;
        job.finished_ms = finished;
        job.scene_size = self.scene_size(&job.spec.scene_hash).map_err(|e| e.to_string())?.unwrap_or(0);
        if job.state.is_final() {
            job.release();
            return Ok(job);
        }
        let mut t =
            self.db.prepare("SELECT tile, folded, sums FROM tiles WHERE job_id = ?1").map_err(|e| e.to_string())?;
        let tiles = t
            .query_map(params![id], |r| Ok((r.get::<_, i64>(0)?, r.get::<_, i64>(1)?, r.get::<_, Vec<u8>>(2)?)))
            .map_err(|e| e.to_string())?;
        for tile in tiles {
            let (tile, folded, blob) = tile.map_err(|e| e.to_string())?;
            let Some(rect) = job.tiles.get(tile as usize).copied() else { continue };
            let sums = PartialSums::decode(rect, &blob).map_err(|e| format!("tile {tile}: {e}"))?;
            job.restore_tile(tile as usize, folded as u32, sums);
        }
        Ok(job)
    }
}

/// The spec a quarantined job is shown with: the stored one if it still parses, else a stand-in
/// (1×1, no scene) that only carries the id and the error.
fn quarantine_spec(spec: &str) -> JobSpec {
    serde_json::from_str::<JobSpec>(spec).ok().filter(|s| s.settings.validate().is_ok()).unwrap_or_else(|| JobSpec {
        name: "(corrupt job)".into(),
        scene_hash: String::new(),
        settings: renderer::RenderSettings { width: 1, height: 1, ..Default::default() },
        priority: 0,
        warnings: Vec::new(),
        shot: None,
    })
}
