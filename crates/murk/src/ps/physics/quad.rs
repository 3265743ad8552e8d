//! Gauss–Legendre rules and an adaptive integrator shared by the table builders and the
//! brute-force references in the tests. Kept private to the physics module: they are means,
//! not model quantities.

use std::sync::OnceLock;

/// Nodes and weights of the `n`-point Gauss–Legendre rule on [−1, 1] (Newton on P_n, which
/// converges to machine precision from the Chebyshev-like initial guess for every n used here).
pub(crate) fn gauss_legendre(n: usize) -> (Vec<f64>, Vec<f64>) {
    let mut x = vec![0.0; n];
    let mut w = vec![0.0; n];
    for i in 0..n.div_ceil(2) {
        let mut z = (std::f64::consts::PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
        let mut dp = 1.0;
        for _ in 0..100 {
            let (mut p0, mut p1) = (1.0, z);
            for k in 2..=n {
                let p2 = ((2 * k - 1) as f64 * z * p1 - (k - 1) as f64 * p0) / k as f64;
                p0 = p1;
                p1 = p2;
            }
            let p = if n == 1 { z } else { p1 };
            let pm1 = if n == 1 { 1.0 } else { p0 };
            dp = n as f64 * (z * p - pm1) / (z * z - 1.0);
            let dz = p / dp;
            z -= dz;
            if dz.abs() < 1e-15 {
                break;
            }
        }
        x[i] = -z;
        x[n - 1 - i] = z;
        let wi = 2.0 / ((1.0 - z * z) * dp * dp);
        w[i] = wi;
        w[n - 1 - i] = wi;
    }
    (x, w)
}

/// A rule mapped onto [a, b] and applied to `f`.
pub(crate) fn gl_apply(
    rule: &(Vec<f64>, Vec<f64>),
    a: f64,
    b: f64,
    f: &mut impl FnMut(f64) -> f64,
) -> f64 {
    let (h, m) = (0.5 * (b - a), 0.5 * (b + a));
    let mut s = 0.0;
    for (x, w) in rule.0.iter().zip(&rule.1) {
        s += w * f(m + h * x);
    }
    s * h
}

fn rule12() -> &'static (Vec<f64>, Vec<f64>) {
    static R: OnceLock<(Vec<f64>, Vec<f64>)> = OnceLock::new();
    R.get_or_init(|| gauss_legendre(12))
}

/// Adaptive 12-point Gauss–Legendre on [a, b]: a panel is accepted when it agrees with the sum
/// of its two halves to `tol` (absolute, scaled down with depth so the total error stays near
/// `tol`). Used only for references and rare cold paths, so simplicity beats speed.
pub(crate) fn adaptive(f: &mut impl FnMut(f64) -> f64, a: f64, b: f64, tol: f64) -> f64 {
    let r = rule12();
    let whole = gl_apply(r, a, b, f);
    adaptive_rec(f, r, a, b, whole, tol, 0)
}

/// [`adaptive`] with a tolerance relative to the first whole-interval estimate; cheaper where
/// only relative accuracy matters (tiny integrals would otherwise recurse to an absolute floor).
pub(crate) fn adaptive_rel(f: &mut impl FnMut(f64) -> f64, a: f64, b: f64, rel: f64) -> f64 {
    let r = rule12();
    let whole = gl_apply(r, a, b, f);
    adaptive_rec(f, r, a, b, whole, rel * whole.abs(), 0)
}

fn adaptive_rec(
    f: &mut impl FnMut(f64) -> f64,
    r: &(Vec<f64>, Vec<f64>),
    a: f64,
    b: f64,
    whole: f64,
    tol: f64,
    depth: u32,
) -> f64 {
    let m = 0.5 * (a + b);
    let left = gl_apply(r, a, m, f);
    let right = gl_apply(r, m, b, f);
    let both = left + right;
    if (both - whole).abs() <= tol || depth >= 40 || m <= a || m >= b {
        return both;
    }
    adaptive_rec(f, r, a, m, left, 0.5 * tol, depth + 1)
        + adaptive_rec(f, r, m, b, right, 0.5 * tol, depth + 1)
}

/// ∫_a^∞ f by the map x = a + s·t/(1 − t), t ∈ [0, 1), whose scale `s` should be near where
/// the integrand has its mass so the adaptive panels land there.
pub(crate) fn adaptive_to_infinity(
    f: &mut impl FnMut(f64) -> f64,
    a: f64,
    s: f64,
    tol: f64,
) -> f64 {
    let mut g = |t: f64| {
        if t >= 1.0 {
            return 0.0;
        }
        let om = 1.0 - t;
        let v = f(a + s * t / om);
        if v == 0.0 {
            0.0
        } else {
            v * s / (om * om)
        }
    };
    adaptive(&mut g, 0.0, 1.0, tol)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gauss_legendre_integrates_polynomials_exactly() {
        let r = gauss_legendre(7);
        // Degree 13 is the highest a 7-point rule integrates exactly.
        let v = gl_apply(&r, 0.0, 2.0, &mut |x| x.powi(13));
        assert!((v - 2f64.powi(14) / 14.0).abs() < 1e-9 * v);
        let sw: f64 = r.1.iter().sum();
        assert!((sw - 2.0).abs() < 1e-14);
    }

    #[test]
    fn adaptive_handles_peaks_and_infinite_ranges() {
        let v = adaptive(&mut |x: f64| 1e-3 / (x * x + 1e-6), -1.0, 1.0, 1e-12);
        let exact = 2.0 * (1e3f64).atan();
        assert!((v - exact).abs() < 1e-9, "{v} vs {exact}");
        let v = adaptive_to_infinity(&mut |x: f64| (-x).exp(), 0.0, 1.0, 1e-13);
        assert!((v - 1.0).abs() < 1e-11);
    }
}
