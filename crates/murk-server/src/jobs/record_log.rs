//! The log of finished job records (the embedded default's memory across restarts): one JSON
//! line per job that reached a terminal state, appended to `--cache-dir/records.log`. At start
//! the server reads it back, so Get, Watch and List answer for jobs that ended before a restart
//! or a crash: failed and cancelled jobs with their errors, and succeeded jobs of every tenant
//! (their results come from the result cache on demand; one the cache evicted is forgotten and
//! recomputed on resubmission). The journal (`journal.rs`) covers jobs that had not finished.
//!
//! Appends of computed jobs are fsynced (≈ 0.17 ms, docs/benchmarks.md); records of cache
//! hits are only written, which a killed process keeps (the kernel holds the bytes) and only a
//! power loss can drop. The newest line of a (tenant, id) wins. A line torn by a crash fails to
//! parse and is skipped. The log is rewritten with only the retained records at start and
//! whenever it has grown past a bound.

use std::io::{BufRead, Write};
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::SystemTime;

use serde::{Deserialize, Serialize};

use super::error_codec::{decode_error, encode_error};
use super::state::{from_unix_ms, unix_ms, JobSnapshot, JobState};
use murk::error::MurkError;

/// One finished job as the log keeps it (no result bytes: those live in the result cache).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LoggedRecord {
    /// Owning tenant (`""` without authentication).
    pub tenant: String,
    /// Job id (content hash).
    pub id: String,
    /// Method name.
    pub method: String,
    /// `succeeded`, `failed` or `cancelled`.
    pub state: String,
    /// Submission time, ms since the Unix epoch.
    pub create_ms: u64,
    /// Start time, ms since the Unix epoch (absent when it never ran).
    pub start_ms: Option<u64>,
    /// End time, ms since the Unix epoch.
    pub end_ms: u64,
    /// Served from the result cache.
    pub cached: bool,
    /// The error of a failed or cancelled job: kind and two detail strings.
    pub error: Option<(String, String, String)>,
}

impl LoggedRecord {
    /// The record of `tenant`'s job `snap` as it ends in `state` with `error`; `None` for a
    /// non-terminal state.
    pub fn ended(
        tenant: &str,
        snap: &JobSnapshot,
        state: JobState,
        error: Option<&MurkError>,
    ) -> Option<Self> {
        if !state.is_terminal() {
            return None;
        }
        Some(Self {
            tenant: tenant.to_string(),
            id: snap.id.clone(),
            method: snap.method.clone(),
            state: state.name().to_string(),
            create_ms: unix_ms(snap.create_time),
            start_ms: snap.start_time.map(unix_ms),
            end_ms: unix_ms(snap.end_time.unwrap_or_else(SystemTime::now)),
            cached: snap.cached,
            error: error.map(|e| {
                let (k, a, b) = encode_error(e);
                (k.to_string(), a, b)
            }),
        })
    }

    /// The job as a snapshot, without its result (a succeeded one gets it from the cache).
    /// `None` when the state is not one this log writes.
    pub fn snapshot(&self) -> Option<JobSnapshot> {
        let state = JobState::from_name(&self.state).filter(|s| s.is_terminal())?;
        Some(JobSnapshot {
            id: self.id.clone(),
            method: self.method.clone(),
            state,
            progress: if state == JobState::Succeeded {
                1.0
            } else {
                0.0
            },
            stage: if state == JobState::Succeeded {
                "done".into()
            } else {
                self.state.clone()
            },
            create_time: from_unix_ms(self.create_ms),
            start_time: self.start_ms.map(from_unix_ms),
            end_time: Some(from_unix_ms(self.end_ms)),
            cached: self.cached,
            result: None,
            error: self.error.as_ref().map(|(k, a, b)| decode_error(k, a, b)),
        })
    }
}

/// An append-only file of [`LoggedRecord`] lines.
#[derive(Debug)]
pub struct RecordLog {
    path: PathBuf,
    /// The open file, the lines appended since the last rewrite, and the number of rewrites.
    file: Mutex<(std::fs::File, usize, u64)>,
}

fn open_append(path: &Path) -> std::io::Result<std::fs::File> {
    std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
}

impl RecordLog {
    /// Opens (creating) the log at `path`.
    pub fn open(path: &Path) -> std::io::Result<Self> {
        Ok(Self {
            path: path.to_path_buf(),
            file: Mutex::new((open_append(path)?, 0, 0)),
        })
    }

    /// Appends `record`; with `sync`, returns once it is on disk. Returns the log's rewrite
    /// count at the time (see [`RecordLog::rewrites`]).
    pub fn append(&self, record: &LoggedRecord, sync: bool) -> std::io::Result<u64> {
        let mut line = serde_json::to_vec(record).map_err(std::io::Error::other)?;
        line.push(b'\n');
        let mut guard = self.file.lock().unwrap_or_else(|p| p.into_inner());
        // One write per line: a crash tears at most the last line.
        guard.0.write_all(&line)?;
        guard.1 += 1;
        if sync {
            guard.0.sync_data()?;
        }
        Ok(guard.2)
    }

    /// How many times the log was rewritten: a line appended before a rewrite that did not
    /// gather its record is gone, and its writer appends it again.
    pub fn rewrites(&self) -> u64 {
        self.file.lock().unwrap_or_else(|p| p.into_inner()).2
    }

    /// Lines appended since the log was last rewritten.
    pub fn appended(&self) -> usize {
        self.file.lock().unwrap_or_else(|p| p.into_inner()).1
    }

    /// The records, newest line per (tenant, id), oldest first; unreadable lines are skipped.
    pub fn load(&self) -> std::io::Result<Vec<LoggedRecord>> {
        let f = match std::fs::File::open(&self.path) {
            Ok(f) => f,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(e),
        };
        let mut all = Vec::new();
        let mut skipped = 0usize;
        for line in std::io::BufReader::new(f).split(b'\n') {
            match serde_json::from_slice::<LoggedRecord>(&line?) {
                Ok(r) => all.push(r),
                Err(_) => skipped += 1,
            }
        }
        if skipped > 0 {
            tracing::warn!(skipped, path = %self.path.display(), "unreadable job-record lines skipped");
        }
        // Keep each key's last line, in the order of those last lines.
        let mut seen = std::collections::HashSet::new();
        let mut newest: Vec<LoggedRecord> = all
            .into_iter()
            .rev()
            .filter(|r| seen.insert((r.tenant.clone(), r.id.clone())))
            .collect();
        newest.reverse();
        Ok(newest)
    }

    /// Replaces the log's content with `records` (temporary file, fsync, rename, directory
    /// fsync); appends go on after them.
    pub fn rewrite(&self, records: &[LoggedRecord]) -> std::io::Result<()> {
        let mut guard = self.file.lock().unwrap_or_else(|p| p.into_inner());
        let tmp = self
            .path
            .with_extension(format!("tmp{}", std::process::id()));
        let mut body = Vec::new();
        for r in records {
            serde_json::to_writer(&mut body, r).map_err(std::io::Error::other)?;
            body.push(b'\n');
        }
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(&body)?;
        f.sync_all()?;
        std::fs::rename(&tmp, &self.path)?;
        if let Some(dir) = self.path.parent() {
            std::fs::File::open(dir)?.sync_all()?;
        }
        *guard = (open_append(&self.path)?, 0, guard.2 + 1);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    fn record(tenant: &str, id: &str, state: JobState, error: Option<MurkError>) -> LoggedRecord {
        let mut snap = JobSnapshot::queued(id, "tof_depth");
        snap.start_time = Some(snap.create_time + Duration::from_millis(5));
        LoggedRecord::ended(tenant, &snap, state, error.as_ref()).unwrap()
    }

    #[test]
    fn records_round_trip_through_the_file_newest_line_winning() {
        let dir = tempfile::tempdir().unwrap();
        let log = RecordLog::open(&dir.path().join("records.log")).unwrap();
        let failed = record(
            "alpha",
            "a1",
            JobState::Failed,
            Some(MurkError::invalid("phase", "must be finite")),
        );
        log.append(
            &record(
                "alpha",
                "a1",
                JobState::Cancelled,
                Some(MurkError::Cancelled),
            ),
            true,
        )
        .unwrap();
        log.append(&record("beta", "b1", JobState::Succeeded, None), false)
            .unwrap();
        log.append(&failed, true).unwrap();
        assert_eq!(log.appended(), 3);
        let back = RecordLog::open(&dir.path().join("records.log"))
            .unwrap()
            .load()
            .unwrap();
        assert_eq!(back.len(), 2);
        assert_eq!(back[0].id, "b1");
        assert_eq!(back[1], failed);
        let snap = back[1].snapshot().unwrap();
        assert_eq!(snap.state, JobState::Failed);
        assert!(matches!(
            snap.error,
            Some(MurkError::InvalidArgument { ref field, .. }) if field == "phase"
        ));
        assert!(snap.start_time.is_some() && snap.end_time.is_some());
    }

    #[test]
    fn a_torn_last_line_is_skipped_and_a_rewrite_keeps_only_what_it_is_given() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("records.log");
        let log = RecordLog::open(&path).unwrap();
        log.append(&record("", "x", JobState::Succeeded, None), true)
            .unwrap();
        // A crash in the middle of a line.
        std::fs::OpenOptions::new()
            .append(true)
            .open(&path)
            .unwrap()
            .write_all(b"{\"tenant\":\"\",\"id\":\"y\",\"meth")
            .unwrap();
        let back = log.load().unwrap();
        assert_eq!(back.len(), 1);
        log.rewrite(&back).unwrap();
        assert_eq!(log.appended(), 0);
        log.append(
            &record("", "z", JobState::Cancelled, Some(MurkError::Cancelled)),
            true,
        )
        .unwrap();
        let ids: Vec<String> = log.load().unwrap().into_iter().map(|r| r.id).collect();
        assert_eq!(ids, ["x", "z"]);
    }
}
