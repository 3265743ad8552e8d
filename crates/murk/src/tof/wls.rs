//! The x-step of Eq. 5.12: with the weights W and the patch quadratics a_k fixed, the scattering
//! component solves the sparse SPD system
//!
//! (W + γ′₁I + γ′₂(F − I)ᵀ(F − I) + γ′₃∇ᵀ∇) x = W x̃ + γ′₁ U a,
//!
//! whose sparsity pattern (5-point Laplacian plus one mirror coupling per pixel) never changes;
//! only the diagonal W does between IRLS iterations.
//!
//! The joint form ([`XStepSystem::with_joint_prior`], the pipeline's default) eliminates the
//! a-step instead of alternating with it: the uniform a-step of Eq. 5.12 is the orthogonal
//! projection P onto per-patch quadratics, so minimising Eq. 5.12 over x and a together is
//!
//! (W + γ′₁(I − P) + γ′₂(F − I)ᵀ(F − I) + γ′₃∇ᵀ∇) x = W x̃,
//!
//! solved by CG with P applied matrix-free (one pass of patch moments per iteration). Where a
//! large object leaves whole patches without data the alternation is a slow diffusion that keeps
//! its starting point (the bright observation) for hundreds of iterations; the joint minimiser
//! instead extends the background's quadratics and smoothness under the object. Two solvers are provided: a matrix-free
//! conjugate gradient warm-started from the previous iterate and preconditioned by a geometric
//! multigrid V-cycle, in the joint form together with a coarse space of the patch quadratics
//! (the default, [`super::coarse_space`]; Jacobi is kept as the simple reference, see
//! `XStepSolver`),
//! and a faer sparse Cholesky whose symbolic factorisation is computed once.

use faer::sparse::{SparseColMat, Triplet};
use faer::Side;
use rayon::prelude::*;

use super::coarse_space::{shared_fixed_coarse_operator, CoarseSpace, FixedCoarseCache};
use super::multigrid::Multigrid;
use super::quadratic_prior::{PatchGrid, QuadraticPrior};
use super::symmetry::RowMirror;
use crate::error::{MurkError, Result};
use crate::linalg::SparseLlt;
use crate::monitor::Monitor;

/// Tiny ridge added to the diagonal so the system stays SPD when γ′₁ = 0 and every weight is
/// zero; it biases x towards 0 by a relative 1e-9, far below any image noise.
const RIDGE: f64 = 1e-9;

/// Preconditioner of the conjugate gradient.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Preconditioner {
    /// Inverse diagonal. Iterations grow with √κ, and κ ≈ 8γ′₃/γ′₁ where W ≈ 0 (objects).
    Jacobi,
    /// One geometric multigrid V-cycle (see [`super::multigrid`]) on the operator without the
    /// mirror's off-diagonal coupling: iterations nearly independent of κ and image size. In
    /// the joint form the V-cycle keeps γ′₁ and is combined additively with a coarse-space
    /// correction on the patch quadratics ([`super::coarse_space`]).
    #[default]
    Multigrid,
    /// The V-cycle alone, without γ′₁ in the joint form (kept to measure the coarse space
    /// against).
    MultigridOnly,
}

/// How the x-step system is solved.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum XStepSolver {
    /// Matrix-free preconditioned conjugate gradient, warm-started from the current x. Stops
    /// when ‖b − Ax‖ ≤ `rel_tol`·‖b‖ or after `max_iterations`.
    Pcg {
        /// Relative residual tolerance.
        rel_tol: f64,
        /// Iteration cap per solve (the IRLS loop tolerates inexact steps: the next solve
        /// continues from this one's iterate).
        max_iterations: usize,
        /// Preconditioner.
        preconditioner: Preconditioner,
    },
    /// faer supernodal sparse Cholesky (AMD ordering); symbolic analysis once, numeric
    /// factorisation every solve. Exact but far slower at 424×512 (see the bench `tof`).
    SparseCholesky,
}

impl Default for XStepSolver {
    fn default() -> Self {
        XStepSolver::Pcg {
            rel_tol: 1e-5,
            max_iterations: 400,
            preconditioner: Preconditioner::Multigrid,
        }
    }
}

/// Statistics of one solve.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SolveStats {
    /// CG iterations (0 for Cholesky).
    pub iterations: usize,
    /// Final relative residual ‖b − Ax‖/‖b‖ (CG only; 0 for Cholesky).
    pub rel_residual: f64,
}

/// The constant part of the x-step operator: image size, γ′, the row pairing of F and, in the
/// joint form, the patch grid of P.
#[derive(Clone, Debug)]
pub struct XStepSystem {
    width: usize,
    height: usize,
    gamma: [f64; 3],
    mirror: RowMirror,
    /// The projection P of the joint form (its fitted coefficients are unused).
    joint: Option<Box<QuadraticPrior>>,
    /// The weight-independent part of the joint form's coarse operator.
    coarse_fixed: FixedCoarseCache,
}

/// Share of γ′₁ kept in the V-cycle's mass term in the joint form when the V-cycle preconditions
/// alone ([`Preconditioner::MultigridOnly`]). The joint operator's γ′₁(I − P) vanishes on patch
/// quadratics, so the full γ′₁ makes the quadratics under objects look 10–100× stiffer than they
/// are; dropping it leaves only W (≈ 0 there) and the Laplacian, which makes every other smooth
/// mode there too soft instead. The default preconditioner keeps the full γ′₁ and corrects the
/// quadratics with the coarse space ([`super::coarse_space`]).
const JOINT_MASS_SHARE: f64 = 0.0;

impl XStepSystem {
    /// `gamma` = [γ′₁, γ′₂, γ′₃] of Eq. 5.12, applied directly.
    pub fn new(width: usize, height: usize, gamma: [f64; 3], mirror: RowMirror) -> Self {
        Self {
            width,
            height,
            gamma,
            mirror,
            joint: None,
            coarse_fixed: FixedCoarseCache::default(),
        }
    }

    /// The joint form: the quadratics of `grid` are eliminated (see the module docs). The
    /// right-hand side then drops γ′₁ U a, and the sparse Cholesky is unavailable (P couples
    /// every pair of pixels in a patch).
    pub fn with_joint_prior(mut self, grid: PatchGrid) -> Result<Self> {
        if grid.width() != self.width || grid.height() != self.height {
            return Err(MurkError::Numerical(
                "joint prior grid does not match the image size".into(),
            ));
        }
        self.joint = Some(Box::new(QuadraticPrior::new(grid)?));
        self.coarse_fixed = FixedCoarseCache::default();
        Ok(self)
    }

    /// True in the joint form.
    pub fn is_joint(&self) -> bool {
        self.joint.is_some()
    }

    /// The joint form's coarse space for `weights` (rebuilding `slot` when it belongs to another
    /// system); `None` in the alternating form.
    fn coarse_space<'a>(
        &self,
        weights: &[f64],
        slot: &'a mut Option<Box<CoarseSpace>>,
    ) -> Result<Option<&'a mut CoarseSpace>> {
        let Some(q) = &self.joint else {
            return Ok(None);
        };
        let fixed = self.coarse_fixed.get_or_init(|| {
            shared_fixed_coarse_operator(q, self.gamma[2], self.pair_weight(), &self.mirror)
        });
        if !slot.as_ref().is_some_and(|c| c.serves(&fixed)) {
            *slot = Some(Box::new(CoarseSpace::new(q, fixed)));
        }
        let cs = slot.as_mut().map(|b| &mut **b).expect("just set");
        cs.set_weights(q, weights, RIDGE)?;
        Ok(Some(cs))
    }

    /// P x's patch coefficients into `coeffs` (joint form only; a no-op otherwise).
    fn project(&self, x: &[f64], sums: &mut Vec<[f64; 3]>, coeffs: &mut Vec<[f64; 6]>) {
        if let Some(q) = &self.joint {
            if coeffs.len() != q.grid().count() {
                (*sums, *coeffs) = q.scratch();
            }
            q.fit_into(x, sums, coeffs);
        }
    }

    /// Number of unknowns (pixels).
    pub fn len(&self) -> usize {
        self.width * self.height
    }

    /// True for an empty image (never the case for validated input).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Image width.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Image height.
    pub fn height(&self) -> usize {
        self.height
    }

    /// The row pairing of F.
    pub fn mirror(&self) -> &RowMirror {
        &self.mirror
    }

    /// Coefficient of the symmetry coupling in row `y`: (F − I)ᵀ(F − I) contributes
    /// 2(x_i − x_F(i)) per paired pixel, since both members of a pair carry the same residual.
    #[inline]
    fn pair_coef(&self, y: usize) -> f64 {
        if self.mirror.partner(y).is_some() {
            self.pair_weight()
        } else {
            0.0
        }
    }

    /// Weight 2γ′₂ of the coupling between a pixel and its mirror partner (see `pair_coef`).
    #[inline]
    fn pair_weight(&self) -> f64 {
        2.0 * self.gamma[1]
    }

    /// Right-hand side W x̃ + γ′₁ U a (W x̃ in the joint form, which ignores `prior`).
    pub fn rhs(&self, weights: &[f64], observed: &[f64], prior: &[f64], out: &mut [f64]) {
        let g1 = if self.is_joint() { 0.0 } else { self.gamma[0] };
        out.par_chunks_mut(self.width)
            .zip(weights.par_chunks(self.width))
            .zip(observed.par_chunks(self.width))
            .zip(prior.par_chunks(self.width))
            .for_each(|(((o, w), xo), p)| {
                for i in 0..o.len() {
                    o[i] = w[i] * xo[i] + g1 * p[i];
                }
            });
    }

    /// Diagonal of the operator (in the joint form, of its alternating part: the Jacobi
    /// preconditioner ignores P's diagonal, which only needs to be SPD there).
    pub fn diagonal(&self, weights: &[f64], out: &mut [f64]) {
        let (w, h) = (self.width, self.height);
        let g3 = self.gamma[2];
        out.par_chunks_mut(w).enumerate().for_each(|(y, o)| {
            let vdeg = (y > 0) as usize + (y + 1 < h) as usize;
            let base = self.gamma[0] + RIDGE + self.pair_coef(y);
            for (i, d) in o.iter_mut().enumerate() {
                let hdeg = (i > 0) as usize + (i + 1 < w) as usize;
                *d = weights[y * w + i] + base + g3 * (hdeg + vdeg) as f64;
            }
        });
    }

    /// `out = A x` for one image row `y`; `proj` holds P x's patch coefficients in the joint
    /// form.
    #[inline]
    fn apply_row(&self, weights: &[f64], x: &[f64], y: usize, proj: &[[f64; 6]], out: &mut [f64]) {
        let w = self.width;
        let [g1, _, g3] = self.gamma;
        let c = self.pair_coef(y);
        let xr = &x[y * w..(y + 1) * w];
        let wr = &weights[y * w..(y + 1) * w];
        for i in 0..w {
            out[i] = (wr[i] + g1 + RIDGE + c) * xr[i];
        }
        // Forward differences: each horizontal/vertical edge adds γ′₃(x_i − x_j) to both ends.
        if w > 1 {
            out[0] += g3 * (xr[0] - xr[1]);
            out[w - 1] += g3 * (xr[w - 1] - xr[w - 2]);
            for i in 1..w - 1 {
                out[i] += g3 * (2.0 * xr[i] - xr[i - 1] - xr[i + 1]);
            }
        }
        if y > 0 {
            let up = &x[(y - 1) * w..y * w];
            for i in 0..w {
                out[i] += g3 * (xr[i] - up[i]);
            }
        }
        if y + 1 < self.height {
            let dn = &x[(y + 1) * w..(y + 2) * w];
            for i in 0..w {
                out[i] += g3 * (xr[i] - dn[i]);
            }
        }
        if let Some(m) = self.mirror.partner(y) {
            let xm = &x[m * w..(m + 1) * w];
            for i in 0..w {
                out[i] -= c * xm[i];
            }
        }
        if let Some(q) = &self.joint {
            q.add_scaled_row(proj, y, -g1, out);
        }
    }

    /// `out = A x` (matrix-free).
    pub fn apply(&self, weights: &[f64], x: &[f64], out: &mut [f64]) {
        let (mut sums, mut coeffs) = (Vec::new(), Vec::new());
        self.apply_with(weights, x, out, &mut sums, &mut coeffs);
    }

    /// [`XStepSystem::apply`] with the projection's scratch supplied.
    fn apply_with(
        &self,
        weights: &[f64],
        x: &[f64],
        out: &mut [f64],
        sums: &mut Vec<[f64; 3]>,
        coeffs: &mut Vec<[f64; 6]>,
    ) {
        self.project(x, sums, coeffs);
        let proj = &coeffs[..];
        out.par_chunks_mut(self.width)
            .enumerate()
            .for_each(|(y, o)| self.apply_row(weights, x, y, proj, o));
    }

    /// `out = A p` and per-row partial sums of `p·out` in `row_dots` (summed by the caller in a
    /// fixed order so results do not depend on thread scheduling).
    fn apply_dot(
        &self,
        weights: &[f64],
        p: &[f64],
        out: &mut [f64],
        row_dots: &mut [f64],
        sums: &mut Vec<[f64; 3]>,
        coeffs: &mut Vec<[f64; 6]>,
    ) {
        let w = self.width;
        self.project(p, sums, coeffs);
        let proj = &coeffs[..];
        out.par_chunks_mut(w)
            .zip(row_dots.par_iter_mut())
            .enumerate()
            .for_each(|(y, (o, d))| {
                self.apply_row(weights, p, y, proj, o);
                let pr = &p[y * w..(y + 1) * w];
                *d = pr.iter().zip(o.iter()).map(|(a, b)| a * b).sum();
            });
    }

    /// Lower triangle (row ≥ column) of the operator without W, as triplets: the pattern and the
    /// constant values for the sparse Cholesky and for tests.
    pub fn lower_triplets(&self) -> Vec<Triplet<usize, usize, f64>> {
        let (w, h) = (self.width, self.height);
        let [g1, _, g3] = self.gamma;
        let mut t = Vec::with_capacity(4 * w * h);
        for y in 0..h {
            let c = self.pair_coef(y);
            for x in 0..w {
                let i = y * w + x;
                let deg = (x > 0) as usize
                    + (x + 1 < w) as usize
                    + (y > 0) as usize
                    + (y + 1 < h) as usize;
                t.push(Triplet::new(i, i, g1 + RIDGE + c + g3 * deg as f64));
                if x + 1 < w {
                    t.push(Triplet::new(i + 1, i, -g3));
                }
                if y + 1 < h {
                    t.push(Triplet::new(i + w, i, -g3));
                }
                if let Some(m) = self.mirror.partner(y) {
                    if m > y {
                        t.push(Triplet::new(m * w + x, i, -c));
                    }
                }
            }
        }
        t
    }
}

/// Reusable buffers of the conjugate-gradient solver.
#[derive(Clone, Debug, Default)]
pub struct PcgWorkspace {
    r: Vec<f64>,
    z: Vec<f64>,
    p: Vec<f64>,
    q: Vec<f64>,
    inv_diag: Vec<f64>,
    row_a: Vec<f64>,
    row_b: Vec<f64>,
    mg: Option<Box<Multigrid>>,
    coarse: Option<Box<CoarseSpace>>,
    /// Scratch of the joint form's projection.
    proj_sums: Vec<[f64; 3]>,
    proj_coeffs: Vec<[f64; 6]>,
}

impl PcgWorkspace {
    fn ensure(&mut self, n: usize, rows: usize) {
        for v in [
            &mut self.r,
            &mut self.z,
            &mut self.p,
            &mut self.q,
            &mut self.inv_diag,
        ] {
            v.resize(n, 0.0);
        }
        self.row_a.resize(rows, 0.0);
        self.row_b.resize(rows, 0.0);
    }
}

/// Checks for cancellation every this many CG iterations (each is a few milliseconds at most at
/// 424×512, so a cancel lands quickly even mid-solve).
const CG_CHECK_EVERY: usize = 4;

/// Σ a·b with per-row partial sums added in a fixed order (deterministic under any scheduling).
fn dot(a: &[f64], b: &[f64], w: usize, rows: &mut [f64]) -> f64 {
    rows.par_iter_mut()
        .zip(a.par_chunks(w).zip(b.par_chunks(w)))
        .for_each(|(d, (x, y))| *d = x.iter().zip(y).map(|(p, q)| p * q).sum());
    rows.iter().sum()
}

/// Sets `ws`'s preconditioner up for `sys` under `weights`: the inverse diagonal, or the
/// V-cycle's mass and (joint form) the coarse space's factorisation. [`solve_pcg`] uses it.
pub fn prepare_preconditioner(
    sys: &XStepSystem,
    weights: &[f64],
    preconditioner: Preconditioner,
    ws: &mut PcgWorkspace,
) -> Result<()> {
    let w = sys.width;
    ws.ensure(sys.len(), sys.height);
    match preconditioner {
        Preconditioner::Jacobi => {
            sys.diagonal(weights, &mut ws.inv_diag);
            ws.inv_diag.par_iter_mut().for_each(|d| *d = 1.0 / *d);
        }
        Preconditioner::Multigrid | Preconditioner::MultigridOnly => {
            if ws
                .mg
                .as_ref()
                .is_some_and(|m| m.dims() != (sys.width, sys.height))
            {
                ws.mg = None;
            }
            let mg = ws.mg.get_or_insert_with(|| {
                Box::new(Multigrid::new(sys.width, sys.height, sys.gamma[2]))
            });
            let share = if sys.is_joint() && preconditioner == Preconditioner::MultigridOnly {
                JOINT_MASS_SHARE
            } else {
                1.0
            };
            let base = share * sys.gamma[0] + RIDGE;
            mg.set_mass(|i| weights[i] + base + sys.pair_coef(i / w));
            if preconditioner == Preconditioner::Multigrid {
                sys.coarse_space(weights, &mut ws.coarse)?;
            }
        }
    }
    Ok(())
}

/// Preconditioned CG on `A x = b`, starting from the given `x`, with `ws`'s preconditioner
/// set up for `sys` and `weights` by [`prepare_preconditioner`]. One setup serves every
/// right-hand side under the same weights: the phasor's two components share them.
///
/// `set_up` is called on the workspace once the starting `x` has been found not to meet the
/// tolerance, before the preconditioner's first use (pass `&mut |_| Ok(())` when it is set up
/// already). It is not called when the solve ends without an iteration (the returned stats say
/// 0), so an IRLS step whose warm start is already converged skips the V-cycle's masses and
/// the coarse space's factorisation.
#[allow(clippy::too_many_arguments)]
pub fn solve_pcg(
    sys: &XStepSystem,
    weights: &[f64],
    b: &[f64],
    x: &mut [f64],
    rel_tol: f64,
    max_iterations: usize,
    preconditioner: Preconditioner,
    ws: &mut PcgWorkspace,
    set_up: &mut dyn FnMut(&mut PcgWorkspace) -> Result<()>,
    monitor: &Monitor,
) -> Result<SolveStats> {
    let w = sys.width;
    let bnorm = b.par_iter().map(|v| v * v).sum::<f64>().sqrt();
    if !bnorm.is_finite() {
        return Err(MurkError::Numerical(
            "x-step right-hand side is not finite".into(),
        ));
    }
    if bnorm == 0.0 {
        // A is SPD (ridge), so b = 0 has the unique solution x = 0.
        x.fill(0.0);
        return Ok(SolveStats::default());
    }
    let target = rel_tol * bnorm;
    ws.ensure(sys.len(), sys.height);
    sys.apply_with(
        weights,
        x,
        &mut ws.q,
        &mut ws.proj_sums,
        &mut ws.proj_coeffs,
    );
    ws.r.par_iter_mut()
        .zip(b.par_iter().zip(ws.q.par_iter()))
        .for_each(|(ri, (bi, qi))| *ri = bi - qi);
    let mut rnorm = dot(&ws.r, &ws.r, w, &mut ws.row_b).sqrt();
    if rnorm <= target {
        return Ok(SolveStats {
            iterations: 0,
            rel_residual: rnorm / bnorm,
        });
    }
    set_up(ws)?;
    let mut coarse = match preconditioner {
        Preconditioner::Multigrid if sys.is_joint() => ws.coarse.as_deref_mut(),
        _ => None,
    };
    let PcgWorkspace {
        r,
        z,
        p,
        q,
        inv_diag,
        row_a,
        row_b,
        mg,
        proj_sums,
        proj_coeffs,
        ..
    } = ws;
    let mut precondition = |r: &[f64], z: &mut [f64]| match preconditioner {
        Preconditioner::Jacobi => z
            .par_iter_mut()
            .zip(r.par_iter().zip(inv_diag.par_iter()))
            .for_each(|(zi, (ri, di))| *zi = ri * di),
        // Set up above whenever the multigrid preconditioner is selected.
        Preconditioner::Multigrid | Preconditioner::MultigridOnly => {
            if let Some(mg) = mg.as_mut() {
                mg.apply(r, z)
            } else {
                z.copy_from_slice(r)
            }
            if let (Some(cs), Some(prior)) = (coarse.as_mut(), sys.joint.as_deref()) {
                cs.add_correction(prior, r, z);
            }
        }
    };
    precondition(r, z);
    p.copy_from_slice(z);
    let mut rz = dot(r, z, w, row_a);
    let mut it = 0;
    while it < max_iterations && rnorm > target {
        if it % CG_CHECK_EVERY == 0 {
            monitor.checkpoint()?;
        }
        sys.apply_dot(weights, p, q, row_a, proj_sums, proj_coeffs);
        let pq: f64 = row_a.iter().sum();
        if pq.is_nan() || pq <= 0.0 || pq.is_infinite() {
            return Err(MurkError::Numerical(format!(
                "conjugate gradient broke down (pᵀAp = {pq}) at iteration {it}"
            )));
        }
        let alpha = rz / pq;
        x.par_chunks_mut(w)
            .zip(r.par_chunks_mut(w))
            .zip(row_b.par_iter_mut())
            .enumerate()
            .for_each(|(y, ((xr, rr), db))| {
                let o = y * w;
                let mut r2 = 0.0;
                for i in 0..w {
                    xr[i] += alpha * p[o + i];
                    let ri = rr[i] - alpha * q[o + i];
                    rr[i] = ri;
                    r2 += ri * ri;
                }
                *db = r2;
            });
        rnorm = row_b.iter().sum::<f64>().sqrt();
        it += 1;
        if !rnorm.is_finite() {
            return Err(MurkError::Numerical(
                "conjugate gradient produced a non-finite residual".into(),
            ));
        }
        if rnorm <= target {
            break;
        }
        precondition(r, z);
        let rz_new = dot(r, z, w, row_a);
        let beta = rz_new / rz;
        rz = rz_new;
        p.par_iter_mut()
            .zip(z.par_iter())
            .for_each(|(pi, zi)| *pi = zi + beta * *pi);
    }
    Ok(SolveStats {
        iterations: it,
        rel_residual: rnorm / bnorm,
    })
}

/// Sparse Cholesky of the x-step system: pattern and symbolic factorisation built once, only the
/// diagonal (W) refreshed per solve.
pub struct CholeskyXSolver {
    mat: SparseColMat<usize, f64>,
    diag_pos: Vec<usize>,
    base_diag: Vec<f64>,
    llt: SparseLlt,
}

impl std::fmt::Debug for CholeskyXSolver {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CholeskyXSolver")
            .field("n", &self.base_diag.len())
            .finish()
    }
}

impl CholeskyXSolver {
    /// Assembles the lower triangle and runs the symbolic analysis (fill-reducing ordering).
    pub fn new(sys: &XStepSystem) -> Result<Self> {
        if sys.is_joint() {
            return Err(MurkError::invalid(
                "solver",
                "the sparse Cholesky solves only the alternating x-step; the joint prior \
                 needs the conjugate gradient",
            ));
        }
        let n = sys.len();
        let mat = SparseColMat::<usize, f64>::try_new_from_triplets(n, n, &sys.lower_triplets())
            .map_err(|e| MurkError::Numerical(format!("x-step matrix assembly failed: {e:?}")))?;
        let llt = SparseLlt::analyse(mat.symbolic(), Side::Lower).map_err(|e| {
            MurkError::Numerical(format!("x-step symbolic factorisation failed: {e:?}"))
        })?;
        let col_ptr = mat.symbolic().col_ptr();
        let row_idx = mat.symbolic().row_idx();
        let mut diag_pos = vec![usize::MAX; n];
        for (j, d) in diag_pos.iter_mut().enumerate() {
            let range = col_ptr[j]..col_ptr[j + 1];
            if let Some(off) = row_idx[range.clone()].iter().position(|&r| r == j) {
                *d = range.start + off;
            }
        }
        if diag_pos.contains(&usize::MAX) {
            return Err(MurkError::Numerical(
                "x-step matrix lacks a diagonal".into(),
            ));
        }
        let base_diag = diag_pos.iter().map(|&k| mat.val()[k]).collect();
        Ok(Self {
            mat,
            diag_pos,
            base_diag,
            llt,
        })
    }

    /// Solves `A x = b` for the current weights; `x` receives the solution.
    pub fn solve(&mut self, weights: &[f64], b: &[f64], x: &mut [f64]) -> Result<SolveStats> {
        let vals = self.mat.val_mut();
        for ((&k, &base), &wi) in self.diag_pos.iter().zip(&self.base_diag).zip(weights) {
            vals[k] = base + wi;
        }
        self.llt
            .factorize(self.mat.as_ref(), Side::Lower)
            .map_err(|e| MurkError::Numerical(format!("x-step Cholesky failed: {e:?}")))?;
        x.copy_from_slice(b);
        self.llt.solve_in_place(x);
        if x.iter().any(|v| !v.is_finite()) {
            return Err(MurkError::Numerical(
                "x-step Cholesky produced a non-finite solution".into(),
            ));
        }
        Ok(SolveStats::default())
    }
}

/// A configured x-step solver with its reusable state.
#[derive(Debug)]
pub enum XStepState {
    /// CG buffers and settings.
    Pcg {
        /// Buffers.
        ws: Box<PcgWorkspace>,
        /// Relative tolerance.
        rel_tol: f64,
        /// Iteration cap.
        max_iterations: usize,
        /// Preconditioner.
        preconditioner: Preconditioner,
        /// The weights of the last setup that was asked for but not needed (its solve's warm
        /// start already met the tolerance); a later solve that reuses that setup does it then.
        deferred: Option<Vec<f64>>,
    },
    /// Factorisation state.
    Cholesky(Box<CholeskyXSolver>),
}

impl XStepState {
    /// Prepares `kind` for `sys` (the Cholesky does its symbolic analysis here).
    pub fn new(kind: XStepSolver, sys: &XStepSystem) -> Result<Self> {
        Ok(match kind {
            XStepSolver::Pcg {
                rel_tol,
                max_iterations,
                preconditioner,
            } => XStepState::Pcg {
                ws: Box::default(),
                rel_tol,
                max_iterations,
                preconditioner,
                deferred: None,
            },
            XStepSolver::SparseCholesky => {
                XStepState::Cholesky(Box::new(CholeskyXSolver::new(sys)?))
            }
        })
    }

    /// Solves the x-step; `x` holds the warm start on entry (used by CG) and the result on exit.
    pub fn solve(
        &mut self,
        sys: &XStepSystem,
        weights: &[f64],
        b: &[f64],
        x: &mut [f64],
        monitor: &Monitor,
    ) -> Result<SolveStats> {
        self.solve_reusing(sys, weights, b, x, 1.0, false, monitor)
    }

    /// [`XStepState::solve`] with the CG tolerance multiplied by `tol_scale` (≥ 1; values
    /// below 1 count as 1): early IRLS iterations, whose weights will still change, do not need
    /// an accurate x-step. The Cholesky ignores it. With `reuse_setup`, for another right-hand
    /// side under the same `sys` and `weights` as this state's previous solve, the CG reuses
    /// that solve's preconditioner setup (the V-cycle's mass, the coarse space's
    /// factorisation), with the same result as setting it up again. Under weights that differ
    /// from the previous solve's in a few pixels, the old setup is still a symmetric positive
    /// definite preconditioner close to the new one: the CG converges to the new system's
    /// solution, in a few more iterations at most.
    #[allow(clippy::too_many_arguments)]
    pub fn solve_reusing(
        &mut self,
        sys: &XStepSystem,
        weights: &[f64],
        b: &[f64],
        x: &mut [f64],
        tol_scale: f64,
        reuse_setup: bool,
        monitor: &Monitor,
    ) -> Result<SolveStats> {
        match self {
            XStepState::Pcg {
                ws,
                rel_tol,
                max_iterations,
                preconditioner,
                deferred,
            } => {
                // The setup waits until the CG needs it: a warm start that already meets the
                // tolerance (the last steps of a converging IRLS) skips it. A solve that reuses
                // a deferred setup does it then, for the weights it was asked for.
                let preconditioner = *preconditioner;
                if !reuse_setup {
                    *deferred = None;
                }
                let mut set_up = |ws: &mut PcgWorkspace| match (reuse_setup, deferred.as_deref()) {
                    (false, _) => prepare_preconditioner(sys, weights, preconditioner, ws),
                    (true, Some(pending)) => {
                        prepare_preconditioner(sys, pending, preconditioner, ws)
                    }
                    (true, None) => Ok(()),
                };
                let stats = solve_pcg(
                    sys,
                    weights,
                    b,
                    x,
                    *rel_tol * tol_scale.max(1.0),
                    *max_iterations,
                    preconditioner,
                    ws,
                    &mut set_up,
                    monitor,
                )?;
                if stats.iterations > 0 {
                    *deferred = None;
                } else if !reuse_setup {
                    *deferred = Some(weights.to_vec());
                }
                Ok(stats)
            }
            XStepState::Cholesky(c) => c.solve(weights, b, x),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Dense A built straight from the definitions: W + γ1·I + γ2·DᵀD + γ3·GᵀG with D the rows
    /// of (F − I) for paired rows and G the forward-difference operator.
    fn dense_reference(w: usize, h: usize, g: [f64; 3], row0: f64, weights: &[f64]) -> Vec<f64> {
        let n = w * h;
        let mut a = vec![0.0; n * n];
        let mirror = RowMirror::new(h, row0);
        let add_outer = |a: &mut Vec<f64>, i: usize, j: usize, s: f64| {
            // s·(e_i − e_j)(e_i − e_j)ᵀ
            a[i * n + i] += s;
            a[j * n + j] += s;
            a[i * n + j] -= s;
            a[j * n + i] -= s;
        };
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                a[i * n + i] += weights[i] + g[0] + RIDGE;
                if x + 1 < w {
                    add_outer(&mut a, i, i + 1, g[2]);
                }
                if y + 1 < h {
                    add_outer(&mut a, i, i + w, g[2]);
                }
                // One row of D per pixel whose row is paired (both members of a pair count).
                if let Some(m) = mirror.partner(y) {
                    add_outer(&mut a, i, m * w + x, g[1]);
                }
            }
        }
        a
    }

    fn dense_solve(mut a: Vec<f64>, mut b: Vec<f64>) -> Vec<f64> {
        let n = b.len();
        for k in 0..n {
            let piv = a[k * n + k];
            for i in k + 1..n {
                let f = a[i * n + k] / piv;
                if f != 0.0 {
                    for j in k..n {
                        a[i * n + j] -= f * a[k * n + j];
                    }
                    b[i] -= f * b[k];
                }
            }
        }
        let mut x = vec![0.0; n];
        for k in (0..n).rev() {
            let mut s = b[k];
            for j in k + 1..n {
                s -= a[k * n + j] * x[j];
            }
            x[k] = s / a[k * n + k];
        }
        x
    }

    fn problem(w: usize, h: usize) -> (Vec<f64>, Vec<f64>) {
        let n = w * h;
        // Deterministic, varied weights including exact zeros (object pixels).
        let weights: Vec<f64> = (0..n)
            .map(|i| {
                if i % 7 == 3 {
                    0.0
                } else {
                    ((i * 37) % 11) as f64 / 10.0
                }
            })
            .collect();
        let b: Vec<f64> = (0..n).map(|i| ((i * 53) % 17) as f64 - 8.0).collect();
        (weights, b)
    }

    #[test]
    fn operator_matches_dense_definition() {
        let (w, h) = (6, 7);
        let g = [0.1, 0.3, 2.0];
        for row0 in [3.0, 2.5, 1.2] {
            let sys = XStepSystem::new(w, h, g, RowMirror::new(h, row0));
            let (weights, xv) = problem(w, h);
            let a = dense_reference(w, h, g, row0, &weights);
            let mut out = vec![0.0; w * h];
            sys.apply(&weights, &xv, &mut out);
            for i in 0..w * h {
                let d: f64 = (0..w * h).map(|j| a[i * w * h + j] * xv[j]).sum();
                assert!(
                    (d - out[i]).abs() < 1e-10,
                    "row0 {row0} i {i}: {d} vs {}",
                    out[i]
                );
            }
            let mut diag = vec![0.0; w * h];
            sys.diagonal(&weights, &mut diag);
            for i in 0..w * h {
                assert!((diag[i] - a[i * w * h + i]).abs() < 1e-12);
            }
        }
    }

    /// A solve whose warm start already meets the tolerance skips the preconditioner setup; a
    /// later solve that reuses the setup under the same weights then does it, and gets the
    /// same answer, bit for bit, as a state that set up eagerly.
    #[test]
    fn a_deferred_setup_is_done_for_the_weights_it_was_asked_for() {
        let (w, h) = (23, 17);
        let grid = PatchGrid::new(w, h, 2, 2);
        let sys = XStepSystem::new(w, h, [0.1, 0.3, 2.0], RowMirror::new(h, 8.0))
            .with_joint_prior(grid)
            .unwrap();
        let (weights, b) = problem(w, h);
        let other: Vec<f64> = weights.iter().map(|v| 1.0 - 0.5 * v).collect();
        let b2: Vec<f64> = b.iter().map(|v| 0.5 * v + 1.0).collect();
        let monitor = Monitor::noop();
        let fresh = || XStepState::new(XStepSolver::default(), &sys).unwrap();
        // A state last set up for `other`, then asked for `weights` with a converged start.
        let mut lazy = fresh();
        let mut scratch = vec![0.0; w * h];
        lazy.solve(&sys, &other, &b, &mut scratch, &monitor)
            .unwrap();
        let mut solved = vec![0.0; w * h];
        fresh()
            .solve(&sys, &weights, &b, &mut solved, &monitor)
            .unwrap();
        let mut start = solved.clone();
        let stats = lazy
            .solve_reusing(&sys, &weights, &b, &mut start, 1.0, false, &monitor)
            .unwrap();
        assert_eq!(stats.iterations, 0);
        assert_eq!(start, solved);
        // The next right-hand side under the same weights, reusing the (deferred) setup.
        let mut lazy_x = vec![0.0; w * h];
        let lazy_stats = lazy
            .solve_reusing(&sys, &weights, &b2, &mut lazy_x, 1.0, true, &monitor)
            .unwrap();
        let mut eager = fresh();
        eager
            .solve(&sys, &weights, &b, &mut scratch.clone(), &monitor)
            .unwrap();
        let mut eager_x = vec![0.0; w * h];
        let eager_stats = eager
            .solve_reusing(&sys, &weights, &b2, &mut eager_x, 1.0, true, &monitor)
            .unwrap();
        assert!(lazy_stats.iterations > 0);
        assert_eq!(lazy_stats.iterations, eager_stats.iterations);
        assert_eq!(lazy_x, eager_x);
    }

    #[test]
    fn solvers_match_dense_solve() {
        let (w, h) = (9, 8);
        for g in [[0.1, 0.1, 10.0], [0.01, 0.1, 50.0], [0.0, 0.0, 1.0]] {
            let row0 = 3.5;
            let sys = XStepSystem::new(w, h, g, RowMirror::new(h, row0));
            let (weights, b) = problem(w, h);
            let reference = dense_solve(dense_reference(w, h, g, row0, &weights), b.clone());
            let scale = reference.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let monitor = Monitor::noop();
            for kind in [
                XStepSolver::Pcg {
                    rel_tol: 1e-12,
                    max_iterations: 10_000,
                    preconditioner: Preconditioner::Jacobi,
                },
                XStepSolver::Pcg {
                    rel_tol: 1e-12,
                    max_iterations: 10_000,
                    preconditioner: Preconditioner::Multigrid,
                },
                XStepSolver::SparseCholesky,
            ] {
                let mut state = XStepState::new(kind, &sys).unwrap();
                let mut x = vec![1.0; w * h];
                state.solve(&sys, &weights, &b, &mut x, &monitor).unwrap();
                for (a, r) in x.iter().zip(&reference) {
                    assert!(
                        (a - r).abs() <= 1e-8 * scale,
                        "{kind:?} γ {g:?}: {a} vs {r}"
                    );
                }
            }
        }
    }

    /// The joint operator is A − γ′₁P, with P the uniform per-patch quadratic fit (built here
    /// column by column from `QuadraticPrior::fit`), and CG solves it to the dense solution.
    #[test]
    fn joint_operator_and_solve_match_dense_definition() {
        let (w, h) = (12, 10);
        let g = [0.1, 0.1, 2.0];
        let row0 = 4.5;
        let grid = PatchGrid::new(w, h, 2, 2);
        let sys = XStepSystem::new(w, h, g, RowMirror::new(h, row0))
            .with_joint_prior(grid.clone())
            .unwrap();
        let (weights, b) = problem(w, h);
        let n = w * h;
        let mut a = dense_reference(w, h, g, row0, &weights);
        let mut q = QuadraticPrior::new(grid).unwrap();
        let (mut e, mut pe) = (vec![0.0; n], vec![0.0; n]);
        for j in 0..n {
            e.fill(0.0);
            e[j] = 1.0;
            q.fit(&e);
            q.evaluate(&mut pe);
            for i in 0..n {
                a[i * n + j] -= g[0] * pe[i];
            }
        }
        let mut out = vec![0.0; n];
        sys.apply(&weights, &b, &mut out);
        for i in 0..n {
            let d: f64 = (0..n).map(|j| a[i * n + j] * b[j]).sum();
            assert!((d - out[i]).abs() < 1e-9, "i {i}: {d} vs {}", out[i]);
        }
        let reference = dense_solve(a, b.clone());
        let scale = reference.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for preconditioner in [
            Preconditioner::Jacobi,
            Preconditioner::Multigrid,
            Preconditioner::MultigridOnly,
        ] {
            let kind = XStepSolver::Pcg {
                rel_tol: 1e-12,
                max_iterations: 10_000,
                preconditioner,
            };
            let mut state = XStepState::new(kind, &sys).unwrap();
            let mut x = vec![1.0; n];
            state
                .solve(&sys, &weights, &b, &mut x, &Monitor::noop())
                .unwrap();
            for (v, r) in x.iter().zip(&reference) {
                assert!(
                    (v - r).abs() <= 1e-7 * scale,
                    "{preconditioner:?}: {v} vs {r}"
                );
            }
        }
        assert!(XStepState::new(XStepSolver::SparseCholesky, &sys).is_err());
    }

    /// A near object that leaves whole patches without data (W = 0) is where the V-cycle alone
    /// is a poor preconditioner of the joint form (see `coarse_space`): with the coarse space
    /// CG needs at least a third fewer iterations for the same solution.
    #[test]
    fn coarse_space_speeds_up_the_joint_solve_under_a_large_object() {
        let (w, h) = (128, 106);
        let s = w as f64 / 512.0;
        let g = [0.1, 0.1, 10.0 * s * s];
        let sys = XStepSystem::new(w, h, g, RowMirror::new(h, 52.0))
            .with_joint_prior(PatchGrid::new(w, h, 4, 4))
            .unwrap();
        let object = |x: usize, y: usize| (30..100).contains(&x) && (20..90).contains(&y);
        let weights: Vec<f64> = (0..w * h)
            .map(|i| if object(i % w, i / w) { 0.0 } else { 1.0 })
            .collect();
        // Observation: a smooth scatter field with a bright object on it; the warm start is the
        // observation itself, as at the first IRLS iteration that rejects the object.
        let observed: Vec<f64> = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f64 / w as f64, (i / w) as f64 / h as f64);
                let scatter = 50.0 + 30.0 * x - 20.0 * y * y + 5.0 * (3.0 * x).sin();
                scatter + if object(i % w, i / w) { 300.0 } else { 0.0 }
            })
            .collect();
        let mut b = vec![0.0; w * h];
        sys.rhs(&weights, &observed, &vec![0.0; w * h], &mut b);
        let solve = |preconditioner| {
            let kind = XStepSolver::Pcg {
                rel_tol: 1e-8,
                max_iterations: 1000,
                preconditioner,
            };
            let mut state = XStepState::new(kind, &sys).unwrap();
            let mut x = observed.clone();
            let stats = state
                .solve(&sys, &weights, &b, &mut x, &Monitor::noop())
                .unwrap();
            (x, stats.iterations)
        };
        let (with, its_with) = solve(Preconditioner::Multigrid);
        let (without, its_without) = solve(Preconditioner::MultigridOnly);
        let diff = with
            .iter()
            .zip(&without)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        assert!(diff < 1e-3, "solutions differ by {diff}");
        // 28 against 50 when written.
        assert!(
            3 * its_with <= 2 * its_without,
            "coarse space {its_with} CG iterations, V-cycle alone {its_without}"
        );
        eprintln!("coarse space {its_with} CG iterations, V-cycle alone {its_without}");
    }

    #[test]
    fn pcg_stops_on_cancel() {
        let (w, h) = (16, 16);
        let sys = XStepSystem::new(w, h, [0.01, 0.1, 50.0], RowMirror::new(h, 7.5));
        let (weights, b) = problem(w, h);
        let monitor = Monitor::noop();
        monitor.cancel();
        let mut x = vec![0.0; w * h];
        let mut ws = PcgWorkspace::default();
        prepare_preconditioner(&sys, &weights, Preconditioner::Multigrid, &mut ws).unwrap();
        let r = solve_pcg(
            &sys,
            &weights,
            &b,
            &mut x,
            1e-12,
            1000,
            Preconditioner::Multigrid,
            &mut ws,
            &mut |_| Ok(()),
            &monitor,
        );
        assert_eq!(r, Err(MurkError::Cancelled));
    }
}
