//! A throw-away nginx in front of test replicas, running the project's own
//! `deploy/nginx.conf` (and, with TLS, `deploy/nginx-tls.conf`) with only the
//! deployment-specific parts rewritten: the listen addresses (free loopback ports), the upstream
//! servers (the replicas' addresses instead of Docker's `murk` name) and the file paths (a
//! temporary directory, so no root is needed). `start` returns `None` (printing why) when nginx
//! is not installed.

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use super::pki::Pki;
use super::redis_server::free_port;

/// An nginx process (foreground, single process), killed on drop.
pub struct Nginx {
    child: Child,
    port: u16,
    tls_port: Option<u16>,
    _dir: tempfile::TempDir,
}

/// `from` → `to` in `text`, once each; panics when a deploy file no longer has a line this
/// rewrites, so the tests keep exercising the shipped configuration rather than silently a
/// different one.
fn rewrite(file: &str, text: &str, replaced: impl IntoIterator<Item = (String, String)>) -> String {
    let mut text = text.to_string();
    for (from, to) in replaced {
        assert!(
            text.contains(&from),
            "{file} no longer contains `{from}`: update tests/service/common/nginx.rs"
        );
        text = text.replacen(&from, &to, 1);
    }
    text
}

/// `deploy/nginx.conf` with the listen port, the upstream servers and the file paths replaced.
fn test_config(deploy_conf: &str, port: u16, upstreams: &[String], dir: &str) -> String {
    let servers: String = upstreams
        .iter()
        .map(|u| format!("server {u};\n        "))
        .collect();
    let replaced = [
        ("pid /tmp/nginx.pid;", format!("pid {dir}/nginx.pid;")),
        ("server murk:50051;", servers),
        (
            "listen 50051 http2;",
            format!("listen 127.0.0.1:{port} http2;"),
        ),
        (
            "include /etc/murk/tls/*.conf;",
            format!("include {dir}/tls/*.conf;"),
        ),
        (
            "http {",
            [
                "http {".to_string(),
                format!("    client_body_temp_path {dir}/body;"),
                format!("    proxy_temp_path {dir}/proxy;"),
                format!("    fastcgi_temp_path {dir}/fastcgi;"),
                format!("    uwsgi_temp_path {dir}/uwsgi;"),
                format!("    scgi_temp_path {dir}/scgi;"),
            ]
            .join("\n"),
        ),
    ];
    rewrite(
        "deploy/nginx.conf",
        deploy_conf,
        replaced.map(|(a, b)| (a.to_string(), b)),
    )
}

/// Writes `deploy/nginx-tls.conf` (listening on `port`) and the server certificate into
/// `dir/tls`, where the rewritten nginx.conf includes it.
fn write_tls(dir: &Path, port: u16, pki: &Pki) {
    let tls = dir.join("tls");
    std::fs::create_dir_all(&tls).unwrap();
    std::fs::write(tls.join("cert.pem"), &pki.server_cert).unwrap();
    std::fs::write(tls.join("key.pem"), &pki.server_key).unwrap();
    let deploy = concat!(env!("CARGO_MANIFEST_DIR"), "/../../deploy/nginx-tls.conf");
    let conf = rewrite(
        "deploy/nginx-tls.conf",
        &std::fs::read_to_string(deploy).unwrap(),
        [
            (
                "listen 50443 ssl http2;".to_string(),
                format!("listen 127.0.0.1:{port} ssl http2;"),
            ),
            (
                "/etc/murk/tls/cert.pem".to_string(),
                tls.join("cert.pem").display().to_string(),
            ),
            (
                "/etc/murk/tls/key.pem".to_string(),
                tls.join("key.pem").display().to_string(),
            ),
        ],
    );
    std::fs::write(tls.join("listen.conf"), conf).unwrap();
}

impl Nginx {
    /// nginx balancing over `upstreams` (`host:port`), with a TLS listener as well when `tls`
    /// is given, or `None` when nginx is not installed.
    pub fn start(upstreams: &[String], tls: Option<&Pki>) -> Option<Self> {
        // Debian installs it in sbin, which a non-root PATH may lack.
        let Some(bin) = super::find_binary("nginx", &["/usr/sbin", "/usr/local/sbin"]) else {
            eprintln!(
                "SKIPPED: nginx is not installed (apt-get install nginx); .ci/run installs it"
            );
            return None;
        };
        let dir = tempfile::tempdir().unwrap();
        let port = free_port();
        let deploy = concat!(env!("CARGO_MANIFEST_DIR"), "/../../deploy/nginx.conf");
        let conf = test_config(
            &std::fs::read_to_string(deploy).unwrap(),
            port,
            upstreams,
            &dir.path().display().to_string(),
        );
        let tls_port = tls.map(|pki| {
            let p = free_port();
            write_tls(dir.path(), p, pki);
            p
        });
        let conf_path = dir.path().join("nginx.conf");
        std::fs::write(&conf_path, conf).unwrap();
        let child = Command::new(bin)
            // -e: the compiled-in error log (/var/log/nginx) may not be writable.
            .args(["-e", "stderr", "-p"])
            .arg(dir.path())
            .arg("-c")
            .arg(&conf_path)
            // One foreground process as the invoking user: no privilege drop to a user that
            // could not write the temporary directory.
            .args(["-g", "daemon off; master_process off;"])
            .stdout(Stdio::null())
            .spawn()
            .expect("nginx starts");
        let mut n = Self {
            child,
            port,
            tls_port,
            _dir: dir,
        };
        let deadline = Instant::now() + Duration::from_secs(10);
        for p in std::iter::once(port).chain(tls_port) {
            while std::net::TcpStream::connect(("127.0.0.1", p)).is_err() {
                if let Ok(Some(status)) = n.child.try_wait() {
                    panic!("nginx exited at start: {status}");
                }
                assert!(
                    Instant::now() < deadline,
                    "nginx did not come up on port {p}"
                );
                std::thread::sleep(Duration::from_millis(20));
            }
        }
        Some(n)
    }

    /// The balancer's plaintext gRPC URL.
    pub fn url(&self) -> String {
        format!("http://127.0.0.1:{}", self.port)
    }

    /// The balancer's TLS URL (the certificate is for `localhost`), when started with TLS.
    pub fn tls_url(&self) -> Option<String> {
        self.tls_port.map(|p| format!("https://localhost:{p}"))
    }
}

impl Drop for Nginx {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
