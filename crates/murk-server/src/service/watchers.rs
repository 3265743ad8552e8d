//! Bounds on `WatchJob` streams: how many watch one job and one tenant, and how many result
//! bytes the streams may hold at once.
//!
//! A watcher's last message carries the job's result. Each stream encodes its own copy into
//! its HTTP/2 buffers, where it stays until the client has read it, so N watchers of a 2.6 MB
//! result held N copies: 100 of them raised the server's RSS by 440 MB, and rounds of 300 that
//! never read pushed it to 1.45 GB. Here every embedded result takes its size from one
//! budget, released when its stream is dropped (sent and done, or cancelled). When the budget
//! is spent the message goes out with `result_omitted` set, as for a result over the unary
//! limit, and the client fetches it with `GetJobResult`, whose 1 MiB chunks are produced as the
//! client reads. Memory then stays within the budget however many clients watch.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use tokio::sync::{OwnedSemaphorePermit, Semaphore};

/// Settings of [`Watchers`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct WatchLimits {
    /// Watch streams of one job at once (per tenant: another tenant's job is another job).
    pub max_per_job: usize,
    /// Watch streams of one tenant at once, over all its jobs.
    pub max_per_tenant: usize,
    /// Result bytes that all watch streams together may hold in their messages.
    pub result_budget_bytes: u64,
}

impl Default for WatchLimits {
    fn default() -> Self {
        Self {
            max_per_job: 64,
            max_per_tenant: 512,
            result_budget_bytes: 32 << 20,
        }
    }
}

/// Budget units are KiB, so the semaphore's u32 permits cover any budget up to 4 TiB.
const UNIT_BYTES: u64 = 1024;

/// Why a watch stream was refused.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum WatchRefusal {
    /// The job has `max_per_job` watchers.
    Job(usize),
    /// The tenant has `max_per_tenant` watchers.
    Tenant(usize),
}

#[derive(Default)]
struct Counts {
    per_job: HashMap<(String, String), usize>,
    per_tenant: HashMap<String, usize>,
}

/// The live watch streams and the result budget they share. Cheap to clone.
#[derive(Clone)]
pub struct Watchers {
    limits: WatchLimits,
    counts: Arc<Mutex<Counts>>,
    budget: Arc<Semaphore>,
}

impl Watchers {
    /// No streams yet, the whole budget free.
    pub fn new(limits: WatchLimits) -> Self {
        let units = (limits.result_budget_bytes / UNIT_BYTES).min(u64::from(u32::MAX)) as usize;
        Self {
            limits,
            counts: Arc::default(),
            budget: Arc::new(Semaphore::new(units.min(Semaphore::MAX_PERMITS))),
        }
    }

    /// Counts a new stream of `tenant`'s job `id`, or refuses it; the slot ends the count when
    /// dropped.
    pub fn open(&self, tenant: &str, id: &str) -> Result<WatchSlot, WatchRefusal> {
        let mut c = self.counts.lock().unwrap_or_else(|p| p.into_inner());
        let key = (tenant.to_string(), id.to_string());
        let job = c.per_job.get(&key).copied().unwrap_or(0);
        if job >= self.limits.max_per_job {
            return Err(WatchRefusal::Job(self.limits.max_per_job));
        }
        let all = c.per_tenant.get(tenant).copied().unwrap_or(0);
        if all >= self.limits.max_per_tenant {
            return Err(WatchRefusal::Tenant(self.limits.max_per_tenant));
        }
        c.per_job.insert(key.clone(), job + 1);
        c.per_tenant.insert(tenant.to_string(), all + 1);
        Ok(WatchSlot {
            counts: self.counts.clone(),
            key,
        })
    }

    /// A share of the budget for a message carrying `bytes` of result, if that much is free
    /// now (never waits: a watcher is better served at once by `GetJobResult`).
    pub fn reserve(&self, bytes: usize) -> Option<OwnedSemaphorePermit> {
        let units = (bytes as u64).div_ceil(UNIT_BYTES).max(1);
        let units = u32::try_from(units).ok()?;
        self.budget.clone().try_acquire_many_owned(units).ok()
    }

    /// Streams open now: `(for this job, for this tenant)`.
    #[cfg(test)]
    fn open_count(&self, tenant: &str, id: &str) -> (usize, usize) {
        let c = self.counts.lock().unwrap_or_else(|p| p.into_inner());
        (
            c.per_job
                .get(&(tenant.to_string(), id.to_string()))
                .copied()
                .unwrap_or(0),
            c.per_tenant.get(tenant).copied().unwrap_or(0),
        )
    }
}

/// One counted watch stream; dropping it ends the count.
pub struct WatchSlot {
    counts: Arc<Mutex<Counts>>,
    key: (String, String),
}

impl Drop for WatchSlot {
    fn drop(&mut self) {
        let mut c = self.counts.lock().unwrap_or_else(|p| p.into_inner());
        decrement(&mut c.per_job, &self.key);
        decrement(&mut c.per_tenant, &self.key.0);
    }
}

/// Decrements a count and removes it at zero, so the maps hold only live streams.
fn decrement<K: std::hash::Hash + Eq>(map: &mut HashMap<K, usize>, key: &K) {
    if let Some(n) = map.get_mut(key) {
        *n -= 1;
        if *n == 0 {
            map.remove(key);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn streams_are_bounded_per_job_and_per_tenant_and_slots_free_them() {
        let w = Watchers::new(WatchLimits {
            max_per_job: 2,
            max_per_tenant: 3,
            result_budget_bytes: 1 << 20,
        });
        let a1 = w.open("t", "a").unwrap();
        let _a2 = w.open("t", "a").unwrap();
        assert_eq!(w.open("t", "a").err(), Some(WatchRefusal::Job(2)));
        let _b1 = w.open("t", "b").unwrap();
        assert_eq!(w.open("t", "c").err(), Some(WatchRefusal::Tenant(3)));
        // Another tenant's streams count apart.
        let _u = w.open("u", "a").unwrap();
        drop(a1);
        assert_eq!(w.open_count("t", "a"), (1, 2));
        let _a3 = w.open("t", "a").unwrap();
        drop((_a2, _a3, _b1, _u));
        assert_eq!(w.open_count("t", "a"), (0, 0));
        assert!(w.counts.lock().unwrap().per_job.is_empty());
    }

    #[test]
    fn the_budget_is_shared_and_returns_when_permits_drop() {
        let w = Watchers::new(WatchLimits {
            result_budget_bytes: 10 * 1024,
            ..WatchLimits::default()
        });
        let big = w.reserve(6 * 1024).expect("6 KiB of 10");
        assert!(w.reserve(6 * 1024).is_none(), "only 4 KiB left");
        let small = w.reserve(3000).expect("3 KiB fits");
        drop(big);
        assert!(w.reserve(6 * 1024).is_some());
        drop(small);
        assert!(w.reserve(usize::MAX).is_none());
    }
}
