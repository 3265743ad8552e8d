//! Event metrics of the job system (Prometheus families, shared by reference): jobs reaching a
//! terminal state, compute time and queue wait per method. Scrape-time gauges (queue depth,
//! running jobs, cache counters) are read from the manager by `telemetry`, not kept here.

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::histogram::{exponential_buckets, Histogram};
use prometheus_client::registry::Registry;

/// Labels of `murk_jobs_total`.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct MethodState {
    /// Job method (`tof_depth`, ...).
    pub method: String,
    /// Terminal state (`succeeded`, `failed`, `cancelled`, `aborted`).
    pub state: String,
}

/// Labels of the per-method histograms.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct MethodLabel {
    /// Job method.
    pub method: String,
}

fn seconds_histogram() -> Histogram {
    // 5 ms … ~82 s: cache-sized ToF frames up to full-size photometric stereo.
    Histogram::new(exponential_buckets(0.005, 2.0, 15))
}

/// The job system's event metrics. Cheap to clone (the families are shared).
#[derive(Clone, Debug)]
pub struct JobMetrics {
    /// Computed jobs by method and terminal state.
    pub jobs_total: Family<MethodState, Counter>,
    /// Compute time of jobs that ran, seconds.
    pub job_duration_seconds: Family<MethodLabel, Histogram, fn() -> Histogram>,
    /// Time from acceptance to a worker starting the job, seconds.
    pub queue_wait_seconds: Family<MethodLabel, Histogram, fn() -> Histogram>,
    /// Submissions answered with a finished result (a record or the result cache).
    pub cache_hits: Counter,
    /// Submissions that queued a new computation.
    pub cache_misses: Counter,
}

impl Default for JobMetrics {
    fn default() -> Self {
        Self {
            jobs_total: Family::default(),
            job_duration_seconds: Family::new_with_constructor(seconds_histogram),
            queue_wait_seconds: Family::new_with_constructor(seconds_histogram),
            cache_hits: Counter::default(),
            cache_misses: Counter::default(),
        }
    }
}

impl JobMetrics {
    /// Registers the families (names relative to the registry's `murk` prefix).
    pub fn register(&self, registry: &mut Registry) {
        registry.register(
            "jobs",
            "Jobs that reached a terminal state after being queued, by method and state",
            self.jobs_total.clone(),
        );
        registry.register(
            "job_duration_seconds",
            "Compute time of jobs, by method",
            self.job_duration_seconds.clone(),
        );
        registry.register(
            "queue_wait_seconds",
            "Time jobs waited in the queue before a worker started them, by method",
            self.queue_wait_seconds.clone(),
        );
        registry.register(
            "cache_hits",
            "Submissions answered with an already computed result, without recomputation",
            self.cache_hits.clone(),
        );
        registry.register(
            "cache_misses",
            "Submissions that queued a new computation",
            self.cache_misses.clone(),
        );
    }

    pub(crate) fn finished(&self, method: &str, state: &str) {
        self.jobs_total
            .get_or_create(&MethodState {
                method: method.to_string(),
                state: state.to_string(),
            })
            .inc();
    }

    pub(crate) fn ran(&self, method: &str, seconds: f64) {
        self.job_duration_seconds
            .get_or_create(&MethodLabel {
                method: method.to_string(),
            })
            .observe(seconds);
    }

    pub(crate) fn waited(&self, method: &str, seconds: f64) {
        self.queue_wait_seconds
            .get_or_create(&MethodLabel {
                method: method.to_string(),
            })
            .observe(seconds);
    }
}
