//! Acceptance of ToF depth in fog (reference Ch. 5) on physically simulated frames: inside the
//! ground-truth object mask the corrected range must be within 3 cm on average, at least 5× better
//! than the uncorrected range, and the estimated object mask must match the truth (IoU ≥ 0.9).

// Diagnostics index several parallel images by pixel.
#![allow(clippy::needless_range_loop)]

use std::time::Instant;

use murk::simulate::tof::{simulate_tof, FogPreset, TofSimConfig, TofSimFrame};
use murk::simulate::SceneLayout;
use murk::tof::{estimate_tof_depth, TofInput, TofOutput, TofParams};
use murk::Monitor;

/// Errors and overlap of one run, all over the ground-truth object mask unless stated.
#[derive(Debug, Clone, Copy)]
struct Scores {
    mean_err_m: f64,
    raw_mean_err_m: f64,
    clear_mean_err_m: f64,
    iou: f64,
    gt_pixels: usize,
    est_pixels: usize,
    seconds: f64,
    /// Share of ground-truth object pixels whose range error is within `range_std_m` (68 % if
    /// the reported σ were exact and the errors Gaussian).
    within_1_std: f64,
}

fn simulate(preset: FogPreset, seed: u64, width: usize, height: usize) -> TofSimFrame {
    simulate_layout(preset, seed, width, height, env_layout())
}

/// `TOF_LAYOUT=cluttered` switches the survey and the diagnostics to cluttered scenes.
fn env_layout() -> SceneLayout {
    std::env::var("TOF_LAYOUT")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or_default()
}

fn simulate_layout(
    preset: FogPreset,
    seed: u64,
    width: usize,
    height: usize,
    layout: SceneLayout,
) -> TofSimFrame {
    let cfg = TofSimConfig {
        preset,
        seed,
        layout,
        ..TofSimConfig::with_size(width, height)
    };
    simulate_tof(&cfg, &Monitor::noop()).expect("simulation")
}

fn run(frame: &TofSimFrame) -> (TofOutput, f64) {
    let input = TofInput {
        amplitude: frame.amplitude.clone(),
        phase: frame.phase.clone(),
        intrinsics: Some(frame.intrinsics),
    };
    let mut params = TofParams {
        modulation_frequency_hz: frame.config.modulation_frequency_hz,
        light_position_m: Some(frame.config.light_position_m()),
        ..TofParams::default()
    };
    if let Some(rel) = std::env::var("TOF_BIL_REL")
        .ok()
        .and_then(|s| s.parse().ok())
    {
        params.bilateral = Some(murk::tof::BilateralParams {
            sigma_range_rel: rel,
            ..Default::default()
        });
    }
    if std::env::var("TOF_ALTERNATING").is_ok() {
        params.prior_coupling = murk::tof::PriorCoupling::Alternating;
    }
    if let Some(c) = std::env::var("TOF_COARSE")
        .ok()
        .and_then(|s| s.parse().ok())
    {
        params.coarse_iterations = c;
    }
    if std::env::var("TOF_AMPLITUDE_PHASE").is_ok() {
        params.channels = murk::tof::ScatterChannels::AmplitudePhase;
    }
    if std::env::var("TOF_NO_BILATERAL").is_ok() {
        params.bilateral = None;
    }
    // Experiment knobs: scale the phasor's prior weights γ₁ (quadratic), γ₂ (symmetry), γ₃
    // (smoothness); the coarse quantile and subdivision; the quadratic patch grid.
    let env_f = |k: &str| std::env::var(k).ok().and_then(|s| s.parse::<f64>().ok());
    for (g, key) in ["TOF_G1", "TOF_G2", "TOF_G3"].iter().enumerate() {
        if let Some(v) = env_f(key) {
            params.phasor.gamma[g] *= v;
        }
    }
    if let Some(v) = env_f("TOF_FINE") {
        params.fine_iterations = v as usize;
    }
    if let Some(v) = env_f("TOF_CQ") {
        params.coarse_quantile = v;
    }
    if let Some(v) = env_f("TOF_CSUB") {
        params.coarse_subdivision = v as usize;
    }
    if let Some(v) = env_f("TOF_PATCHES") {
        params.patches_x = v as usize;
        params.patches_y = v as usize;
    }
    let t = Instant::now();
    let out = match std::env::var("TOF_CG_MAX")
        .ok()
        .and_then(|s| s.parse().ok())
    {
        Some(max_iterations) => murk::tof::estimate_tof_depth_with_solver(
            &input,
            &params,
            murk::tof::XStepSolver::Pcg {
                rel_tol: 1e-5,
                max_iterations,
                preconditioner: Default::default(),
            },
            &Monitor::noop(),
        ),
        None => estimate_tof_depth(&input, &params, &Monitor::noop()),
    }
    .expect("estimate");
    (out, t.elapsed().as_secs_f64())
}

fn score(frame: &TofSimFrame, out: &TofOutput, seconds: f64) -> Scores {
    let gt = frame.gt_mask.data();
    let gt_range = frame.gt_range_m.data();
    let c = murk::tof::SPEED_OF_LIGHT_M_PER_S;
    let f = frame.config.modulation_frequency_hz;
    let (mut e, mut e_raw, mut e_clear, mut n) = (0.0, 0.0, 0.0, 0usize);
    let (mut inter, mut uni, mut est) = (0usize, 0usize, 0usize);
    let mut covered = 0usize;
    for i in 0..gt.len() {
        let g = gt[i] > 0.5;
        let m = out.mask.data()[i] > 0.5;
        inter += (g && m) as usize;
        uni += (g || m) as usize;
        est += m as usize;
        if g {
            let r = gt_range[i] as f64;
            let err = (out.range_m.data()[i] as f64 - r).abs();
            e += err;
            covered += (err <= out.range_std_m.data()[i] as f64) as usize;
            e_raw += (out.raw_range_m.data()[i] as f64 - r).abs();
            let clear = c * frame.phase_clear.data()[i] as f64 / (4.0 * std::f64::consts::PI * f);
            e_clear += (clear - r).abs();
            n += 1;
        }
    }
    let nn = n.max(1) as f64;
    Scores {
        mean_err_m: e / nn,
        raw_mean_err_m: e_raw / nn,
        clear_mean_err_m: e_clear / nn,
        iou: if uni == 0 {
            1.0
        } else {
            inter as f64 / uni as f64
        },
        gt_pixels: n,
        est_pixels: est,
        seconds,
        within_1_std: covered as f64 / nn,
    }
}

fn assert_acceptance(s: &Scores, what: &str) {
    assert!(s.gt_pixels > 0, "{what}: scene without objects");
    assert!(
        s.mean_err_m <= 0.03,
        "{what}: mean range error {:.4} m > 0.03 m ({s:?})",
        s.mean_err_m
    );
    assert!(
        s.raw_mean_err_m >= 5.0 * s.mean_err_m,
        "{what}: uncorrected error {:.4} m is not ≥ 5× the corrected {:.4} m ({s:?})",
        s.raw_mean_err_m,
        s.mean_err_m
    );
    assert!(s.iou >= 0.9, "{what}: mask IoU {:.3} < 0.9 ({s:?})", s.iou);
}

/// Medium fog at 128 × 106 on seeds 0–5 (all of the survey's medium seeds).
///
/// Seeds 0, 3 and 4 failed (0.036 / 0.12 / 0.06 m) until two changes to `murk::tof::irls`: the
/// a-step fits the patch quadratics with the IRLS weights, so the scatter estimate no longer
/// drifts under large objects (seeds 3, 4), and σ₁ is re-measured from the first x-step solved
/// under pixel weights instead of the coarse level's leftovers (seed 0: σ₁ was 3.5× the noise,
/// dim object pixels stayed amplitude inliers). The thin preset's seeds 3 and 4 (large objects
/// in weak scatter) still end worse than the uncorrected range; see `survey`.
#[test]
fn medium_fog_reduced_size_meets_acceptance() {
    for seed in 0..6 {
        let frame = simulate(FogPreset::Medium, seed, 128, 106);
        let (out, secs) = run(&frame);
        let s = score(&frame, &out, secs);
        assert_acceptance(&s, &format!("medium 128x106 seed {seed}"));
    }
}

/// Masks in thin and medium fog on the separated layout at 128 × 106, seeds 0–5: IoU ≥ 0.99
/// (measured 0.995–1.000). With σ₁ the MAD over every pixel, objects included, the scale came
/// out above the noise and dim object edges stayed inliers (thin seed 5: 0.951, medium seed 5:
/// 0.967); over the background alone it came out below the noise and flagged noise. σ₁ is the
/// background's MAD floored at the sensor noise (`tof::irls`, docs/ACCURACY.md).
#[test]
fn thin_and_medium_masks_reduced_size_are_tight() {
    for preset in [FogPreset::Thin, FogPreset::Medium] {
        for seed in 0..6 {
            let frame = simulate_layout(preset, seed, 128, 106, SceneLayout::Separated);
            let (out, secs) = run(&frame);
            let s = score(&frame, &out, secs);
            assert!(s.iou >= 0.99, "separated {preset} seed {seed}: {s:?}");
        }
    }
}

/// Issue 22's occluding scenes at 128 × 106, seeds 0–5 of the cluttered layout (a large bright
/// sphere 0.75–1.05 m away hiding part of a panel, plus 1–2 objects): medium fog within 30 mm
/// and at most a third of the uncorrected error, thick fog within the issue's 40 mm (worst:
/// seed 1, 36.7 mm; 41.8 mm when the simulator still added the noise's standard deviations),
/// mask IoU ≥ 0.95 in both (the issue asks 0.9; measured 0.988–1.000 since σ₁ is floored at the
/// sensor noise). Before the joint prior, the phasor channels and the coarse blocks, medium fog
/// gave 14–450 mm and IoU 0.66–0.99.
#[test]
fn cluttered_scenes_reduced_size_meet_issue_22() {
    for seed in 0..6 {
        for (preset, limit) in [(FogPreset::Medium, 0.03), (FogPreset::Thick, 0.04)] {
            let frame = simulate_layout(preset, seed, 128, 106, SceneLayout::Cluttered);
            let (out, secs) = run(&frame);
            let s = score(&frame, &out, secs);
            let what = format!("cluttered {preset} seed {seed}");
            assert!(s.mean_err_m <= limit, "{what}: {s:?}");
            assert!(s.raw_mean_err_m >= 3.0 * s.mean_err_m, "{what}: {s:?}");
            assert!(s.iou >= 0.95, "{what}: {s:?}");
        }
    }
}

/// The frame that failed issue 22's thick-fog target at full size: cluttered thick seed 1 at
/// 512 × 424, where a band of the panel beside the large near sphere passed the coarse level
/// as background (219 mm, IoU 0.864 in session 19; 65.9 mm, IoU 0.957 with physical noise and
/// σ₁ at the noise floor). The held-out check of the coarse level's blocks
/// (`tof::irls::HELD_OUT_ROUNDS`) rejects most of the band (40.5 mm, IoU 0.980 with 50 fine
/// iterations); the fine level then peels the rest off the band's edges and converges after
/// about 105 iterations (`tof::DEFAULT_FINE_ITERATIONS`): measured 24.7 mm, IoU 0.999.
#[test]
fn cluttered_thick_seed_1_full_size_keeps_the_panel_band_out_of_the_background() {
    let frame = simulate_layout(FogPreset::Thick, 1, 512, 424, SceneLayout::Cluttered);
    let (out, secs) = run(&frame);
    let s = score(&frame, &out, secs);
    eprintln!("{s:?}");
    assert!(s.mean_err_m <= 0.03, "{s:?}");
    assert!(s.iou >= 0.99, "{s:?}");
    assert!(s.raw_mean_err_m >= 10.0 * s.mean_err_m, "{s:?}");
}

/// Survey over presets, seeds and sizes; prints a table. Run with
/// `cargo test --release --test tof_accuracy -- --ignored --nocapture`.
#[test]
#[ignore]
fn survey() {
    let sizes: Vec<(usize, usize)> = match std::env::var("TOF_SURVEY_SIZES").as_deref() {
        Ok("full") => vec![(512, 424)],
        Ok("both") => vec![(128, 106), (512, 424)],
        _ => vec![(128, 106)],
    };
    let seeds: u64 = std::env::var("TOF_SURVEY_SEEDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(6);
    println!(
        "size      preset  seed  err_m   raw_m   clear_m  ratio  IoU    gt_px  est_px  secs   in1σ"
    );
    for &(w, h) in &sizes {
        for preset in FogPreset::ALL {
            for seed in 0..seeds {
                let frame = simulate(preset, seed, w, h);
                let (out, secs) = run(&frame);
                let s = score(&frame, &out, secs);
                println!(
                    "{w}x{h:<4} {preset:<7} {seed:<4} {:.4}  {:.4}  {:.4}   {:5.1}  {:.3}  {:6} {:6}  {:.3}  {:.3}",
                    s.mean_err_m,
                    s.raw_mean_err_m,
                    s.clear_mean_err_m,
                    s.raw_mean_err_m / s.mean_err_m.max(1e-9),
                    s.iou,
                    s.gt_pixels,
                    s.est_pixels,
                    s.seconds,
                    s.within_1_std
                );
            }
        }
    }
}

/// The frame the diagnostics look at: `TOF_PRESET` (thin, medium by default, thick),
/// `TOF_SEED` (1), `TOF_SIZE` (`full` for 512×424, else 128×106) and `TOF_LAYOUT`.
fn env_frame() -> TofSimFrame {
    let preset = match std::env::var("TOF_PRESET").as_deref() {
        Ok("thin") => FogPreset::Thin,
        Ok("thick") => FogPreset::Thick,
        _ => FogPreset::Medium,
    };
    let seed: u64 = std::env::var("TOF_SEED")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(1);
    let (w, h) = match std::env::var("TOF_SIZE").as_deref() {
        Ok("full") => (512, 424),
        _ => (128, 106),
    };
    simulate(preset, seed, w, h)
}

/// Diagnostics of one frame: scatter-estimate errors in and out of the object, σ, CG work.
#[test]
#[ignore]
fn diagnose() {
    use murk::tof::irls::{run_irls, IrlsConfig};
    use murk::tof::quadratic_prior::{PatchGrid, QuadraticPrior};
    use murk::tof::symmetry::RowMirror;
    use murk::tof::wls::XStepSystem;
    use murk::tof::{IrlsChannelParams, XStepSolver};
    let frame = env_frame();
    let (w, h) = frame.amplitude.dims();
    let gt = frame.gt_mask.data();
    for (name, img, truth, ch) in [
        (
            "amplitude",
            &frame.amplitude,
            &frame.scatter_amplitude,
            IrlsChannelParams::AMPLITUDE,
        ),
        (
            "phase",
            &frame.phase,
            &frame.scatter_phase,
            IrlsChannelParams::PHASE,
        ),
    ] {
        let mut filtered = img.data().to_vec();
        if std::env::var("TOF_DIAG_BILATERAL").is_ok() {
            let b = murk::tof::BilateralParams::default();
            murk::tof::bilateral::bilateral_filter(img.data(), w, h, &b, &mut filtered);
        }
        let observed: Vec<f64> = filtered.iter().map(|&v| v as f64).collect();
        let mut ch = ch;
        if let Some(v) = std::env::var("TOF_CFINE_SCALE")
            .ok()
            .and_then(|s| s.parse::<f64>().ok())
        {
            ch.c_fine *= v;
        }
        if let Some(v) = std::env::var("TOF_G1_SCALE")
            .ok()
            .and_then(|s| s.parse::<f64>().ok())
        {
            ch.gamma[0] *= v;
        }
        if let Some(v) = std::env::var("TOF_G3_SCALE")
            .ok()
            .and_then(|s| s.parse::<f64>().ok())
        {
            ch.gamma[2] *= v;
        }
        let sys = XStepSystem::new(
            w,
            h,
            ch.effective_gamma(w, h),
            RowMirror::new(h, frame.intrinsics.cy),
        );
        let sys = if std::env::var("TOF_JOINT").is_ok() {
            sys.with_joint_prior(PatchGrid::new(w, h, 4, 4)).unwrap()
        } else {
            sys
        };
        let mut prior = QuadraticPrior::new(PatchGrid::new(w, h, 4, 4)).unwrap();
        let cfg = IrlsConfig {
            channel: ch,
            coarse_iterations: std::env::var("TOF_COARSE")
                .ok()
                .and_then(|s| s.parse().ok())
                .unwrap_or(5),
            fine_iterations: 50,
            solver: XStepSolver::default(),
            weight_tolerance: murk::tof::irls::DEFAULT_WEIGHT_TOLERANCE,
            mask_threshold: 0.5,
            coarse_subdivision: 1,
            coarse_quantile: 0.5,
        };
        let t = Instant::now();
        let o = run_irls(
            &observed,
            &sys,
            &mut prior,
            &cfg,
            "d",
            &Monitor::noop(),
            &|_| {},
        )
        .unwrap();
        let secs = t.elapsed().as_secs_f64();
        if std::env::var("TOF_MAPS").is_ok() {
            // Coarse map: '#' object outlier, 'x' background outlier, 'o' object inlier, '.' ok;
            // then the scatter error relative to the truth's spread, 0–9.
            let (sx, sy) = (w / 64, h / 26);
            let spread = truth.data().iter().fold(0.0f32, |m, v| m.max(v.abs())) as f64;
            for y in (0..h).step_by(sy.max(1)) {
                let mut line = String::new();
                let mut line2 = String::new();
                for x in (0..w).step_by(sx.max(1)) {
                    let i = y * w + x;
                    let obj = gt[i] > 0.5;
                    let out = o.weights[i] < 0.5;
                    line.push(match (obj, out) {
                        (true, true) => '#',
                        (false, true) => 'x',
                        (true, false) => 'o',
                        _ => '.',
                    });
                    let d = o.scatter[0][i] - truth.data()[i] as f64;
                    let e = (d.abs() / spread * 50.0).min(9.0);
                    if std::env::var("TOF_SIGNED").is_ok() && d < 0.0 && e >= 1.0 {
                        // Underestimate: letters a (1) … i (9).
                        line2.push(char::from(b'a' + e as u8 - 1));
                    } else {
                        line2.push(char::from(b'0' + e as u8));
                    }
                }
                println!("{line}   {line2}");
            }
        }
        let (mut ein, mut eout, mut obs_bg, mut nin, mut nout, mut tin) =
            (0.0, 0.0, 0.0, 0, 0, 0.0);
        let (mut fp, mut fneg) = (0, 0);
        for i in 0..w * h {
            let e = (o.scatter[0][i] - truth.data()[i] as f64).abs();
            if gt[i] > 0.5 {
                ein += e;
                tin += truth.data()[i] as f64;
                nin += 1;
                fneg += (o.weights[i] >= 0.5) as usize;
            } else {
                eout += e;
                obs_bg += (observed[i] - truth.data()[i] as f64).abs();
                nout += 1;
                fp += (o.weights[i] < 0.5) as usize;
            }
        }
        println!(
            "{name}: |x−s| in obj {:.4} (mean s {:.4}), bg {:.4}; |x̃−s| bg {:.4}; σ2 {:?} σ1 {:?}; \
             cg its {} ({:.1}/solve, {}+{} its, {} held-out rejections); {:.3}s; outlier-bg px {fp}/{nout}, inlier-obj px {fneg}/{nin}",
            ein / nin as f64,
            tin / nin as f64,
            eout / nout as f64,
            obs_bg / nout as f64,
            o.sigma_coarse,
            o.sigma_fine,
            o.cg_iterations,
            o.cg_iterations as f64 / (o.coarse_iterations_run + o.fine_iterations_run).max(1) as f64,
            o.coarse_iterations_run,
            o.fine_iterations_run,
            o.held_out_rejected,
            secs
        );
    }
    // Oracle: subtract the true scatter phasor from the observation (floor of the method).
    let c = murk::tof::SPEED_OF_LIGHT_M_PER_S;
    let f = frame.config.modulation_frequency_hz;
    let k = c / (4.0 * std::f64::consts::PI * f);
    let (out, _) = run(&frame);
    let (mut eo, mut ee, mut esa, mut esp, mut n) = (0.0, 0.0, 0.0, 0.0, 0);
    let mut mixed = [0.0f64; 2];
    for i in 0..w * h {
        if gt[i] < 0.5 {
            continue;
        }
        let (a, p) = (
            frame.amplitude.data()[i] as f64,
            frame.phase.data()[i] as f64,
        );
        let (sa, sp) = (
            frame.scatter_amplitude.data()[i] as f64,
            frame.scatter_phase.data()[i] as f64,
        );
        let re = a * p.cos() - sa * sp.cos();
        let im = a * p.sin() - sa * sp.sin();
        let ph = im.atan2(re).rem_euclid(2.0 * std::f64::consts::PI);
        eo += (k * ph - frame.gt_range_m.data()[i] as f64).abs();
        // Mixed oracles: one channel's scatter true, the other estimated.
        let (ea, ep) = (
            out.scatter_amplitude.data()[i] as f64,
            out.scatter_phase.data()[i] as f64,
        );
        for (j, (a_s, p_s)) in [(sa, ep), (ea, sp)].into_iter().enumerate() {
            let re = a * p.cos() - a_s * p_s.cos();
            let im = a * p.sin() - a_s * p_s.sin();
            let ph = im.atan2(re).rem_euclid(2.0 * std::f64::consts::PI);
            mixed[j] += (k * ph - frame.gt_range_m.data()[i] as f64).abs();
        }
        ee += (out.range_m.data()[i] as f64 - frame.gt_range_m.data()[i] as f64).abs();
        esa += (out.scatter_amplitude.data()[i] as f64 - sa).abs();
        esp += (out.scatter_phase.data()[i] as f64 - sp).abs();
        n += 1;
    }
    if std::env::var("TOF_MAPS").is_ok() {
        // Pipeline mask: '#' right, 'o' missed, 'x' false on the background, 's' an object pixel
        // the light does not reach (not in the ground-truth mask).
        let (sx, sy) = (w / 64, h / 26);
        let obj = frame.gt_object_mask.data();
        let phasor = |a: f32, p: f32| {
            let (s, c) = (p as f64).sin_cos();
            (a as f64 * c, a as f64 * s)
        };
        for y in (0..h).step_by(sy.max(1)) {
            let mut line = String::new();
            let mut errs = String::new();
            for x in (0..w).step_by(sx.max(1)) {
                let i = y * w + x;
                // Scatter phasor error in units of 2 (≈ the noise σ of a bright pixel).
                let (er, ei) = phasor(out.scatter_amplitude.data()[i], out.scatter_phase.data()[i]);
                let (tr, ti) = phasor(
                    frame.scatter_amplitude.data()[i],
                    frame.scatter_phase.data()[i],
                );
                errs.push(char::from(
                    b'0' + ((er - tr).hypot(ei - ti) / 2.0).min(9.0) as u8,
                ));
                let m = out.mask.data()[i] > 0.5;
                line.push(match (gt[i] > 0.5, m, obj[i] > 0.5) {
                    (true, true, _) => '#',
                    (true, false, _) => 'o',
                    (false, true, true) => 's',
                    (false, true, false) => 'x',
                    (false, false, true) => ',',
                    _ => '.',
                });
            }
            println!("{line}   {errs}");
        }
    }
    if let Some(row) = std::env::var("TOF_PROBE_ROW")
        .ok()
        .and_then(|s| s.parse::<usize>().ok())
    {
        for x in (w * 3 / 4..w).step_by(2) {
            let i = row * w + x;
            let (a, p) = (
                frame.scatter_amplitude.data()[i],
                frame.scatter_phase.data()[i],
            );
            let (ea, ep) = (out.scatter_amplitude.data()[i], out.scatter_phase.data()[i]);
            println!(
                "x {x}: true a {a:.2} p {p:.4} re {:.2} im {:.2}; est a {ea:.2} p {ep:.4}; obs a {:.2} p {:.4}",
                a * p.cos(),
                a * p.sin(),
                frame.amplitude.data()[i],
                frame.phase.data()[i]
            );
        }
    }
    // Saturation oracle: the fog-only phasor to the wall along each object pixel's ray (what
    // a perfect interpolation of the background scatter gives), subtracted instead of the truth.
    let (mut esat, mut amp_t, mut amp_sat) = (0.0, 0.0, 0.0);
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if gt[i] < 0.5 {
                continue;
            }
            let d = frame.intrinsics.ray(x as f64, y as f64);
            let sat = murk::simulate::tof::scatter_along_ray(
                &frame.config,
                d,
                frame.scene.wall_z_m / d[2],
            )
            .unwrap();
            let (a, p) = (
                frame.amplitude.data()[i] as f64,
                frame.phase.data()[i] as f64,
            );
            let re = a * p.cos() - sat.re;
            let im = a * p.sin() - sat.im;
            let ph = im.atan2(re).rem_euclid(2.0 * std::f64::consts::PI);
            esat += (k * ph - frame.gt_range_m.data()[i] as f64).abs();
            amp_t += frame.scatter_amplitude.data()[i] as f64;
            amp_sat += sat.amplitude();
        }
    }
    let n = n as f64;
    println!(
        "saturated-scatter oracle range err {:.4} m; mean scatter amplitude true {:.3}, saturated {:.3}",
        esat / n,
        amp_t / n,
        amp_sat / n
    );
    println!(
        "range err with true α_s + estimated φ_s {:.4} m; estimated α_s + true φ_s {:.4} m",
        mixed[0] / n,
        mixed[1] / n
    );
    println!(
        "oracle-scatter range err {:.4} m; pipeline err {:.4} m; pipeline |Δα_s| {:.3} |Δφ_s| {:.4}",
        eo / n,
        ee / n,
        esa / n,
        esp / n
    );
}

/// The production pipeline's mask and scatter estimate on one frame (same environment
/// variables as `diagnose`, plus `TOF_LAYOUT`), as three coarse maps: '#' object flagged, 'x'
/// background flagged, 'o' object missed, '.' background kept; the scatter phasor's error, 0–9
/// in fiftieths of the largest true scatter amplitude, as in `diagnose`; the true scatter
/// amplitude in tenths of its largest value. Then the frame's fitted noise model against the
/// simulator's, and the residuals in units of that model's σ where background is flagged, in
/// the dark left columns and in the middle.
#[test]
#[ignore]
fn production_maps() {
    let frame = env_frame();
    let (w, h) = frame.amplitude.dims();
    let (out, secs) = run(&frame);
    let s = score(&frame, &out, secs);
    println!("{s:?}");
    let gt = frame.gt_mask.data();
    let (ta, tp) = (frame.scatter_amplitude.data(), frame.scatter_phase.data());
    let (ea, ep) = (out.scatter_amplitude.data(), out.scatter_phase.data());
    let spread = ta.iter().fold(0.0f32, |m, v| m.max(v.abs())) as f64;
    let (sx, sy) = (w / 64, h / 26);
    for y in (0..h).step_by(sy.max(1)) {
        let (mut l1, mut l2, mut l3) = (String::new(), String::new(), String::new());
        for x in (0..w).step_by(sx.max(1)) {
            let i = y * w + x;
            let (obj, out_px) = (gt[i] > 0.5, out.mask.data()[i] > 0.5);
            l1.push(match (obj, out_px) {
                (true, true) => '#',
                (false, true) => 'x',
                (true, false) => 'o',
                _ => '.',
            });
            let t = (
                ta[i] as f64 * (tp[i] as f64).cos(),
                ta[i] as f64 * (tp[i] as f64).sin(),
            );
            let e = (
                ea[i] as f64 * (ep[i] as f64).cos(),
                ea[i] as f64 * (ep[i] as f64).sin(),
            );
            let d = ((t.0 - e.0).powi(2) + (t.1 - e.1).powi(2)).sqrt();
            let v = (d / spread * 50.0).min(9.0) as u8;
            l2.push(char::from(b'0' + v));
            let v = (ta[i] as f64 / spread * 10.0).min(9.0) as u8;
            l3.push(char::from(b'0' + v));
        }
        println!("{l1}   {l2}   {l3}");
    }
    let flagged_bg: Vec<usize> = (0..w * h)
        .filter(|&i| gt[i] <= 0.5 && out.mask.data()[i] > 0.5)
        .collect();
    let obs = frame.amplitude.data();
    let mean = |f: &dyn Fn(usize) -> f64| {
        flagged_bg.iter().map(|&i| f(i)).sum::<f64>() / flagged_bg.len().max(1) as f64
    };
    println!(
        "background flagged: {} px; mean observed amplitude {:.2}, true scatter {:.2}, estimated {:.2}, weight {:.3}",
        flagged_bg.len(),
        mean(&|i| obs[i] as f64),
        mean(&|i| ta[i] as f64),
        mean(&|i| ea[i] as f64),
        mean(&|i| out.weight_phase.data()[i] as f64),
    );
    let ph = frame.phase.data();
    let (re, im): (Vec<f32>, Vec<f32>) = obs
        .iter()
        .zip(ph)
        .map(|(&a, &p)| (a * p.cos(), a * p.sin()))
        .unzip();
    let noise = murk::tof::noise_model::NoiseModel::fit(&re, &im, obs, w).unwrap();
    let true_sigma = |a: f64| frame.config.noise_sigma(a);
    println!(
        "noise model {noise:?}; σ at 2: fitted {:.3} true {:.3}; at 20: {:.3} / {:.3}",
        noise.sigma(2.0),
        true_sigma(2.0),
        noise.sigma(20.0),
        true_sigma(20.0)
    );
    let resid = |i: usize, est: bool| {
        let (a, p) = if est { (ea[i], ep[i]) } else { (ta[i], tp[i]) };
        let (sr, si) = (a * p.cos(), a * p.sin());
        (((re[i] - sr) as f64).powi(2) + ((im[i] - si) as f64).powi(2)).sqrt()
            / noise.sigma(a as f64)
    };
    for (name, set) in [
        ("flagged bg", flagged_bg.clone()),
        (
            "missed object",
            (0..w * h)
                .filter(|&i| gt[i] > 0.5 && out.mask.data()[i] <= 0.5)
                .collect::<Vec<_>>(),
        ),
        (
            "object kept",
            (0..w * h)
                .filter(|&i| gt[i] > 0.5 && out.mask.data()[i] > 0.5)
                .collect::<Vec<_>>(),
        ),
        (
            "bg, 8 left columns",
            (0..w * h)
                .filter(|&i| i % w < 8 && gt[i] <= 0.5)
                .collect::<Vec<_>>(),
        ),
        (
            "bg, middle",
            (0..w * h)
                .filter(|&i| (i % w).abs_diff(w / 2) < 8 && gt[i] <= 0.5)
                .collect::<Vec<_>>(),
        ),
    ] {
        let m = |f: &dyn Fn(usize) -> f64| {
            set.iter().map(|&i| f(i)).sum::<f64>() / set.len().max(1) as f64
        };
        println!(
            "{name}: {} px, |obs − est s|/σ {:.2}, |obs − true s|/σ {:.2}, est − true amplitude {:.3}, flagged share {:.3}, mean true s {:.2}",
            set.len(),
            m(&|i| resid(i, true)),
            m(&|i| resid(i, false)),
            m(&|i| (ea[i] - ta[i]) as f64),
            m(&|i| (out.mask.data()[i] > 0.5) as u8 as f64),
            m(&|i| ta[i] as f64),
        );
    }
}
