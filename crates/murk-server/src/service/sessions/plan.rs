//! A session's configuration, validated once (`SessionConfig` → [`SessionPlan`]), and the
//! computation of one frame under it.

use std::time::Duration;

use crate::service::convert::{
    intrinsics_from_proto, stereo_images_from_proto, stereo_to_proto, tof_images_from_proto,
    tof_outputs_from_proto, tof_params_from_proto, tof_points_from_proto, tof_to_proto, Delivery,
    ImageLimits, OutputSelection, StereoConfig, TofPoints,
};
use crate::service::proto::v1 as pb;
use murk::camera::Intrinsics;
use murk::error::{MurkError, Result};
use murk::monitor::Monitor;
use murk::mvs::{Search, StereoTracker};
use murk::tof::{TofInput, TofParams, TofStart, TofTracker, MAX_SCATTER_GRID};

/// Most frames a session may queue.
pub const MAX_QUEUED_FRAMES: u32 = 64;
/// Longest accepted frame id, bytes.
pub const MAX_FRAME_ID_BYTES: usize = 256;

/// A ToF session's settings, validated for its frame size; each frame brings amplitude and
/// phase.
#[derive(Clone, Debug)]
pub struct TofSettings {
    /// The method's parameters.
    pub params: TofParams,
    /// The camera's intrinsics, when given.
    pub intrinsics: Option<Intrinsics>,
    /// The result images each frame returns, and their encoding.
    pub outputs: OutputSelection,
    /// Each frame's point cloud, when asked for.
    pub points: Option<TofPoints>,
    /// The block size on which warm frames solve the scatter (1: the frame's pixels).
    pub scatter_grid: usize,
}

/// The block size of a ToF session's warm frames when the configuration leaves it 0.
pub const DEFAULT_TOF_SCATTER_GRID: usize = 2;

/// What a session computes.
#[derive(Clone, Debug)]
pub enum SessionMethod {
    /// ToF depth in fog.
    Tof(Box<TofSettings>),
    /// Rectified stereo, its settings validated for the session's frame size.
    Stereo(Box<StereoConfig>),
}

impl SessionMethod {
    /// The method's name in metrics and logs (the one-shot job method's).
    pub fn name(&self) -> &'static str {
        match self {
            SessionMethod::Tof(_) => "tof_depth",
            SessionMethod::Stereo(_) => "rectified_stereo",
        }
    }
}

/// What a session carries from one frame to the next.
#[derive(Debug)]
pub enum SessionState {
    /// ToF frames start from the previous frame's scatter and weights.
    Tof(Box<TofTracker>),
    /// Stereo frames search a band around the previous frame's disparities.
    Stereo(Box<StereoTracker>),
}

/// A validated session configuration.
#[derive(Clone, Debug)]
pub struct SessionPlan {
    /// Frame width and height, pixels.
    pub dims: (usize, usize),
    /// The method and its settings.
    pub method: SessionMethod,
    /// The queue policy (UNSPECIFIED resolved to LATEST).
    pub policy: pb::QueuePolicy,
    /// Frames that may wait while one is computed.
    pub capacity: usize,
    /// Longest a frame may wait before its computation starts.
    pub deadline: Option<Duration>,
}

impl SessionPlan {
    /// Validates a configuration. Errors name fields relative to `SessionConfig`
    /// (`width`, `tof.modulation_frequency_hz`, `stereo.baseline`, `max_queued_frames`, ...).
    pub fn from_proto(c: &pb::SessionConfig, limits: &ImageLimits) -> Result<Self> {
        let (w, h) = (c.width as usize, c.height as usize);
        if w < 2 || h < 2 {
            return Err(MurkError::invalid(
                if w < 2 { "width" } else { "height" },
                format!("frames need at least 2x2 pixels, got {w}x{h}"),
            ));
        }
        if (w as u64) * (h as u64) > limits.max_pixels {
            return Err(MurkError::invalid(
                "width",
                format!(
                    "{w}x{h} frames exceed the server's limit of {} pixels per image",
                    limits.max_pixels
                ),
            ));
        }
        let method = match &c.method {
            None => {
                return Err(MurkError::invalid(
                    "method",
                    "one method (tof or stereo) must be set",
                ))
            }
            Some(pb::session_config::Method::Tof(t)) => {
                if t.amplitude.is_some() || t.phase.is_some() {
                    return Err(MurkError::invalid(
                        "tof.amplitude",
                        "the images come with each frame; leave them unset in the configuration",
                    ));
                }
                let params = tof_params_from_proto(t, w, h).map_err(|e| e.within("tof"))?;
                let outputs =
                    tof_outputs_from_proto(t, Delivery::Session).map_err(|e| e.within("tof"))?;
                let intrinsics = t.intrinsics.as_ref().map(intrinsics_from_proto);
                let points = tof_points_from_proto(t).map_err(|e| e.within("tof"))?;
                let scatter_grid = match c.tof_scatter_grid as usize {
                    0 => DEFAULT_TOF_SCATTER_GRID,
                    g if g <= MAX_SCATTER_GRID => g,
                    g => {
                        return Err(MurkError::invalid(
                            "tof_scatter_grid",
                            format!("must be 1 to {MAX_SCATTER_GRID} (0: the default), got {g}"),
                        ))
                    }
                };
                SessionMethod::Tof(Box::new(TofSettings {
                    params,
                    intrinsics,
                    outputs,
                    points,
                    scatter_grid,
                }))
            }
            Some(pb::session_config::Method::Stereo(s)) => {
                if s.left.is_some() || s.right.is_some() {
                    return Err(MurkError::invalid(
                        "stereo.left",
                        "the images come with each frame; leave them unset in the configuration",
                    ));
                }
                if c.tof_scatter_grid != 0 {
                    return Err(MurkError::invalid(
                        "tof_scatter_grid",
                        "applies to ToF sessions; leave it 0 for stereo",
                    ));
                }
                let config = StereoConfig::from_proto(s, w, h, Delivery::Session)
                    .map_err(|e| e.within("stereo"))?;
                SessionMethod::Stereo(Box::new(config))
            }
        };
        let policy = match pb::QueuePolicy::try_from(c.queue_policy) {
            Ok(pb::QueuePolicy::Unspecified) => pb::QueuePolicy::Latest,
            Ok(p) => p,
            Err(_) => {
                return Err(MurkError::invalid(
                    "queue_policy",
                    format!("unknown queue policy {}", c.queue_policy),
                ))
            }
        };
        let capacity = match c.max_queued_frames {
            0 if policy == pb::QueuePolicy::Fifo => 4,
            0 => 1,
            n if n > MAX_QUEUED_FRAMES => {
                return Err(MurkError::invalid(
                    "max_queued_frames",
                    format!("at most {MAX_QUEUED_FRAMES}, got {n}"),
                ))
            }
            n => n as usize,
        };
        let d = c.frame_deadline_seconds;
        if !(d.is_finite() && (0.0..=3600.0).contains(&d)) {
            return Err(MurkError::invalid(
                "frame_deadline_seconds",
                format!("must be finite, in [0, 3600] seconds (0 = none), got {d}"),
            ));
        }
        Ok(Self {
            dims: (w, h),
            method,
            policy,
            capacity,
            deadline: (d > 0.0).then(|| Duration::from_secs_f64(d)),
        })
    }

    /// The state a new session starts with.
    pub fn initial_state(&self) -> Result<SessionState> {
        Ok(match &self.method {
            SessionMethod::Tof(settings) => SessionState::Tof(Box::new(
                TofTracker::with_scatter_grid(settings.params.clone(), settings.scatter_grid)?,
            )),
            SessionMethod::Stereo(c) => {
                SessionState::Stereo(Box::new(StereoTracker::new(c.rig, c.options)?))
            }
        })
    }

    /// Decodes and computes one frame, with and into the session's `state`; returns the outcome
    /// and the frame's warnings. Errors name fields relative to `SessionFrame` (`amplitude`,
    /// `left.…`); the caller adds `frame.`.
    pub fn compute(
        &self,
        frame: &pb::SessionFrame,
        limits: &ImageLimits,
        monitor: &Monitor,
        state: &mut SessionState,
    ) -> Result<(pb::frame_result::Outcome, Vec<String>)> {
        if frame.frame_id.len() > MAX_FRAME_ID_BYTES {
            return Err(MurkError::invalid(
                "frame_id",
                format!(
                    "at most {MAX_FRAME_ID_BYTES} bytes, got {}",
                    frame.frame_id.len()
                ),
            ));
        }
        match &self.method {
            SessionMethod::Tof(settings) => {
                let (amplitude, phase) =
                    tof_images_from_proto(frame.amplitude.as_ref(), frame.phase.as_ref(), limits)?;
                if amplitude.dims() != self.dims {
                    let (w, h) = self.dims;
                    return Err(MurkError::invalid(
                        "amplitude",
                        format!(
                            "the frame is {}x{}, the session's frames are {w}x{h}",
                            amplitude.width(),
                            amplitude.height()
                        ),
                    ));
                }
                let input = TofInput {
                    amplitude,
                    phase,
                    intrinsics: settings.intrinsics,
                };
                input.validate()?;
                let SessionState::Tof(tracker) = state else {
                    return Err(MurkError::Internal(
                        "ToF session without its tracker".into(),
                    ));
                };
                let tracked = tracker.estimate(&input, monitor)?;
                let warnings = match tracked.start {
                    TofStart::Restarted => vec![
                        "the scene or the fog changed too much for the previous frame's answer; \
                         the frame was computed from scratch"
                            .to_string(),
                    ],
                    TofStart::Cold | TofStart::Warm => Vec::new(),
                };
                Ok((
                    pb::frame_result::Outcome::Tof(tof_to_proto(
                        &tracked.output,
                        &settings.params,
                        &settings.outputs,
                        settings.points.as_ref(),
                    )?),
                    warnings,
                ))
            }
            SessionMethod::Stereo(config) => {
                let SessionState::Stereo(tracker) = state else {
                    return Err(MurkError::Internal(
                        "stereo session without its tracker".into(),
                    ));
                };
                let (left, right) =
                    stereo_images_from_proto(frame.left.as_ref(), frame.right.as_ref(), limits)?;
                let input = config.with_images(left, right)?;
                let started = std::time::Instant::now();
                let tracked = tracker.estimate(&input.left, &input.right, monitor)?;
                let points = if input.return_points {
                    tracked.depth.points(&input.rig, &input.left)?
                } else {
                    Vec::new()
                };
                let seconds = started.elapsed().as_secs_f64();
                let warnings = match tracked.search {
                    Search::Restarted => vec![
                        "the scene left the previous frame's disparity band, or a group of rows \
                         left its window of it; the whole range was searched again"
                            .to_string(),
                    ],
                    Search::Full | Search::Band => Vec::new(),
                };
                Ok((
                    pb::frame_result::Outcome::Stereo(stereo_to_proto(
                        &input,
                        &tracked.depth,
                        &points,
                        seconds,
                    )?),
                    warnings,
                ))
            }
        }
    }
}
