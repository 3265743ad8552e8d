//! Job system: bounded queue → dispatcher threads → rayon pool, with content-hash deduplication,
//! cooperative cancellation, progress snapshots and a byte-bounded result cache (memory + disk).
//! Knows nothing of gRPC: work is an opaque closure returning encoded result bytes.

mod backend;
mod cache;
mod config;
mod dispatch;
mod entry;
mod error_codec;
mod handle;
mod journal;
mod manager;
mod metrics;
mod queue;
mod record_log;
pub mod redis;
mod registry;
mod shared;
mod state;

pub use backend::JobBackend;
pub use cache::{CacheStats, ResultCache};
pub use config::{JobsConfig, DEFAULT_CACHE_DIR_BYTES};
pub use entry::Work;
pub use handle::{JobHandle, Submitted, WaiterGuard};
pub use journal::{Journal, JournalEntry};
pub use manager::{JobManager, JobsError};
pub use metrics::{JobMetrics, MethodLabel, MethodState};
pub use record_log::{LoggedRecord, RecordLog};
pub use state::{JobSnapshot, JobState, ResultBytes};

#[cfg(test)]
mod tests;
