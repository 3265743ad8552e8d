//! End-to-end checks of the pipeline on simulated captures (release mode; small images).

use crate::metrics::mean_angular_error_deg;
use crate::monitor::Monitor;
use crate::ps::physics::{FacetEmission, FarField};
use crate::ps::{photometric_stereo, DistanceMode, PsMode, PsParams};
use crate::simulate::ps::{simulate_ps, PsSimConfig};

/// Mean |z − z_gt| over the mask, mm.
fn depth_mae_mm(depth: &[f32], gt: &[f32], mask: &[bool]) -> f64 {
    let (mut sum, mut n) = (0.0f64, 0usize);
    for ((d, g), &m) in depth.iter().zip(gt).zip(mask) {
        if m {
            sum += f64::from((d - g).abs());
            n += 1;
        }
    }
    sum / n.max(1) as f64
}

fn errors(cfg: &PsSimConfig, params: &PsParams) -> Vec<f64> {
    let sim = simulate_ps(cfg, &Monitor::noop()).unwrap();
    let params = PsParams {
        initial_distance_mm: sim.initial_distance_mm,
        ..params.clone()
    };
    let out = photometric_stereo(&sim.capture, &params, &Monitor::noop()).unwrap();
    out.normals_history
        .iter()
        .map(|n| mean_angular_error_deg(n, &sim.gt_normals, &sim.capture.mask).unwrap())
        .collect()
}

#[test]
fn without_a_medium_it_is_classic_near_light_photometric_stereo() {
    let cfg = PsSimConfig {
        beta_per_mm: 0.0,
        sigma_per_mm: 0.0,
        ..PsSimConfig::with_size(64, 64)
    };
    let params = PsParams {
        support_r: 15,
        max_iterations: 10,
        ..PsParams::default()
    };
    let e = errors(&cfg, &params);
    eprintln!("β = σ = 0, per iteration: {e:?}");
    assert!(*e.last().unwrap() < 0.5, "{e:?}");
}

#[test]
fn converges_in_turbid_water_and_beats_the_backscatter_only_baseline() {
    let cfg = PsSimConfig::with_size(96, 96);
    let params = PsParams {
        support_r: 25,
        max_iterations: 5,
        ..PsParams::default()
    };
    let full = errors(&cfg, &params);
    let base = errors(
        &cfg,
        &PsParams {
            mode: PsMode::BackscatterOnly,
            ..params.clone()
        },
    );
    eprintln!("full: {full:?}\nbackscatter only: {base:?}");
    let (f, b) = (*full.last().unwrap(), *base.last().unwrap());
    // The reduced scene ends at 0.28° against the baseline's 10.6° (measured; at full size the
    // method ends at 0.05°, docs/photometric-stereo.md), so both bounds leave a wide margin.
    assert!(f < 1.5, "full model error {f}° ({full:?})");
    assert!(f < 0.25 * b, "full {f}° vs baseline {b}°");
    assert!(
        f < full[0],
        "no improvement over the first iteration: {full:?}"
    );
}

/// A kernel kept while the shape barely moves gives the answer of rebuilding it every
/// iteration: the iterations that reuse it are flagged and cost no build, the normals agree to
/// a fiftieth of a degree, and the depths differ by less than the tolerance times the distance
/// (the kept kernel's shape is that close to the current one; measured: 0.006 mm of 212 mm, the
/// bound is 0.21 mm); a tolerance of 0 rebuilds every time.
#[test]
fn a_kept_kernel_matches_rebuilding_it() {
    let cfg = PsSimConfig::with_size(96, 96);
    let sim = simulate_ps(&cfg, &Monitor::noop()).unwrap();
    let run = |kernel_rebuild_tolerance: f64| {
        let params = PsParams {
            initial_distance_mm: sim.initial_distance_mm,
            support_r: 25,
            max_iterations: 6,
            tolerance: 0.0,
            kernel_rebuild_tolerance,
            ..PsParams::default()
        };
        photometric_stereo(&sim.capture, &params, &Monitor::noop()).unwrap()
    };
    let (always, kept) = (run(0.0), run(PsParams::default().kernel_rebuild_tolerance));
    assert!(always.iterations.iter().all(|s| !s.kernel_reused));
    let reused: Vec<usize> = kept
        .iterations
        .iter()
        .filter(|s| s.kernel_reused)
        .map(|s| s.iteration)
        .collect();
    eprintln!(
        "kept: {reused:?} reused; changes {:?}",
        kept.iterations
            .iter()
            .map(|s| s.relative_depth_change)
            .collect::<Vec<_>>()
    );
    assert!(!reused.is_empty(), "no iteration reused the kernel");
    assert!(!kept.iterations[0].kernel_reused);
    for s in kept.iterations.iter().filter(|s| s.kernel_reused) {
        assert_eq!(s.kernel_s, 0.0);
    }
    let mask = &sim.capture.mask;
    let e_always = mean_angular_error_deg(&always.normals, &sim.gt_normals, mask).unwrap();
    let e_kept = mean_angular_error_deg(&kept.normals, &sim.gt_normals, mask).unwrap();
    let d_always = depth_mae_mm(&always.depth_mm, &sim.gt_depth_mm, mask);
    let d_kept = depth_mae_mm(&kept.depth_mm, &sim.gt_depth_mm, mask);
    eprintln!("rebuilt: {e_always:.3}°, {d_always:.3} mm; kept: {e_kept:.3}°, {d_kept:.3} mm");
    assert!((e_always - e_kept).abs() < 0.02, "{e_always}° vs {e_kept}°");
    let bound = PsParams::default().kernel_rebuild_tolerance * sim.initial_distance_mm;
    assert!(
        (d_always - d_kept).abs() < bound,
        "{d_always} mm vs {d_kept} mm (bound {bound} mm)"
    );
}

/// At reduced size: with the physical (Lambertian) facet in the scene and the
/// method, a starting distance 20 % off either way, or none at all, still ends below the
/// reference's 1.29° and within 2 mm of the true depth, because the distance is fitted to the
/// lights' fall-off; with the distance fixed at the wrong value the depth is 40 mm off. The
/// fit is only as good as the reflected component: with the far field summed in blocks (the
/// default) it lands within 0.5 % (measured 0.1 %, 0.15–0.17 mm); the per-pixel far field,
/// which takes the unevenly lit outside of each support as uniform, puts it further off.
#[test]
fn distance_is_estimated_from_a_wrong_or_missing_start() {
    let cfg = PsSimConfig::with_size(96, 96);
    assert_eq!(cfg.facet_emission, FacetEmission::Lambertian);
    let sim = simulate_ps(&cfg, &Monitor::noop()).unwrap();
    let truth = sim.initial_distance_mm;
    for (scale, distance) in [
        (0.8, DistanceMode::Estimate),
        (1.2, DistanceMode::Estimate),
        (0.0, DistanceMode::Estimate),
        (0.8, DistanceMode::Fixed),
    ] {
        let params = PsParams {
            initial_distance_mm: truth * scale,
            distance,
            support_r: 25,
            ..PsParams::default()
        };
        let out = photometric_stereo(&sim.capture, &params, &Monitor::noop()).unwrap();
        let err = mean_angular_error_deg(&out.normals, &sim.gt_normals, &sim.capture.mask).unwrap();
        let mae = depth_mae_mm(&out.depth_mm, &sim.gt_depth_mm, &sim.capture.mask);
        let mean = out.iterations.last().unwrap().mean_depth_mm;
        eprintln!("start {scale} × truth, {distance:?}: {err:.2}°, depth MAE {mae:.2} mm, mean z {mean:.1} (truth {truth:.1})");
        if distance == DistanceMode::Fixed {
            assert!(
                (mean / (truth * scale) - 1.0).abs() < 1e-3,
                "a fixed distance stays put"
            );
            assert!(mae > 20.0, "{mae}");
            assert!(out.iterations.iter().all(|s| s.distance_fit.is_none()));
            continue;
        }
        assert_eq!(out.initial_distance_fit.is_some(), scale == 0.0);
        assert!(err < 1.29, "{err}° from a start {scale} × truth");
        assert!(mae < 0.6, "depth MAE {mae} mm from a start {scale} × truth");
        assert!((mean / truth - 1.0).abs() < 0.005, "{mean} vs {truth}");
    }
    let per_pixel = PsParams {
        initial_distance_mm: truth,
        support_r: 25,
        far_field: FarField::PerPixel,
        ..PsParams::default()
    };
    let out = photometric_stereo(&sim.capture, &per_pixel, &Monitor::noop()).unwrap();
    let mae = depth_mae_mm(&out.depth_mm, &sim.gt_depth_mm, &sim.capture.mask);
    let mean = out.iterations.last().unwrap().mean_depth_mm;
    eprintln!("per-pixel far field from the true start: depth MAE {mae:.2} mm, mean z {mean:.1}");
    assert!(mae > 0.8, "per-pixel far field: {mae} mm");
}

/// Eq. 4.41's isotropic facet stays selectable, and on a physical scene it is the worse model:
/// the method with the Lambertian facet beats it on the same capture.
#[test]
fn physical_facet_emission_beats_eq_4_41_on_a_physical_scene() {
    let cfg = PsSimConfig::with_size(96, 96);
    let params = PsParams {
        support_r: 25,
        distance: DistanceMode::Fixed,
        ..PsParams::default()
    };
    let lambertian = *errors(&cfg, &params).last().unwrap();
    let isotropic = *errors(
        &cfg,
        &PsParams {
            facet_emission: FacetEmission::Isotropic,
            ..params.clone()
        },
    )
    .last()
    .unwrap();
    eprintln!(
        "physical scene: Lambertian facet {lambertian:.2}°, Eq. 4.41 isotropic {isotropic:.2}°"
    );
    assert!(lambertian < 0.7 * isotropic, "{lambertian} vs {isotropic}");
}
