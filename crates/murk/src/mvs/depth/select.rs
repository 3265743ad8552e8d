//! Winner-take-all over the aggregated curve, sub-plane refinement and confidence.
//!
//! - **Winner-take-all**: `i* = argmin_i S(p, i)` (lowest index on ties).
//! - **Sub-plane refinement**: a parabola through `S(i*−1), S(i*), S(i*+1)` has its vertex at
//!   `i* + δ`, `δ = (S(i*−1) − S(i*+1)) / (2 (S(i*−1) − 2 S(i*) + S(i*+1)))`, clamped to
//!   `[−½, ½]`; no refinement at the first/last plane or for a non-convex triple. Planes are
//!   uniform in inverse depth, so the fractional index maps linearly to inverse depth
//!   ([`crate::mvs::PlaneSet::inverse_depth`]) — the fit is done where the sampling is uniform.
//! - **Confidence**: `(S₂ − S₁) / (S₂ + ε) ∈ [0, 1]` with `S₁` the best aggregated cost and `S₂` the
//!   best cost **outside** `i* ± 1` (the neighbours of the minimum belong to the same basin and
//!   say nothing about ambiguity). A sharp, unique minimum gives a value near 1; a flat curve
//!   (textureless or unobserved pixel) or a competing minimum gives a value near 0. With
//!   `N ≤ 3` there is no plane outside `i* ± 1` and the confidence is 0. `ε` (cost units,
//!   [`CONFIDENCE_EPS_PER_PATH`] per path) keeps a curve that is zero up to rounding — a
//!   perfectly flat, textureless match — from reading as certain.

use rayon::prelude::*;

use super::sgm::PathCost;

/// `ε` of the confidence per aggregation path, cost units: a second-best aggregated cost below
/// about `0.01` per path is indistinguishable from a perfect (flat) match.
pub const CONFIDENCE_EPS_PER_PATH: f32 = 0.01;

/// Per-pixel selection result.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Selection {
    /// Fractional plane index `i* + δ`.
    pub index: f32,
    /// Confidence in `[0, 1]`.
    pub confidence: f32,
}

impl Selection {
    /// Plane 0 with no confidence: the value of a buffer before selection fills it.
    pub const NONE: Self = Self {
        index: 0.0,
        confidence: 0.0,
    };
}

/// The smallest value of `s` (`None` when empty) with 16 running minima, so the loop vectorises
/// (one scalar minimum is a loop-carried dependency LLVM will not reassociate for floats). The
/// values must not be NaN.
#[inline(always)]
fn min_of<T: PathCost>(s: &[T]) -> Option<T> {
    const LANES: usize = 16;
    let mut acc = [T::MAX; LANES];
    let mut chunks = s.chunks_exact(LANES);
    for c in &mut chunks {
        for j in 0..LANES {
            acc[j] = acc[j].lesser(c[j]);
        }
    }
    let m = chunks.remainder().iter().fold(T::MAX, |a, &b| a.lesser(b));
    (!s.is_empty()).then(|| acc.iter().fold(m, |a, &b| a.lesser(b)))
}

/// Selects the minimum of one curve (see the module docs); `eps` is the confidence's `ε`, in
/// the curve's units. Values must be finite (aggregated costs are): `f32` in cost units, or
/// `u16` levels ([`super::quantise`]), whose parabola and confidence are computed in `f32`.
#[inline(always)]
pub fn select_curve<T: PathCost>(s: &[T], eps: f32) -> Selection {
    let n = s.len();
    let Some(s1) = min_of(s) else {
        return Selection::NONE;
    };
    // The first index holding the minimum: the lowest index on ties.
    let best = s.iter().position(|&v| v == s1).unwrap_or(0);
    let s1 = s1.to_f32();
    let mut delta = 0.0f32;
    if best > 0 && best + 1 < n {
        let (a, b, c) = (s[best - 1].to_f32(), s1, s[best + 1].to_f32());
        let denom = a - 2.0 * b + c;
        if denom > 0.0 {
            delta = (0.5 * (a - c) / denom).clamp(-0.5, 0.5);
        }
    }
    let outside = |r: &[T]| min_of(r).map_or(f32::INFINITY, T::to_f32);
    let s2 = outside(&s[..best.saturating_sub(1)]).min(outside(&s[(best + 2).min(n)..]));
    let confidence = if s2.is_finite() && s2 + eps > 0.0 {
        ((s2 - s1) / (s2 + eps)).clamp(0.0, 1.0)
    } else {
        0.0
    };
    Selection {
        index: best as f32 + delta,
        confidence,
    }
}

/// [`select_curve`] for every pixel of a pixel-major `[pixel][plane]` volume of `n` planes
/// (`n ≥ 1`), in parallel ([`select_into`] on chunks of pixels).
pub fn select_each<T: PathCost>(sum: &[T], n: usize, eps: f32) -> Vec<Selection> {
    const PIXELS: usize = 256;
    let mut out = vec![Selection::NONE; sum.len() / n.max(1)];
    out.par_chunks_mut(PIXELS)
        .zip(sum.par_chunks(PIXELS * n.max(1)))
        .for_each(|(o, c)| select_into(c, n, eps, o));
    out
}

/// [`select_curve`] of each curve of `curves` (`n ≥ 1` planes per pixel) into `out`, one per
/// pixel, compiled for AVX2 where the CPU has it (the same results: only minima).
pub fn select_into<T: PathCost>(curves: &[T], n: usize, eps: f32, out: &mut [Selection]) {
    #[inline(always)]
    fn plain<T: PathCost>(curves: &[T], n: usize, eps: f32, out: &mut [Selection]) {
        for (o, c) in out.iter_mut().zip(curves.chunks_exact(n)) {
            *o = select_curve(c, eps);
        }
    }
    #[cfg(target_arch = "x86_64")]
    {
        #[target_feature(enable = "avx2")]
        unsafe fn with_avx2<T: PathCost>(curves: &[T], n: usize, eps: f32, out: &mut [Selection]) {
            plain(curves, n, eps, out)
        }
        if crate::cpu::avx2_enabled() {
            // SAFETY: the CPU has AVX2 ([`crate::cpu::avx2_enabled`]).
            return unsafe { with_avx2(curves, n, eps, out) };
        }
    }
    plain(curves, n, eps, out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The module docs read literally: a strict `<` scan for the winner, a filtered scan for the
    /// best cost outside its neighbours.
    fn naive(s: &[f32], eps: f32) -> Selection {
        let n = s.len();
        let mut best = 0;
        for i in 0..n {
            if s[i] < s[best] {
                best = i;
            }
        }
        let s1 = s[best];
        let mut delta = 0.0f32;
        if best > 0 && best + 1 < n {
            let (a, c) = (s[best - 1], s[best + 1]);
            let denom = a - 2.0 * s1 + c;
            if denom > 0.0 {
                delta = (0.5 * (a - c) / denom).clamp(-0.5, 0.5);
            }
        }
        let s2 = (0..n)
            .filter(|i| i.abs_diff(best) > 1)
            .map(|i| s[i])
            .fold(f32::INFINITY, f32::min);
        let confidence = if s2.is_finite() && s2 + eps > 0.0 {
            ((s2 - s1) / (s2 + eps)).clamp(0.0, 1.0)
        } else {
            0.0
        };
        Selection {
            index: best as f32 + delta,
            confidence,
        }
    }

    proptest! {
        /// Curves of every length around the 8-lane chunks, with values drawn from a few levels
        /// so ties are common.
        #[test]
        fn vectorised_selection_equals_the_plain_scan(
            curves in proptest::collection::vec(0u8..6, 1..160),
            n in 1usize..40,
        ) {
            let n = n.min(curves.len());
            let sum: Vec<f32> = curves[..curves.len() / n * n]
                .iter()
                .map(|&v| f32::from(v) * 0.25)
                .collect();
            let got = select_each(&sum, n, 0.08);
            // The same curves as u16 levels (×4): the same winners, refinements and confidences.
            let levels: Vec<u16> = sum.iter().map(|&v| (v * 4.0) as u16).collect();
            let got_levels = select_each(&levels, n, 0.32);
            for (k, c) in sum.chunks_exact(n).enumerate() {
                prop_assert_eq!(got[k], naive(c, 0.08));
                prop_assert_eq!(select_curve(c, 0.08), naive(c, 0.08));
                let scaled: Vec<f32> = c.iter().map(|&v| v * 4.0).collect();
                prop_assert_eq!(got_levels[k], naive(&scaled, 0.32));
            }
        }
    }
}
