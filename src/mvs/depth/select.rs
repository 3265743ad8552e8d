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

/// Selects the minimum of one curve (see the module docs); `eps` is the confidence's `ε`.
#[inline]
pub fn select_curve(s: &[f32], eps: f32) -> Selection {
    let n = s.len();
    let mut best = 0usize;
    for (i, &v) in s.iter().enumerate() {
        if v < s[best] {
            best = i;
        }
    }
    let s1 = s[best];
    let mut delta = 0.0f32;
    if best > 0 && best + 1 < n {
        let (a, b, c) = (s[best - 1], s1, s[best + 1]);
        let denom = a - 2.0 * b + c;
        if denom > 0.0 {
            delta = (0.5 * (a - c) / denom).clamp(-0.5, 0.5);
        }
    }
    let s2 = s
        .iter()
        .enumerate()
        .filter(|(i, _)| i.abs_diff(best) > 1)
        .map(|(_, &v)| v)
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

/// [`select_curve`] for every pixel of a pixel-major `[pixel][plane]` volume of `n` planes.
pub fn select_each(sum: &[f32], n: usize, eps: f32) -> Vec<Selection> {
    sum.par_chunks(n).map(|c| select_curve(c, eps)).collect()
}
