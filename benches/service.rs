//! Service overhead: a cache-hit round trip over loopback (SubmitJob of an already computed
//! request: hashing, cache lookup, result encoding, HTTP/2 transfer, client decoding).
//!
//! cargo bench --bench service

use criterion::{criterion_group, criterion_main, Criterion};
use murk::jobs::JobsConfig;
use murk::server::{InProcessServer, ServerConfig};
use murk::service::convert::tof_request_to_proto;
use murk::service::proto::v1 as pb;
use murk::simulate::tof::{simulate_tof, TofSimConfig};
use murk::Monitor;
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

fn cache_hit_round_trip(c: &mut Criterion) {
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let server = rt
        .block_on(InProcessServer::start(ServerConfig {
            jobs: JobsConfig {
                workers: 2,
                ..JobsConfig::default()
            },
            ..ServerConfig::default()
        }))
        .expect("server");
    // The lazy channel spawns its connection task on the current runtime.
    let _enter = rt.enter();
    let channel = Endpoint::from_shared(server.url())
        .expect("url")
        .connect_lazy();
    let client = pb::jobs_client::JobsClient::new(channel)
        .max_decoding_message_size(usize::MAX)
        .max_encoding_message_size(usize::MAX);

    let mut group = c.benchmark_group("cache_hit_round_trip");
    group.sample_size(20);
    for (label, w, h) in [("64x53", 64, 53), ("512x424", 512, 424)] {
        let req = request(w, h);
        // Compute once so every measured call is a cache hit.
        rt.block_on(async {
            let mut cl = client.clone();
            let job = cl
                .submit_job(req.clone())
                .await
                .expect("submit")
                .into_inner();
            let mut s = cl
                .watch_job(pb::WatchJobRequest {
                    id: job.id,
                    omit_result: true,
                })
                .await
                .expect("watch")
                .into_inner();
            while s.message().await.expect("stream").is_some() {}
        });
        let executed = server.manager().executed();
        group.bench_function(format!("submit_job_with_result/{label}"), |b| {
            b.to_async(&rt).iter(|| {
                let mut cl = client.clone();
                let req = req.clone();
                async move {
                    let job = cl.submit_job(req).await.expect("submit").into_inner();
                    assert!(job.cached);
                    job
                }
            })
        });
        assert_eq!(server.manager().executed(), executed, "no recomputation");
    }
    group.finish();
    rt.block_on(server.stop()).expect("stop");
}

criterion_group!(benches, cache_hit_round_trip);
criterion_main!(benches);
