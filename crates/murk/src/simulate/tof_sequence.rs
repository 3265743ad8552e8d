//! Simulated ToF sequences: the frames a camera streams while objects move and the fog drifts,
//! with scene cuts, each frame with its ground truth. They drive the sensor-session benchmarks
//! and tests: a stream's results can be scored frame by frame against the truth, and against
//! one-shot processing of the same frames.
//!
//! Frame `k` is a [`simulate_tof`](super::tof::simulate_tof)-style frame at time
//! `t = k / frame_rate_hz`:
//! - the scene is the configured seed's layout, a new one (seed + 1, + 2, ...) after each cut;
//! - each object moves at its own constant velocity (drawn from the scene's seed, up to
//!   `max_speed_m_per_s`, mostly across the view) since the scene's first frame;
//! - β drifts as `β₀·(1 + fog_drift·sin(2π·t / fog_period_s))`;
//! - the noise is drawn afresh per frame.
//!
//! Frame 0 is exactly [`simulate_tof`](super::tof::simulate_tof)'s frame of the same
//! configuration.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::scene::{Scene, V3};
use super::tof::{render_tof, TofSimConfig, TofSimFrame};
use crate::error::{MurkError, Result};
use crate::monitor::Monitor;

/// How a simulated ToF sequence changes from frame to frame.
#[derive(Clone, Debug, PartialEq)]
pub struct TofMotion {
    /// Frames per second of the camera.
    pub frame_rate_hz: f64,
    /// Fastest an object moves, metres per second; each object's speed is drawn between a third
    /// of this and this.
    pub max_speed_m_per_s: f64,
    /// Relative amplitude of the fog's drift in β, in [0, 0.9].
    pub fog_drift: f64,
    /// Period of the fog's drift, seconds.
    pub fog_period_s: f64,
    /// A new scene every this many frames (a scene cut); `None` keeps one scene.
    pub cut_every: Option<usize>,
}

impl Default for TofMotion {
    fn default() -> Self {
        Self {
            frame_rate_hz: 10.0,
            max_speed_m_per_s: 0.3,
            fog_drift: 0.1,
            fog_period_s: 10.0,
            cut_every: None,
        }
    }
}

impl TofMotion {
    /// Checks every field; errors name it.
    pub fn validate(&self) -> Result<()> {
        for (name, v, lo, hi) in [
            ("frame_rate_hz", self.frame_rate_hz, 0.01, 1000.0),
            ("max_speed_m_per_s", self.max_speed_m_per_s, 0.0, 10.0),
            ("fog_drift", self.fog_drift, 0.0, 0.9),
            ("fog_period_s", self.fog_period_s, 0.01, 1e6),
        ] {
            if !v.is_finite() || v < lo || v > hi {
                return Err(MurkError::invalid(
                    name,
                    format!("must be finite and in [{lo}, {hi}], got {v}"),
                ));
            }
        }
        if self.cut_every == Some(0) {
            return Err(MurkError::invalid("cut_every", "must be at least 1 frame"));
        }
        Ok(())
    }

    /// The scene index (0, then 1 after the first cut, ...) and the frame's index within it.
    fn segment(&self, index: usize) -> (usize, usize) {
        match self.cut_every {
            Some(n) => (index / n, index % n),
            None => (0, index),
        }
    }

    /// Whether frame `index` starts a new scene after a cut.
    pub fn is_cut(&self, index: usize) -> bool {
        index > 0 && self.segment(index).1 == 0
    }
}

/// The stream of the scene's seed that draws the objects' velocities, apart from the layout's.
const VELOCITY_STREAM: u64 = 1 << 48;
/// Noise streams of frame `k` start at `k · NOISE_STREAMS_PER_FRAME` (each row takes one).
const NOISE_STREAMS_PER_FRAME: u64 = 1 << 32;

/// Frame `index` of the sequence that starts with `cfg`'s frame and changes by `motion`.
pub fn simulate_tof_sequence_frame(
    cfg: &TofSimConfig,
    motion: &TofMotion,
    index: usize,
    monitor: &Monitor,
) -> Result<TofSimFrame> {
    cfg.validate()?;
    motion.validate()?;
    let (segment, local) = motion.segment(index);
    let mut frame_cfg = cfg.clone();
    frame_cfg.seed = cfg.seed.wrapping_add(segment as u64);
    let t = index as f64 / motion.frame_rate_hz;
    let t_local = local as f64 / motion.frame_rate_hz;
    if motion.fog_drift > 0.0 {
        let phase = std::f64::consts::TAU * t / motion.fog_period_s;
        frame_cfg.beta_per_mm =
            Some(cfg.effective_beta_per_mm() * (1.0 + motion.fog_drift * phase.sin()));
    }
    let k = frame_cfg.intrinsics();
    let mut layout_rng = ChaCha8Rng::seed_from_u64(frame_cfg.seed);
    let mut scene = Scene::generate_layout(
        frame_cfg.layout,
        &mut layout_rng,
        &k,
        frame_cfg.width,
        frame_cfg.height,
    );
    let mut velocity_rng = ChaCha8Rng::seed_from_u64(frame_cfg.seed);
    velocity_rng.set_stream(VELOCITY_STREAM);
    for object in &mut scene.objects {
        // Mostly across the view (x, y), a little in depth, as a robot sees things pass.
        let angle = velocity_rng.random::<f64>() * std::f64::consts::TAU;
        let speed = motion.max_speed_m_per_s * (1.0 + 2.0 * velocity_rng.random::<f64>()) / 3.0;
        let dz = 0.3 * (2.0 * velocity_rng.random::<f64>() - 1.0);
        let v = V3::new(angle.cos(), angle.sin(), dz).normalize() * speed;
        object.shape = object.shape.translated(v * t_local);
    }
    render_tof(
        &frame_cfg,
        scene,
        (index as u64).wrapping_mul(NOISE_STREAMS_PER_FRAME),
        monitor,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::simulate::tof::simulate_tof;

    fn small() -> TofSimConfig {
        TofSimConfig {
            seed: 3,
            ..TofSimConfig::with_size(48, 40)
        }
    }

    #[test]
    fn frame_zero_is_the_single_frame() {
        let m = Monitor::noop();
        let seq = simulate_tof_sequence_frame(&small(), &TofMotion::default(), 0, &m).unwrap();
        let one = simulate_tof(&small(), &m).unwrap();
        assert_eq!(seq.amplitude, one.amplitude);
        assert_eq!(seq.phase, one.phase);
        assert_eq!(seq.gt_range_m, one.gt_range_m);
    }

    #[test]
    fn objects_move_fog_drifts_noise_changes_and_cuts_change_the_scene() {
        let m = Monitor::noop();
        let motion = TofMotion {
            cut_every: Some(3),
            max_speed_m_per_s: 1.0,
            fog_drift: 0.5,
            fog_period_s: 1.0,
            ..TofMotion::default()
        };
        let frames: Vec<TofSimFrame> = (0..4)
            .map(|k| simulate_tof_sequence_frame(&small(), &motion, k, &m).unwrap())
            .collect();
        let centre = |f: &TofSimFrame| f.scene.objects[0].shape.centre();
        // 0.1 s at 1/3..1 m/s: 33 to 100 mm per frame, at a constant velocity.
        let step = centre(&frames[1]) - centre(&frames[0]);
        assert!((0.03..=0.101).contains(&step.norm()), "{step:?}");
        assert!((centre(&frames[2]) - centre(&frames[1]) - step).norm() < 1e-12);
        assert_ne!(frames[1].gt_range_m, frames[0].gt_range_m);
        // β = β0 (1 + 0.5 sin(2π t)) at t = 0.1 s.
        let beta0 = small().effective_beta_per_mm();
        let beta1 = frames[1].config.effective_beta_per_mm();
        let expect = beta0 * (1.0 + 0.5 * (std::f64::consts::TAU * 0.1).sin());
        assert!((beta1 - expect).abs() < 1e-15, "{beta1} vs {expect}");
        // Frame 3 starts the next scene: the next seed's layout, from rest.
        assert!(motion.is_cut(3) && !motion.is_cut(2) && !motion.is_cut(0));
        assert_eq!(frames[3].config.seed, small().seed + 1);
        assert_ne!(frames[3].scene, frames[0].scene);
    }

    #[test]
    fn bad_motion_is_named() {
        let bad = TofMotion {
            frame_rate_hz: 0.0,
            ..TofMotion::default()
        };
        match simulate_tof_sequence_frame(&small(), &bad, 0, &Monitor::noop()) {
            Err(MurkError::InvalidArgument { field, .. }) => assert_eq!(field, "frame_rate_hz"),
            other => panic!("expected InvalidArgument, got {other:?}"),
        }
    }
}
