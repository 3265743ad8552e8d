//! End-to-end checks of the pipeline on simulated captures (release mode; small images).

use crate::metrics::mean_angular_error_deg;
use crate::monitor::Monitor;
use crate::ps::physics::{FacetEmission, FarField};
use crate::ps::{photometric_stereo, DistanceMode, PsMode, PsParams};
use crate::simulate::ps::{simulate_ps, PsShape, PsSimConfig};

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
    // The target at full size is 1.5°; with the per-pixel far field the reduced scene
    // reaches 0.91° (1.65° with Eq. 4.52's constant ε).
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
/// (the kept kernel's shape is that close to the current one; measured: 0.05 mm of 212 mm, the
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

/// Issue 22's claim at reduced size: with the physical (Lambertian) facet in the scene and the
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

#[test]
#[ignore = "experiment: the reference's synthetic table at full size; run with --ignored --nocapture"]
fn reference_table_full_size() {
    let shape = match std::env::var("MURK_PS_SHAPE").as_deref() {
        Ok("vase") => PsShape::Vase,
        Ok("bumps") => PsShape::Bumps,
        _ => PsShape::Sphere,
    };
    let r: usize = std::env::var("MURK_PS_R")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(81);
    let side: usize = std::env::var("MURK_PS_SIDE")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(300);
    // MURK_PS_SIM_EMISSION=isotropic renders with Eq. 4.41's facet instead of the physical one.
    let facet_emission = match std::env::var("MURK_PS_SIM_EMISSION").as_deref() {
        Ok("isotropic") => FacetEmission::Isotropic,
        _ => FacetEmission::Lambertian,
    };
    let cfg = PsSimConfig {
        shape,
        facet_emission,
        // A ±40 % albedo pattern must stay ≤ 1.
        textured: std::env::var("MURK_PS_TEXTURED").is_ok(),
        albedo: if std::env::var("MURK_PS_TEXTURED").is_ok() {
            0.6
        } else {
            PsSimConfig::default().albedo
        },
        ..PsSimConfig::with_size(side, side)
    };
    let t0 = std::time::Instant::now();
    let sim = simulate_ps(&cfg, &Monitor::noop()).unwrap();
    eprintln!(
        "{shape:?} {side}x{side} ({facet_emission:?} facets): {} object px, simulated in {:.1} s, \
         initial plane {:.1} mm",
        sim.capture.mask.iter().filter(|&&b| b).count(),
        t0.elapsed().as_secs_f64(),
        sim.initial_distance_mm
    );
    let far_cell: usize = std::env::var("MURK_PS_CELL")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(crate::ps::pipeline::DEFAULT_FAR_CELL);
    let near_radius_px: usize = std::env::var("MURK_PS_NEAR")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(crate::ps::pipeline::DEFAULT_NEAR_RADIUS_PX);
    // MURK_PS_AUTO=1: the support and far cell that `auto_support` would choose.
    let (r, far_cell) = if std::env::var("MURK_PS_AUTO").is_ok() {
        let (w, h) = sim.capture.dims();
        let c = crate::ps::choose_support(
            &sim.capture.mask,
            w,
            h,
            near_radius_px,
            crate::ps::pipeline::DEFAULT_MAX_KERNEL_BYTES,
        )
        .unwrap();
        eprintln!("auto support: {c:?}");
        (c.support_r, c.far_cell)
    } else {
        (r, far_cell)
    };
    // MURK_PS_INIT_SCALE: start from the true mean depth times each of these (comma-separated;
    // 0 = no distance given).
    let scales: Vec<f64> = std::env::var("MURK_PS_INIT_SCALE")
        .map(|v| v.split(',').filter_map(|x| x.trim().parse().ok()).collect())
        .unwrap_or_else(|_| vec![1.0]);
    for init_scale in scales {
        eprintln!("start at {init_scale} × the true mean depth:");
        let base = PsParams {
            initial_distance_mm: sim.initial_distance_mm * init_scale,
            far_field: env_far_field(),
            far_cell,
            near_radius_px,
            support_r: r,
            max_iterations: 5,
            tolerance: 0.0,
            ..PsParams::default()
        };
        // MURK_PS_PUBLISHED_PHYSICS=1: session 9's model (isotropic facet, no backscatter tail,
        // the distance fixed at the start).
        let base = if std::env::var("MURK_PS_PUBLISHED_PHYSICS").is_ok() {
            PsParams {
                facet_emission: FacetEmission::Isotropic,
                backscatter_tail: false,
                distance: DistanceMode::Fixed,
                ..base
            }
        } else {
            base
        };
        let variants = [
            ("full, exact G (murk default)", PsParams { ..base.clone() }),
            (
                "full, Eq. 4.41 isotropic facet",
                PsParams {
                    facet_emission: FacetEmission::Isotropic,
                    ..base.clone()
                },
            ),
            (
                "full, Eq. 4.55 linear G (as published)",
                PsParams {
                    exact_g: false,
                    ..base.clone()
                },
            ),
            (
                "backscatter only [15]",
                PsParams {
                    mode: PsMode::BackscatterOnly,
                    ..base.clone()
                },
            ),
            (
                "input GT, exact G",
                PsParams {
                    initial_depth_mm: Some(sim.gt_depth_mm.clone()),
                    max_iterations: 1,
                    ..base.clone()
                },
            ),
            (
                "input GT, linear G",
                PsParams {
                    initial_depth_mm: Some(sim.gt_depth_mm.clone()),
                    max_iterations: 1,
                    exact_g: false,
                    ..base.clone()
                },
            ),
            (
                "full, Eq. 4.52 constant ε (as published)",
                PsParams {
                    far_field: FarField::ConstantEpsilon,
                    ..base.clone()
                },
            ),
            (
                "input GT, Eq. 4.52 constant ε",
                PsParams {
                    initial_depth_mm: Some(sim.gt_depth_mm.clone()),
                    max_iterations: 1,
                    far_field: FarField::ConstantEpsilon,
                    ..base.clone()
                },
            ),
        ];
        let count: usize = std::env::var("MURK_PS_VARIANTS")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(variants.len());
        for (name, params) in variants.into_iter().take(count) {
            let out = photometric_stereo(&sim.capture, &params, &Monitor::noop()).unwrap();
            let e: Vec<String> = out
                .normals_history
                .iter()
                .map(|n| {
                    format!(
                        "{:.2}",
                        mean_angular_error_deg(n, &sim.gt_normals, &sim.capture.mask).unwrap()
                    )
                })
                .collect();
            let kernel: f64 = out.iterations.iter().map(|s| s.kernel_s).sum();
            let solve: f64 = out.iterations.iter().map(|s| s.solve_s).sum();
            let tail: f64 = out.iterations.iter().map(|s| s.tail_s).sum();
            let builds = out.iterations.iter().filter(|s| !s.kernel_reused).count();
            let normals: f64 = out.iterations.iter().map(|s| s.normals_s).sum();
            let integrate: f64 = out.iterations.iter().map(|s| s.integrate_s).sum();
            let depth_mae = depth_mae_mm(&out.depth_mm, &sim.gt_depth_mm, &sim.capture.mask);
            let means: Vec<String> = out
                .iterations
                .iter()
                .map(|s| format!("{:.1}", s.mean_depth_mm))
                .collect();
            let changes: Vec<String> = out
                .iterations
                .iter()
                .map(|s| format!("{:.1e}", s.relative_depth_change))
                .collect();
            eprintln!(
                "| {name} | {} | depth MAE {depth_mae:.2} mm | {:.1} s (kernel {kernel:.1} in {builds} builds, \
                 BiCGStab {solve:.1}, tail {tail:.1}, normals {normals:.1}, integration {integrate:.1}) | mean z {} | relative change {} |",
                e.join(" | "),
                out.total_s,
                means.join(" → "),
                changes.join(" → ")
            );
        }
    }
}

#[test]
#[ignore = "experiment: run with --ignored --nocapture (MURK_PS_SIDE, MURK_PS_R, MURK_PS_INIT)"]
fn experiment_iterations() {
    let side: usize = std::env::var("MURK_PS_SIDE")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(96);
    let r: usize = std::env::var("MURK_PS_R")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(25);
    let cfg = PsSimConfig::with_size(side, side);
    let sim = simulate_ps(&cfg, &Monitor::noop()).unwrap();
    let gt_mean: f64 = sim
        .gt_depth_mm
        .iter()
        .zip(&sim.capture.mask)
        .filter(|(_, &m)| m)
        .map(|(z, _)| f64::from(*z))
        .sum::<f64>()
        / sim.capture.mask.iter().filter(|&&m| m).count() as f64;
    eprintln!("gt mean depth {gt_mean}");
    for (mode, scale) in [
        (PsMode::Full, true),
        (PsMode::Full, false),
        (PsMode::BackscatterOnly, true),
    ] {
        let init: f64 = std::env::var("MURK_PS_INIT")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(sim.initial_distance_mm);
        let params = PsParams {
            initial_distance_mm: if init > 0.0 { init } else { gt_mean },
            support_r: r,
            max_iterations: 6,
            tolerance: 0.0,
            mode,
            exact_g: scale,
            ..PsParams::default()
        };
        let out = photometric_stereo(&sim.capture, &params, &Monitor::noop()).unwrap();
        let e: Vec<f64> = out
            .normals_history
            .iter()
            .map(|n| mean_angular_error_deg(n, &sim.gt_normals, &sim.capture.mask).unwrap())
            .collect();
        let z: Vec<f64> = out.iterations.iter().map(|s| s.mean_depth_mm).collect();
        let it: Vec<usize> = out
            .iterations
            .iter()
            .map(|s| s.solver_iterations.iter().copied().max().unwrap_or(0))
            .collect();
        let c: Vec<f64> = out
            .iterations
            .iter()
            .map(|s| s.constant_term.first().copied().unwrap_or(0.0))
            .collect();
        eprintln!(
            "{mode:?} scale={scale}: err {e:.2?}\n   z {z:.1?} solver {it:?} C {c:?} eps {:.3e}",
            out.iterations[0].epsilon
        );
    }
    for (mode, median) in [
        (PsMode::Full, true),
        (PsMode::Full, false),
        (PsMode::BackscatterOnly, true),
    ] {
        let params = PsParams {
            median_filter: median,
            initial_distance_mm: gt_mean,
            initial_depth_mm: Some(sim.gt_depth_mm.clone()),
            support_r: r,
            max_iterations: 1,
            tolerance: 0.0,
            mode,
            ..PsParams::default()
        };
        let out = photometric_stereo(&sim.capture, &params, &Monitor::noop()).unwrap();
        let e = mean_angular_error_deg(&out.normals, &sim.gt_normals, &sim.capture.mask).unwrap();
        let dz: f64 = out
            .depth_mm
            .iter()
            .zip(&sim.gt_depth_mm)
            .zip(&sim.capture.mask)
            .filter(|(_, &m)| m)
            .map(|((a, b), _)| f64::from((a - b).abs()))
            .sum::<f64>()
            / sim.capture.mask.iter().filter(|&&m| m).count() as f64;
        eprintln!("input GT {mode:?} median {median}: normals {e:.2}°, integrated depth mean |dz| {dz:.2} mm");
    }
}

/// MURK_PS_FAR: the far-field model of the experiments (blocks, per-pixel, constant-epsilon;
/// unset = the default).
pub(crate) fn env_far_field() -> FarField {
    match std::env::var("MURK_PS_FAR").as_deref() {
        Ok("per-pixel") => FarField::PerPixel,
        Ok("blocks") => FarField::Blocks,
        Ok("constant-epsilon") => FarField::ConstantEpsilon,
        _ => FarField::default(),
    }
}

#[test]
#[ignore = "experiment: run with --ignored --nocapture (MURK_PS_SIDE, MURK_PS_R, MURK_PS_INIT)"]
fn experiment_error_floors() {
    use crate::ps::bicgstab::{bicgstab_block, BicgstabParams, BlockOperator};
    use crate::ps::near_light::{solve_normals, ShadingModel};
    use crate::ps::physics::{backscatter, FTable, ForwardKernel, GTable, SurfaceGeometry};
    use crate::ps::pipeline::back_project;
    struct Aug<'a>(&'a ForwardKernel);
    impl BlockOperator for Aug<'_> {
        fn dim(&self) -> usize {
            self.0.dim()
        }
        fn apply_block(&self, xs: &[f64], ys: &mut [f64], k: usize) {
            self.0.apply_block(xs, ys, k)
        }
    }
    let side: usize = std::env::var("MURK_PS_SIDE")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(150);
    let r: usize = std::env::var("MURK_PS_R")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(41);
    let cfg = PsSimConfig::with_size(side, side);
    let sim = simulate_ps(&cfg, &Monitor::noop()).unwrap();
    let cap = &sim.capture;
    let (w, h) = cap.dims();
    let mask = &cap.mask;
    let pts = back_project(&cap.intrinsics, w, &sim.gt_depth_mm, mask);
    let gt = GTable::global();
    let err = |n: &[[f32; 3]]| mean_angular_error_deg(n, &sim.gt_normals, mask).unwrap();
    for refine in [false, true] {
        for model in [ShadingModel::ForwardScatter, ShadingModel::DirectOnly] {
            let est = solve_normals(
                &sim.gt_reflected,
                &cap.lights,
                &cap.medium,
                gt,
                model,
                &pts,
                mask,
                w,
                0.05,
                refine,
            );
            eprintln!(
                "E1 GT L_s, {model:?}, refine {refine}: {:.3}°",
                err(&est.normals)
            );
        }
    }
    // Interior only (cos view > 0.3) to see the silhouette's share.
    let interior: Vec<bool> = (0..w * h)
        .map(|p| {
            mask[p] && {
                let n = sim.gt_normals[p];
                let pt = pts[p];
                let d = (pt[0] * pt[0] + pt[1] * pt[1] + pt[2] * pt[2]).sqrt();
                -(n[0] * pt[0] + n[1] * pt[1] + n[2] * pt[2]) / d > 0.3
            }
        })
        .collect();
    let est = solve_normals(
        &sim.gt_reflected,
        &cap.lights,
        &cap.medium,
        gt,
        ShadingModel::ForwardScatter,
        &pts,
        mask,
        w,
        0.05,
        true,
    );
    eprintln!(
        "E1 interior only: {:.3}° ({} of {} px)",
        mean_angular_error_deg(&est.normals, &sim.gt_normals, &interior).unwrap(),
        interior.iter().filter(|&&b| b).count(),
        mask.iter().filter(|&&b| b).count()
    );
    let geom = SurfaceGeometry {
        width: w,
        height: h,
        intrinsics: cap.intrinsics,
        points_mm: pts.clone(),
        normals: sim.gt_normals.clone(),
        mask: mask.clone(),
        emission: FacetEmission::default(),
    };
    let kernel = ForwardKernel::build(FTable::global(), &cap.medium, &geom, r).unwrap();
    let masked: Vec<usize> = (0..w * h).filter(|&p| mask[p]).collect();
    let dim = masked.len() + 1;
    let m = cap.lights.len();
    for exact_bg in [true, false] {
        let mut b = vec![0.0; dim * m];
        for i in 0..m {
            for (k, &p) in masked.iter().enumerate() {
                let d = {
                    let q = pts[p];
                    ((q[0] * q[0] + q[1] * q[1] + q[2] * q[2]) as f64).sqrt()
                };
                let ray = cap.intrinsics.ray((p % w) as f64, (p / w) as f64);
                let bg = if exact_bg {
                    backscatter(
                        FTable::global(),
                        &cap.medium,
                        cap.lights[i].intensity,
                        cap.lights[i].position_mm,
                        ray,
                        d,
                    )
                } else {
                    f64::from(cap.backgrounds[i].data()[p])
                };
                b[i * dim + k] = f64::from(cap.images[i].data()[p]) - bg;
            }
        }
        let mut x = b.clone();
        bicgstab_block(
            &Aug(&kernel),
            &b,
            &mut x,
            m,
            &BicgstabParams::default(),
            &Monitor::noop(),
        )
        .unwrap();
        let ls: Vec<Vec<f32>> = (0..m)
            .map(|i| {
                let mut v = vec![0.0f32; w * h];
                for (k, &p) in masked.iter().enumerate() {
                    v[p] = x[i * dim + k] as f32;
                }
                v
            })
            .collect();
        let rel: f64 = (0..m)
            .map(|i| {
                masked
                    .iter()
                    .map(|&p| {
                        ((ls[i][p] - sim.gt_reflected[i][p]).abs()
                            / sim.gt_reflected[i][p].abs().max(1e-6)) as f64
                    })
                    .sum::<f64>()
                    / masked.len() as f64
            })
            .sum::<f64>()
            / m as f64;
        let est = solve_normals(
            &ls,
            &cap.lights,
            &cap.medium,
            gt,
            ShadingModel::ForwardScatter,
            &pts,
            mask,
            w,
            0.05,
            true,
        );
        eprintln!(
            "E3 kernel r={r} exact_bg={exact_bg}: {:.3}° (mean rel. L_s error {rel:.4}, C {:.3e})",
            err(&est.normals),
            x[dim - 1]
        );
    }
}

#[test]
#[ignore = "experiment: run with --ignored --nocapture (MURK_PS_SIDE, MURK_PS_R, MURK_PS_INIT)"]
fn experiment_g_shape() {
    let g = crate::ps::physics::GTable::global();
    for t in [0.5, 1.0, 1.5, 2.0] {
        let row: Vec<String> = [-0.5, 0.0, 0.25, 0.5, 0.75, 0.9, 1.0]
            .iter()
            .map(|&c| format!("{c}:{:.4}", g.eval(t, c)))
            .collect();
        eprintln!("T={t}: {}", row.join(" "));
    }
}

#[test]
#[ignore = "experiment: kernel build time on the simulator's sphere, the initial plane and the pipeline's shapes"]
fn experiment_kernel_build_time() {
    use crate::ps::integrate::normals_from_depth;
    use crate::ps::physics::{FTable, ForwardKernel, SurfaceGeometry};
    use crate::ps::pipeline::back_project;
    let side: usize = std::env::var("MURK_PS_SIDE")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(300);
    let r: usize = std::env::var("MURK_PS_R")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(81);
    let cfg = PsSimConfig {
        far_stride: 8,
        ..PsSimConfig::with_size(side, side)
    };
    let sim = simulate_ps(&cfg, &Monitor::noop()).unwrap();
    let cap = &sim.capture;
    let (w, h) = cap.dims();
    let params = PsParams {
        initial_distance_mm: sim.initial_distance_mm,
        support_r: r,
        tolerance: 0.0,
        ..PsParams::default()
    };
    let layout = params.kernel_layout().unwrap();
    let plane: Vec<f32> = vec![sim.initial_distance_mm as f32; w * h];
    let mut shapes = vec![
        (
            "sphere".to_string(),
            sim.gt_depth_mm.clone(),
            sim.gt_normals.clone(),
        ),
        ("plane".to_string(), plane, vec![[0.0f32, 0.0, -1.0]; w * h]),
    ];
    for its in [1, 2] {
        let out = photometric_stereo(
            cap,
            &PsParams {
                max_iterations: its,
                ..params.clone()
            },
            &Monitor::noop(),
        )
        .unwrap();
        let n = normals_from_depth(&cap.intrinsics, w, h, &out.depth_mm, &cap.mask);
        shapes.push((format!("after {its} iteration(s)"), out.depth_mm, n));
    }
    for (name, depth, normals) in shapes {
        let points = back_project(&cap.intrinsics, w, &depth, &cap.mask);
        // Pixels the far cells must sum one by one (oblique view, `CELL_MIN_COS_VIEW`).
        let oblique = (0..w * h)
            .filter(|&p| {
                let (q, n) = (points[p], normals[p]);
                let d = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt();
                cap.mask[p] && -(q[0] * n[0] + q[1] * n[1] + q[2] * n[2]) / d < 0.3
            })
            .count();
        let geom = SurfaceGeometry {
            width: w,
            height: h,
            intrinsics: cap.intrinsics,
            points_mm: points,
            normals,
            mask: cap.mask.clone(),
            emission: FacetEmission::default(),
        };
        for _ in 0..2 {
            let t = std::time::Instant::now();
            let k = ForwardKernel::build_with(
                FTable::global(),
                &cap.medium,
                &geom,
                &layout,
                params.far_field,
            )
            .unwrap();
            eprintln!(
                "{name}: build {:.2} s, ε {:.3e}, oblique pixels {oblique}",
                t.elapsed().as_secs_f64(),
                k.epsilon()
            );
        }
    }
}
