//! How a surface facet radiates toward the medium in the surface-camera forward scatter.
//!
//! Eq. 4.41 treats the facet q as an *isotropic* point source of radiant intensity
//! L_s(q)·dA_q. A Lambertian facet is not isotropic: its radiance is the same in every
//! direction, so its radiant intensity toward a scattering point x is L_s(q)·dA_q·cos θ(x), θ
//! the angle between the facet normal and the direction q → x. Toward the camera cos θ = v_q·n_q,
//! which cancels the 1/(v_q·n_q) of the facet area (Eq. 4.44): a tilted facet sends the camera's
//! neighbourhood no more light than a fronto-parallel one, where the isotropic model lets it
//! grow without bound toward the silhouette. [`FacetEmission::Lambertian`] is murk's default;
//! [`FacetEmission::Isotropic`] keeps Eq. 4.41 as published.
//!
//! Closed form. In the parametrisation of [`super::h`] (the point x at angle t from the foot of
//! q's perpendicular on p's ray, h = D sin γ, ξ = π/4 + t/2) the vector q → x is
//! h·(tan t·r_p − u), u the unit vector from the foot to q, so
//! cos θ = a·sin t − b·cos t = −a·cos 2ξ − b·sin 2ξ with a = n_q·r_p and
//! b = n_q·u = (n_q·r_q − cos γ·a)/sin γ. The integral of Eq. 4.41 with the cosine becomes
//!
//! β L dA e^{−σ D cos γ}/(2π h) · ∫_{ξ₀}^{ξ₁} e^{−σ h tan ξ}(−a cos 2ξ − b sin 2ξ) dξ,
//!
//! the isotropic form with F replaced by −a·F_c − b·F_s ([`super::FTable::eval_facet_diff`]).
//! At the camera end (ξ₀ = γ/2) the weight is −n_q·r_q = v_q·n_q, and it reaches 0 exactly
//! where p's ray crosses q's tangent plane, which is where Eq. 4.43's d_vp′ already ends the
//! integral: the weight is ≥ 0 over the whole lit segment.

use std::f64::consts::FRAC_PI_2;
#[cfg(test)]
use std::f64::consts::PI;

#[cfg(test)]
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use super::f_table::FTable;
use super::h::{segment, segment_fast, Bracket, Segment, MIN_TABLE_BRACKET, SMALL_BRACKET};
use super::quad;
#[cfg(test)]
use super::Medium;

/// The accurate path reads the table unless the bracket is below this share of
/// [`MIN_TABLE_BRACKET`]·(|a| + |b|). The cosine weight vanishes where p's ray meets q's tangent
/// plane, which is where a near q's scatter concentrates, so near entries have brackets many
/// times smaller than the isotropic ones. The isotropic threshold (share 1) sent most of the
/// simulator's entries to adaptive quadrature; at 0.03 the simulator is 1.5× slower than with
/// isotropic facets instead of 3.8×, and the entries over a sphere stay within 4·10⁻⁴ of
/// quadrature (test `lambertian_entries_match_quadrature_over_a_sphere`): the tables' error is
/// far below its worst-case bound away from the (u → 0, v → π/2) corner.
const LAMBERTIAN_TABLE_SHARE: f64 = 0.03;

/// The radiant intensity of a surface facet toward a scattering point (module documentation).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FacetEmission {
    /// L_s·dA·cos θ: the physics of a Lambertian facet (murk's default).
    #[default]
    Lambertian,
    /// L_s·dA in every direction: Eq. 4.41 as published.
    Isotropic,
}

impl FacetEmission {
    /// Name used by the CLI, the API and the docs.
    pub fn name(self) -> &'static str {
        match self {
            FacetEmission::Lambertian => "lambertian",
            FacetEmission::Isotropic => "isotropic",
        }
    }
}

/// The weight coefficients (a, b) of cos θ = −a·cos 2ξ − b·sin 2ξ for facet normal `n_q`:
/// a = n_q·r_p, b = (n_q·r_q − cos γ·a)/sin γ (module documentation); `n_dot_rp` = n_q·r_p,
/// `n_dot_rq` = n_q·r_q.
#[inline(always)]
fn weights(n_dot_rp: f64, n_dot_rq: f64, cos_g: f64, sin_g: f64) -> (f64, f64) {
    (n_dot_rp, (n_dot_rq - cos_g * n_dot_rp) / sin_g)
}

/// ∫_{v1}^{v2} e^{−u tan ξ}(−a cos 2ξ − b sin 2ξ) dξ from the tables.
#[inline(always)]
fn bracket_table(table: &FTable, u: f64, v1: f64, v2: f64, a: f64, b: f64) -> f64 {
    let [fc, fs] = table.eval_facet_diff(u, v1, v2);
    -a * fc - b * fs
}

/// e^{−u tan ξ}(−a cos 2ξ − b sin 2ξ), with cos 2ξ = (1 − τ²)/(1 + τ²) and sin 2ξ = 2τ/(1 + τ²)
/// from τ = tan ξ (one `tan`, no `sin_cos`).
#[inline(always)]
fn weighted(u: f64, a: f64, b: f64, xi: f64) -> f64 {
    let tau = xi.min(FRAC_PI_2).tan();
    if !tau.is_finite() || tau > 1e150 {
        // ξ = π/2: cos 2ξ = −1, sin 2ξ = 0, and e^{−u·∞} = 0 unless u = 0.
        return if u == 0.0 { a } else { 0.0 };
    }
    let inv = 1.0 / (1.0 + tau * tau);
    (-u * tau).exp() * (-a * (1.0 - tau * tau) * inv - b * 2.0 * tau * inv)
}

/// The Lambertian facet's forward scatter collected along a viewing ray of length `len` (mm)
/// from a facet of area·radiance `intensity` at distance `d` (mm), γ its angle to the ray
/// (cosine and sine given), with n_q·r_p = `n_dot_rp` and n_q·r_q = `n_dot_rq`. Accurate path
/// (the simulator's dense sum and the public [`mod@super::kernel_entry`]): short or small brackets
/// are integrated adaptively, like [`super::h::bracket`]. Limits as for
/// [`super::point_source_scatter`].
#[allow(clippy::too_many_arguments)]
#[inline]
pub(crate) fn lambertian_scatter_cs(
    table: &FTable,
    beta: f64,
    sigma: f64,
    intensity: f64,
    d: f64,
    cos_g: f64,
    sin_g: f64,
    len: f64,
    n_dot_rp: f64,
    n_dot_rq: f64,
) -> f64 {
    let Bracket {
        pre,
        u,
        v1,
        v2,
        sin_g,
    } = match segment(beta, sigma, intensity, d, cos_g, sin_g, len) {
        Segment::Value(v) => return v,
        Segment::Bracket(b) => b,
    };
    let (a, b) = weights(n_dot_rp, n_dot_rq, cos_g, sin_g);
    let br = bracket_table(table, u, v1, v2, a, b);
    // The weight is at most |a| + |b| in size: judge the table's error against that, as
    // `h::bracket` does with weight 1 (see [`LAMBERTIAN_TABLE_SHARE`]).
    let br = if v2 - v1 >= SMALL_BRACKET
        && br * (1.0 + u) >= LAMBERTIAN_TABLE_SHARE * MIN_TABLE_BRACKET * (a.abs() + b.abs())
    {
        br
    } else {
        let (v1, v2) = (v1.clamp(0.0, FRAC_PI_2), v2.clamp(0.0, FRAC_PI_2));
        if v2 <= v1 {
            0.0
        } else {
            quad::adaptive_rel(&mut |xi| weighted(u, a, b, xi), v1, v2, 1e-9)
        }
    };
    // Rounding can leave a hair below 0 where the segment ends on the tangent plane.
    pre * br.max(0.0)
}

/// [`lambertian_scatter_cs`] for the kernel build's hot loop, with the same shortcuts as
/// [`super::h::scatter_cs_fast`]: `att` = e^{−σ d} times a Taylor polynomial for
/// e^{σ d (1 − cos γ)}, [`super::h::fast_atan`], and a 3-point Gauss–Legendre rule on brackets shorter
/// than [`SMALL_BRACKET`] (the table's ~2·10⁻⁵ absolute error is accepted on the others).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub(crate) fn lambertian_scatter_cs_fast(
    table: &FTable,
    beta: f64,
    sigma: f64,
    intensity: f64,
    d: f64,
    att: f64,
    cos_g: f64,
    sin_g: f64,
    len: f64,
    n_dot_rp: f64,
    n_dot_rq: f64,
) -> f64 {
    let Bracket {
        pre,
        u,
        v1,
        v2,
        sin_g,
    } = match segment_fast(beta, sigma, intensity, d, att, cos_g, sin_g, len) {
        Segment::Value(v) => return v,
        Segment::Bracket(b) => b,
    };
    let (a, b) = weights(n_dot_rp, n_dot_rq, cos_g, sin_g);
    let span = v2 - v1;
    let br = if span >= SMALL_BRACKET {
        bracket_table(table, u, v1, v2, a, b)
    } else if span <= 0.0 {
        0.0
    } else {
        const X: f64 = 0.774_596_669_241_483_4;
        let (hw, m) = (0.5 * span, 0.5 * (v1 + v2));
        hw * ((5.0 / 9.0) * (weighted(u, a, b, m - hw * X) + weighted(u, a, b, m + hw * X))
            + (8.0 / 9.0) * weighted(u, a, b, m))
    };
    pre * br.max(0.0)
}

/// Eq. 4.41 with the Lambertian cosine by brute force: ∫₀^len I cos θ/d² · β/(4π) · e^{−σ(x+d)}
/// dx along the unit ray `ray_p` for a facet at `q_mm` with unit normal `n_q`. The test
/// reference for [`lambertian_scatter_cs`].
#[cfg(test)]
pub(crate) fn lambertian_quadrature(
    medium: &Medium,
    intensity: f64,
    ray_p: Vector3<f64>,
    q_mm: Vector3<f64>,
    n_q: Vector3<f64>,
    len: f64,
) -> f64 {
    let (beta, sigma) = (medium.beta_per_mm, medium.sigma_per_mm);
    let k = intensity * beta / (4.0 * PI);
    let mut f = |x: f64| {
        let v = ray_p * x - q_mm;
        let d2 = v.norm_squared();
        let d = d2.sqrt();
        let cos = n_q.dot(&v) / d;
        k * cos.max(0.0) * (-sigma * (x + d)).exp() / d2
    };
    let dq = q_mm.norm();
    let cos_g = ray_p.dot(&q_mm) / dq;
    let h = dq * (1.0 - cos_g * cos_g).max(0.0).sqrt();
    let x0 = (dq * cos_g).max(0.0);
    let scale = k * (-sigma * (x0 + h)).exp() * PI / h.max(1e-3 * dq);
    let tol = 1e-11 * scale;
    let mut breaks = vec![0.0];
    for b in [x0 - 4.0 * h, x0 - h, x0, x0 + h, x0 + 4.0 * h] {
        if b > *breaks.last().unwrap() && b < len {
            breaks.push(b);
        }
    }
    breaks.push(len);
    breaks
        .windows(2)
        .map(|w| quad::adaptive(&mut f, w[0], w[1], tol))
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn norm(v: [f64; 3]) -> [f64; 3] {
        let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        [v[0] / l, v[1] / l, v[2] / l]
    }

    fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
        a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    }

    /// Both paths agree with brute-force quadrature of the cosine-weighted Eq. 4.41, for facets
    /// facing the camera, tilted toward and away from the ray, near and far from it, with the
    /// segment ending on the tangent plane and beyond it.
    #[test]
    fn closed_form_matches_quadrature() {
        let ft = FTable::global();
        let m = Medium {
            beta_per_mm: 5e-3,
            sigma_per_mm: 6e-3,
        };
        let mut worst = 0.0f64;
        for &(ray, q, n) in &[
            ([0.0, 0.0, 1.0], [3.0, 0.0, 300.0], [0.0, 0.0, -1.0]),
            ([0.01, 0.0, 1.0], [-2.0, 1.0, 280.0], [0.3, 0.1, -1.0]),
            ([0.1, 0.05, 1.0], [-20.0, 10.0, 250.0], [-0.5, 0.2, -0.8]),
            ([0.0, 0.2, 1.0], [0.0, -30.0, 320.0], [0.0, 0.7, -0.7]),
            ([0.05, 0.0, 1.0], [40.0, 0.0, 200.0], [0.9, 0.0, -0.3]),
            ([0.0, 0.0, 1.0], [0.5, 0.0, 300.0], [0.0, -0.95, -0.3]),
        ] {
            let (ray, n) = (norm(ray), norm(n));
            let dq = dot(q, q).sqrt();
            let rq = [q[0] / dq, q[1] / dq, q[2] / dq];
            let (cos_g, sin_g) = {
                let c = dot(ray, rq);
                (c, (1.0 - c * c).max(0.0).sqrt())
            };
            // The lit segment: up to the tangent plane, at most the facet's depth + 20 mm.
            let t = dot(n, q) / dot(n, ray);
            let end = dq + 20.0;
            for len in [end, if t > 0.0 { t.min(end) } else { end }, 0.5 * dq] {
                let want = lambertian_quadrature(&m, 2.0, ray.into(), q.into(), n.into(), len);
                let acc = lambertian_scatter_cs(
                    ft,
                    m.beta_per_mm,
                    m.sigma_per_mm,
                    2.0,
                    dq,
                    cos_g,
                    sin_g,
                    len,
                    dot(n, ray),
                    dot(n, rq),
                );
                let fast = lambertian_scatter_cs_fast(
                    ft,
                    m.beta_per_mm,
                    m.sigma_per_mm,
                    2.0,
                    dq,
                    (-m.sigma_per_mm * dq).exp(),
                    cos_g,
                    sin_g,
                    len,
                    dot(n, ray),
                    dot(n, rq),
                );
                // Segments running past the tangent plane include a stretch the facet does
                // not light; the closed form is only claimed up to the crossing.
                if t > 0.0 && len > t + 1e-9 {
                    continue;
                }
                let rel = (acc - want).abs() / want;
                let rel_fast = (fast - want).abs() / want;
                eprintln!("len {len:.1}: {want:.4e} accurate {rel:.1e} fast {rel_fast:.1e}");
                assert!(rel < 1e-3, "accurate {acc} vs {want}");
                assert!(rel_fast < 2e-3, "fast {fast} vs {want}");
                worst = worst.max(rel);
            }
        }
        eprintln!("worst relative error {worst:.2e}");
    }

    /// Toward the camera a Lambertian facet of area dA sends L·dA·(v·n): against the isotropic
    /// facet its scatter is smaller by about v·n (exactly so for a short segment near the
    /// camera, where θ barely changes), so a facet seen at 60° scatters half as much.
    #[test]
    fn tilted_facet_scatters_less_than_the_isotropic_one() {
        let ft = FTable::global();
        let (beta, sigma) = (5e-3, 5e-3);
        let q = [2.0, 0.0, 300.0];
        let dq = dot(q, q).sqrt();
        let rq = [q[0] / dq, q[1] / dq, q[2] / dq];
        let ray = [0.0, 0.0, 1.0];
        let cos_g = dot(ray, rq);
        let sin_g = (1.0 - cos_g * cos_g).sqrt();
        let n = norm([
            0.0,
            -(60f64.to_radians().sin()),
            -(60f64.to_radians().cos()),
        ]);
        let len = 20.0;
        let iso = super::super::h::scatter_cs(ft, beta, sigma, 1.0, dq, cos_g, sin_g, len);
        let lam = lambertian_scatter_cs(
            ft,
            beta,
            sigma,
            1.0,
            dq,
            cos_g,
            sin_g,
            len,
            dot(n, ray),
            dot(n, rq),
        );
        let vn = -dot(n, rq);
        assert!((lam / iso - vn).abs() < 0.01, "{} vs v·n {vn}", lam / iso);
    }
}
