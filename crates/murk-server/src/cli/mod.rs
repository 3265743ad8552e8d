//! Command-line interface. Every flag that configures the server is also an environment variable.

mod bag;
mod client;
mod demo;
mod health;
mod mvs;
mod outputs;
mod params;
mod ps;
mod serve;
mod session;
mod simulate;
mod stereo;
mod tof;
mod train;

use std::io::IsTerminal;

use anyhow::Context;
use clap::{Parser, Subcommand};
use tracing_subscriber::EnvFilter;

/// murk — 3D shape and depth through fog, smoke and turbid water.
#[derive(Parser, Debug)]
#[command(name = "murk", version, about)]
struct Cli {
    /// Log line format on stderr: `text` (ANSI colours only on a terminal) or `json` (one
    /// object per line, for log collectors). Levels come from `MURK_LOG` (tracing filter syntax,
    /// e.g. `info` or `murk=debug,h2=warn`).
    #[arg(long, global = true, env = "MURK_LOG_FORMAT", value_enum, default_value_t = LogFormat::Text)]
    log_format: LogFormat,
    #[command(subcommand)]
    command: Command,
}

/// See `--log-format`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum LogFormat {
    Text,
    Json,
}

/// Each source's corner brightness relative to the reference's (`1 + δ` for its relative
/// fall-off δ), as "[0.750, 1.000]"; `None` when no source has one (all δ exactly 0).
fn source_corners(falloffs: impl IntoIterator<Item = f64> + Clone) -> Option<String> {
    falloffs.clone().into_iter().any(|d| d != 0.0).then(|| {
        let d: Vec<String> = falloffs
            .into_iter()
            .map(|d| format!("{:.3}", 1.0 + d))
            .collect();
        format!("[{}]", d.join(", "))
    })
}

/// The log filter from `MURK_LOG` (or `default_level` when unset). A value that is not a
/// filter is an error naming the problem rather than a silently empty log: `EnvFilter` would
/// read a bare word such as `json` as "only the target `json`" and drop every murk line.
fn log_filter(value: Option<&str>, default_level: &str) -> anyhow::Result<EnvFilter> {
    let Some(v) = value.filter(|v| !v.trim().is_empty()) else {
        return Ok(EnvFilter::new(default_level));
    };
    const LEVELS: [&str; 6] = ["trace", "debug", "info", "warn", "error", "off"];
    for directive in v.split(',').map(str::trim).filter(|d| !d.is_empty()) {
        let bare = !directive.contains('=') && !directive.contains('[');
        let word = directive.to_ascii_lowercase();
        if bare && !LEVELS.contains(&word.as_str()) && !directive.contains("::") {
            anyhow::bail!(
                "MURK_LOG={v:?}: directive `{directive}` is neither a level ({}) nor \
                 `target=level`{}",
                LEVELS.join(", "),
                if matches!(word.as_str(), "json" | "text") {
                    "; the log format is chosen with --log-format / MURK_LOG_FORMAT"
                } else {
                    ""
                }
            );
        }
    }
    EnvFilter::try_new(v).with_context(|| format!("MURK_LOG={v:?} is not a valid log filter"))
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run the gRPC server.
    Serve(serve::ServeArgs),
    /// Synthesise scenes with ground truth.
    #[command(subcommand)]
    Simulate(simulate::SimulateCommand),
    /// ToF depth in fog: send amplitude + phase to a server, write depth, mask and scatter.
    Tof(tof::TofArgs),
    /// MVS depth in haze: COLMAP model + images → depth, confidence and a point cloud.
    Mvs(mvs::MvsArgs),
    /// Rectified stereo in haze: left + right images, intrinsics and baseline → depth,
    /// disparity, confidence and a point cloud.
    Stereo(stereo::StereoArgs),
    /// Airlight and scattering coefficient (Algorithm 1) from a COLMAP model + images, then
    /// the depth with them.
    Params(params::ParamsArgs),
    /// A ROS 2 bag (MCAP) of stereo pairs or ToF frames through a sensor session; the results
    /// (depth, confidence or mask, disparity, point clouds, CameraInfo) to a new MCAP file.
    Bag(bag::BagArgs),
    /// Photometric stereo in turbid water: per-light images with and without the object →
    /// normals, albedo, depth and a mesh.
    Ps(ps::PsArgs),
    /// Start a server in-process, run simulated scenes through the gRPC API, print accuracy.
    Demo(demo::DemoArgs),
    /// Train a learned estimator on simulated scenes (e.g. the airlight CNN).
    #[command(subcommand)]
    Train(train::TrainCommand),
    /// Ask a server whether it serves (grpc.health.v1): exit 0 if SERVING, 1 otherwise. For
    /// container health checks.
    Health(health::HealthArgs),
}

/// Parses the command line and runs the chosen command.
pub fn run() -> anyhow::Result<()> {
    // Before any other thread allocates: frames then reuse their buffers' pages.
    let allocator = murk_server::allocator::keep_working_set();
    let cli = Cli::parse();
    // The server logs every job; the client commands only warnings, so progress bars and
    // result tables stay readable.
    let default_level = match cli.command {
        Command::Serve(_) => "info",
        _ => "warn",
    };
    let filter = log_filter(std::env::var("MURK_LOG").ok().as_deref(), default_level)?;
    let logs = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    match cli.log_format {
        LogFormat::Json => logs.json().with_current_span(true).init(),
        LogFormat::Text => logs.with_ansi(std::io::stderr().is_terminal()).init(),
    }
    tracing::debug!(?allocator, "allocator thresholds");
    match cli.command {
        Command::Serve(a) => serve::run(a),
        Command::Simulate(c) => simulate::run(c),
        Command::Tof(a) => tof::run(a),
        Command::Mvs(a) => mvs::run(a),
        Command::Stereo(a) => stereo::run(a),
        Command::Params(a) => params::run(a),
        Command::Bag(a) => bag::run(a),
        Command::Ps(a) => ps::run(a),
        Command::Demo(a) => demo::run(a),
        Command::Train(c) => train::run(c),
        Command::Health(a) => health::run(a),
    }
}

#[cfg(test)]
mod tests {
    use super::{log_filter, source_corners};

    #[test]
    fn source_corners_print_only_a_fall_off_that_was_applied() {
        assert_eq!(source_corners([0.0, 0.0]), None);
        assert_eq!(
            source_corners([-0.25, 0.0]).as_deref(),
            Some("[0.750, 1.000]")
        );
    }

    #[test]
    fn log_filters_are_checked() {
        assert!(log_filter(None, "info").is_ok());
        assert!(log_filter(Some("debug"), "info").is_ok());
        assert!(log_filter(Some("murk=debug,h2=warn"), "info").is_ok());
        assert!(log_filter(Some("murk_server::jobs"), "info").is_ok());
        let e = log_filter(Some("json"), "info").unwrap_err().to_string();
        assert!(e.contains("json") && e.contains("--log-format"), "{e}");
        assert!(log_filter(Some("murk=loud"), "info").is_err());
    }
}
