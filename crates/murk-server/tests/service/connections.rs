//! What anyone who reaches the port can hold before auth: idle sockets are closed after the
//! handshake timeout, the connections are capped, and each connection's streams are bounded
//! in its HTTP/2 SETTINGS.

use crate::common;

use std::time::{Duration, Instant};

use common::*;
use murk_server::connections::ConnectionLimits;
use murk_server::server::ServerConfig;
use tokio::io::AsyncReadExt;
use tokio::net::TcpStream;

fn limits(max_connections: usize, handshake: Duration) -> ServerConfig {
    ServerConfig {
        connections: ConnectionLimits {
            max_connections,
            handshake_timeout: handshake,
            max_concurrent_streams: 8,
            ..ConnectionLimits::default()
        },
        ..config(4)
    }
}

/// A socket that sends the HTTP/2 preface and an empty SETTINGS frame, then nothing: it
/// neither reads nor answers pings.
async fn open_http2_then_go_silent(server: &murk_server::server::InProcessServer) -> TcpStream {
    let mut sock = TcpStream::connect(server.addr()).await.unwrap();
    let mut opening = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n".to_vec();
    opening.extend_from_slice(&[0, 0, 0, 4, 0, 0, 0, 0, 0]);
    tokio::io::AsyncWriteExt::write_all(&mut sock, &opening)
        .await
        .unwrap();
    sock
}

/// Reads until the server closes the socket (EOF or reset); the time it took, or `None` if it
/// stayed open for `within`.
async fn closed_within(sock: &mut TcpStream, within: Duration) -> Option<Duration> {
    let started = Instant::now();
    let mut buf = [0u8; 64];
    loop {
        match tokio::time::timeout(
            within.saturating_sub(started.elapsed()),
            sock.read(&mut buf),
        )
        .await
        {
            Err(_) => return None,
            Ok(Ok(0)) | Ok(Err(_)) => return Some(started.elapsed()),
            // The server's SETTINGS or GOAWAY: keep reading until it closes.
            Ok(Ok(_)) => continue,
        }
    }
}

#[tokio::test]
async fn a_socket_that_never_speaks_is_closed_after_the_handshake_timeout() {
    let server = start(limits(16, Duration::from_millis(300))).await;
    let connected = Instant::now();
    let mut silent = TcpStream::connect(server.addr()).await.unwrap();
    let mut preface_only = TcpStream::connect(server.addr()).await.unwrap();
    // Half a preface, then nothing: still short of the opening bytes.
    tokio::io::AsyncWriteExt::write_all(&mut preface_only, b"PRI * HTTP/2.0\r\n")
        .await
        .unwrap();
    for sock in [&mut silent, &mut preface_only] {
        closed_within(sock, Duration::from_secs(5))
            .await
            .expect("an idle socket stayed open 5 s");
        let t = connected.elapsed();
        assert!(
            t >= Duration::from_millis(250),
            "closed {t:?} after connecting"
        );
    }
    // A client that speaks is served.
    health_ok(&server).await;
    server.stop().await.unwrap();
}

#[tokio::test]
async fn a_peer_that_opens_http2_then_goes_silent_is_closed_by_keepalive() {
    let mut cfg = limits(16, Duration::from_secs(30));
    cfg.connections.keepalive_interval = Duration::from_millis(200);
    cfg.connections.keepalive_timeout = Duration::from_millis(200);
    let server = start(cfg).await;
    let connected = Instant::now();
    let mut sock = open_http2_then_go_silent(&server).await;
    closed_within(&mut sock, Duration::from_secs(10))
        .await
        .expect("a silent HTTP/2 peer stayed open 10 s");
    assert!(connected.elapsed() >= Duration::from_millis(300));
    server.stop().await.unwrap();
}

#[tokio::test]
async fn a_silent_peer_does_not_hold_the_shutdown() {
    let server = start(limits(16, Duration::from_secs(30))).await;
    // Only keepalive (30 s + 20 s by default) would close this peer.
    let sock = open_http2_then_go_silent(&server).await;
    health_ok(&server).await;
    let started = Instant::now();
    tokio::time::timeout(Duration::from_secs(10), server.stop())
        .await
        .expect("stop waited 10 s on a silent connection")
        .unwrap();
    assert!(
        started.elapsed() < Duration::from_secs(5),
        "{:?}",
        started.elapsed()
    );
    drop(sock);
}

#[tokio::test]
async fn connections_beyond_the_cap_are_closed_and_slots_free_when_sockets_go() {
    let server = start(limits(2, Duration::from_secs(30))).await;
    let idle: Vec<TcpStream> =
        futures::future::join_all((0..2).map(|_| TcpStream::connect(server.addr())))
            .await
            .into_iter()
            .map(Result::unwrap)
            .collect();
    // Accepted in order: give the server the time to take both slots.
    tokio::time::sleep(Duration::from_millis(100)).await;
    let mut third = TcpStream::connect(server.addr()).await.unwrap();
    let t = closed_within(&mut third, Duration::from_secs(5)).await;
    assert!(t.expect("the third connection stayed open") < Duration::from_secs(2));
    drop(idle);
    // The slots free as the idle sockets close; a real client then gets one.
    let deadline = Instant::now() + Duration::from_secs(5);
    loop {
        if try_health(&server).await {
            break;
        }
        assert!(Instant::now() < deadline, "no slot freed within 5 s");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    server.stop().await.unwrap();
}

#[tokio::test]
async fn the_server_announces_its_stream_limit() {
    let server = start(limits(16, Duration::from_secs(30))).await;
    let tcp = TcpStream::connect(server.addr()).await.unwrap();
    let (client, mut conn) = h2::client::handshake(tcp).await.unwrap();
    // Drive the connection until the server's SETTINGS have been read.
    let deadline = Instant::now() + Duration::from_secs(5);
    while conn.max_concurrent_send_streams() == usize::MAX {
        assert!(
            Instant::now() < deadline,
            "no MAX_CONCURRENT_STREAMS in 5 s"
        );
        let _ = tokio::time::timeout(Duration::from_millis(50), &mut conn).await;
    }
    assert_eq!(conn.max_concurrent_send_streams(), 8);
    drop((client, conn));
    server.stop().await.unwrap();
}

async fn try_health(server: &murk_server::server::InProcessServer) -> bool {
    let Ok(ch) = tonic::transport::Endpoint::from_shared(server.url())
        .unwrap()
        .connect_timeout(Duration::from_secs(1))
        .timeout(Duration::from_secs(2))
        .connect()
        .await
    else {
        return false;
    };
    tonic_health::pb::health_client::HealthClient::new(ch)
        .check(tonic_health::pb::HealthCheckRequest {
            service: String::new(),
        })
        .await
        .is_ok()
}

async fn health_ok(server: &murk_server::server::InProcessServer) {
    assert!(try_health(server).await, "health did not answer");
}

/// CPU seconds (user + system) the process `pid` has used.
#[cfg(target_os = "linux")]
fn cpu_seconds(pid: u32) -> f64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap();
    // The fields after the command name, which is parenthesised and may hold spaces.
    let fields: Vec<&str> = stat[stat.rfind(')').unwrap() + 2..]
        .split_whitespace()
        .collect();
    let ticks: f64 = fields[11].parse::<f64>().unwrap() + fields[12].parse::<f64>().unwrap();
    // SAFETY: sysconf reads a constant of the system.
    ticks / unsafe { libc::sysconf(libc::_SC_CLK_TCK) } as f64
}

#[cfg(target_os = "linux")]
#[tokio::test]
async fn at_the_descriptor_limit_the_server_keeps_answering_and_does_not_spin() {
    if std::process::Command::new("prlimit")
        .arg("--version")
        .output()
        .is_err()
    {
        eprintln!("skipped: prlimit (util-linux) is not installed");
        return;
    }
    let mut cmd = std::process::Command::new("prlimit");
    cmd.args(["--nofile=128:128", env!("CARGO_BIN_EXE_murk"), "serve"])
        .args(["--addr", "127.0.0.1:0", "--workers", "1"])
        .args(["--handshake-timeout-secs", "1", "--max-connections", "1000"]);
    // prlimit execs the server: the child's pid is the server's.
    let (child, url) = spawn_serve(cmd);
    let child = KillOnDrop(child);
    let addr = url.trim_start_matches("http://").to_string();
    // More idle sockets than the server has descriptors: it runs out and accept fails. A full
    // backlog may leave a connect hanging: each has a bound.
    let mut idle = Vec::new();
    for _ in 0..300 {
        if let Ok(Ok(s)) =
            tokio::time::timeout(Duration::from_millis(200), TcpStream::connect(&addr)).await
        {
            idle.push(s);
        }
    }
    let before = cpu_seconds(child.0.id());
    let window = Duration::from_secs(2);
    tokio::time::sleep(window).await;
    let burnt = cpu_seconds(child.0.id()) - before;
    assert!(
        burnt < 0.5,
        "the server used {burnt:.2} s of CPU in {window:?} with idle sockets queued"
    );
    // The handshake timeout closes the idle sockets a batch at a time; health gets through.
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let ok = match tonic::transport::Endpoint::from_shared(url.clone())
            .unwrap()
            .connect_timeout(Duration::from_secs(2))
            .timeout(Duration::from_secs(3))
            .connect()
            .await
        {
            Ok(ch) => tonic_health::pb::health_client::HealthClient::new(ch)
                .check(tonic_health::pb::HealthCheckRequest {
                    service: String::new(),
                })
                .await
                .is_ok(),
            Err(_) => false,
        };
        if ok {
            break;
        }
        assert!(Instant::now() < deadline, "health did not answer in 30 s");
    }
    drop(idle);
}

/// A child process killed when the test ends, passed or failed.
struct KillOnDrop(std::process::Child);

impl Drop for KillOnDrop {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}
