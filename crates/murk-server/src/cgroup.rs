//! The memory limit of the container or unit the server runs in, from Linux control groups,
//! so that memory bounds follow a pod's or a compose service's limit when the operator set none.
//!
//! - **cgroup v2** (unified): `/proc/self/cgroup` has the line `0::PATH`; the limit is the
//!   smallest `memory.max` of `PATH` and its ancestors (a parent's limit binds its children).
//!   `max` means none.
//! - **cgroup v1**: the `memory` controller's line `N:memory:PATH` (or `N:…,memory,…:PATH`);
//!   the limit is `memory.limit_in_bytes` under the memory hierarchy, where "no limit" is a value
//!   near `i64::MAX` rounded to the page size.
//!
//! Inside a container the process's cgroup is usually the namespace's root (`0::/`), whose
//! `memory.max` is the container's limit.

use std::path::{Path, PathBuf};

/// Values at or above this are v1's "no limit" (`i64::MAX` rounded down to a page) or larger
/// than any machine: 2^60 bytes.
const UNLIMITED: u64 = 1 << 60;

/// The memory limit of this process's cgroup, bytes; `None` when there is none or it cannot be
/// read (not Linux, no cgroup file system mounted).
pub fn memory_limit_bytes() -> Option<u64> {
    let cgroups = std::fs::read_to_string("/proc/self/cgroup").ok()?;
    memory_limit_in(Path::new("/sys/fs/cgroup"), &cgroups)
}

/// [`memory_limit_bytes`] with the cgroup file system at `root` and `/proc/self/cgroup`'s text.
pub(crate) fn memory_limit_in(root: &Path, proc_self_cgroup: &str) -> Option<u64> {
    for line in proc_self_cgroup.lines() {
        let mut parts = line.splitn(3, ':');
        let (Some(id), Some(controllers), Some(path)) = (parts.next(), parts.next(), parts.next())
        else {
            continue;
        };
        let relative = path.trim_start_matches('/');
        if id == "0" && controllers.is_empty() {
            // v2: walk from the process's group up to the root; the smallest limit binds.
            let mut dir = root.join(relative);
            let mut smallest: Option<u64> = None;
            loop {
                if let Some(limit) = read_limit(&dir.join("memory.max")) {
                    smallest = Some(smallest.map_or(limit, |s| s.min(limit)));
                }
                if dir == root || !dir.pop() {
                    break;
                }
            }
            // A v2 line where the v1 memory hierarchy is mounted too (hybrid) may name a group
            // without the memory controller: fall through to the v1 lines then.
            if smallest.is_some() {
                return smallest;
            }
        } else if controllers.split(',').any(|c| c == "memory") {
            let base: PathBuf = root.join("memory");
            return read_limit(&base.join(relative).join("memory.limit_in_bytes"))
                .or_else(|| read_limit(&base.join("memory.limit_in_bytes")));
        }
    }
    None
}

/// A limit file's value; `None` for `max`, a missing file, or a value meaning "no limit".
fn read_limit(file: &Path) -> Option<u64> {
    let text = std::fs::read_to_string(file).ok()?;
    let value: u64 = text.trim().parse().ok()?;
    (value > 0 && value < UNLIMITED).then_some(value)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(root: &Path, relative: &str, text: &str) {
        let file = root.join(relative);
        std::fs::create_dir_all(file.parent().unwrap()).unwrap();
        std::fs::write(file, text).unwrap();
    }

    #[test]
    fn v2_takes_the_smallest_limit_on_the_way_to_the_root() {
        let root = tempfile::tempdir().unwrap();
        let r = root.path();
        write(r, "kubepods/memory.max", "3221225472\n");
        write(r, "kubepods/pod1/memory.max", "max\n");
        write(r, "kubepods/pod1/c1/memory.max", "4294967296\n");
        assert_eq!(memory_limit_in(r, "0::/kubepods/pod1/c1\n"), Some(3 << 30));
        // Inside the container's namespace its group is the root.
        let ns = tempfile::tempdir().unwrap();
        write(ns.path(), "memory.max", "1073741824\n");
        assert_eq!(memory_limit_in(ns.path(), "0::/\n"), Some(1 << 30));
        write(ns.path(), "memory.max", "max\n");
        assert_eq!(memory_limit_in(ns.path(), "0::/\n"), None);
    }

    #[test]
    fn v1_reads_the_memory_hierarchy_and_ignores_no_limit() {
        let root = tempfile::tempdir().unwrap();
        let r = root.path();
        let cgroups = "12:cpu,cpuacct:/docker/abc\n4:memory:/docker/abc\n1:name=systemd:/x\n";
        write(r, "memory/docker/abc/memory.limit_in_bytes", "536870912\n");
        assert_eq!(memory_limit_in(r, cgroups), Some(512 << 20));
        write(
            r,
            "memory/docker/abc/memory.limit_in_bytes",
            "9223372036854771712\n",
        );
        assert_eq!(memory_limit_in(r, cgroups), None);
    }

    #[test]
    fn nothing_readable_is_no_limit() {
        let root = tempfile::tempdir().unwrap();
        assert_eq!(memory_limit_in(root.path(), "0::/\n"), None);
        assert_eq!(memory_limit_in(root.path(), "garbage"), None);
        assert_eq!(memory_limit_in(root.path(), ""), None);
    }
}
