//! A ToF stream computed frame by frame from scratch against the same stream through
//! [`TofTracker`] (each frame from the previous one's answer): time per frame and the mean range
//! error on the lit object pixels, frame by frame, on a simulated sequence with moving objects,
//! drifting fog and scene cuts.
//!
//! ```sh
//! cargo run --release -p murk --example tof_stream_survey -- --frames 30 --cut-every 15
//! cargo run --release -p murk --example tof_stream_survey -- --frames 8 --fps 1 --fog-drift 0.9
//! cargo run --release -p murk --example tof_stream_survey -- --frames 12 --preset thick \
//!     --scatter-grid 1
//! ```
//!
//! The stream's tracker solves its warm frames' scatter on K×K block means, `--scatter-grid K`
//! (`TofTracker::with_scatter_grid`; cold and restarted frames solve only their coarse level
//! there, judged at full size), 2 by default as in a session; both columns are scored by their
//! range. With `--cold-on-grid`, the stream instead hands the tracker the block means
//! themselves, so every frame, the cold ones included, runs wholly on the grid; both columns are then scored by subtracting a scatter phasor
//! from the full frame: the from-scratch estimate's own, and the stream's interpolated back
//! (bilinear). Neither fills unmeasured outline pixels.

mod common;

use std::time::Instant;

use clap::Parser;

use common::{mean, range_error, Phasor, Table};
use murk::simulate::tof::FogPreset;
use murk::simulate::{simulate_tof_sequence_frame, SceneLayout, TofMotion, TofSimConfig};
use murk::tof::{estimate_tof_depth, TofInput, TofOutput, TofParams, TofStart, TofTracker};
use murk::Monitor;

/// Cold against warm-started frames of one simulated stream.
#[derive(Parser, Debug)]
struct Args {
    /// Frames in the stream.
    #[arg(long, default_value_t = 30)]
    frames: usize,
    /// Seed of the first scene.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// A scene cut every this many frames.
    #[arg(long)]
    cut_every: Option<usize>,
    /// Frame width.
    #[arg(long, default_value_t = 512)]
    width: usize,
    /// Frame height.
    #[arg(long, default_value_t = 424)]
    height: usize,
    /// Object placement: separated, cluttered or obstacles.
    #[arg(long, default_value = "separated")]
    layout: String,
    /// Camera frame rate, Hz (how far things move between frames).
    #[arg(long, default_value_t = 10.0)]
    fps: f64,
    /// Relative amplitude of the fog's drift in beta (a 10 s sine), in [0, 0.9].
    #[arg(long, default_value_t = 0.1)]
    fog_drift: f64,
    /// Fastest an object moves, metres per second.
    #[arg(long, default_value_t = 0.3)]
    max_speed_m_per_s: f64,
    /// Solve the warm frames' scatter on a grid this many times coarser than the frames (see
    /// the module documentation), as a session does by default; 1: the frames themselves.
    #[arg(long, default_value_t = 2)]
    scatter_grid: usize,
    /// With `--scatter-grid`: every frame on the grid, cold ones included (see the module
    /// documentation).
    #[arg(long)]
    cold_on_grid: bool,
    /// Fog preset: thin, medium or thick.
    #[arg(long, default_value = "medium")]
    preset: FogPreset,
}

/// What a streamed frame is scored by.
enum Streamed {
    /// Its result, by its range.
    Output(Box<TofOutput>),
    /// A scatter phasor at the frame's size, subtracted from the observation.
    Scatter(Phasor),
}

/// Mean |range − truth| on the lit object pixels, millimetres; NaN when none is in view.
fn error_mm(out: &TofOutput, truth: &murk::ImageF32, mask: &murk::ImageF32) -> f64 {
    let (mut sum, mut n) = (0.0, 0usize);
    for ((&r, &t), &m) in out.range_m.data().iter().zip(truth.data()).zip(mask.data()) {
        if m > 0.5 {
            sum += (f64::from(r) - f64::from(t)).abs();
            n += 1;
        }
    }
    if n == 0 {
        return f64::NAN;
    }
    1e3 * sum / n as f64
}

fn main() -> anyhow::Result<()> {
    let a = Args::parse();
    let grid = a.scatter_grid;
    if grid == 0 || a.width % grid != 0 || a.height % grid != 0 {
        anyhow::bail!("--scatter-grid must be at least 1 and divide the frame's sides");
    }
    let layout: SceneLayout = a.layout.parse()?;
    if a.cold_on_grid && grid == 1 {
        anyhow::bail!("--cold-on-grid needs --scatter-grid 2 or more");
    }
    let cfg = TofSimConfig {
        seed: a.seed,
        layout,
        preset: a.preset,
        ..TofSimConfig::with_size(a.width, a.height)
    };
    let motion = TofMotion {
        frame_rate_hz: a.fps,
        cut_every: a.cut_every,
        fog_drift: a.fog_drift,
        max_speed_m_per_s: a.max_speed_m_per_s,
        ..TofMotion::default()
    };
    let params = TofParams {
        light_position_m: Some(cfg.light_position_m()),
        ..TofParams::default()
    };
    let monitor = Monitor::noop();
    let mut tracker = if a.cold_on_grid {
        TofTracker::new(params.clone())
    } else {
        TofTracker::with_scatter_grid(params.clone(), grid)?
    };
    let mut table = Table::new(&[
        "frame",
        "start",
        "cold s",
        "stream s",
        "cold mm",
        "stream mm",
        "ratio",
    ]);
    let (mut cold_s, mut warm_s, mut ratios) = (Vec::new(), Vec::new(), Vec::new());
    for k in 0..a.frames {
        let f = simulate_tof_sequence_frame(&cfg, &motion, k, &monitor)?;
        let input = TofInput {
            amplitude: f.amplitude.clone(),
            phase: f.phase.clone(),
            intrinsics: Some(f.intrinsics),
        };
        let observed = Phasor::from_polar(&f.amplitude, &f.phase);
        let t = Instant::now();
        let cold = estimate_tof_depth(&input, &params, &monitor)?;
        let tc = t.elapsed().as_secs_f64();
        let t = Instant::now();
        // The stream's frame: its start, and what it is scored by.
        let (label, streamed) = if !a.cold_on_grid {
            let tracked = tracker.estimate(&input, &monitor)?;
            (tracked.start, Streamed::Output(Box::new(tracked.output)))
        } else {
            let (amplitude, phase) = observed.block_means(grid)?.to_polar();
            let coarse = TofInput {
                amplitude,
                phase,
                intrinsics: Some(f.intrinsics.box_downsampled(grid)),
            };
            let tracked = tracker.estimate(&coarse, &monitor)?;
            let output = tracked.output;
            let scatter = Phasor::from_polar(&output.scatter_amplitude, &output.scatter_phase)
                .upsampled(grid)?;
            (tracked.start, Streamed::Scatter(scatter))
        };
        let tw = t.elapsed().as_secs_f64();
        let (ec, ew) = match &streamed {
            Streamed::Output(output) => (
                error_mm(&cold, &f.gt_range_m, &f.gt_mask),
                error_mm(output, &f.gt_range_m, &f.gt_mask),
            ),
            Streamed::Scatter(scatter) => {
                let own = Phasor::from_polar(&cold.scatter_amplitude, &cold.scatter_phase);
                (
                    range_error(&f, &observed, &own) * 1e3,
                    range_error(&f, &observed, scatter) * 1e3,
                )
            }
        };
        cold_s.push(tc);
        warm_s.push(tw);
        // Frames with no object in view have no error to compare.
        if ec.is_finite() && ew.is_finite() {
            ratios.push(ew / ec.max(1e-9));
        }
        let start = match label {
            TofStart::Cold => "cold",
            TofStart::Warm => "warm",
            TofStart::Restarted => "restarted",
        };
        let cut = if motion.is_cut(k) { " (cut)" } else { "" };
        table.row(&[
            format!("{k}{cut}"),
            start.to_string(),
            format!("{tc:.3}"),
            format!("{tw:.3}"),
            format!("{ec:.1}"),
            format!("{ew:.1}"),
            format!("{:.3}", ew / ec.max(1e-9)),
        ]);
    }
    table.print();
    let worst = ratios.iter().copied().fold(0.0, f64::max);
    println!(
        "\n{} frames {}x{} (scatter grid 1/{grid}): from scratch {:.3} s a frame, streamed {:.3} s ({:.2}x); stream \
         error / from-scratch error over the {} frames with objects in view: mean {:.3}, worst \
         {:.3}",
        a.frames,
        a.width,
        a.height,
        mean(&cold_s),
        mean(&warm_s),
        mean(&cold_s) / mean(&warm_s),
        ratios.len(),
        mean(&ratios),
        worst
    );
    Ok(())
}
