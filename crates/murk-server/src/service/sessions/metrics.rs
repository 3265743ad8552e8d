//! Session metrics: `murk_session_frames_total{method,outcome}`,
//! `murk_session_frame_latency_seconds{method}` (a frame's arrival to its result) and
//! `murk_sessions_open{method}`.

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{exponential_buckets, Histogram};
use prometheus_client::registry::Registry;

/// Labels of `murk_session_frames_total`.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct FrameOutcome {
    /// `tof_depth` or `rectified_stereo`.
    pub method: &'static str,
    /// `received`, `computed`, `failed`, `superseded` or `deadline`.
    pub outcome: &'static str,
}

/// Labels by method.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct SessionMethodLabel {
    /// `tof_depth` or `rectified_stereo`.
    pub method: &'static str,
}

/// The session families. Cheap to clone (shared).
#[derive(Clone, Debug)]
pub struct SessionMetrics {
    frames: Family<FrameOutcome, Counter>,
    latency: Family<SessionMethodLabel, Histogram, fn() -> Histogram>,
    open: Family<SessionMethodLabel, Gauge>,
}

fn frame_latency_histogram() -> Histogram {
    // 1 ms … ~30 s: a small stereo frame up to a large ToF frame behind a queue.
    Histogram::new(exponential_buckets(1e-3, 2.0, 16))
}

impl Default for SessionMetrics {
    fn default() -> Self {
        Self {
            frames: Family::default(),
            latency: Family::new_with_constructor(frame_latency_histogram),
            open: Family::default(),
        }
    }
}

impl SessionMetrics {
    /// Registers the families (names relative to the registry's `murk` prefix).
    pub fn register(&self, registry: &mut Registry) {
        registry.register(
            "session_frames",
            "Session frames by method and outcome (received, computed, failed, superseded, deadline)",
            self.frames.clone(),
        );
        registry.register(
            "session_frame_latency_seconds",
            "Time from a session frame's arrival to its result, by method",
            self.latency.clone(),
        );
        registry.register(
            "sessions_open",
            "Sensor sessions open on this replica, by method",
            self.open.clone(),
        );
    }

    /// Counts a frame event.
    pub fn frame(&self, method: &'static str, outcome: &'static str) {
        self.frames
            .get_or_create(&FrameOutcome { method, outcome })
            .inc();
    }

    /// Records a computed frame's latency, seconds.
    pub fn latency(&self, method: &'static str, seconds: f64) {
        self.latency
            .get_or_create(&SessionMethodLabel { method })
            .observe(seconds);
    }

    /// A session of `method` opened (`+1`) or ended (`-1`).
    pub fn open(&self, method: &'static str, delta: i64) {
        self.open
            .get_or_create(&SessionMethodLabel { method })
            .inc_by(delta);
    }
}
