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
        };
        r.spawn();
        Some(r)
    }

    fn spawn(&mut self) {
        let child = Command::new("redis-server")
            .args(["--bind", "127.0.0.1", "--port", &self.port.to_string()])
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
        let client = redis::Client::open(self.url()).unwrap();
        loop {
            if let Ok(mut c) = client.get_connection() {
                if redis::cmd("PING").query::<String>(&mut c).is_ok() {
                    return;
                }
            }
            assert!(Instant::now() < deadline, "redis-server did not come up");
            std::thread::sleep(Duration::from_millis(20));
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

    pub fn url(&self) -> String {
        format!("redis://127.0.0.1:{}/", self.port)
    }

    pub fn conn(&self) -> redis::Connection {
        redis::Client::open(self.url())
            .unwrap()
            .get_connection()
            .unwrap()
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
