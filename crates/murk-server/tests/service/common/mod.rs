//! Shared fixtures for the integration tests: an in-process server on 127.0.0.1:0 and clients
//! generated from the proto files.

#![allow(dead_code)]

pub mod nginx;
pub mod pki;
pub mod redis_server;

mod serve;

use std::sync::LazyLock;
use std::time::Duration;

use murk::atmosphere::AtmosphereParams;
use murk::mvs::{PlaneSet, View};
use murk::simulate::mvs::{simulate_mvs, MvsScene, MvsSimConfig};
use murk::simulate::tof::{simulate_tof, TofSimConfig};
use murk::Monitor;
use murk_server::jobs::JobsConfig;
use murk_server::server::{InProcessServer, ServerConfig};
use murk_server::service::convert::{mvs_request_to_proto, simulated_tof_request};
use murk_server::service::proto::v1 as pb;
use pb::jobs_client::JobsClient;
use pb::reconstruction_client::ReconstructionClient;
use tonic::transport::{Channel, Endpoint};

pub use serve::spawn_serve;

/// A small server: 2 workers, one job at a time.
pub fn config(queue: usize) -> ServerConfig {
    ServerConfig {
        jobs: JobsConfig {
            workers: 2,
            concurrent_jobs: 1,
            queue_capacity: queue,
            retry_after: Duration::from_millis(1500),
            ..JobsConfig::default()
        },
        shutdown_grace: Duration::from_millis(200),
        ..ServerConfig::default()
    }
}

pub async fn start(cfg: ServerConfig) -> InProcessServer {
    InProcessServer::start(cfg).await.expect("server starts")
}

pub fn channel(server: &InProcessServer) -> Channel {
    Endpoint::from_shared(server.url())
        .expect("url")
        .connect_lazy()
}

pub fn jobs(server: &InProcessServer) -> JobsClient<Channel> {
    JobsClient::new(channel(server))
        .max_decoding_message_size(usize::MAX)
        .max_encoding_message_size(usize::MAX)
}

pub fn recon(server: &InProcessServer) -> ReconstructionClient<Channel> {
    ReconstructionClient::new(channel(server))
        .max_decoding_message_size(usize::MAX)
        .max_encoding_message_size(usize::MAX)
}

/// A simulated medium-fog ToF request of `width × height`.
pub fn tof_request(width: usize, height: usize, seed: u64) -> pb::TofDepthRequest {
    let cfg = TofSimConfig {
        seed,
        ..TofSimConfig::with_size(width, height)
    };
    let frame = simulate_tof(&cfg, &Monitor::noop()).expect("simulate");
    simulated_tof_request(&frame, &cfg)
}

/// The frame of [`long_tof_request`], rendered once per test process: a debug build takes
/// seconds to render it, which every test that submits a long job would otherwise pay again.
static LONG_TOF_FRAME: LazyLock<pb::TofDepthRequest> = LazyLock::new(|| tof_request(256, 212, 7));

/// A request that runs for a long time (thousands of fine iterations, early stopping off)
/// unless cancelled.
pub fn long_tof_request(fine_iterations: u32) -> pb::TofDepthRequest {
    let mut r = LONG_TOF_FRAME.clone();
    r.options = Some(pb::TofOptions {
        fine_iterations: Some(fine_iterations),
        convergence_tolerance: Some(0.0),
        ..Default::default()
    });
    r
}

pub fn job(req: pb::TofDepthRequest) -> pb::SubmitJobRequest {
    pb::SubmitJobRequest {
        request: Some(pb::JobRequest {
            method: Some(pb::job_request::Method::TofDepth(req)),
        }),
        omit_result: false,
    }
}

/// A simulated hazy multi-view scene of `width × height`: 5 views along a line, the reference in
/// the middle, ground-truth depth, A and β.
pub fn mvs_scene(width: usize, height: usize, seed: u64) -> MvsScene {
    let cfg = MvsSimConfig {
        seed,
        ..MvsSimConfig::with_size(width, height)
    };
    simulate_mvs(&cfg, &Monitor::noop()).expect("simulate mvs")
}

/// A request for `scene`'s reference view against all its other (hazy) views, with the
/// ground-truth A and β and the given planes.
pub fn mvs_request(
    scene: &MvsScene,
    kind: pb::CostVolumeKind,
    planes: &PlaneSet,
) -> pb::MvsDepthRequest {
    let views: Vec<View<'_>> = scene.hazy_views();
    let sources: Vec<View<'_>> = (0..views.len())
        .filter(|&i| i != scene.reference)
        .map(|i| views[i])
        .collect();
    let atmosphere = AtmosphereParams {
        airlight: scene.airlight,
        beta: scene.beta,
    };
    mvs_request_to_proto(
        &views[scene.reference],
        &sources,
        kind,
        Some(atmosphere),
        Some(planes),
    )
}

pub fn mvs_job(req: pb::MvsDepthRequest) -> pb::SubmitJobRequest {
    pb::SubmitJobRequest {
        request: Some(pb::JobRequest {
            method: Some(pb::job_request::Method::MvsDepth(req)),
        }),
        omit_result: false,
    }
}

pub fn state(j: &pb::Job) -> pb::JobState {
    pb::JobState::try_from(j.state).unwrap_or(pb::JobState::Unspecified)
}

/// Opens the job's watch stream (without results).
pub async fn watch(client: &mut JobsClient<Channel>, id: &str) -> tonic::codec::Streaming<pb::Job> {
    client
        .watch_job(pb::WatchJobRequest {
            id: id.to_string(),
            omit_result: true,
        })
        .await
        .expect("watch")
        .into_inner()
}

/// Follows the watch stream until a terminal state; returns every message seen.
pub async fn watch_to_end(client: &mut JobsClient<Channel>, id: &str) -> Vec<pb::Job> {
    let mut stream = watch(client, id).await;
    let mut seen = Vec::new();
    while let Some(j) = stream.message().await.expect("stream") {
        seen.push(j);
    }
    seen
}

/// Waits (via the watch stream, no polling) until the job is RUNNING.
pub async fn wait_running(client: &mut JobsClient<Channel>, id: &str) {
    let mut stream = watch(client, id).await;
    while let Some(j) = stream.message().await.expect("stream") {
        match state(&j) {
            pb::JobState::Running => return,
            pb::JobState::Queued => continue,
            other => panic!("job ended before running: {other:?}"),
        }
    }
    panic!("stream ended before the job ran");
}

/// The field named by an INVALID_ARGUMENT status's google.rpc.BadRequest detail.
pub fn bad_field(s: &tonic::Status) -> String {
    use tonic_types::StatusExt;
    assert_eq!(
        s.code(),
        tonic::Code::InvalidArgument,
        "expected INVALID_ARGUMENT, got {s:?}"
    );
    let d = s.get_error_details();
    let field = d
        .bad_request()
        .and_then(|b| b.field_violations.first())
        .map(|v| v.field.clone())
        .unwrap_or_default();
    assert!(
        s.message().contains(&field),
        "message should name the field: {}",
        s.message()
    );
    field
}

/// Submits a long job (see [`long_tof_request`]) and returns its id once it is RUNNING.
pub async fn submit_running_long_job(client: &mut JobsClient<Channel>) -> String {
    // Built off the runtime's thread: on a test's single-threaded runtime, seconds of rendering
    // there would keep the connected client from sending its HTTP/2 preface, and the server
    // closes a connection that stays silent past its handshake timeout.
    let request = tokio::task::spawn_blocking(|| job(long_tof_request(10_000)))
        .await
        .expect("the long request is built");
    let j = client
        .submit_job(request)
        .await
        .expect("submit")
        .into_inner();
    wait_running(client, &j.id).await;
    j.id
}

/// `GET /metrics` over a raw HTTP/1.1 connection to a metrics endpoint.
pub async fn scrape(addr: std::net::SocketAddr) -> String {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    s.write_all(b"GET /metrics HTTP/1.1\r\nHost: murk\r\nConnection: close\r\n\r\n")
        .await
        .unwrap();
    let mut out = String::new();
    tokio::time::timeout(Duration::from_secs(10), s.read_to_string(&mut out))
        .await
        .expect("scrape answered")
        .unwrap();
    assert!(out.starts_with("HTTP/1.1 200"), "{out}");
    out
}

/// The value of one sample (`name{labels}` exactly as exposed), 0 when absent.
pub fn sample(text: &str, series: &str) -> f64 {
    text.lines()
        .find_map(|l| l.strip_prefix(series)?.trim().parse().ok())
        .unwrap_or(0.0)
}

/// `name` on the PATH or in one of `extra` directories (e.g. /usr/sbin, which a non-root PATH
/// may lack), for the tests that need an external server.
pub fn find_binary(name: &str, extra: &[&str]) -> Option<std::path::PathBuf> {
    let mut dirs: Vec<std::path::PathBuf> = std::env::var_os("PATH")
        .map(|p| std::env::split_paths(&p).collect())
        .unwrap_or_default();
    dirs.extend(extra.iter().map(std::path::PathBuf::from));
    dirs.into_iter().map(|d| d.join(name)).find(|p| p.is_file())
}

/// Codec that sends raw bytes, to put something that is not protobuf on the wire.
#[derive(Default, Clone)]
pub struct RawCodec;

impl tonic::codec::Codec for RawCodec {
    type Encode = Vec<u8>;
    type Decode = Vec<u8>;
    type Encoder = RawCodec;
    type Decoder = RawCodec;
    fn encoder(&mut self) -> Self::Encoder {
        RawCodec
    }
    fn decoder(&mut self) -> Self::Decoder {
        RawCodec
    }
}

impl tonic::codec::Encoder for RawCodec {
    type Item = Vec<u8>;
    type Error = tonic::Status;
    fn encode(
        &mut self,
        item: Vec<u8>,
        dst: &mut tonic::codec::EncodeBuf<'_>,
    ) -> Result<(), tonic::Status> {
        use bytes::BufMut;
        dst.put_slice(&item);
        Ok(())
    }
}

impl tonic::codec::Decoder for RawCodec {
    type Item = Vec<u8>;
    type Error = tonic::Status;
    fn decode(
        &mut self,
        src: &mut tonic::codec::DecodeBuf<'_>,
    ) -> Result<Option<Vec<u8>>, tonic::Status> {
        use bytes::Buf;
        let mut v = vec![0; src.remaining()];
        src.copy_to_slice(&mut v);
        Ok(Some(v))
    }
}
