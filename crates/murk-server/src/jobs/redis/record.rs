//! A job record as Redis stores it (a hash of strings) ↔ the [`JobSnapshot`] handlers see.

use std::collections::HashMap;
use std::time::SystemTime;

use crate::jobs::error_codec::decode_error;
use crate::jobs::state::{from_unix_ms, unix_ms, JobSnapshot, JobState, ResultBytes};

/// The fields of one record (`HGETALL`).
#[derive(Debug, Default, Clone)]
pub(super) struct Record {
    fields: HashMap<String, String>,
}

impl Record {
    /// `None` for a missing key (an empty hash).
    pub(super) fn from_fields(fields: HashMap<String, String>) -> Option<Self> {
        (!fields.is_empty()).then_some(Self { fields })
    }

    pub(super) fn get(&self, k: &str) -> &str {
        self.fields.get(k).map_or("", String::as_str)
    }

    pub(super) fn state(&self) -> Option<JobState> {
        JobState::from_name(self.get("state"))
    }

    /// The computation generation (changes when a resubmission restarts the record).
    pub(super) fn gen(&self) -> &str {
        self.get("gen")
    }

    pub(super) fn version(&self) -> u64 {
        self.get("version").parse().unwrap_or(0)
    }

    /// Cancellation was requested (the record must not be reused by a resubmission).
    pub(super) fn cancelling(&self) -> bool {
        self.get("cancel") == "1"
    }

    /// Whether a new submission of the same request may attach to this record.
    pub(super) fn reusable(&self) -> bool {
        match self.state() {
            Some(JobState::Succeeded) => true,
            Some(JobState::Queued | JobState::Running) => !self.cancelling(),
            _ => false,
        }
    }

    /// The snapshot, with `result` attached to a succeeded job.
    pub(super) fn snapshot(&self, result: Option<ResultBytes>) -> Option<JobSnapshot> {
        let state = self.state()?;
        let time =
            |k: &str| -> Option<SystemTime> { Some(from_unix_ms(self.get(k).parse().ok()?)) };
        Some(JobSnapshot {
            id: self.get("id").to_string(),
            method: self.get("method").to_string(),
            state,
            progress: self.get("progress").parse().unwrap_or(0.0),
            stage: self.get("stage").to_string(),
            create_time: time("create_ms").unwrap_or_else(SystemTime::now),
            start_time: time("start_ms"),
            end_time: time("end_ms"),
            cached: self.get("cached") == "1",
            result: if state == JobState::Succeeded {
                result
            } else {
                None
            },
            error: match state {
                JobState::Failed | JobState::Cancelled => Some(decode_error(
                    self.get("err_kind"),
                    self.get("err_a"),
                    self.get("err_b"),
                )),
                _ => None,
            },
        })
    }
}

/// Milliseconds since the Unix epoch.
pub(super) fn now_ms() -> u64 {
    unix_ms(SystemTime::now())
}

#[cfg(test)]
mod tests {
    use super::*;
    use murk::error::MurkError;

    #[test]
    fn snapshot_reads_state_times_and_errors() {
        let fields: HashMap<String, String> = [
            ("id", "ab"),
            ("method", "tof_depth"),
            ("state", "failed"),
            ("progress", "0.5"),
            ("stage", "failed"),
            ("create_ms", "1000"),
            ("end_ms", "3000"),
            ("err_kind", "invalid"),
            ("err_a", "phase"),
            ("err_b", "bad"),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect();
        let r = Record::from_fields(fields).unwrap();
        let s = r.snapshot(None).unwrap();
        assert_eq!(s.state, JobState::Failed);
        assert_eq!(s.progress, 0.5);
        assert_eq!(s.create_time, from_unix_ms(1000));
        assert_eq!(s.error, Some(MurkError::invalid("phase", "bad")));
        assert!(!r.reusable());
        assert!(Record::from_fields(HashMap::new()).is_none());
    }
}
