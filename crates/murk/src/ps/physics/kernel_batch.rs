//! The kernel build's entries K_pq ([`super::forward_kernel`]) for one p and a run of
//! neighbours q, several at a time.
//!
//! Why: at 300×300 with r = 81 the build evaluates ~4·10⁷ entries (docs/benchmarks.md), each a
//! scalar chain of four square roots, six or seven divisions and two arctangents. Here the
//! geometry of Eq. 4.42–4.43 and the bracket ends of Eq. 4.33, everything up to the table
//! lookups, run in a branch-free loop over structure-of-arrays pixel data ([`PreLanes`]), which
//! the compiler turns into 4-wide arithmetic where the CPU has AVX2; the table lookups stay
//! scalar.
//!
//! Every entry is bit for bit [`k_entry_fast`]'s: the same operations in the same order (no
//! FMA), with each branch replaced by computing its common side and flagging the lanes that
//! need the other. Flagged lanes are an outright value (empty ray, zero facet), e^{x} beyond the
//! Taylor range, γ ≥ 90° (atan2), a bracket shorter than [`SMALL_BRACKET`] (quadrature), or u
//! beyond the table; [`k_entry_fast`] recomputes them one by one.

use std::f64::consts::{FRAC_PI_4, PI};

use nalgebra::Vector3;

use super::f_table::U_MAX;
use super::facet_emission::FacetEmission;
use super::h::{fast_atan, SIN_GAMMA_MIN, SMALL_BRACKET};
use super::kernel_entry::{k_entry_fast, Physics, Pre};

/// Entries computed per pass of the branch-free loop (its outputs live on the stack).
const CHUNK: usize = 32;

/// [`Pre`] for many pixels as one array per field, so that consecutive q's are consecutive
/// lanes.
#[derive(Clone, Debug, Default)]
pub(super) struct PreLanes {
    ray: [Vec<f64>; 3],
    d: Vec<f64>,
    n: [Vec<f64>; 3],
    nq: Vec<f64>,
    da: Vec<f64>,
    att: Vec<f64>,
}

impl PreLanes {
    /// The lanes of `pres`, in order.
    pub(super) fn new(pres: &[Pre]) -> PreLanes {
        let field = |f: &dyn Fn(&Pre) -> f64| pres.iter().map(f).collect::<Vec<f64>>();
        PreLanes {
            ray: [
                field(&|p| p.ray[0]),
                field(&|p| p.ray[1]),
                field(&|p| p.ray[2]),
            ],
            d: field(&|p| p.d),
            n: [field(&|p| p.n[0]), field(&|p| p.n[1]), field(&|p| p.n[2])],
            nq: field(&|p| p.nq),
            da: field(&|p| p.da),
            att: field(&|p| p.att),
        }
    }

    /// Pixel `i` as a [`Pre`] again.
    fn get(&self, i: usize) -> Pre {
        Pre {
            ray: Vector3::new(self.ray[0][i], self.ray[1][i], self.ray[2][i]),
            d: self.d[i],
            n: Vector3::new(self.n[0][i], self.n[1][i], self.n[2][i]),
            nq: self.nq[i],
            da: self.da[i],
            att: self.att[i],
        }
    }
}

/// What the branch-free pass leaves for the lookups, per lane.
struct Ends {
    /// Eq. 4.33's prefactor β·dA·e^{−σ d cos γ}/(2π h).
    pre: [f64; CHUNK],
    /// Table coordinates of u = σh and of the bracket's ends v1, v2.
    su: [f64; CHUNK],
    sv1: [f64; CHUNK],
    sv2: [f64; CHUNK],
    /// The Lambertian facet's weights (a, b) (`facet_emission`); unused for the isotropic one.
    a: [f64; CHUNK],
    b: [f64; CHUNK],
    /// The lane needs [`k_entry_fast`]'s other branches.
    scalar: [bool; CHUNK],
}

impl Ends {
    fn new() -> Ends {
        Ends {
            pre: [0.0; CHUNK],
            su: [0.0; CHUNK],
            sv1: [0.0; CHUNK],
            sv2: [0.0; CHUNK],
            a: [0.0; CHUNK],
            b: [0.0; CHUNK],
            scalar: [false; CHUNK],
        }
    }
}

/// K_pq, as [`k_entry_fast`] computes it bit for bit, for p = `p` and q = pixels
/// `start..start + out.len()` of `qs`, into `out`.
pub(super) fn k_entries_fast(ph: &Physics, p: &Pre, qs: &PreLanes, start: usize, out: &mut [f64]) {
    if ph.beta == 0.0 {
        // No scattering: every entry is outright 0 (`h::outright`).
        out.fill(0.0);
        return;
    }
    let mut ends = Ends::new();
    for (c, chunk) in out.chunks_mut(CHUNK).enumerate() {
        let s = start + c * CHUNK;
        let n = chunk.len();
        bracket_ends(Run { ph, p, qs, s, n }, &mut ends);
        let table = ph.ft;
        for (i, slot) in chunk.iter_mut().enumerate() {
            *slot = if ends.scalar[i] {
                if qs.da[s + i] == 0.0 {
                    // An unmasked pixel or an empty cell (no facet): outright 0, as
                    // `h::outright` says, without the scalar geometry.
                    0.0
                } else {
                    k_entry_fast(ph, p, &qs.get(s + i))
                }
            } else {
                match ph.emission {
                    FacetEmission::Isotropic => {
                        ends.pre[i] * table.eval_diff_coords(ends.su[i], ends.sv1[i], ends.sv2[i])
                    }
                    FacetEmission::Lambertian => {
                        let [fc, fs] =
                            table.eval_facet_diff_coords(ends.su[i], ends.sv1[i], ends.sv2[i]);
                        let br = -ends.a[i] * fc - ends.b[i] * fs;
                        ends.pre[i] * br.max(0.0)
                    }
                }
            };
        }
    }
}

/// One run of the branch-free pass: p, and q = lanes `s..s + n` of `qs` (n ≤ [`CHUNK`]).
#[derive(Clone, Copy)]
struct Run<'a> {
    ph: &'a Physics<'a>,
    p: &'a Pre,
    qs: &'a PreLanes,
    s: usize,
    n: usize,
}

/// The branch-free pass over `run`, through a copy compiled for AVX2 where the CPU has it (the
/// same operations on wider registers, so the same results).
fn bracket_ends(run: Run, ends: &mut Ends) {
    #[cfg(target_arch = "x86_64")]
    {
        #[target_feature(enable = "avx2")]
        unsafe fn with_avx2(run: Run, ends: &mut Ends) {
            bracket_ends_for_emission(run, ends)
        }
        if crate::cpu::avx2_enabled() {
            // SAFETY: the CPU has AVX2.
            return unsafe { with_avx2(run, ends) };
        }
    }
    bracket_ends_for_emission(run, ends)
}

/// [`bracket_ends_generic`] for the facet model of `run.ph`.
#[inline(always)]
fn bracket_ends_for_emission(run: Run, ends: &mut Ends) {
    match run.ph.emission {
        FacetEmission::Lambertian => bracket_ends_generic::<true>(run, ends),
        FacetEmission::Isotropic => bracket_ends_generic::<false>(run, ends),
    }
}

/// The body of [`bracket_ends`]: `k_geometry`, `segment_fast` and the facet weights of
/// [`k_entry_fast`] with selects for branches; see the module documentation.
// `!(x > 0.0)` rather than `x <= 0.0` on purpose: a NaN must flag its lane for the scalar path.
#[allow(clippy::neg_cmp_op_on_partial_ord)]
#[inline(always)]
fn bracket_ends_generic<const LAMBERTIAN: bool>(run: Run, ends: &mut Ends) {
    let Run { ph, p, qs, s, n } = run;
    assert!(n <= CHUNK && s + n <= qs.d.len());
    let (beta, sigma, table) = (ph.beta, ph.sigma, ph.ft);
    let (pr, pd) = (p.ray, p.d);
    let (rx, ry, rz) = (
        &qs.ray[0][s..s + n],
        &qs.ray[1][s..s + n],
        &qs.ray[2][s..s + n],
    );
    let (nx, ny, nz) = (&qs.n[0][s..s + n], &qs.n[1][s..s + n], &qs.n[2][s..s + n]);
    let (d_q, nq, da, att) = (
        &qs.d[s..s + n],
        &qs.nq[s..s + n],
        &qs.da[s..s + n],
        &qs.att[s..s + n],
    );
    for i in 0..n {
        let q_ray = [rx[i], ry[i], rz[i]];
        let q_n = [nx[i], ny[i], nz[i]];
        let d = d_q[i];
        // k_geometry.
        let cos_g = pr[0] * q_ray[0] + pr[1] * q_ray[1] + pr[2] * q_ray[2];
        let cx = pr[1] * q_ray[2] - pr[2] * q_ray[1];
        let cy = pr[2] * q_ray[0] - pr[0] * q_ray[2];
        let cz = pr[0] * q_ray[1] - pr[1] * q_ray[0];
        let sin_g = (cx * cx + cy * cy + cz * cz).sqrt();
        let n_dot_rp = q_n[0] * pr[0] + q_n[1] * pr[1] + q_n[2] * pr[2];
        let t = nq[i] / n_dot_rp;
        let len = if t > 0.0 { t.min(pd) } else { pd };
        // segment_fast (outright values: `h::outright`; β = 0 never gets here).
        let mut scalar = !(len > 0.0) || da[i] == 0.0 || !(d > 0.0);
        let sin_g = sin_g.abs().max(SIN_GAMMA_MIN);
        let h = d * sin_g;
        let one_minus_cos = sin_g * sin_g / (1.0 + cos_g.max(-1.0 + 1e-12));
        let x = sigma * d * one_minus_cos;
        scalar |= !(x < 0.02);
        let growth = 1.0 + x * (1.0 + x * (0.5 + x * (1.0 / 6.0)));
        scalar |= !(cos_g > 0.0);
        let v1 = 0.5 * fast_atan(sin_g / cos_g);
        let pre = beta * da[i] * att[i] * growth / (2.0 * PI * h);
        let u = sigma * h;
        let v2 = FRAC_PI_4 + 0.5 * fast_atan((len - d * cos_g) / h);
        // The bracket: the table only for spans ≥ SMALL_BRACKET and u ≤ U_MAX.
        scalar |= !(v2 - v1 >= SMALL_BRACKET) || !(u <= U_MAX);
        if LAMBERTIAN {
            let n_dot_rq = q_n[0] * q_ray[0] + q_n[1] * q_ray[1] + q_n[2] * q_ray[2];
            ends.a[i] = n_dot_rp;
            ends.b[i] = (n_dot_rq - cos_g * n_dot_rp) / sin_g;
        }
        ends.pre[i] = pre;
        ends.su[i] = table.u_coord(u);
        ends.sv1[i] = table.v_coord(v1);
        ends.sv2[i] = table.v_coord(v2);
        ends.scalar[i] = scalar;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ps::physics::kernel_entry::Pre;
    use crate::ps::physics::FTable;

    fn lcg(seed: &mut u64) -> f64 {
        *seed = seed
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (*seed >> 11) as f64 / (1u64 << 53) as f64
    }

    fn unit(v: [f64; 3]) -> [f64; 3] {
        let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        [v[0] / l, v[1] / l, v[2] / l]
    }

    /// Pixels on a bumpy surface about 200 mm away, viewed by a 100 px focal length camera,
    /// with some unmasked (zero) pixels, tilted and back-facing normals, and a few far-flung
    /// points so that every flagged branch is taken.
    fn pixels(count: usize, seed: &mut u64, sigma: f64) -> Vec<Pre> {
        (0..count)
            .map(|_| {
                let r = lcg(seed);
                if r < 0.05 {
                    return Pre::default();
                }
                let spread = if r < 0.1 { 3.0 } else { 0.3 };
                let dir = unit([spread * (lcg(seed) - 0.5), spread * (lcg(seed) - 0.5), 1.0]);
                let dist = 150.0 + 100.0 * lcg(seed);
                let point = [dir[0] * dist, dir[1] * dist, dir[2] * dist];
                let tilt = if r < 0.15 { 3.0 } else { 0.8 };
                let sign = if r > 0.97 { 1.0 } else { -1.0 };
                let n = unit([tilt * (lcg(seed) - 0.5), tilt * (lcg(seed) - 0.5), sign]);
                let mut pre = Pre::new(point.into(), n.into(), 1e-4 * (0.5 + lcg(seed)));
                pre.att = (-sigma * pre.d).exp();
                pre
            })
            .collect()
    }

    /// Every lane equals the scalar entry bit for bit, on the AVX2 copy and the plain one,
    /// for both facet models and every flagged branch.
    #[test]
    fn batch_entries_equal_the_scalar_entries_bit_for_bit() {
        let ft = FTable::global();
        let mut seed = 7u64;
        for (beta, sigma) in [(5e-3, 5e-3), (5e-3, 0.2), (0.0, 5e-3), (0.0, 0.0)] {
            let medium = super::super::Medium {
                beta_per_mm: beta,
                sigma_per_mm: sigma,
            };
            let qs_pre = pixels(257, &mut seed, sigma);
            let qs = PreLanes::new(&qs_pre);
            for emission in [FacetEmission::Lambertian, FacetEmission::Isotropic] {
                let ph = Physics::new(ft, &medium, emission);
                for force_scalar in [false, true] {
                    crate::cpu::force_scalar(force_scalar);
                    let mut scalar_lanes = 0;
                    for p in qs_pre.iter().filter(|p| p.d > 0.0).take(24) {
                        for (start, len) in [(0, 257), (3, 1), (10, 31), (40, 33)] {
                            let mut out = vec![0.0; len];
                            k_entries_fast(&ph, p, &qs, start, &mut out);
                            for (i, &v) in out.iter().enumerate() {
                                let want = k_entry_fast(&ph, p, &qs_pre[start + i]);
                                assert_eq!(
                                    v.to_bits(),
                                    want.to_bits(),
                                    "{emission:?} β {beta} σ {sigma} lane {}: {v} vs {want}",
                                    start + i
                                );
                            }
                        }
                        let mut ends = Ends::new();
                        if beta > 0.0 {
                            let run = Run {
                                ph: &ph,
                                p,
                                qs: &qs,
                                s: 0,
                                n: CHUNK,
                            };
                            bracket_ends(run, &mut ends);
                            scalar_lanes += ends.scalar.iter().filter(|&&f| f).count();
                        }
                    }
                    if beta > 0.0 {
                        // Both the vector path and the scalar fallback are exercised.
                        assert!(
                            scalar_lanes > 0 && scalar_lanes < 24 * CHUNK,
                            "{scalar_lanes}"
                        );
                    }
                }
                crate::cpu::force_scalar(false);
            }
        }
    }
}
