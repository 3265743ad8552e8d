//! A throw-away `redis-server` for the scale-out tests: AOF (by default with fsync on every
//! write), a free loopback port, killed on drop. `start` returns `None` (printing why) when redis-server is not
//! installed, so tests skip rather than fail.

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// A `redis-server` with AOF persistence, killed on drop.
pub struct RedisServer {
    child: Option<Child>,
    port: u16,
    dir: tempfile::TempDir,
    appendfsync: &'static str,
    secure: Option<Secure>,
}

/// TLS only (no plaintext port) with certificates from a test PKI, and a password.
struct Secure {
    ca_pem: String,
    password: String,
    /// The client certificate and key Redis demands (`tls-auth-clients yes`), if it does.
    client: Option<(String, String)>,
}

/// A loopback port nothing listens on (at the time of asking).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

impl RedisServer {
    /// `None` (with the reason printed) when redis-server is not installed.
    pub fn start() -> Option<Self> {
        Self::start_on(free_port())
    }

    /// [`RedisServer::start`] on a given port.
    pub fn start_on(port: u16) -> Option<Self> {
        Self::start_with(port, "always")
    }

    /// [`RedisServer::start`] with another AOF fsync policy (`everysec` is what
    /// deploy/docker-compose.yml runs).
    pub fn start_with_fsync(appendfsync: &'static str) -> Option<Self> {
        Self::start_with(free_port(), appendfsync)
    }

    fn start_with(port: u16, appendfsync: &'static str) -> Option<Self> {
        let Some(_) = super::find_binary("redis-server", &[]) else {
            eprintln!(
                "SKIPPED: redis-server is not installed (apt-get install redis-server); \
                 .ci/run installs it"
            );
            return None;
        };
        let mut r = Self {
            child: None,
            port,
            dir: tempfile::tempdir().unwrap(),
            appendfsync,
            secure: None,
        };
        r.spawn();
        Some(r)
    }

    /// A Redis that speaks only TLS (the server certificate from `pki`, for `localhost`) and
    /// requires `password`; with `client_certificates` it also demands a client certificate
    /// signed by the PKI's CA. `None` (with the reason printed) when redis-server is not
    /// installed or was built without TLS.
    pub fn start_tls(
        pki: &super::pki::Pki,
        password: &str,
        client_certificates: bool,
    ) -> Option<Self> {
        super::find_binary("redis-server", &[]).or_else(|| {
            eprintln!("SKIPPED: redis-server is not installed (apt-get install redis-server)");
            None
        })?;
        let dir = tempfile::tempdir().unwrap();
        for (name, pem) in [
            ("ca.pem", &pki.ca_pem),
            ("server.pem", &pki.server_cert),
            ("server.key", &pki.server_key),
        ] {
            std::fs::write(dir.path().join(name), pem).unwrap();
        }
        let mut r = Self {
            child: None,
            port: free_port(),
            dir,
            appendfsync: "always",
            secure: Some(Secure {
                ca_pem: pki.ca_pem.clone(),
                password: password.to_string(),
                client: client_certificates
                    .then(|| (pki.client_cert.clone(), pki.client_key.clone())),
            }),
        };
        if !r.spawn_checked() {
            eprintln!("SKIPPED: this redis-server was built without TLS (BUILD_TLS=yes)");
            return None;
        }
        Some(r)
    }

    fn spawn(&mut self) {
        assert!(self.spawn_checked(), "redis-server did not come up");
    }

    /// Starts the server and waits until it answers PING; false when it exits first (a build
    /// without TLS refuses the TLS options).
    fn spawn_checked(&mut self) -> bool {
        let mut cmd = Command::new("redis-server");
        cmd.args(["--bind", "127.0.0.1"]);
        match &self.secure {
            None => {
                cmd.args(["--port", &self.port.to_string()]);
            }
            Some(s) => {
                let file = |name: &str| self.dir.path().join(name).display().to_string();
                cmd.args(["--port", "0", "--tls-port", &self.port.to_string()])
                    .args(["--tls-cert-file", &file("server.pem")])
                    .args(["--tls-key-file", &file("server.key")])
                    .args(["--tls-ca-cert-file", &file("ca.pem")])
                    .args([
                        "--tls-auth-clients",
                        if s.client.is_some() { "yes" } else { "no" },
                    ])
                    .args(["--requirepass", &s.password]);
            }
        }
        let child = cmd
            .args([
                "--appendonly",
                "yes",
                "--appendfsync",
                self.appendfsync,
                "--save",
                "",
            ])
            .arg("--dir")
            .arg(self.dir.path())
            .stdout(Stdio::null())
            .spawn()
            .expect("redis-server starts");
        self.child = Some(child);
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            if let Ok(mut c) = self.client().get_connection() {
                if redis::cmd("PING").query::<String>(&mut c).is_ok() {
                    return true;
                }
            }
            if let Some(Ok(Some(_))) = self.child.as_mut().map(Child::try_wait) {
                self.child = None;
                return false;
            }
            assert!(Instant::now() < deadline, "redis-server did not come up");
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// A client of this server (over TLS with the PKI's CA and client certificate, and the
    /// password, when it is secure).
    fn client(&self) -> redis::Client {
        match &self.secure {
            None => redis::Client::open(self.url()).unwrap(),
            Some(s) => redis::Client::build_with_tls(
                self.url(),
                redis::TlsCertificates {
                    client_tls: s.client.as_ref().map(|(cert, key)| redis::ClientTlsConfig {
                        client_cert: cert.clone().into_bytes(),
                        client_key: key.clone().into_bytes(),
                    }),
                    root_cert: Some(s.ca_pem.clone().into_bytes()),
                },
            )
            .unwrap(),
        }
    }

    /// SIGKILL, then start again on the same port and data directory.
    pub fn crash_and_restart(&mut self) {
        if let Some(mut c) = self.child.take() {
            c.kill().unwrap();
            c.wait().unwrap();
        }
        self.spawn();
    }

    /// The server's URL: `redis://127.0.0.1:PORT/`, or for a TLS server
    /// `rediss://:PASSWORD@localhost:PORT/` (the name its certificate is for).
    pub fn url(&self) -> String {
        match &self.secure {
            None => format!("redis://127.0.0.1:{}/", self.port),
            Some(s) => format!("rediss://:{}@localhost:{}/", s.password, self.port),
        }
    }

    pub fn conn(&self) -> redis::Connection {
        self.client().get_connection().unwrap()
    }

    /// A field of a job record (tenant "" = no authentication).
    pub fn record_field(&self, id: &str, field: &str) -> Option<String> {
        redis::cmd("HGET")
            .arg(format!("murk:job::{id}"))
            .arg(field)
            .query(&mut self.conn())
            .unwrap()
    }
}

impl Drop for RedisServer {
    fn drop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}
