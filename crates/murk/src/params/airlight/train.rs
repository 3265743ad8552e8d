//! Training and evaluation of the learned airlight estimator (reference Table 3.1, §3.3.1) on
//! hazy images made on the fly by murk's MVS scene simulator.
//!
//! The reference's synthetic dataset draws `A` uniformly from [0.7, 1.0]; murk's default is
//! [0.4, 1.0], because real haze is often dimmer than that (a network trained on [0.7, 1.0]
//! read 0.764 for A = 0.6). The haze density varies through the simulator's target
//! median transmission (a wider range than the simulator's default, so the network sees thin
//! and thick haze). With `varied_scenes` each scene also draws its own brightness against the
//! airlight, furniture, field of view, trajectory and noise level ([`TrainConfig::sim_config`]),
//! so that the network cannot learn `A` from one room's typical brightness. A pool of simulated
//! images is generated once (both views of each scene), and every step draws a batch from it
//! with random horizontal flips and a random global gain `g ≤ 1`. The gain is exact
//! augmentation of the haze model, not a heuristic: `g·I = g·J·t + g·A·(1 − t)`, so a darkened
//! hazy image is a hazy image of airlight `g·A`, and the target is scaled with it.
//!
//! With `uniform_targets` the target is drawn first, uniform over the pool's range of `A`, and
//! then a pool image whose `A` lies in `[target, target / min_gain]` is darkened to it. A gain
//! drawn independently of `A` makes targets near the top of the range rare (only an undarkened
//! image of `A` near 1 gives one), and an L1 loss then reads high airlights low (the weights
//! trained that way: bias −0.02 to −0.03 above 0.85).
//!
//! The held-out set uses a fixed range of scene seeds, disjoint from every training seed, and
//! scores the CNN next to the dark-channel rule on the same images.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::{Device, Tensor, TensorData};

use super::cnn::{images_to_tensor, network_input, tensor_to_vec, AirlightCnn, AirlightNet};
use super::dark_channel::{dark_channel_airlight, DarkChannelParams};
use crate::error::{MurkError, Result};
use crate::image::ImageF32;
use crate::monitor::Monitor;
use crate::simulate::mvs::{simulate_mvs, MvsSimConfig};

/// First scene seed of the held-out set; training seeds are `(seed << 32) | i` with
/// `seed < 2^30`, so the two never meet.
pub const EVAL_SEED_BASE: u64 = 1 << 62;

/// Settings of [`train`].
#[derive(Clone, Debug, PartialEq)]
pub struct TrainConfig {
    /// Seed of the training scenes, the weight initialisation and the batch sampling.
    pub seed: u64,
    /// Optimiser steps.
    pub steps: usize,
    /// Images per batch (batch norm needs a few; ≥ 4).
    pub batch: usize,
    /// Peak Adam learning rate (linear warm-up, then cosine decay to 5 % of it).
    pub learning_rate: f64,
    /// Scenes simulated for the training pool (two views each).
    pub pool_scenes: usize,
    /// Width of the simulated images (the network sees them area-averaged to 128×96).
    pub sim_width: usize,
    /// Height of the simulated images.
    pub sim_height: usize,
    /// `A` is drawn uniformly from this range.
    pub airlight_range: [f32; 2],
    /// Median transmission of the reference view, drawn uniformly from this range.
    pub transmission_range: [f64; 2],
    /// Lowest random gain of the gain augmentation (1 disables it).
    pub min_gain: f32,
    /// Each scene draws its own albedo scale, furniture, focal length, trajectory and noise
    /// level (seeded by the scene seed); `false`: every scene is the simulator's default room.
    pub varied_scenes: bool,
    /// Targets uniform over the pool's range of `A` (see the module docs); `false`: the gain is
    /// drawn independently of the image.
    pub uniform_targets: bool,
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            seed: 1,
            // The run that made the committed weights (docs/airlight.md).
            steps: 3000,
            batch: 32,
            learning_rate: 1e-3,
            pool_scenes: 4000,
            sim_width: 256,
            sim_height: 192,
            airlight_range: [0.4, 1.0],
            transmission_range: [0.1, 0.7],
            min_gain: 0.9,
            varied_scenes: true,
            uniform_targets: true,
        }
    }
}

impl TrainConfig {
    /// Fails naming the first bad field.
    pub fn validate(&self) -> Result<()> {
        if self.seed >= 1 << 30 {
            return Err(MurkError::invalid(
                "seed",
                format!(
                    "must be < 2^30 (held-out seeds start at 2^62), got {}",
                    self.seed
                ),
            ));
        }
        if self.steps == 0 {
            return Err(MurkError::invalid("steps", "must be >= 1"));
        }
        if !(4..=256).contains(&self.batch) {
            return Err(MurkError::invalid(
                "batch",
                format!("must be in 4..=256, got {}", self.batch),
            ));
        }
        if !(self.learning_rate > 0.0 && self.learning_rate < 1.0) {
            return Err(MurkError::invalid(
                "learning_rate",
                format!("must be in (0, 1), got {}", self.learning_rate),
            ));
        }
        if self.pool_scenes == 0 || self.pool_scenes >= 1 << 32 {
            return Err(MurkError::invalid("pool_scenes", "must be in 1..2^32"));
        }
        if !(self.min_gain > 0.0 && self.min_gain <= 1.0) {
            return Err(MurkError::invalid(
                "min_gain",
                format!("must be in (0, 1], got {}", self.min_gain),
            ));
        }
        self.sim_config(0).validate()
    }

    /// The simulator settings of scene `seed`. With `varied_scenes` they are drawn from a
    /// stream of their own (the simulator's stream of the same seed is untouched):
    /// - albedo scale `U[0.5, 1.6]`: above about 1 the lit surfaces can outshine a dim airlight,
    ///   below it the room is dark against the haze;
    /// - 0–6 boxes and 0–4 spheres;
    /// - focal length ×`U[0.7, 1.5]` (field of view about 50°–100° at the default 256 px);
    /// - trajectory length `U[0.2, 0.6]`, and forward motion `U[0, 0.6]` in half the scenes;
    /// - noise σ `U[0.003, 0.02]`.
    pub fn sim_config(&self, seed: u64) -> MvsSimConfig {
        let base = MvsSimConfig {
            seed,
            num_views: 2,
            supersample: 1,
            airlight_range: self.airlight_range,
            median_transmission_range: self.transmission_range,
            ..MvsSimConfig::with_size(self.sim_width, self.sim_height)
        };
        if !self.varied_scenes {
            return base;
        }
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5CE7_E5EE_D0F0_0D15);
        MvsSimConfig {
            albedo_scale: rng.random_range(0.5..=1.6),
            num_boxes: rng.random_range(0..=6),
            num_spheres: rng.random_range(0..=4),
            focal_px: base.focal_px * rng.random_range(0.7..=1.5),
            trajectory_length: rng.random_range(0.2..=0.6),
            forward_motion: if rng.random_bool(0.5) {
                rng.random_range(0.0..=0.6)
            } else {
                0.0
            },
            noise_sigma: rng.random_range(0.003..=0.02),
            ..base
        }
    }
}

/// One simulated hazy image, ready for the network, with its ground truth.
#[derive(Clone, Debug)]
pub struct AirlightSample {
    /// The hazy image resampled to the network input size.
    pub input: ImageF32,
    /// True airlight.
    pub airlight: f32,
    /// Median transmission of the scene's reference view (the haze density).
    pub median_transmission: f64,
    /// Dark-channel estimate on the full-resolution image (held-out samples only).
    pub dark_channel: Option<f32>,
}

/// Simulates one scene per seed; all views of each when `all_views`, else the reference view
/// with its dark-channel estimate. Parallel over scenes, returned in seed order.
pub fn simulate_samples(
    cfg: &TrainConfig,
    seeds: &[u64],
    all_views: bool,
    on_scene: &(dyn Fn() + Sync),
) -> Result<Vec<AirlightSample>> {
    let per_scene: Vec<Vec<AirlightSample>> = seeds
        .par_iter()
        .map(|&seed| {
            let scene = simulate_mvs(&cfg.sim_config(seed), &Monitor::noop())?;
            let views: Vec<&ImageF32> = if all_views {
                scene.views.iter().map(|v| &v.hazy).collect()
            } else {
                vec![&scene.views[scene.reference].hazy]
            };
            let out = views
                .into_iter()
                .map(|hazy| {
                    let dark_channel = if all_views {
                        None
                    } else {
                        Some(dark_channel_airlight(hazy, &DarkChannelParams::default())?)
                    };
                    Ok(AirlightSample {
                        input: network_input(hazy)?,
                        airlight: scene.airlight,
                        median_transmission: scene.median_transmission,
                        dark_channel,
                    })
                })
                .collect::<Result<Vec<_>>>()?;
            on_scene();
            Ok(out)
        })
        .collect::<Result<_>>()?;
    Ok(per_scene.into_iter().flatten().collect())
}

/// Seeds of the training pool for `cfg.seed`.
pub fn training_seeds(cfg: &TrainConfig) -> Vec<u64> {
    (0..cfg.pool_scenes as u64)
        .map(|i| (cfg.seed << 32) | i)
        .collect()
}

/// Seeds of the held-out set (the same for every training run).
pub fn eval_seeds(n: usize) -> Vec<u64> {
    (0..n as u64).map(|i| EVAL_SEED_BASE + i).collect()
}

/// What [`train`] reports while it runs.
#[derive(Clone, Copy, Debug)]
pub enum TrainEvent {
    /// One optimiser step done: its index (from 1), batch loss (mean |Â − A|) and learning rate.
    Step {
        /// Steps done.
        step: usize,
        /// Mean absolute error of the batch before the update.
        loss: f32,
        /// Learning rate used.
        lr: f64,
    },
}

/// Learning rate at `step` (0-based): linear warm-up over the first 5 % of the steps, then
/// cosine decay to 5 % of the peak.
fn learning_rate(cfg: &TrainConfig, step: usize) -> f64 {
    let warmup = (cfg.steps / 20).max(1);
    if step < warmup {
        return cfg.learning_rate * (step + 1) as f64 / warmup as f64;
    }
    let p = (step - warmup) as f64 / (cfg.steps - warmup).max(1) as f64;
    let floor = 0.05;
    cfg.learning_rate * (floor + (1.0 - floor) * 0.5 * (1.0 + (std::f64::consts::PI * p).cos()))
}

/// The pool's indices in order of their `A`, for drawing a uniform target first
/// ([`TrainConfig::uniform_targets`]).
struct AirlightOrder {
    /// `(A, pool index)`, ascending in `A`.
    sorted: Vec<(f32, usize)>,
}

impl AirlightOrder {
    fn new(pool: &[AirlightSample]) -> Self {
        let mut sorted: Vec<(f32, usize)> = pool
            .iter()
            .enumerate()
            .map(|(i, s)| (s.airlight, i))
            .collect();
        sorted.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        Self { sorted }
    }

    /// A target `T ~ U[A_min, A_max]` of the pool, and a pool image whose `A` lies in
    /// `[T, T / min_gain]` (uniformly among them) with the gain `T / A` that darkens it to `T`.
    /// Returns the image's index and the gain. A target with no image in its interval (a gap
    /// in a small pool) takes the nearest `A` above it, or the largest, at gain ≤ 1.
    fn draw(&self, rng: &mut ChaCha8Rng, min_gain: f32) -> (usize, f32) {
        let (lo, hi) = (self.sorted[0].0, self.sorted[self.sorted.len() - 1].0);
        let target = if hi > lo {
            rng.random_range(lo..=hi)
        } else {
            lo
        };
        let first = self.sorted.partition_point(|&(a, _)| a < target);
        let end = self
            .sorted
            .partition_point(|&(a, _)| a <= target / min_gain);
        let k = if end > first {
            rng.random_range(first..end)
        } else {
            first.min(self.sorted.len() - 1)
        };
        let (a, index) = self.sorted[k];
        (index, (target / a).min(1.0))
    }
}

/// Mirrors an interleaved RGB image left–right.
fn flip_horizontal(img: &ImageF32) -> ImageF32 {
    let (w, h) = img.dims();
    let c = img.channels();
    let src = img.data();
    let mut out = Vec::with_capacity(src.len());
    for y in 0..h {
        for x in (0..w).rev() {
            out.extend_from_slice(&src[(y * w + x) * c..(y * w + x + 1) * c]);
        }
    }
    ImageF32::from_vec(w, h, c, out).expect("same dimensions")
}

/// Trains the Table 3.1 network on `pool` (from [`simulate_samples`] with all views) with Adam
/// and an L1 loss on `A`, reporting each step to `on_event`; checks `monitor` for cancellation
/// between steps.
///
/// Deterministic for a given config and pool on a given machine and thread count, in a process
/// that draws no other burn random numbers meanwhile (like `murk train airlight`): the batch
/// sampler is a ChaCha RNG seeded from `cfg.seed`, and the initial weights come from burn's
/// RNG, seeded from `cfg.seed` too — but that RNG is process-global (burn 0.22), so random
/// tensors made by other threads while the network initialises would change them.
pub fn train(
    cfg: &TrainConfig,
    pool: &[AirlightSample],
    monitor: &Monitor,
    on_event: &mut dyn FnMut(TrainEvent),
) -> Result<AirlightCnn> {
    cfg.validate()?;
    let device = Device::flex().autodiff();
    device.seed(cfg.seed);
    let net = AirlightNet::new(&device);
    train_from(cfg, net, &device, pool, monitor, on_event)
}

/// The training loop of [`train`] from given initial weights (on the autodiff `device`).
fn train_from(
    cfg: &TrainConfig,
    mut net: AirlightNet,
    device: &Device,
    pool: &[AirlightSample],
    monitor: &Monitor,
    on_event: &mut dyn FnMut(TrainEvent),
) -> Result<AirlightCnn> {
    cfg.validate()?;
    if pool.is_empty() {
        return Err(MurkError::invalid("pool", "no training samples"));
    }
    let mut optim = AdamConfig::new().init();
    let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed ^ 0xA1B2_C3D4_E5F6_0718);
    let by_airlight = AirlightOrder::new(pool);
    for step in 0..cfg.steps {
        monitor.checkpoint()?;
        let mut images = Vec::with_capacity(cfg.batch);
        let mut targets = Vec::with_capacity(cfg.batch);
        for _ in 0..cfg.batch {
            let (index, gain) = if cfg.uniform_targets && cfg.min_gain < 1.0 {
                by_airlight.draw(&mut rng, cfg.min_gain)
            } else {
                let index = rng.random_range(0..pool.len());
                let gain = if cfg.min_gain < 1.0 {
                    rng.random_range(cfg.min_gain..=1.0)
                } else {
                    1.0
                };
                (index, gain)
            };
            let s = &pool[index];
            let mut img = if rng.random_bool(0.5) {
                flip_horizontal(&s.input)
            } else {
                s.input.clone()
            };
            if gain != 1.0 {
                img.data_mut().iter_mut().for_each(|v| *v *= gain);
            }
            images.push(img);
            targets.push(s.airlight * gain);
        }
        let x = images_to_tensor(images.iter(), device);
        let y = Tensor::<1>::from_data(TensorData::new(targets, [cfg.batch]), device);
        let loss = (net.forward(x) - y).abs().mean();
        let loss_value = tensor_to_vec(loss.clone())?[0];
        if !loss_value.is_finite() {
            return Err(MurkError::Numerical(format!(
                "training loss became {loss_value} at step {}",
                step + 1
            )));
        }
        let grads = GradientsParams::from_grads(loss.backward(), &net);
        let lr = learning_rate(cfg, step);
        net = optim.step(lr, net, grads);
        on_event(TrainEvent::Step {
            step: step + 1,
            loss: loss_value,
            lr,
        });
    }
    Ok(AirlightCnn::from_net(net, Device::flex()))
}

/// Mean absolute errors of the CNN and of the dark-channel rule over a set of held-out images.
#[derive(Clone, Debug, PartialEq)]
pub struct EvalRow {
    /// Median-transmission interval `[lo, hi)` of the scenes in this row.
    pub transmission: [f64; 2],
    /// Airlight interval `[lo, hi)` of the scenes in this row.
    pub airlight: [f64; 2],
    /// Number of images.
    pub count: usize,
    /// Mean |Â − A| of the CNN.
    pub mae_cnn: f64,
    /// Mean |Â − A| of the dark-channel rule.
    pub mae_dark_channel: f64,
    /// Largest |Â − A| of the CNN.
    pub max_cnn: f64,
    /// Largest |Â − A| of the dark-channel rule.
    pub max_dark_channel: f64,
    /// Mean signed error Â − A of the CNN.
    pub bias_cnn: f64,
    /// Mean signed error Â − A of the dark-channel rule.
    pub bias_dark_channel: f64,
}

/// Scores `cnn` and the dark-channel rule on held-out samples (from [`simulate_samples`] with
/// `all_views = false`): one row per transmission interval in `t_bins` that holds any image,
/// one per airlight interval in `a_bins`, then the row of all images.
pub fn evaluate(
    cnn: &AirlightCnn,
    samples: &[AirlightSample],
    t_bins: &[[f64; 2]],
    a_bins: &[[f64; 2]],
) -> Result<Vec<EvalRow>> {
    let mut cnn_est = Vec::with_capacity(samples.len());
    for chunk in samples.chunks(32) {
        let inputs: Vec<ImageF32> = chunk.iter().map(|s| s.input.clone()).collect();
        cnn_est.extend(cnn.estimate_batch(&inputs)?);
    }
    // Half-open like the bins, so the largest value is just inside.
    let span = |f: &dyn Fn(&AirlightSample) -> f64| {
        let [lo, hi] = samples
            .iter()
            .map(f)
            .fold([f64::INFINITY, f64::NEG_INFINITY], |[lo, hi], v| {
                [lo.min(v), hi.max(v)]
            });
        [lo, hi.next_up()]
    };
    let t_all = span(&|s| s.median_transmission);
    let a_all = span(&|s| f64::from(s.airlight));
    let row = |t_range: [f64; 2], a_range: [f64; 2]| -> Result<Option<EvalRow>> {
        let inside = |v: f64, [lo, hi]: [f64; 2]| v >= lo && v < hi;
        let mut r = EvalRow {
            transmission: t_range,
            airlight: a_range,
            count: 0,
            mae_cnn: 0.0,
            mae_dark_channel: 0.0,
            max_cnn: 0.0,
            max_dark_channel: 0.0,
            bias_cnn: 0.0,
            bias_dark_channel: 0.0,
        };
        for (s, &a_cnn) in samples.iter().zip(&cnn_est) {
            if !inside(s.median_transmission, t_range) || !inside(f64::from(s.airlight), a_range) {
                continue;
            }
            let a_dc = s.dark_channel.ok_or_else(|| {
                MurkError::invalid("samples", "held-out samples need a dark-channel estimate")
            })?;
            let (e_cnn, e_dc) = ((a_cnn - s.airlight) as f64, (a_dc - s.airlight) as f64);
            r.count += 1;
            r.mae_cnn += e_cnn.abs();
            r.mae_dark_channel += e_dc.abs();
            r.max_cnn = r.max_cnn.max(e_cnn.abs());
            r.max_dark_channel = r.max_dark_channel.max(e_dc.abs());
            r.bias_cnn += e_cnn;
            r.bias_dark_channel += e_dc;
        }
        if r.count == 0 {
            return Ok(None);
        }
        let n = r.count as f64;
        r.mae_cnn /= n;
        r.mae_dark_channel /= n;
        r.bias_cnn /= n;
        r.bias_dark_channel /= n;
        Ok(Some(r))
    };
    let mut rows = Vec::new();
    for &b in t_bins {
        rows.extend(row(b, a_all)?);
    }
    for &b in a_bins {
        rows.extend(row(t_all, b)?);
    }
    rows.extend(row(t_all, a_all)?);
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::module::Module;
    use burn::store::ModuleRecord;
    use burn::tensor::Bytes;

    fn tiny() -> TrainConfig {
        TrainConfig {
            seed: 3,
            steps: 2,
            batch: 4,
            pool_scenes: 2,
            sim_width: 64,
            sim_height: 48,
            ..TrainConfig::default()
        }
    }

    #[test]
    fn tiny_training_run_is_deterministic_and_evaluates() {
        let cfg = tiny();
        let pool = simulate_samples(&cfg, &training_seeds(&cfg), true, &|| {}).unwrap();
        assert_eq!(pool.len(), 4);
        let mut losses = Vec::new();
        let a = train(
            &cfg,
            &pool,
            &Monitor::noop(),
            &mut |TrainEvent::Step { loss, .. }| losses.push(loss),
        )
        .unwrap();
        assert_eq!(losses.len(), 2);
        // The training loop is deterministic from given initial weights. (Two `train` calls are
        // not compared: burn's RNG is process-global and the other tests draw from it
        // concurrently.)
        // Each run gets its own copy through a record: clones of a module share the batch
        // norms' running statistics, which training updates.
        let device = Device::flex().autodiff();
        let init = super::super::cnn::net_to_bytes(AirlightNet::new(&device)).unwrap();
        let fresh = || {
            let record = ModuleRecord::from_bytes(Bytes::from_bytes_vec(init.clone())).unwrap();
            AirlightNet::new(&device).load_record(record)
        };
        let run = |net: AirlightNet| {
            train_from(&cfg, net, &device, &pool, &Monitor::noop(), &mut |_| {}).unwrap()
        };
        let (b, c) = (run(fresh()), run(fresh()));
        let inputs: Vec<ImageF32> = pool.iter().map(|s| s.input.clone()).collect();
        let out_b = b.estimate_batch(&inputs).unwrap();
        assert_eq!(out_b, c.estimate_batch(&inputs).unwrap());
        let untrained = AirlightCnn::from_bytes(&init).unwrap();
        assert_ne!(
            out_b,
            untrained.estimate_batch(&inputs).unwrap(),
            "training changed nothing"
        );

        let held_out = simulate_samples(&cfg, &eval_seeds(2), false, &|| {}).unwrap();
        // One band of A per held-out scene, and one that holds none (no row).
        let (a0, a1) = (held_out[0].airlight, held_out[1].airlight);
        assert_ne!(a0, a1);
        let split = f64::from(0.5 * (a0 + a1));
        let a_bins = [[0.0, split], [split, 1.1], [1.5, 2.0]];
        let rows = evaluate(&a, &held_out, &[], &a_bins).unwrap();
        assert_eq!(rows.len(), 3, "{rows:?}");
        assert_eq!((rows[0].count, rows[1].count), (1, 1));
        // The row of all scenes includes the largest values of t and A (half-open intervals).
        let all = rows.last().unwrap();
        assert_eq!(all.count, 2);
        assert!(all.mae_cnn.is_finite() && all.mae_dark_channel.is_finite());
        assert!(all.airlight[1] > f64::from(a0.max(a1)));
    }

    #[test]
    fn seeds_are_disjoint_and_config_is_checked() {
        let cfg = TrainConfig {
            seed: (1 << 30) - 1,
            pool_scenes: 10,
            ..TrainConfig::default()
        };
        assert!(training_seeds(&cfg).iter().all(|&s| s < EVAL_SEED_BASE));
        let bad = TrainConfig {
            seed: 1 << 30,
            ..TrainConfig::default()
        };
        assert_eq!(bad.validate().unwrap_err().field(), Some("seed"));
        let bad = TrainConfig {
            batch: 2,
            ..TrainConfig::default()
        };
        assert_eq!(bad.validate().unwrap_err().field(), Some("batch"));
    }

    #[test]
    fn varied_scenes_are_valid_seeded_and_span_their_ranges() {
        let cfg = TrainConfig::default();
        assert_eq!(cfg.sim_config(7), cfg.sim_config(7));
        let configs: Vec<MvsSimConfig> = (0..64).map(|s| cfg.sim_config(s)).collect();
        for c in &configs {
            c.validate().unwrap();
            assert_eq!(c.airlight_range, [0.4, 1.0]);
        }
        let any = |f: &dyn Fn(&MvsSimConfig) -> bool| configs.iter().any(f);
        assert!(any(&|c| c.albedo_scale > 1.3) && any(&|c| c.albedo_scale < 0.8));
        assert!(any(&|c| c.forward_motion > 0.0) && any(&|c| c.forward_motion == 0.0));
        assert!(any(&|c| c.num_boxes == 0) && any(&|c| c.num_boxes >= 5));
        let plain = TrainConfig {
            varied_scenes: false,
            ..cfg
        }
        .sim_config(7);
        assert_eq!(
            plain,
            MvsSimConfig {
                seed: 7,
                num_views: 2,
                supersample: 1,
                airlight_range: [0.4, 1.0],
                median_transmission_range: [0.1, 0.7],
                ..MvsSimConfig::with_size(256, 192)
            }
        );
    }

    /// Targets drawn first are uniform over the pool's range of A, each from an image of A in
    /// `[T, T / min_gain]` darkened by a gain in `[min_gain, 1]`; a gain drawn independently of
    /// A leaves the top of the range nearly empty.
    #[test]
    fn uniform_targets_cover_the_top_of_the_range() {
        let sample = |airlight: f32| AirlightSample {
            input: ImageF32::from_fn(2, 2, |_, _| 0.5),
            airlight,
            median_transmission: 0.3,
            dark_channel: None,
        };
        // A pool uniform in A over [0.4, 1.0], shuffled.
        let pool: Vec<AirlightSample> = (0..601)
            .map(|i| sample(0.4 + ((i * 97) % 601) as f32 * 0.001))
            .collect();
        let order = AirlightOrder::new(&pool);
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let min_gain = 0.9;
        let targets: Vec<f32> = (0..20_000)
            .map(|_| {
                let (i, g) = order.draw(&mut rng, min_gain);
                assert!((min_gain..=1.0).contains(&g), "gain {g}");
                pool[i].airlight * g
            })
            .collect();
        let share = |lo: f32, hi: f32| {
            targets.iter().filter(|&&t| t >= lo && t < hi).count() as f64 / targets.len() as f64
        };
        // Each tenth of the range holds a tenth of the targets.
        for k in 0..10 {
            let lo = 0.4 + 0.06 * k as f32;
            let p = share(lo, lo + 0.06);
            assert!((p - 0.1).abs() < 0.012, "[{lo}, {}): {p}", lo + 0.06);
        }
        // Independent gains put about a quarter as many in the top tenth.
        let independent: Vec<f32> = (0..20_000)
            .map(|_| {
                pool[rng.random_range(0..pool.len())].airlight * rng.random_range(min_gain..=1.0)
            })
            .collect();
        let top = independent.iter().filter(|&&t| t >= 0.94).count() as f64 / 20_000.0;
        assert!(top < 0.05, "{top}");
    }

    #[test]
    fn learning_rate_warms_up_and_decays() {
        let cfg = TrainConfig {
            steps: 100,
            ..TrainConfig::default()
        };
        assert!(learning_rate(&cfg, 0) < learning_rate(&cfg, 4));
        assert!((learning_rate(&cfg, 5) - cfg.learning_rate).abs() < 1e-12);
        assert!((learning_rate(&cfg, 99) - 0.05 * cfg.learning_rate).abs() < 1e-5);
    }

    #[test]
    fn flip_mirrors_rows() {
        let img = ImageF32::from_vec(3, 1, 1, vec![1.0, 2.0, 3.0]).unwrap();
        assert_eq!(flip_horizontal(&img).data(), &[3.0, 2.0, 1.0]);
    }
}
