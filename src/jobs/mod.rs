//! Job system: bounded queue → dispatcher threads → rayon pool, with content-hash deduplication,
//! cooperative cancellation, progress snapshots and a byte-bounded result cache (memory + disk).
//! Knows nothing of gRPC: work is an opaque closure returning encoded result bytes.

mod backend;
mod cache;
mod error_codec;
mod journal;
mod manager;
mod metrics;
mod record_log;
pub mod redis;
mod state;

pub use backend::JobBackend;
pub use cache::{CacheStats, ResultCache};
pub use journal::{Journal, JournalEntry};
pub use manager::{
    JobHandle, JobManager, JobsConfig, JobsError, Submitted, WaiterGuard, Work,
    DEFAULT_CACHE_DIR_BYTES,
};
pub use metrics::{JobMetrics, MethodLabel, MethodState};
pub use record_log::{LoggedRecord, RecordLog};
pub use state::{JobSnapshot, JobState, ResultBytes};

#[cfg(test)]
mod tests;
