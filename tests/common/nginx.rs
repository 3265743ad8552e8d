//! A throw-away nginx in front of test replicas, running the project's own
//! `deploy/nginx.conf` with only the deployment-specific parts rewritten: the listen address
//! (a free loopback port), the upstream servers (the replicas' addresses instead of Docker's
//! `murk` name) and the pid/temp paths (a temporary directory, so no root is needed).
//! `start` returns `None` (printing why) when nginx is not installed.

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use super::redis_server::free_port;

/// An nginx process (foreground, single process), killed on drop.
pub struct Nginx {
    child: Child,
    port: u16,
    _dir: tempfile::TempDir,
}

fn nginx_binary() -> Option<PathBuf> {
    let mut dirs: Vec<PathBuf> = std::env::var_os("PATH")
        .map(|p| std::env::split_paths(&p).collect())
        .unwrap_or_default();
    // Debian installs it in sbin, which a non-root PATH may lack.
    dirs.extend(["/usr/sbin", "/usr/local/sbin"].map(PathBuf::from));
    dirs.into_iter()
        .map(|d| d.join("nginx"))
        .find(|p| p.is_file())
}

/// `deploy/nginx.conf` with the listen port, the upstream servers and the file paths replaced.
/// Panics when the deploy file no longer has the lines this rewrites, so the test keeps
/// exercising the shipped configuration rather than silently a different one.
pub fn test_config(deploy_conf: &str, port: u16, upstreams: &[String], dir: &str) -> String {
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
    let mut conf = deploy_conf.to_string();
    for (from, to) in replaced {
        assert!(
            conf.contains(from),
            "deploy/nginx.conf no longer contains `{from}`: update tests/common/nginx.rs"
        );
        conf = conf.replacen(from, &to, 1);
    }
    conf
}

impl Nginx {
    /// nginx balancing over `upstreams` (`host:port`), or `None` when nginx is not installed.
    pub fn start(upstreams: &[String]) -> Option<Self> {
        let Some(bin) = nginx_binary() else {
            eprintln!(
                "SKIPPED: nginx is not installed (apt-get install nginx); .ci/run installs it"
            );
            return None;
        };
        let dir = tempfile::tempdir().unwrap();
        let port = free_port();
        let deploy = concat!(env!("CARGO_MANIFEST_DIR"), "/deploy/nginx.conf");
        let conf = test_config(
            &std::fs::read_to_string(deploy).unwrap(),
            port,
            upstreams,
            &dir.path().display().to_string(),
        );
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
            _dir: dir,
        };
        let deadline = Instant::now() + Duration::from_secs(10);
        while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
            if let Ok(Some(status)) = n.child.try_wait() {
                panic!("nginx exited at start: {status}");
            }
            assert!(Instant::now() < deadline, "nginx did not come up");
            std::thread::sleep(Duration::from_millis(20));
        }
        Some(n)
    }

    /// The balancer's gRPC URL.
    pub fn url(&self) -> String {
        format!("http://127.0.0.1:{}", self.port)
    }
}

impl Drop for Nginx {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
