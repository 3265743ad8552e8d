//! How the `murk` process's allocator keeps freed memory between frames.
//!
//! A stream's frame allocates and frees the same tens of megabytes every time: a 640×480
//! stereo pair its smoothed and corrected views, cost rows and results, a 512×424 ToF frame its
//! solver levels and outputs. With glibc's defaults much of that goes back to the kernel when
//! the frame ends (trimmed off the top of a heap, or unmapped), and the next frame faults it in
//! again, a zeroed page at a time: on a 30-pair 640×480 bag, 170 000 page faults and 0.6 s of
//! system time for 2.9 s of work. [`keep_working_set`] sets two fixed thresholds instead:
//!
//! - blocks from [`MMAP_THRESHOLD_BYTES`] up are mapped on their own and unmapped when freed
//!   (the default threshold adapts between 128 KiB and the same 32 MiB, and moves as frames
//!   free their buffers);
//! - up to [`TRIM_THRESHOLD_BYTES`] of free memory at the top of a heap stays with the process
//!   for the next frame.
//!
//! The same bag then takes 50 000 faults and runs about 5 % faster, for 20–30 MiB more peak
//! memory (docs/benchmarks.md). An operator who sets glibc's malloc tunables
//! (`GLIBC_TUNABLES=glibc.malloc.…`) keeps them: murk then leaves the allocator alone.

/// Blocks at least this large are mapped on their own and returned when freed, bytes: the
/// largest threshold glibc accepts on 64-bit systems (`DEFAULT_MMAP_THRESHOLD_MAX`).
pub const MMAP_THRESHOLD_BYTES: usize = 32 << 20;

/// Free memory at the top of a heap kept for the next allocation, bytes: a few frames' working
/// set, so that a stream does not hand its buffers back between frames.
pub const TRIM_THRESHOLD_BYTES: usize = 128 << 20;

/// What [`keep_working_set`] did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AllocatorPolicy {
    /// The thresholds are set.
    Applied,
    /// The environment sets glibc's malloc tunables; they stay in force.
    OperatorTunables,
    /// Not glibc, or glibc refused a setting: the allocator's defaults stay.
    Unavailable,
}

/// Whether `GLIBC_TUNABLES` (its value, if set) sets any of glibc's malloc tunables.
pub fn sets_malloc_tunables(glibc_tunables: Option<&str>) -> bool {
    glibc_tunables.is_some_and(|v| {
        v.split(':')
            .any(|t| t.trim_start().starts_with("glibc.malloc."))
    })
}

/// Sets the thresholds of the module docs, unless `GLIBC_TUNABLES` sets malloc tunables. Call
/// it first thing in `main`, before other threads allocate.
pub fn keep_working_set() -> AllocatorPolicy {
    if sets_malloc_tunables(std::env::var("GLIBC_TUNABLES").ok().as_deref()) {
        return AllocatorPolicy::OperatorTunables;
    }
    apply()
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn apply() -> AllocatorPolicy {
    // SAFETY: `mallopt` only changes glibc's allocation parameters, under the allocator's own
    // lock; both values are within the ranges glibc documents for these options.
    let ok = unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES as libc::c_int) == 1
            && libc::mallopt(libc::M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES as libc::c_int) == 1
    };
    if ok {
        AllocatorPolicy::Applied
    } else {
        AllocatorPolicy::Unavailable
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn apply() -> AllocatorPolicy {
    AllocatorPolicy::Unavailable
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_operators_malloc_tunables_are_recognised() {
        assert!(!sets_malloc_tunables(None));
        assert!(!sets_malloc_tunables(Some("")));
        assert!(!sets_malloc_tunables(Some("glibc.rtld.nns=2")));
        assert!(sets_malloc_tunables(Some("glibc.malloc.trim_threshold=0")));
        assert!(sets_malloc_tunables(Some(
            "glibc.rtld.nns=2:glibc.malloc.arena_max=2"
        )));
    }

    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    #[test]
    fn glibc_accepts_the_thresholds() {
        // The same calls as `keep_working_set`, whatever the test's environment says.
        assert_eq!(apply(), AllocatorPolicy::Applied);
    }
}
