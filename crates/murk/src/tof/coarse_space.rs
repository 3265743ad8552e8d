//! Two-level preconditioning of the joint x-step: the per-patch quadratics as a coarse space.
//!
//! The joint operator of Eq. 5.12 with the a-step eliminated ([`super::wls`]),
//!
//! A = W + γ′₁(I − P) + γ′₂(F − I)ᵀ(F − I) + γ′₃∇ᵀ∇,
//!
//! treats two kinds of smooth field differently where an object leaves the data term empty
//! (W ≈ 0): a per-patch quadratic (the range of P) costs only the smoothness, every other smooth
//! mode costs γ′₁ as well, and γ′₁ = 0.1 outweighs γ′₃k² for every wavelength above ≈ 60 px at
//! 512 px. A multigrid V-cycle preconditions a diagonal-plus-Laplacian operator and can get only
//! one kind right. Without γ′₁ in its mass every non-quadratic smooth mode
//! under a large object looks up to 40× softer than it is, and CG needed 27–41 iterations per
//! solve at the coarse IRLS iterations that first reject a large near object (cluttered frame,
//! 424×512): 440 of the pipeline's 830 ms. With γ′₁ it is the quadratics that look too stiff.
//!
//! The remedy is the standard additive two-level preconditioner
//!
//! M⁻¹ = B⁻¹ + Z E⁻¹ Zᵀ,  E = Zᵀ A Z,
//!
//! with B the V-cycle on the operator with the full γ′₁ and Z the basis of the patch quadratics
//! (six columns per patch, the same basis as P). P Z = Z, so γ′₁(I − P) vanishes from E:
//!
//! E = Zᵀ diag(W + ridge) Z + γ′₃ Σ_edges d dᵀ + c Σ_pairs d dᵀ,
//!
//! where an edge's (or mirrored pair's) d is the difference of the two pixels' basis vectors,
//! each in its own patch's block. Only the first term depends on the weights: it is assembled
//! per solve from patch moments (diagonal blocks); the rest once per system. E is 6K × 6K
//! (96 for the default 4 × 4 patches), factored by a dense Cholesky.

use std::sync::{Arc, Mutex, OnceLock};

use rayon::prelude::*;

use super::quadratic_prior::{PatchGrid, QuadraticPrior};
use super::symmetry::RowMirror;
use crate::error::{MurkError, Result};

/// Rows per task of the edge assembly: fixed, so the per-chunk sums and their reduction (in
/// chunk order) do not depend on the thread count.
const ROWS_PER_CHUNK: usize = 16;

/// The weight-independent part of E: γ′₃'s edges and the mirror pairs between the patch
/// quadratics, as a dense row-major `6K × 6K` matrix.
pub fn fixed_coarse_operator(
    prior: &QuadraticPrior,
    g3: f64,
    pair_coef: f64,
    mirror: &RowMirror,
) -> Vec<f64> {
    let grid = prior.grid();
    let (w, h) = (grid.width(), grid.height());
    let n = 6 * grid.count();
    let chunks: Vec<Vec<f64>> = (0..h.div_ceil(ROWS_PER_CHUNK))
        .into_par_iter()
        .map(|chunk| {
            let mut e = vec![0.0; n * n];
            let mut add_edge =
                |weight: f64, (p, bp): (usize, [f64; 6]), (q, bq): (usize, [f64; 6])| {
                    if p == q {
                        let d: [f64; 6] = std::array::from_fn(|k| bp[k] - bq[k]);
                        add_outer(&mut e, n, p, p, weight, &d, &d);
                    } else {
                        add_outer(&mut e, n, p, p, weight, &bp, &bp);
                        add_outer(&mut e, n, q, q, weight, &bq, &bq);
                        add_outer(&mut e, n, p, q, -weight, &bp, &bq);
                        add_outer(&mut e, n, q, p, -weight, &bq, &bp);
                    }
                };
            let y0 = chunk * ROWS_PER_CHUNK;
            for y in y0..(y0 + ROWS_PER_CHUNK).min(h) {
                let partner = mirror.partner(y).filter(|&m| m > y);
                for x in 0..w {
                    let here = prior.basis_at(x, y);
                    if x + 1 < w {
                        add_edge(g3, here, prior.basis_at(x + 1, y));
                    }
                    if y + 1 < h {
                        add_edge(g3, here, prior.basis_at(x, y + 1));
                    }
                    if let Some(m) = partner {
                        add_edge(pair_coef, here, prior.basis_at(x, m));
                    }
                }
            }
            e
        })
        .collect();
    let mut e = vec![0.0; n * n];
    for c in &chunks {
        for (a, b) in e.iter_mut().zip(c) {
            *a += b;
        }
    }
    e
}

/// How many geometries [`shared_fixed_coarse_operator`] remembers.
const RECENT_GEOMETRIES: usize = 4;
/// The largest operator [`shared_fixed_coarse_operator`] keeps (bytes): 4 MiB, the operator of
/// 85 patches; the default 16 take 72 KiB.
const RECENT_MAX_BYTES: usize = 4 << 20;

/// Everything [`fixed_coarse_operator`] depends on.
#[derive(Clone, Debug, PartialEq)]
struct Geometry {
    grid: PatchGrid,
    g3_bits: u64,
    pair_coef_bits: u64,
    mirror: RowMirror,
}

/// The operators of the last [`RECENT_GEOMETRIES`] geometries, the latest first.
static RECENT: Mutex<Vec<(Geometry, Arc<Vec<f64>>)>> = Mutex::new(Vec::new());

/// [`fixed_coarse_operator`], remembered for the last few geometries of the process. It
/// depends only on the image size, the patch grid, γ′₃ and the mirror pairs, which every frame
/// of a stream (and every frame of one camera) shares, while it sums over every pixel's edges:
/// 5–10 ms of a 512 × 424 frame on two cores, and a stream frame takes about 100 ms.
pub fn shared_fixed_coarse_operator(
    prior: &QuadraticPrior,
    g3: f64,
    pair_coef: f64,
    mirror: &RowMirror,
) -> Arc<Vec<f64>> {
    let geometry = Geometry {
        grid: prior.grid().clone(),
        g3_bits: g3.to_bits(),
        pair_coef_bits: pair_coef.to_bits(),
        mirror: mirror.clone(),
    };
    // A panic elsewhere cannot leave the list inconsistent: every change is one push or one
    // truncation.
    let lock = || RECENT.lock().unwrap_or_else(|e| e.into_inner());
    if let Some((_, op)) = lock().iter().find(|(g, _)| *g == geometry) {
        return op.clone();
    }
    let op = Arc::new(fixed_coarse_operator(prior, g3, pair_coef, mirror));
    if op.len() * std::mem::size_of::<f64>() <= RECENT_MAX_BYTES {
        let mut recent = lock();
        if !recent.iter().any(|(g, _)| *g == geometry) {
            recent.insert(0, (geometry, op.clone()));
            recent.truncate(RECENT_GEOMETRIES);
        }
    }
    op
}

/// A system's [`fixed_coarse_operator`], computed on first use and shared by every solve (and
/// clone) of that system.
#[derive(Clone, Default)]
pub struct FixedCoarseCache(OnceLock<Arc<Vec<f64>>>);

impl FixedCoarseCache {
    /// The cached matrix, from `make` on the first call.
    pub fn get_or_init(&self, make: impl FnOnce() -> Arc<Vec<f64>>) -> Arc<Vec<f64>> {
        self.0.get_or_init(make).clone()
    }
}

impl std::fmt::Debug for FixedCoarseCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FixedCoarseCache")
            .field("computed", &self.0.get().is_some())
            .finish()
    }
}

/// `e[block (p, q)] += weight · a bᵀ` (6 × 6 blocks of an `n × n` row-major matrix).
#[inline]
fn add_outer(e: &mut [f64], n: usize, p: usize, q: usize, weight: f64, a: &[f64; 6], b: &[f64; 6]) {
    for (r, &ar) in a.iter().enumerate() {
        let row = &mut e[(6 * p + r) * n + 6 * q..(6 * p + r) * n + 6 * q + 6];
        let s = weight * ar;
        for (o, &bc) in row.iter_mut().zip(b) {
            *o += s * bc;
        }
    }
}

/// The coarse correction Z E⁻¹ Zᵀ for one set of weights, with its scratch.
///
/// E is factored by the dense Cholesky below rather than faer's: faer's dense kernels hand
/// matrices of this size to its own worker threads (spindle), which keep spinning after the
/// call and took a third of both cores from the rest of the process on this 2-core host
/// (the ToF pipeline ran 35 % slower after a single 96 × 96 factorisation).
#[derive(Clone)]
pub struct CoarseSpace {
    fixed: Arc<Vec<f64>>,
    /// Lower Cholesky factor of E (row-major `n × n`); empty before the first weights.
    chol: Vec<f64>,
    row_sums: Vec<[f64; 3]>,
    moments: Vec<[f64; 6]>,
}

impl std::fmt::Debug for CoarseSpace {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CoarseSpace")
            .field("unknowns", &(self.moments.len() * 6))
            .finish()
    }
}

impl CoarseSpace {
    /// Scratch for `prior`'s grid around the weight-independent part `fixed` (from
    /// [`fixed_coarse_operator`]).
    pub fn new(prior: &QuadraticPrior, fixed: Arc<Vec<f64>>) -> Self {
        let (row_sums, moments) = prior.scratch();
        Self {
            fixed,
            chol: Vec::new(),
            row_sums,
            moments,
        }
    }

    /// True when this scratch was built around `fixed` (the same system).
    pub fn serves(&self, fixed: &Arc<Vec<f64>>) -> bool {
        Arc::ptr_eq(&self.fixed, fixed)
    }

    /// Assembles E for `weights` (`ridge` is the operator's diagonal ridge) and factors it.
    pub fn set_weights(
        &mut self,
        prior: &QuadraticPrior,
        weights: &[f64],
        ridge: f64,
    ) -> Result<()> {
        let n = 6 * self.moments.len();
        assemble(prior, &self.fixed, weights, ridge, &mut self.chol);
        if !cholesky_in_place(&mut self.chol, n) {
            self.chol.clear();
            return Err(MurkError::Numerical(
                "x-step coarse operator is not positive definite".into(),
            ));
        }
        Ok(())
    }

    /// `z += Z E⁻¹ Zᵀ r`; a no-op before [`CoarseSpace::set_weights`].
    pub fn add_correction(&mut self, prior: &QuadraticPrior, r: &[f64], z: &mut [f64]) {
        if self.chol.is_empty() {
            return;
        }
        prior.moments_into(r, &mut self.row_sums, &mut self.moments);
        cholesky_solve_in_place(&self.chol, self.moments.as_flattened_mut());
        let coeffs = &self.moments;
        let w = prior.grid().width();
        z.par_chunks_mut(w)
            .enumerate()
            .for_each(|(y, row)| prior.add_scaled_row(coeffs, y, 1.0, row));
    }
}

/// E = `fixed` + Zᵀ diag(`weights` + `ridge`) Z into `out` (dense, row-major).
fn assemble(
    prior: &QuadraticPrior,
    fixed: &[f64],
    weights: &[f64],
    ridge: f64,
    out: &mut Vec<f64>,
) {
    let n = 6 * prior.grid().count();
    out.clear();
    out.extend_from_slice(fixed);
    for (p, g) in prior.weighted_grams(weights, ridge).iter().enumerate() {
        for (r, row) in g.iter().enumerate() {
            let at = (6 * p + r) * n + 6 * p;
            for (e, v) in out[at..at + 6].iter_mut().zip(row) {
                *e += v;
            }
        }
    }
}

/// Overwrites the lower triangle of the SPD row-major `n × n` matrix `a` with its Cholesky
/// factor L (A = L Lᵀ); false when a pivot is not positive (or not finite).
fn cholesky_in_place(a: &mut [f64], n: usize) -> bool {
    for j in 0..n {
        let (head, tail) = a.split_at_mut(j * n);
        let row_j = &mut tail[..n];
        for k in 0..j {
            let row_k = &head[k * n..k * n + k + 1];
            let s: f64 = row_j[..k].iter().zip(&row_k[..k]).map(|(x, y)| x * y).sum();
            row_j[k] = (row_j[k] - s) / row_k[k];
        }
        let d = row_j[j] - row_j[..j].iter().map(|v| v * v).sum::<f64>();
        if d.is_nan() || d <= 0.0 || d.is_infinite() {
            return false;
        }
        row_j[j] = d.sqrt();
    }
    true
}

/// Solves L Lᵀ x = b in place, with L from [`cholesky_in_place`].
fn cholesky_solve_in_place(l: &[f64], b: &mut [f64]) {
    let n = b.len();
    for i in 0..n {
        let s: f64 = l[i * n..i * n + i]
            .iter()
            .zip(&b[..i])
            .map(|(x, y)| x * y)
            .sum();
        b[i] = (b[i] - s) / l[i * n + i];
    }
    for i in (0..n).rev() {
        let mut s = b[i];
        for k in i + 1..n {
            s -= l[k * n + i] * b[k];
        }
        b[i] = s / l[i * n + i];
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::tof::quadratic_prior::PatchGrid;
    use crate::tof::wls::XStepSystem;

    #[test]
    fn a_geometry_seen_before_shares_its_operator() {
        let prior = QuadraticPrior::new(PatchGrid::new(23, 17, 3, 2)).expect("grid");
        let mirror = RowMirror::new(17, 7.5);
        let first = shared_fixed_coarse_operator(&prior, 2.5, 0.6, &mirror);
        assert_eq!(*first, fixed_coarse_operator(&prior, 2.5, 0.6, &mirror));
        let again = shared_fixed_coarse_operator(&prior, 2.5, 0.6, &mirror);
        assert!(Arc::ptr_eq(&first, &again));
        // Any input that changes the operator is another geometry.
        let other = shared_fixed_coarse_operator(&prior, 2.5, 0.6, &RowMirror::new(17, 8.0));
        assert_eq!(
            *other,
            fixed_coarse_operator(&prior, 2.5, 0.6, &RowMirror::new(17, 8.0))
        );
        assert_ne!(*other, *first);
        let stiffer = shared_fixed_coarse_operator(&prior, 2.6, 0.6, &mirror);
        assert_ne!(*stiffer, *first);
    }

    /// E assembled from the edges, the pairs and the weighted Grams is Zᵀ A Z, with A applied
    /// column by column to the patch quadratics (uneven patches, a fractional mirror axis,
    /// weights with zeros).
    #[test]
    fn coarse_operator_is_the_galerkin_product() {
        let (w, h) = (13, 11);
        let gamma = [0.1, 0.3, 2.5];
        let mirror = RowMirror::new(h, 4.5);
        let grid = PatchGrid::new(w, h, 3, 2);
        let sys = XStepSystem::new(w, h, gamma, mirror.clone())
            .with_joint_prior(grid.clone())
            .unwrap();
        let prior = QuadraticPrior::new(grid).unwrap();
        let weights: Vec<f64> = (0..w * h)
            .map(|i| {
                if i % 5 == 2 {
                    0.0
                } else {
                    ((i * 29) % 13) as f64 / 12.0
                }
            })
            .collect();
        let ridge = 1e-9;
        let fixed = fixed_coarse_operator(&prior, gamma[2], 2.0 * gamma[1], &mirror);
        let mut e = Vec::new();
        assemble(&prior, &fixed, &weights, ridge, &mut e);

        let n = 6 * prior.grid().count();
        let columns: Vec<Vec<f64>> = (0..n)
            .map(|j| {
                let mut coeffs = vec![[0.0; 6]; prior.grid().count()];
                coeffs[j / 6][j % 6] = 1.0;
                let mut z = vec![0.0; w * h];
                for y in 0..h {
                    prior.add_scaled_row(&coeffs, y, 1.0, &mut z[y * w..(y + 1) * w]);
                }
                z
            })
            .collect();
        let scale = e.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let mut az = vec![0.0; w * h];
        for (j, zj) in columns.iter().enumerate() {
            sys.apply(&weights, zj, &mut az);
            for (i, zi) in columns.iter().enumerate() {
                let want: f64 = zi.iter().zip(&az).map(|(a, b)| a * b).sum();
                let got = e[i * n + j];
                assert!(
                    (got - want).abs() <= 1e-10 * scale,
                    "E[{i}][{j}] = {got}, Zᵀ A Z = {want}"
                );
            }
        }
    }

    #[test]
    fn dense_cholesky_solves_an_spd_system() {
        let n = 7;
        let a: Vec<f64> = (0..n * n)
            .map(|k| {
                let (i, j) = (k / n, k % n);
                if i == j {
                    4.0 + i as f64
                } else {
                    1.0 / (1.0 + (i as f64 - j as f64).abs())
                }
            })
            .collect();
        let x: Vec<f64> = (0..n).map(|i| (i as f64 * 0.7).sin()).collect();
        let mut b: Vec<f64> = (0..n)
            .map(|i| (0..n).map(|j| a[i * n + j] * x[j]).sum())
            .collect();
        let mut l = a.clone();
        assert!(cholesky_in_place(&mut l, n));
        cholesky_solve_in_place(&l, &mut b);
        for (got, want) in b.iter().zip(&x) {
            assert!((got - want).abs() < 1e-12, "{got} vs {want}");
        }
        let mut not_pd = a;
        not_pd[0] = -1.0;
        assert!(!cholesky_in_place(&mut not_pd, n));
    }
}
