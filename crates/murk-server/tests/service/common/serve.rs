//! Starting the `murk` binary as a child process. Its own file, so the examples that measure a
//! separate server process (`examples/watch_memory.rs`) include it too, with `#[path]`.

use std::time::Duration;

/// Starts `murk serve` (a command already carrying its flags, `--addr 127.0.0.1:0` among them)
/// as a separate process and returns it with its URL, read from the bound address in its log.
/// With `MURK_TEST_SERVER_LOGS` set, the server's log lines are echoed to the test's stderr.
pub fn spawn_serve(mut cmd: std::process::Command) -> (std::process::Child, String) {
    use std::io::BufRead;
    let mut child = cmd
        .env("MURK_LOG", "info")
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("murk serve starts");
    let stderr = child.stderr.take().expect("piped stderr");
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let echo = std::env::var_os("MURK_TEST_SERVER_LOGS").is_some();
        let mut sent = false;
        for line in std::io::BufReader::new(stderr)
            .lines()
            .map_while(Result::ok)
        {
            if !sent && line.contains("murk serving") {
                let addr = line
                    .split_whitespace()
                    .find_map(|w| w.strip_prefix("addr="))
                    .map(str::to_string);
                let _ = tx.send(addr);
                sent = true;
            }
            if echo {
                eprintln!("[server] {line}");
            }
        }
    });
    let addr = rx
        .recv_timeout(Duration::from_secs(60))
        .expect("server started")
        .expect("address in the log");
    (child, format!("http://{addr}"))
}
