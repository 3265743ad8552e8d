//! The resident set size of a process, for the examples that measure a separate server process
//! (`watch_memory`, `session_overload`), which include this file with `#[path]`.

/// Resident set size of `pid`, bytes (0 when `/proc` cannot tell: the process is gone, or this
/// is not Linux).
pub fn rss_bytes(pid: u32) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("VmRSS:"))
                .and_then(|v| v.split_whitespace().next()?.parse::<u64>().ok())
        })
        .map_or(0, |kib| kib * 1024)
}
