//! Client side shared by the method commands and the demo: connect, submit, follow the watch
//! stream with a progress bar, fetch the result in chunks.
//!
//! The client keeps gRPC's default 4 MiB receive limit, as a client in any other language
//! would: results come through `GetJobResult`'s 1 MiB chunks, never in one message. A server
//! that requires a bearer token gets the one in `MURK_TOKEN`.

use std::time::Duration;

use anyhow::{anyhow, bail, Context};
use indicatif::{ProgressBar, ProgressStyle};
use prost::Message;
use sha2::{Digest, Sha256};
use tonic::metadata::{Ascii, MetadataValue};
use tonic::service::interceptor::InterceptedService;
use tonic::service::Interceptor;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint, Identity};

use murk_server::service::proto::v1 as pb;
use pb::jobs_client::JobsClient;

/// Adds `authorization: Bearer TOKEN` to every call when a token is configured.
#[derive(Clone)]
pub struct BearerToken(Option<MetadataValue<Ascii>>);

impl Interceptor for BearerToken {
    fn call(&mut self, mut req: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
        if let Some(v) = &self.0 {
            req.metadata_mut().insert("authorization", v.clone());
        }
        Ok(req)
    }
}

/// The Jobs client of the CLI.
pub type Client = JobsClient<InterceptedService<Channel, BearerToken>>;

/// Connects to `url`, sending `MURK_TOKEN` as bearer token when set. An `https://` URL uses TLS
/// with the CA certificate(s) in the PEM file `MURK_TLS_CA` (and, for mutual TLS, the client
/// certificate and key in `MURK_TLS_CLIENT_CERT` / `MURK_TLS_CLIENT_KEY`).
pub async fn connect(url: &str) -> anyhow::Result<Client> {
    let channel = channel(url).await?;
    // Requests (megapixel image sets) may be large; responses stay within the default limit.
    Ok(
        JobsClient::with_interceptor(channel, bearer_token()?)
            .max_encoding_message_size(usize::MAX),
    )
}

/// The bearer token of `MURK_TOKEN`, when set.
pub fn bearer_token() -> anyhow::Result<BearerToken> {
    Ok(BearerToken(match std::env::var("MURK_TOKEN") {
        Ok(t) if !t.is_empty() => Some(
            format!("Bearer {t}")
                .parse()
                .context("MURK_TOKEN is not a valid header value")?,
        ),
        _ => None,
    }))
}

/// HTTP/2 receive window of each call, bytes. A streamed stereo pair's result with its point
/// cloud is about 7 MB and a ToF frame's with every image 10 MB; hyper's 2 MiB default made the
/// server stop several times within each result for the client's window updates (about 3 % of
/// `murk bag`'s CPU, a sixth of its system time). The client's own receive side only: how far a
/// client may run ahead of the server is the server's window, unchanged.
pub const RECEIVE_STREAM_WINDOW_BYTES: u32 = 16 << 20;
/// HTTP/2 receive window of the whole connection, bytes: two calls' windows.
pub const RECEIVE_CONNECTION_WINDOW_BYTES: u32 = 2 * RECEIVE_STREAM_WINDOW_BYTES;
/// The largest HTTP/2 frame the client accepts, bytes (16 KiB by default): a result arrives in
/// fewer, larger frames.
pub const RECEIVE_MAX_FRAME_BYTES: u32 = 1 << 20;

/// A channel to `url` (TLS for `https://`, see [`connect`]).
pub async fn channel(url: &str) -> anyhow::Result<Channel> {
    let mut endpoint = Endpoint::from_shared(url.to_string())
        .with_context(|| format!("bad server url {url}"))?
        .connect_timeout(Duration::from_secs(10))
        .initial_stream_window_size(RECEIVE_STREAM_WINDOW_BYTES)
        .initial_connection_window_size(RECEIVE_CONNECTION_WINDOW_BYTES)
        .max_frame_size(RECEIVE_MAX_FRAME_BYTES);
    if url.starts_with("https://") {
        let pem = |var: &str| -> anyhow::Result<Option<Vec<u8>>> {
            match std::env::var_os(var) {
                Some(p) => {
                    Ok(Some(std::fs::read(&p).with_context(|| {
                        format!("{var}={}", p.to_string_lossy())
                    })?))
                }
                None => Ok(None),
            }
        };
        let ca = pem("MURK_TLS_CA")?
            .ok_or_else(|| anyhow!("an https:// server needs MURK_TLS_CA (a PEM CA file)"))?;
        let mut tls = ClientTlsConfig::new().ca_certificate(Certificate::from_pem(ca));
        if let (Some(cert), Some(key)) = (pem("MURK_TLS_CLIENT_CERT")?, pem("MURK_TLS_CLIENT_KEY")?)
        {
            tls = tls.identity(Identity::from_pem(cert, key));
        }
        endpoint = endpoint.tls_config(tls).context("TLS configuration")?;
    }
    endpoint
        .connect()
        .await
        .with_context(|| format!("connecting to {url}"))
}

/// Fetches a succeeded job's result through `GetJobResult`, checking its length and SHA-256.
pub async fn fetch_result(client: &mut Client, id: &str) -> anyhow::Result<pb::JobResult> {
    let mut stream = client
        .get_job_result(pb::GetJobResultRequest {
            id: id.to_string(),
            chunk_bytes: 0,
        })
        .await
        .map_err(|s| {
            anyhow!(
                "fetching the result failed: {:?}: {}",
                s.code(),
                s.message()
            )
        })?
        .into_inner();
    let mut bytes = Vec::new();
    let mut expected: Option<(u64, String)> = None;
    while let Some(chunk) = stream
        .message()
        .await
        .map_err(|s| anyhow!("result stream failed: {}", s.message()))?
    {
        anyhow::ensure!(
            chunk.offset == bytes.len() as u64,
            "result chunk at offset {} where {} was expected",
            chunk.offset,
            bytes.len()
        );
        if expected.is_none() {
            bytes.reserve(chunk.total_bytes.min(1 << 32) as usize);
        }
        expected = Some((chunk.total_bytes, chunk.sha256));
        bytes.extend_from_slice(&chunk.data);
    }
    let (total, sha) = expected.ok_or_else(|| anyhow!("empty result stream"))?;
    anyhow::ensure!(
        bytes.len() as u64 == total && hex::encode(Sha256::digest(&bytes)) == sha,
        "reassembled result does not match its length or SHA-256"
    );
    pb::JobResult::decode(bytes.as_slice()).context("decoding the result")
}

/// Submits `request`, shows progress until the job is terminal, and returns the result
/// together with the final job record.
pub async fn run_job(
    client: &mut Client,
    request: pb::JobRequest,
    label: &str,
    show_progress: bool,
) -> anyhow::Result<(pb::Job, pb::JobResult)> {
    let submit = pb::SubmitJobRequest {
        request: Some(request),
        omit_result: true,
    };
    // Submitting is idempotent (a job's id is its request's content hash, and an identical
    // submission attaches to the job), so a submit whose answer was lost — the server died after
    // accepting it, or the balancer's upstream did — is sent again.
    let mut attempts = 0;
    let job = loop {
        match client.submit_job(submit.clone()).await {
            Ok(r) => break r.into_inner(),
            Err(s) if transient(&s) && attempts < SUBMIT_RETRY_LIMIT => {
                attempts += 1;
                tracing::warn!(why = %s.message(), attempts, "submit interrupted; sending it again");
                tokio::time::sleep(Duration::from_millis(250 << attempts.min(4))).await;
            }
            Err(s) => bail!("submit failed: {:?}: {}", s.code(), s.message()),
        }
    };
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
    // The job lives in the service, not in this connection: when the stream breaks (a replica
    // behind the balancer died, say) or ends early, attach to the job again; another replica
    // answers for it.
    let mut breaks = 0;
    while !is_terminal(&last) {
        let id = last.id.clone();
        let outcome = follow(client, &id, &bar, &mut last).await;
        if is_terminal(&last) {
            break;
        }
        breaks += 1;
        let why = match outcome {
            Ok(()) => "the watch ended before the job did".to_string(),
            Err(s) if transient(&s) => s.message().to_string(),
            Err(s) => bail!(
                "watching job {} failed: {:?}: {}",
                last.id,
                s.code(),
                s.message()
            ),
        };
        if breaks > WATCH_REATTACH_LIMIT {
            bail!(
                "watching job {} failed {breaks} times, last: {why}",
                last.id
            );
        }
        tracing::warn!(id = %last.id, %why, "watch interrupted; attaching to the job again");
        tokio::time::sleep(Duration::from_millis(250 << breaks.min(4))).await;
    }
    bar.finish_and_clear();
    if last.state == pb::JobState::Succeeded as i32 {
        let result = fetch_result(client, &last.id).await?;
        return Ok((last, result));
    }
    match &last.outcome {
        Some(pb::job::Outcome::Error(e)) => {
            bail!("job {} failed ({}): {}", last.id, e.code, e.message)
        }
        _ => bail!(
            "job {} ended in state {:?} without a result",
            last.id,
            pb::JobState::try_from(last.state).unwrap_or(pb::JobState::Unspecified)
        ),
    }
}

/// Times a broken watch is re-attached before giving up (≈ 30 s of back-off in all).
const WATCH_REATTACH_LIMIT: u32 = 8;

/// Times a submit that failed in transit is sent again (the same back-off as the watch's).
const SUBMIT_RETRY_LIMIT: u32 = 8;

/// Follows job `id` until its stream ends, keeping `last` at the newest update.
async fn follow(
    client: &mut Client,
    id: &str,
    bar: &ProgressBar,
    last: &mut pb::Job,
) -> Result<(), tonic::Status> {
    let mut stream = client
        .watch_job(pb::WatchJobRequest {
            id: id.to_string(),
            omit_result: true,
        })
        .await?
        .into_inner();
    while let Some(update) = stream.message().await? {
        bar.set_position((update.progress.clamp(0.0, 1.0) * 1000.0) as u64);
        bar.set_message(update.stage.clone());
        let done = is_terminal(&update);
        *last = update;
        if done {
            break;
        }
    }
    Ok(())
}

/// Failures of the connection rather than answers about the job: worth attaching again.
fn transient(s: &tonic::Status) -> bool {
    match s.code() {
        tonic::Code::Unavailable | tonic::Code::Unknown => true,
        // A stream reset by the balancer when its upstream died.
        tonic::Code::Internal => s.message().contains("h2 protocol error"),
        _ => false,
    }
}

fn is_terminal(j: &pb::Job) -> bool {
    matches!(
        pb::JobState::try_from(j.state),
        Ok(pb::JobState::Succeeded | pb::JobState::Failed | pb::JobState::Cancelled)
    )
}
