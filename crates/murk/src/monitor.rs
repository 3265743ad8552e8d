//! Progress reporting and cooperative cancellation for long-running algorithms.
//!
//! Algorithms take a `&Monitor`, call [`Monitor::progress`] at stage boundaries and iterations, and
//! call [`Monitor::checkpoint`] inside their outer loops so a cancel request (RPC, shutdown, or the
//! last caller going away) stops the worker within one iteration.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use crate::error::{MurkError, Result};

/// Callback receiving `(stage, fraction)` where `fraction ∈ [0, 1]` is overall job progress.
pub type ProgressSink = Arc<dyn Fn(&str, f32) + Send + Sync>;

/// Cancellation flag plus progress sink handed to every algorithm.
#[derive(Clone)]
pub struct Monitor {
    cancelled: Arc<AtomicBool>,
    sink: Option<ProgressSink>,
    /// Sub-range `[lo, hi)` of overall progress this monitor maps its local fractions into.
    span: (f32, f32),
}

impl Default for Monitor {
    fn default() -> Self {
        Self::noop()
    }
}

impl std::fmt::Debug for Monitor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Monitor")
            .field("cancelled", &self.is_cancelled())
            .field("span", &self.span)
            .finish()
    }
}

impl Monitor {
    /// A monitor that never cancels and discards progress (library callers, tests).
    pub fn noop() -> Self {
        Self {
            cancelled: Arc::new(AtomicBool::new(false)),
            sink: None,
            span: (0.0, 1.0),
        }
    }

    /// A monitor observing `cancelled` and reporting to `sink`.
    pub fn new(cancelled: Arc<AtomicBool>, sink: Option<ProgressSink>) -> Self {
        Self {
            cancelled,
            sink,
            span: (0.0, 1.0),
        }
    }

    /// True once cancellation was requested.
    pub fn is_cancelled(&self) -> bool {
        self.cancelled.load(Ordering::Relaxed)
    }

    /// Requests cancellation (visible to every clone).
    pub fn cancel(&self) {
        self.cancelled.store(true, Ordering::Relaxed);
    }

    /// Returns `Err(Cancelled)` if cancellation was requested. Call this inside outer loops.
    pub fn checkpoint(&self) -> Result<()> {
        if self.is_cancelled() {
            Err(MurkError::Cancelled)
        } else {
            Ok(())
        }
    }

    /// The same cancellation without progress reports: for work running beside other work
    /// under one span (parallel strips), whose caller reports the progress of all of it.
    pub fn silent(&self) -> Monitor {
        Monitor {
            cancelled: self.cancelled.clone(),
            sink: None,
            span: self.span,
        }
    }

    /// Reports `fraction ∈ [0, 1]` of this monitor's span, under the name `stage`.
    pub fn progress(&self, stage: &str, fraction: f32) {
        if let Some(sink) = &self.sink {
            let f = fraction.clamp(0.0, 1.0);
            sink(stage, self.span.0 + (self.span.1 - self.span.0) * f);
        }
    }

    /// A child monitor whose local progress `[0, 1]` maps to `[lo, hi]` of this one's.
    /// Shares the cancellation flag.
    pub fn sub(&self, lo: f32, hi: f32) -> Monitor {
        let (a, b) = self.span;
        Monitor {
            cancelled: self.cancelled.clone(),
            sink: self.sink.clone(),
            span: (a + (b - a) * lo, a + (b - a) * hi),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex;

    #[test]
    fn sub_monitor_maps_progress_and_shares_cancel() {
        let seen = Arc::new(Mutex::new(Vec::new()));
        let s2 = seen.clone();
        let m = Monitor::new(
            Arc::new(AtomicBool::new(false)),
            Some(Arc::new(move |st: &str, f: f32| {
                s2.lock().unwrap().push((st.to_string(), f))
            })),
        );
        let child = m.sub(0.5, 1.0);
        child.progress("fine", 0.5);
        assert_eq!(seen.lock().unwrap()[0], ("fine".to_string(), 0.75));
        assert!(child.checkpoint().is_ok());
        m.cancel();
        assert_eq!(child.checkpoint(), Err(MurkError::Cancelled));
    }
}
