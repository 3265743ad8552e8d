//! faer runs single-threaded inside murk.
//!
//! murk parallelises over pixels, rows and jobs on rayon. faer's own parallel kernels (dense
//! factorisations from about 100 unknowns, the supernodal sparse Cholesky) hand work to
//! separate worker threads (the `spindle` crate) that keep spinning after the call returns. On
//! the 2-core host those threads took the cores from everything that ran afterwards in the same
//! process: one photometric-stereo normal integration (300 × 300 sparse Cholesky) made every
//! later 424 × 512 ToF frame 2.2× slower (578 → 1 298 ms), one 96 × 96 dense Cholesky 1.35×;
//! and the integration itself ran faster sequentially (120–146 ms against 200–210 ms). So
//! every murk function that calls faer first sets faer's global parallelism to sequential.
//! It is a process-wide faer setting: an application that wants faer's threads for its own
//! work can set it again after murk's first call.

use std::sync::Once;

static SEQUENTIAL: Once = Once::new();

/// Sets faer's global parallelism to sequential, once per process.
pub(crate) fn sequential_faer() {
    SEQUENTIAL.call_once(|| faer::set_global_parallelism(faer::Par::Seq));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn faer_is_sequential_after_murk_sets_it() {
        sequential_faer();
        assert!(matches!(faer::get_global_parallelism(), faer::Par::Seq));
    }
}
