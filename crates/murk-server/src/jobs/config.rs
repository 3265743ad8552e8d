//! Sizing of the job system: every limit is explicit.

use std::path::PathBuf;
use std::time::Duration;

/// Default bound of the cache directory: 8 GiB.
pub const DEFAULT_CACHE_DIR_BYTES: u64 = 8 << 30;

/// Sizing of the job system. Every limit is explicit.
#[derive(Clone, Debug)]
pub struct JobsConfig {
    /// Threads of the rayon compute pool (0 = number of cores).
    pub workers: usize,
    /// Jobs computed at the same time, each using the whole pool for its inner loops.
    pub concurrent_jobs: usize,
    /// Jobs that may wait in the queue; one more is refused with a retry hint.
    pub queue_capacity: usize,
    /// In-memory result cache budget in bytes.
    pub cache_bytes: u64,
    /// Optional directory where results persist across restarts. It also holds the journal of
    /// accepted jobs (`journal/`), so queued and running jobs survive a crash.
    pub cache_dir: Option<PathBuf>,
    /// Largest total size of the entry files in `cache_dir`; least recently used go first.
    pub cache_dir_bytes: u64,
    /// Smallest client back-off suggested when the queue is full; the hint is the estimated
    /// time until a slot frees when that is longer, +0–50 % jitter.
    pub retry_after: Duration,
    /// Job records kept for Get/List; the oldest terminal ones are forgotten beyond this
    /// (their results stay in the cache).
    pub max_job_records: usize,
}

impl Default for JobsConfig {
    fn default() -> Self {
        Self {
            workers: 0,
            concurrent_jobs: 1,
            queue_capacity: 64,
            cache_bytes: 512 << 20,
            cache_dir: None,
            cache_dir_bytes: DEFAULT_CACHE_DIR_BYTES,
            retry_after: Duration::from_millis(500),
            max_job_records: 10_000,
        }
    }
}
