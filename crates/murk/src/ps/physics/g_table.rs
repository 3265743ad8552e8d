//! Sun et al.'s table G(T, c) of Eq. 4.40 behind the source-surface forward scatter of Eq. 4.39,
//! with T = σ·d_sp and c = n·l.
//!
//! Evaluation of Eq. 4.40. In spherical coordinates (γ′, φ) about the source direction l the
//! solid angle dω = sin γ′ dγ′ dφ cancels the 1/sin γ′, and n·ω = a + b·cos φ with
//! a = c·cos γ′, b = √(1 − c²)·sin γ′. The hemisphere restriction is max(0, n·ω), whose azimuthal
//! integral A(a, b) = ∫₀^{2π} max(0, a + b cos φ) dφ is 2πa for a ≥ |b|, 0 for a ≤ −|b| and
//! 2(a·acos(−a/|b|) + √(b² − a²)) otherwise. What is left is
//!
//! G(T, c) = ∫₀^π e^{−T cos γ′} [F(T sin γ′, π/2) − F(T sin γ′, γ′/2)] A(c cos γ′, √(1−c²) sin γ′) dγ′,
//!
//! integrated by Gauss–Legendre over γ′ (see [`GTable::new`]; the reference evaluation used by
//! the tests breaks the range where A changes form, γ′ = |π/2 − θ| and θ + π/2, θ = acos c).
//!
//! Table: ln G (G > 0 for every c > −1 and at c = −1 too, scattered light arrives from all
//! around) on a grid uniform in √(T/T_MAX) (G has T·ln T terms at T → 0 from F's corner) and in
//! c, bilinear. Beyond [`T_MAX`] ln G is extrapolated linearly in T from the last grid cell;
//! asymptotically G ∝ e^{−T}/T, so this is an approximation whose error grows slowly with
//! T − T_MAX (at T = 2·T_MAX the light reaching the surface is attenuated by e^{−40}).
//!
//! Accuracy (tests): against a brute-force hemisphere integral of Eq. 4.37–4.38 (no F) the
//! relative error is ≤ 1.9·10⁻⁴ (bound 3·10⁻³); against the untabulated 1D integral at
//! off-grid (T, c) ≤ 2.8·10⁻⁴ (bound 2·10⁻³).
//!
//! Eq. 4.55, G(T, c) ≈ G(T, 1)·c, underestimates G by the relative gap (G − G(T,1)c)/G of
//! 2.2 %, 6.4 %, 18 %, 42 % at c = 0.9, 0.75, 0.5, 0.25 for T = 0.6 and 1.6 %, 4.8 %, 14 %, 36 %
//! for T = 2: growing with the angle, as in Fig. 4.10.

use std::f64::consts::{FRAC_PI_2, PI};
use std::sync::OnceLock;

use rayon::prelude::*;

use super::f_table::FTable;
use super::h::bracket;
use super::quad;
use super::Medium;

/// Largest optical thickness σ·d_sp held in the table.
pub const T_MAX: f64 = 20.0;
const DEFAULT_NT: usize = 161;
const DEFAULT_NC: usize = 257;
#[cfg(test)]
const NODES_PER_PIECE: usize = 48;

/// Tabulated G(T, c) of Eq. 4.40 (see the module documentation for grid and range).
#[derive(Clone, Debug)]
pub struct GTable {
    nt: usize,
    nc: usize,
    /// Row-major over T: `ln_g[i·nc + j] = ln G(T_i, c_j)`.
    ln_g: Vec<f64>,
}

/// ∫₀^{2π} max(0, a + b cos φ) dφ for b ≥ 0.
pub(crate) fn azimuthal(a: f64, b: f64) -> f64 {
    if a >= b {
        2.0 * PI * a
    } else if a <= -b {
        0.0
    } else {
        2.0 * (a * (-a / b).clamp(-1.0, 1.0).acos() + (b * b - a * a).max(0.0).sqrt())
    }
}

/// G(T, c) by direct 1D quadrature with breaks at the kinks of the azimuthal factor (no table
/// for G; F from `ft` with the small-bracket fallback): the tests' reference for the table.
#[cfg(test)]
pub(crate) fn g_direct(ft: &FTable, rule: &(Vec<f64>, Vec<f64>), t: f64, c: f64) -> f64 {
    let c = c.clamp(-1.0, 1.0);
    let theta = c.acos();
    let s = (1.0 - c * c).max(0.0).sqrt();
    let mut breaks = vec![0.0, PI];
    for b in [FRAC_PI_2 - theta, theta - FRAC_PI_2, theta + FRAC_PI_2] {
        if b > 1e-12 && b < PI - 1e-12 {
            breaks.push(b);
        }
    }
    breaks.sort_by(f64::total_cmp);
    let mut f = |g: f64| {
        let (sg, cg) = g.sin_cos();
        let az = azimuthal(c * cg, s * sg);
        if az == 0.0 {
            return 0.0;
        }
        (-t * cg).exp() * bracket(ft, t * sg, 0.5 * g, FRAC_PI_2) * az
    };
    breaks
        .windows(2)
        .map(|w| quad::gl_apply(rule, w[0], w[1], &mut f))
        .sum()
}

fn t_at(i: usize, nt: usize) -> f64 {
    let s = i as f64 / (nt - 1) as f64;
    T_MAX * s * s
}

fn c_at(j: usize, nc: usize) -> f64 {
    -1.0 + 2.0 * j as f64 / (nc - 1) as f64
}

impl GTable {
    /// Builds an `nt × nc` table (each ≥ 2) in parallel over T. Per T the bracket of Eq. 4.40,
    /// which does not depend on c, is evaluated once on fixed Gauss–Legendre nodes over γ′
    /// (96 panels × 8 nodes); the kinks of the azimuthal factor then fall inside panels, which
    /// costs ~10⁻⁴ relative accuracy (measured in the tests) but makes the build cheap.
    pub fn new(ft: &FTable, nt: usize, nc: usize) -> GTable {
        let (nt, nc) = (nt.max(2), nc.max(2));
        let rule = quad::gauss_legendre(8);
        let panels = 96;
        let hw = 0.5 * PI / panels as f64;
        let mut nodes = Vec::with_capacity(panels * rule.0.len());
        for k in 0..panels {
            let mid = (2 * k + 1) as f64 * hw;
            for (x, w) in rule.0.iter().zip(&rule.1) {
                let g: f64 = mid + hw * x;
                let (sg, cg) = g.sin_cos();
                nodes.push((sg, cg, w * hw));
            }
        }
        let mut ln_g = vec![0.0; nt * nc];
        ln_g.par_chunks_mut(nc).enumerate().for_each(|(i, row)| {
            let t = t_at(i, nt);
            // e^{−T cos γ′}·bracket·weight per node.
            let eb: Vec<f64> = nodes
                .iter()
                .map(|&(sg, cg, w)| {
                    let g = sg.atan2(cg);
                    w * (-t * cg).exp() * bracket(ft, t * sg, 0.5 * g, FRAC_PI_2)
                })
                .collect();
            for (j, slot) in row.iter_mut().enumerate() {
                let c = c_at(j, nc);
                let s = (1.0 - c * c).max(0.0).sqrt();
                let g: f64 = nodes
                    .iter()
                    .zip(&eb)
                    .map(|(&(sg, cg, _), &e)| e * azimuthal(c * cg, s * sg))
                    .sum();
                *slot = g.ln();
            }
        });
        GTable { nt, nc, ln_g }
    }

    /// The process-wide table (161 × 257 over T ∈ [0, 20], c ∈ [−1, 1]) built on first use from
    /// [`FTable::global`].
    pub fn global() -> &'static GTable {
        static G: OnceLock<GTable> = OnceLock::new();
        G.get_or_init(|| GTable::new(FTable::global(), DEFAULT_NT, DEFAULT_NC))
    }

    /// G(T, c): T < 0 reads as 0, c is clamped to [−1, 1], T > [`T_MAX`] is extrapolated (see
    /// the module documentation).
    pub fn eval(&self, t: f64, c: f64) -> f64 {
        self.eval_with_slope(t, c).0
    }

    /// G(T, c) as [`GTable::eval`] and ∂G/∂c from the same lookup, for Gauss–Newton on the
    /// normal: ln G is bilinear in (√T, c), so ∂G/∂c = G·∂ln G/∂c with the cell's slope in c, which
    /// a central difference of ±10⁻³ inside one 2/256-wide cell reproduces at three times the
    /// cost. At c = ±1 the slope is the end cell's (one-sided), not 0.
    pub fn eval_with_slope(&self, t: f64, c: f64) -> (f64, f64) {
        let t = t.max(0.0);
        let per_c = 0.5 * (self.nc - 1) as f64;
        let sc = ((c.clamp(-1.0, 1.0) + 1.0) * 0.5) * (self.nc - 1) as f64;
        let j = (sc as usize).min(self.nc - 2);
        let fc = sc - j as f64;
        // ln G along c in row i at c, and its step across the cell.
        let row = |i: usize| {
            let r = i * self.nc + j;
            let step = self.ln_g[r + 1] - self.ln_g[r];
            (self.ln_g[r] + fc * step, step)
        };
        let last = self.nt - 1;
        let (ln_g, slope) = if t >= T_MAX {
            let (t0, t1) = (t_at(last - 1, self.nt), T_MAX);
            let ((g0, s0), (g1, s1)) = (row(last - 1), row(last));
            let k = (t - t1) / (t1 - t0);
            (g1 + (g1 - g0) / (t1 - t0) * (t - t1), s1 + (s1 - s0) * k)
        } else {
            let st = (t / T_MAX).sqrt() * last as f64;
            let i = (st as usize).min(last - 1);
            let ft = st - i as f64;
            let ((g0, s0), (g1, s1)) = (row(i), row(i + 1));
            (g0 + ft * (g1 - g0), s0 + ft * (s1 - s0))
        };
        let g = ln_g.exp();
        (g, g * slope * per_c)
    }
}

/// Source-surface forward scatter per unit albedo, Eq. 4.39: βσI₀/(2π T_sp)·G(T_sp, n·l) with
/// T_sp = σ·d_sp, evaluated as β I₀/(2π d_sp)·G so that σ = 0 works. `cos_nl` = n·l, l the unit
/// direction from the surface point to the source.
pub fn source_surface_forward(
    table_g: &GTable,
    medium: &Medium,
    intensity: f64,
    d_sp_mm: f64,
    cos_nl: f64,
) -> f64 {
    if medium.beta_per_mm == 0.0 || intensity == 0.0 {
        return 0.0;
    }
    medium.beta_per_mm * intensity / (2.0 * PI * d_sp_mm)
        * table_g.eval(medium.sigma_per_mm * d_sp_mm, cos_nl)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ps::physics::h::scatter_quadrature_cs;

    #[test]
    fn azimuthal_closed_form_matches_quadrature() {
        let rule = quad::gauss_legendre(64);
        for &(a, b) in &[
            (0.5f64, 0.2f64),
            (-0.5, 0.2),
            (0.1, 0.7),
            (-0.3, 0.4),
            (0.0, 1.0),
        ] {
            let phi_star = if a.abs() < b { (-a / b).acos() } else { PI };
            // Split at the kink so the brute force converges.
            let f = &mut |p: f64| (a + b * p.cos()).max(0.0);
            let num = 2.0
                * (quad::gl_apply(&rule, 0.0, phi_star, f)
                    + quad::gl_apply(&rule, phi_star, PI, f));
            assert!((num - azimuthal(a, b)).abs() < 1e-10, "{a} {b}: {num}");
        }
    }

    /// Eq. 4.37–4.38 integrated directly over the hemisphere (per unit albedo), without F: the
    /// inner ray integral is brute-force quadrature of Eq. 4.38 and the azimuth is integrated
    /// numerically.
    fn source_surface_brute(m: &Medium, d: f64, c: f64) -> f64 {
        let rule = quad::gauss_legendre(40);
        let theta = c.acos();
        let s = (1.0 - c * c).sqrt();
        let mut breaks = vec![0.0, PI];
        for b in [FRAC_PI_2 - theta, theta - FRAC_PI_2, theta + FRAC_PI_2] {
            if b > 1e-9 && b < PI - 1e-9 {
                breaks.push(b);
            }
        }
        breaks.sort_by(f64::total_cmp);
        let mut outer = |g: f64| {
            let (sg, cg) = g.sin_cos();
            let (a, b) = (c * cg, s * sg);
            if a <= -b {
                return 0.0;
            }
            let lb = scatter_quadrature_cs(m, 1.0, d, cg, sg, f64::INFINITY);
            let phi_star = if a.abs() < b { (-a / b).acos() } else { PI };
            let f = &mut |p: f64| (a + b * p.cos()).max(0.0);
            let az = 2.0
                * (quad::gl_apply(&rule, 0.0, phi_star, f)
                    + quad::gl_apply(&rule, phi_star, PI, f));
            lb * az * sg
        };
        breaks
            .windows(2)
            .map(|w| quad::gl_apply(&rule, w[0], w[1], &mut outer))
            .sum()
    }

    #[test]
    fn table_matches_brute_force_hemisphere_integral() {
        let g = GTable::global();
        let m = Medium {
            beta_per_mm: 0.008,
            sigma_per_mm: 0.01,
        };
        let mut worst = 0.0f64;
        for &tsp in &[0.05, 0.6, 2.0, 7.0] {
            for &c in &[1.0, 0.8, 0.3, 0.0, -0.5] {
                let d = tsp / m.sigma_per_mm;
                let got = source_surface_forward(g, &m, 1.0, d, c);
                let want = source_surface_brute(&m, d, c);
                let rel = (got - want).abs() / want;
                worst = worst.max(rel);
                assert!(rel < 3e-3, "T={tsp} c={c}: {got} vs {want}");
            }
        }
        eprintln!("G table vs brute force worst relative error {worst:.2e}");
    }

    #[test]
    fn table_matches_direct_evaluation_off_grid() {
        let ft = FTable::global();
        let g = GTable::global();
        let rule = quad::gauss_legendre(NODES_PER_PIECE);
        let mut worst = (0.0f64, 0.0, 0.0);
        for k in 0..23 {
            let t = 19.7 * (k as f64 / 22.0).powi(2) + 0.013;
            for l in 0..37 {
                let c = -0.993 + 1.99 * l as f64 / 36.0;
                let want = g_direct(ft, &rule, t, c);
                let rel = (g.eval(t, c) - want).abs() / want;
                if rel > worst.0 {
                    worst = (rel, t, c);
                }
            }
        }
        eprintln!(
            "G table interpolation worst relative error {:.2e} at T={} c={}",
            worst.0, worst.1, worst.2
        );
        assert!(worst.0 < 2e-3, "{worst:?}");
        // Beyond T_MAX: continuous at the edge, decaying.
        let edge = g.eval(T_MAX, 0.5);
        assert!((g.eval(T_MAX + 1e-9, 0.5) - edge).abs() < 1e-7 * edge);
        assert!(g.eval(25.0, 0.5) < edge);
    }

    #[test]
    fn slope_matches_the_difference_quotient_inside_a_cell() {
        let g = GTable::global();
        for &t in &[0.0, 0.3, 1.7, 6.0, 19.9, 24.0] {
            for &c in &[-1.0, -0.61, -0.2, 0.013, 0.4, 0.77, 0.999, 1.0] {
                let (v, slope) = g.eval_with_slope(t, c);
                assert!(v > 0.0 && v.is_finite(), "T {t}, c {c}: {v}");
                // A difference inside c's cell (the grid step is 2/256).
                let sc = (c + 1.0) * 0.5 * 256.0;
                let j = (sc.floor() as i64).clamp(0, 255) as f64;
                let (lo, hi) = (j / 128.0 - 1.0, (j + 1.0) / 128.0 - 1.0);
                let (a, b) = (lo + 0.25 * (hi - lo), lo + 0.75 * (hi - lo));
                let fd = (g.eval(t, b) - g.eval(t, a)) / (b - a);
                // Inside a cell ln G is linear in c, so G's difference quotient is the slope
                // at a point between a and b: compare with the slope there.
                let mid = g.eval_with_slope(t, 0.5 * (a + b)).1;
                assert!(
                    (fd - mid).abs() <= 2e-3 * mid.abs().max(1e-12) + 1e-15,
                    "T {t}, c {c}: difference {fd} against slope {mid}"
                );
                assert!(slope.is_finite());
            }
        }
    }

    #[test]
    fn linear_in_cos_approximation_of_eq_4_55() {
        let g = GTable::global();
        for &t in &[0.6, 2.0] {
            let g1 = g.eval(t, 1.0);
            let mut prev_gap = -1.0;
            let mut line = String::new();
            for &c in &[1.0, 0.9, 0.75, 0.5, 0.25] {
                let gap = (g.eval(t, c) - g1 * c) / g.eval(t, c);
                line.push_str(&format!(" c={c}: {gap:+.3}"));
                // The gap grows as the angle grows (Fig. 4.10).
                assert!(gap >= prev_gap - 1e-9, "T={t} c={c}: {gap}");
                prev_gap = gap;
            }
            eprintln!("Eq. 4.55 relative gap (G − G(T,1)·c)/G at T={t}:{line}");
            assert!((g.eval(t, 0.9) - g1 * 0.9).abs() / g.eval(t, 0.9) < 0.05);
        }
    }
}
