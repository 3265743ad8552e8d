//! `murk demo`: the main job on the embedded default. Starts a server in-process on an ephemeral
//! port, simulates one foggy ToF scene per fog preset, one hazy multi-view scene and one
//! photometric-stereo capture in turbid water, runs each
//! through the gRPC API exactly as a remote client would, writes the outputs and prints accuracy
//! tables.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context};
use clap::Args;

use murk::atmosphere::AtmosphereParams;
use murk::metrics::{depth_metrics, mask_iou, mean_abs_error};
use murk::mvs::{PlaneSet, View};
use murk::params::search::plane_range_from_sparse;
use murk::params::sparse::{selected_points, PointSelection, SparseDepth};
use murk::ps::{PsMode, PsParams};
use murk::simulate::mvs::{simulate_mvs, write_mvs_scene, MvsSimConfig};
use murk::simulate::ps::{simulate_ps, write_ps_capture, PsSimConfig};
use murk::simulate::tof::{simulate_tof, FogPreset, TofSimConfig};
use murk::simulate::write_tof_frame;
use murk::Monitor;
use murk_server::server::{InProcessServer, ServerConfig};
use murk_server::service::convert::{
    mvs_request_to_proto, params_request_to_proto, tof_request_to_proto,
};
use murk_server::service::convert::{ps_from_result, ps_request_to_proto};
use murk_server::service::proto::v1 as pb;

use super::client::{connect, run_job};
use super::mvs::{print_metrics_header, print_metrics_row, write_mvs_result};
use super::params::source_name;
use super::ps::{print_iteration_table, write_ps_result};
use super::tof::write_tof_result;

/// The MVS scene of the demo: the reference's evaluation size (256×192), 5 views (the reference
/// and 4 sources), 256 planes over the simulated room's depth range (z 1.5…15, as in
/// docs/accuracy.md).
const MVS_SIZE: (usize, usize) = (256, 192);
/// Planes of the MVS depth; their range comes from the scene's SfM points.
const MVS_PLANES: usize = 256;

/// The photometric-stereo scene of the demo: the reference's sphere setting (§4.4.4: β = σ =
/// 5e-3 /mm, 8 lights, initialised as a plane) at half its 300×300 size so the demo stays
/// quick, with the kernel support scaled alike (81 → 41).
const PS_SIZE: usize = 150;
/// Kernel support of the demo's photometric stereo.
const PS_SUPPORT: usize = 41;

/// Options of `murk demo`.
#[derive(Args, Debug)]
pub struct DemoArgs {
    /// Output folder.
    #[arg(long, default_value = "demo-out")]
    pub out: PathBuf,
    /// Scene seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Image width (the Kinect v2's 512 by default).
    #[arg(long, default_value_t = 512)]
    pub width: usize,
    /// Image height (424 by default).
    #[arg(long, default_value_t = 424)]
    pub height: usize,
}

/// One row of the printed table.
struct Row {
    preset: FogPreset,
    raw_err_m: f64,
    err_m: f64,
    iou: f64,
    seconds: f64,
    cached: bool,
}

/// Runs the demo.
pub fn run(a: DemoArgs) -> anyhow::Result<()> {
    let rt = tokio::runtime::Runtime::new()?;
    rt.block_on(async move {
        let server = InProcessServer::start(ServerConfig::default()).await?;
        println!(
            "murk demo: server on {} ({} worker threads); outputs in {}",
            server.addr(),
            server.manager().worker_threads(),
            a.out.display()
        );
        let mut client = connect(&server.url()).await?;
        let mut rows = Vec::new();
        for preset in [FogPreset::Thin, FogPreset::Medium, FogPreset::Thick] {
            let cfg = TofSimConfig {
                preset,
                seed: a.seed,
                ..TofSimConfig::with_size(a.width, a.height)
            };
            let frame = tokio::task::spawn_blocking(move || simulate_tof(&cfg, &Monitor::noop()))
                .await??;
            let dir = a.out.join(format!("tof-{preset}"));
            write_tof_frame(&dir.join("input"), &frame)
                .with_context(|| format!("writing {}", dir.display()))?;
            let request = tof_request_to_proto(
                &frame.amplitude,
                &frame.phase,
                Some(&frame.intrinsics),
                frame.config.modulation_frequency_hz,
                Some(frame.config.light_position_m()),
            );
            let t0 = Instant::now();
            let (job, result) = run_job(
                &mut client,
                pb::JobRequest {
                    method: Some(pb::job_request::Method::TofDepth(request)),
                },
                &format!("tof/{preset}"),
                true,
            )
            .await?;
            let seconds = t0.elapsed().as_secs_f64();
            let Some(pb::job_result::Method::TofDepth(r)) = result.method else {
                bail!("unexpected result kind");
            };
            let out = write_tof_result(&dir.join("output"), &r)?
                .context("the result lacks the range, the raw range or the mask")?;
            let gt_mask = Some(&frame.gt_mask);
            rows.push(Row {
                preset,
                raw_err_m: mean_abs_error(&out.raw_range_m, &frame.gt_range_m, gt_mask)?,
                err_m: mean_abs_error(&out.range_m, &frame.gt_range_m, gt_mask)?,
                iou: mask_iou(&out.mask, &frame.gt_mask)?,
                seconds,
                cached: job.cached,
            });
        }
        println!();
        println!(
            "ToF depth in fog, {}x{}, seed {} (errors: mean |range − GT| inside the GT object mask)",
            a.width, a.height, a.seed
        );
        println!(
            "{:<8} {:>12} {:>14} {:>9} {:>9} {:>9}",
            "fog", "raw err [m]", "murk err [m]", "improve", "mask IoU", "time [s]"
        );
        for r in &rows {
            println!(
                "{:<8} {:>12.4} {:>14.4} {:>8.1}x {:>9.3} {:>9.2}{}",
                r.preset.to_string(),
                r.raw_err_m,
                r.err_m,
                r.raw_err_m / r.err_m.max(1e-12),
                r.iou,
                r.seconds,
                if r.cached { " (cached)" } else { "" }
            );
        }
        mvs_demo(&a, &mut client).await?;
        ps_demo(&a, &mut client).await?;
        server.stop().await?;
        Ok(())
    })
}

/// Simulates one hazy multi-view scene (β ∈ [0.4, 0.8] per scene unit, the reference's setting),
/// estimates A and β through the API (Algorithm 1 against the scene's SfM points), then runs
/// the MVS depth with the ordinary cost volume, the dehazing one with the estimated parameters,
/// and the dehazing one with the ground truth, printing the reference's depth metrics.
async fn mvs_demo(a: &DemoArgs, client: &mut super::client::Client) -> anyhow::Result<()> {
    let cfg = MvsSimConfig {
        seed: a.seed,
        beta_range: Some([0.4, 0.8]),
        ..MvsSimConfig::with_size(MVS_SIZE.0, MVS_SIZE.1)
    };
    let scene = tokio::task::spawn_blocking(move || simulate_mvs(&cfg, &Monitor::noop())).await??;
    let dir = a.out.join("mvs");
    write_mvs_scene(&dir.join("input"), &scene)
        .with_context(|| format!("writing {}", dir.display()))?;
    let views: Vec<View<'_>> = scene.hazy_views();
    let reference = views
        .get(scene.reference)
        .context("simulated scene has no reference view")?;
    let sources: Vec<View<'_>> = views
        .iter()
        .enumerate()
        .filter(|(i, _)| *i != scene.reference)
        .map(|(_, v)| *v)
        .collect();
    let gt = &scene.views[scene.reference].depth;
    let ref_name = &scene.views[scene.reference].name;
    let points = selected_points(&scene.sparse, ref_name, PointSelection::ObservedInReference)?;
    let sparse = SparseDepth::from_points(
        &points,
        &reference.intrinsics,
        &reference.pose,
        reference.image.width(),
        reference.image.height(),
    )?;
    let (near, far) = plane_range_from_sparse(&sparse).context("no SfM point in the reference")?;
    let planes = PlaneSet::new(near, far, MVS_PLANES)?;

    // Scattering parameters first, as a user without ground truth would.
    let mut request = params_request_to_proto(
        reference,
        &sources,
        &points,
        pb::AirlightSource::Unspecified,
        0.0,
    );
    request.num_planes = MVS_PLANES as u32;
    let t0 = Instant::now();
    let (job, result) = run_job(
        client,
        pb::JobRequest {
            method: Some(pb::job_request::Method::ScatteringParams(request)),
        },
        "params",
        true,
    )
    .await?;
    let params_seconds = t0.elapsed().as_secs_f64();
    let Some(pb::job_result::Method::ScatteringParams(p)) = result.method else {
        bail!("unexpected result kind");
    };
    let mut rows = Vec::new();
    if let Some(depth) = &p.depth {
        let out = write_mvs_result(&dir.join("estimated_params"), depth)?;
        rows.push((
            "dehazing, estimated A, beta",
            depth_metrics(&out.z_depth, gt, None)?,
            params_seconds,
            job.cached,
        ));
    }
    println!();
    println!(
        "Scattering parameters (Algorithm 1, {} SfM pixels, {} depth evaluations, {:.2} s): \
         A* = {:.3}{} (A0 = {:.3} from {}; truth {:.3}), beta* = {:.3}{}/unit from {}{}; \
         truth {:.3}",
        p.num_sparse_points,
        p.grid.len(),
        p.search_seconds,
        p.airlight,
        p.airlight_std_error
            .map_or(String::new(), |e| format!(" ± {e:.3}")),
        p.airlight_initial,
        source_name(p.airlight_source),
        scene.airlight,
        p.beta,
        p.beta_std_error
            .map_or(String::new(), |e| format!(" ± {e:.3}")),
        match pb::BetaSource::try_from(p.beta_source) {
            Ok(pb::BetaSource::JointFit) => {
                let eqs = p.joint_fit.as_ref().map_or(0, |j| j.equations);
                format!("the joint fit of A, beta and gains to the SfM points ({eqs} equations)")
            }
            Ok(pb::BetaSource::PointRatio) => "the SfM points' transmission ratios".to_string(),
            _ => "the Eq. 3.10 sweep".to_string(),
        },
        if p.identifiable {
            ""
        } else {
            " (NOT identifiable from these views: a guess)"
        },
        scene.beta
    );
    let atmosphere = AtmosphereParams {
        airlight: scene.airlight,
        beta: scene.beta,
    };
    for (name, kind) in [
        ("ordinary", pb::CostVolumeKind::Ordinary),
        ("dehazing, true A, beta", pb::CostVolumeKind::Dehazing),
    ] {
        let request =
            mvs_request_to_proto(reference, &sources, kind, Some(atmosphere), Some(&planes));
        let t0 = Instant::now();
        let (job, result) = run_job(
            client,
            pb::JobRequest {
                method: Some(pb::job_request::Method::MvsDepth(request)),
            },
            &format!("mvs/{name}"),
            true,
        )
        .await?;
        let seconds = t0.elapsed().as_secs_f64();
        let Some(pb::job_result::Method::MvsDepth(r)) = result.method else {
            bail!("unexpected result kind");
        };
        let folder = if name == "ordinary" {
            "ordinary"
        } else {
            "true_params"
        };
        let out = write_mvs_result(&dir.join(folder), &r)?;
        rows.push((
            name,
            depth_metrics(&out.z_depth, gt, None)?,
            seconds,
            job.cached,
        ));
    }
    println!();
    println!(
        "MVS depth in haze, {}x{}, {} sources, {} planes (z {:.3}..{:.3}), seed {}: A = {:.3}, \
         beta = {:.4}/unit (ground truth), median transmission {:.2}; the first row's time \
         includes the parameter search",
        MVS_SIZE.0,
        MVS_SIZE.1,
        sources.len(),
        planes.num_planes,
        planes.near,
        planes.far,
        a.seed,
        scene.airlight,
        scene.beta,
        scene.median_transmission
    );
    print_metrics_header();
    for (name, m, seconds, cached) in &rows {
        print_metrics_row(name, m, *seconds, if *cached { " (cached)" } else { "" });
    }
    Ok(())
}

/// Simulates the reference's synthetic sphere in turbid water and runs photometric stereo
/// through the API with the full model and with the backscatter-only baseline, printing the
/// per-iteration mean angular error (the reference's Table 4.1).
async fn ps_demo(a: &DemoArgs, client: &mut super::client::Client) -> anyhow::Result<()> {
    let cfg = PsSimConfig {
        seed: a.seed,
        ..PsSimConfig::with_size(PS_SIZE, PS_SIZE)
    };
    let t0 = Instant::now();
    let sim = tokio::task::spawn_blocking(move || simulate_ps(&cfg, &Monitor::noop())).await??;
    let sim_seconds = t0.elapsed().as_secs_f64();
    let dir = a.out.join("ps-sphere");
    write_ps_capture(&dir.join("input"), &sim)
        .with_context(|| format!("writing {}", dir.display()))?;
    for (mode, name) in [
        (PsMode::Full, "full model"),
        (PsMode::BackscatterOnly, "backscatter only [15]"),
    ] {
        let params = PsParams {
            initial_distance_mm: sim.initial_distance_mm,
            support_r: PS_SUPPORT,
            tolerance: 0.0,
            mode,
            ..PsParams::default()
        };
        let mut request = ps_request_to_proto(&sim.capture, &params);
        request.return_iteration_normals = true;
        let (job, result) = run_job(
            client,
            pb::JobRequest {
                method: Some(pb::job_request::Method::PhotometricStereo(request)),
            },
            &format!(
                "ps/{}",
                if mode == PsMode::Full {
                    "full"
                } else {
                    "baseline"
                }
            ),
            true,
        )
        .await?;
        let Some(pb::job_result::Method::PhotometricStereo(r)) = result.method else {
            bail!("unexpected result kind");
        };
        let out = ps_from_result(&r, &sim.capture.mask)?;
        let folder = if mode == PsMode::Full {
            "full"
        } else {
            "backscatter_only"
        };
        write_ps_result(&dir.join(folder), &sim.capture.intrinsics, &out)?;
        println!();
        println!(
            "Photometric stereo in turbid water, {name}: sphere {PS_SIZE}x{PS_SIZE}, beta = sigma \
             = {:.0e}/mm, {} lights, r = {PS_SUPPORT}, initial plane at {:.0} mm, seed {} \
             (simulated in {sim_seconds:.1} s){}",
            sim.config.beta_per_mm,
            sim.capture.lights.len(),
            sim.initial_distance_mm,
            a.seed,
            if job.cached { "; cached" } else { "" }
        );
        print_iteration_table(&out, Some(&sim.gt_normals));
    }
    Ok(())
}
