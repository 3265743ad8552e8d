//! End to end on simulated hazy scenes with ground-truth `A` and `β`: the dehazing cost volume
//! against the ordinary one (Eq. 3.1), and what the depth pipeline does on a rectified pair
//! (consistency check, exposure gains, lens fall-off, census term, strips, bounds).
//!
//! These check behaviour at reduced size; the accuracy tables at the reference's size come from
//! `cargo run --release -p murk --example mvs_survey` (docs/accuracy.md).

use crate::atmosphere::AtmosphereParams;
use crate::metrics::{depth_metrics, DepthMetrics};
use crate::monitor::Monitor;
use crate::mvs::{
    estimate_depth, CostKind, DehazingOptions, DepthParams, MatchingParams, PhotometricParams,
    PlaneSet, RejectionParams, SgmParams, View,
};
use crate::simulate::mvs::{simulate_mvs, MvsScene, MvsSimConfig};

/// Metrics of the depth of `scene`'s reference view with `kind` and the default
/// [`DepthParams`], from its `num_sources` nearest sources.
fn evaluate(
    scene: &MvsScene,
    planes: &PlaneSet,
    kind: CostKind,
    num_sources: usize,
) -> DepthMetrics {
    let views: Vec<View<'_>> = scene.hazy_views();
    let sources = nearest_sources(&views, scene.reference, num_sources);
    let depth = estimate_depth(
        &views[scene.reference],
        &sources,
        planes,
        kind,
        &DepthParams::default(),
        &Monitor::noop(),
    )
    .unwrap();
    depth_metrics(&depth.z_depth, &scene.views[scene.reference].depth, None).unwrap()
}

/// The `n` views nearest to `reference` along the trajectory (by index), nearest first.
fn nearest_sources<'a>(views: &[View<'a>], reference: usize, n: usize) -> Vec<View<'a>> {
    let mut others: Vec<usize> = (0..views.len()).filter(|&i| i != reference).collect();
    others.sort_by_key(|&i| i.abs_diff(reference));
    others.iter().take(n).map(|&i| views[i]).collect()
}

/// Reduced size (128×96, 96 planes, 4 sources, seeds 0–4, sensor noise σ = 0.01): the
/// ordinary volume, Eq. 3.7 as published and the default dehazing volume all give a valid depth
/// at every pixel, and the default dehazing volume beats the ordinary one on mean L1-rel and
/// mean C.P. over the seeds.
#[test]
fn dehazing_vs_ordinary_at_reduced_size() {
    let planes = PlaneSet::new(1.5, 15.0, 96).unwrap();
    let seeds = 0..5u64;
    let mut rows: Vec<(&'static str, DepthMetrics)> = Vec::new();
    for seed in seeds.clone() {
        let cfg = MvsSimConfig {
            seed,
            ..MvsSimConfig::with_size(128, 96)
        };
        let scene = simulate_mvs(&cfg, &Monitor::noop()).unwrap();
        let atm = AtmosphereParams {
            airlight: scene.airlight,
            beta: scene.beta,
        };
        for (name, kind) in [
            ("ordinary", CostKind::Ordinary),
            ("eq37", CostKind::Dehazing(atm)),
            (
                "default",
                CostKind::DehazingWith(atm, DehazingOptions::default()),
            ),
        ] {
            let m = evaluate(&scene, &planes, kind, 4);
            assert_eq!(m.missing_predictions, 0, "{name}, seed {seed}");
            assert!(
                m.l1_rel.is_finite() && m.c_p.is_finite(),
                "{name}, seed {seed}"
            );
            rows.push((name, m));
        }
    }
    let mean = |name: &str, f: fn(&DepthMetrics) -> f64| {
        rows.iter()
            .filter(|r| r.0 == name)
            .map(|r| f(&r.1))
            .sum::<f64>()
            / seeds.clone().count() as f64
    };
    let (l1_ord, l1_def) = (
        mean("ordinary", |m| m.l1_rel),
        mean("default", |m| m.l1_rel),
    );
    let (cp_ord, cp_def) = (mean("ordinary", |m| m.c_p), mean("default", |m| m.c_p));
    println!(
        "means: ordinary L1-rel {l1_ord:.3}, C.P. {:.1} %; dehazing {l1_def:.3}, {:.1} %",
        100.0 * cp_ord,
        100.0 * cp_def
    );
    assert!(
        l1_def < l1_ord,
        "mean L1-rel: dehazing {l1_def} >= ordinary {l1_ord}"
    );
    assert!(
        cp_def > cp_ord,
        "mean C.P.: dehazing {cp_def} <= ordinary {cp_ord}"
    );
}

/// The depth of `scene`'s reference from its nearest source with `sgm`, over `planes`.
fn depth_of(scene: &MvsScene, planes: &PlaneSet, sgm: &DepthParams) -> crate::mvs::DepthResult {
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
fn true_haze(scene: &MvsScene) -> CostKind {
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
    off: DepthParams,
) -> [(crate::mvs::DepthResult, f64); 3] {
    let gt = &clean.views[clean.reference].depth;
    [
        (clean, DepthParams::default()),
        (changed, DepthParams::default()),
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
        &DepthParams {
            rejection: RejectionParams {
                consistency_check: false,
                speckle_max_size_px: Some(0),
                ..RejectionParams::default()
            },
            ..DepthParams::default()
        },
    );
    let on = depth_of(&scene, &planes, &DepthParams::default());
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
        DepthParams {
            photometric: PhotometricParams {
                exposure_compensation: false,
                ..PhotometricParams::default()
            },
            ..DepthParams::default()
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
    let eight = DepthParams {
        sgm: SgmParams {
            num_paths: 8,
            ..SgmParams::default()
        },
        ..DepthParams::default()
    };
    let whole = depth_of(&scene, &planes, &eight);
    let strips = depth_of(
        &scene,
        &planes,
        &DepthParams {
            sgm: SgmParams {
                volume_budget_mib: 1,
                ..eight.sgm
            },
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
    let plain_params = DepthParams {
        photometric: PhotometricParams {
            vignetting_compensation: false,
            ..PhotometricParams::default()
        },
        ..DepthParams::default()
    };
    let census = DepthParams {
        matching: MatchingParams {
            census_weight: 3.0,
            ..plain_params.matching
        },
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
        DepthParams {
            photometric: PhotometricParams {
                vignetting_compensation: false,
                ..PhotometricParams::default()
            },
            ..DepthParams::default()
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
        DepthParams {
            photometric: PhotometricParams {
                exposure_compensation: false,
                ..PhotometricParams::default()
            },
            ..DepthParams::default()
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
    let d = depth_of(&brighter, &planes, &DepthParams::default());
    println!("gains {:?}, warnings {:?}", d.source_gains, d.warnings);
    assert_eq!(d.warnings.len(), 3, "{:?}", d.warnings);
    assert!(d
        .warnings
        .iter()
        .all(|w| w.contains("end of the searched range")));
    for g in &d.source_gains {
        assert!((g - 2.0).abs() < 2e-3, "{:?}", d.source_gains);
    }
    assert!(depth_of(&equal, &planes, &DepthParams::default())
        .warnings
        .is_empty());
}
