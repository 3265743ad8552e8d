//! What a job looks like from outside: its state machine and snapshots.

use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use murk::error::MurkError;

/// Lifecycle of a job. Terminal states never change again.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum JobState {
    /// Waiting in the bounded queue.
    Queued,
    /// A worker is computing it.
    Running,
    /// Finished; the result is available (and cached).
    Succeeded,
    /// Finished with an error.
    Failed,
    /// Stopped by the cancel RPC, server shutdown, or because every caller went away.
    Cancelled,
}

impl JobState {
    /// The lowercase name stores outside the process use (`queued`, …, `cancelled`).
    pub fn name(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Succeeded => "succeeded",
            JobState::Failed => "failed",
            JobState::Cancelled => "cancelled",
        }
    }

    /// Inverse of [`JobState::name`].
    pub fn from_name(name: &str) -> Option<Self> {
        Some(match name {
            "queued" => JobState::Queued,
            "running" => JobState::Running,
            "succeeded" => JobState::Succeeded,
            "failed" => JobState::Failed,
            "cancelled" => JobState::Cancelled,
            _ => return None,
        })
    }

    /// True for `Succeeded`, `Failed` and `Cancelled`.
    pub fn is_terminal(self) -> bool {
        matches!(
            self,
            JobState::Succeeded | JobState::Failed | JobState::Cancelled
        )
    }
}

/// Milliseconds since the Unix epoch (0 before it): how stores outside the process keep times.
pub(crate) fn unix_ms(t: SystemTime) -> u64 {
    t.duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// Inverse of [`unix_ms`].
pub(crate) fn from_unix_ms(ms: u64) -> SystemTime {
    UNIX_EPOCH + Duration::from_millis(ms)
}

/// Result payload of a finished job: the encoded result message, shared without copying.
pub type ResultBytes = Arc<Vec<u8>>;

/// A point-in-time view of a job, published to watchers on every change.
#[derive(Clone, Debug)]
pub struct JobSnapshot {
    /// Content hash of the canonical request.
    pub id: String,
    /// Method name, e.g. `tof_depth`.
    pub method: String,
    /// Current state.
    pub state: JobState,
    /// Overall progress in [0, 1].
    pub progress: f32,
    /// Current algorithm stage.
    pub stage: String,
    /// When the job was first submitted (or found in the cache).
    pub create_time: SystemTime,
    /// When a worker started it.
    pub start_time: Option<SystemTime>,
    /// When it reached a terminal state.
    pub end_time: Option<SystemTime>,
    /// Served from the result cache without recomputation.
    pub cached: bool,
    /// Encoded result, once `Succeeded`.
    pub result: Option<ResultBytes>,
    /// The error, once `Failed` (or `Cancelled`).
    pub error: Option<MurkError>,
}

impl JobSnapshot {
    pub(crate) fn queued(id: &str, method: &str) -> Self {
        Self {
            id: id.to_string(),
            method: method.to_string(),
            state: JobState::Queued,
            progress: 0.0,
            stage: "queued".to_string(),
            create_time: SystemTime::now(),
            start_time: None,
            end_time: None,
            cached: false,
            result: None,
            error: None,
        }
    }

    pub(crate) fn from_cache(id: &str, method: &str, result: ResultBytes) -> Self {
        let now = SystemTime::now();
        Self {
            state: JobState::Succeeded,
            progress: 1.0,
            stage: "done".to_string(),
            start_time: None,
            end_time: Some(now),
            cached: true,
            result: Some(result),
            ..Self::queued(id, method)
        }
    }
}
