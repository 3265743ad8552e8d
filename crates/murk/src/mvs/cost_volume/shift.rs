//! Cost-volume rows whose warp is a horizontal shift (a rectified pair, a rig translating along
//! its rows: [`crate::mvs::plane_sweep::RowWarp::shift`]).
//!
//! Why: on such a row every sample sits at `(x + du, v)` with one `du` and one `v`, so the
//! bilinear weights `(fx, fy)` are the same for the whole row and the source pixels it reads are
//! consecutive. The general loop computes each pixel's coordinates, cell and weights and reads a
//! 4-lane pixel at a time ([`super::simd`]); here each channel is one contiguous run of the
//! source's channel plane, eight pixels per AVX2 instruction, and no coordinates are computed.
//!
//! The arithmetic per sample and per channel is the general loop's (`t = p₀ + fx·(p₁ − p₀)`, then
//! `t + fy·(b − t)`; the residual `(I_r − o) − k(I_s − o)`; channels summed from 0 up), on
//! images minus the same offset `o` ([`planar`]), so a row agrees with the general loop to the bit
//! when the general loop's per-pixel `fx` equals the row's (an integer shift) and up to the `f32`
//! rounding of the coordinates otherwise (tested).

use rayon::prelude::*;

use crate::mvs::plane_sweep::RowWarp;

/// Largest distance, pixels, between a sample of the shift path and the exact warp of its row
/// that still counts as a shift: the general path's `f32` coordinates round by about this much
/// at a few thousand pixels.
pub(crate) const SHIFT_TOLERANCE_PX: f64 = 1e-3;

/// The shift `(du, v)` of a row whose warp is `warp`, where the source and the reference both
/// have channel planes ([`planar`]): the test that sends a row to [`accumulate`], shared by the
/// row loop and by [`super::CostRows::fill_plane`]'s planning of the 4-lane copies. `None`
/// sends the row to the general loop.
pub(super) fn row_shift(
    source_planar: &[f32],
    reference_planar: &[f32],
    warp: &RowWarp,
    width: usize,
) -> Option<(f64, f64)> {
    if source_planar.is_empty() || reference_planar.is_empty() {
        return None;
    }
    warp.shift(width, SHIFT_TOLERANCE_PX)
}

/// A `C`-channel interleaved image as `C` channel planes (`[c][y][x]`), each value minus
/// `offset` (the airlight for the observation-space dehazing volume, 0 for the ordinary one).
pub(super) fn planar(data: &[f32], channels: usize, offset: f32) -> Vec<f32> {
    // Blocks of pixels on rayon: the copy's fresh pages cost more than the copy itself.
    const BLOCK: usize = 8192;
    let channels = channels.max(1);
    let pixels = data.len() / channels;
    let mut out = vec![0.0f32; data.len()];
    for (c, plane) in out.chunks_exact_mut(pixels.max(1)).enumerate() {
        plane
            .par_chunks_mut(BLOCK)
            .zip(data.par_chunks(BLOCK * channels))
            .for_each(|(plane, data)| {
                for (o, px) in plane.iter_mut().zip(data.chunks_exact(channels)) {
                    *o = px[c] - offset;
                }
            });
    }
    out
}

/// One shift row: the source sample of pixel `x` is at `(x + du, v)`.
#[derive(Clone, Copy, Debug)]
pub(super) struct ShiftRow<'a> {
    /// Reference row `y`'s channel planes' rows are read from here ([`planar`], whole image).
    pub reference: &'a [f32],
    /// The source's channel planes ([`planar`], same offset).
    pub source: &'a [f32],
    /// Reference row.
    pub y: usize,
    /// Column shift, pixels.
    pub du: f64,
    /// Source row coordinate, pixels.
    pub v: f64,
}

impl<'a> ShiftRow<'a> {
    /// Reference row `y`'s samples in the source whose channel planes are `source` (the
    /// reference's: `reference`), where the row's warp is a shift ([`row_shift`]).
    pub(super) fn of(
        source: &'a [f32],
        reference: &'a [f32],
        y: usize,
        warp: &RowWarp,
        width: usize,
    ) -> Option<Self> {
        row_shift(source, reference, warp, width).map(|(du, v)| ShiftRow {
            reference,
            source,
            y,
            du,
            v,
        })
    }
}

/// Where [`accumulate`] puts one source's costs of a row.
pub(super) enum Target<'a> {
    /// Added to the running sums of several sources: `sum[x] += cost`, `observed[x] += 1`;
    /// `cost` is scratch of at least `width` values.
    Sums {
        sum: &'a mut [f32],
        observed: &'a mut [u32],
        cost: &'a mut [f32],
    },
    /// The costs of the only source, written: `out[x] = cost`, and `penalty` where the sample
    /// is outside the source. That is the mean [`super::kernel::mean_or_penalty`] takes of one
    /// source's sums bit for bit (`0 + c = c` and `c / 1 = c` for costs `≥ +0`), without
    /// clearing, adding to and dividing the sums.
    Only(&'a mut [f32]),
}

/// This source's cost `Σ_c |(I_r − o) − k(I_s − o)|` (`k = ratio[x]` when `HAZE`, else 1;
/// capped at `penalty` when `HAZE`) for every pixel of the row whose sample lies inside the
/// source (`0 ≤ x + du ≤ w − 1`, `0 ≤ v ≤ h − 1`), put into `target`. Images are at least 2×2.
#[allow(clippy::too_many_arguments)]
#[inline]
pub(super) fn accumulate<const C: usize, const HAZE: bool>(
    target: Target<'_>,
    row: ShiftRow<'_>,
    ratio: &[f32],
    width: usize,
    height: usize,
    penalty: f32,
) {
    #[cfg(target_arch = "x86_64")]
    {
        #[target_feature(enable = "avx2")]
        unsafe fn with_avx2<const C: usize, const HAZE: bool>(
            target: Target<'_>,
            row: ShiftRow<'_>,
            ratio: &[f32],
            width: usize,
            height: usize,
            penalty: f32,
        ) {
            accumulate_body::<C, HAZE>(target, row, ratio, width, height, penalty)
        }
        if crate::cpu::avx2_enabled() {
            // SAFETY: the CPU has AVX2 ([`crate::cpu::avx2_enabled`]).
            return unsafe { with_avx2::<C, HAZE>(target, row, ratio, width, height, penalty) };
        }
    }
    accumulate_body::<C, HAZE>(target, row, ratio, width, height, penalty)
}

/// The observed columns `lo..=hi` of a shift row (`0 ≤ x + du ≤ w − 1`, `0 ≤ v ≤ h − 1`), or
/// `None` where no pixel of the row is observed.
#[inline(always)]
fn observed_columns(row: &ShiftRow<'_>, w: usize, h: usize) -> Option<(usize, usize)> {
    let (wmax, hmax) = ((w - 1) as f64, (h - 1) as f64);
    // `!(a <= b)` is true for NaN too.
    if !(row.v >= 0.0 && row.v <= hmax) {
        return None;
    }
    let lo = (-row.du).ceil().max(0.0);
    let hi = (wmax - row.du).floor().min(wmax);
    // (`du` is finite: [`crate::mvs::plane_sweep::RowWarp::shift`].)
    (lo <= hi).then_some((lo as usize, hi as usize))
}

#[inline(always)]
fn accumulate_body<const C: usize, const HAZE: bool>(
    target: Target<'_>,
    row: ShiftRow<'_>,
    ratio: &[f32],
    width: usize,
    height: usize,
    penalty: f32,
) {
    let (w, h) = (width, height);
    let Some((lo, hi)) = observed_columns(&row, w, h) else {
        if let Target::Only(out) = target {
            out[..w].fill(penalty);
        }
        return;
    };
    // The cell and weights of the general sampler: `x₀ = ⌊u⌋` at most `w − 2`, `fx = u − x₀`.
    let y0 = (row.v.floor() as usize).min(h - 2);
    let fy = (row.v - y0 as f64) as f32;
    let whole = row.du.floor();
    let fx = (row.du - whole) as f32;
    let whole = whole as isize;
    // Columns whose right neighbour `x + ⌊du⌋ + 1` is inside; the last observed column may sit
    // exactly on the border (`u = w − 1`, `fx = 0`), where the general sampler takes the cell to
    // its left with `fx = 1`.
    let end = ((w as isize - 1 - whole).max(0) as usize).clamp(lo, hi + 1);
    // The only source's costs go straight to the output; several sources' through scratch.
    let (cost, sums) = match target {
        Target::Only(out) => {
            out[..lo].fill(penalty);
            out[hi + 1..w].fill(penalty);
            (&mut out[lo..=hi], None)
        }
        Target::Sums {
            sum,
            observed,
            cost,
        } => (&mut cost[lo..=hi], Some((sum, observed))),
    };
    for c in 0..C {
        let plane = &row.source[c * w * h..(c + 1) * w * h];
        let top = &plane[y0 * w..(y0 + 1) * w];
        let bottom = &plane[(y0 + 1) * w..(y0 + 2) * w];
        let ir = &row.reference[(c * h + row.y) * w..][lo..=hi];
        let k = &ratio[lo..=hi];
        let start = (lo as isize + whole) as usize;
        let n = end - lo;
        let sample = |x0: usize, fx: f32| -> f32 {
            let t = top[x0] + fx * (top[x0 + 1] - top[x0]);
            if fy == 0.0 {
                t
            } else {
                let b = bottom[x0] + fx * (bottom[x0 + 1] - bottom[x0]);
                t + fy * (b - t)
            }
        };
        let residual = |j: usize, is: f32| -> f32 {
            if HAZE {
                ir[j] - k[j] * is
            } else {
                ir[j] - is
            }
        };
        // The first channel writes the cost, the others add to it: `0 + x = x` for `x ≥ +0`,
        // so this is the sum from zero bit for bit without clearing it first.
        let put = |o: &mut f32, v: f32| {
            if c == 0 {
                *o = v;
            } else {
                *o += v;
            }
        };
        // The contiguous part: `top[start..start + n]` and its right neighbours, vectorised.
        if fy == 0.0 {
            let (p0, p1) = (&top[start..start + n], &top[start + 1..start + n + 1]);
            for (j, (o, (&a, &b))) in cost[..n].iter_mut().zip(p0.iter().zip(p1)).enumerate() {
                put(o, residual(j, a + fx * (b - a)).abs());
            }
        } else {
            let (p0, p1) = (&top[start..start + n], &top[start + 1..start + n + 1]);
            let (q0, q1) = (&bottom[start..start + n], &bottom[start + 1..start + n + 1]);
            for (j, (o, ((&a, &b), (&d, &e)))) in cost[..n]
                .iter_mut()
                .zip(p0.iter().zip(p1).zip(q0.iter().zip(q1)))
                .enumerate()
            {
                let t = a + fx * (b - a);
                let bt = d + fx * (e - d);
                put(o, residual(j, t + fy * (bt - t)).abs());
            }
        }
        // The border column, as the general sampler clamps it.
        for x in end..=hi {
            let u = x as f64 + row.du;
            let x0 = (u.floor() as usize).min(w - 2);
            let j = x - lo;
            put(
                &mut cost[j],
                residual(j, sample(x0, (u - x0 as f64) as f32)).abs(),
            );
        }
    }
    match sums {
        None => {
            if HAZE {
                for o in cost.iter_mut() {
                    *o = o.min(penalty);
                }
            }
        }
        Some((sum, observed)) => {
            for ((s, o), &c) in sum[lo..=hi]
                .iter_mut()
                .zip(&mut observed[lo..=hi])
                .zip(cost.iter())
            {
                *s += if HAZE { c.min(penalty) } else { c };
                *o += 1;
            }
        }
    }
}
