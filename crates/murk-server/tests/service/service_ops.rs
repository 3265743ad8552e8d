//! The server as a fleet operator runs it: bearer tokens and tenants, TLS and mutual TLS,
//! Prometheus metrics, retries after deadlines, results larger than a default client's 4 MiB
//! receive limit, draining on shutdown, cancellation of photometric stereo, and requests that
//! are not protobuf at all. Every test talks to a real in-process server over loopback.

use crate::common;

use std::time::{Duration, Instant};

use common::pki::{pki, Pki};
use common::*;
use murk_server::server::{InProcessServer, ServerConfig, TlsSettings};
use murk_server::service::auth::TokenStore;
use murk_server::service::proto::v1 as pb;
use murk_server::service::{CacheScope, JOB_ID_HEADER};
use pb::jobs_client::JobsClient;
use pb::reconstruction_client::ReconstructionClient;
use tonic::metadata::MetadataValue;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint, Identity};
use tonic::Code;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_health::pb::HealthCheckRequest;
use tonic_types::StatusExt;

const ALPHA: &str = "alpha-token-0123456789";
const BETA: &str = "beta-token-9876543210";

fn authed_config(queue: usize) -> ServerConfig {
    ServerConfig {
        auth: Some(
            TokenStore::from_text(&format!("# test tenants\nalpha {ALPHA}\nbeta {BETA}\n"))
                .unwrap(),
        ),
        ..config(queue)
    }
}

fn with_token<T>(msg: T, token: &str) -> tonic::Request<T> {
    let mut r = tonic::Request::new(msg);
    r.metadata_mut().insert(
        "authorization",
        MetadataValue::try_from(format!("Bearer {token}")).unwrap(),
    );
    r
}

/// A Jobs client left at tonic's defaults: 4 MiB receive limit, like any other gRPC client.
fn default_jobs(server: &InProcessServer) -> JobsClient<Channel> {
    JobsClient::new(channel(server))
}

async fn health(server: &InProcessServer, service: &str) -> ServingStatus {
    HealthClient::new(channel(server))
        .check(HealthCheckRequest {
            service: service.into(),
        })
        .await
        .expect("health check")
        .into_inner()
        .status()
}

/// The job id a unary call's response (or error) carries in its metadata.
fn job_id(metadata: &tonic::metadata::MetadataMap) -> String {
    metadata
        .get(JOB_ID_HEADER)
        .expect("job id header")
        .to_str()
        .unwrap()
        .to_string()
}

#[tokio::test]
async fn tokens_are_required_except_for_health_and_reflection() {
    let server = start(authed_config(4)).await;
    let mut c = jobs(&server);
    let list = || pb::ListJobsRequest::default();
    let none = c.list_jobs(list()).await.unwrap_err();
    assert_eq!(none.code(), Code::Unauthenticated, "{none:?}");
    assert!(none.message().contains("authorization"), "{none:?}");
    let wrong = c
        .list_jobs(with_token(list(), "alpha-token-012345678X"))
        .await
        .unwrap_err();
    assert_eq!(wrong.code(), Code::Unauthenticated, "{wrong:?}");
    let mut basic = tonic::Request::new(list());
    basic.metadata_mut().insert(
        "authorization",
        MetadataValue::from_static("Basic YWxwaGE="),
    );
    assert_eq!(
        c.list_jobs(basic).await.unwrap_err().code(),
        Code::Unauthenticated
    );
    let unary = recon(&server)
        .tof_depth(tof_request(32, 24, 1))
        .await
        .unwrap_err();
    assert_eq!(unary.code(), Code::Unauthenticated);
    assert!(c.list_jobs(with_token(list(), ALPHA)).await.is_ok());
    // Probes and discovery stay open.
    assert_eq!(health(&server, "").await, ServingStatus::Serving);
    assert_eq!(
        health(&server, "murk.v1.Jobs").await,
        ServingStatus::Serving
    );
    assert_eq!(
        server.manager().executed(),
        0,
        "nothing ran for refused calls"
    );
    server.stop().await.unwrap();
}

#[tokio::test]
async fn jobs_are_invisible_to_other_tenants_and_a_global_cache_shares_results() {
    let server = start(ServerConfig {
        cache_scope: Some(CacheScope::Global),
        ..authed_config(4)
    })
    .await;
    let mut c = jobs(&server);
    let submitted = c
        .submit_job(with_token(job(tof_request(48, 36, 2)), ALPHA))
        .await
        .unwrap()
        .into_inner();
    let id = submitted.id.clone();
    let mut watch = c
        .watch_job(with_token(
            pb::WatchJobRequest {
                id: id.clone(),
                omit_result: true,
            },
            ALPHA,
        ))
        .await
        .unwrap()
        .into_inner();
    while watch.message().await.unwrap().is_some() {}

    let get = |token| {
        with_token(
            pb::GetJobRequest {
                id: id.clone(),
                omit_result: true,
            },
            token,
        )
    };
    assert!(c.get_job(get(ALPHA)).await.is_ok());
    assert_eq!(
        c.get_job(get(BETA)).await.unwrap_err().code(),
        Code::NotFound
    );
    let watch_beta = c
        .watch_job(with_token(
            pb::WatchJobRequest {
                id: id.clone(),
                omit_result: true,
            },
            BETA,
        ))
        .await;
    assert_eq!(watch_beta.unwrap_err().code(), Code::NotFound);
    let cancel_beta = c
        .cancel_job(with_token(pb::CancelJobRequest { id: id.clone() }, BETA))
        .await;
    assert_eq!(cancel_beta.unwrap_err().code(), Code::NotFound);
    let result_beta = c
        .get_job_result(with_token(
            pb::GetJobResultRequest {
                id: id.clone(),
                chunk_bytes: 0,
            },
            BETA,
        ))
        .await;
    assert_eq!(result_beta.unwrap_err().code(), Code::NotFound);
    let server = &server;
    let listed = |token| async move {
        jobs(server)
            .list_jobs(with_token(pb::ListJobsRequest::default(), token))
            .await
            .unwrap()
            .into_inner()
            .jobs
    };
    assert_eq!(listed(ALPHA).await.len(), 1);
    assert!(
        listed(BETA).await.is_empty(),
        "beta lists only its own jobs"
    );

    // beta's identical work is served from the shared result, in a record of beta's own.
    let again = c
        .submit_job(with_token(job(tof_request(48, 36, 2)), BETA))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(again.id, id);
    assert!(again.cached);
    assert_eq!(listed(BETA).await.len(), 1);
    assert_eq!(server.manager().executed(), 1);
}

#[tokio::test]
async fn with_authentication_a_tenant_cannot_learn_that_another_ran_the_same_input() {
    // The default cache scope with tokens: per tenant.
    let server = start(authed_config(4)).await;
    let mut c = jobs(&server);
    let client = c.clone();
    let submit = |token| {
        let mut c = client.clone();
        async move {
            let j = c
                .submit_job(with_token(job(tof_request(48, 36, 2)), token))
                .await
                .unwrap()
                .into_inner();
            (j.id.clone(), j.cached, j.state)
        }
    };
    let (alpha_id, cached, _) = submit(ALPHA).await;
    assert!(!cached);
    let mut watch = c
        .watch_job(with_token(
            pb::WatchJobRequest {
                id: alpha_id.clone(),
                omit_result: true,
            },
            ALPHA,
        ))
        .await
        .unwrap()
        .into_inner();
    while watch.message().await.unwrap().is_some() {}
    // Alpha's own repeat is a cache hit.
    let (again, cached, _) = submit(ALPHA).await;
    assert_eq!(again, alpha_id);
    assert!(cached);
    // Beta's identical request is a job of beta's own: another id, queued, computed afresh,
    // exactly as for an input nobody ran.
    let (beta_id, cached, state) = submit(BETA).await;
    assert_ne!(beta_id, alpha_id);
    assert!(!cached);
    assert_ne!(state, pb::JobState::Succeeded as i32);
    let mut watch = c
        .watch_job(with_token(
            pb::WatchJobRequest {
                id: beta_id.clone(),
                omit_result: true,
            },
            BETA,
        ))
        .await
        .unwrap()
        .into_inner();
    while watch.message().await.unwrap().is_some() {}
    assert_eq!(server.manager().executed(), 2);
    server.stop().await.unwrap();
}

/// A throw-away CA, a server certificate for `localhost` and a client certificate.
async fn tls_channel(
    server: &InProcessServer,
    pki: &Pki,
    client_identity: bool,
) -> Result<Channel, tonic::transport::Error> {
    let mut tls = ClientTlsConfig::new()
        .ca_certificate(Certificate::from_pem(&pki.ca_pem))
        .domain_name("localhost");
    if client_identity {
        tls = tls.identity(Identity::from_pem(&pki.client_cert, &pki.client_key));
    }
    Endpoint::from_shared(format!("https://localhost:{}", server.addr().port()))?
        .tls_config(tls)?
        .connect()
        .await
}

#[tokio::test]
async fn tls_round_trip_and_mutual_tls_refuses_clients_without_a_certificate() {
    let pki = pki();
    let tls = |mutual: bool| TlsSettings {
        cert_pem: pki.server_cert.clone().into_bytes(),
        key_pem: pki.server_key.clone().into_bytes(),
        client_ca_pem: mutual.then(|| pki.ca_pem.clone().into_bytes()),
    };
    let server = start(ServerConfig {
        tls: Some(tls(false)),
        ..config(4)
    })
    .await;
    let ch = tls_channel(&server, &pki, false)
        .await
        .expect("TLS connect");
    let result = ReconstructionClient::new(ch)
        .tof_depth(tof_request(32, 24, 3))
        .await
        .expect("a result over TLS")
        .into_inner();
    assert_eq!(result.range_m.expect("range").width, 32);
    // A plaintext client cannot talk to a TLS server.
    let plain = JobsClient::new(channel(&server))
        .list_jobs(pb::ListJobsRequest::default())
        .await;
    assert!(plain.is_err());
    server.stop().await.unwrap();

    let server = start(ServerConfig {
        tls: Some(tls(true)),
        ..config(4)
    })
    .await;
    let with_cert = tls_channel(&server, &pki, true)
        .await
        .expect("mTLS connect");
    assert!(JobsClient::new(with_cert)
        .list_jobs(pb::ListJobsRequest::default())
        .await
        .is_ok());
    // Without a client certificate the handshake (or the first call) fails.
    let refused = match tls_channel(&server, &pki, false).await {
        Err(_) => true,
        Ok(ch) => JobsClient::new(ch)
            .list_jobs(pb::ListJobsRequest::default())
            .await
            .is_err(),
    };
    assert!(refused, "a client without a certificate must be refused");
    server.stop().await.unwrap();
}

#[tokio::test]
async fn metrics_scrape_reports_queue_jobs_cache_and_rpcs() {
    let server = start(authed_config(4)).await;
    let mut c = recon(&server);
    c.tof_depth(with_token(tof_request(32, 24, 4), ALPHA))
        .await
        .unwrap();
    c.tof_depth(with_token(tof_request(32, 24, 4), ALPHA))
        .await
        .unwrap(); // a cache hit
    let _ = c.tof_depth(tof_request(32, 24, 4)).await; // refused: no token
    let text = scrape(server.metrics_addr()).await;
    for name in [
        "murk_queue_depth",
        "murk_jobs_running",
        "murk_jobs_total{",
        "murk_job_duration_seconds_bucket{",
        "murk_queue_wait_seconds_bucket{",
        "murk_cache_hits_total",
        "murk_cache_misses_total",
        "murk_cache_bytes",
        "murk_grpc_requests_total{",
    ] {
        assert!(text.contains(name), "{name} missing from:\n{text}");
    }
    assert!(
        text.contains(r#"murk_jobs_total{method="tof_depth",state="succeeded"} 1"#),
        "{text}"
    );
    assert!(
        text.contains(
            r#"murk_grpc_requests_total{method="murk.v1.Reconstruction/TofDepth",code="OK"} 2"#
        ),
        "{text}"
    );
    assert!(
        text.contains(r#"murk_grpc_requests_total{method="murk.v1.Reconstruction/TofDepth",code="UNAUTHENTICATED"} 1"#),
        "{text}"
    );
    assert!(text.contains("murk_cache_hits_total 1"), "{text}");
    server.stop().await.unwrap();
}

#[tokio::test]
async fn a_retry_after_the_deadline_computes_afresh_and_succeeds() {
    let server = start(config(4)).await;
    let mut c = recon(&server);
    let req = long_tof_request(400);
    let mut first = tonic::Request::new(req.clone());
    first.set_timeout(Duration::from_millis(100));
    let err = c.tof_depth(first).await.unwrap_err();
    assert!(
        matches!(err.code(), Code::DeadlineExceeded | Code::Cancelled),
        "{err:?}"
    );
    // Right away, while the abandoned job may still be stopping: the retry must not attach to
    // it and inherit its cancellation.
    let mut retry = tonic::Request::new(req);
    retry.set_timeout(Duration::from_secs(120));
    let ok = c.tof_depth(retry).await.expect("the retry succeeds");
    let id = job_id(ok.metadata());
    assert_eq!(id.len(), 64, "a content hash");
    let job = jobs(&server)
        .get_job(pb::GetJobRequest {
            id,
            omit_result: true,
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(job.state, pb::JobState::Succeeded as i32);
    server.stop().await.unwrap();
}

#[tokio::test]
async fn a_512x424_tof_result_reaches_a_client_left_at_the_4_mib_default() {
    use prost::Message;
    let server = start(config(4)).await;
    let mut c = default_jobs(&server);
    let submitted = c
        .submit_job(job(tof_request(512, 424, 5)))
        .await
        .expect("submit")
        .into_inner();
    let id = submitted.id.clone();
    let mut watch = c
        .watch_job(pb::WatchJobRequest {
            id: id.clone(),
            omit_result: false,
        })
        .await
        .expect("watch")
        .into_inner();
    let mut last = None;
    while let Some(j) = watch.message().await.expect("watch stream within 4 MiB") {
        last = Some(j);
    }
    let last = last.unwrap();
    assert_eq!(last.state, pb::JobState::Succeeded as i32);
    assert!(
        last.result_omitted,
        "the result exceeds 4 MiB and is left out"
    );
    assert!(
        last.result_size_bytes > 4 << 20,
        "{}",
        last.result_size_bytes
    );
    let got = c
        .get_job(pb::GetJobRequest {
            id: id.clone(),
            omit_result: false,
        })
        .await
        .expect("GetJob within 4 MiB")
        .into_inner();
    assert!(got.result_omitted);
    let cached = c
        .submit_job(job(tof_request(512, 424, 5)))
        .await
        .expect("cache-hit SubmitJob within 4 MiB")
        .into_inner();
    assert!(cached.cached && cached.result_omitted);

    let mut stream = c
        .get_job_result(pb::GetJobResultRequest {
            id: id.clone(),
            chunk_bytes: 0,
        })
        .await
        .unwrap()
        .into_inner();
    let mut bytes = Vec::new();
    let mut chunks = 0;
    while let Some(chunk) = stream.message().await.expect("chunk") {
        assert_eq!(chunk.offset as usize, bytes.len());
        assert!(chunk.data.len() <= 1 << 20);
        assert_eq!(chunk.total_bytes, last.result_size_bytes);
        bytes.extend_from_slice(&chunk.data);
        chunks += 1;
    }
    assert_eq!(bytes.len() as u64, last.result_size_bytes);
    assert!(chunks >= 5, "{chunks} chunks");
    let result = pb::JobResult::decode(bytes.as_slice()).expect("reassembled result decodes");
    let Some(pb::job_result::Method::TofDepth(tof)) = result.method else {
        panic!("a ToF result");
    };
    let range = tof.range_m.expect("range");
    assert_eq!((range.width, range.height), (512, 424));

    // The unary RPC says where to go instead of sending what the client cannot receive.
    let unary = ReconstructionClient::new(channel(&server))
        .tof_depth(tof_request(512, 424, 5))
        .await
        .unwrap_err();
    assert_eq!(unary.code(), Code::FailedPrecondition, "{unary:?}");
    assert!(unary.message().contains("GetJobResult"), "{unary:?}");
    assert_eq!(job_id(unary.metadata()), id);
    server.stop().await.unwrap();
}

#[tokio::test]
async fn draining_turns_overall_health_not_serving_and_aborted_jobs_say_resubmit() {
    let mut server = start(ServerConfig {
        shutdown_grace: Duration::from_secs(2),
        ..config(4)
    })
    .await;
    let mut c = jobs(&server);
    let long = c
        .submit_job(job(long_tof_request(10_000)))
        .await
        .unwrap()
        .into_inner();
    let mut watch = c
        .watch_job(pb::WatchJobRequest {
            id: long.id.clone(),
            omit_result: true,
        })
        .await
        .unwrap()
        .into_inner();
    // Wait until it runs.
    while let Some(j) = watch.message().await.unwrap() {
        if j.state == pb::JobState::Running as i32 {
            break;
        }
    }
    server.begin_shutdown();
    let deadline = Instant::now() + Duration::from_secs(2);
    let mut status = health(&server, "").await;
    while status != ServingStatus::NotServing && Instant::now() < deadline {
        tokio::task::yield_now().await;
        status = health(&server, "").await;
    }
    assert_eq!(status, ServingStatus::NotServing, "\"\" while draining");
    // The job outlives the grace period and is stopped by the server. It is not over (a
    // restart with a journal resumes it), so the watcher never gets a terminal message: the
    // stream ends with a retryable UNAVAILABLE that says to watch again or resubmit.
    let end = loop {
        match watch.message().await {
            Ok(Some(j)) => assert!(
                j.state == pb::JobState::Running as i32,
                "an interrupted job is never shown as ended: {j:?}"
            ),
            Ok(None) => panic!("the stream ended without saying the job was interrupted"),
            Err(status) => break status,
        }
    };
    assert_eq!(end.code(), Code::Unavailable, "{end:?}");
    assert!(end.message().contains("interrupted"), "{end:?}");
    assert!(end.message().contains("resubmit"), "{end:?}");
    assert!(
        end.get_details_retry_info().is_some(),
        "UNAVAILABLE with RetryInfo: {end:?}"
    );
    server.stop().await.unwrap();
}

#[tokio::test]
async fn a_job_interrupted_by_shutdown_resumes_after_the_restart_and_was_never_shown_ended() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = config(4);
    cfg.jobs.cache_dir = Some(dir.path().to_path_buf());
    cfg.shutdown_grace = Duration::ZERO;
    // Long enough to be running when the shutdown comes, short enough to finish after it.
    let req = job(long_tof_request(40));

    let mut a = start(cfg.clone()).await;
    let mut c = jobs(&a);
    let id = c.submit_job(req).await.unwrap().into_inner().id;
    let mut stream = watch(&mut c, &id).await;
    while let Some(j) = stream.message().await.unwrap() {
        if j.state == pb::JobState::Running as i32 {
            break;
        }
    }
    a.begin_shutdown();
    let end = loop {
        match stream.message().await {
            Ok(Some(j)) => assert!(!is_terminal(&j), "shown as ended: {j:?}"),
            Ok(None) => panic!("the stream ended without a status"),
            Err(status) => break status,
        }
    };
    assert_eq!(end.code(), Code::Unavailable, "{end:?}");
    a.stop().await.unwrap();

    // The journal runs it again; watching it anew shows it succeed.
    let b = start(cfg).await;
    let mut c = jobs(&b);
    let seen = watch_to_end(&mut c, &id).await;
    assert_eq!(state(seen.last().unwrap()), pb::JobState::Succeeded);
    assert_eq!(b.manager().executed(), 1);
    b.stop().await.unwrap();
}

#[tokio::test]
async fn result_chunks_below_16_kib_are_refused_naming_chunk_bytes() {
    let server = start(config(4)).await;
    let mut c = jobs(&server);
    let id = c
        .submit_job(job(tof_request(96, 80, 3)))
        .await
        .unwrap()
        .into_inner()
        .id;
    watch_to_end(&mut c, &id).await;
    let fetch = |chunk_bytes| {
        let mut c = c.clone();
        let id = id.clone();
        async move {
            let mut stream = c
                .get_job_result(pb::GetJobResultRequest { id, chunk_bytes })
                .await?
                .into_inner();
            let mut sizes = Vec::new();
            while let Some(chunk) = stream.message().await? {
                sizes.push(chunk.data.len());
            }
            Ok::<_, tonic::Status>(sizes)
        }
    };
    for tiny in [1, 4096, 16383] {
        let err = fetch(tiny).await.unwrap_err();
        assert_eq!(err.code(), Code::InvalidArgument, "{err:?}");
        assert_eq!(bad_field(&err), "chunk_bytes");
    }
    let sizes = fetch(16 << 10).await.unwrap();
    assert!(sizes.len() > 1, "{sizes:?}");
    assert!(sizes.iter().all(|&n| n <= 16 << 10), "{sizes:?}");
    let whole: usize = fetch(0).await.unwrap().iter().sum();
    assert_eq!(whole, sizes.iter().sum::<usize>());
    server.stop().await.unwrap();
}

fn is_terminal(j: &pb::Job) -> bool {
    [
        pb::JobState::Succeeded as i32,
        pb::JobState::Failed as i32,
        pb::JobState::Cancelled as i32,
    ]
    .contains(&j.state)
}

#[tokio::test]
async fn bytes_that_are_not_protobuf_get_invalid_argument() {
    let server = start(config(4)).await;
    let mut grpc = tonic::client::Grpc::new(channel(&server));
    grpc.ready().await.unwrap();
    // Field 1 announced as length-delimited with a length far past the end.
    let garbage = vec![0x0a, 0xff, 0xff, 0xff, 0x0f, 0x01];
    let err = grpc
        .unary(
            tonic::Request::new(garbage),
            http::uri::PathAndQuery::from_static("/murk.v1.Jobs/SubmitJob"),
            RawCodec,
        )
        .await
        .unwrap_err();
    assert_eq!(err.code(), Code::InvalidArgument, "{err:?}");
    assert_eq!(server.manager().executed(), 0);
    server.stop().await.unwrap();
}

#[tokio::test]
async fn reflection_resolves_the_google_rpc_error_details() {
    use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
    use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
    use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;
    use tonic_reflection::pb::v1::ServerReflectionRequest;
    let server = start(config(4)).await;
    let mut refl = ServerReflectionClient::new(channel(&server));
    for symbol in [
        "google.rpc.BadRequest",
        "google.rpc.RetryInfo",
        "google.rpc.PreconditionFailure",
    ] {
        let req = ServerReflectionRequest {
            host: String::new(),
            message_request: Some(MessageRequest::FileContainingSymbol(symbol.into())),
        };
        let resp = refl
            .server_reflection_info(futures::stream::iter([req]))
            .await
            .unwrap()
            .into_inner()
            .message()
            .await
            .unwrap()
            .expect("a response");
        assert!(
            matches!(
                resp.message_response,
                Some(MessageResponse::FileDescriptorResponse(_))
            ),
            "{symbol}: {:?}",
            resp.message_response
        );
    }
    server.stop().await.unwrap();
}

/// The f32 samples of a raw single-channel image message.
fn raw_samples(img: &pb::Image) -> Vec<f32> {
    let Some(pb::image::Data::RawF32Le(bytes)) = &img.data else {
        panic!("raw image expected");
    };
    bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}

#[tokio::test]
async fn mono_inputs_as_equal_colour_channels_or_float32_tiff_are_accepted() {
    let server = start(config(4)).await;
    let mut c = recon(&server);
    let reference = c
        .tof_depth(tof_request(32, 24, 6))
        .await
        .unwrap()
        .into_inner();

    let mut req = tof_request(32, 24, 6);
    // Amplitude as three equal planes (raw is planar: all of R, then G, then B).
    let amp = req.amplitude.as_mut().unwrap();
    let a = raw_samples(amp);
    amp.channels = 3;
    amp.data = Some(pb::image::Data::RawF32Le(
        a.iter()
            .chain(&a)
            .chain(&a)
            .flat_map(|v| v.to_le_bytes())
            .collect(),
    ));
    // Phase as a greyscale float32 TIFF, the usual layout of phase and depth maps.
    let ph = req.phase.as_mut().unwrap();
    let p = raw_samples(ph);
    let mut tif = std::io::Cursor::new(Vec::new());
    tiff::encoder::TiffEncoder::new(&mut tif)
        .unwrap()
        .write_image::<tiff::encoder::colortype::Gray32Float>(32, 24, &p)
        .unwrap();
    ph.data = Some(pb::image::Data::Encoded(tif.into_inner()));
    let same = c
        .tof_depth(req.clone())
        .await
        .expect("accepted")
        .into_inner();
    assert_eq!(same.range_m, reference.range_m, "same input, same depth");

    // Colour channels that differ are refused, naming the field.
    let amp = req.amplitude.as_mut().unwrap();
    let mut planes: Vec<f32> = a.iter().chain(&a).chain(&a).copied().collect();
    planes[a.len() + 5] += 0.25;
    amp.data = Some(pb::image::Data::RawF32Le(
        planes.iter().flat_map(|v| v.to_le_bytes()).collect(),
    ));
    let e = c.tof_depth(req).await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().contains("amplitude"), "{e:?}");
    server.stop().await.unwrap();
}

#[tokio::test]
async fn a_cache_file_swapped_under_another_job_id_is_not_served() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = config(4);
    cfg.jobs.cache_dir = Some(dir.path().to_path_buf());
    let (ra, rb) = (tof_request(40, 30, 7), tof_request(40, 30, 8));
    let a = start(cfg.clone()).await;
    let mut c = recon(&a);
    let res_a = c.tof_depth(ra).await.unwrap();
    let id_a = job_id(res_a.metadata());
    let res_b = c.tof_depth(rb.clone()).await.unwrap();
    let id_b = job_id(res_b.metadata());
    a.stop().await.unwrap();
    // An operator (or an attacker with file access) copies A's entry over B's.
    std::fs::copy(
        dir.path().join(format!("{id_a}.murkres")),
        dir.path().join(format!("{id_b}.murkres")),
    )
    .unwrap();

    let b = start(cfg).await;
    let again = recon(&b).tof_depth(rb).await.unwrap().into_inner();
    assert_eq!(
        again.range_m,
        res_b.into_inner().range_m,
        "B's own result, not A's"
    );
    assert_eq!(
        b.manager().executed(),
        1,
        "B was recomputed, not served from A's file"
    );
    assert!(b.manager().cache_stats().disk_rejected >= 1);
    b.stop().await.unwrap();
}

#[tokio::test]
async fn compressed_requests_and_responses_round_trip() {
    use tonic::codec::CompressionEncoding;
    let server = start(config(4)).await;
    let plain = recon(&server)
        .tof_depth(tof_request(32, 24, 12))
        .await
        .unwrap()
        .into_inner();
    for enc in [CompressionEncoding::Gzip, CompressionEncoding::Zstd] {
        let mut c = ReconstructionClient::new(channel(&server))
            .send_compressed(enc)
            .accept_compressed(enc);
        let r = c
            .tof_depth(tof_request(32, 24, 12))
            .await
            .expect("compressed call");
        let encoding = r
            .metadata()
            .get("grpc-encoding")
            .map(|v| v.to_str().unwrap().to_string());
        assert_eq!(
            encoding.as_deref(),
            Some(enc.to_string().as_str()),
            "{enc:?}"
        );
        assert_eq!(r.into_inner().range_m, plain.range_m);
    }
    server.stop().await.unwrap();
}

#[tokio::test]
async fn watch_streams_are_bounded_per_job_and_a_spent_budget_omits_the_result() {
    use murk_server::service::watchers::WatchLimits;
    let server = start(ServerConfig {
        watchers: WatchLimits {
            max_per_job: 2,
            max_per_tenant: 8,
            // Less than one 96×80 ToF result.
            result_budget_bytes: 16 * 1024,
        },
        ..config(4)
    })
    .await;
    let mut c = jobs(&server);
    // Not waited for through a watch stream, so no earlier stream can still count.
    let long = c
        .submit_job(job(long_tof_request(10_000)))
        .await
        .unwrap()
        .into_inner()
        .id;
    let first = watch(&mut c, &long).await;
    let _second = watch(&mut c, &long).await;
    let third = c
        .watch_job(pb::WatchJobRequest {
            id: long.clone(),
            omit_result: true,
        })
        .await
        .unwrap_err();
    assert_eq!(third.code(), Code::ResourceExhausted, "{third:?}");
    assert!(
        third.message().contains("--max-watchers-per-job"),
        "{third:?}"
    );
    assert!(third.get_details_retry_info().is_some());
    // A stream the client drops frees its slot (once the server has seen it go).
    drop(first);
    let deadline = Instant::now() + Duration::from_secs(10);
    let reopened = loop {
        match c
            .watch_job(pb::WatchJobRequest {
                id: long.clone(),
                omit_result: true,
            })
            .await
        {
            Ok(s) => break s,
            Err(e) if e.code() == Code::ResourceExhausted && Instant::now() < deadline => {
                tokio::task::yield_now().await
            }
            Err(e) => panic!("the dropped stream's slot was not freed: {e:?}"),
        }
    };
    drop(reopened);
    c.cancel_job(pb::CancelJobRequest { id: long })
        .await
        .unwrap();

    // A finished result larger than the whole budget goes out omitted; GetJobResult has it.
    let id = c
        .submit_job(job(tof_request(96, 80, 3)))
        .await
        .unwrap()
        .into_inner()
        .id;
    let mut stream = c
        .watch_job(pb::WatchJobRequest {
            id: id.clone(),
            omit_result: false,
        })
        .await
        .unwrap()
        .into_inner();
    let mut last = None;
    while let Some(j) = stream.message().await.unwrap() {
        last = Some(j);
    }
    let last = last.unwrap();
    assert_eq!(state(&last), pb::JobState::Succeeded);
    assert!(
        last.result_omitted && last.result_size_bytes > 16 * 1024,
        "{last:?}"
    );
    let mut chunks = c
        .get_job_result(pb::GetJobResultRequest { id, chunk_bytes: 0 })
        .await
        .unwrap()
        .into_inner();
    let mut total = 0;
    while let Some(chunk) = chunks.message().await.unwrap() {
        total += chunk.data.len() as u64;
    }
    assert_eq!(total, last.result_size_bytes);
    server.stop().await.unwrap();
}
