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
//! 1/(1 + τ²) ≈ 1 − τ² + τ⁴ in F = ∫₀^{tan v} e^{−uτ}/(1 + τ²) dτ, whose error is below
//! 720/u⁷ ≤ 1.6·10⁻⁷ there. Arguments are clamped: u < 0 reads as 0, v outside [0, π/2] as the
//! nearest end.

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
        }
    }

    /// The process-wide table (2048 × 1024, 8 MiB), built on first use (~0.1 s).
    pub fn global() -> &'static FTable {
        static T: OnceLock<FTable> = OnceLock::new();
        T.get_or_init(|| FTable::new(DEFAULT_NU, DEFAULT_NV))
    }

    /// Memory held by the table, bytes.
    pub fn bytes(&self) -> usize {
        self.values.len() * std::mem::size_of::<f32>()
    }

    /// Fractional u index, clamped to the table.
    #[inline(always)]
    fn u_index(&self, u: f64) -> (usize, f64) {
        let su = (u.max(0.0).sqrt() * self.su_scale).min((self.nu - 1) as f64);
        let i = (su as usize).min(self.nu - 2);
        (i, su - i as f64)
    }

    /// Fractional v index, clamped to the table.
    #[inline(always)]
    fn v_index(&self, v: f64) -> (usize, f64) {
        let w = (1.0 - v * (1.0 / FRAC_PI_2)).clamp(0.0, 1.0);
        let sv = (1.0 - w.sqrt()) * self.sv_scale;
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
}

#[inline(always)]
fn integrand(u: f64, xi: f64) -> f64 {
    if u == 0.0 {
        1.0
    } else {
        (-u * xi.tan()).exp()
    }
}

/// F for large u from 1/(1 + τ²) ≈ 1 − τ² + τ⁴ (error ≤ ∫τ⁶e^{−uτ} ≤ 720/u⁷).
fn f_asymptotic(u: f64, v: f64) -> f64 {
    let tau = v.clamp(0.0, FRAC_PI_2).tan();
    let w = u * tau;
    // ∫₀^τ t^k e^{−ut} dt = k!/u^{k+1}·(1 − e^{−w} Σ_{i≤k} wⁱ/i!); for huge w the partial sum
    // overflows while e^{−w} is 0, and their product is 0.
    let (mut term, mut sum) = (1.0, 1.0);
    let mut tails = [0.0; 3];
    let e = if w < 700.0 { (-w).exp() } else { 0.0 };
    for (k, tail) in tails.iter_mut().enumerate() {
        if k > 0 {
            for i in (2 * k - 1)..=(2 * k) {
                term *= w / i as f64;
                sum += term;
            }
        }
        *tail = if e == 0.0 { 1.0 } else { 1.0 - e * sum };
    }
    let u2 = u * u;
    tails[0] / u - 2.0 / (u2 * u) * tails[1] + 24.0 / (u2 * u2 * u) * tails[2]
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
