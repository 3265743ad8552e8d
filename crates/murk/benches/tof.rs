//! ToF-in-fog benchmarks at the Kinect v2 size 424×512, on simulated medium-fog frames (seed 1):
//!
//! * `tof_pipeline_424x512/*`: the full pipeline with the defaults (the phasor's two parts with
//!   shared weights, the joint prior, caps of 5 coarse + 150 fine IRLS iterations) on a
//!   separated and a cluttered frame; the same with the V-cycle alone as the x-step's
//!   preconditioner (no coarse space); the reference's configuration (amplitude and phase
//!   separately, alternating x- and a-steps).
//! * `tof_xstep_424x512/*`: one x-step solve (Eq. 5.12) with each solver, warm and cold start.
//! * `tof_stream_424x512/*`: the second frame of a simulated stream (`TofMotion::default()`,
//!   10 fps) from the first frame's answer, as a session computes it by default: its scatter
//!   solved on 2×2 block means (`estimate_tof_depth_on_grid`); the same at full size; the full
//!   size start without its σ₁ (the fine level from the previous weights alone); and the frame
//!   from scratch, by itself and as a session's first frame (`TofTracker` with its 2×2 grid:
//!   the coarse level on the grid).
//!
//! Run: `cargo bench -p murk --bench tof` (or `-- pipeline`, `-- xstep`, `-- stream` for one
//! group).

use criterion::{criterion_group, criterion_main, Criterion};

use murk::simulate::tof::{simulate_tof, FogPreset, TofSimConfig};
use murk::simulate::{simulate_tof_sequence_frame, SceneLayout, TofMotion};
use murk::tof::irls::{run_irls, IrlsConfig};
use murk::tof::quadratic_prior::{PatchGrid, QuadraticPrior};
use murk::tof::symmetry::RowMirror;
use murk::tof::wls::{XStepState, XStepSystem};
use murk::tof::{
    estimate_tof_depth_from, estimate_tof_depth_on_grid, estimate_tof_depth_with_solver,
    IrlsChannelParams, IrlsStart, Preconditioner, PriorCoupling, ScatterChannels, TofInput,
    TofParams, TofTracker, XStepSolver,
};
use murk::Monitor;

const W: usize = 512;
const H: usize = 424;

fn frame() -> TofInput {
    frame_of(SceneLayout::Separated)
}

fn frame_of(layout: SceneLayout) -> TofInput {
    let cfg = TofSimConfig {
        preset: FogPreset::Medium,
        seed: 1,
        layout,
        ..TofSimConfig::with_size(W, H)
    };
    let f = simulate_tof(&cfg, &Monitor::noop()).expect("simulate");
    TofInput {
        amplitude: f.amplitude,
        phase: f.phase,
        intrinsics: Some(f.intrinsics),
    }
}

fn bench(c: &mut Criterion) {
    let input = frame();
    let params = TofParams::default();
    let monitor = Monitor::noop();

    let mut g = c.benchmark_group("tof_pipeline_424x512");
    g.sample_size(10);
    g.bench_function("pcg_default", |b| {
        b.iter(|| {
            estimate_tof_depth_with_solver(&input, &params, XStepSolver::default(), &monitor)
                .expect("pipeline")
        })
    });
    let cluttered = frame_of(SceneLayout::Cluttered);
    g.bench_function("pcg_default_cluttered", |b| {
        b.iter(|| {
            estimate_tof_depth_with_solver(&cluttered, &params, XStepSolver::default(), &monitor)
                .expect("pipeline")
        })
    });
    // The V-cycle alone, no coarse space, for comparison.
    let vcycle_only = XStepSolver::Pcg {
        rel_tol: 1e-5,
        max_iterations: 400,
        preconditioner: Preconditioner::MultigridOnly,
    };
    for (name, frame) in [
        ("pcg_vcycle_only", &input),
        ("pcg_vcycle_only_cluttered", &cluttered),
    ] {
        g.bench_function(name, |b| {
            b.iter(|| {
                estimate_tof_depth_with_solver(frame, &params, vcycle_only, &monitor)
                    .expect("pipeline")
            })
        });
    }
    let reference = TofParams {
        channels: ScatterChannels::AmplitudePhase,
        prior_coupling: PriorCoupling::Alternating,
        coarse_subdivision: 1,
        coarse_quantile: 0.5,
        ..TofParams::default()
    };
    g.bench_function("reference_amplitude_phase_alternating", |b| {
        b.iter(|| {
            estimate_tof_depth_with_solver(&input, &reference, XStepSolver::default(), &monitor)
                .expect("pipeline")
        })
    });
    g.finish();

    // One x-step at the state the fine level sees: weights from a short IRLS run on the phase
    // image (γ′ = PHASE, the stiffer system), warm start = that run's x (as inside the loop) and
    // cold start = the observation.
    let observed: Vec<f64> = input.phase.data().iter().map(|&v| v as f64).collect();
    let ch = IrlsChannelParams::PHASE;
    let sys = XStepSystem::new(W, H, ch.gamma, RowMirror::new(H, (H as f64 - 1.0) / 2.0));
    let mut prior = QuadraticPrior::new(PatchGrid::new(W, H, 4, 4)).expect("prior");
    let cfg = IrlsConfig {
        channel: ch,
        coarse_iterations: 5,
        fine_iterations: 5,
        solver: XStepSolver::default(),
        weight_tolerance: 0.0,
        mask_threshold: 0.5,
        coarse_subdivision: 1,
        coarse_quantile: 0.5,
    };
    let st = run_irls(
        &observed,
        &sys,
        &mut prior,
        &cfg,
        "bench",
        &monitor,
        &|_| {},
    )
    .expect("irls");
    let mut prior_img = vec![0.0; W * H];
    prior.evaluate(&mut prior_img);
    let mut rhs = vec![0.0; W * H];
    sys.rhs(&st.weights, &observed, &prior_img, &mut rhs);

    let mut g = c.benchmark_group("tof_xstep_424x512");
    g.sample_size(10);
    let mut x = st.scatter[0].clone();
    for (name, pre) in [
        ("mg", Preconditioner::Multigrid),
        ("jacobi", Preconditioner::Jacobi),
    ] {
        let kind = XStepSolver::Pcg {
            rel_tol: 1e-5,
            max_iterations: 1000,
            preconditioner: pre,
        };
        let mut pcg = XStepState::new(kind, &sys).expect("pcg");
        for (start, label) in [(&st.scatter[0], "warm"), (&observed, "cold")] {
            x.copy_from_slice(start);
            let s = pcg
                .solve(&sys, &st.weights, &rhs, &mut x, &monitor)
                .expect("solve");
            println!(
                "x-step {name} {label}: {} CG iterations, rel. residual {:.1e}",
                s.iterations, s.rel_residual
            );
            g.bench_function(format!("pcg_{name}_{label}"), |b| {
                b.iter(|| {
                    x.copy_from_slice(start);
                    pcg.solve(&sys, &st.weights, &rhs, &mut x, &monitor)
                        .expect("solve")
                })
            });
        }
    }
    let mut chol = XStepState::new(XStepSolver::SparseCholesky, &sys).expect("cholesky");
    g.bench_function("sparse_cholesky", |b| {
        b.iter(|| {
            chol.solve(&sys, &st.weights, &rhs, &mut x, &monitor)
                .expect("solve")
        })
    });
    g.finish();
}

/// A stream's warm frame against the same frame from scratch (see the module docs).
fn bench_stream(c: &mut Criterion) {
    let cfg = TofSimConfig::with_size(W, H);
    let motion = TofMotion::default();
    let frame = |k| {
        let f = simulate_tof_sequence_frame(&cfg, &motion, k, &Monitor::noop()).expect("simulate");
        TofInput {
            amplitude: f.amplitude,
            phase: f.phase,
            intrinsics: Some(f.intrinsics),
        }
    };
    let params = TofParams {
        light_position_m: Some(cfg.light_position_m()),
        ..TofParams::default()
    };
    let monitor = Monitor::noop();
    let (_, start) =
        estimate_tof_depth_from(&frame(0), &params, None, &monitor).expect("first frame");
    let start = start.expect("the phasor channels leave a start");
    let weights_only = IrlsStart {
        sigma_fine: None,
        ..start.clone()
    };
    let on_grid = start.box_downsampled(W, H, 2).expect("2 divides the sides");
    let next = frame(1);
    let mut g = c.benchmark_group("tof_stream_424x512");
    g.sample_size(10);
    g.bench_function("warm_frame_on_2x2_grid", |b| {
        b.iter(|| estimate_tof_depth_on_grid(&next, &params, &on_grid, 2, &monitor).expect("frame"))
    });
    // A session's first frame: from scratch, its coarse level on the grid.
    g.bench_function("cold_frame_with_2x2_grid", |b| {
        b.iter(|| {
            let mut tracker = TofTracker::with_scatter_grid(params.clone(), 2).expect("grid");
            tracker.estimate(&next, &monitor).expect("frame")
        })
    });
    for (name, from) in [
        ("warm_frame", Some(&start)),
        ("warm_frame_from_previous_weights", Some(&weights_only)),
        ("cold_frame", None),
    ] {
        g.bench_function(name, |b| {
            b.iter(|| estimate_tof_depth_from(&next, &params, from, &monitor).expect("frame"))
        });
    }
    g.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(10);
    targets = bench, bench_stream
}
criterion_main!(benches);
