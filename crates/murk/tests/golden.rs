//! Golden regression tests: each method's outputs on one small seeded scene, pinned by a
//! checksum of every output value's bits and a few statistics.
//!
//! A change that moves any output value by one ulp fails here. When the change is meant to
//! move results, regenerate and commit the files, so that the diff shows what moved:
//!
//! ```sh
//! REGENERATE=1 cargo test --release -p murk --test golden
//! git diff crates/murk/tests/golden/
//! ```
//!
//! The statistics (errors against the scene's ground truth, mask sizes, estimates) are there to
//! be read in that diff; the checksum is what the test compares. A failure prints both files.

use std::collections::BTreeMap;
use std::path::PathBuf;

use murk::metrics::{depth_metrics, mean_angular_error_deg};
use murk::mvs::{estimate_depth, CostKind, DehazingOptions, DepthParams, PlaneSet};
use murk::params::search::{plane_range_from_sparse, search_scattering, SearchParams, SfmEvidence};
use murk::ps::{photometric_stereo, PsParams};
use murk::simulate::mvs::{simulate_mvs, MvsSimConfig};
use murk::simulate::ps::{simulate_ps, PsSimConfig};
use murk::simulate::tof::{simulate_tof, FogPreset, TofSimConfig};
use murk::simulate::SceneLayout;
use murk::tof::{estimate_tof_depth, TofInput, TofParams};
use murk::{ImageF32, Monitor};

/// FNV-1a over the little-endian bytes of every value fed to it: order- and bit-sensitive.
struct Checksum(u64);

impl Checksum {
    fn new() -> Self {
        Self(0xcbf2_9ce4_8422_2325)
    }

    fn bytes(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 ^= u64::from(b);
            self.0 = self.0.wrapping_mul(0x0100_0000_01b3);
        }
    }

    fn f32s(&mut self, values: impl IntoIterator<Item = f32>) {
        for v in values {
            self.bytes(&v.to_bits().to_le_bytes());
        }
    }

    fn f64s(&mut self, values: impl IntoIterator<Item = f64>) {
        for v in values {
            self.bytes(&v.to_bits().to_le_bytes());
        }
    }

    fn image(&mut self, img: &ImageF32) {
        let (w, h) = img.dims();
        self.bytes(&(w as u64).to_le_bytes());
        self.bytes(&(h as u64).to_le_bytes());
        self.f32s(img.data().iter().copied());
    }
}

/// One method's pinned outputs: the checksum and readable statistics.
struct Golden {
    name: &'static str,
    checksum: Checksum,
    stats: BTreeMap<&'static str, String>,
}

impl Golden {
    fn new(name: &'static str) -> Self {
        Self {
            name,
            checksum: Checksum::new(),
            stats: BTreeMap::new(),
        }
    }

    /// Records a statistic, with 6 significant digits.
    fn stat(&mut self, key: &'static str, value: f64) {
        self.stats.insert(key, format!("{value:.6e}"));
    }

    fn render(&self) -> String {
        let mut s = format!("checksum = \"{:016x}\"\n\n[stats]\n", self.checksum.0);
        for (k, v) in &self.stats {
            s.push_str(&format!("{k} = {v}\n"));
        }
        s
    }

    /// Compares with (or, under `REGENERATE=1`, rewrites) `tests/golden/<name>.toml`.
    fn check(self) {
        let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("tests/golden")
            .join(format!("{}.toml", self.name));
        let rendered = self.render();
        if std::env::var_os("REGENERATE").is_some_and(|v| v == "1") {
            std::fs::create_dir_all(path.parent().unwrap()).unwrap();
            std::fs::write(&path, &rendered).unwrap();
            eprintln!("regenerated {}", path.display());
            return;
        }
        let pinned = std::fs::read_to_string(&path).unwrap_or_else(|e| {
            panic!(
                "{}: {e}; create it with REGENERATE=1 cargo test --release -p murk --test golden",
                path.display()
            )
        });
        assert!(
            pinned == rendered,
            "{} moved.\n--- pinned ({})\n{pinned}\n--- now\n{rendered}\nIf the change is \
             intended: REGENERATE=1 cargo test --release -p murk --test golden, and commit the \
             diff.",
            self.name,
            path.display()
        );
    }
}

/// Mean of `values` where `keep` holds.
fn masked_mean(values: &[f32], keep: impl Fn(usize) -> bool) -> f64 {
    let (mut sum, mut n) = (0.0f64, 0usize);
    for (i, &v) in values.iter().enumerate() {
        if keep(i) {
            sum += f64::from(v);
            n += 1;
        }
    }
    sum / n.max(1) as f64
}

/// ToF in fog (Ch. 5): a cluttered 64×53 frame in medium fog, the default method with the
/// emitter's position.
#[test]
fn tof_cluttered_medium_fog() {
    let cfg = TofSimConfig {
        preset: FogPreset::Medium,
        seed: 1,
        layout: SceneLayout::Cluttered,
        ..TofSimConfig::with_size(64, 53)
    };
    let frame = simulate_tof(&cfg, &Monitor::noop()).unwrap();
    let input = TofInput {
        amplitude: frame.amplitude.clone(),
        phase: frame.phase.clone(),
        intrinsics: Some(frame.intrinsics),
    };
    let params = TofParams {
        modulation_frequency_hz: cfg.modulation_frequency_hz,
        light_position_m: Some(cfg.light_position_m()),
        ..TofParams::default()
    };
    let out = estimate_tof_depth(&input, &params, &Monitor::noop()).unwrap();

    let mut g = Golden::new("tof");
    for img in [
        &out.range_m,
        &out.range_std_m,
        &out.raw_range_m,
        &out.mask,
        &out.scatter_amplitude,
        &out.scatter_phase,
        &out.corrected_amplitude,
        &out.corrected_phase,
    ] {
        g.checksum.image(img);
    }
    g.checksum.image(out.z_depth_m.as_ref().unwrap());
    let gt_mask = frame.gt_mask.data();
    let error = |range: &ImageF32| {
        let e: Vec<f32> = range
            .data()
            .iter()
            .zip(frame.gt_range_m.data())
            .map(|(r, t)| (r - t).abs())
            .collect();
        masked_mean(&e, |i| gt_mask[i] > 0.5)
    };
    g.stat("mean_error_in_gt_mask_m", error(&out.range_m));
    g.stat("raw_mean_error_in_gt_mask_m", error(&out.raw_range_m));
    g.stat(
        "mask_pixels",
        out.mask.data().iter().filter(|&&m| m > 0.5).count() as f64,
    );
    g.stat(
        "mean_scatter_amplitude",
        masked_mean(out.scatter_amplitude.data(), |_| true),
    );
    g.check();
}

/// MVS in haze (Ch. 3.2): a 96×72 hazy room, reference + 4 sources, the default dehazing cost
/// volume with the true A and β, 64 planes, SGM with its defaults.
#[test]
fn mvs_dehazing_room() {
    let cfg = MvsSimConfig {
        seed: 3,
        ..MvsSimConfig::with_size(96, 72)
    };
    let scene = simulate_mvs(&cfg, &Monitor::noop()).unwrap();
    let (reference, sources) = scene.reference_and_sources();
    let gt = &scene.views[scene.reference].depth;
    let finite: Vec<f32> = gt
        .data()
        .iter()
        .copied()
        .filter(|z| z.is_finite())
        .collect();
    let near = f64::from(finite.iter().copied().fold(f32::INFINITY, f32::min)) * 0.9;
    let far = f64::from(finite.iter().copied().fold(0.0, f32::max)) * 1.1;
    let planes = PlaneSet::new(near, far, 64).unwrap();
    let atmosphere = murk::atmosphere::AtmosphereParams {
        airlight: scene.airlight,
        beta: scene.beta,
    };
    let kind = CostKind::DehazingWith(atmosphere, DehazingOptions::default());
    let r = estimate_depth(
        &reference,
        &sources,
        &planes,
        kind,
        &DepthParams::default(),
        &Monitor::noop(),
    )
    .unwrap();

    let mut g = Golden::new("mvs");
    g.checksum.image(&r.z_depth);
    g.checksum.image(&r.inverse_depth);
    g.checksum.image(&r.confidence);
    g.checksum.f32s(r.source_gains.iter().copied());
    g.checksum.f32s([r.vignetting_falloff]);
    g.checksum.f32s(r.source_falloffs.iter().copied());
    let m = depth_metrics(&r.z_depth, gt, None).unwrap();
    g.stat("c_p", m.c_p);
    g.stat("l1_rel", m.l1_rel);
    g.stat("sc_inv", m.sc_inv);
    g.stat(
        "confident_share",
        r.confidence.data().iter().filter(|&&c| c > 0.0).count() as f64
            / r.confidence.pixel_count() as f64,
    );
    g.check();
}

/// Scattering parameters (Ch. 3.3, Algorithm 1 with the joint fit): a 128×96 hazy room with
/// forward motion, β drawn from [0.4, 0.8], the search started 0.06 below the true A.
#[test]
fn params_joint_fit_walking_room() {
    let cfg = MvsSimConfig {
        seed: 5,
        beta_range: Some([0.4, 0.8]),
        forward_motion: 0.5,
        ..MvsSimConfig::with_size(128, 96)
    };
    let scene = simulate_mvs(&cfg, &Monitor::noop()).unwrap();
    let (reference, sources) = scene.reference_and_sources();
    let sparse = scene.sparse_depth().unwrap();
    let (near, far) = plane_range_from_sparse(&sparse).unwrap();
    let planes = PlaneSet::new(near, far, 32).unwrap();
    let params = SearchParams {
        search_planes: 16,
        ..SearchParams::default()
    };
    let est = search_scattering(
        &reference,
        &sources,
        SfmEvidence::map(&sparse),
        scene.airlight - 0.06,
        &planes,
        &params,
        &Monitor::noop(),
    )
    .unwrap();

    let mut g = Golden::new("params");
    g.checksum
        .f32s([est.airlight, est.beta, est.beta_unclamped]);
    g.checksum.f32s(est.beta_range);
    g.checksum.f64s([
        est.airlight_std_error.unwrap_or(f64::NAN),
        est.beta_std_error.unwrap_or(f64::NAN),
        est.residual,
    ]);
    g.checksum.bytes(est.identifiability.name().as_bytes());
    g.stat("airlight", f64::from(est.airlight));
    g.stat("airlight_true", f64::from(scene.airlight));
    g.stat(
        "airlight_std_error",
        est.airlight_std_error.unwrap_or(f64::NAN),
    );
    g.stat("beta", f64::from(est.beta));
    g.stat("beta_true", f64::from(scene.beta));
    g.stat("beta_std_error", est.beta_std_error.unwrap_or(f64::NAN));
    // Where SfM put its points: the share of the errors from sampling at twice the blur.
    let share = est.sampling.and_then(|s| s.share).unwrap_or([f64::NAN; 2]);
    g.checksum.f64s(share);
    g.stat("airlight_sampling_share", share[0]);
    g.stat("beta_sampling_share", share[1]);
    g.check();
}

/// Photometric stereo in turbid water (Ch. 4): the reference's sphere at 64×64 (8 lights,
/// β = σ = 5e-3 /mm), kernel radius 15, 3 iterations.
#[test]
fn ps_sphere_turbid_water() {
    let sim = simulate_ps(&PsSimConfig::with_size(64, 64), &Monitor::noop()).unwrap();
    let params = PsParams {
        support_r: 15,
        max_iterations: 3,
        initial_distance_mm: sim.initial_distance_mm,
        ..PsParams::default()
    };
    let out = photometric_stereo(&sim.capture, &params, &Monitor::noop()).unwrap();

    let mut g = Golden::new("ps");
    g.checksum.f32s(out.normals.iter().flatten().copied());
    g.checksum.f32s(out.albedo.iter().copied());
    g.checksum.f32s(out.depth_mm.iter().copied());
    g.checksum
        .bytes(&out.mask.iter().map(|&m| u8::from(m)).collect::<Vec<_>>());
    let mask = &sim.capture.mask;
    for (i, n) in out.normals_history.iter().enumerate() {
        let key: &'static str = [
            "angular_error_deg_1",
            "angular_error_deg_2",
            "angular_error_deg_3",
        ]
        .get(i)
        .copied()
        .unwrap_or("angular_error_deg_later");
        g.stat(
            key,
            mean_angular_error_deg(n, &sim.gt_normals, mask).unwrap(),
        );
    }
    let depth_error: Vec<f32> = out
        .depth_mm
        .iter()
        .zip(&sim.gt_depth_mm)
        .map(|(d, t)| (d - t).abs())
        .collect();
    g.stat("depth_mae_mm", masked_mean(&depth_error, |i| mask[i]));
    g.check();
}
