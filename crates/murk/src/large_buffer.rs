//! Zeroed buffers for the MVS volumes (`W·H·N` `f32` or `u16` values, 50 MB of `f32` at
//! 256×192×256) backed by transparent huge pages where Linux offers them.
//!
//! Why: a fresh 50 MB volume is first touched inside the plane sweep, and on the project's VMs
//! each 4 KiB first-touch page fault is expensive (and the faults of the two workers contend on
//! the process's memory lock). Measured on the default dehazing volume at 256×192×256 with one
//! source (`cargo bench -p murk --bench mvs`, docs/benchmarks.md): 86–92 ms with 4 KiB pages, 54–64 ms
//! with the volume advised to 2 MiB pages, back to back on one host.
//!
//! `madvise(MADV_HUGEPAGE)` is advice: with THP disabled (`/sys/kernel/mm/transparent_hugepage/
//! enabled` = `never`), on other systems, or for buffers under 2 MiB the buffer is an ordinary
//! zeroed `Vec`, with the same contents either way.

/// Huge-page size on x86-64 and aarch64 Linux with 4 KiB base pages.
const HUGE_PAGE: usize = 2 << 20;

/// A `vec![0; len]` of a plain numeric type (the `f32` cost volume, SGM's `u16` levels) whose
/// whole 2 MiB-aligned interior is advised to the kernel as a transparent-huge-page candidate
/// before anything touches it.
pub fn zeroed<T: bytemuck::Zeroable + Copy>(len: usize) -> Vec<T> {
    // All-zero bytes: `vec!` takes already-zeroed pages from the allocator instead of a memset.
    let mut data = vec![T::zeroed(); len];
    advise_huge_pages(&mut data);
    data
}

/// `buf` reused as a buffer of `len` values for a caller that overwrites every one of them: the
/// values kept from `buf` are left as they are (no `memset`, no fresh pages to fault in), new
/// ones are zero; a new [`zeroed`] when its capacity is too small. Depth estimation in strips
/// hands each strip's spent volumes on to the next this way.
pub fn reuse<T: bytemuck::Zeroable + Copy>(mut buf: Vec<T>, len: usize) -> Vec<T> {
    if buf.capacity() < len {
        drop(buf);
        return zeroed(len);
    }
    buf.resize(len, T::zeroed());
    buf
}

#[cfg(target_os = "linux")]
fn advise_huge_pages<T>(data: &mut [T]) {
    let start = data.as_mut_ptr() as usize;
    let end = start + std::mem::size_of_val(data);
    let aligned_start = start.next_multiple_of(HUGE_PAGE);
    let aligned_end = end & !(HUGE_PAGE - 1);
    if aligned_end > aligned_start {
        // SAFETY: the range lies inside `data`'s allocation (rounded inwards to page
        // boundaries), which this function borrows mutably; MADV_HUGEPAGE changes neither the
        // mapping nor its contents, only how the kernel backs it. A failure (e.g. EINVAL where
        // THP is compiled out) leaves ordinary pages, so the result is ignored.
        unsafe {
            libc::madvise(
                aligned_start as *mut libc::c_void,
                aligned_end - aligned_start,
                libc::MADV_HUGEPAGE,
            );
        }
    }
}

#[cfg(not(target_os = "linux"))]
fn advise_huge_pages<T>(_data: &mut [T]) {}

#[cfg(test)]
mod tests {
    use super::*;

    /// Zeroed, of the asked length, and writable end to end, for sizes below, at and above
    /// the huge-page size.
    #[test]
    fn zeroed_and_full_length() {
        for len in [0usize, 1, 1000, HUGE_PAGE / 4, 3 * HUGE_PAGE / 4 + 17] {
            let mut v = zeroed::<f32>(len);
            assert_eq!(v.len(), len);
            assert!(v.iter().all(|&x| x == 0.0));
            for (i, x) in v.iter_mut().enumerate() {
                *x = i as f32;
            }
            assert!(v.iter().enumerate().all(|(i, &x)| x == i as f32));
        }
    }

    /// Reused buffers come back at the asked length, whether they shrink, keep their size or
    /// must grow, keeping their memory when it is large enough.
    #[test]
    fn reused_buffers_have_the_asked_length() {
        for (had, len) in [(100usize, 40usize), (100, 100), (10, 1000), (0, 0)] {
            let buf = vec![7.0; had];
            let ptr = buf.as_ptr();
            let v = reuse(buf, len);
            assert_eq!(v.len(), len);
            assert_eq!(v.as_ptr() == ptr, len <= had);
            assert!(v[had.min(len)..].iter().all(|&x| x == 0.0));
        }
    }
}
