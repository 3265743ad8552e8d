//! Service overhead: a cache-hit round trip over loopback (SubmitJob of an already computed
//! request: hashing, cache lookup, result encoding, HTTP/2 transfer, client decoding), through
//! the request-metrics and request-id layers, without and with bearer-token authentication.
//!
//! Also the record log's append, fsynced and not (`record_log_append`).
//!
//! cargo bench -p murk-server --bench service

use criterion::{criterion_group, criterion_main, Criterion};
use murk::simulate::tof::{simulate_tof, TofSimConfig};
use murk::Monitor;
use murk_server::jobs::JobsConfig;
use murk_server::server::{InProcessServer, ServerConfig};
use murk_server::service::auth::TokenStore;
use murk_server::service::convert::tof_request_to_proto;
use murk_server::service::proto::v1 as pb;
use tonic::transport::Endpoint;

fn request(width: usize, height: usize) -> pb::SubmitJobRequest {
    let cfg = TofSimConfig::with_size(width, height);
    let frame = simulate_tof(&cfg, &Monitor::noop()).expect("simulate");
    let mut tof = tof_request_to_proto(
        &frame.amplitude,
        &frame.phase,
        None,
        cfg.modulation_frequency_hz,
        None,
    );
    // The result's content does not matter here, only its size.
    tof.options = Some(pb::TofOptions {
        fine_iterations: Some(5),
        ..Default::default()
    });
    pb::SubmitJobRequest {
        request: Some(pb::JobRequest {
            method: Some(pb::job_request::Method::TofDepth(tof)),
        }),
        omit_result: false,
    }
}

const TOKEN: &str = "bench-token-0123456789abcdef";

fn cache_hit_round_trip(c: &mut Criterion) {
    round_trips(c, "cache_hit_round_trip", false);
    round_trips(c, "cache_hit_round_trip_auth", true);
}

fn round_trips(c: &mut Criterion, name: &str, auth: bool) {
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let server = rt
        .block_on(InProcessServer::start(ServerConfig {
            jobs: JobsConfig {
                workers: 2,
                ..JobsConfig::default()
            },
            // The client below accepts any size: measure the full result in the response, as
            // before the unary result limit existed.
            max_unary_result_bytes: usize::MAX,
            auth: auth.then(|| {
                TokenStore::from_text(&format!("a {TOKEN}\nb other-token-0123456789\n"))
                    .expect("tokens")
            }),
            ..ServerConfig::default()
        }))
        .expect("server");
    let with_token = move |req: pb::SubmitJobRequest| {
        let mut r = tonic::Request::new(req);
        if auth {
            r.metadata_mut().insert(
                "authorization",
                format!("Bearer {TOKEN}").parse().expect("header"),
            );
        }
        r
    };
    // The lazy channel spawns its connection task on the current runtime.
    let _enter = rt.enter();
    let channel = Endpoint::from_shared(server.url())
        .expect("url")
        .connect_lazy();
    let client = pb::jobs_client::JobsClient::new(channel)
        .max_decoding_message_size(usize::MAX)
        .max_encoding_message_size(usize::MAX);

    let mut group = c.benchmark_group(name);
    group.sample_size(20);
    for (label, w, h) in [("64x53", 64, 53), ("512x424", 512, 424)] {
        let req = request(w, h);
        // Compute once so every measured call is a cache hit.
        let id = rt.block_on(async {
            let mut cl = client.clone();
            let job = cl
                .submit_job(with_token(req.clone()))
                .await
                .expect("submit")
                .into_inner();
            let mut s = cl
                .watch_job(with_token_watch(auth, job.id.clone()))
                .await
                .expect("watch")
                .into_inner();
            while s.message().await.expect("stream").is_some() {}
            job.id
        });
        let executed = server.manager().executed();
        group.bench_function(format!("submit_job_with_result/{label}"), |b| {
            b.to_async(&rt).iter(|| {
                let mut cl = client.clone();
                let req = req.clone();
                async move {
                    let job = cl
                        .submit_job(with_token(req))
                        .await
                        .expect("submit")
                        .into_inner();
                    assert!(job.cached);
                    job
                }
            })
        });
        if !auth {
            // The path of clients left at the default 4 MiB limit: the result in 1 MiB chunks
            // (with its SHA-256), reassembled.
            let default_client = pb::jobs_client::JobsClient::new(
                Endpoint::from_shared(server.url())
                    .expect("url")
                    .connect_lazy(),
            );
            group.bench_function(format!("get_job_result_chunks/{label}"), |b| {
                b.to_async(&rt).iter(|| {
                    let mut cl = default_client.clone();
                    let id = id.clone();
                    async move {
                        let mut s = cl
                            .get_job_result(pb::GetJobResultRequest { id, chunk_bytes: 0 })
                            .await
                            .expect("result stream")
                            .into_inner();
                        let mut bytes = Vec::new();
                        while let Some(c) = s.message().await.expect("chunk") {
                            bytes.extend_from_slice(&c.data);
                        }
                        bytes
                    }
                })
            });
        }
        assert_eq!(server.manager().executed(), executed, "no recomputation");
    }
    group.finish();
    rt.block_on(server.stop()).expect("stop");
}

fn with_token_watch(auth: bool, id: String) -> tonic::Request<pb::WatchJobRequest> {
    let mut r = tonic::Request::new(pb::WatchJobRequest {
        id,
        omit_result: true,
    });
    if auth {
        r.metadata_mut().insert(
            "authorization",
            format!("Bearer {TOKEN}").parse().expect("header"),
        );
    }
    r
}

/// What the record log (`--cache-dir/records.log`) adds to a job's end: one fsynced line for a
/// computed job, one unsynced line for an authenticated tenant's cache hit.
fn record_log_append(c: &mut Criterion) {
    use murk_server::jobs::{JobSnapshot, JobState, LoggedRecord, RecordLog};
    let dir = tempfile::tempdir().expect("temp dir");
    let log = RecordLog::open(&dir.path().join("records.log")).expect("log");
    let now = std::time::SystemTime::now();
    let snap = JobSnapshot {
        id: "ab".repeat(32),
        method: "tof_depth".into(),
        state: JobState::Running,
        progress: 0.9,
        stage: "fine".into(),
        create_time: now,
        start_time: Some(now),
        end_time: None,
        cached: false,
        result: None,
        error: None,
    };
    let record =
        LoggedRecord::ended("alpha", &snap, JobState::Succeeded, None).expect("terminal record");
    let mut group = c.benchmark_group("record_log_append");
    group.sample_size(30);
    for (label, sync) in [("fsynced", true), ("written", false)] {
        group.bench_function(label, |b| {
            b.iter(|| log.append(&record, sync).expect("append"))
        });
    }
    group.finish();
}

criterion_group!(benches, cache_hit_round_trip, record_log_append);
criterion_main!(benches);
