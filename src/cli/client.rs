//! Client side shared by the method commands and the demo: connect, submit, follow the watch
//! stream with a progress bar, fetch the result.

use std::time::Duration;

use anyhow::{anyhow, bail, Context};
use indicatif::{ProgressBar, ProgressStyle};
use tonic::transport::{Channel, Endpoint};

use murk::service::proto::v1 as pb;
use pb::jobs_client::JobsClient;

/// Connects to `url` with message limits large enough for megapixel results.
pub async fn connect(url: &str) -> anyhow::Result<JobsClient<Channel>> {
    let channel = Endpoint::from_shared(url.to_string())
        .with_context(|| format!("bad server url {url}"))?
        .connect_timeout(Duration::from_secs(10))
        .connect()
        .await
        .with_context(|| format!("connecting to {url}"))?;
    Ok(JobsClient::new(channel)
        .max_decoding_message_size(usize::MAX)
        .max_encoding_message_size(usize::MAX))
}

/// Submits `request`, shows progress until the job is terminal, and returns the result
/// together with the final job record.
pub async fn run_job(
    client: &mut JobsClient<Channel>,
    request: pb::JobRequest,
    label: &str,
    show_progress: bool,
) -> anyhow::Result<(pb::Job, pb::JobResult)> {
    let job = client
        .submit_job(pb::SubmitJobRequest {
            request: Some(request),
        })
        .await
        .map_err(|s| anyhow!("submit failed: {:?}: {}", s.code(), s.message()))?
        .into_inner();
    let bar = if show_progress {
        let b = ProgressBar::new(1000);
        b.set_style(
            ProgressStyle::with_template("{prefix:>12} [{bar:40}] {percent:>3}% {msg}")
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> "),
        );
        b.set_prefix(label.to_string());
        b
    } else {
        ProgressBar::hidden()
    };
    let mut last = job.clone();
    if !is_terminal(&job) {
        let mut stream = client
            .watch_job(pb::WatchJobRequest {
                id: job.id.clone(),
                omit_result: true,
            })
            .await
            .map_err(|s| anyhow!("watch failed: {}", s.message()))?
            .into_inner();
        while let Some(update) = stream
            .message()
            .await
            .map_err(|s| anyhow!("watch stream failed: {}", s.message()))?
        {
            bar.set_position((update.progress.clamp(0.0, 1.0) * 1000.0) as u64);
            bar.set_message(update.stage.clone());
            let done = is_terminal(&update);
            last = update;
            if done {
                break;
            }
        }
    }
    bar.finish_and_clear();
    let final_job = if matches!(last.outcome, Some(pb::job::Outcome::Result(_))) {
        last
    } else {
        client
            .get_job(pb::GetJobRequest {
                id: job.id.clone(),
                omit_result: false,
            })
            .await
            .map_err(|s| anyhow!("get failed: {}", s.message()))?
            .into_inner()
    };
    match &final_job.outcome {
        Some(pb::job::Outcome::Result(r)) => Ok((final_job.clone(), r.clone())),
        Some(pb::job::Outcome::Error(e)) => {
            bail!("job {} failed ({}): {}", final_job.id, e.code, e.message)
        }
        None => bail!(
            "job {} ended in state {:?} without a result",
            final_job.id,
            pb::JobState::try_from(final_job.state).unwrap_or(pb::JobState::Unspecified)
        ),
    }
}

fn is_terminal(j: &pb::Job) -> bool {
    matches!(
        pb::JobState::try_from(j.state),
        Ok(pb::JobState::Succeeded | pb::JobState::Failed | pb::JobState::Cancelled)
    )
}
