//! `murk health`: asks a server's `grpc.health.v1` service whether it serves, for container
//! HEALTHCHECKs and scripts. Exit status 0 when SERVING, 1 otherwise (not serving, draining,
//! unreachable, or no answer within the timeout).

use std::time::Duration;

use anyhow::{bail, Context};
use clap::Args;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_health::pb::HealthCheckRequest;

use super::client::channel;

/// Health probe arguments.
#[derive(Args, Debug)]
pub struct HealthArgs {
    /// Server URL (`https://…` uses TLS with `MURK_TLS_CA`).
    #[arg(long, env = "MURK_SERVER", default_value = "http://127.0.0.1:50051")]
    pub server: String,
    /// Service to ask about; empty = the server as a whole (NOT_SERVING while it drains).
    #[arg(long, default_value = "")]
    pub service: String,
    /// Give up after this many seconds.
    #[arg(long, default_value_t = 3.0)]
    pub timeout_secs: f64,
}

/// Runs the probe; an error (exit status 1) unless the server answers SERVING.
pub fn run(a: HealthArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        a.timeout_secs.is_finite() && a.timeout_secs > 0.0,
        "--timeout-secs must be positive"
    );
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    let status = rt.block_on(async {
        let probe = async {
            let ch = channel(&a.server).await?;
            let reply = HealthClient::new(ch)
                .check(HealthCheckRequest {
                    service: a.service.clone(),
                })
                .await
                .context("health check")?;
            anyhow::Ok(reply.into_inner().status())
        };
        tokio::time::timeout(Duration::from_secs_f64(a.timeout_secs), probe)
            .await
            .context("no answer in time")?
    })?;
    if status != ServingStatus::Serving {
        bail!("{} is {}", a.server, status.as_str_name());
    }
    println!("SERVING");
    Ok(())
}
