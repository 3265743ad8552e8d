//! Cholesky factorisations and solves on faer, sequential by argument.
//!
//! murk parallelises over pixels, rows and jobs on rayon. faer's own parallel kernels (dense
//! factorisations from about 100 unknowns, the supernodal sparse Cholesky) hand work to
//! separate worker threads (the `spindle` crate) that keep spinning after the call returns. On
//! the 2-core host those threads took the cores from everything that ran afterwards in the same
//! process: one photometric-stereo normal integration (300 × 300 sparse Cholesky) made every
//! later 424 × 512 ToF frame 2.2× slower (578 → 1 298 ms), one 96 × 96 dense Cholesky 1.35×;
//! and the integration itself ran faster sequentially (120–146 ms against 200–210 ms).
//!
//! So every faer call in murk goes through this module, which passes [`Par::Seq`] to faer's
//! factorisation and solve kernels. faer's process-wide setting (`faer::set_global_parallelism`)
//! is never read or written: a program that embeds murk keeps whatever it chose for its own
//! faer calls.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt;
use faer::sparse::linalg::cholesky::{factorize_symbolic_cholesky, LltRef, SymbolicCholesky};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Conj, Mat, MatMut, Par, Side};

/// The parallelism murk passes to every faer kernel.
const PAR: Par = Par::Seq;

/// A sparse symmetric positive-definite matrix's `L Lᵀ` factorisation: the symbolic analysis
/// (fill-reducing ordering, elimination tree) done once for a sparsity pattern, the numeric
/// factorisation redone whenever the values change.
#[derive(Debug)]
pub(crate) struct SparseLlt {
    symbolic: SymbolicCholesky<usize>,
    /// The numeric factor's values, `symbolic.len_val()` of them; meaningful after
    /// [`SparseLlt::factorize`] succeeded.
    values: Vec<f64>,
}

impl SparseLlt {
    /// Analyses the pattern of a square matrix of which only `side`'s triangle is read.
    pub(crate) fn analyse(
        pattern: SymbolicSparseColMatRef<'_, usize>,
        side: Side,
    ) -> Result<Self, faer::sparse::FaerError> {
        let symbolic =
            factorize_symbolic_cholesky(pattern, side, Default::default(), Default::default())?;
        let values = vec![0.0; symbolic.len_val()];
        Ok(Self { symbolic, values })
    }

    /// Factorises `mat`, which must have the analysed pattern; only `side`'s triangle is read.
    /// Fails where the matrix is not numerically positive definite.
    pub(crate) fn factorize(
        &mut self,
        mat: SparseColMatRef<'_, usize, f64>,
        side: Side,
    ) -> Result<(), faer::linalg::cholesky::llt::factor::LltError> {
        let mut scratch = MemBuffer::new(
            self.symbolic
                .factorize_numeric_llt_scratch::<f64>(PAR, Default::default()),
        );
        self.symbolic.factorize_numeric_llt(
            &mut self.values,
            mat,
            side,
            Default::default(),
            PAR,
            MemStack::new(&mut scratch),
            Default::default(),
        )?;
        Ok(())
    }

    /// Overwrites `x` (one column of the matrix's size) with `A⁻¹ x`, by the last factorisation.
    pub(crate) fn solve_in_place(&self, x: &mut [f64]) {
        let n = x.len();
        let mut scratch = MemBuffer::new(self.symbolic.solve_in_place_scratch::<f64>(1, PAR));
        LltRef::<'_, usize, f64>::new(&self.symbolic, &self.values).solve_in_place_with_conj(
            Conj::No,
            MatMut::from_column_major_slice_mut(x, n, 1),
            PAR,
            MemStack::new(&mut scratch),
        );
    }
}

/// A dense symmetric positive-definite matrix's `L Lᵀ` factorisation.
#[derive(Debug)]
pub(crate) struct DenseLlt {
    /// `L` in the lower triangle, zeros above.
    l: Mat<f64>,
}

impl DenseLlt {
    /// Factorises `a`, reading its lower triangle. `None` where `a` is not numerically
    /// positive definite.
    pub(crate) fn factorize(a: &Mat<f64>) -> Option<Self> {
        let n = a.nrows();
        let mut l = Mat::<f64>::zeros(n, n);
        l.copy_from_triangular_lower(a);
        let mut scratch = MemBuffer::new(llt::factor::cholesky_in_place_scratch::<f64>(
            n,
            PAR,
            Default::default(),
        ));
        llt::factor::cholesky_in_place(
            l.as_mut(),
            Default::default(),
            PAR,
            MemStack::new(&mut scratch),
            Default::default(),
        )
        .ok()?;
        Some(Self { l })
    }

    /// Overwrites `rhs` with `A⁻¹ rhs`.
    pub(crate) fn solve_in_place(&self, rhs: MatMut<'_, f64>) {
        let mut scratch = MemBuffer::new(llt::solve::solve_in_place_scratch::<f64>(
            self.l.nrows(),
            rhs.ncols(),
            PAR,
        ));
        llt::solve::solve_in_place_with_conj(
            self.l.as_ref(),
            Conj::No,
            rhs,
            PAR,
            MemStack::new(&mut scratch),
        );
    }

    /// The diagonal of `A⁻¹` (e.g. the variances of a Gauss–Newton fit's parameters).
    pub(crate) fn inverse_diagonal(&self) -> Vec<f64> {
        let n = self.l.nrows();
        let mut inverse = Mat::<f64>::zeros(n, n);
        let mut scratch = MemBuffer::new(llt::inverse::inverse_scratch::<f64>(n, PAR));
        llt::inverse::inverse(
            inverse.as_mut(),
            self.l.as_ref(),
            PAR,
            MemStack::new(&mut scratch),
        );
        (0..n).map(|i| inverse[(i, i)]).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use faer::sparse::{SparseColMat, Triplet};

    /// A 1-D Laplacian plus a diagonal shift: SPD, tridiagonal.
    fn laplacian(n: usize, shift: f64) -> Vec<Triplet<usize, usize, f64>> {
        let mut t = Vec::new();
        for i in 0..n {
            t.push(Triplet::new(i, i, 2.0 + shift));
            if i + 1 < n {
                t.push(Triplet::new(i + 1, i, -1.0));
            }
        }
        t
    }

    fn residual(n: usize, shift: f64, x: &[f64], b: &[f64]) -> f64 {
        (0..n)
            .map(|i| {
                let mut ax = (2.0 + shift) * x[i];
                if i > 0 {
                    ax -= x[i - 1];
                }
                if i + 1 < n {
                    ax -= x[i + 1];
                }
                (ax - b[i]).abs()
            })
            .fold(0.0, f64::max)
    }

    #[test]
    fn sparse_solve_inverts_the_matrix_and_refactorises_new_values() {
        let n = 50;
        let b: Vec<f64> = (0..n).map(|i| (i as f64 * 0.37).sin()).collect();
        let mat = SparseColMat::try_new_from_triplets(n, n, &laplacian(n, 0.1)).unwrap();
        let mut llt = SparseLlt::analyse(mat.symbolic(), Side::Lower).unwrap();
        for shift in [0.1, 3.0] {
            let mat = SparseColMat::try_new_from_triplets(n, n, &laplacian(n, shift)).unwrap();
            llt.factorize(mat.as_ref(), Side::Lower).unwrap();
            let mut x = b.clone();
            llt.solve_in_place(&mut x);
            assert!(residual(n, shift, &x, &b) < 1e-12, "shift {shift}");
        }
    }

    #[test]
    fn dense_solve_inverts_the_matrix_and_rejects_an_indefinite_one() {
        let n = 6;
        let a = Mat::<f64>::from_fn(n, n, |i, j| match i.abs_diff(j) {
            0 => 2.5,
            1 => -1.0,
            _ => 0.0,
        });
        let b: Vec<f64> = (0..n).map(|i| i as f64 - 2.0).collect();
        let llt = DenseLlt::factorize(&a).unwrap();
        let mut x = Mat::<f64>::from_fn(n, 1, |i, _| b[i]);
        llt.solve_in_place(x.as_mut());
        let x: Vec<f64> = (0..n).map(|i| x[(i, 0)]).collect();
        assert!(residual(n, 0.5, &x, &b) < 1e-12);

        // Column i of A⁻¹ solves A y = e_i.
        for (i, d) in llt.inverse_diagonal().into_iter().enumerate() {
            let mut e = Mat::<f64>::from_fn(n, 1, |k, _| f64::from(u8::from(k == i)));
            llt.solve_in_place(e.as_mut());
            assert!((e[(i, 0)] - d).abs() < 1e-12);
        }

        let indefinite = Mat::<f64>::from_fn(2, 2, |i, j| if i == j { -1.0 } else { 0.0 });
        assert!(DenseLlt::factorize(&indefinite).is_none());
    }

    #[test]
    fn the_global_setting_is_left_alone() {
        let before = format!("{:?}", faer::get_global_parallelism());
        let mut x = Mat::<f64>::from_fn(3, 1, |i, _| i as f64);
        DenseLlt::factorize(&Mat::<f64>::identity(3, 3))
            .unwrap()
            .solve_in_place(x.as_mut());
        assert_eq!(format!("{:?}", faer::get_global_parallelism()), before);
    }
}
