//! Scattering-parameter estimation (reference Ch. 3.3) on the simulator's 256×192 scene with 4
//! sources and β ∈ [0.4, 0.8]:
//! - the airlight estimators on the reference image, and loading the CNN's embedded weights;
//! - the points' transmission-ratio fit at A₀, and the joint fit of A, β, the source gains and
//!   the lens fall-offs (with and without the fall-off terms);
//! - the search as `murk params` runs it by default (the joint fit, then one depth evaluation),
//!   without and with the model's observations (the SfM poses' share of the errors);
//! - the published Algorithm 1 (β₀ by the sweep of Eq. 3.10, then the 4×4 grid with
//!   Δ_A = Δ_β = 0.05: 10 + 16 = 26 depth evaluations at 128×96 with 64 planes), alone and with
//!   the final 256-plane depth.
//!
//! Run: `cargo bench -p murk --bench params`.

use criterion::{criterion_group, criterion_main, Criterion};

use murk::atmosphere::AtmosphereParams;
use murk::mvs::{estimate_depth, CostKind, DehazingOptions, DepthParams, PlaneSet};
use murk::params::airlight::{dark_channel_airlight, DarkChannelParams};
use murk::params::search::{plane_range_from_sparse, search_scattering, SearchParams, SfmEvidence};
use murk::simulate::mvs::{simulate_mvs, MvsSimConfig};
use murk::Monitor;

fn bench(c: &mut Criterion) {
    let cfg = MvsSimConfig {
        beta_range: Some([0.4, 0.8]),
        ..MvsSimConfig::default()
    };
    let scene = simulate_mvs(&cfg, &Monitor::noop()).expect("simulate");
    let (reference, sources) = scene.reference_and_sources();
    let sparse = scene.sparse_depth().expect("sparse");
    let (near, far) = plane_range_from_sparse(&sparse).expect("points");
    let planes = PlaneSet::new(near, far, 256).expect("planes");
    // The published algorithm: the sweep over the reference's range and the 4×4 grid.
    let params = SearchParams {
        delta_airlight: 0.05,
        beta_from_points: false,
        joint_fit: false,
        beta_min: Some(0.4),
        beta_max: Some(0.8),
        delta_beta: Some(0.05),
        ..SearchParams::default()
    };
    let defaults = SearchParams::default();
    let monitor = Monitor::noop();

    let mut g = c.benchmark_group(format!("params_{}x{}", cfg.width, cfg.height));
    g.sample_size(10);
    g.bench_function("airlight_dark_channel", |b| {
        b.iter(|| dark_channel_airlight(reference.image, &DarkChannelParams::default()).unwrap())
    });
    let cnn = murk::params::airlight::AirlightCnn::embedded().expect("weights");
    g.bench_function("airlight_cnn", |b| {
        b.iter(|| cnn.estimate(reference.image).unwrap())
    });
    // What a caller pays once: build the estimator once and share it.
    g.bench_function("airlight_cnn_load", |b| {
        b.iter(|| murk::params::airlight::AirlightCnn::embedded().expect("weights"))
    });
    g.bench_function("search_26_evaluations", |b| {
        b.iter(|| {
            search_scattering(
                &reference,
                &sources,
                SfmEvidence::map(&sparse),
                0.9,
                &planes,
                &params,
                &monitor,
            )
            .expect("search")
        })
    });
    g.bench_function("point_ratio_fit", |b| {
        b.iter(|| {
            murk::params::point_ratio::beta_from_point_ratios(&reference, &sources, &sparse, 0.9)
                .expect("fit")
        })
    });
    let priors = murk::params::joint_fit::JointPriors {
        airlight: 0.9,
        airlight_sigma: 0.015,
        gain_sigma: 0.2,
        beta_start: 0.5,
        falloff_sigma: murk::params::joint_fit::FALLOFF_PRIOR_SIGMA,
        relative_falloff_sigma: murk::params::joint_fit::RELATIVE_FALLOFF_PRIOR_SIGMA,
    };
    g.bench_function("joint_fit", |b| {
        b.iter(|| {
            murk::params::joint_fit::fit_joint(&reference, &sources, &sparse, &priors).expect("fit")
        })
    });
    // The fall-off terms' share: each is one more Gauss–Newton run.
    let no_falloffs = murk::params::joint_fit::JointPriors {
        falloff_sigma: 0.0,
        relative_falloff_sigma: 0.0,
        ..priors
    };
    g.bench_function("joint_fit_without_falloffs", |b| {
        b.iter(|| {
            murk::params::joint_fit::fit_joint(&reference, &sources, &sparse, &no_falloffs)
                .expect("fit")
        })
    });
    g.bench_function("search_default_joint_fit", |b| {
        b.iter(|| {
            search_scattering(
                &reference,
                &sources,
                SfmEvidence::map(&sparse),
                0.9,
                &planes,
                &defaults,
                &monitor,
            )
            .expect("search")
        })
    });
    // The same with the model's observations: the SfM poses' share of the errors, 46 sigma-point
    // refits for 4 sources.
    let tracks = scene.sfm_tracks(sources.len()).expect("tracks");
    g.bench_function("search_default_joint_fit_with_pose_error", |b| {
        b.iter(|| {
            let est = search_scattering(
                &reference,
                &sources,
                SfmEvidence {
                    sparse: &sparse,
                    tracks: Some(&tracks),
                },
                0.9,
                &planes,
                &defaults,
                &monitor,
            )
            .expect("search");
            assert!(est.pose_error.is_some());
            est
        })
    });
    g.bench_function("full_estimation_26_search_plus_final_depth", |b| {
        b.iter(|| {
            let est = search_scattering(
                &reference,
                &sources,
                SfmEvidence::map(&sparse),
                0.9,
                &planes,
                &params,
                &monitor,
            )
            .expect("search");
            let kind = CostKind::DehazingWith(
                AtmosphereParams {
                    airlight: est.airlight,
                    beta: est.beta,
                },
                DehazingOptions::default(),
            );
            estimate_depth(
                &reference,
                &sources,
                &planes,
                kind,
                &DepthParams::default(),
                &monitor,
            )
            .expect("depth")
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
