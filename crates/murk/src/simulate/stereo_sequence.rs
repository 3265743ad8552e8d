//! Simulated rectified stereo sequences: a stereo rig moving through the hazy room of
//! [`simulate_mvs`](super::mvs::simulate_mvs), pair by pair, each with the left camera's ground
//! truth depth. They drive the stereo session and bag tests and benchmarks with a scene that
//! moves, as a robot's does.
//!
//! - The room, the airlight A and the rig (intrinsics, baseline `trajectory_length`) are those
//!   of the configuration's seed with `rectified_pair`.
//! - The rig moves at constant velocity, `forward_m_per_s` along +z and `sideways_m_per_s`
//!   along +x (scene units per second), without turning.
//! - β is fixed for the whole sequence: the one that gives frame 0's left view its drawn median
//!   transmission. The haze therefore thins as the rig approaches the far wall, as real haze
//!   does.
//! - The noise is drawn afresh per frame.
//!
//! Frame 0 is exactly the rectified pair of [`simulate_mvs`](super::mvs::simulate_mvs) with the
//! same configuration.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use std::path::Path;

use super::mvs::{add_noise, encode_rgb16, median, render_view, MvsSimConfig, World};
use crate::atmosphere::haze;
use crate::camera::Intrinsics;
use crate::error::{MurkError, Result};
use crate::image::ImageF32;
use crate::io;
use crate::monitor::Monitor;
use crate::mvs::Pose;

/// How the rig moves.
#[derive(Clone, Debug, PartialEq)]
pub struct StereoMotion {
    /// Frames per second of the rig.
    pub frame_rate_hz: f64,
    /// Speed along the optical axis, scene units per second.
    pub forward_m_per_s: f64,
    /// Speed along +x, scene units per second.
    pub sideways_m_per_s: f64,
}

impl Default for StereoMotion {
    fn default() -> Self {
        Self {
            frame_rate_hz: 10.0,
            forward_m_per_s: 0.5,
            sideways_m_per_s: 0.0,
        }
    }
}

/// Farthest the rig may travel from its start, scene units: the room's nearest objects stand
/// a few units ahead.
pub const MAX_TRAVEL: f64 = 3.0;

impl StereoMotion {
    /// Checks every field; errors name it.
    pub fn validate(&self) -> Result<()> {
        for (name, v, lo, hi) in [
            ("frame_rate_hz", self.frame_rate_hz, 0.01, 1000.0),
            ("forward_m_per_s", self.forward_m_per_s, -10.0, 10.0),
            ("sideways_m_per_s", self.sideways_m_per_s, -10.0, 10.0),
        ] {
            if !v.is_finite() || !(lo..=hi).contains(&v) {
                return Err(MurkError::invalid(
                    name,
                    format!("must be in [{lo}, {hi}], got {v}"),
                ));
            }
        }
        Ok(())
    }
}

/// One pair of a sequence.
#[derive(Clone, Debug)]
pub struct StereoFrame {
    /// Seconds since frame 0.
    pub time_s: f64,
    /// Hazy left and right images, RGB in [0, 1] (noise included).
    pub left: ImageF32,
    /// The right image.
    pub right: ImageF32,
    /// Ground-truth z-depth of the left view, scene units.
    pub left_depth: ImageF32,
    /// World-to-camera pose of the left camera (the world is frame 0's left camera).
    pub left_pose: Pose,
}

/// A rig moving through one simulated hazy room.
pub struct StereoSequence {
    cfg: MvsSimConfig,
    motion: StereoMotion,
    world: World,
    /// Airlight A.
    pub airlight: f32,
    /// Scattering coefficient β, per scene unit.
    pub beta: f32,
}

impl StereoSequence {
    /// The room, A and β of `cfg` (whose `rectified_pair` is implied and `beta_range` must be
    /// unset: β follows from the room, as in [`simulate_mvs`](super::mvs::simulate_mvs)).
    pub fn new(cfg: &MvsSimConfig, motion: &StereoMotion) -> Result<Self> {
        let cfg = MvsSimConfig {
            rectified_pair: true,
            num_views: 2,
            ..cfg.clone()
        };
        cfg.validate()?;
        motion.validate()?;
        if cfg.beta_range.is_some() {
            return Err(MurkError::invalid(
                "beta_range",
                "a sequence keeps the room's own scale; leave beta_range unset",
            ));
        }
        // The same draws, in the same order, as `simulate_mvs` (the rectified pair draws no
        // pose), so frame 0 is its pair.
        let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
        let world = World::random(&cfg, &mut rng);
        let airlight = rng.random_range(cfg.airlight_range[0]..=cfg.airlight_range[1]);
        let t_target =
            rng.random_range(cfg.median_transmission_range[0]..=cfg.median_transmission_range[1]);
        let (_, depth) = render_view(&world, &cfg, &Pose::identity())?;
        let beta = (-t_target.ln() / median(depth.data())) as f32;
        Ok(Self {
            cfg,
            motion: motion.clone(),
            world,
            airlight,
            beta,
        })
    }

    /// The rectified intrinsics of both cameras, pixels.
    pub fn intrinsics(&self) -> Intrinsics {
        self.cfg.intrinsics()
    }

    /// The baseline, scene units: the right camera sits this far along the left camera's +x.
    pub fn baseline(&self) -> f64 {
        self.cfg.trajectory_length
    }

    /// Pair `k`. Errors name `frame` when the rig would have left the room's free space.
    pub fn frame(&self, k: usize, monitor: &Monitor) -> Result<StereoFrame> {
        let t = k as f64 / self.motion.frame_rate_hz;
        let centre = [
            self.motion.sideways_m_per_s * t,
            0.0,
            self.motion.forward_m_per_s * t,
        ];
        let travel = centre.iter().map(|c| c * c).sum::<f64>().sqrt();
        if travel > MAX_TRAVEL {
            return Err(MurkError::invalid(
                "frame",
                format!(
                    "frame {k} puts the rig {travel:.2} units from its start, past the \
                     {MAX_TRAVEL} units the room leaves free: fewer frames or a slower rig"
                ),
            ));
        }
        let b = self.baseline();
        let left_pose = Pose::translation_only(centre.map(|c| -c))?;
        let right_pose = Pose::translation_only([-(centre[0] + b), -centre[1], -centre[2]])?;
        let mut views = Vec::with_capacity(2);
        for (i, pose) in [left_pose, right_pose].iter().enumerate() {
            monitor.checkpoint()?;
            let (clear, depth) = render_view(&self.world, &self.cfg, pose)?;
            let mut hazy = haze(&clear, &depth, self.airlight, self.beta)?;
            // `simulate_mvs`'s noise streams for frame 0; a stream of their own for later frames.
            let base = self.cfg.seed.wrapping_mul(0x9E37_79B9_7F4A_7C15)
                ^ ((i as u64) << 32)
                ^ ((k as u64) << 48);
            add_noise(&mut hazy, self.cfg.noise_sigma, base ^ 2);
            views.push((hazy, depth));
        }
        let (right, _) = views.pop().expect("two views");
        let (left, left_depth) = views.pop().expect("two views");
        Ok(StereoFrame {
            time_s: t,
            left,
            right,
            left_depth,
            left_pose,
        })
    }
}

/// Writes pair `frame` of `seq` into `dir` (created): `left.png` and `right.png` (16-bit
/// linear RGB), the left view's ground truth `depth.exr` (scene units) and `meta.json` with the
/// rig, the haze and the time, the layout `murk stereo --sequence` streams.
pub fn write_stereo_frame(dir: &Path, seq: &StereoSequence, frame: &StereoFrame) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| io::io_error(dir, e))?;
    io::write_file(&dir.join("left.png"), &encode_rgb16(&frame.left)?)?;
    io::write_file(&dir.join("right.png"), &encode_rgb16(&frame.right)?)?;
    io::write_exr(&dir.join("depth.exr"), &frame.left_depth)?;
    let k = seq.intrinsics();
    let meta = serde_json::json!({
        "format": "murk.stereo_frame",
        "version": 1,
        "time_s": frame.time_s,
        "intrinsics": {"fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy},
        "baseline": seq.baseline(),
        "airlight": seq.airlight,
        "beta": seq.beta,
        "units": {
            "intrinsics": "pixels, origin at the centre of the top-left pixel",
            "baseline": "scene units; depth.exr and 1/beta are in the same unit",
            "depth.exr": "z-depth of the left view",
            "left.png, right.png": "linear RGB, 16-bit",
        },
    });
    let text = serde_json::to_string_pretty(&meta)
        .map_err(|e| MurkError::Internal(format!("encoding meta.json: {e}")))?;
    io::write_file(&dir.join("meta.json"), text.as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::simulate::mvs::simulate_mvs;

    fn cfg() -> MvsSimConfig {
        MvsSimConfig {
            seed: 4,
            rectified_pair: true,
            num_views: 2,
            ..MvsSimConfig::with_size(64, 48)
        }
    }

    #[test]
    fn frame_zero_is_the_rectified_pair_of_simulate_mvs() {
        let scene = simulate_mvs(&cfg(), &Monitor::noop()).unwrap();
        let seq = StereoSequence::new(&cfg(), &StereoMotion::default()).unwrap();
        let f = seq.frame(0, &Monitor::noop()).unwrap();
        assert_eq!(seq.airlight, scene.airlight);
        assert_eq!(seq.beta, scene.beta);
        assert_eq!(f.left, scene.views[0].hazy);
        assert_eq!(f.right, scene.views[1].hazy);
        assert_eq!(f.left_depth, scene.views[0].depth);
        assert!((seq.baseline() + scene.views[1].pose.translation()[0]).abs() < 1e-12);
    }

    #[test]
    fn the_rig_moves_forward_and_the_scene_comes_closer() {
        let seq = StereoSequence::new(&cfg(), &StereoMotion::default()).unwrap();
        let (a, b) = (
            seq.frame(0, &Monitor::noop()).unwrap(),
            seq.frame(10, &Monitor::noop()).unwrap(),
        );
        assert!((b.time_s - 1.0).abs() < 1e-12);
        // 0.5 units a second for a second: a surface point seen at frame 0 is half a unit
        // nearer at frame 10, where it projects (unless something now hides it).
        let k = seq.intrinsics();
        let (w, h) = a.left_depth.dims();
        let (mut seen, mut agree) = (0, 0);
        for v in 0..h {
            for u in 0..w {
                let z0 = f64::from(a.left_depth.get(u, v, 0));
                let ray = k.ray(u as f64, v as f64);
                let p = [ray.x / ray.z * z0, ray.y / ray.z * z0, z0 - 0.5];
                let Some((u1, v1)) = k.project(p) else {
                    continue;
                };
                let (u1, v1) = (u1.round(), v1.round());
                if u1 < 0.0 || v1 < 0.0 || u1 >= w as f64 || v1 >= h as f64 {
                    continue;
                }
                seen += 1;
                let z1 = f64::from(b.left_depth.get(u1 as usize, v1 as usize, 0));
                if (z1 - p[2]).abs() < 0.03 * p[2] {
                    agree += 1;
                }
            }
        }
        assert!(
            seen > w * h / 2 && agree as f64 > 0.9 * seen as f64,
            "{agree} of {seen}"
        );
        assert_ne!(a.left, b.left);
        let far = seq.frame(100, &Monitor::noop()).unwrap_err();
        assert!(matches!(far, MurkError::InvalidArgument { ref field, .. } if field == "frame"));
        let bad = StereoSequence::new(
            &cfg(),
            &StereoMotion {
                frame_rate_hz: 0.0,
                ..StereoMotion::default()
            },
        )
        .err()
        .unwrap();
        assert!(
            matches!(bad, MurkError::InvalidArgument { ref field, .. } if field == "frame_rate_hz")
        );
    }
}
