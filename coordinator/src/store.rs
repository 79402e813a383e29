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

pub struct Store {
    db: Connection,
}

impl Store {
    pub fn open(dir: &Path) -> Result<Self, StoreError> {
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
             CREATE TABLE IF NOT EXISTS images (job_id TEXT PRIMARY KEY, exr BLOB NOT NULL);",
        )?;
        Ok(Store { db })
    }

    /// Stores a scene bundle unless one with the same hash is already there (deduplication).
    pub fn put_scene(&self, hash: &str, data: &[u8]) -> Result<(), StoreError> {
        self.db.execute("INSERT OR IGNORE INTO scenes (hash, data) VALUES (?1, ?2)", params![hash, data])?;
        Ok(())
    }

    pub fn scene(&self, hash: &str) -> Result<Option<Vec<u8>>, StoreError> {
        Ok(self.db.query_row("SELECT data FROM scenes WHERE hash = ?1", params![hash], |r| r.get(0)).optional()?)
    }

    pub fn put_job(&self, job: &Job) -> Result<(), StoreError> {
        let spec = serde_json::to_string(&job.spec).map_err(|e| StoreError::Corrupt(e.to_string()))?;
        self.db.execute(
            "INSERT OR REPLACE INTO jobs (id, spec, state, error, submitted_ms, started_ms, finished_ms) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7)",
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

    /// Stores the finished EXR and marks the job done, in one transaction.
    pub fn finish_job(&mut self, job: &Job, exr: &[u8]) -> Result<(), StoreError> {
        let tx = self.db.transaction()?;
        tx.execute("INSERT OR REPLACE INTO images (job_id, exr) VALUES (?1, ?2)", params![job.id, exr])?;
        tx.execute(
            "UPDATE jobs SET state = ?2, error = ?3, started_ms = ?4, finished_ms = ?5 WHERE id = ?1",
            params![job.id, job.state.as_str(), job.error, job.started_ms, job.finished_ms],
        )?;
        tx.execute("DELETE FROM tiles WHERE job_id = ?1", params![job.id])?;
        tx.commit()?;
        Ok(())
    }

    pub fn image(&self, job_id: &str) -> Result<Option<Vec<u8>>, StoreError> {
        Ok(self.db.query_row("SELECT exr FROM images WHERE job_id = ?1", params![job_id], |r| r.get(0)).optional()?)
    }

    /// Every job, with unfinished ones restored to their checkpointed progress.
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
        for row in rows {
            let (id, spec, state, error, submitted, started, finished) = row?;
            let spec: JobSpec =
                serde_json::from_str(&spec).map_err(|e| StoreError::Corrupt(format!("job {id}: {e}")))?;
            let mut job = Job::new(id.clone(), spec, submitted);
            job.state =
                JobState::parse(&state).ok_or_else(|| StoreError::Corrupt(format!("job {id}: state '{state}'")))?;
            job.error = error;
            job.started_ms = started;
            job.finished_ms = finished;
            if !job.state.is_final() {
                let mut t = self.db.prepare("SELECT tile, folded, sums FROM tiles WHERE job_id = ?1")?;
                let tiles = t.query_map(params![id], |r| {
                    Ok((r.get::<_, i64>(0)?, r.get::<_, i64>(1)?, r.get::<_, Vec<u8>>(2)?))
                })?;
                for tile in tiles {
                    let (tile, folded, blob) = tile?;
                    let Some(rect) = job.tiles.get(tile as usize).copied() else { continue };
                    let sums = PartialSums::decode(rect, &blob)
                        .map_err(|e| StoreError::Corrupt(format!("job {id} tile {tile}: {e}")))?;
                    job.restore_tile(tile as usize, folded as u32, sums);
                }
            }
            jobs.push(job);
        }
        Ok(jobs)
    }
}
