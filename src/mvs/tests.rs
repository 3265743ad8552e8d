//! End-to-end comparison for issue 3: on simulated hazy scenes with ground-truth `A` and `β`,
//! the dehazing cost volume (Eq. 3.7) + SGM against the ordinary one (Eq. 3.1) + SGM.
//!
//! Status (measured, see the printed tables): with the simulator's default sensor noise
//! (σ = 0.01) the dehazing volume + SGM does **not** beat the ordinary volume + SGM — the
//! `1/t` noise amplification of Eq. 3.5 pushes correct-depth voxels of dark or bright pixels
//! out of `[0, 1]` (penalty γ) and biases far pixels towards nearer planes. Without sensor
//! noise it wins on C.P. but not on L1-rel. So the ordering is *measured and printed*, not
//! asserted; the "dehazing beats ordinary" test stays open.

use std::time::Instant;

use crate::atmosphere::AtmosphereParams;
use crate::image::ImageF32;
use crate::metrics::{depth_metrics, DepthMetrics};
use crate::monitor::Monitor;
use crate::mvs::{build_cost_volume, depth_from_cost_volume, CostKind, PlaneSet, SgmParams, View};
use crate::simulate::mvs::{simulate_mvs, MvsScene, MvsSimConfig};

/// Depth of the reference view of `scene` with `kind`, and the metrics against GT; also the
/// wall time of cost volume and of aggregation (+ selection), seconds.
fn evaluate(
    scene: &MvsScene,
    planes: &PlaneSet,
    kind: CostKind,
    num_sources: usize,
) -> (DepthMetrics, f64, f64) {
    let views: Vec<View<'_>> = scene
        .views
        .iter()
        .map(|v| View {
            image: &v.hazy,
            intrinsics: v.intrinsics,
            pose: v.pose,
        })
        .collect();
    let reference = views[scene.reference];
    // Sources nearest to the reference first (by trajectory position).
    let mut others: Vec<usize> = (0..views.len()).filter(|&i| i != scene.reference).collect();
    others.sort_by_key(|&i| i.abs_diff(scene.reference));
    let sources: Vec<View<'_>> = others.iter().take(num_sources).map(|&i| views[i]).collect();
    let m = Monitor::noop();
    let t0 = Instant::now();
    let volume = build_cost_volume(&reference, &sources, planes, kind, &m).unwrap();
    let t1 = Instant::now();
    let depth = depth_from_cost_volume(volume, reference.image, &SgmParams::default(), &m).unwrap();
    let t2 = Instant::now();
    let gt: &ImageF32 = &scene.views[scene.reference].depth;
    let metrics = depth_metrics(&depth.z_depth, gt, None).unwrap();
    (metrics, (t1 - t0).as_secs_f64(), (t2 - t1).as_secs_f64())
}

fn kinds(scene: &MvsScene) -> [(&'static str, CostKind); 2] {
    [
        ("ordinary", CostKind::Ordinary),
        (
            "dehazing",
            CostKind::Dehazing(AtmosphereParams {
                airlight: scene.airlight,
                beta: scene.beta,
            }),
        ),
    ]
}

/// Reduced-size comparison (128×96, 96 planes, 4 sources, 3 seeds). Sensor noise from
/// `MURK_NOISE` (default: the simulator's 0.01). Asserts only that both pipelines produce
/// valid depth everywhere; prints the metrics.
#[test]
fn dehazing_vs_ordinary_at_reduced_size() {
    let planes = PlaneSet::new(1.5, 15.0, 96).unwrap();
    let mut sums = [[0.0f64; 2]; 2]; // [kind][l1_rel, c_p]
    let seeds = 0..3u64;
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
        for (k, (name, kind)) in kinds(&scene).into_iter().enumerate() {
            let (m, _, _) = evaluate(&scene, &planes, kind, 4);
            assert_eq!(m.missing_predictions, 0, "{name}");
            eprintln!(
                "seed {seed} {name}: L1-rel {:.3} L1-inv {:.4} sc-inv {:.3} C.P. {:.1}% (t_med {:.2})",
                m.l1_rel,
                m.l1_inv,
                m.sc_inv,
                100.0 * m.c_p,
                scene.median_transmission
            );
            sums[k][0] += m.l1_rel;
            sums[k][1] += m.c_p;
        }
    }
    let [ord, dcv] = sums;
    eprintln!(
        "mean over 3 seeds: ordinary L1-rel {:.3} C.P. {:.1}%, dehazing L1-rel {:.3} C.P. {:.1}%",
        ord[0] / 3.0,
        100.0 * ord[1] / 3.0,
        dcv[0] / 3.0,
        100.0 * dcv[1] / 3.0
    );
    assert!(sums.iter().flatten().all(|v| v.is_finite()));
}

/// Full-size measurement for the issue (256×192, 256 planes, 4 sources, 5 seeds): prints a
/// metric table and timings. Run with
/// `cargo test --release --lib mvs::tests::measure_full_size -- --ignored --nocapture`.
#[test]
#[ignore = "measurement (several seconds); prints the table for docs/"]
fn measure_full_size() {
    let planes = PlaneSet::new(1.5, 15.0, 256).unwrap();
    println!("| seed | t_med | cost volume | L1-rel | L1-inv | sc-inv | C.P. (%) | CV s | SGM s |");
    println!("|---|---|---|---|---|---|---|---|---|");
    let mut mean = [[0.0f64; 4]; 2];
    for seed in 0..5u64 {
        let cfg = MvsSimConfig {
            seed,
            ..MvsSimConfig::default()
        };
        let scene = simulate_mvs(&cfg, &Monitor::noop()).unwrap();
        for (k, (name, kind)) in kinds(&scene).into_iter().enumerate() {
            let (m, tc, ta) = evaluate(&scene, &planes, kind, 4);
            println!(
                "| {seed} | {:.2} | {name} | {:.3} | {:.4} | {:.3} | {:.1} | {tc:.3} | {ta:.3} |",
                scene.median_transmission,
                m.l1_rel,
                m.l1_inv,
                m.sc_inv,
                100.0 * m.c_p
            );
            for (acc, v) in mean[k]
                .iter_mut()
                .zip([m.l1_rel, m.l1_inv, m.sc_inv, m.c_p])
            {
                *acc += v / 5.0;
            }
        }
    }
    for (k, name) in ["ordinary", "dehazing"].iter().enumerate() {
        let m = mean[k];
        println!(
            "| mean | | {name} | {:.3} | {:.4} | {:.3} | {:.1} | | |",
            m[0],
            m[1],
            m[2],
            100.0 * m[3]
        );
    }
    // Timing with one source (the issue's ≤ 0.5 s target for cost volume + aggregation).
    let scene = simulate_mvs(&MvsSimConfig::default(), &Monitor::noop()).unwrap();
    for (name, kind) in kinds(&scene) {
        let mut best = (f64::INFINITY, f64::INFINITY);
        for _ in 0..3 {
            let (_, tc, ta) = evaluate(&scene, &planes, kind, 1);
            if tc + ta < best.0 + best.1 {
                best = (tc, ta);
            }
        }
        println!(
            "1 source, {name}: cost volume {:.3} s + aggregation/selection {:.3} s = {:.3} s",
            best.0,
            best.1,
            best.0 + best.1
        );
    }
}
