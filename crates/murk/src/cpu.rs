//! Which vector instructions the hot loops may use, decided once per process at run time.
//!
//! The AVX2 loops (the MVS cost volume's rows, SGM's path step, the photometric-stereo kernel
//! entries) compute the same results as their plain copies, bit for bit; tests check that by
//! forcing the plain copies on a CPU that has AVX2 (`force_scalar`). The few loops with an
//! AVX-512 copy as well ([`avx512bw_enabled`]) are checked against the AVX2 and plain ones the
//! same way (`force_no_avx512`).

#[cfg(test)]
thread_local! {
    /// Set by tests to run the plain loops on this thread.
    static FORCE_SCALAR: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
    /// Set by tests to run the AVX2 (or plain) loops instead of the AVX-512 ones on this thread.
    static FORCE_NO_AVX512: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Whether the AVX2 loops run: the CPU has AVX2 (the standard library caches the detection),
/// and no test on this thread asked for the plain loops. Always false off x86-64.
#[inline]
pub(crate) fn avx2_enabled() -> bool {
    #[cfg(test)]
    if FORCE_SCALAR.with(|f| f.get()) {
        return false;
    }
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Makes [`avx2_enabled`] report false on this thread (`true`) or the CPU's answer again
/// (`false`).
#[cfg(test)]
pub(crate) fn force_scalar(on: bool) {
    FORCE_SCALAR.with(|f| f.set(on));
}

/// Whether the AVX-512 loops run: the CPU has AVX-512 F, BW (16-bit lanes and masks) and VL,
/// and no test on this thread asked for the AVX2 or plain loops. Always false off x86-64.
#[inline]
pub(crate) fn avx512bw_enabled() -> bool {
    #[cfg(test)]
    if FORCE_SCALAR.with(|f| f.get()) || FORCE_NO_AVX512.with(|f| f.get()) {
        return false;
    }
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512bw")
            && std::arch::is_x86_feature_detected!("avx512vl")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Makes [`avx512bw_enabled`] report false on this thread (`true`) or the CPU's answer again
/// (`false`); [`avx2_enabled`] is unchanged.
#[cfg(test)]
pub(crate) fn force_no_avx512(on: bool) {
    FORCE_NO_AVX512.with(|f| f.set(on));
}

/// Which copies of the hot loops run, read once on the calling thread and handed to loops that
/// run on rayon's workers (a test's `force_scalar` and `force_no_avx512` are thread-local
/// and do not reach the workers).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Isa {
    /// [`avx2_enabled`].
    pub avx2: bool,
    /// [`avx512bw_enabled`].
    pub avx512: bool,
}

impl Isa {
    /// The copies this thread may use now.
    pub(crate) fn detect() -> Self {
        Self {
            avx2: avx2_enabled(),
            avx512: avx512bw_enabled(),
        }
    }
}

/// Defines `$vis fn $name(..) -> $ret` that calls the plain function `$body` (which must be
/// `#[inline(always)]`) through a copy compiled with AVX2 enabled where the CPU has it
/// ([`avx2_enabled`]): the same operations on wider registers, so the same results. The target
/// feature enables neither FMA nor fast-math, so the compiler may not contract or reorder the
/// body's float operations in either copy.
macro_rules! compiled_for_avx2 {
    ($(#[$doc:meta])* $vis:vis fn $name:ident($($arg:ident: $ty:ty),* $(,)?) $(-> $ret:ty)?
        => $body:path;) => {
        $(#[$doc])*
        #[inline]
        $vis fn $name($($arg: $ty),*) $(-> $ret)? {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx2")]
                unsafe fn with_avx2($($arg: $ty),*) $(-> $ret)? {
                    $body($($arg),*)
                }
                if $crate::cpu::avx2_enabled() {
                    // SAFETY: AVX2 is present.
                    return unsafe { with_avx2($($arg),*) };
                }
            }
            $body($($arg),*)
        }
    };
}
pub(crate) use compiled_for_avx2;
