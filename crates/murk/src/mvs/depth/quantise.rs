//! The windowed costs of a strip as 16-bit integer levels for SGM (as OpenCV's SGBM aggregates
//! 16-bit costs).
//!
//! SGM is the largest stage of depth estimation and bound by memory: its three sweeps stream the
//! cost volume and the aggregated volume `S` through memory. On `u16` instead of `f32` they move
//! half the bytes, and an AVX2 register holds 16 lanes instead of 8.
//!
//! Each strip's windowed costs `c ∈ [0, c_max]` become levels `q = round(c · k)`, `k = Q / c_max`,
//! and the penalties `P1`, `P2` (and the selection's `ε`) are scaled by the same `k`, so the
//! aggregation is the `f32` one of costs rounded to a step of `c_max / Q`. `Q` is as large as
//! `u16` sums allow: a sum of `paths` path costs, each at most `Q + P2·k` (the recursion's
//! bound), must fit `u16`, so the integer sums never saturate and equal the `f32` sums of the
//! levels exactly. With 8 paths and the default `P2` that is about 8000 levels (13 bits), with
//! the default 5 about 13 000; with
//! `Q = 4095` (12 bits) the simulator's full-size C.P. had moved by 0.1–0.3 points against `f32`
//! and the hazy Aloe pair not at all (docs/benchmarks.md).
//!
//! `c_max` is known before a strip's costs are ([`super::estimate_depth`] builds and quantises
//! them band by band): the largest weighted cost the volume can hold. A larger cost, which only
//! the ordinary volume of images outside `[0, 1]` produces, takes the top level: a truncated
//! cost.
//!
//! `S` of different strips is in different levels; [`Quantiser::unit`] converts it back to cost
//! units where strips meet (the consistency check's claims).

use super::sgm::Penalties;

/// The most levels a strip's costs get (14 bits, reached with 4 paths and small penalties; 8
/// paths leave room for about half of it, see the module docs).
pub const MAX_LEVELS: u16 = 16383;

/// The scale from one strip's costs to `u16` levels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Quantiser {
    /// Levels per cost unit, `k`.
    per_unit: f32,
    /// The largest level, `Q`.
    levels: u16,
    /// The largest penalty in levels that keeps a sum of the paths' costs inside `u16`.
    max_penalty: f32,
}

impl Quantiser {
    /// The quantiser for costs in `[0, max_cost]` aggregated over `num_paths` directions with a
    /// largest jump penalty `p2` (cost units; `P2 ≥ P1`, so it bounds every penalty). A
    /// `max_cost` that is 0, negative or not finite (every cost 0) gives one level per cost unit.
    pub fn new(max_cost: f32, p2: f32, num_paths: usize) -> Self {
        // paths · (Q + P2·Q/c_max + ½) ≤ 65535, with ½ for the rounding of P2.
        let per_path = (f64::from(u16::MAX) / num_paths.max(1) as f64) - 0.5;
        let most = per_path.floor().clamp(1.0, f64::from(MAX_LEVELS));
        let (q, per_unit) = if max_cost.is_finite() && max_cost > 0.0 {
            let ratio = f64::from(p2.max(0.0)) / f64::from(max_cost);
            let q = (per_path / (1.0 + ratio)).floor().clamp(1.0, most) as u16;
            (q, (f64::from(q) / f64::from(max_cost)) as f32)
        } else {
            (most as u16, 1.0)
        };
        Self {
            per_unit,
            levels: q,
            // Binds only where one level is left (`P2` thousands of times the costs' range,
            // a strip of near-zero costs): the penalties are capped rather than overflow.
            max_penalty: (per_path - f64::from(q)).floor() as f32,
        }
    }

    /// `Q`, the largest level.
    pub fn levels(&self) -> u16 {
        self.levels
    }

    /// Cost units per level, `1 / k`.
    pub fn unit(&self) -> f32 {
        1.0 / self.per_unit
    }

    /// A value in cost units (a penalty, `ε`) in levels, unrounded.
    pub fn scaled(&self, cost: f32) -> f32 {
        cost * self.per_unit
    }

    /// The penalties in levels ([`super::sgm::PathCost::penalty`] rounds them per step, after
    /// the adaptive `P2` is computed, so a gradient-reduced `P2` keeps its fraction until then),
    /// capped so that sums of path costs fit `u16` (the cap binds only in the degenerate case
    /// of [`Quantiser::new`]).
    pub fn penalties(&self, pen: &Penalties) -> Penalties {
        Penalties {
            p1: self.scaled(pen.p1).min(self.max_penalty),
            p2: self.scaled(pen.p2).min(self.max_penalty),
            p2_gradient_scale: pen.p2_gradient_scale,
        }
    }

    /// `dst[i] = round(src[i] · k)`, clamped to `[0, Q]` (a cost above `max_cost` takes the top
    /// level; a NaN, which validation keeps out, level 0). Inlined into the caller, so it runs
    /// on the caller's vector width.
    #[inline(always)]
    pub fn quantise_row(&self, src: &[f32], dst: &mut [u16]) {
        assert_eq!(src.len(), dst.len(), "row lengths");
        for (d, &c) in dst.iter_mut().zip(src) {
            *d = self.level(c);
        }
    }

    /// `(k, Q)`: levels per cost unit and the top level as `f32`, for a vector copy of
    /// [`Self::level`].
    pub(crate) fn factors(&self) -> (f32, f32) {
        (self.per_unit, f32::from(self.levels))
    }

    /// `round(c · k)` clamped to `[0, Q]`, the level of one cost (see [`Self::quantise_row`]).
    /// Branch-free, so a loop of it vectorises (the box window's AVX2 copy quantises each
    /// chunk of means while they are in registers).
    #[inline(always)]
    pub fn level(&self, c: f32) -> u16 {
        let v = c * self.per_unit + 0.5;
        // `v > 0` is false for NaN, so `v` ends finite in `[0, Q]`.
        let v = if v > 0.0 { v } else { 0.0 };
        let top = f32::from(self.levels);
        let v = if v < top { v } else { top };
        // SAFETY: `v` is finite and in `[0, MAX_LEVELS]`, so it fits `i32`; truncating `v + ½`
        // rounds half up. (The saturating `as` keeps a loop scalar.)
        unsafe { v.to_int_unchecked::<i32>() as u16 }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::monitor::Monitor;
    use crate::mvs::depth::sgm::{aggregate, DIRECTIONS};
    use proptest::prelude::*;

    #[test]
    fn levels_fit_u16_sums_and_the_top_cost_takes_the_top_level() {
        for (max, p2, paths) in [
            (4.0f32, 0.1f32, 8usize),
            (0.05, 0.1, 8),
            (1e-6, 0.1, 8),
            (12.0, 0.0, 4),
            (3.0, 1e6, 8),
            (12.0, 0.1, 5),
        ] {
            let q = Quantiser::new(max, p2, paths);
            let p2_levels = q
                .penalties(&Penalties {
                    p1: 0.0,
                    p2,
                    p2_gradient_scale: 0.0,
                })
                .p2
                .round();
            assert!(q.levels() >= 1 && q.levels() <= MAX_LEVELS, "{q:?}");
            assert!(
                paths as f32 * (f32::from(q.levels()) + p2_levels) <= f32::from(u16::MAX),
                "{max} {p2} {paths}: {q:?}"
            );
            let mut top = [0u16; 3];
            q.quantise_row(&[max, 0.0, max * 2.0], &mut top);
            assert_eq!(top, [q.levels(), 0, q.levels()]);
        }
        // As many levels as the u16 sums allow: 8 · (Q + P2·Q/c_max + ½) ≤ 65535.
        assert_eq!(Quantiser::new(4.0, 0.1, 8).levels(), 7991);
        // The one pass's 5 paths at hazy Aloe's bound (γ = 3 times the largest weight 4).
        assert_eq!(Quantiser::new(12.0, 0.1, 5).levels(), 12998);
        assert_eq!(Quantiser::new(12.0, 0.0, 4).levels(), MAX_LEVELS);
        assert_eq!(Quantiser::new(0.0, 0.1, 8).levels(), 8191);
        assert_eq!(Quantiser::new(0.0, 0.1, 4).levels(), MAX_LEVELS);
    }

    #[test]
    fn levels_are_the_costs_rounded_to_the_nearest_level() {
        let q = Quantiser::new(7.3, 0.1, 8);
        let src: Vec<f32> = (0..1001).map(|i| (i as f32 * 0.731) % 7.3).collect();
        let mut got = vec![0u16; src.len()];
        q.quantise_row(&src, &mut got);
        for (i, (&a, &c)) in got.iter().zip(&src).enumerate() {
            // Within half a level of the exact product (the `f32` product may round a value at a
            // half level either way).
            let exact = f64::from(c) * f64::from(q.per_unit);
            assert!(
                (f64::from(a) - exact).abs() <= 0.5 + 1e-4,
                "{i}: {a} for {exact}"
            );
        }
    }

    proptest! {
        /// The `u16` aggregation of quantised costs is the `f32` aggregation of the same levels
        /// as floats, to the bit: sums of integers below 2²⁴ are exact in both, and the levels
        /// keep every sum inside `u16`. (With a constant `P2`: the adaptive one is rounded per
        /// step for `u16` only.)
        #[test]
        fn u16_aggregation_equals_f32_aggregation_of_the_levels(
            seed in 0u64..1000,
            n in 1usize..40,
            paths in prop_oneof![Just(4usize), Just(5usize), Just(8usize)],
            p2 in prop_oneof![Just(0.05f32), Just(0.4f32), Just(30.0f32)],
        ) {
            let (w, h) = (19, 6);
            let mut s = seed.wrapping_mul(6364136223846793005).wrapping_add(1);
            let costs: Vec<f32> = (0..w * h * n)
                .map(|_| {
                    s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                    5.0 * ((s >> 40) as f32) / (1u64 << 24) as f32
                })
                .collect();
            let max = costs.iter().copied().fold(0.0f32, f32::max);
            let q = Quantiser::new(max, p2, paths);
            let mut levels = vec![0u16; costs.len()];
            q.quantise_row(&costs, &mut levels);
            let levels_pen = q.penalties(&Penalties { p1: p2 / 10.0, p2, p2_gradient_scale: 0.0 });
            let pen = Penalties {
                p1: levels_pen.p1.round(),
                p2: levels_pen.p2.round(),
                p2_gradient_scale: 0.0,
            };
            let ints = aggregate(&levels, w, h, n, paths, &pen, None, &Monitor::noop()).unwrap();
            let as_f32: Vec<f32> = levels.iter().map(|&v| f32::from(v)).collect();
            let floats = aggregate(&as_f32, w, h, n, paths, &pen, None, &Monitor::noop()).unwrap();
            prop_assert!(paths <= DIRECTIONS.len());
            prop_assert!(ints.iter().all(|&v| v < u16::MAX));
            for (a, b) in ints.iter().zip(&floats) {
                prop_assert_eq!(f32::from(*a), *b);
            }
        }
    }
}
