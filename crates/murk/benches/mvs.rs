//! MVS in haze (docs/benchmarks.md, "MVS depth in haze"):
//!
//! - `mvs_cost_volume_256x192x256`: the cost volumes (Eq. 3.1, Eq. 3.7 as published and the
//!   default observation-space dehazing residual) at the reference's DCV size, 256×192 with 256
//!   planes, from 1 and 4 sources;
//! - `mvs_depth_256x192x256`: the whole depth (pre-smoothing, cost volume, contrast
//!   normalisation, SGM over the default 5 paths in one pass or 8 in two, selection,
//!   consistency check), and the pre-smoothing of one view and the contrast normalisation alone;
//! - `mvs_stereo_pair_640x480x128`: a rectified 640×480 pair, the whole depth with the defaults
//!   and with one option changed each;
//! - `mvs_sgm_u16_640x160x173`: SGM alone on one strip of that pair's size as `u16` levels;
//! - `mvs_stereo_tracker_640x480`: that pair over the default disparity range (1 px to a
//!   quarter of the width) from cold, against a stream's next pair, which searches the band
//!   around the previous pair's disparities (`StereoTracker`).
//!
//! Run: `cargo bench -p murk --bench mvs` (a group: `-- mvs_stereo_pair`).

use criterion::{criterion_group, criterion_main, Criterion};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use murk::atmosphere::AtmosphereParams;
use murk::mvs::{
    build_cost_volume,
    depth::contrast::{apply_weights, contrast_weights, local_contrast},
    depth::presmooth::gaussian_presmooth,
    estimate_depth, estimate_rectified, CostKind, DehazingOptions, DepthParams, MatchingParams,
    PhotometricParams, PlaneSet, RectifiedOptions, RectifiedRig, RejectionParams, Search,
    SgmParams, StereoTracker, View,
};
use murk::simulate::mvs::{simulate_mvs, MvsSimConfig};
use murk::Monitor;

fn bench(c: &mut Criterion) {
    let scene = simulate_mvs(&MvsSimConfig::default(), &Monitor::noop()).expect("simulate");
    let view = |i: usize| View {
        image: &scene.views[i].hazy,
        intrinsics: scene.views[i].intrinsics,
        pose: scene.views[i].pose,
    };
    let reference = view(scene.reference);
    let sources: Vec<View> = (0..scene.views.len())
        .filter(|&i| i != scene.reference)
        .map(view)
        .collect();
    let planes = PlaneSet::new(0.5, 50.0, 256).expect("planes");
    let atm = AtmosphereParams {
        airlight: scene.airlight,
        beta: scene.beta,
    };
    let monitor = Monitor::noop();
    let (w, h) = scene.views[0].hazy.dims();

    let mut g = c.benchmark_group(format!("mvs_cost_volume_{w}x{h}x256"));
    g.sample_size(10);
    for n_src in [1usize, 4] {
        for (name, kind) in [
            ("ordinary", CostKind::Ordinary),
            ("dehazing_eq37", CostKind::Dehazing(atm)),
            (
                "dehazing_default",
                CostKind::DehazingWith(atm, DehazingOptions::default()),
            ),
        ] {
            g.bench_function(format!("{name}/{n_src}src"), |b| {
                b.iter(|| {
                    build_cost_volume(&reference, &sources[..n_src], &planes, kind, &monitor)
                        .expect("cost volume")
                })
            });
        }
    }
    g.finish();

    let mut g = c.benchmark_group(format!("mvs_depth_{w}x{h}x256"));
    g.sample_size(10);
    let sigma = DepthParams::default().matching.presmooth_sigma_px;
    g.bench_function("presmooth_one_view", |b| {
        b.iter(|| gaussian_presmooth(reference.image, sigma))
    });
    // Weights from the reference, applied to a 256-plane volume in place (the values only grow,
    // by at most w_max per iteration; inf costs the same as a finite value).
    let defaults = DepthParams::default();
    let mut volume = vec![1.0f32; w * h * 256];
    g.bench_function("contrast_normalisation_256_planes", |b| {
        b.iter(|| {
            let c = local_contrast(reference.image.data(), w, h, reference.image.channels(), 2);
            let weights = contrast_weights(
                &c,
                defaults.matching.contrast_percentile,
                defaults.matching.contrast_max_weight,
            );
            apply_weights(&mut volume, &weights);
        })
    });
    let kind = CostKind::DehazingWith(atm, DehazingOptions::default());
    let eight = DepthParams {
        sgm: SgmParams {
            num_paths: 8,
            ..SgmParams::default()
        },
        ..DepthParams::default()
    };
    for n_src in [1usize, 4] {
        for (name, sgm) in [("default", DepthParams::default()), ("eight_paths", eight)] {
            g.bench_function(format!("dehazing_{name}_sgm/{n_src}src"), |b| {
                b.iter(|| {
                    estimate_depth(&reference, &sources[..n_src], &planes, kind, &sgm, &monitor)
                        .expect("depth")
                })
            });
        }
    }
    g.finish();
}

/// A rectified 640×480 pair (the size of the hazy Aloe pair in docs/accuracy.md) over 128
/// planes: the whole depth with the defaults (consistency check, speckle rejection, 5 paths in
/// one pass), without the check, with 8 paths (strips under the default budget, or one
/// volume), with the census term, and without the exposure and fall-off estimates.
fn bench_stereo_pair(c: &mut Criterion) {
    let cfg = MvsSimConfig {
        num_views: 2,
        rectified_pair: true,
        ..MvsSimConfig::with_size(640, 480)
    };
    let scene = simulate_mvs(&cfg, &Monitor::noop()).expect("simulate");
    let views = scene.hazy_views();
    let reference = views[scene.reference];
    let source = views[1 - scene.reference];
    let gt = scene.views[scene.reference].depth.data();
    let (lo, hi) = gt
        .iter()
        .fold((f32::INFINITY, 0.0f32), |(a, b), &z| (a.min(z), b.max(z)));
    let planes = PlaneSet::new(0.9 * f64::from(lo), 1.2 * f64::from(hi), 128).expect("planes");
    let kind = CostKind::DehazingWith(
        AtmosphereParams {
            airlight: scene.airlight,
            beta: scene.beta,
        },
        DehazingOptions::default(),
    );
    let mut g = c.benchmark_group("mvs_stereo_pair_640x480x128");
    g.sample_size(10);
    for (name, sgm) in [
        ("default", DepthParams::default()),
        (
            "no_consistency_check",
            DepthParams {
                rejection: RejectionParams {
                    consistency_check: false,
                    ..RejectionParams::default()
                },
                ..DepthParams::default()
            },
        ),
        // 8 paths: the upward ones need the stored volumes, in strips under the default
        // budget or as one volume (2 × 80 MiB of `u16`).
        (
            "eight_paths",
            DepthParams {
                sgm: SgmParams {
                    num_paths: 8,
                    ..SgmParams::default()
                },
                ..DepthParams::default()
            },
        ),
        (
            "eight_paths_one_volume",
            DepthParams {
                sgm: SgmParams {
                    num_paths: 8,
                    volume_budget_mib: 1024,
                    ..SgmParams::default()
                },
                ..DepthParams::default()
            },
        ),
        // The opt-in census term for cameras with different tone curves (docs/stereo-mvs.md).
        (
            "census_weight_1",
            DepthParams {
                matching: MatchingParams {
                    census_weight: 1.0,
                    ..MatchingParams::default()
                },
                ..DepthParams::default()
            },
        ),
        // Without the exposure and fall-off estimates, to show what they cost.
        (
            "no_exposure_no_vignetting",
            DepthParams {
                photometric: PhotometricParams {
                    exposure_compensation: false,
                    vignetting_compensation: false,
                },
                ..DepthParams::default()
            },
        ),
    ] {
        g.bench_function(name, |b| {
            b.iter(|| {
                estimate_depth(&reference, &[source], &planes, kind, &sgm, &Monitor::noop())
                    .expect("depth")
            })
        });
    }
    g.finish();
}

/// SGM alone on a strip the size of hazy Aloe's (640×160 pixels, 173 planes) as `u16` levels,
/// 8 and 4 paths: the aggregation `estimate_depth` runs once per strip. Levels are seeded
/// pseudo-random in `0..4000` and the penalties in levels, as the quantiser's are.
fn bench_sgm(c: &mut Criterion) {
    use murk::mvs::depth::sgm::{aggregate_into, Penalties};
    let (w, h, n) = (640usize, 160usize, 173usize);
    let mut rng = ChaCha8Rng::seed_from_u64(12345);
    let levels: Vec<u16> = (0..w * h * n)
        .map(|_| rng.random_range(0..4000u16))
        .collect();
    let mut sum = vec![0u16; levels.len()];
    let pen = Penalties {
        p1: 300.0,
        p2: 1200.0,
        p2_gradient_scale: 0.0,
    };
    let mut g = c.benchmark_group("mvs_sgm_u16_640x160x173");
    g.sample_size(20);
    for paths in [8usize, 4] {
        g.bench_function(format!("{paths}_paths"), |b| {
            b.iter(|| {
                aggregate_into(
                    &levels,
                    &mut sum,
                    w,
                    h,
                    n,
                    paths,
                    &pen,
                    None,
                    &Monitor::noop(),
                )
                .expect("aggregate")
            })
        });
    }
    g.finish();
}

/// A stream's steady state against a cold start: the simulator's rectified 640×480 pair over the
/// default range (1 to 160 px of disparity, 160 planes), and the same pair as a tracker's next
/// frame after one pair, which searches only the band around that pair's disparities.
fn bench_stereo_tracker(c: &mut Criterion) {
    let cfg = MvsSimConfig {
        num_views: 2,
        rectified_pair: true,
        ..MvsSimConfig::with_size(640, 480)
    };
    let scene = simulate_mvs(&cfg, &Monitor::noop()).expect("simulate");
    let (left, right) = (&scene.views[0].hazy, &scene.views[1].hazy);
    let rig = RectifiedRig::new(
        scene.views[0].intrinsics,
        -scene.views[1].pose.translation()[0],
    );
    let options = RectifiedOptions {
        cost: CostKind::DehazingWith(
            AtmosphereParams {
                airlight: scene.airlight,
                beta: scene.beta,
            },
            DehazingOptions::default(),
        ),
        ..RectifiedOptions::default()
    };
    let noop = Monitor::noop();
    let mut primed = StereoTracker::new(rig, options).expect("rig");
    let cold = primed.estimate(left, right, &noop).expect("first pair");
    let warm = primed
        .clone()
        .estimate(left, right, &noop)
        .expect("next pair");
    assert_eq!(
        warm.search,
        Search::Band,
        "the band must hold a repeated pair"
    );
    eprintln!(
        "full range: {} planes; band: {} planes ({:.1}..{:.1} px)",
        cold.depth.planes.num_planes,
        warm.depth.planes.num_planes,
        rig.disparity_of_depth(warm.depth.planes.far),
        rig.disparity_of_depth(warm.depth.planes.near),
    );
    let mut g = c.benchmark_group("mvs_stereo_tracker_640x480");
    g.sample_size(10);
    g.bench_function("full_range", |b| {
        b.iter(|| estimate_rectified(left, right, &rig, &options, &noop).expect("depth"))
    });
    g.bench_function("band_after_a_pair", |b| {
        b.iter(|| {
            let mut t = primed.clone();
            t.estimate(left, right, &noop).expect("depth")
        })
    });
    g.finish();
}

criterion_group!(
    benches,
    bench,
    bench_stereo_pair,
    bench_sgm,
    bench_stereo_tracker
);
criterion_main!(benches);
