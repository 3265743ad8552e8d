//! Command-line interface. Every flag that configures the server is also an environment variable.

mod client;
mod demo;
mod mvs;
mod params;
mod ps;
mod serve;
mod simulate;
mod tof;
mod train;

use clap::{Parser, Subcommand};
use tracing_subscriber::EnvFilter;

/// murk — 3D shape and depth through fog, smoke and turbid water.
#[derive(Parser, Debug)]
#[command(name = "murk", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
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
    /// Airlight and scattering coefficient (Algorithm 1) from a COLMAP model + images, then
    /// the depth with them.
    Params(params::ParamsArgs),
    /// Photometric stereo in turbid water: per-light images with and without the object →
    /// normals, albedo, depth and a mesh.
    Ps(ps::PsArgs),
    /// Start a server in-process, run simulated scenes through the gRPC API, print accuracy.
    Demo(demo::DemoArgs),
    /// Train a learned estimator on simulated scenes (e.g. the airlight CNN).
    #[command(subcommand)]
    Train(train::TrainCommand),
}

/// Parses the command line and runs the chosen command.
pub fn run() -> anyhow::Result<()> {
    let cli = Cli::parse();
    // The server logs every job; the client commands only warnings, so progress bars and
    // result tables stay readable.
    let default_level = match cli.command {
        Command::Serve(_) => "info",
        _ => "warn",
    };
    tracing_subscriber::fmt()
        .with_env_filter(
            EnvFilter::try_from_env("MURK_LOG").unwrap_or_else(|_| EnvFilter::new(default_level)),
        )
        .with_writer(std::io::stderr)
        .init();
    match cli.command {
        Command::Serve(a) => serve::run(a),
        Command::Simulate(c) => simulate::run(c),
        Command::Tof(a) => tof::run(a),
        Command::Mvs(a) => mvs::run(a),
        Command::Params(a) => params::run(a),
        Command::Ps(a) => ps::run(a),
        Command::Demo(a) => demo::run(a),
        Command::Train(c) => train::run(c),
    }
}
