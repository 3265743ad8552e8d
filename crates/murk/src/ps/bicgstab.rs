//! Block BiCGStab (van der Vorst 1992, reference \[70\]) for the k = m right-hand sides of
//! Eq. 4.52, one per light source.
//!
//! The k systems share the operator but not their Krylov spaces: each column runs its own
//! BiCGStab recurrence (own ρ, α, ω), only in lockstep, so that every operator application is a
//! single pass over the operator's data (the scattering kernel) for all k vectors at once. That
//! pass, not the vector arithmetic, dominates the cost, which is why the columns are batched
//! rather than solved one after another.
//!
//! Per iteration and column (unpreconditioned BiCGStab, Saad's "Iterative Methods", Alg. 7.7):
//!
//! ```text
//! ρ' = (r̂, r);  β = (ρ'/ρ)(α/ω);  p = r + β(p − ω v);  v = A p;  α = ρ'/(r̂, v)
//! s = r − α v;                       (stop with x += α p if ‖s‖ ≤ tol‖b‖)
//! t = A s;  ω = (t, s)/(t, t);  x += α p + ω s;  r = s − ω t
//! ```
//!
//! Breakdown — ρ' ≈ 0, (r̂, v) ≈ 0 or ω ≈ 0, each measured as a cosine below
//! [`BREAKDOWN_COSINE`] — restarts that column from its current iterate with the shadow residual
//! r̂ = r (and p = v = 0, ρ = α = ω = 1), keeping whatever progress the half step made. A
//! column whose operator is such that every restart breaks down again (e.g. skew-symmetric A,
//! where (r, A r) = 0) just runs out of iterations and is reported as not converged.

use rayon::prelude::*;

use crate::error::{MurkError, Result};
use crate::monitor::Monitor;

/// A linear operator applied to k vectors in one pass.
pub trait BlockOperator: Sync {
    /// Length of one vector.
    fn dim(&self) -> usize;

    /// `ys[j·dim..(j+1)·dim] = A · xs[j·dim..(j+1)·dim]` for j < k. Implementations should
    /// overwrite `ys` (it holds stale data) and traverse their own data once for all k columns.
    fn apply_block(&self, xs: &[f64], ys: &mut [f64], k: usize);
}

/// Stopping rule of [`bicgstab_block`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BicgstabParams {
    /// A column stops once its (recursively updated) residual satisfies ‖r‖ ≤ tol·‖b‖.
    pub rel_tolerance: f64,
    /// Iteration cap per column; each iteration applies the operator twice.
    pub max_iterations: usize,
}

impl Default for BicgstabParams {
    fn default() -> Self {
        Self {
            rel_tolerance: 1e-6,
            max_iterations: 500,
        }
    }
}

/// Outcome of [`bicgstab_block`], one entry per column.
#[derive(Clone, Debug, PartialEq)]
pub struct BicgstabReport {
    /// Iterations the column ran (0 if the initial guess already satisfied the tolerance).
    pub iterations: Vec<usize>,
    /// True relative residual ‖b − A x‖/‖b‖ of the returned x, recomputed after the iteration
    /// (0 for b = 0). It can differ in the last digits from the recursive residual used for
    /// stopping.
    pub rel_residuals: Vec<f64>,
    /// Whether the column met the tolerance (by the recursive residual) within the cap.
    pub converged: Vec<bool>,
}

/// Cosine below which an inner product counts as a breakdown (see the module documentation).
/// Healthy iterations keep these cosines many orders of magnitude larger; only a genuinely
/// (near-)orthogonal pair, where the next coefficient would be noise, gets near it.
pub const BREAKDOWN_COSINE: f64 = 1e-13;

/// Chunk length of the parallel vector kernels: large enough that rayon's per-task overhead is
/// negligible, small enough that n ≈ 40k–90k still splits over several cores. The chunking is
/// fixed, so reductions are deterministic (bit-identical for a column solved alone or in a
/// block).
const CHUNK: usize = 4096;

/// Per-column inner products (a_j, b_j) into `out`, with `partials` as scratch.
fn dots(a: &[f64], b: &[f64], n: usize, partials: &mut [f64], out: &mut [f64]) {
    let nchunks = n.div_ceil(CHUNK).max(1);
    partials.par_iter_mut().enumerate().for_each(|(idx, o)| {
        let (j, c) = (idx / nchunks, idx % nchunks);
        let lo = j * n + (c * CHUNK).min(n);
        let hi = j * n + ((c + 1) * CHUNK).min(n);
        *o = a[lo..hi].iter().zip(&b[lo..hi]).map(|(p, q)| p * q).sum();
    });
    for (j, o) in out.iter_mut().enumerate() {
        *o = partials[j * nchunks..(j + 1) * nchunks].iter().sum();
    }
}

/// Runs `f(j, start, chunk)` on the chunks of every column j with `sel[j]`, where `chunk` is
/// `y[start..start + chunk.len()]`.
fn update(y: &mut [f64], n: usize, sel: &[bool], f: impl Fn(usize, usize, &mut [f64]) + Sync) {
    if n == 0 {
        return;
    }
    y.par_chunks_mut(n)
        .enumerate()
        .filter(|(j, _)| sel[*j])
        .for_each(|(j, col)| {
            col.par_chunks_mut(CHUNK)
                .enumerate()
                .for_each(|(c, ch)| f(j, j * n + c * CHUNK, ch));
        });
}

fn col(v: &mut [f64], n: usize, j: usize) -> &mut [f64] {
    &mut v[j * n..(j + 1) * n]
}

/// Solves A x_j = b_j for the k columns of `b` (each `op.dim()` long, one after another) by k
/// lockstep BiCGStab iterations; `x` holds the initial guesses on entry and the solutions on
/// return.
///
/// Columns with b_j = 0 return x_j = 0 without iterating. Converged columns are frozen: from
/// then on they pass through [`BlockOperator::apply_block`] as zero vectors (the pass costs the
/// same either way) and their outputs are ignored. Not converging within
/// `params.max_iterations` is not an error; the report says which columns did. The monitor is
/// checked once per iteration, so a cancelled job stops with [`MurkError::Cancelled`] after at
/// most two operator applications. Errors name `k`, `b`, `x`, `rel_tolerance`; a non-finite
/// inner product (operator or input producing NaN/∞) is a [`MurkError::Numerical`].
pub fn bicgstab_block(
    op: &impl BlockOperator,
    b: &[f64],
    x: &mut [f64],
    k: usize,
    params: &BicgstabParams,
    monitor: &Monitor,
) -> Result<BicgstabReport> {
    let n = op.dim();
    if k == 0 {
        return Err(MurkError::invalid("k", "must be at least 1"));
    }
    let len = n
        .checked_mul(k)
        .ok_or_else(|| MurkError::invalid("k", "k·dim overflows"))?;
    if b.len() != len {
        return Err(MurkError::invalid(
            "b",
            format!("expected k·dim = {len} entries, got {}", b.len()),
        ));
    }
    if x.len() != len {
        return Err(MurkError::invalid(
            "x",
            format!("expected k·dim = {len} entries, got {}", x.len()),
        ));
    }
    let tol = params.rel_tolerance;
    if !tol.is_finite() || tol <= 0.0 {
        return Err(MurkError::invalid(
            "rel_tolerance",
            format!("must be finite and > 0, got {tol}"),
        ));
    }
    if b.iter().chain(x.iter()).any(|v| !v.is_finite()) {
        return Err(MurkError::invalid(
            if b.iter().any(|v| !v.is_finite()) {
                "b"
            } else {
                "x"
            },
            "must be finite",
        ));
    }

    let nchunks = n.div_ceil(CHUNK).max(1);
    let mut partials = vec![0.0; k * nchunks];
    let mut d1 = vec![0.0; k];
    let mut d2 = vec![0.0; k];
    let mut d3 = vec![0.0; k];
    let mut broke = vec![false; k];

    let mut report = BicgstabReport {
        iterations: vec![0; k],
        rel_residuals: vec![0.0; k],
        converged: vec![false; k],
    };
    let mut bnorm = vec![0.0; k];
    dots(b, b, n, &mut partials, &mut bnorm);
    bnorm.iter_mut().for_each(|v| *v = v.sqrt());
    // active: still iterating; step: takes part in the current (half) step.
    let mut active: Vec<bool> = bnorm.iter().map(|&v| v > 0.0).collect();
    for j in (0..k).filter(|&j| !active[j]) {
        col(x, n, j).fill(0.0);
        report.converged[j] = true;
    }
    if !active.contains(&true) {
        return Ok(report);
    }

    let mut r = vec![0.0; len];
    let mut t = vec![0.0; len];
    op.apply_block(x, &mut t, k);
    r.par_iter_mut()
        .zip(b.par_iter().zip(t.par_iter()))
        .with_min_len(CHUNK)
        .for_each(|(ri, (bi, ti))| *ri = bi - ti);
    let mut rnorm = vec![0.0; k];
    dots(&r, &r, n, &mut partials, &mut rnorm);
    rnorm.iter_mut().for_each(|v| *v = v.sqrt());
    for j in 0..k {
        if active[j] && rnorm[j] <= tol * bnorm[j] {
            active[j] = false;
            report.converged[j] = true;
        }
    }
    let mut r_hat = r.clone();
    let mut r_hat_norm = rnorm.clone();
    let mut p = vec![0.0; len];
    let mut v = vec![0.0; len];
    let mut rho = vec![1.0; k];
    let mut alpha = vec![1.0; k];
    let mut omega = vec![1.0; k];
    let mut beta = vec![0.0; k];
    let mut step = vec![false; k];
    for j in (0..k).filter(|&j| !active[j]) {
        col(&mut r, n, j).fill(0.0);
    }

    // Fresh start of column j from its current residual (also the breakdown restart).
    let restart = |j: usize,
                   r: &[f64],
                   r_hat: &mut [f64],
                   r_hat_norm: &mut [f64],
                   rnorm: f64,
                   p: &mut [f64],
                   v: &mut [f64],
                   coef: [&mut [f64]; 3]| {
        col(r_hat, n, j).copy_from_slice(&r[j * n..(j + 1) * n]);
        r_hat_norm[j] = rnorm;
        col(p, n, j).fill(0.0);
        col(v, n, j).fill(0.0);
        for c in coef {
            c[j] = 1.0;
        }
    };
    let finite = |vals: &[f64], sel: &[bool], what: &str| -> Result<()> {
        if vals.iter().zip(sel).any(|(v, &s)| s && !v.is_finite()) {
            return Err(MurkError::Numerical(format!(
                "BiCGStab: non-finite {what} (operator or input produced NaN/∞)"
            )));
        }
        Ok(())
    };

    for iter in 1..=params.max_iterations {
        if !active.contains(&true) {
            break;
        }
        monitor.checkpoint()?;
        step.copy_from_slice(&active);

        // ρ' = (r̂, r) → β, p.
        dots(&r_hat, &r, n, &mut partials, &mut d1);
        finite(&d1, &step, "(r̂, r)")?;
        for j in 0..k {
            if !step[j] {
                continue;
            }
            if d1[j].abs() <= BREAKDOWN_COSINE * r_hat_norm[j] * rnorm[j] {
                restart(
                    j,
                    &r,
                    &mut r_hat,
                    &mut r_hat_norm,
                    rnorm[j],
                    &mut p,
                    &mut v,
                    [&mut rho, &mut alpha, &mut omega],
                );
                d1[j] = rnorm[j] * rnorm[j];
            }
            beta[j] = (d1[j] / rho[j]) * (alpha[j] / omega[j]);
            rho[j] = d1[j];
        }
        update(&mut p, n, &step, |j, s, ch| {
            let (bj, wj) = (beta[j], omega[j]);
            let e = s + ch.len();
            for ((pi, ri), vi) in ch.iter_mut().zip(&r[s..e]).zip(&v[s..e]) {
                *pi = ri + bj * (*pi - wj * vi);
            }
        });

        // v = A p, α = ρ'/(r̂, v), s = r − α v (stored in r).
        op.apply_block(&p, &mut v, k);
        dots(&r_hat, &v, n, &mut partials, &mut d1);
        dots(&v, &v, n, &mut partials, &mut d2);
        finite(&d1, &step, "(r̂, v)")?;
        finite(&d2, &step, "(v, v)")?;
        for j in 0..k {
            if !step[j] {
                continue;
            }
            if d1[j].abs() <= BREAKDOWN_COSINE * r_hat_norm[j] * d2[j].sqrt() {
                restart(
                    j,
                    &r,
                    &mut r_hat,
                    &mut r_hat_norm,
                    rnorm[j],
                    &mut p,
                    &mut v,
                    [&mut rho, &mut alpha, &mut omega],
                );
                step[j] = false;
                report.iterations[j] = iter;
            } else {
                alpha[j] = rho[j] / d1[j];
            }
        }
        update(&mut r, n, &step, |j, s, ch| {
            let aj = alpha[j];
            let e = s + ch.len();
            for (ri, vi) in ch.iter_mut().zip(&v[s..e]) {
                *ri -= aj * vi;
            }
        });
        dots(&r, &r, n, &mut partials, &mut d2);
        finite(&d2, &step, "(s, s)")?;
        // Half-step convergence: x += α p and freeze.
        for j in 0..k {
            if !step[j] {
                continue;
            }
            if d2[j].sqrt() <= tol * bnorm[j] {
                let aj = alpha[j];
                let (xs, ps) = (col(x, n, j), &p[j * n..(j + 1) * n]);
                xs.par_iter_mut()
                    .zip(ps.par_iter())
                    .with_min_len(CHUNK)
                    .for_each(|(xi, pi)| *xi += aj * pi);
                step[j] = false;
                active[j] = false;
                report.converged[j] = true;
                report.iterations[j] = iter;
                col(&mut r, n, j).fill(0.0);
                col(&mut p, n, j).fill(0.0);
            }
        }

        // t = A s, ω = (t, s)/(t, t), x += α p + ω s, r = s − ω t.
        op.apply_block(&r, &mut t, k);
        // d2 still holds (s, s).
        dots(&t, &r, n, &mut partials, &mut d1);
        dots(&t, &t, n, &mut partials, &mut d3);
        finite(&d1, &step, "(t, s)")?;
        finite(&d3, &step, "(t, t)")?;
        for j in 0..k {
            if !step[j] {
                continue;
            }
            let tn = d3[j].sqrt();
            broke[j] = false;
            if tn == 0.0 || d1[j].abs() <= BREAKDOWN_COSINE * tn * d2[j].sqrt() {
                broke[j] = true;
                omega[j] = 0.0;
            } else {
                omega[j] = d1[j] / d3[j];
            }
        }
        update(x, n, &step, |j, s, ch| {
            let (aj, wj) = (alpha[j], omega[j]);
            let e = s + ch.len();
            for ((xi, pi), si) in ch.iter_mut().zip(&p[s..e]).zip(&r[s..e]) {
                *xi += aj * pi + wj * si;
            }
        });
        update(&mut r, n, &step, |j, s, ch| {
            let wj = omega[j];
            let e = s + ch.len();
            for (ri, ti) in ch.iter_mut().zip(&t[s..e]) {
                *ri -= wj * ti;
            }
        });
        dots(&r, &r, n, &mut partials, &mut d2);
        finite(&d2, &step, "(r, r)")?;
        for j in 0..k {
            if !step[j] {
                continue;
            }
            rnorm[j] = d2[j].sqrt();
            report.iterations[j] = iter;
            if rnorm[j] <= tol * bnorm[j] {
                active[j] = false;
                report.converged[j] = true;
                col(&mut r, n, j).fill(0.0);
                col(&mut p, n, j).fill(0.0);
            } else if broke[j] {
                restart(
                    j,
                    &r,
                    &mut r_hat,
                    &mut r_hat_norm,
                    rnorm[j],
                    &mut p,
                    &mut v,
                    [&mut rho, &mut alpha, &mut omega],
                );
            }
        }
    }

    // True residuals of the returned iterates.
    op.apply_block(x, &mut t, k);
    r.par_iter_mut()
        .zip(b.par_iter().zip(t.par_iter()))
        .with_min_len(CHUNK)
        .for_each(|(ri, (bi, ti))| *ri = bi - ti);
    dots(&r, &r, n, &mut partials, &mut d2);
    for j in 0..k {
        report.rel_residuals[j] = if bnorm[j] > 0.0 {
            d2[j].sqrt() / bnorm[j]
        } else {
            0.0
        };
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use std::sync::atomic::{AtomicUsize, Ordering};

    /// Sparse matrix in compressed rows; `apply_block` walks the rows once for all k vectors.
    struct Csr {
        n: usize,
        ptr: Vec<usize>,
        idx: Vec<usize>,
        val: Vec<f64>,
        applies: AtomicUsize,
    }

    impl Csr {
        fn from_rows(rows: Vec<Vec<(usize, f64)>>) -> Self {
            let mut ptr = vec![0];
            let (mut idx, mut val) = (Vec::new(), Vec::new());
            for row in &rows {
                for &(c, v) in row {
                    idx.push(c);
                    val.push(v);
                }
                ptr.push(idx.len());
            }
            Self {
                n: rows.len(),
                ptr,
                idx,
                val,
                applies: AtomicUsize::new(0),
            }
        }

        /// Random non-symmetric, strictly diagonally dominant matrix.
        fn random(n: usize, per_row: usize, seed: u64) -> Self {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let rows = (0..n)
                .map(|i| {
                    let mut row: Vec<(usize, f64)> = (0..per_row)
                        .map(|_| (rng.random_range(0..n), rng.random_range(-1.0..1.0)))
                        .filter(|&(c, _)| c != i)
                        .collect();
                    let off: f64 = row.iter().map(|e| e.1.abs()).sum();
                    row.push((i, off + 0.5 + rng.random_range(0.0..1.0)));
                    row
                })
                .collect();
            Self::from_rows(rows)
        }

        fn dense(&self) -> Vec<f64> {
            let mut a = vec![0.0; self.n * self.n];
            for i in 0..self.n {
                for e in self.ptr[i]..self.ptr[i + 1] {
                    a[i * self.n + self.idx[e]] += self.val[e];
                }
            }
            a
        }
    }

    impl BlockOperator for Csr {
        fn dim(&self) -> usize {
            self.n
        }
        fn apply_block(&self, xs: &[f64], ys: &mut [f64], k: usize) {
            self.applies.fetch_add(1, Ordering::Relaxed);
            let n = self.n;
            ys.fill(0.0);
            for i in 0..n {
                for e in self.ptr[i]..self.ptr[i + 1] {
                    let (c, a) = (self.idx[e], self.val[e]);
                    for j in 0..k {
                        ys[j * n + i] += a * xs[j * n + c];
                    }
                }
            }
        }
    }

    /// Gaussian elimination with partial pivoting, row-major `a`.
    fn dense_solve(mut a: Vec<f64>, mut b: Vec<f64>) -> Vec<f64> {
        let n = b.len();
        for c in 0..n {
            let piv = (c..n)
                .max_by(|&i, &j| a[i * n + c].abs().total_cmp(&a[j * n + c].abs()))
                .unwrap();
            for q in 0..n {
                a.swap(c * n + q, piv * n + q);
            }
            b.swap(c, piv);
            for i in c + 1..n {
                let f = a[i * n + c] / a[c * n + c];
                for q in c..n {
                    a[i * n + q] -= f * a[c * n + q];
                }
                b[i] -= f * b[c];
            }
        }
        for i in (0..n).rev() {
            let s: f64 = (i + 1..n).map(|q| a[i * n + q] * b[q]).sum();
            b[i] = (b[i] - s) / a[i * n + i];
        }
        b
    }

    fn random_vec(len: usize, seed: u64) -> Vec<f64> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..len).map(|_| rng.random_range(-1.0..1.0)).collect()
    }

    fn rel_diff(a: &[f64], b: &[f64]) -> f64 {
        let d: f64 = a.iter().zip(b).map(|(p, q)| (p - q) * (p - q)).sum();
        let s: f64 = b.iter().map(|q| q * q).sum();
        (d / s).sqrt()
    }

    const TIGHT: BicgstabParams = BicgstabParams {
        rel_tolerance: 1e-13,
        max_iterations: 500,
    };

    #[test]
    fn matches_dense_lu() {
        let (n, k) = (300, 3);
        let op = Csr::random(n, 6, 1);
        let b = random_vec(n * k, 2);
        let mut x = random_vec(n * k, 3);
        let rep = bicgstab_block(&op, &b, &mut x, k, &TIGHT, &Monitor::noop()).unwrap();
        assert!(rep.converged.iter().all(|&c| c), "{rep:?}");
        for j in 0..k {
            let reference = dense_solve(op.dense(), b[j * n..(j + 1) * n].to_vec());
            let e = rel_diff(&x[j * n..(j + 1) * n], &reference);
            assert!(e < 1e-8, "column {j}: relative error {e}");
            assert!(rep.rel_residuals[j] < 1e-12, "{rep:?}");
        }
    }

    #[test]
    fn block_equals_columns_solved_alone() {
        // Large enough to span several parallel chunks.
        let (n, k) = (20_000, 3);
        let op = Csr::random(n, 5, 4);
        let b = random_vec(n * k, 5);
        let params = BicgstabParams {
            rel_tolerance: 1e-10,
            max_iterations: 200,
        };
        let mut x = vec![0.0; n * k];
        let rep = bicgstab_block(&op, &b, &mut x, k, &params, &Monitor::noop()).unwrap();
        for j in 0..k {
            let mut xj = vec![0.0; n];
            let rj = bicgstab_block(
                &op,
                &b[j * n..(j + 1) * n],
                &mut xj,
                1,
                &params,
                &Monitor::noop(),
            )
            .unwrap();
            assert!(rj.converged[0] && rep.converged[j]);
            assert_eq!(rj.iterations[0], rep.iterations[j]);
            assert!(rel_diff(&x[j * n..(j + 1) * n], &xj) < 1e-14);
            assert!(rep.rel_residuals[j] < 2e-10, "{rep:?}");
        }
    }

    #[test]
    fn zero_rhs_returns_zero_without_applying() {
        let op = Csr::random(50, 4, 6);
        let b = vec![0.0; 100];
        let mut x = random_vec(100, 7);
        let rep = bicgstab_block(&op, &b, &mut x, 2, &TIGHT, &Monitor::noop()).unwrap();
        assert!(x.iter().all(|&v| v == 0.0));
        assert_eq!(rep.iterations, vec![0, 0]);
        assert_eq!(rep.converged, vec![true, true]);
        assert_eq!(op.applies.load(Ordering::Relaxed), 0);
    }

    #[test]
    fn zero_column_next_to_nonzero_one() {
        let n = 60;
        let op = Csr::random(n, 4, 8);
        let mut b = random_vec(2 * n, 9);
        b[n..].fill(0.0);
        let mut x = random_vec(2 * n, 10);
        let rep = bicgstab_block(&op, &b, &mut x, 2, &TIGHT, &Monitor::noop()).unwrap();
        assert!(x[n..].iter().all(|&v| v == 0.0));
        assert_eq!(rep.converged, vec![true, true]);
        assert!(rep.rel_residuals[0] < 1e-12);
    }

    #[test]
    fn cancelled_monitor_stops() {
        let op = Csr::random(50, 4, 11);
        let b = random_vec(50, 12);
        let mut x = vec![0.0; 50];
        let m = Monitor::noop();
        m.cancel();
        let e = bicgstab_block(&op, &b, &mut x, 1, &TIGHT, &m).unwrap_err();
        assert_eq!(e, MurkError::Cancelled);
    }

    #[test]
    fn identity_converges_in_one_iteration() {
        let n = 40;
        let op = Csr::from_rows((0..n).map(|i| vec![(i, 1.0)]).collect());
        let b = random_vec(4 * n, 13);
        let mut x = random_vec(4 * n, 14);
        let rep = bicgstab_block(&op, &b, &mut x, 4, &TIGHT, &Monitor::noop()).unwrap();
        assert_eq!(rep.iterations, vec![1; 4]);
        assert!(rep.converged.iter().all(|&c| c));
        assert!(rel_diff(&x, &b) < 1e-15);
    }

    #[test]
    fn persistent_breakdown_is_reported_not_fatal() {
        // Skew-symmetric: (r, A r) = 0 for every r, so every restart breaks down again.
        let n = 10;
        let op = Csr::from_rows(
            (0..n)
                .map(|i| {
                    let p = i ^ 1;
                    vec![(p, if i % 2 == 0 { 1.0 } else { -1.0 })]
                })
                .collect(),
        );
        let b = random_vec(n, 15);
        let mut x = vec![0.0; n];
        let params = BicgstabParams {
            rel_tolerance: 1e-8,
            max_iterations: 20,
        };
        let rep = bicgstab_block(&op, &b, &mut x, 1, &params, &Monitor::noop()).unwrap();
        assert_eq!(rep.converged, vec![false]);
        assert_eq!(rep.iterations, vec![20]);
        assert!(x.iter().all(|v| v.is_finite()) && rep.rel_residuals[0].is_finite());
    }

    #[test]
    fn bad_inputs_name_their_field() {
        let op = Csr::random(10, 3, 16);
        let m = Monitor::noop();
        let p = BicgstabParams::default();
        let field = |r: Result<BicgstabReport>| r.unwrap_err().field().unwrap().to_string();
        assert_eq!(
            field(bicgstab_block(&op, &[0.0; 9], &mut [0.0; 10], 1, &p, &m)),
            "b"
        );
        assert_eq!(
            field(bicgstab_block(&op, &[0.0; 20], &mut [0.0; 10], 2, &p, &m)),
            "x"
        );
        assert_eq!(field(bicgstab_block(&op, &[], &mut [], 0, &p, &m)), "k");
        let bad = BicgstabParams {
            rel_tolerance: 0.0,
            ..p
        };
        assert_eq!(
            field(bicgstab_block(&op, &[1.0; 10], &mut [0.0; 10], 1, &bad, &m)),
            "rel_tolerance"
        );
        let mut b = [1.0; 10];
        b[3] = f64::NAN;
        assert_eq!(
            field(bicgstab_block(&op, &b, &mut [0.0; 10], 1, &p, &m)),
            "b"
        );
    }
}
