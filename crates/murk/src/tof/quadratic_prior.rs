//! Local quadratic prior (Eq. 5.10): the scattering component is a quadratic in each of K
//! non-overlapping patches. The a-step of Eq. 5.12 fits every patch's six coefficients.

// Small dense 6×6 algebra reads best with explicit indices.
#![allow(clippy::needless_range_loop)]

use rayon::prelude::*;

use crate::error::{MurkError, Result};

/// Weight floor ε of [`QuadraticPrior::fit_weighted`]: relative to an inlier's weight 1, small
/// enough that outliers barely pull the fit, large enough to keep every patch's system SPD.
pub const WEIGHTED_FIT_FLOOR: f64 = 1e-3;

/// Non-overlapping patch grid; the last patch along each axis absorbs the remainder pixels.
#[derive(Clone, Debug, PartialEq)]
pub struct PatchGrid {
    width: usize,
    height: usize,
    /// Column ranges `[start, end)` of the patch columns.
    cols: Vec<(usize, usize)>,
    /// Row ranges `[start, end)` of the patch rows.
    rows: Vec<(usize, usize)>,
}

fn split(len: usize, parts: usize) -> Vec<(usize, usize)> {
    let step = len / parts;
    (0..parts)
        .map(|i| {
            let end = if i + 1 == parts { len } else { (i + 1) * step };
            (i * step, end)
        })
        .collect()
}

impl PatchGrid {
    /// `patches_x × patches_y` patches over a `width × height` image. Callers validate that every
    /// patch is at least 3 pixels along each axis (`TofParams::validate`).
    pub fn new(width: usize, height: usize, patches_x: usize, patches_y: usize) -> Self {
        Self {
            width,
            height,
            cols: split(width, patches_x.max(1)),
            rows: split(height, patches_y.max(1)),
        }
    }
    /// Number of patches K.
    pub fn count(&self) -> usize {
        self.cols.len() * self.rows.len()
    }
    /// Patch columns.
    pub fn patches_x(&self) -> usize {
        self.cols.len()
    }
    /// Patch rows.
    pub fn patches_y(&self) -> usize {
        self.rows.len()
    }
    /// Column ranges `[start, end)`.
    pub fn col_ranges(&self) -> &[(usize, usize)] {
        &self.cols
    }
    /// Row ranges `[start, end)`.
    pub fn row_ranges(&self) -> &[(usize, usize)] {
        &self.rows
    }
    /// Patch row containing image row `y`.
    pub fn patch_row_of(&self, y: usize) -> usize {
        let step = self.height / self.rows.len();
        (y / step.max(1)).min(self.rows.len() - 1)
    }
    /// Patch column containing image column `x`.
    pub fn patch_col_of(&self, x: usize) -> usize {
        let step = self.width / self.cols.len();
        (x / step.max(1)).min(self.cols.len() - 1)
    }
    /// Image width.
    pub fn width(&self) -> usize {
        self.width
    }
    /// Image height.
    pub fn height(&self) -> usize {
        self.height
    }
}

/// Maps pixel coordinates into [−1, 1] over a patch so the 6×6 normal equations stay well
/// conditioned (raw pixel coordinates make u² ~ 10⁵ next to 1).
#[derive(Clone, Copy, Debug)]
struct Normaliser {
    centre: f64,
    inv_half: f64,
}

impl Normaliser {
    fn new((start, end): (usize, usize)) -> Self {
        let centre = 0.5 * (start as f64 + (end - 1) as f64);
        let half = (0.5 * (end - 1 - start) as f64).max(0.5);
        Self {
            centre,
            inv_half: 1.0 / half,
        }
    }
    #[inline]
    fn at(&self, p: usize) -> f64 {
        (p as f64 - self.centre) * self.inv_half
    }
}

/// Basis vector u = [u², uv, v², u, v, 1] of Eq. 5.10 in patch-normalised coordinates.
#[inline]
fn basis(u: f64, v: f64) -> [f64; 6] {
    [u * u, u * v, v * v, u, v, 1.0]
}

/// Cholesky factor (lower, row-major) of a 6×6 SPD matrix; `None` if not numerically PD.
fn cholesky6(a: &[[f64; 6]; 6]) -> Option<[[f64; 6]; 6]> {
    let mut l = [[0.0; 6]; 6];
    for i in 0..6 {
        for j in 0..=i {
            let mut s = a[i][j];
            for k in 0..j {
                s -= l[i][k] * l[j][k];
            }
            if i == j {
                // NaN also fails: compare explicitly instead of negating `>`.
                if s.is_nan() || s <= 1e-12 * a[i][i].abs().max(1e-300) {
                    return None;
                }
                l[i][i] = s.sqrt();
            } else {
                l[i][j] = s / l[j][j];
            }
        }
    }
    Some(l)
}

fn cholesky6_solve(l: &[[f64; 6]; 6], b: &[f64; 6]) -> [f64; 6] {
    let mut y = [0.0; 6];
    for i in 0..6 {
        let mut s = b[i];
        for k in 0..i {
            s -= l[i][k] * y[k];
        }
        y[i] = s / l[i][i];
    }
    let mut x = [0.0; 6];
    for i in (0..6).rev() {
        let mut s = y[i];
        for k in i + 1..6 {
            s -= l[k][i] * x[k];
        }
        x[i] = s / l[i][i];
    }
    x
}

/// Per-patch least-squares quadratic fits `a_k = argmin ‖U a_k − x_k‖²` (Eq. 5.10, a-step of
/// Eq. 5.12). `U` never changes, so each patch's Gram matrix is factored once. The IRLS a-step
/// uses the weighted variant [`QuadraticPrior::fit_weighted`] (a documented deviation, see
/// `irls::x_and_a_step`); the uniform [`QuadraticPrior::fit`] initialises Algorithm 2.
#[derive(Clone, Debug)]
pub struct QuadraticPrior {
    grid: PatchGrid,
    col_norm: Vec<Normaliser>,
    row_norm: Vec<Normaliser>,
    gram_chol: Vec<[[f64; 6]; 6]>,
    coeffs: Vec<[f64; 6]>,
    /// Per image row and patch column: Σu²x, Σux, Σx (f64 accumulation).
    row_sums: Vec<[f64; 3]>,
}

impl QuadraticPrior {
    /// Prepares the fits for `grid`; fails (`Numerical`) if a patch is too small to determine a
    /// quadratic, which validated parameters rule out.
    pub fn new(grid: PatchGrid) -> Result<Self> {
        let col_norm: Vec<_> = grid.cols.iter().map(|&r| Normaliser::new(r)).collect();
        let row_norm: Vec<_> = grid.rows.iter().map(|&r| Normaliser::new(r)).collect();
        let mut gram_chol = Vec::with_capacity(grid.count());
        for (py, &(y0, y1)) in grid.rows.iter().enumerate() {
            for (px, &(x0, x1)) in grid.cols.iter().enumerate() {
                let mut g = [[0.0; 6]; 6];
                for y in y0..y1 {
                    let v = row_norm[py].at(y);
                    for x in x0..x1 {
                        let b = basis(col_norm[px].at(x), v);
                        for i in 0..6 {
                            for j in 0..=i {
                                g[i][j] += b[i] * b[j];
                            }
                        }
                    }
                }
                for i in 0..6 {
                    for j in 0..i {
                        g[j][i] = g[i][j];
                    }
                }
                let l = cholesky6(&g).ok_or_else(|| {
                    MurkError::Numerical(format!(
                        "patch ({px}, {py}) of {}x{} pixels cannot determine a quadratic",
                        x1 - x0,
                        y1 - y0
                    ))
                })?;
                gram_chol.push(l);
            }
        }
        let k = grid.count();
        let row_sums = vec![[0.0; 3]; grid.height * grid.patches_x()];
        Ok(Self {
            grid,
            col_norm,
            row_norm,
            gram_chol,
            coeffs: vec![[0.0; 6]; k],
            row_sums,
        })
    }

    /// The patch grid.
    pub fn grid(&self) -> &PatchGrid {
        &self.grid
    }

    /// Coefficients a_k (row-major patch order) in patch-normalised coordinates: u, v ∈ [−1, 1]
    /// across each patch.
    pub fn coeffs(&self) -> &[[f64; 6]] {
        &self.coeffs
    }

    /// Fits every patch's quadratic to `x` (row-major, `width·height`).
    pub fn fit(&mut self, x: &[f64]) {
        let mut row_sums = std::mem::take(&mut self.row_sums);
        let mut coeffs = std::mem::take(&mut self.coeffs);
        self.fit_into(x, &mut row_sums, &mut coeffs);
        self.row_sums = row_sums;
        self.coeffs = coeffs;
    }

    /// Scratch for [`QuadraticPrior::fit_into`] sized for this grid: per image row and patch
    /// column the partial sums, and one coefficient vector per patch.
    pub fn scratch(&self) -> (Vec<[f64; 3]>, Vec<[f64; 6]>) {
        (
            vec![[0.0; 3]; self.grid.height * self.grid.patches_x()],
            vec![[0.0; 6]; self.grid.count()],
        )
    }

    /// The uniform fits of [`QuadraticPrior::fit`] written to `coeffs` (one per patch) without
    /// touching the prior's own state; `row_sums` is scratch from [`QuadraticPrior::scratch`].
    /// With [`QuadraticPrior::add_scaled_row`] this applies the orthogonal projection P onto
    /// per-patch quadratics, which the joint x-step needs inside every CG iteration.
    pub fn fit_into(&self, x: &[f64], row_sums: &mut [[f64; 3]], coeffs: &mut [[f64; 6]]) {
        self.moments_into(x, row_sums, coeffs);
        for (c, l) in coeffs.iter_mut().zip(&self.gram_chol) {
            *c = cholesky6_solve(l, c);
        }
    }

    /// Every patch's moments `Uᵀ x` (the right-hand side of its least-squares fit) into
    /// `moments`; `row_sums` is scratch from [`QuadraticPrior::scratch`]. With the patches'
    /// basis functions as the columns of a matrix Z (one 6-column block per patch), this is Zᵀx.
    pub fn moments_into(&self, x: &[f64], row_sums: &mut [[f64; 3]], moments: &mut [[f64; 6]]) {
        let w = self.grid.width;
        let pxn = self.grid.patches_x();
        let cols = &self.grid.cols;
        let col_norm = &self.col_norm;
        // Row partial sums in parallel, then a fixed-order reduction: deterministic results.
        row_sums
            .par_chunks_mut(pxn)
            .zip(x.par_chunks(w))
            .for_each(|(sums, row)| {
                for (px, &(x0, x1)) in cols.iter().enumerate() {
                    let (mut s2, mut s1, mut s0) = (0.0, 0.0, 0.0);
                    for (i, &val) in row[x0..x1].iter().enumerate() {
                        let u = col_norm[px].at(x0 + i);
                        s2 += u * u * val;
                        s1 += u * val;
                        s0 += val;
                    }
                    sums[px] = [s2, s1, s0];
                }
            });
        for (py, &(y0, y1)) in self.grid.rows.iter().enumerate() {
            for px in 0..pxn {
                let mut rhs = [0.0; 6];
                for y in y0..y1 {
                    let v = self.row_norm[py].at(y);
                    let [s2, s1, s0] = row_sums[y * pxn + px];
                    // Σ u·x over the row expands each basis term with v fixed along the row.
                    rhs[0] += s2;
                    rhs[1] += v * s1;
                    rhs[2] += v * v * s0;
                    rhs[3] += s1;
                    rhs[4] += v * s0;
                    rhs[5] += s0;
                }
                moments[py * pxn + px] = rhs;
            }
        }
    }

    /// Basis vector U at pixel (`x`, `y`) in its patch's normalised coordinates, and that
    /// patch's index (row-major).
    #[inline]
    pub fn basis_at(&self, x: usize, y: usize) -> (usize, [f64; 6]) {
        let (px, py) = (self.grid.patch_col_of(x), self.grid.patch_row_of(y));
        (
            py * self.grid.patches_x() + px,
            basis(self.col_norm[px].at(x), self.row_norm[py].at(y)),
        )
    }

    /// Every patch's weighted Gram matrix Σᵢ (wᵢ + `ridge`) Uᵢ Uᵢᵀ over its pixels, i.e. the
    /// diagonal blocks of Zᵀ diag(w + ridge) Z. Each entry is a moment Σ w·uᵖ·v^q (p + q ≤ 4),
    /// so per image row only the five sums Σ w·uᵖ are accumulated.
    pub fn weighted_grams(&self, weights: &[f64], ridge: f64) -> Vec<[[f64; 6]; 6]> {
        // Exponents (of u, of v) of the basis [u², uv, v², u, v, 1].
        const EXP: [(usize, usize); 6] = [(2, 0), (1, 1), (0, 2), (1, 0), (0, 1), (0, 0)];
        let w = self.grid.width;
        let pxn = self.grid.patches_x();
        let (cols, col_norm) = (&self.grid.cols, &self.col_norm);
        let mut row_sums = vec![[0.0; 5]; self.grid.height * pxn];
        row_sums
            .par_chunks_mut(pxn)
            .zip(weights.par_chunks(w))
            .for_each(|(sums, row)| {
                for (px, &(x0, x1)) in cols.iter().enumerate() {
                    let mut s = [0.0; 5];
                    for (i, &wi) in row[x0..x1].iter().enumerate() {
                        let u = col_norm[px].at(x0 + i);
                        let wi = wi + ridge;
                        let u2 = u * u;
                        s[0] += wi;
                        s[1] += wi * u;
                        s[2] += wi * u2;
                        s[3] += wi * u2 * u;
                        s[4] += wi * u2 * u2;
                    }
                    sums[px] = s;
                }
            });
        let mut grams = vec![[[0.0; 6]; 6]; self.grid.count()];
        for (py, &(y0, y1)) in self.grid.rows.iter().enumerate() {
            for px in 0..pxn {
                let g = &mut grams[py * pxn + px];
                for y in y0..y1 {
                    let v = self.row_norm[py].at(y);
                    let vp = [1.0, v, v * v, v * v * v, v * v * v * v];
                    let s = &row_sums[y * pxn + px];
                    for r in 0..6 {
                        for c in 0..=r {
                            g[r][c] += vp[EXP[r].1 + EXP[c].1] * s[EXP[r].0 + EXP[c].0];
                        }
                    }
                }
                for r in 0..6 {
                    for c in 0..r {
                        g[c][r] = g[r][c];
                    }
                }
            }
        }
        grams
    }

    /// `out[i] += scale·(U a_k)` along image row `y`, with `coeffs` one vector per patch (as from
    /// [`QuadraticPrior::fit_into`]).
    #[inline]
    pub fn add_scaled_row(&self, coeffs: &[[f64; 6]], y: usize, scale: f64, out: &mut [f64]) {
        let pxn = self.grid.patches_x();
        let py = self.grid.patch_row_of(y);
        let v = self.row_norm[py].at(y);
        for (px, &(x0, x1)) in self.grid.cols.iter().enumerate() {
            let a = &coeffs[py * pxn + px];
            let lin = a[1] * v + a[3];
            let cst = (a[2] * v + a[4]) * v + a[5];
            for (i, o) in out[x0..x1].iter_mut().enumerate() {
                let u = self.col_norm[px].at(x0 + i);
                *o += scale * ((a[0] * u + lin) * u + cst);
            }
        }
    }

    /// Weighted fits `a_k = argmin Σᵢ (wᵢ + ε)(U a_k − x)ᵢ²` over every patch, with `weights`
    /// the IRLS weights (row-major, `width·height`) and ε = [`WEIGHTED_FIT_FLOOR`]. Equal weights
    /// over a patch (the coarse level) give exactly [`QuadraticPrior::fit`]; ε keeps a patch
    /// whose pixels are all outliers determined (it then falls back to the unweighted fit).
    pub fn fit_weighted(&mut self, x: &[f64], weights: &[f64]) {
        let w = self.grid.width;
        let pxn = self.grid.patches_x();
        let grid = &self.grid;
        let (col_norm, row_norm) = (&self.col_norm, &self.row_norm);
        let fits: Vec<Option<[f64; 6]>> = (0..grid.count())
            .into_par_iter()
            .map(|k| {
                let (py, px) = (k / pxn, k % pxn);
                let (y0, y1) = grid.rows[py];
                let (x0, x1) = grid.cols[px];
                let mut g = [[0.0; 6]; 6];
                let mut rhs = [0.0; 6];
                for y in y0..y1 {
                    let v = row_norm[py].at(y);
                    for xi in x0..x1 {
                        let i = y * w + xi;
                        let wi = weights[i].max(0.0) + WEIGHTED_FIT_FLOOR;
                        let b = basis(col_norm[px].at(xi), v);
                        for r in 0..6 {
                            let wb = wi * b[r];
                            rhs[r] += wb * x[i];
                            for c in 0..=r {
                                g[r][c] += wb * b[c];
                            }
                        }
                    }
                }
                for r in 0..6 {
                    for c in 0..r {
                        g[c][r] = g[r][c];
                    }
                }
                cholesky6(&g).map(|l| cholesky6_solve(&l, &rhs))
            })
            .collect();
        let mut unweighted = None;
        for (k, f) in fits.into_iter().enumerate() {
            match f {
                Some(a) => self.coeffs[k] = a,
                None => {
                    // Numerically degenerate weighted Gram matrix: use the plain fit.
                    let plain = unweighted.get_or_insert_with(|| {
                        let mut q = self.clone();
                        q.fit(x);
                        q.coeffs
                    });
                    self.coeffs[k] = plain[k];
                }
            }
        }
    }

    /// Writes U a_k for every pixel (the prior image that enters the x-step right-hand side).
    pub fn evaluate(&self, out: &mut [f64]) {
        let w = self.grid.width;
        let pxn = self.grid.patches_x();
        out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            let py = self.grid.patch_row_of(y);
            let v = self.row_norm[py].at(y);
            for (px, &(x0, x1)) in self.grid.cols.iter().enumerate() {
                let a = &self.coeffs[py * pxn + px];
                let lin = a[1] * v + a[3];
                let cst = (a[2] * v + a[4]) * v + a[5];
                for (i, o) in row[x0..x1].iter_mut().enumerate() {
                    let u = self.col_norm[px].at(x0 + i);
                    *o = (a[0] * u + lin) * u + cst;
                }
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_last_patch_absorbs_remainder() {
        let g = PatchGrid::new(10, 7, 3, 2);
        assert_eq!(g.col_ranges(), &[(0, 3), (3, 6), (6, 10)]);
        assert_eq!(g.row_ranges(), &[(0, 3), (3, 7)]);
        assert_eq!(g.patch_row_of(6), 1);
        assert_eq!(g.patch_row_of(2), 0);
        assert_eq!(g.count(), 6);
    }

    #[test]
    fn fit_is_exact_on_a_quadratic() {
        let (w, h) = (37, 29);
        // A different quadratic per patch region would not be exact; one global quadratic is a
        // quadratic in every patch, whatever the per-patch normalisation.
        let f =
            |x: f64, y: f64| 0.3 * x * x - 0.07 * x * y + 0.11 * y * y - 2.0 * x + 5.0 * y + 40.0;
        let img: Vec<f64> = (0..w * h)
            .map(|i| f((i % w) as f64, (i / w) as f64))
            .collect();
        let mut q = QuadraticPrior::new(PatchGrid::new(w, h, 4, 3)).unwrap();
        q.fit(&img);
        let mut out = vec![0.0; w * h];
        q.evaluate(&mut out);
        for (a, b) in out.iter().zip(&img) {
            assert!((a - b).abs() < 1e-9 * b.abs().max(1.0), "{a} vs {b}");
        }
    }

    #[test]
    fn weighted_fit_ignores_zero_weight_pixels_and_matches_uniform_weights() {
        let (w, h) = (24, 18);
        let f = |x: f64, y: f64| 0.02 * x * x - 0.01 * x * y + 0.03 * y * y + x - y + 10.0;
        let clean: Vec<f64> = (0..w * h)
            .map(|i| f((i % w) as f64, (i / w) as f64))
            .collect();
        let mut q = QuadraticPrior::new(PatchGrid::new(w, h, 2, 2)).unwrap();
        // Uniform weights (any value, zero included) reproduce the plain fit.
        let noisy: Vec<f64> = (0..w * h).map(|i| ((i * 7919) % 13) as f64).collect();
        q.fit(&noisy);
        let plain = q.coeffs().to_vec();
        for wt in [1.0, 0.3, 0.0] {
            q.fit_weighted(&noisy, &vec![wt; w * h]);
            for (a, b) in q.coeffs().iter().zip(&plain) {
                for (u, v) in a.iter().zip(b) {
                    assert!((u - v).abs() < 1e-9 * v.abs().max(1.0), "{u} vs {v}");
                }
            }
        }
        // A bright block with weight 0 barely moves the fit of the quadratic underneath (only ε
        // of it pulls: < 0.5 % of its height).
        let mut img = clean.clone();
        let mut weights = vec![1.0; w * h];
        for y in 2..8 {
            for x in 3..10 {
                img[y * w + x] += 500.0;
                weights[y * w + x] = 0.0;
            }
        }
        q.fit_weighted(&img, &weights);
        let mut out = vec![0.0; w * h];
        q.evaluate(&mut out);
        for (a, b) in out.iter().zip(&clean) {
            assert!((a - b).abs() < 2.5, "{a} vs {b}");
        }
        q.fit(&img);
        q.evaluate(&mut out);
        assert!(out.iter().zip(&clean).any(|(a, b)| (a - b).abs() > 50.0));
    }

    #[test]
    fn fit_is_least_squares_on_noise() {
        // Residual of a least-squares fit is orthogonal to the basis: Σ (x − Ua)·1 = 0 per patch.
        let (w, h) = (20, 12);
        let img: Vec<f64> = (0..w * h).map(|i| ((i * 7919) % 13) as f64).collect();
        let mut q = QuadraticPrior::new(PatchGrid::new(w, h, 2, 2)).unwrap();
        q.fit(&img);
        let mut out = vec![0.0; w * h];
        q.evaluate(&mut out);
        for &(y0, y1) in q.grid().row_ranges() {
            for &(x0, x1) in q.grid().col_ranges() {
                let mut s = 0.0;
                for y in y0..y1 {
                    for x in x0..x1 {
                        s += img[y * w + x] - out[y * w + x];
                    }
                }
                assert!(s.abs() < 1e-9, "{s}");
            }
        }
    }
}
