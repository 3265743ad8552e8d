//! The order in which waiting jobs start.

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::sync::Arc;

use super::entry::JobEntry;

/// Waiting jobs: one FIFO per method. The next job comes from the waiting method that has
/// received the least compute time (fair queuing by time, not by job count): a method of
/// millisecond jobs is not held to one job per multi-second job of another. A method that comes
/// back after its queue ran empty starts level with the least-served active method, so idle time
/// earns no credit.
#[derive(Default)]
pub(super) struct FairQueue {
    by_method: BTreeMap<String, VecDeque<Arc<JobEntry>>>,
    /// Compute seconds charged to each method.
    served: HashMap<String, f64>,
    len: usize,
}

impl FairQueue {
    pub(super) fn push(&mut self, e: Arc<JobEntry>) {
        let q = self.by_method.entry(e.method.clone()).or_default();
        if q.is_empty() {
            let level = self
                .by_method
                .iter()
                .filter(|(m, q)| !q.is_empty() && **m != e.method)
                .filter_map(|(m, _)| self.served.get(m))
                .copied()
                .fold(f64::INFINITY, f64::min);
            let own = self.served.entry(e.method.clone()).or_insert(0.0);
            if level.is_finite() && *own < level {
                *own = level;
            }
        }
        self.by_method
            .get_mut(&e.method)
            .expect("inserted above")
            .push_back(e);
        self.len += 1;
    }

    pub(super) fn pop(&mut self) -> Option<Arc<JobEntry>> {
        let served = &self.served;
        let method = self
            .by_method
            .iter()
            .filter(|(_, q)| !q.is_empty())
            .map(|(m, _)| (m, served.get(m).copied().unwrap_or(0.0)))
            .min_by(|a, b| a.1.total_cmp(&b.1))?
            .0
            .clone();
        let e = self.by_method.get_mut(&method)?.pop_front()?;
        self.len -= 1;
        Some(e)
    }

    /// Charges `seconds` of compute to `method`.
    pub(super) fn charge(&mut self, method: &str, seconds: f64) {
        *self.served.entry(method.to_string()).or_insert(0.0) += seconds;
    }

    pub(super) fn remove(&mut self, entry: &Arc<JobEntry>) -> bool {
        let Some(q) = self.by_method.get_mut(&entry.method) else {
            return false;
        };
        let before = q.len();
        q.retain(|e| !Arc::ptr_eq(e, entry));
        let removed = before - q.len();
        self.len -= removed;
        removed > 0
    }

    pub(super) fn len(&self) -> usize {
        self.len
    }

    pub(super) fn is_empty(&self) -> bool {
        self.len == 0
    }
}
