//! The registry: every job record this process knows, by owner and id, with the queue of the
//! waiting ones; one lock guards both.
//!
//! Job records belong to a tenant (the authenticated caller; `""` when authentication is off):
//! the registry is keyed by `(tenant, id)`, so another tenant's Get/Watch/Cancel never reaches a
//! record it does not own. Results are shared across tenants through the cache, which is keyed
//! by the content hash alone: identical work computes once, but records are never shared.

use std::collections::{HashMap, VecDeque};
use std::sync::Arc;

use super::cache::ResultCache;
use super::entry::{JobEntry, JobKey};
use super::queue::FairQueue;
use super::state::JobState;

/// The job records and the waiting queue, under the manager's one lock.
#[derive(Default)]
pub(super) struct Registry {
    pub(super) jobs: HashMap<JobKey, Arc<JobEntry>>,
    /// Keys in submission order (oldest first), for listing and record eviction.
    pub(super) order: VecDeque<JobKey>,
    pub(super) queue: FairQueue,
    /// Set at shutdown: the dispatchers stop once the queue is empty.
    pub(super) stopped: bool,
}

impl Registry {
    /// Records `entry` as the newest (replacing a record of the same key), then forgets the
    /// oldest terminal records beyond `max_records`.
    pub(super) fn insert(&mut self, entry: Arc<JobEntry>, max_records: usize) {
        let key = entry.key();
        if self.jobs.insert(key.clone(), entry).is_some() {
            self.order.retain(|x| x != &key);
        }
        self.order.push_back(key);
        // Forget the oldest terminal records beyond the limit; live jobs are never forgotten.
        let mut i = 0;
        while self.jobs.len() > max_records && i < self.order.len() {
            let terminal = self
                .jobs
                .get(&self.order[i])
                .is_none_or(|e| e.state().is_terminal());
            if terminal {
                if let Some(old) = self.order.remove(i) {
                    self.jobs.remove(&old);
                }
            } else {
                i += 1;
            }
        }
    }

    /// The registry's entry for `key`, with the result of a succeeded record restored from the
    /// record log loaded from the cache; such a record whose result the cache no longer holds
    /// is forgotten (`None`: a resubmission recomputes it).
    pub(super) fn hydrated(&mut self, key: &JobKey, cache: &ResultCache) -> Option<Arc<JobEntry>> {
        let e = self.jobs.get(key)?.clone();
        let needs_result = {
            let s = e.tx.borrow();
            s.state == JobState::Succeeded && s.result.is_none()
        };
        if !needs_result {
            return Some(e);
        }
        match cache.get(&e.id) {
            Some(bytes) => {
                e.tx.send_modify(|s| s.result = Some(bytes));
                Some(e)
            }
            None => {
                self.jobs.remove(key);
                self.order.retain(|k| k != key);
                None
            }
        }
    }
}
