//! Geometric multigrid V-cycle used as the conjugate-gradient preconditioner of the x-step
//! (Eq. 5.12).
//!
//! The preconditioned operator is the x-step operator without the (non-local) mirror coupling:
//! a weighted graph Laplacian on the pixel grid plus a diagonal "mass",
//!
//! M = diag(W + γ′₁ + 2γ′₂[row paired]) + γ′₃∇ᵀ∇,
//!
//! i.e. the mirror term keeps only its diagonal. Jacobi-preconditioned CG needs O(√κ) iterations
//! and κ ≈ 8γ′₃/γ′₁ is huge where W ≈ 0 (objects); a V-cycle removes the smooth error at every
//! scale, so the iteration count barely depends on κ or on the image size.
//!
//! Levels: 2×2 aggregation (odd sizes leave 1-wide aggregates at the far border), piecewise-
//! constant prolongation P and restriction Pᵀ. The coarse mass is the Galerkin one (sum of the
//! aggregate's masses: a zeroth-order term integrates over area), the coarse edge weights are
//! rediscretised (mean of the fine edges crossing between two aggregates: the Dirichlet energy
//! Σ γ(Δx)² of a smooth field is scale-invariant in 2-D). Pure Galerkin aggregation would double
//! the stiffness at each level and make the coarse corrections far too small.
//!
//! Smoother: red-black Gauss–Seidel, red→black before and black→red after the coarse
//! correction, and a fixed number of symmetric sweeps on the coarsest grid; with zero initial
//! guesses the whole V-cycle is a fixed symmetric positive-definite linear operator, as CG needs.

use rayon::prelude::*;

/// Coarsening stops once both sides are at most this many pixels.
const COARSEST_SIDE: usize = 8;
/// Symmetric Gauss–Seidel sweeps on the coarsest grid (≤ 64 unknowns whose mass dominates).
const COARSEST_SWEEPS: usize = 8;
/// Rows per rayon task; smaller levels run sequentially.
const PAR_MIN_PIXELS: usize = 16_384;

/// Precision of the preconditioner's arithmetic: it only has to approximate M⁻¹, and f32 halves
/// the memory traffic of the (bandwidth-bound) sweeps. CG itself stays in f64.
type Real = f32;

#[derive(Clone, Debug, Default)]
struct Level {
    w: usize,
    h: usize,
    /// Zeroth-order diagonal per pixel.
    mass: Vec<Real>,
    /// Weight of the edge (x, y)–(x+1, y) at `y·w + x` (0 in the last column).
    ex: Vec<Real>,
    /// Weight of the edge (x, y)–(x, y+1) at `y·w + x` (0 in the last row).
    ey: Vec<Real>,
    diag: Vec<Real>,
    inv_diag: Vec<Real>,
    /// Solution, right-hand side and residual buffers.
    u: Vec<Real>,
    f: Vec<Real>,
    r: Vec<Real>,
}

impl Level {
    fn len(&self) -> usize {
        self.w * self.h
    }

    fn refresh_diag(&mut self) {
        let w = self.w;
        let (mass, ex, ey) = (&self.mass, &self.ex, &self.ey);
        self.diag
            .par_chunks_mut(w)
            .zip(self.inv_diag.par_chunks_mut(w))
            .enumerate()
            .with_min_len(rows_per_task(w))
            .for_each(|(y, (d, inv))| {
                for x in 0..w {
                    let i = y * w + x;
                    let mut s = mass[i] + ex[i] + ey[i];
                    if x > 0 {
                        s += ex[i - 1];
                    }
                    if y > 0 {
                        s += ey[i - w];
                    }
                    d[x] = s;
                    inv[x] = 1.0 / s;
                }
            });
    }

    /// Gauss–Seidel update of the pixels of row `y` with `(x + y) % 2 == colour`.
    ///
    /// # Safety
    /// `u` points to `self.len()` values; no other thread writes the pixels this reads (the
    /// other colour in rows y−1..=y+1) or reads/writes the ones it writes.
    #[inline(always)]
    unsafe fn relax_row(&self, u: *mut Real, f: &[Real], y: usize, colour: usize) {
        let w = self.w;
        let row = y * w;
        let (up, dn) = (y > 0, y + 1 < self.h);
        let (ex, ey, inv) = (&self.ex[..], &self.ey[..], &self.inv_diag[..]);
        let mut x = (colour + y) % 2;
        while x < w {
            let i = row + x;
            let mut s = f[i];
            if x > 0 {
                s += ex[i - 1] * *u.add(i - 1);
            }
            if x + 1 < w {
                s += ex[i] * *u.add(i + 1);
            }
            if up {
                s += ey[i - w] * *u.add(i - w);
            }
            if dn {
                s += ey[i] * *u.add(i + w);
            }
            *u.add(i) = s * inv[i];
            x += 2;
        }
    }

    /// One Gauss–Seidel half-sweep over the pixels with `(x + y) % 2 == colour`.
    fn relax(&self, u: &mut [Real], f: &[Real], colour: usize) {
        assert_eq!(u.len(), self.len());
        if self.len() >= PAR_MIN_PIXELS {
            // Pixels of one colour only read pixels of the other: rows are independent.
            let ptr = SharedMut(u.as_mut_ptr());
            (0..self.h)
                .into_par_iter()
                .with_min_len(rows_per_task(self.w))
                .for_each(|y| {
                    let p = &ptr;
                    // SAFETY: every task writes only the `colour` pixels of its own row and
                    // reads only pixels of the other colour, which no task writes during this
                    // half-sweep.
                    unsafe { self.relax_row(p.0, f, y, colour) };
                });
        } else {
            let p = u.as_mut_ptr();
            for y in 0..self.h {
                // SAFETY: sequential; `p` covers the level.
                unsafe { self.relax_row(p, f, y, colour) };
            }
        }
    }

    /// `r = f − M u` for row `y`.
    #[inline(always)]
    fn residual_row(&self, u: &[Real], f: &[Real], y: usize, rr: &mut [Real]) {
        let w = self.w;
        let row = y * w;
        let (up, dn) = (y > 0, y + 1 < self.h);
        for (x, ri) in rr.iter_mut().enumerate() {
            let i = row + x;
            let mut s = f[i] - self.diag[i] * u[i];
            if x > 0 {
                s += self.ex[i - 1] * u[i - 1];
            }
            if x + 1 < w {
                s += self.ex[i] * u[i + 1];
            }
            if up {
                s += self.ey[i - w] * u[i - w];
            }
            if dn {
                s += self.ey[i] * u[i + w];
            }
            *ri = s;
        }
    }

    /// `r = f − M u`.
    fn residual(&self, u: &[Real], f: &[Real], r: &mut [Real]) {
        let w = self.w;
        if self.len() >= PAR_MIN_PIXELS {
            r.par_chunks_mut(w)
                .enumerate()
                .with_min_len(rows_per_task(w))
                .for_each(|(y, rr)| self.residual_row(u, f, y, rr));
        } else {
            for (y, rr) in r.chunks_mut(w).enumerate() {
                self.residual_row(u, f, y, rr);
            }
        }
    }
}

fn rows_per_task(w: usize) -> usize {
    (4096 / w.max(1)).max(1)
}

struct SharedMut(*mut Real);
// SAFETY: used only for the disjoint red-black writes documented in `Level::relax`.
unsafe impl Sync for SharedMut {}
unsafe impl Send for SharedMut {}

/// The level hierarchy; built once per image size and γ′, refreshed per solve (only W changes).
#[derive(Clone, Debug, Default)]
pub struct Multigrid {
    levels: Vec<Level>,
    /// Smoothing sweeps before and after each coarse correction.
    sweeps: usize,
}

impl Multigrid {
    /// Hierarchy for a `w × h` grid with uniform edge weight `g3` (γ′₃); masses set by
    /// [`Multigrid::set_mass`].
    pub fn new(w: usize, h: usize, g3: f64) -> Self {
        let mut levels = vec![Level {
            w,
            h,
            mass: vec![0.0; w * h],
            ex: (0..w * h)
                .map(|i| if i % w + 1 < w { g3 as Real } else { 0.0 })
                .collect(),
            ey: (0..w * h)
                .map(|i| if i / w + 1 < h { g3 as Real } else { 0.0 })
                .collect(),
            diag: vec![0.0; w * h],
            inv_diag: vec![0.0; w * h],
            u: vec![0.0; w * h],
            f: vec![0.0; w * h],
            r: Vec::new(),
        }];
        while {
            let l = levels.last().expect("level");
            l.w > COARSEST_SIDE || l.h > COARSEST_SIDE
        } {
            let f = levels.last().expect("level");
            let (cw, ch) = (f.w.div_ceil(2), f.h.div_ceil(2));
            let n = cw * ch;
            let mut ex = vec![0.0; n];
            let mut ey = vec![0.0; n];
            for cy in 0..ch {
                let rows = (2 * cy)..(2 * cy + 2).min(f.h);
                for cx in 0..cw {
                    let cols = (2 * cx)..(2 * cx + 2).min(f.w);
                    if cx + 1 < cw {
                        let s: Real = rows.clone().map(|y| f.ex[y * f.w + 2 * cx + 1]).sum();
                        ex[cy * cw + cx] = s / rows.len() as Real;
                    }
                    if cy + 1 < ch {
                        let s: Real = cols.clone().map(|x| f.ey[(2 * cy + 1) * f.w + x]).sum();
                        ey[cy * cw + cx] = s / cols.len() as Real;
                    }
                }
            }
            levels.push(Level {
                w: cw,
                h: ch,
                mass: vec![0.0; n],
                ex,
                ey,
                diag: vec![0.0; n],
                inv_diag: vec![0.0; n],
                u: vec![0.0; n],
                f: vec![0.0; n],
                r: Vec::new(),
            });
        }
        for l in 0..levels.len() - 1 {
            let n = levels[l].len();
            levels[l].r = vec![0.0; n];
        }
        Self { levels, sweeps: 1 }
    }

    /// Finest grid's `(width, height)`.
    pub fn dims(&self) -> (usize, usize) {
        (self.levels[0].w, self.levels[0].h)
    }

    /// Number of levels (the finest included).
    pub fn levels(&self) -> usize {
        self.levels.len()
    }

    /// Sets the finest level's mass (`mass(i)` per pixel) and aggregates it down the hierarchy.
    pub fn set_mass(&mut self, mass: impl Fn(usize) -> f64 + Sync) {
        let l0 = &mut self.levels[0];
        l0.mass
            .par_iter_mut()
            .enumerate()
            .for_each(|(i, m)| *m = mass(i) as Real);
        l0.refresh_diag();
        for l in 1..self.levels.len() {
            let (fine, coarse) = self.levels.split_at_mut(l);
            let f = &fine[l - 1];
            let c = &mut coarse[0];
            c.mass.fill(0.0);
            for y in 0..f.h {
                let crow = (y / 2) * c.w;
                for x in 0..f.w {
                    c.mass[crow + x / 2] += f.mass[y * f.w + x];
                }
            }
            c.refresh_diag();
        }
    }

    /// `z = B r`, B ≈ M⁻¹ the V-cycle (symmetric positive definite).
    pub fn apply(&mut self, r: &[f64], z: &mut [f64]) {
        let l0 = &mut self.levels[0];
        l0.f.par_iter_mut()
            .zip(r.par_iter())
            .for_each(|(f, &v)| *f = v as Real);
        l0.u.fill(0.0);
        self.vcycle_at(0);
        z.par_iter_mut()
            .zip(self.levels[0].u.par_iter())
            .for_each(|(z, &v)| *z = v as f64);
    }

    fn vcycle_at(&mut self, l: usize) {
        let lv = &mut self.levels[l];
        let mut f = std::mem::take(&mut lv.f);
        let mut u = std::mem::take(&mut lv.u);
        let mut r = std::mem::take(&mut lv.r);
        self.vcycle(l, &f, &mut u, &mut r);
        let lv = &mut self.levels[l];
        std::mem::swap(&mut lv.f, &mut f);
        std::mem::swap(&mut lv.u, &mut u);
        std::mem::swap(&mut lv.r, &mut r);
    }

    fn vcycle(&mut self, l: usize, f: &[Real], u: &mut [Real], res: &mut [Real]) {
        let last = l + 1 == self.levels.len();
        if last {
            let lv = &self.levels[l];
            for _ in 0..COARSEST_SWEEPS {
                lv.relax(u, f, 0);
                lv.relax(u, f, 1);
                lv.relax(u, f, 1);
                lv.relax(u, f, 0);
            }
            return;
        }
        for _ in 0..self.sweeps {
            self.levels[l].relax(u, f, 0);
            self.levels[l].relax(u, f, 1);
        }
        self.levels[l].residual(u, f, res);
        let (fine, coarse) = self.levels.split_at_mut(l + 1);
        let fl = &fine[l];
        let c = &mut coarse[0];
        // Restriction Pᵀ: sum over the aggregate, coarse row by coarse row (each cell adds its
        // fine pixels in the same order either way).
        let restrict = |cy: usize, crow: &mut [Real]| {
            crow.fill(0.0);
            for y in 2 * cy..(2 * cy + 2).min(fl.h) {
                for (x, &v) in res[y * fl.w..(y + 1) * fl.w].iter().enumerate() {
                    crow[x / 2] += v;
                }
            }
        };
        if fl.w * fl.h >= PAR_MIN_PIXELS {
            c.f.par_chunks_mut(c.w)
                .enumerate()
                .for_each(|(cy, crow)| restrict(cy, crow));
        } else {
            for (cy, crow) in c.f.chunks_mut(c.w).enumerate() {
                restrict(cy, crow);
            }
        }
        c.u.fill(0.0);
        self.vcycle_at(l + 1);
        let fl = &self.levels[l];
        let cw = self.levels[l + 1].w;
        // Prolongation P: piecewise constant.
        let (fw, fh) = (fl.w, fl.h);
        let cu = &self.levels[l + 1].u;
        if fw * fh >= PAR_MIN_PIXELS {
            u.par_chunks_mut(fw).enumerate().for_each(|(y, row)| {
                let crow = &cu[(y / 2) * cw..];
                for (x, ui) in row.iter_mut().enumerate() {
                    *ui += crow[x / 2];
                }
            });
        } else {
            for (y, row) in u.chunks_mut(fw).enumerate() {
                let crow = &cu[(y / 2) * cw..];
                for (x, ui) in row.iter_mut().enumerate() {
                    *ui += crow[x / 2];
                }
            }
        }
        for _ in 0..self.sweeps {
            self.levels[l].relax(u, f, 1);
            self.levels[l].relax(u, f, 0);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Dense M of a level (mass + graph Laplacian).
    fn dense(l: &Level) -> Vec<f64> {
        let n = l.len();
        let mut a = vec![0.0; n * n];
        for y in 0..l.h {
            for x in 0..l.w {
                let i = y * l.w + x;
                a[i * n + i] += l.mass[i] as f64;
                for (j, e) in [(i + 1, l.ex[i] as f64), (i + l.w, l.ey[i] as f64)] {
                    if e != 0.0 {
                        a[i * n + i] += e;
                        a[j * n + j] += e;
                        a[i * n + j] -= e;
                        a[j * n + i] -= e;
                    }
                }
            }
        }
        a
    }

    #[test]
    fn vcycle_is_symmetric_and_positive() {
        for (w, h) in [(13, 11), (20, 17), (5, 4)] {
            let mut mg = Multigrid::new(w, h, 7.0);
            mg.set_mass(|i| if i % 5 == 0 { 0.01 } else { 1.0 });
            let n = w * h;
            // Columns of B.
            let mut b = vec![0.0; n * n];
            let mut e = vec![0.0; n];
            let mut z = vec![0.0; n];
            for j in 0..n {
                e.fill(0.0);
                e[j] = 1.0;
                mg.apply(&e, &mut z);
                for i in 0..n {
                    b[i * n + j] = z[i];
                }
            }
            for i in 0..n {
                assert!(b[i * n + i] > 0.0);
                for j in 0..i {
                    let (p, q) = (b[i * n + j], b[j * n + i]);
                    // f32 arithmetic: symmetric up to rounding.
                    assert!(
                        (p - q).abs() <= 1e-5 * (p.abs() + q.abs() + 1e-3),
                        "{w}x{h}"
                    );
                }
            }
            // Residual check on level 0: M applied to B r approximates r (one V-cycle contracts).
            let a = dense(&mg.levels[0]);
            let r: Vec<f64> = (0..n).map(|i| ((i * 31) % 13) as f64 - 6.0).collect();
            mg.apply(&r, &mut z);
            let mut res = 0.0;
            let mut rn = 0.0;
            for i in 0..n {
                let ar: f64 = (0..n).map(|j| a[i * n + j] * z[j]).sum();
                res += (r[i] - ar).powi(2);
                rn += r[i] * r[i];
            }
            assert!(
                res.sqrt() < 0.5 * rn.sqrt(),
                "{w}x{h}: {}",
                res.sqrt() / rn.sqrt()
            );
        }
    }
}
