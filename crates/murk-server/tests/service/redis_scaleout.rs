//! Scale-out on Redis: several `murk serve --redis-url` replicas, each a separate process, share
//! one job registry, queue and result cache in a real `redis-server` started by the test on a
//! free loopback port. Without `redis-server` on the PATH every test here prints why and
//! passes vacuously (`.ci/run` installs it, so CI runs them).

use crate::common;

use std::process::{Child, Command};
use std::time::{Duration, Instant};

use common::nginx::Nginx;
use common::redis_server::{free_port, RedisServer};
use common::{job, long_tof_request, sample, scrape, tof_request};
use murk_server::service::proto::v1 as pb;
use pb::jobs_client::JobsClient;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint};
use tonic::Code;
use tonic_types::StatusExt;

/// A `murk serve` process in the Redis backend, killed on drop.
struct Replica {
    child: Child,
    url: String,
}

impl Replica {
    fn start(redis: &RedisServer, extra: &[&str]) -> Self {
        Self::start_url(&redis.url(), extra)
    }

    fn start_url(url: &str, extra: &[&str]) -> Self {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_murk"));
        cmd.args(["serve", "--addr", "127.0.0.1:0", "--workers", "1"])
            .args(["--redis-url", url])
            .args(["--shutdown-grace-secs", "0.5"])
            .args(extra);
        // A short lease so takeovers happen within the tests' patience.
        if !extra.contains(&"--redis-lease-secs") {
            cmd.args(["--redis-lease-secs", "1.5"]);
        }
        let (child, url) = common::spawn_serve(cmd);
        Self { child, url }
    }

    fn jobs(&self) -> JobsClient<Channel> {
        JobsClient::new(
            Endpoint::from_shared(self.url.clone())
                .unwrap()
                .connect_lazy(),
        )
        .max_decoding_message_size(usize::MAX)
    }

    fn pid(&self) -> u32 {
        self.child.id()
    }

    fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Replica {
    fn drop(&mut self) {
        self.kill();
    }
}

async fn submit(c: &mut JobsClient<Channel>, req: pb::TofDepthRequest) -> pb::Job {
    c.submit_job(job(req))
        .await
        .expect("submitted")
        .into_inner()
}

async fn get(c: &mut JobsClient<Channel>, id: &str) -> pb::Job {
    c.get_job(pb::GetJobRequest {
        id: id.into(),
        omit_result: true,
    })
    .await
    .expect("get")
    .into_inner()
}

/// Polls GetJob until `pred` holds (bounded).
async fn wait_until(
    c: &mut JobsClient<Channel>,
    id: &str,
    limit: Duration,
    pred: impl Fn(&pb::Job) -> bool,
) -> pb::Job {
    let deadline = Instant::now() + limit;
    loop {
        let j = get(c, id).await;
        if pred(&j) {
            return j;
        }
        assert!(
            Instant::now() < deadline,
            "job {id} still {:?} after {limit:?}",
            j.state()
        );
        tokio::time::sleep(Duration::from_millis(25)).await;
    }
}

fn running(j: &pb::Job) -> bool {
    j.state() == pb::JobState::Running
}

fn terminal(j: &pb::Job) -> bool {
    matches!(
        j.state(),
        pb::JobState::Succeeded | pb::JobState::Failed | pb::JobState::Cancelled
    )
}

/// The pid in a replica's consumer name (`host-pid-rand`).
fn owner_pid(owner: &str) -> u32 {
    owner.rsplit('-').nth(1).unwrap().parse().unwrap()
}

#[tokio::test]
async fn a_job_submitted_on_one_replica_is_watched_and_fetched_on_another() {
    let Some(redis) = RedisServer::start() else {
        return;
    };
    let a = Replica::start(&redis, &[]);
    let b = Replica::start(&redis, &[]);
    let (mut ca, mut cb) = (a.jobs(), b.jobs());
    let submitted = submit(&mut ca, tof_request(96, 80, 3)).await;
    // Watch through B: progress from whichever replica computes it, then the result.
    let mut stream = cb
        .watch_job(pb::WatchJobRequest {
            id: submitted.id.clone(),
            omit_result: false,
        })
        .await
        .expect("B knows the job")
        .into_inner();
    let mut last = None;
    let mut updates = 0;
    while let Some(j) = stream.message().await.unwrap() {
        updates += 1;
        last = Some(j);
    }
    let last = last.expect("at least one update");
    assert_eq!(last.state(), pb::JobState::Succeeded, "{last:?}");
    assert!(
        matches!(last.outcome, Some(pb::job::Outcome::Result(_))),
        "the result comes with the final update"
    );
    assert!(updates >= 2, "saw the job change, not only its end");
    let on_b = get(&mut cb, &submitted.id).await;
    assert_eq!(on_b.state(), pb::JobState::Succeeded);
    // Both replicas list it.
    for c in [&mut ca, &mut cb] {
        let list = c
            .list_jobs(pb::ListJobsRequest::default())
            .await
            .unwrap()
            .into_inner();
        assert_eq!(list.jobs.len(), 1);
        assert_eq!(list.jobs[0].id, submitted.id);
    }
}

#[tokio::test]
async fn a_job_whose_replica_is_killed_is_completed_by_another() {
    let Some(redis) = RedisServer::start() else {
        return;
    };
    let mut replicas = [Replica::start(&redis, &[]), Replica::start(&redis, &[])];
    let mut c = replicas[0].jobs();
    // Long enough to be caught running, short enough to finish on the survivor.
    let submitted = submit(&mut c, long_tof_request(150)).await;
    wait_until(&mut c, &submitted.id, Duration::from_secs(30), running).await;
    let owner = redis.record_field(&submitted.id, "owner").unwrap();
    let victim = replicas
        .iter()
        .position(|r| r.pid() == owner_pid(&owner))
        .expect("one of ours runs it");
    replicas[victim].kill();
    let mut survivor = replicas[1 - victim].jobs();
    let done = wait_until(
        &mut survivor,
        &submitted.id,
        Duration::from_secs(120),
        terminal,
    )
    .await;
    assert_eq!(done.state(), pb::JobState::Succeeded, "{done:?}");
    let new_owner = redis.record_field(&submitted.id, "owner").unwrap();
    assert_ne!(new_owner, owner, "the survivor took it over");
    assert_eq!(
        redis.record_field(&submitted.id, "attempts").as_deref(),
        Some("2")
    );
}

/// The computing replica's watchers see the end only once Redis has it, so that a Get through
/// any other replica right after agrees, even when Redis is slow to take the write (here: its
/// writes paused for 3.5 s, longer than the old 2 s local fallback and shorter than the 5 s
/// response timeout after which Redis counts as unreachable and local callers see the end
/// first).
#[tokio::test]
async fn a_watch_ends_only_once_every_replica_agrees() {
    let Some(redis) = RedisServer::start() else {
        return;
    };
    // A lease well beyond the pause, so no takeover muddles the picture.
    let lease = ["--redis-lease-secs", "30"];
    let replicas = [
        Replica::start(&redis, &lease),
        Replica::start(&redis, &lease),
    ];
    let mut c = replicas[0].jobs();
    let submitted = submit(&mut c, long_tof_request(25)).await;
    wait_until(&mut c, &submitted.id, Duration::from_secs(30), running).await;
    let owner = owner_pid(&redis.record_field(&submitted.id, "owner").unwrap());
    let computing = replicas.iter().position(|r| r.pid() == owner).unwrap();
    let (mut on_owner, mut other) = (replicas[computing].jobs(), replicas[1 - computing].jobs());
    let mut stream = on_owner
        .watch_job(pb::WatchJobRequest {
            id: submitted.id.clone(),
            omit_result: true,
        })
        .await
        .unwrap()
        .into_inner();
    // The job finishes during the pause; its end cannot reach Redis until the pause is over.
    let paused = Instant::now();
    let _: () = redis::cmd("CLIENT")
        .arg("PAUSE")
        .arg(3500)
        .arg("WRITE")
        .query(&mut redis.conn())
        .unwrap();
    let mut last = None;
    while let Some(j) = stream.message().await.unwrap() {
        last = Some(j);
    }
    let last = last.unwrap();
    assert_eq!(last.state(), pb::JobState::Succeeded, "{last:?}");
    // What any replica reads (Redis, through a connection of its own that the pause does not
    // hold up) already says so.
    let recorded = redis.record_field(&submitted.id, "state");
    let watch_ended = paused.elapsed();
    assert_eq!(
        recorded.as_deref(),
        Some("succeeded"),
        "the watch ended {watch_ended:?} after the pause began, Redis still says {recorded:?}"
    );
    assert!(
        watch_ended >= Duration::from_millis(3000),
        "{watch_ended:?}"
    );
    let elsewhere = get(&mut other, &submitted.id).await;
    assert_eq!(elsewhere.state(), pb::JobState::Succeeded);
}

#[tokio::test]
async fn a_result_computed_on_one_replica_is_a_cache_hit_on_another() {
    let Some(redis) = RedisServer::start() else {
        return;
    };
    let tokens = tempfile::NamedTempFile::new().unwrap();
    std::fs::write(
        tokens.path(),
        "alpha alpha-token-0123456789\nbeta beta-token-9876543210\n",
    )
    .unwrap();
    // Results shared between tenants, so the hit below can only come from the shared cache.
    let auth = [
        "--auth-tokens-file",
        tokens.path().to_str().unwrap(),
        "--cache-scope",
        "global",
    ];
    let a = Replica::start(&redis, &auth);
    let with = |token: &str, req: pb::SubmitJobRequest| {
        let mut r = tonic::Request::new(req);
        r.metadata_mut()
            .insert("authorization", format!("Bearer {token}").parse().unwrap());
        r
    };
    let req = tof_request(64, 48, 5);
    let first = a
        .jobs()
        .submit_job(with("alpha-token-0123456789", job(req.clone())))
        .await
        .unwrap()
        .into_inner();
    let mut stream = a
        .jobs()
        .watch_job({
            let mut r = tonic::Request::new(pb::WatchJobRequest {
                id: first.id.clone(),
                omit_result: true,
            });
            r.metadata_mut().insert(
                "authorization",
                "Bearer alpha-token-0123456789".parse().unwrap(),
            );
            r
        })
        .await
        .unwrap()
        .into_inner();
    while stream.message().await.unwrap().is_some() {}
    // B starts only now, so it cannot have computed anything; another tenant has no record of
    // the job, so the hit comes from the shared result cache.
    let b = Replica::start(&redis, &auth);
    let hit = b
        .jobs()
        .submit_job(with("beta-token-9876543210", job(req)))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(hit.id, first.id);
    assert!(hit.cached, "{hit:?}");
    assert_eq!(hit.state(), pb::JobState::Succeeded);
    assert!(matches!(hit.outcome, Some(pb::job::Outcome::Result(_))));
}

#[tokio::test]
async fn cancel_through_one_replica_stops_the_job_running_on_another_within_a_second() {
    let Some(redis) = RedisServer::start() else {
        return;
    };
    let replicas = [Replica::start(&redis, &[]), Replica::start(&redis, &[])];
    let mut c = replicas[0].jobs();
    let submitted = submit(&mut c, long_tof_request(9_000)).await;
    wait_until(&mut c, &submitted.id, Duration::from_secs(30), running).await;
    let owner = owner_pid(&redis.record_field(&submitted.id, "owner").unwrap());
    let other = replicas.iter().position(|r| r.pid() != owner).unwrap();
    let runner = 1 - other;
    let mut via = replicas[other].jobs();
    let mut on_runner = replicas[runner].jobs();
    let t0 = Instant::now();
    via.cancel_job(pb::CancelJobRequest {
        id: submitted.id.clone(),
    })
    .await
    .unwrap();
    let done = wait_until(
        &mut on_runner,
        &submitted.id,
        Duration::from_secs(5),
        terminal,
    )
    .await;
    let took = t0.elapsed();
    assert_eq!(done.state(), pb::JobState::Cancelled, "{done:?}");
    assert!(took < Duration::from_secs(1), "took {took:?}");
}

#[tokio::test]
async fn a_full_global_queue_is_refused_with_a_retry_hint() {
    let Some(redis) = RedisServer::start() else {
        return;
    };
    let cap = ["--queue-capacity", "1"];
    let replicas = [Replica::start(&redis, &cap), Replica::start(&redis, &cap)];
    let mut c = replicas[0].jobs();
    let mut ids = Vec::new();
    // One running on each replica …
    for seed in 0..2u32 {
        let j = submit(&mut c, long_tof_request(9_000 + seed)).await;
        wait_until(&mut c, &j.id, Duration::from_secs(30), running).await;
        ids.push(j.id);
    }
    // … one waiting, whichever replica it was sent to …
    let mut other = replicas[1].jobs();
    ids.push(submit(&mut other, long_tof_request(9_002)).await.id);
    // … and the next is refused by both.
    for client in [&mut c, &mut other] {
        let err = client
            .submit_job(job(long_tof_request(9_003)))
            .await
            .unwrap_err();
        assert_eq!(err.code(), Code::ResourceExhausted, "{err:?}");
        let hint = err.get_details_retry_info().expect("RetryInfo");
        assert!(hint.retry_delay.is_some_and(|d| d > Duration::ZERO));
    }
    for id in ids {
        c.cancel_job(pb::CancelJobRequest { id }).await.unwrap();
    }
}

#[tokio::test]
async fn no_accepted_job_is_lost_when_redis_crashes_and_restarts_with_aof() {
    let Some(mut redis) = RedisServer::start() else {
        return;
    };
    let replica = Replica::start(&redis, &[]);
    let mut c = replica.jobs();
    // Keep the replica busy so the next jobs wait in the queue.
    let blocker = submit(&mut c, long_tof_request(9_000)).await;
    wait_until(&mut c, &blocker.id, Duration::from_secs(30), running).await;
    let mut waiting = Vec::new();
    for seed in 0..3 {
        waiting.push(submit(&mut c, tof_request(48, 40, 100 + seed)).await.id);
    }
    redis.crash_and_restart();
    // While Redis was away the replica answered UNAVAILABLE; once it is back, it serves again.
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        match c
            .cancel_job(pb::CancelJobRequest {
                id: blocker.id.clone(),
            })
            .await
        {
            Ok(_) => break,
            Err(e) => {
                assert_eq!(e.code(), Code::Unavailable, "{e:?}");
                assert!(Instant::now() < deadline, "replica did not reconnect");
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
    }
    for id in &waiting {
        let j = wait_until(&mut c, id, Duration::from_secs(60), terminal).await;
        assert_eq!(j.state(), pb::JobState::Succeeded, "{j:?}");
    }
}

#[tokio::test]
async fn a_replica_started_before_redis_answers_unavailable_then_serves() {
    let Some(redis) = RedisServer::start() else {
        return;
    };
    // A replica pointed at a port where nothing listens yet.
    let port = common::redis_server::free_port();
    let url = format!("redis://127.0.0.1:{port}/");
    let replica = Replica::start_url(&url, &[]);
    let mut c = replica.jobs();
    let err = c.submit_job(job(tof_request(32, 24, 1))).await.unwrap_err();
    assert_eq!(err.code(), Code::Unavailable, "{err:?}");
    assert!(err.get_details_retry_info().is_some());
    drop(redis);
    // Redis appears on that port: the replica reconnects by itself.
    let _late = RedisServer::start_on(port);
    let deadline = Instant::now() + Duration::from_secs(20);
    let submitted = loop {
        match c.submit_job(job(tof_request(32, 24, 1))).await {
            Ok(j) => break j.into_inner(),
            Err(e) => {
                assert_eq!(e.code(), Code::Unavailable, "{e:?}");
                assert!(Instant::now() < deadline, "replica did not connect");
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
    };
    let done = wait_until(&mut c, &submitted.id, Duration::from_secs(30), terminal).await;
    assert_eq!(done.state(), pb::JobState::Succeeded);
}

#[cfg(unix)]
#[tokio::test]
async fn a_replica_stopped_with_sigterm_hands_its_job_to_another_at_once() {
    let Some(redis) = RedisServer::start() else {
        return;
    };
    // A long lease: a handover within it can only come from the stopping replica itself.
    let lease = ["--redis-lease-secs", "60"];
    let mut replicas = [
        Replica::start(&redis, &lease),
        Replica::start(&redis, &lease),
    ];
    let mut c = replicas[0].jobs();
    let submitted = submit(&mut c, long_tof_request(150)).await;
    wait_until(&mut c, &submitted.id, Duration::from_secs(30), running).await;
    let owner = owner_pid(&redis.record_field(&submitted.id, "owner").unwrap());
    let victim = replicas.iter().position(|r| r.pid() == owner).unwrap();
    let status = Command::new("kill")
        .args(["-TERM", &owner.to_string()])
        .status()
        .unwrap();
    assert!(status.success());
    // Waited for without blocking this runtime: the stopping server closes the connections of
    // this test's clients, which this runtime drives.
    let deadline = Instant::now() + Duration::from_secs(10);
    while replicas[victim].child.try_wait().unwrap().is_none() {
        assert!(Instant::now() < deadline, "the replica did not stop");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let mut survivor = replicas[1 - victim].jobs();
    let done = wait_until(
        &mut survivor,
        &submitted.id,
        Duration::from_secs(50),
        terminal,
    )
    .await;
    assert_eq!(done.state(), pb::JobState::Succeeded, "{done:?}");
    assert_eq!(
        redis.record_field(&submitted.id, "attempts").as_deref(),
        Some("1"),
        "a handover is not a failed attempt"
    );
}

/// Item 7: the shipped `deploy/nginx.conf` (listen address and upstreams rewritten) balances
/// RPCs over two replicas, both of them serve requests and both compute jobs, and results come
/// back through the balancer, in plaintext and over TLS with `deploy/nginx-tls.conf`.
#[tokio::test]
async fn two_replicas_behind_nginx_both_receive_work() {
    let Some(redis) = RedisServer::start() else {
        return;
    };
    let metrics: Vec<String> = (0..2)
        .map(|_| format!("127.0.0.1:{}", free_port()))
        .collect();
    let replicas: Vec<Replica> = metrics
        .iter()
        .map(|m| Replica::start(&redis, &["--metrics-addr", m]))
        .collect();
    let upstreams: Vec<String> = replicas
        .iter()
        .map(|r| r.url.trim_start_matches("http://").to_string())
        .collect();
    let pki = common::pki::pki();
    let Some(lb) = Nginx::start(&upstreams, Some(&pki)) else {
        return;
    };
    let mut c = JobsClient::new(Endpoint::from_shared(lb.url()).unwrap().connect_lazy())
        .max_decoding_message_size(usize::MAX);
    // Distinct jobs (distinct ids) of a few hundred ms each, all submitted before the first can
    // finish: with one slot per replica, the second job finds the first one's replica busy.
    let mut ids = Vec::new();
    for n in 0..6 {
        ids.push(submit(&mut c, long_tof_request(20 + n)).await.id);
    }
    for id in &ids {
        let j = wait_until(&mut c, id, Duration::from_secs(120), terminal).await;
        assert_eq!(j.state(), pb::JobState::Succeeded, "{j:?}");
    }
    // A result of several MB comes back through nginx on the ordinary call.
    let full = c
        .get_job(pb::GetJobRequest {
            id: ids[0].clone(),
            omit_result: false,
        })
        .await
        .expect("result through nginx")
        .into_inner();
    assert!(matches!(full.outcome, Some(pb::job::Outcome::Result(_))));
    // deploy/nginx-tls.conf: the same service over TLS terminated at the balancer.
    let tls = ClientTlsConfig::new()
        .ca_certificate(Certificate::from_pem(&pki.ca_pem))
        .domain_name("localhost");
    let channel = Endpoint::from_shared(lb.tls_url().unwrap())
        .unwrap()
        .tls_config(tls)
        .unwrap()
        .connect()
        .await
        .expect("TLS through nginx");
    let over_tls = JobsClient::new(channel)
        .max_decoding_message_size(usize::MAX)
        .get_job(pb::GetJobRequest {
            id: ids[1].clone(),
            omit_result: false,
        })
        .await
        .expect("a result over TLS")
        .into_inner();
    assert!(matches!(
        over_tls.outcome,
        Some(pb::job::Outcome::Result(_))
    ));
    // nginx spread the RPCs: each replica answered some of the submissions...
    let submits = r#"murk_grpc_requests_total{method="murk.v1.Jobs/SubmitJob",code="OK"}"#;
    for m in &metrics {
        let served = sample(&scrape(m.parse().unwrap()).await, submits);
        assert!(
            served >= 1.0,
            "replica {m} answered {served} SubmitJob calls"
        );
    }
    // ...and each computed some of the jobs.
    let owners: std::collections::BTreeSet<u32> = ids
        .iter()
        .map(|id| owner_pid(&redis.record_field(id, "owner").unwrap()))
        .collect();
    let pids: std::collections::BTreeSet<u32> = replicas.iter().map(Replica::pid).collect();
    assert_eq!(owners, pids, "jobs were computed by {owners:?}");
}

/// Writes the test PKI's files for the replicas' `--redis-…` flags.
fn redis_tls_files(pki: &common::pki::Pki) -> (tempfile::TempDir, [String; 3]) {
    let dir = tempfile::tempdir().unwrap();
    let files = [
        ("ca.pem", &pki.ca_pem),
        ("client.pem", &pki.client_cert),
        ("client.key", &pki.client_key),
    ]
    .map(|(name, pem)| {
        let path = dir.path().join(name);
        std::fs::write(&path, pem).unwrap();
        path.display().to_string()
    });
    (dir, files)
}

/// A replica that cannot use Redis answers UNAVAILABLE with a retry hint (and keeps trying).
async fn refused_by_redis(replica: &Replica) {
    let err = replica
        .jobs()
        .submit_job(job(tof_request(32, 24, 1)))
        .await
        .unwrap_err();
    assert_eq!(err.code(), Code::Unavailable, "{err:?}");
    assert!(err.get_details_retry_info().is_some(), "{err:?}");
}

/// Redis over TLS only, with a password: replicas that trust its CA (`--redis-ca-file`) and use
/// a `rediss://:PASSWORD@…` URL share a job through it; a wrong password, or a plaintext URL,
/// is UNAVAILABLE.
#[tokio::test]
async fn replicas_share_work_through_redis_over_tls_with_a_password() {
    let pki = common::pki::pki();
    let Some(redis) = RedisServer::start_tls(&pki, "pw-3f9a1c", false) else {
        return;
    };
    let (_dir, [ca, _, _]) = redis_tls_files(&pki);
    let a = Replica::start(&redis, &["--redis-ca-file", &ca]);
    let b = Replica::start(&redis, &["--redis-ca-file", &ca]);
    let submitted = submit(&mut a.jobs(), tof_request(48, 40, 2)).await;
    let done = wait_until(
        &mut b.jobs(),
        &submitted.id,
        Duration::from_secs(60),
        terminal,
    )
    .await;
    assert_eq!(done.state(), pb::JobState::Succeeded, "{done:?}");
    assert_eq!(
        redis.record_field(&submitted.id, "state").as_deref(),
        Some("succeeded"),
        "the record went through the TLS connection"
    );
    let wrong = Replica::start_url(
        &redis.url().replace("pw-3f9a1c", "not-the-password"),
        &["--redis-ca-file", &ca],
    );
    refused_by_redis(&wrong).await;
    let plaintext = Replica::start_url(
        &redis
            .url()
            .replace("rediss://", "redis://")
            .replace("localhost", "127.0.0.1"),
        &[],
    );
    refused_by_redis(&plaintext).await;
}

/// A Redis that authenticates TLS clients: a replica with `--redis-client-cert` and
/// `--redis-client-key` is let in; one without a client certificate is not.
#[tokio::test]
async fn a_redis_that_demands_client_certificates_admits_replicas_that_have_one() {
    let pki = common::pki::pki();
    let Some(redis) = RedisServer::start_tls(&pki, "pw-77d0", true) else {
        return;
    };
    let (_dir, [ca, cert, key]) = redis_tls_files(&pki);
    let with_cert = Replica::start(
        &redis,
        &[
            "--redis-ca-file",
            &ca,
            "--redis-client-cert",
            &cert,
            "--redis-client-key",
            &key,
        ],
    );
    let mut c = with_cert.jobs();
    let submitted = submit(&mut c, tof_request(32, 24, 1)).await;
    let done = wait_until(&mut c, &submitted.id, Duration::from_secs(60), terminal).await;
    assert_eq!(done.state(), pb::JobState::Succeeded, "{done:?}");
    let without = Replica::start(&redis, &["--redis-ca-file", &ca]);
    refused_by_redis(&without).await;
}
