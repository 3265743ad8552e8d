//! `murk demo`: the main job on the embedded default. Starts a server in-process on an ephemeral
//! port, simulates one foggy ToF scene per fog preset, runs each through the gRPC API exactly as
//! a remote client would, writes the outputs and prints an accuracy table.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context};
use clap::Args;

use murk::metrics::{mask_iou, mean_abs_error};
use murk::server::{InProcessServer, ServerConfig};
use murk::service::convert::tof_request_to_proto;
use murk::service::proto::v1 as pb;
use murk::simulate::tof::{simulate_tof, FogPreset, TofSimConfig};
use murk::simulate::write_tof_frame;
use murk::Monitor;

use super::client::{connect, run_job};
use super::tof::write_tof_result;

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
            let out = write_tof_result(&dir.join("output"), &r)?;
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
        server.stop().await?;
        Ok(())
    })
}
