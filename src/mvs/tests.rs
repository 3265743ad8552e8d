//! End-to-end comparison for issue 3: on simulated hazy scenes with ground-truth `A` and `β`,
//! the dehazing cost volume + SGM against the ordinary one (Eq. 3.1) + SGM.
//!
//! Status (measured, see the printed tables; sensor noise σ = 0.01): the reference's Eq. 3.7
//! (`eq37`) loses badly to the ordinary volume — Eq. 3.5 amplifies noise by `1/t`, so far,
//! low-transmission voxels look bad at the correct depth. Measuring the same constraint in
//! observation space (`DehazingResidual::ObservationSpace`, the default) removes that: at
//! 256×192×256, 4 sources, seeds 0–4 it beats ordinary on every metric on every seed
//! (mean L1-rel 0.074 vs 0.156, C.P. 81.5 % vs 69.0 % with the defaults: SGM P1 = 0.01,
//! P2 = 0.1, views pre-smoothed with σ = 0.8 px, contrast-normalised costs; on held-out seeds
//! 5–9 0.066 vs 0.109 and 81.9 % vs 68.9 %). Every `[0, 1]` range penalty tried
//! (hard, noise-aware, reference-only, soft) *costs* accuracy here, even though at the true
//! depth the reference's dehazed values never leave the noise-widened range, so the default
//! has none. At reduced size the test below asserts mean L1-rel and mean C.P.
//! Without the contrast normalisation the default reached 73.4 % (70.7 % without the
//! pre-smoothing): far, low-transmission surfaces had too little evidence against the fixed SGM
//! penalties. A dark-channel range prior (haze as a depth cue, a windowed form of Eq. 3.7's
//! [0, 1] check) was tried and lowered C.P. to 59–64 % (our textures' dark channel is 0.1–0.4,
//! not ≈ 0).

use std::time::Instant;

use crate::atmosphere::AtmosphereParams;
use crate::image::ImageF32;
use crate::metrics::{depth_metrics, DepthMetrics};
use crate::monitor::Monitor;
use crate::mvs::{
    estimate_depth, CostKind, DehazingOptions, DehazingResidual, PlaneSet, RangePenalty, SgmParams,
    View,
};
use crate::simulate::mvs::{simulate_mvs, MvsScene, MvsSimConfig};

/// Depth of the reference view of `scene` with `kind` and `sgm`, the metrics against GT, and
/// the wall time of [`estimate_depth`] (pre-smoothing, cost volume, aggregation), seconds.
fn evaluate_with(
    scene: &MvsScene,
    planes: &PlaneSet,
    kind: CostKind,
    num_sources: usize,
    sgm: &SgmParams,
) -> (DepthMetrics, f64) {
    let views: Vec<View<'_>> = scene.hazy_views();
    let reference = views[scene.reference];
    // Sources nearest to the reference first (by trajectory position).
    let sources = nearest_sources(&views, scene.reference, num_sources);
    let t0 = Instant::now();
    let depth = estimate_depth(&reference, &sources, planes, kind, sgm, &Monitor::noop()).unwrap();
    let elapsed = t0.elapsed().as_secs_f64();
    let gt: &ImageF32 = &scene.views[scene.reference].depth;
    (depth_metrics(&depth.z_depth, gt, None).unwrap(), elapsed)
}

/// The `n` views nearest to `reference` along the trajectory (by index), nearest first.
fn nearest_sources<'a>(views: &[View<'a>], reference: usize, n: usize) -> Vec<View<'a>> {
    let mut others: Vec<usize> = (0..views.len()).filter(|&i| i != reference).collect();
    others.sort_by_key(|&i| i.abs_diff(reference));
    others.iter().take(n).map(|&i| views[i]).collect()
}

/// [`evaluate_with`] with the default [`SgmParams`], but for the census term's weight and the
/// number of SGM paths, which `MURK_CENSUS_WEIGHT` and `MURK_PATHS` set for the measurements
/// (default: the library's).
fn evaluate(
    scene: &MvsScene,
    planes: &PlaneSet,
    kind: CostKind,
    num_sources: usize,
) -> (DepthMetrics, f64) {
    let defaults = SgmParams::default();
    let sgm = SgmParams {
        census_weight: std::env::var("MURK_CENSUS_WEIGHT")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(defaults.census_weight),
        num_paths: std::env::var("MURK_PATHS")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(defaults.num_paths),
        ..defaults
    };
    evaluate_with(scene, planes, kind, num_sources, &sgm)
}

/// The cost volumes compared: ordinary, the reference's Eq. 3.7, and the noise-robust variants
/// (residual space × range penalty; `default` is `DehazingOptions::default()`).
/// `MURK_VARIANTS` (comma-separated names, or `all`) overrides the set `default_set`.
fn kinds(scene: &MvsScene, default_set: &[&str]) -> Vec<(&'static str, CostKind)> {
    let atm = AtmosphereParams {
        airlight: scene.airlight,
        beta: scene.beta,
    };
    let with = |residual, range| {
        CostKind::DehazingWith(
            atm,
            DehazingOptions {
                residual,
                range,
                noise_sigma: None,
            },
        )
    };
    let aware = RangePenalty::NoiseAware { k: 3.0 };
    let soft = RangePenalty::Soft { k: 3.0 };
    let refaware = RangePenalty::ReferenceAware { k: 3.0 };
    let all = vec![
        ("ordinary", CostKind::Ordinary),
        ("eq37", CostKind::Dehazing(atm)),
        ("eq37+aware", with(DehazingResidual::Eq37, aware)),
        (
            "obs+hard",
            with(DehazingResidual::ObservationSpace, RangePenalty::Hard),
        ),
        ("obs+aware", with(DehazingResidual::ObservationSpace, aware)),
        (
            "obs+off",
            with(DehazingResidual::ObservationSpace, RangePenalty::Off),
        ),
        ("obs+soft", with(DehazingResidual::ObservationSpace, soft)),
        ("eq37+soft", with(DehazingResidual::Eq37, soft)),
        (
            "obs+refaware",
            with(DehazingResidual::ObservationSpace, refaware),
        ),
        ("eq37+refaware", with(DehazingResidual::Eq37, refaware)),
        ("white+aware", with(DehazingResidual::NoiseWhitened, aware)),
        (
            "white+off",
            with(DehazingResidual::NoiseWhitened, RangePenalty::Off),
        ),
        (
            "default",
            CostKind::DehazingWith(atm, DehazingOptions::default()),
        ),
    ];
    let list = std::env::var("MURK_VARIANTS").unwrap_or_else(|_| default_set.join(","));
    if list == "all" {
        return all;
    }
    all.into_iter()
        .filter(|(n, _)| list.split(',').any(|l| l == *n))
        .collect()
}

/// Reduced-size comparison (128×96, 96 planes, 4 sources, seeds 0..5). Sensor noise from
/// `MURK_NOISE` (default: the simulator's 0.01). Asserts that every pipeline produces valid
/// depth everywhere; prints the metrics.
#[test]
fn dehazing_vs_ordinary_at_reduced_size() {
    let planes = PlaneSet::new(1.5, 15.0, 96).unwrap();
    let seeds = 0..5u64;
    let mut rows: Vec<(&'static str, u64, DepthMetrics)> = Vec::new();
    for seed in seeds.clone() {
        let cfg = MvsSimConfig {
            seed,
            noise_sigma: std::env::var("MURK_NOISE")
                .ok()
                .and_then(|v| v.parse().ok())
                .unwrap_or(0.01),
            ..MvsSimConfig::with_size(128, 96)
        };
        let scene = simulate_mvs(&cfg, &Monitor::noop()).unwrap();
        for (name, kind) in kinds(&scene, &["ordinary", "eq37", "default"]) {
            let (m, _) = evaluate(&scene, &planes, kind, 4);
            assert_eq!(m.missing_predictions, 0, "{name}");
            assert!(m.l1_rel.is_finite() && m.c_p.is_finite(), "{name}");
            rows.push((name, seed, m));
        }
    }
    print_table(&rows, seeds.clone().count());
    if std::env::var("MURK_NOISE").is_ok() || std::env::var("MURK_VARIANTS").is_ok() {
        return;
    }
    // The ordering, on the default noise: the default dehazing volume (observation-space
    // residual) beats the ordinary one on mean L1-rel and mean C.P. over the seeds. Per seed it
    // wins on L1-rel on 4 of 5 seeds at this size (seed 2 loses by 0.004); at 256×192×256 see
    // `measure_full_size`.
    let mean = |name: &str, f: fn(&DepthMetrics) -> f64| {
        rows.iter()
            .filter(|r| r.0 == name)
            .map(|r| f(&r.2))
            .sum::<f64>()
            / seeds.clone().count() as f64
    };
    let (l1_ord, l1_def) = (
        mean("ordinary", |m| m.l1_rel),
        mean("default", |m| m.l1_rel),
    );
    let (cp_ord, cp_def) = (mean("ordinary", |m| m.c_p), mean("default", |m| m.c_p));
    assert!(
        l1_def < l1_ord,
        "mean L1-rel: dehazing {l1_def} >= ordinary {l1_ord}"
    );
    assert!(
        cp_def > cp_ord,
        "mean C.P.: dehazing {cp_def} <= ordinary {cp_ord}"
    );
}

/// Prints per-seed rows and per-variant means of `rows` (variant, seed, metrics).
fn print_table(rows: &[(&'static str, u64, DepthMetrics)], n_seeds: usize) {
    println!("| seed | cost volume | L1-rel | L1-inv | sc-inv | C.P. (%) |");
    println!("|---|---|---|---|---|---|");
    for (name, seed, m) in rows {
        println!(
            "| {seed} | {name} | {:.3} | {:.4} | {:.3} | {:.1} |",
            m.l1_rel,
            m.l1_inv,
            m.sc_inv,
            100.0 * m.c_p
        );
    }
    let mut names: Vec<&str> = rows.iter().map(|r| r.0).collect();
    names.dedup();
    names.truncate(rows.len() / n_seeds.max(1));
    for name in names {
        let mut mean = [0.0f64; 4];
        for (_, _, m) in rows.iter().filter(|r| r.0 == name) {
            for (acc, v) in mean.iter_mut().zip([m.l1_rel, m.l1_inv, m.sc_inv, m.c_p]) {
                *acc += v / n_seeds as f64;
            }
        }
        println!(
            "| mean | {name} | {:.3} | {:.4} | {:.3} | {:.1} |",
            mean[0],
            mean[1],
            mean[2],
            100.0 * mean[3]
        );
    }
}

/// Variants measured at full size unless `MURK_VARIANTS` says otherwise.
const FULL_SIZE_SET: [&str; 9] = [
    "ordinary",
    "eq37",
    "eq37+aware",
    "obs+hard",
    "obs+aware",
    "obs+refaware",
    "obs+soft",
    "obs+off",
    "white+off",
];

/// Full-size measurement for the issue (256×192, 256 planes, 4 sources, 5 seeds): prints a
/// metric table and timings. Run with
/// `cargo test --release --lib mvs::tests::measure_full_size -- --ignored --nocapture`.
#[test]
#[ignore = "measurement (several seconds); prints the table for docs/"]
fn measure_full_size() {
    let planes = PlaneSet::new(1.5, 15.0, 256).unwrap();
    let mut rows: Vec<(&'static str, u64, DepthMetrics)> = Vec::new();
    // `MURK_FIRST_SEED` shifts the five seeds (e.g. 5 for the held-out seeds 5–9).
    let first: u64 = std::env::var("MURK_FIRST_SEED")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    for seed in first..first + 5 {
        let cfg = MvsSimConfig {
            seed,
            ..MvsSimConfig::default()
        };
        let scene = simulate_mvs(&cfg, &Monitor::noop()).unwrap();
        for (name, kind) in kinds(&scene, &FULL_SIZE_SET) {
            let (m, t) = evaluate(&scene, &planes, kind, 4);
            eprintln!(
                "seed {seed} t_med {:.2} {name}: C.P. {:.1}% depth {t:.3} s",
                scene.median_transmission,
                100.0 * m.c_p
            );
            rows.push((name, seed, m));
        }
    }
    print_table(&rows, 5);
    // Timing with one source (the issue's ≤ 0.5 s target for cost volume + aggregation).
    let scene = simulate_mvs(&MvsSimConfig::default(), &Monitor::noop()).unwrap();
    for (name, kind) in kinds(&scene, &FULL_SIZE_SET)
        .into_iter()
        .filter(|(n, _)| ["ordinary", "eq37", "obs+off"].contains(n))
    {
        let best = (0..3)
            .map(|_| evaluate(&scene, &planes, kind, 1).1)
            .fold(f64::INFINITY, f64::min);
        println!("1 source, {name}: depth (smoothing, cost volume, aggregation) {best:.3} s");
    }
}

/// Pre-smoothing sweep at full size (256×192×256, 4 sources, seeds 0–4): mean C.P. of the
/// default dehazing and the ordinary volume in haze, and of the ordinary volume on the clear
/// images, for each σ in `MURK_SIGMAS` (default `0,0.5,0.8,1,1.5`). Run with
/// `cargo test --release --lib mvs::tests::experiment_presmooth -- --ignored --nocapture`.
#[test]
#[ignore = "experiment (about a minute)"]
fn experiment_presmooth() {
    let planes = PlaneSet::new(1.5, 15.0, 256).unwrap();
    let sigmas: Vec<f32> = std::env::var("MURK_SIGMAS")
        .unwrap_or_else(|_| "0,0.5,0.8,1,1.5".into())
        .split(',')
        .map(|v| v.parse().unwrap())
        .collect();
    let scenes: Vec<MvsScene> = (0..5u64)
        .map(|seed| {
            simulate_mvs(
                &MvsSimConfig {
                    seed,
                    ..MvsSimConfig::default()
                },
                &Monitor::noop(),
            )
            .unwrap()
        })
        .collect();
    println!("| σ px | dehazing (haze) | ordinary (haze) | ordinary (clear) |");
    println!("|---|---|---|---|");
    for &sigma in &sigmas {
        let sgm = SgmParams {
            presmooth_sigma_px: sigma,
            ..SgmParams::default()
        };
        let mut cp = [0.0f64; 3];
        for scene in &scenes {
            let atm = AtmosphereParams {
                airlight: scene.airlight,
                beta: scene.beta,
            };
            let mut clear = scene.clone();
            for v in &mut clear.views {
                v.hazy = v.clear.clone();
            }
            let runs = [
                (
                    scene,
                    CostKind::DehazingWith(atm, DehazingOptions::default()),
                ),
                (scene, CostKind::Ordinary),
                (&clear, CostKind::Ordinary),
            ];
            for (acc, (s, kind)) in cp.iter_mut().zip(runs) {
                *acc += evaluate_with(s, &planes, kind, 4, &sgm).0.c_p / scenes.len() as f64;
            }
        }
        println!(
            "| {sigma} | {:.1} | {:.1} | {:.1} |",
            100.0 * cp[0],
            100.0 * cp[1],
            100.0 * cp[2]
        );
    }
}

/// Experiment: two depth maps per scene, a fine one (the defaults) and a coarse one
/// (`MURK_COARSE=σ,r`, default `2,4`: heavier pre-smoothing and window), combined per pixel by
/// the reference's local texture SNR (5×5 standard deviation of the pre-smoothed reference over
/// the estimated noise σ; coarse where it is below each threshold of `MURK_SNR`). Prints mean
/// C.P. of fine, coarse, the oracle per-pixel choice, and each threshold. Run with
/// `cargo test --release --lib mvs::tests::experiment_adaptive_scale -- --ignored --nocapture`.
#[test]
#[ignore = "experiment (about a minute)"]
fn experiment_adaptive_scale() {
    use crate::mvs::cost_volume::estimate_noise_sigma;
    use crate::mvs::depth::contrast::local_contrast;
    use crate::mvs::depth::presmooth::gaussian_presmooth;
    let planes = PlaneSet::new(1.5, 15.0, 256).unwrap();
    let coarse: Vec<f32> = std::env::var("MURK_COARSE")
        .unwrap_or_else(|_| "2,4".into())
        .split(',')
        .map(|v| v.parse().unwrap())
        .collect();
    let thresholds: Vec<f32> = std::env::var("MURK_SNR")
        .unwrap_or_else(|_| "1,2,3,5,8".into())
        .split(',')
        .map(|v| v.parse().unwrap())
        .collect();
    let fine_p = SgmParams::default();
    let coarse_p = SgmParams {
        presmooth_sigma_px: coarse[0],
        cost_window_radius: coarse[1] as usize,
        ..SgmParams::default()
    };
    let mut sums = vec![0.0f64; 3 + thresholds.len()];
    for seed in 0..5u64 {
        let scene = simulate_mvs(
            &MvsSimConfig {
                seed,
                ..MvsSimConfig::default()
            },
            &Monitor::noop(),
        )
        .unwrap();
        let views = scene.hazy_views();
        let reference = views[scene.reference];
        let sources = nearest_sources(&views, scene.reference, 4);
        let kind = true_haze(&scene);
        let m = Monitor::noop();
        let zf = estimate_depth(&reference, &sources, &planes, kind, &fine_p, &m)
            .unwrap()
            .z_depth;
        let zc = estimate_depth(&reference, &sources, &planes, kind, &coarse_p, &m)
            .unwrap()
            .z_depth;
        let gt = &scene.views[scene.reference].depth;
        let (w, h) = gt.dims();
        let ok = |z: f32, g: f32| ((z - g) / g).abs() < 0.1;
        let noise = estimate_noise_sigma(reference.image).max(1e-4);
        let sm = gaussian_presmooth(reference.image, fine_p.presmooth_sigma_px);
        let snr: Vec<f32> = local_contrast(sm.data(), w, h, sm.channels(), 2)
            .into_iter()
            .map(|c| c / noise)
            .collect();
        let n = (w * h) as f64;
        let (f, co, g) = (zf.data(), zc.data(), gt.data());
        if let Ok(dir) = std::env::var("MURK_DUMP") {
            // Reference image | error map of the fine depth (green within 10 %, red too near,
            // blue too far).
            let mut rgb = vec![0u8; 2 * w * h * 3];
            for p in 0..w * h {
                let (x, y) = (p % w, p / w);
                for ch in 0..3 {
                    rgb[(y * 2 * w + x) * 3 + ch] =
                        (reference.image.data()[p * 3 + ch].clamp(0.0, 1.0) * 255.0) as u8;
                }
                let rel = (f[p] - g[p]) / g[p];
                let px: [u8; 3] = if rel.abs() < 0.1 {
                    [0, 160, 0]
                } else if rel < 0.0 {
                    [220, 0, 0]
                } else {
                    [0, 0, 220]
                };
                rgb[(y * 2 * w + w + x) * 3..][..3].copy_from_slice(&px);
            }
            crate::io::write_png_rgb8(
                &std::path::Path::new(&dir).join(format!("seed{seed}.png")),
                2 * w,
                h,
                &rgb,
            )
            .unwrap();
        }
        let mut row = vec![
            (0..w * h).filter(|&p| ok(f[p], g[p])).count() as f64 / n,
            (0..w * h).filter(|&p| ok(co[p], g[p])).count() as f64 / n,
            (0..w * h)
                .filter(|&p| ok(f[p], g[p]) || ok(co[p], g[p]))
                .count() as f64
                / n,
        ];
        for &t in &thresholds {
            row.push(
                (0..w * h)
                    .filter(|&p| ok(if snr[p] < t { co[p] } else { f[p] }, g[p]))
                    .count() as f64
                    / n,
            );
        }
        let below: Vec<String> = thresholds
            .iter()
            .map(|&t| {
                format!(
                    "{:.0}%",
                    100.0 * snr.iter().filter(|&&s| s < t).count() as f64 / n
                )
            })
            .collect();
        eprintln!(
            "seed {seed}: noise σ {noise:.4}; share below thresholds {below:?}; C.P. {:?}",
            row.iter()
                .map(|v| (1000.0 * v).round() / 10.0)
                .collect::<Vec<_>>()
        );
        for (s, v) in sums.iter_mut().zip(&row) {
            *s += v / 5.0;
        }
    }
    println!(
        "fine {:.1}%  coarse {:.1}%  oracle {:.1}%",
        100.0 * sums[0],
        100.0 * sums[1],
        100.0 * sums[2]
    );
    for (t, s) in thresholds.iter().zip(&sums[3..]) {
        println!("SNR < {t} → coarse: {:.1}%", 100.0 * s);
    }
}

/// Experiment: per-pixel cost weights from the reference's local contrast before aggregation,
/// `w_p = clamp(c₀ / c_p, 1, w_max)` with `c_p` the 5×5 standard deviation of the pre-smoothed
/// reference (mean over channels) and `c₀` its `MURK_PCT` percentile (default 50) — so
/// low-contrast regions, whose per-pixel evidence is far below P1/P2, weigh as much as typical
/// ones. `MURK_WMAX` lists `w_max` values (default `1,2,4,8`; 1 = off). Run with
/// `cargo test --release --lib mvs::tests::experiment_contrast_weight -- --ignored --nocapture`.
#[test]
#[ignore = "experiment (about a minute)"]
fn experiment_contrast_weight() {
    use crate::mvs::depth::contrast::{apply_weights, contrast_weights, local_contrast};
    use crate::mvs::depth::presmooth::gaussian_presmooth;
    use crate::mvs::{build_cost_volume, depth_from_costs};
    let planes = PlaneSet::new(1.5, 15.0, 256).unwrap();
    let wmaxes: Vec<f32> = std::env::var("MURK_WMAX")
        .unwrap_or_else(|_| "1,2,4,8".into())
        .split(',')
        .map(|v| v.parse().unwrap())
        .collect();
    let pct: f32 = std::env::var("MURK_PCT")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(50.0);
    let clear = std::env::var("MURK_CLEAR").is_ok();
    // The weights are applied here, so the library's own normalisation is off.
    let sgm = SgmParams {
        contrast_max_weight: 1.0,
        ..SgmParams::default()
    };
    let mut sums = vec![0.0f64; wmaxes.len()];
    let first: u64 = std::env::var("MURK_FIRST_SEED")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    for seed in first..first + 5 {
        let mut scene = simulate_mvs(
            &MvsSimConfig {
                seed,
                ..MvsSimConfig::default()
            },
            &Monitor::noop(),
        )
        .unwrap();
        if clear {
            for v in &mut scene.views {
                v.hazy = v.clear.clone();
            }
        }
        let smoothed: Vec<ImageF32> = scene
            .views
            .iter()
            .map(|v| gaussian_presmooth(&v.hazy, sgm.presmooth_sigma_px))
            .collect();
        let views: Vec<View<'_>> = scene
            .views
            .iter()
            .zip(&smoothed)
            .map(|(v, img)| View {
                image: img,
                intrinsics: v.intrinsics,
                pose: v.pose,
            })
            .collect();
        let reference = views[scene.reference];
        let sources = nearest_sources(&views, scene.reference, 4);
        let kind = if clear {
            CostKind::Ordinary
        } else {
            true_haze(&scene)
        };
        let volume =
            build_cost_volume(&reference, &sources, &planes, kind, &Monitor::noop()).unwrap();
        let (w, h) = (volume.width(), volume.height());
        let sm = reference.image;
        let contrast = local_contrast(sm.data(), w, h, sm.channels(), 2);
        let gt = &scene.views[scene.reference].depth;
        let mut row = Vec::new();
        for &wmax in &wmaxes {
            let mut data = volume.data().to_vec();
            apply_weights(&mut data, &contrast_weights(&contrast, pct, wmax));
            let d = depth_from_costs(data, w, h, &planes, sm, &sgm, &Monitor::noop()).unwrap();
            row.push(depth_metrics(&d.z_depth, gt, None).unwrap().c_p);
        }
        eprintln!(
            "seed {seed}: C.P. {:?}",
            row.iter()
                .map(|v| (1000.0 * v).round() / 10.0)
                .collect::<Vec<_>>()
        );
        for (s, v) in sums.iter_mut().zip(&row) {
            *s += v / 5.0;
        }
    }
    for (wm, s) in wmaxes.iter().zip(&sums) {
        println!("w_max {wm}: C.P. {:.1}%", 100.0 * s);
    }
}

/// The depth of `scene`'s reference from its nearest source with `sgm`, over `planes`.
fn depth_of(scene: &MvsScene, planes: &PlaneSet, sgm: &SgmParams) -> crate::mvs::DepthResult {
    let views: Vec<View<'_>> = scene.hazy_views();
    let sources = nearest_sources(&views, scene.reference, 1);
    let kind = true_haze(scene);
    estimate_depth(
        &views[scene.reference],
        &sources,
        planes,
        kind,
        sgm,
        &Monitor::noop(),
    )
    .unwrap()
}

/// The dehazing volume with `scene`'s true A and β and the default options.
pub(crate) fn true_haze(scene: &MvsScene) -> CostKind {
    CostKind::DehazingWith(
        AtmosphereParams {
            airlight: scene.airlight,
            beta: scene.beta,
        },
        DehazingOptions::default(),
    )
}

/// The three depths a compensation test compares: the clean scene's and the `changed` scene's
/// with the defaults, and the `changed` scene's with `off` (the compensation under test
/// disabled); with each one's C.P. against the clean ground truth.
fn clean_compensated_off(
    clean: &MvsScene,
    changed: &MvsScene,
    planes: &PlaneSet,
    off: SgmParams,
) -> [(crate::mvs::DepthResult, f64); 3] {
    let gt = &clean.views[clean.reference].depth;
    [
        (clean, SgmParams::default()),
        (changed, SgmParams::default()),
        (changed, off),
    ]
    .map(|(scene, sgm)| {
        let d = depth_of(scene, planes, &sgm);
        let c_p = depth_metrics(&d.z_depth, gt, None).unwrap().c_p;
        (d, c_p)
    })
}

/// The simulator's 160×120 rectified pair (seed 3) and 64 planes over z 1.5…15.
fn small_rectified_pair() -> (MvsScene, PlaneSet) {
    let cfg = MvsSimConfig {
        seed: 3,
        num_views: 2,
        rectified_pair: true,
        ..MvsSimConfig::with_size(160, 120)
    };
    (
        simulate_mvs(&cfg, &Monitor::noop()).unwrap(),
        PlaneSet::new(1.5, 15.0, 64).unwrap(),
    )
}

/// On a rectified pair (the configuration of real stereo rigs) the source–reference check
/// rejects the pixels the source cannot see or got wrong: their confidence becomes 0, and the
/// filled depth there is better than the winner-take-all's; accuracy over the image does not
/// drop. Without the check nothing has confidence 0 that the curve did not already call flat.
#[test]
fn consistency_check_on_a_rectified_pair() {
    let (scene, planes) = small_rectified_pair();
    let off = depth_of(
        &scene,
        &planes,
        &SgmParams {
            consistency_check: false,
            speckle_max_size_px: Some(0),
            ..SgmParams::default()
        },
    );
    let on = depth_of(&scene, &planes, &SgmParams::default());
    let gt = &scene.views[scene.reference].depth;
    let rejected: Vec<usize> = (0..gt.data().len())
        .filter(|&p| on.confidence.data()[p] == 0.0 && off.confidence.data()[p] > 0.0)
        .collect();
    let frac = rejected.len() as f64 / gt.data().len() as f64;
    let inv_err = |d: &crate::mvs::DepthResult| {
        rejected
            .iter()
            .map(|&p| f64::from((d.inverse_depth.data()[p] - 1.0 / gt.data()[p]).abs()))
            .sum::<f64>()
            / rejected.len().max(1) as f64
    };
    let (m_off, m_on) = (
        depth_metrics(&off.z_depth, gt, None).unwrap(),
        depth_metrics(&on.z_depth, gt, None).unwrap(),
    );
    println!(
        "rejected {:.1} %; inverse-depth error there {:.4} -> {:.4}; C.P. {:.1} -> {:.1} %",
        100.0 * frac,
        inv_err(&off),
        inv_err(&on),
        100.0 * m_off.c_p,
        100.0 * m_on.c_p
    );
    assert!((0.005..0.3).contains(&frac), "rejected fraction {frac}");
    assert!(inv_err(&on) < inv_err(&off));
    assert!(m_on.c_p >= m_off.c_p - 0.002, "{m_on:?} vs {m_off:?}");
    assert_eq!(m_on.missing_predictions, 0);
}

/// A source camera 6 % brighter than the reference (exposure or gain, as between the two cameras
/// of a real rig): the estimated gain compensates it and the depth is as accurate as with equal
/// exposures; without the compensation the dehazing residual carries the offset everywhere and
/// C.P. collapses.
#[test]
fn a_brighter_source_camera_is_compensated() {
    let (equal, planes) = small_rectified_pair();
    let mut brighter = equal.clone();
    let source = 1 - brighter.reference;
    for v in brighter.views[source].hazy.data_mut() {
        *v *= 1.06;
    }
    let [(base, cp_base), (on, cp_on), (off, cp_off)] = clean_compensated_off(
        &equal,
        &brighter,
        &planes,
        SgmParams {
            exposure_compensation: false,
            ..SgmParams::default()
        },
    );
    println!(
        "gains: equal {:?}, brighter {:?}; C.P. equal {:.1} %, brighter compensated {:.1} %, not compensated {:.1} %",
        base.source_gains,
        on.source_gains,
        100.0 * cp_base,
        100.0 * cp_on,
        100.0 * cp_off
    );
    // One gain per channel of the one source.
    assert_eq!(base.source_gains, vec![1.0; 3], "within the dead band");
    for g in &on.source_gains {
        assert!((g - 1.06).abs() < 0.005, "{:?}", on.source_gains);
    }
    assert_eq!(off.source_gains, vec![1.0; 3]);
    assert!(cp_on >= cp_base - 0.01);
    assert!(cp_off < cp_base - 0.1);
}

/// Depth in strips (a memory budget far below the volume: 8 strips of 15 rows) agrees with the
/// whole-volume depth except where SGM's vertical and diagonal paths carry evidence further
/// than a strip's overlap, and the accuracy is the same.
#[test]
fn strips_match_the_whole_volume() {
    let planes = PlaneSet::new(1.5, 15.0, 64).unwrap();
    let scene = simulate_mvs(&MvsSimConfig::with_size(160, 120), &Monitor::noop()).unwrap();
    // 160 px × 64 planes × 4 bytes = 40 KiB a row: 1 MiB holds 25 rows, so strips of 16 own
    // rows with 24 rows of overlap each side (8 strips).
    // Strips are where the paths run both ways (8 paths): the default one pass keeps no volume.
    let eight = SgmParams {
        num_paths: 8,
        ..SgmParams::default()
    };
    let whole = depth_of(&scene, &planes, &eight);
    let strips = depth_of(
        &scene,
        &planes,
        &SgmParams {
            volume_budget_mib: 1,
            ..eight
        },
    );
    let n = whole.inverse_depth.data().len();
    // "The same" within one plane step: the strips' paths start 24 rows before their own rows
    // instead of at the image border, which moves the sub-plane refinement slightly.
    let tol = planes.inverse_depth_step() as f32;
    let same = whole
        .inverse_depth
        .data()
        .iter()
        .zip(strips.inverse_depth.data())
        .filter(|(a, b)| (*a - *b).abs() <= tol)
        .count();
    let gt = &scene.views[scene.reference].depth;
    let (a, b) = (
        depth_metrics(&whole.z_depth, gt, None).unwrap(),
        depth_metrics(&strips.z_depth, gt, None).unwrap(),
    );
    println!(
        "within one plane step {same}/{n}; C.P. {:.2} vs {:.2} %",
        100.0 * a.c_p,
        100.0 * b.c_p
    );
    assert!(same as f64 >= 0.9 * n as f64, "{same}/{n}");
    assert!((a.c_p - b.c_p).abs() < 0.005, "{a:?} vs {b:?}");
}

/// The small rectified pair with both cameras vignetted alike: gain `1 + a·r²`, `r` = 1 at the
/// corners, airlight included, as a lens does.
fn vignetted_pair(a: f32) -> (MvsScene, MvsScene, PlaneSet) {
    let (clean, planes) = small_rectified_pair();
    let mut vignetted = clean.clone();
    for view in &mut vignetted.views {
        view.hazy = crate::mvs::depth::vignetting::vignette(&view.hazy, a);
    }
    (clean, vignetted, planes)
}

/// Vignetting of 0.3 on both views of the small rectified pair, with the fall-off compensation
/// off: a reference pixel and its match sit at different radii, so the photometric residual
/// carries an offset that grows toward the image's sides, while the census codes barely
/// change. The census term recovers most of what the vignetting costs; without it C.P. falls.
#[test]
fn census_term_survives_vignetting() {
    let (clean, vignetted, planes) = vignetted_pair(-0.3);
    let gt = &clean.views[clean.reference].depth;
    let c_p = |d: &crate::mvs::DepthResult| depth_metrics(&d.z_depth, gt, None).unwrap().c_p;
    let plain_params = SgmParams {
        vignetting_compensation: false,
        ..SgmParams::default()
    };
    let census = SgmParams {
        census_weight: 3.0,
        ..plain_params
    };
    let base = c_p(&depth_of(&clean, &planes, &plain_params));
    let plain = c_p(&depth_of(&vignetted, &planes, &plain_params));
    let with_census = c_p(&depth_of(&vignetted, &planes, &census));
    let clean_census = c_p(&depth_of(&clean, &planes, &census));
    println!(
        "C.P. clean {:.1} % (census {:.1} %), vignetted {:.1} %, vignetted with census {:.1} %",
        100.0 * base,
        100.0 * clean_census,
        100.0 * plain,
        100.0 * with_census
    );
    assert!(plain < base - 0.05, "vignetting should hurt the L1 cost");
    assert!(with_census > plain + 0.05);
}

/// The same lens fall-off on both views is estimated and divided out: the vignetted pair's
/// depth is as good as the clean pair's, the fall-off found is the one applied, and the clean
/// pair's estimate falls in the dead band (nothing applied, depth unchanged).
#[test]
fn a_shared_lens_falloff_is_compensated() {
    let (clean, vignetted, planes) = vignetted_pair(-0.3);
    let [(clean_depth, cp_clean), (on, cp_on), (off, cp_off)] = clean_compensated_off(
        &clean,
        &vignetted,
        &planes,
        SgmParams {
            vignetting_compensation: false,
            ..SgmParams::default()
        },
    );
    println!(
        "fall-off found {:.4} (clean {:.4}); C.P. clean {:.1} %, compensated {:.1} %, not {:.1} %; gains {:?}",
        on.vignetting_falloff,
        clean_depth.vignetting_falloff,
        100.0 * cp_clean,
        100.0 * cp_on,
        100.0 * cp_off,
        on.source_gains
    );
    assert!(
        (on.vignetting_falloff + 0.3).abs() < 0.03,
        "{}",
        on.vignetting_falloff
    );
    assert_eq!(clean_depth.vignetting_falloff, 0.0);
    assert_eq!(off.vignetting_falloff, 0.0);
    assert!(cp_on >= cp_clean - 0.01);
    assert!(cp_off < cp_clean - 0.1);
}

/// Only the source's lens vignettes (−0.3, on top of a 4 % gain): its fall-off relative to the
/// reference's is estimated with its gains and divided out of it, so the depth is as good as the
/// clean pair's. The shared fall-off cannot represent this (it would be found wrong or not at
/// all), and with exposure compensation off nothing relative is estimated.
#[test]
fn a_source_lens_that_differs_is_compensated() {
    let (clean, planes) = small_rectified_pair();
    let mut vignetted = clean.clone();
    let source = 1 - clean.reference;
    let recorded = crate::mvs::depth::vignetting::vignette(&clean.views[source].hazy, -0.3);
    vignetted.views[source].hazy =
        crate::mvs::depth::exposure::compensate(&recorded, &[1.0 / 1.04; 3]);
    let [(clean_depth, cp_clean), (on, cp_on), (shared_only, cp_shared)] = clean_compensated_off(
        &clean,
        &vignetted,
        &planes,
        SgmParams {
            exposure_compensation: false,
            ..SgmParams::default()
        },
    );
    println!(
        "relative fall-off found {:?} (clean {:?}), gains {:?}, shared {:.4}; C.P. clean {:.1} %, \
         compensated {:.1} %, without the relative fall-off and gains {:.1} %",
        on.source_falloffs,
        clean_depth.source_falloffs,
        on.source_gains,
        on.vignetting_falloff,
        100.0 * cp_clean,
        100.0 * cp_on,
        100.0 * cp_shared,
    );
    assert_eq!(on.source_falloffs.len(), 1);
    assert!((on.source_falloffs[0] + 0.3).abs() < 0.03, "{on:?}");
    for g in &on.source_gains {
        assert!((g - 1.04).abs() < 0.01, "{:?}", on.source_gains);
    }
    assert_eq!(clean_depth.source_falloffs, vec![0.0]);
    assert_eq!(shared_only.source_falloffs, vec![0.0]);
    assert!(cp_on >= cp_clean - 0.01);
    assert!(cp_shared < cp_clean - 0.1);
}

/// A source 2.5 times brighter than the reference is beyond the gain search's range: the gain
/// stops at the bound, is applied, and the result says so instead of passing it off as the
/// camera's gain. Equal cameras get no warning.
#[test]
fn a_gain_at_the_search_bound_is_reported() {
    let (equal, planes) = small_rectified_pair();
    let mut brighter = equal.clone();
    let source = 1 - brighter.reference;
    for v in brighter.views[source].hazy.data_mut() {
        *v *= 2.5;
    }
    let d = depth_of(&brighter, &planes, &SgmParams::default());
    println!("gains {:?}, warnings {:?}", d.source_gains, d.warnings);
    assert_eq!(d.warnings.len(), 3, "{:?}", d.warnings);
    assert!(d
        .warnings
        .iter()
        .all(|w| w.contains("end of the searched range")));
    for g in &d.source_gains {
        assert!((g - 2.0).abs() < 2e-3, "{:?}", d.source_gains);
    }
    assert!(depth_of(&equal, &planes, &SgmParams::default())
        .warnings
        .is_empty());
}

/// The shared fall-off on lateral and forward motion (256×192, 256 planes, 4 sources, seeds
/// 0–4), each scene without vignetting and with every view vignetted by −0.15: the fall-off
/// found and C.P. with the compensation on and off; the dehazing volume with the true A and β,
/// or with `MURK_ORDINARY` set the ordinary volume. Run with
/// `cargo test --release --lib mvs::tests::measure_falloff_by_motion -- --ignored --nocapture`.
#[test]
#[ignore = "measurement (about two minutes)"]
fn measure_falloff_by_motion() {
    let planes = PlaneSet::new(1.5, 15.0, 256).unwrap();
    let ordinary = std::env::var_os("MURK_ORDINARY").is_some();
    println!("| seed | motion | vignetting | fall-off found | C.P. on (%) | C.P. off (%) |");
    println!("|---|---|---|---|---|---|");
    for seed in 0..5u64 {
        for (motion, forward) in [("lateral", 0.0), ("forward 0.5", 0.5)] {
            for vignetting in [0.0f32, -0.15] {
                let cfg = MvsSimConfig {
                    seed,
                    forward_motion: forward,
                    ..MvsSimConfig::default()
                };
                let mut scene = simulate_mvs(&cfg, &Monitor::noop()).unwrap();
                for view in &mut scene.views {
                    view.hazy = crate::mvs::depth::vignetting::vignette(&view.hazy, vignetting);
                }
                let kind = if ordinary {
                    CostKind::Ordinary
                } else {
                    true_haze(&scene)
                };
                let run = |on: bool| {
                    let sgm = SgmParams {
                        vignetting_compensation: on,
                        ..SgmParams::default()
                    };
                    let views: Vec<View<'_>> = scene.hazy_views();
                    let sources = nearest_sources(&views, scene.reference, 4);
                    let depth = estimate_depth(
                        &views[scene.reference],
                        &sources,
                        &planes,
                        kind,
                        &sgm,
                        &Monitor::noop(),
                    )
                    .unwrap();
                    let gt = &scene.views[scene.reference].depth;
                    let c_p = depth_metrics(&depth.z_depth, gt, None).unwrap().c_p;
                    (depth.vignetting_falloff, c_p)
                };
                let ((found, on), (_, off)) = (run(true), run(false));
                println!(
                    "| {seed} | {motion} | {vignetting} | {found:.3} | {:.1} | {:.1} |",
                    100.0 * on,
                    100.0 * off
                );
            }
        }
    }
}
