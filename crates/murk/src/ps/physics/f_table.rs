//! Sun et al.'s 2D lookup table F(u, v) = ∫₀^v exp(−u·tan ξ) dξ (text after Eq. 4.36), for
//! u ≥ 0 and v ∈ [0, π/2].
//!
//! Grid. F is smooth except at the corner (u, v) = (0, π/2): there F(u, π/2) ≈ π/2 + u·ln u
//! (∂F/∂u = ln cos v diverges) and, for small u, ∂F/∂v = exp(−u·tan v) drops from 1 to 0 within
//! π/2 − v ~ u. Near the corner F − F(0, ·) behaves like u·φ((π/2 − v)/u), a function homogeneous
//! of degree one in (u, π/2 − v). The table is therefore uniform in
//! `s = √(u/U_MAX)` and `t = 1 − √(1 − v/(π/2))`: both are quadratic maps, so the corner
//! term becomes homogeneous of degree two in (s, 1 − t), and bilinear interpolation has an
//! O(h²) error except for a mild O(h²·|ln u|) growth along v = π/2 from the u·ln u term. The
//! measured worst absolute error of [`FTable::global`] is 1.6·10⁻⁵ (at u = 10⁻⁶, v → π/2;
//! the test bound is 2·10⁻⁵ over a grid of u ∈ [0, 1000] incl. the corner and the table edge).
//!
//! Beyond the table (u > [`U_MAX`]) F uses the asymptotic expansion
//! 1/(1 + τ²) ≈ 1 − τ² + τ⁴ − τ⁶ in F = ∫₀^{tan v} e^{−uτ}/(1 + τ²) dτ, whose error is below
//! 8!/u⁹ ≤ 1.2·10⁻⁸ there. Arguments are clamped: u < 0 reads as 0, v outside [0, π/2] as the
//! nearest end.
//!
//! The same grid also holds, built on first use, the two weighted companions that the
//! Lambertian facet's forward scatter needs ([`super::facet_emission`]):
//! F_c(u, v) = ∫₀^v e^{−u tan ξ} cos 2ξ dξ and F_s(u, v) = ∫₀^v e^{−u tan ξ} sin 2ξ dξ. Their
//! integrands are bounded by F's, so the grid's accuracy carries over; beyond [`U_MAX`] they use
//! the same asymptotic expansion with (1 − τ²)/(1 + τ²)² and 2τ/(1 + τ²)² in place of
//! 1/(1 + τ²).

use std::f64::consts::FRAC_PI_2;
use std::sync::OnceLock;

use rayon::prelude::*;

use super::quad;

/// Largest u held in the table; larger u use the asymptotic form.
pub const U_MAX: f64 = 24.0;
const DEFAULT_NU: usize = 2048;
const DEFAULT_NV: usize = 1024;

/// Tabulated F(u, v) with bilinear interpolation on the quadratic grid described in the module
/// documentation.
#[derive(Clone, Debug)]
pub struct FTable {
    nu: usize,
    nv: usize,
    /// (nu−1)/√U_MAX: maps √u straight to a fractional grid index.
    su_scale: f64,
    /// nv − 1: maps t to a fractional grid index.
    sv_scale: f64,
    /// Row-major, `values[i·nv + j] = F(u_i, v_j)`.
    values: Vec<f32>,
    /// Row-major `[F_c, F_s]` on the same grid, built on first use (module documentation).
    facet: OnceLock<Vec<[f32; 2]>>,
}

/// u at grid index i.
fn u_at(i: usize, nu: usize) -> f64 {
    let s = i as f64 / (nu - 1) as f64;
    U_MAX * s * s
}

/// v at grid index j.
fn v_at(j: usize, nv: usize) -> f64 {
    let t = 1.0 - j as f64 / (nv - 1) as f64;
    FRAC_PI_2 * (1.0 - t * t)
}

impl FTable {
    /// Builds an `nu × nv` table (each ≥ 2) by integrating F cell by cell in v with an 8-point
    /// Gauss–Legendre rule per cell (the cells shrink quadratically towards π/2, where the
    /// integrand is sharp, so this is accurate to ~1e-12), in parallel over u.
    pub fn new(nu: usize, nv: usize) -> FTable {
        let (nu, nv) = (nu.max(2), nv.max(2));
        let rule = quad::gauss_legendre(8);
        let mut values = vec![0f32; nu * nv];
        values.par_chunks_mut(nv).enumerate().for_each(|(i, row)| {
            let u = u_at(i, nu);
            let mut acc = 0.0f64;
            let mut v0 = 0.0;
            row[0] = 0.0;
            for (j, slot) in row.iter_mut().enumerate().skip(1) {
                let v1 = v_at(j, nv);
                acc += quad::gl_apply(&rule, v0, v1, &mut |xi| integrand(u, xi));
                *slot = acc as f32;
                v0 = v1;
            }
        });
        FTable {
            nu,
            nv,
            su_scale: (nu - 1) as f64 / U_MAX.sqrt(),
            sv_scale: (nv - 1) as f64,
            values,
            facet: OnceLock::new(),
        }
    }

    /// `[F_c, F_s]` at every grid node, integrated like F (8-point Gauss–Legendre per cell).
    fn facet_values(&self) -> &[[f32; 2]] {
        self.facet.get_or_init(|| {
            let (nu, nv) = (self.nu, self.nv);
            let rule = quad::gauss_legendre(8);
            let mut values = vec![[0f32; 2]; nu * nv];
            values.par_chunks_mut(nv).enumerate().for_each(|(i, row)| {
                let u = u_at(i, nu);
                let (mut acc_c, mut acc_s) = (0.0f64, 0.0f64);
                let mut v0 = 0.0;
                for (j, slot) in row.iter_mut().enumerate().skip(1) {
                    let v1 = v_at(j, nv);
                    acc_c += quad::gl_apply(&rule, v0, v1, &mut |xi| {
                        integrand(u, xi) * (2.0 * xi).cos()
                    });
                    acc_s += quad::gl_apply(&rule, v0, v1, &mut |xi| {
                        integrand(u, xi) * (2.0 * xi).sin()
                    });
                    *slot = [acc_c as f32, acc_s as f32];
                    v0 = v1;
                }
            });
            values
        })
    }

    /// The process-wide table (2048 × 1024, 8 MiB), built on first use (~0.1 s).
    pub fn global() -> &'static FTable {
        static T: OnceLock<FTable> = OnceLock::new();
        T.get_or_init(|| FTable::new(DEFAULT_NU, DEFAULT_NV))
    }

    /// Memory held by the table (and its facet companions once built), bytes.
    pub fn bytes(&self) -> usize {
        self.values.len() * std::mem::size_of::<f32>()
            + self
                .facet
                .get()
                .map_or(0, |f| f.len() * std::mem::size_of::<[f32; 2]>())
    }

    /// Fractional u index, clamped to the table.
    #[inline(always)]
    fn u_index(&self, u: f64) -> (usize, f64) {
        self.u_split(self.u_coord(u))
    }

    /// Fractional v index, clamped to the table.
    #[inline(always)]
    fn v_index(&self, v: f64) -> (usize, f64) {
        self.v_split(self.v_coord(v))
    }

    /// u's fractional grid coordinate, clamped to the table: the arithmetic half of the lookup,
    /// which the kernel build computes for several entries at once
    /// ([`super::kernel_batch`]); [`FTable::eval_diff_coords`] takes it.
    #[inline(always)]
    pub(crate) fn u_coord(&self, u: f64) -> f64 {
        (u.max(0.0).sqrt() * self.su_scale).min((self.nu - 1) as f64)
    }

    /// v's fractional grid coordinate (see [`FTable::u_coord`]).
    #[inline(always)]
    pub(crate) fn v_coord(&self, v: f64) -> f64 {
        let w = (1.0 - v * (1.0 / FRAC_PI_2)).clamp(0.0, 1.0);
        (1.0 - w.sqrt()) * self.sv_scale
    }

    /// Grid row and fraction of a u coordinate.
    #[inline(always)]
    fn u_split(&self, su: f64) -> (usize, f64) {
        let i = (su as usize).min(self.nu - 2);
        (i, su - i as f64)
    }

    /// Grid column and fraction of a v coordinate.
    #[inline(always)]
    fn v_split(&self, sv: f64) -> (usize, f64) {
        let j = (sv as usize).min(self.nv - 2);
        (j, sv - j as f64)
    }

    #[inline(always)]
    fn bilinear(&self, (i, fu): (usize, f64), (j, fv): (usize, f64)) -> f64 {
        let r0 = i * self.nv + j;
        let r1 = r0 + self.nv;
        let a = self.values[r0] as f64 + fv * (self.values[r0 + 1] - self.values[r0]) as f64;
        let b = self.values[r1] as f64 + fv * (self.values[r1 + 1] - self.values[r1]) as f64;
        a + fu * (b - a)
    }

    /// F(u, v), interpolated (asymptotic beyond [`U_MAX`]; see the module documentation).
    #[inline]
    pub fn eval(&self, u: f64, v: f64) -> f64 {
        if u > U_MAX {
            return f_asymptotic(u, v);
        }
        self.bilinear(self.u_index(u), self.v_index(v))
    }

    /// F(u, v2) − F(u, v1), the bracket of Eq. 4.33, sharing the u lookup between both ends
    /// (the hot path of the kernel build).
    #[inline]
    pub fn eval_diff(&self, u: f64, v1: f64, v2: f64) -> f64 {
        if u > U_MAX {
            return f_asymptotic(u, v2) - f_asymptotic(u, v1);
        }
        let iu = self.u_index(u);
        self.bilinear(iu, self.v_index(v2)) - self.bilinear(iu, self.v_index(v1))
    }

    /// [`FTable::eval_diff`] from grid coordinates ([`FTable::u_coord`], [`FTable::v_coord`]) of
    /// u ≤ [`U_MAX`], v1 and v2: the same value bit for bit.
    #[inline(always)]
    pub(crate) fn eval_diff_coords(&self, su: f64, sv1: f64, sv2: f64) -> f64 {
        let iu = self.u_split(su);
        self.bilinear(iu, self.v_split(sv2)) - self.bilinear(iu, self.v_split(sv1))
    }

    /// [`FTable::eval_facet_diff`] from grid coordinates of u ≤ [`U_MAX`], v1 and v2 (see
    /// [`FTable::eval_diff_coords`]).
    #[inline(always)]
    pub(crate) fn eval_facet_diff_coords(&self, su: f64, sv1: f64, sv2: f64) -> [f64; 2] {
        let t = self.facet_values();
        let (i, fu) = self.u_split(su);
        let hi = bilinear_pair(t, self.nv, i, fu, self.v_split(sv2));
        let lo = bilinear_pair(t, self.nv, i, fu, self.v_split(sv1));
        [hi[0] - lo[0], hi[1] - lo[1]]
    }

    /// [F_c(u, v2) − F_c(u, v1), F_s(u, v2) − F_s(u, v1)] (module documentation), sharing the
    /// index computations between both tables and both ends. The first call builds the
    /// companions (about twice F's build time).
    #[inline(always)]
    pub fn eval_facet_diff(&self, u: f64, v1: f64, v2: f64) -> [f64; 2] {
        if u > U_MAX {
            return [
                series_asymptotic(u, v2, &FC_SERIES) - series_asymptotic(u, v1, &FC_SERIES),
                series_asymptotic(u, v2, &FS_SERIES) - series_asymptotic(u, v1, &FS_SERIES),
            ];
        }
        let t = self.facet_values();
        let (i, fu) = self.u_index(u);
        let hi = bilinear_pair(t, self.nv, i, fu, self.v_index(v2));
        let lo = bilinear_pair(t, self.nv, i, fu, self.v_index(v1));
        [hi[0] - lo[0], hi[1] - lo[1]]
    }

    /// [F_c(u, v), F_s(u, v)], interpolated (asymptotic beyond [`U_MAX`]).
    pub fn eval_facet(&self, u: f64, v: f64) -> [f64; 2] {
        self.eval_facet_diff(u, 0.0, v)
    }
}

/// Bilinear interpolation of both companions at row `i` (fraction `fu`) and column `j`
/// (fraction `fv`) of the row-major pair table with `nv` columns.
#[inline(always)]
fn bilinear_pair(t: &[[f32; 2]], nv: usize, i: usize, fu: f64, (j, fv): (usize, f64)) -> [f64; 2] {
    let r0 = i * nv + j;
    let (a, b) = (&t[r0..r0 + 2], &t[r0 + nv..r0 + nv + 2]);
    let lerp = |k: usize| {
        let x = a[0][k] as f64 + fv * (a[1][k] - a[0][k]) as f64;
        let y = b[0][k] as f64 + fv * (b[1][k] - b[0][k]) as f64;
        x + fu * (y - x)
    };
    [lerp(0), lerp(1)]
}

/// Taylor coefficients in τ = tan ξ of 1/(1 + τ²) = Σ (−1)^k τ^{2k}, F's weight after
/// dξ = dτ/(1 + τ²).
const F_SERIES: [f64; 7] = [1.0, 0.0, -1.0, 0.0, 1.0, 0.0, -1.0];
/// Taylor coefficients in τ = tan ξ of (1 − τ²)/(1 + τ²)² = Σ (−1)^k (2k+1) τ^{2k}, the weight of
/// F_c after dξ = dτ/(1 + τ²).
const FC_SERIES: [f64; 7] = [1.0, 0.0, -3.0, 0.0, 5.0, 0.0, -7.0];
/// The same for 2τ/(1 + τ²)² = Σ (−1)^k 2(k+1) τ^{2k+1}, the weight of F_s.
const FS_SERIES: [f64; 7] = [0.0, 2.0, 0.0, -4.0, 0.0, 6.0, 0.0];

/// ∫₀^{tan v} Σ_k c_k τ^k e^{−uτ} dτ for large u (the tail of an alternating series, bounded by
/// its first omitted term: ≤ 8·7!/u⁸ ≈ 4·10⁻⁷ at u = [`U_MAX`] for both series above).
fn series_asymptotic(u: f64, v: f64, coeffs: &[f64; 7]) -> f64 {
    let tau = v.clamp(0.0, FRAC_PI_2).tan();
    let w = u * tau;
    let e = if w < 700.0 { (-w).exp() } else { 0.0 };
    // ∫₀^τ t^k e^{−ut} dt = k!/u^{k+1}·(1 − e^{−w} Σ_{i≤k} wⁱ/i!).
    let (mut term, mut partial, mut fact, mut upow) = (1.0, 1.0, 1.0, u);
    let mut total = 0.0;
    for (k, &c) in coeffs.iter().enumerate() {
        if k > 0 {
            term *= w / k as f64;
            partial += term;
            fact *= k as f64;
            upow *= u;
        }
        if c != 0.0 {
            let tail = if e == 0.0 { 1.0 } else { 1.0 - e * partial };
            total += c * fact / upow * tail;
        }
    }
    total
}

#[inline(always)]
fn integrand(u: f64, xi: f64) -> f64 {
    if u == 0.0 {
        1.0
    } else {
        (-u * xi.tan()).exp()
    }
}

/// F for large u: [`series_asymptotic`] with 1/(1 + τ²) ≈ 1 − τ² + τ⁴ − τ⁶ (error below the
/// next term's integral, 8!/u⁹).
fn f_asymptotic(u: f64, v: f64) -> f64 {
    series_asymptotic(u, v, &F_SERIES)
}

/// F(u, v) by adaptive Gauss–Legendre quadrature to ~1e-13 absolute: the reference the table is
/// tested against. Same clamping as [`FTable::eval`].
pub fn f_quadrature(u: f64, v: f64) -> f64 {
    let (u, v) = (u.max(0.0), v.clamp(0.0, FRAC_PI_2));
    if u == 0.0 {
        return v;
    }
    quad::adaptive(&mut |xi| integrand(u, xi), 0.0, v, 1e-13)
}

/// [F_c(u, v), F_s(u, v)] by adaptive quadrature to ~1e-13 absolute: the reference the facet
/// companions are tested against. Same clamping as [`FTable::eval`].
pub fn facet_quadrature(u: f64, v: f64) -> [f64; 2] {
    let (u, v) = (u.max(0.0), v.clamp(0.0, FRAC_PI_2));
    [
        quad::adaptive(&mut |xi| integrand(u, xi) * (2.0 * xi).cos(), 0.0, v, 1e-13),
        quad::adaptive(&mut |xi| integrand(u, xi) * (2.0 * xi).sin(), 0.0, v, 1e-13),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The stated accuracy of [`FTable::global`]: absolute error of F.
    const TOL: f64 = 2e-5;

    #[test]
    fn table_matches_quadrature_over_a_grid_and_edges() {
        let t = FTable::global();
        let mut worst = (0.0f64, 0.0, 0.0);
        let us = [
            0.0, 1e-6, 1e-4, 3e-4, 1e-3, 3e-3, 0.01, 0.033, 0.1, 0.27, 0.5, 1.0, 1.7, 3.0, 7.3,
            15.0, 31.0, 63.9, 64.0, 64.1, 100.0, 1000.0,
        ];
        for &u in &us {
            for k in 0..=40 {
                // Dense near π/2 (the corner) and uniform elsewhere.
                let frac = k as f64 / 40.0;
                for v in [
                    FRAC_PI_2 * frac,
                    FRAC_PI_2 * (1.0 - 1e-3 * frac),
                    FRAC_PI_2 - 1e-6 * frac,
                ] {
                    let e = (t.eval(u, v) - f_quadrature(u, v)).abs();
                    if e > worst.0 {
                        worst = (e, u, v);
                    }
                }
            }
        }
        eprintln!(
            "F table worst abs error {:.2e} at u={} v={}",
            worst.0, worst.1, worst.2
        );
        assert!(worst.0 < TOL, "{worst:?}");
    }

    /// The facet companions meet F's accuracy over the same grid, including the corner and the
    /// asymptotic region; F_s has the closed form 1 − cos²v·e^{−u tan v} − u·F(u, v)
    /// (integration by parts), which checks the quadrature reference itself.
    #[test]
    fn facet_companions_match_quadrature_and_closed_form() {
        let t = FTable::global();
        let mut worst = (0.0f64, 0.0, 0.0);
        for &u in &[
            0.0, 1e-6, 1e-3, 0.01, 0.1, 0.5, 1.0, 3.0, 15.0, 23.9, 24.1, 40.0, 300.0,
        ] {
            for k in 0..=30 {
                let frac = k as f64 / 30.0;
                for v in [FRAC_PI_2 * frac, FRAC_PI_2 * (1.0 - 1e-3 * frac)] {
                    let q = facet_quadrature(u, v);
                    let closed =
                        1.0 - v.cos().powi(2) * (-u * v.tan()).exp() - u * f_quadrature(u, v);
                    assert!(
                        (q[1] - closed).abs() < 1e-9,
                        "F_s closed form at u={u} v={v}"
                    );
                    let got = t.eval_facet(u, v);
                    for c in 0..2 {
                        let e = (got[c] - q[c]).abs();
                        if e > worst.0 {
                            worst = (e, u, v);
                        }
                    }
                }
            }
        }
        eprintln!(
            "facet tables worst abs error {:.2e} at u={} v={}",
            worst.0, worst.1, worst.2
        );
        assert!(worst.0 < TOL, "{worst:?}");
    }

    #[test]
    fn known_values_and_clamping() {
        let t = FTable::global();
        // F(0, v) = v; F(u, π/2) = Ci(u)·sin u − (Si(u) − π/2)·cos u, at u = 1: 0.6214496.
        assert!((f_quadrature(0.0, 1.0) - 1.0).abs() < 1e-15);
        assert!((f_quadrature(1.0, FRAC_PI_2) - 0.621_449_624_235_813_3).abs() < 1e-9);
        assert!((t.eval(1.0, FRAC_PI_2) - 0.621_449_624_235_813_3).abs() < TOL);
        assert_eq!(t.eval(-1.0, 0.5), t.eval(0.0, 0.5));
        assert_eq!(t.eval(0.3, 2.0), t.eval(0.3, FRAC_PI_2));
        assert_eq!(t.eval(0.3, -1.0), 0.0);
        let d = t.eval_diff(0.7, 0.2, 1.1) - (t.eval(0.7, 1.1) - t.eval(0.7, 0.2));
        assert!(d.abs() < 1e-15);
        assert!(t.eval(f64::INFINITY, 1.0).is_finite());
    }
}
