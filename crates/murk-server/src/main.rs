//! `murk`: the server, a client for each method, the simulator and an end-to-end demo.

mod cli;

fn main() -> anyhow::Result<()> {
    cli::run()
}
