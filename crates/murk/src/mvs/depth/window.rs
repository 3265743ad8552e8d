//! Optional per-plane box aggregation of the raw matching cost before SGM.
//!
//! The pixel-wise L1 cost of Eq. 3.1 / 3.7 is noisy, more so for the dehazing volume, whose
//! residuals are the camera noise amplified by `1/t` (Eq. 3.5). A small box mean over each
//! plane (the classical "window" of block matching) averages that noise out before the
//! semi-global smoothness term sees it, at the price of slightly fattened depth edges.

use rayon::prelude::*;

use super::quantise::Quantiser;
use crate::error::Result;
use crate::monitor::Monitor;

/// Planes windowed together by [`window_groups_to_levels`], one rayon task per group: a group's
/// costs for a band of rows (164 KB for 8 planes of 8 rows of 640 pixels) stay in L2 from the
/// moment they are computed until their levels are written, and each pixel's levels of a group
/// are written as one contiguous run of the pixel-major row (16 bytes).
pub const LEVEL_GROUP: usize = 8;

/// The largest weighted cost `weights[y][x] · data[i][y][x]` of the `[plane][y][x]` volume
/// `data` (`n` planes of `w·h`; `weights` row-major `w·h`, empty = all 1), 0 for an empty
/// volume. Every box mean of [`window_to_levels`] is at most this, so it sets the strip's
/// quantisation before the window runs. Costs must not be NaN. One streaming read of the
/// volume, plane by plane on rayon.
pub fn largest_weighted(data: &[f32], weights: &[f32], w: usize, h: usize, n: usize) -> f32 {
    /// The largest `row[x] · weights[x]` (`row[x]` without weights), 8 running maxima over
    /// fixed-size chunks so the loop vectorises.
    #[inline(always)]
    fn row_max(row: &[f32], weights: Option<&[f32]>) -> f32 {
        const LANES: usize = 8;
        #[inline(always)]
        fn larger(a: f32, b: f32) -> f32 {
            if b > a {
                b
            } else {
                a
            }
        }
        let mut m = [0.0f32; LANES];
        let mut rest = 0.0f32;
        let full = row.len() / LANES * LANES;
        match weights {
            Some(wts) => {
                for (c, wt) in row[..full]
                    .chunks_exact(LANES)
                    .zip(wts[..full].chunks_exact(LANES))
                {
                    for j in 0..LANES {
                        m[j] = larger(m[j], c[j] * wt[j]);
                    }
                }
                for (&c, &wt) in row[full..].iter().zip(&wts[full..]) {
                    rest = larger(rest, c * wt);
                }
            }
            None => {
                for c in row[..full].chunks_exact(LANES) {
                    for j in 0..LANES {
                        m[j] = larger(m[j], c[j]);
                    }
                }
                for &c in &row[full..] {
                    rest = larger(rest, c);
                }
            }
        }
        m.iter().fold(rest, |a, &b| larger(a, b))
    }
    #[inline(always)]
    fn plane_max(plane: &[f32], weights: &[f32], w: usize) -> f32 {
        plane
            .chunks_exact(w)
            .enumerate()
            .map(|(y, row)| {
                let wts = (!weights.is_empty()).then(|| &weights[y * w..(y + 1) * w]);
                row_max(row, wts)
            })
            .fold(0.0, f32::max)
    }
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn plane_max_avx2(plane: &[f32], weights: &[f32], w: usize) -> f32 {
        plane_max(plane, weights, w)
    }
    assert_eq!(data.len(), w * h * n, "volume size");
    assert!(weights.is_empty() || weights.len() == w * h, "weights size");
    if w * h == 0 {
        return 0.0;
    }
    let avx2 = crate::cpu::avx2_enabled();
    data.par_chunks(w * h)
        .map(|plane| {
            #[cfg(target_arch = "x86_64")]
            if avx2 {
                // SAFETY: the CPU has AVX2 ([`crate::cpu::avx2_enabled`]).
                return unsafe { plane_max_avx2(plane, weights, w) };
            }
            let _ = avx2;
            plane_max(plane, weights, w)
        })
        .reduce(|| 0.0, f32::max)
}

/// The contrast weights, box mean, transpose and quantisation of step 2 of [`super`] on a whole
/// volume: from the `[plane][y][x]` volume `data` (`n` planes of `w·h`) into the pixel-major
/// `[y][x][plane]` volume of `u16` levels `out` (same length; every value is overwritten, so it
/// may hold anything):
///
/// `out[y][x][i] = quant(mean over the (2r+1)² window, clipped at the border, of weights[y'][x']·data[i][y'][x'])`
///
/// with `weights` row-major `w·h` (empty = all 1), `r = 0` meaning no window and `quant`
/// [`Quantiser::quantise_row`]. `data` is spent: it is left holding the weighted horizontal
/// means ([`window_groups_to_levels`], which this is with every row given at once).
#[allow(clippy::too_many_arguments)]
pub fn window_to_levels(
    data: &mut [f32],
    weights: &[f32],
    w: usize,
    h: usize,
    n: usize,
    r: usize,
    quant: &Quantiser,
    out: &mut [u16],
    monitor: &Monitor,
) -> Result<()> {
    assert_eq!(data.len(), w * h * n, "volume size");
    window_groups_to_levels(
        data,
        w * h,
        GroupRows {
            data_rows: 0..h,
            filtered: 0,
            out_rows: 0..h,
        },
        weights,
        (w, h, n, r),
        quant,
        out,
        || (),
        |_, _, _| Ok(()),
        monitor,
    )
}

/// Which rows [`window_groups_to_levels`] is given and which it windows, all relative to the
/// `h` rows of its volume (a strip's rows, or the whole image's).
#[derive(Clone, Debug)]
pub struct GroupRows {
    /// The rows held in each plane's part of the buffer, from its start: every row the windows
    /// of `out_rows` read (`r` rows above and below, clipped at `0` and `h`).
    pub data_rows: std::ops::Range<usize>,
    /// How many of the held rows, from the first, already hold the weighted horizontal means
    /// that an earlier call left there; the rest are costs (written by `prepare`).
    pub filtered: usize,
    /// The rows whose levels are written.
    pub out_rows: std::ops::Range<usize>,
}

/// [`window_to_levels`] of the output rows `rows.out_rows` of an `h`-row volume whose rows
/// `rows.data_rows` only are held, a group of [`LEVEL_GROUP`] planes per rayon task, each group
/// made by the caller's `prepare` just before it is windowed, so its rows are still in L2:
///
/// - `costs` holds `n` planes `stride` values apart, plane `i`'s row `k` (image row
///   `data_rows.start + k`) at `costs[i·stride + k·w ..][..w]`;
/// - `prepare(scratch, g0, group)` (`scratch` from `init`, once per worker) writes the costs of
///   rows `filtered..` of the planes `g0..g0 + group.len() / stride` into `group` (those planes'
///   part of `costs`); it may move rows that an earlier call filtered to the front first;
/// - the held rows from `filtered` on are then weighted (`weights`, row-major `w·h`, or empty
///   for unit weights) and box-summed along the row in place, so every held row ends holding the weighted
///   horizontal means, which the next band may keep (passing them as `filtered`);
/// - each output row's vertical sums over those rows are scaled, quantised and written to
///   `out` (`[row][x][plane]`, `out_rows.len() · w · n` values).
///
/// Every sum adds `2r + 1` `f32` values directly (no running sums, so no drift), in the same
/// order whatever the band, so a volume windowed band by band is the whole volume windowed at
/// once, bit for bit (tested), and so is AVX2 code and plain code (no fused multiply-adds).
#[allow(clippy::too_many_arguments)]
pub fn window_groups_to_levels<S, I, P>(
    costs: &mut [f32],
    stride: usize,
    rows: GroupRows,
    weights: &[f32],
    (w, h, n, r): (usize, usize, usize, usize),
    quant: &Quantiser,
    out: &mut [u16],
    init: I,
    prepare: P,
    monitor: &Monitor,
) -> Result<()>
where
    I: Fn() -> S + Sync + Send,
    P: Fn(&mut S, usize, &mut [f32]) -> Result<()> + Sync + Send,
{
    let GroupRows {
        data_rows,
        filtered,
        out_rows,
    } = rows;
    assert_eq!(costs.len(), n * stride, "volume size");
    assert!(
        data_rows.len() * w <= stride,
        "a plane's rows fit its stride"
    );
    assert!(filtered <= data_rows.len(), "filtered rows are held rows");
    assert_eq!(out.len(), out_rows.len() * w * n, "output size");
    assert!(weights.is_empty() || weights.len() == w * h, "weights size");
    assert!(
        data_rows.end <= h && out_rows.end <= h,
        "rows inside the volume"
    );
    if out_rows.is_empty() || w == 0 || n == 0 {
        return Ok(());
    }
    assert!(
        data_rows.start <= out_rows.start.saturating_sub(r)
            && data_rows.end >= (out_rows.end + r).min(h),
        "data rows hold the windows of the output rows"
    );
    monitor.checkpoint()?;
    // 1 / (pixels of the clipped window) along each axis: a multiply per voxel, not a divide.
    let inv_counts = |len: usize| -> Vec<f32> {
        (0..len)
            .map(|i| 1.0 / ((i + r + 1).min(len) - i.saturating_sub(r)) as f32)
            .collect()
    };
    let window = GroupWindow {
        w,
        h,
        r,
        inv_x: inv_counts(w),
        inv_y: inv_counts(h),
        weights,
        quant,
        data_rows,
        filtered,
        out_rows,
        out: LevelsOut {
            ptr: out.as_mut_ptr(),
            n,
        },
    };
    let avx2 = crate::cpu::avx2_enabled();
    costs
        .par_chunks_mut(LEVEL_GROUP * stride)
        .enumerate()
        .try_for_each_init(
            || (init(), GroupScratch::new(w, r)),
            |(user, scratch), (gi, group)| -> Result<()> {
                monitor.checkpoint()?;
                let g0 = gi * LEVEL_GROUP;
                prepare(user, g0, group)?;
                // SAFETY: group `gi` is the only task given planes `g0..g0 + LEVEL_GROUP`, so
                // its writes to `out` are disjoint from every other task's.
                unsafe { window.group_fast(avx2, group, stride, g0, scratch) };
                Ok(())
            },
        )
}

/// `out` of [`window_groups_to_levels`], written by every group's task at its own planes.
struct LevelsOut {
    ptr: *mut u16,
    n: usize,
}

// SAFETY: tasks write disjoint planes of the levels (see `window_groups_to_levels`), and the
// buffer outlives them (it is borrowed mutably for the whole call).
unsafe impl Sync for LevelsOut {}
unsafe impl Send for LevelsOut {}

/// Per-worker buffers of a group's window, all in L1.
struct GroupScratch {
    /// A weighted row with `r` zeros on each side: the clipped window's missing pixels add 0.
    padded: Vec<f32>,
    /// One plane row's vertical sums.
    means: Vec<f32>,
    /// The group's levels of one output row, plane row after plane row.
    levels: Vec<u16>,
}

impl GroupScratch {
    fn new(w: usize, r: usize) -> Self {
        Self {
            padded: vec![0.0; w + 2 * r],
            means: vec![0.0; w],
            levels: vec![0; LEVEL_GROUP * w],
        }
    }
}

/// What every group's window shares (see [`window_groups_to_levels`]).
struct GroupWindow<'a> {
    w: usize,
    h: usize,
    r: usize,
    inv_x: Vec<f32>,
    inv_y: Vec<f32>,
    weights: &'a [f32],
    quant: &'a Quantiser,
    data_rows: std::ops::Range<usize>,
    filtered: usize,
    out_rows: std::ops::Range<usize>,
    out: LevelsOut,
}

impl GroupWindow<'_> {
    /// [`Self::group`] compiled for AVX2 when `avx2` (the CPU has it): the same operations on
    /// wider registers, so the same results.
    ///
    /// # Safety
    /// No other task writes the planes `g0..g0 + group.len() / stride` of `out` meanwhile.
    #[inline]
    unsafe fn group_fast(
        &self,
        avx2: bool,
        group: &mut [f32],
        stride: usize,
        g0: usize,
        scratch: &mut GroupScratch,
    ) {
        #[cfg(target_arch = "x86_64")]
        {
            #[target_feature(enable = "avx2")]
            unsafe fn with_avx2(
                this: &GroupWindow<'_>,
                group: &mut [f32],
                stride: usize,
                g0: usize,
                scratch: &mut GroupScratch,
            ) {
                // SAFETY: passed on from the caller; this function runs only where the CPU
                // has AVX2.
                unsafe { this.group::<true>(group, stride, g0, scratch) }
            }
            if avx2 {
                // SAFETY: the caller detected AVX2 on this CPU ([`crate::cpu::avx2_enabled`]);
                // the rest is passed on from the caller.
                return unsafe { with_avx2(self, group, stride, g0, scratch) };
            }
        }
        let _ = avx2;
        // SAFETY: passed on from the caller.
        unsafe { self.group::<false>(group, stride, g0, scratch) }
    }

    /// The group's held rows from `filtered` on filtered in place ([`horizontal_in_place`]),
    /// then each output row's vertical means of every plane quantised and written to `out`.
    ///
    /// # Safety
    /// No other task writes the planes `g0..g0 + group.len() / stride` of `out` meanwhile.
    #[inline(always)]
    unsafe fn group<const AVX2: bool>(
        &self,
        group: &mut [f32],
        stride: usize,
        g0: usize,
        scratch: &mut GroupScratch,
    ) {
        let (w, r) = (self.w, self.r);
        let held = self.data_rows.len();
        let g = group.len() / stride;
        let GroupScratch {
            padded,
            means,
            levels,
        } = scratch;
        for plane in group.chunks_exact_mut(stride) {
            for k in self.filtered..held {
                let y = self.data_rows.start + k;
                let row_weights = (!self.weights.is_empty()).then(|| &self.weights[y * w..][..w]);
                horizontal_in_place::<AVX2>(
                    &mut plane[k * w..][..w],
                    row_weights,
                    r,
                    &self.inv_x,
                    padded,
                );
            }
        }
        let row_len = w * self.out.n;
        for y in self.out_rows.clone() {
            let lo = y.saturating_sub(r) - self.data_rows.start;
            let last = (y + r).min(self.h - 1) - self.data_rows.start;
            let k = self.inv_y[y];
            for (j, plane) in group.chunks_exact(stride).enumerate() {
                vertical_levels::<AVX2>(
                    &plane[..(last + 1) * w],
                    w,
                    lo,
                    k,
                    self.quant,
                    means,
                    &mut levels[j * w..][..w],
                );
            }
            // SAFETY: this row's pixels' planes `g0..g0 + g` are inside `out` and written by
            // this task alone (the caller's promise).
            unsafe {
                let dst = self.out.ptr.add((y - self.out_rows.start) * row_len + g0);
                write_group(&levels[..g * w], w, g, self.out.n, dst);
            }
        }
    }
}

/// Row `row` (`w` costs) weighted by `weights` (`w` values, `None` = all 1) and replaced by its
/// box means along the row, clipped at the image's columns: each mean is `2r + 1` shifted
/// additions of the padded weighted row, in order from the leftmost, times `inv_x`. `padded`
/// holds `w + 2r` values.
#[inline(always)]
fn horizontal_in_place<const AVX2: bool>(
    row: &mut [f32],
    weights: Option<&[f32]>,
    r: usize,
    inv_x: &[f32],
    padded: &mut [f32],
) {
    let w = row.len();
    let padded = &mut padded[..w + 2 * r];
    padded[..r].fill(0.0);
    padded[r + w..].fill(0.0);
    match weights {
        Some(weights) => {
            for ((o, &c), &wt) in padded[r..r + w].iter_mut().zip(&*row).zip(weights) {
                *o = c * wt;
            }
        }
        // Multiplying by 1 changes no value, so unit weights are a copy.
        None => padded[r..r + w].copy_from_slice(row),
    }
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if AVX2 {
        // SAFETY: `AVX2` is set only where the CPU has it ([`GroupWindow::group_fast`]).
        done = unsafe { box_row_avx2(padded, 2 * r + 1, inv_x, row) };
    }
    let row = &mut row[done..];
    row.copy_from_slice(&padded[done..w]);
    for k in 1..=2 * r {
        for (o, &v) in row.iter_mut().zip(&padded[done + k..k + w]) {
            *o += v;
        }
    }
    for (o, &k) in row.iter_mut().zip(&inv_x[done..]) {
        *o *= k;
    }
}

/// The levels of one output row of one plane: `out[x] = quant(k · (rows[lo][x] + … +
/// rows[last][x]))`, `rows` holding `w`-value rows up to `last` (its length), added in that
/// order, scaled and quantised ([`Quantiser::quantise_row`]); `means` is scratch of `w`
/// values. With `AVX2` (only where the CPU has it) 8 pixels at a time in registers
/// ([`vertical_levels_avx2`]), else, and for the rest of the row, as passes over the row.
#[inline(always)]
fn vertical_levels<const AVX2: bool>(
    rows: &[f32],
    w: usize,
    lo: usize,
    k: f32,
    quant: &Quantiser,
    means: &mut [f32],
    out: &mut [u16],
) {
    let last = rows.len() / w - 1;
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if AVX2 {
        // SAFETY: `AVX2` is set only where the CPU has it ([`GroupWindow::group_fast`]).
        done = unsafe { vertical_levels_avx2(rows, w, lo, k, quant, out) };
    }
    if done < w {
        let row = |i: usize| &rows[i * w..][done..w];
        let means = &mut means[done..w];
        means.copy_from_slice(row(lo));
        for i in lo + 1..=last {
            for (o, &v) in means.iter_mut().zip(row(i)) {
                *o += v;
            }
        }
        for o in means.iter_mut() {
            *o *= k;
        }
        quant.quantise_row(means, &mut out[done..w]);
    }
}

/// [`horizontal_in_place`]'s sums of the padded row for the first `8·⌊w/8⌋` pixels, 8 at a
/// time in one register: `row[x] = (padded[x] + padded[x + 1] + … + padded[x + taps − 1]) ·
/// inv_x[x]`, added in that order, so the same values as the plain passes (a copy, `taps − 1`
/// additions and a scaling, each over the whole row) in one pass instead of `taps + 1`. The
/// common widths (3, 5, 7 taps) are unrolled. Returns the pixels done.
///
/// # Safety
/// The CPU has AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn box_row_avx2(padded: &[f32], taps: usize, inv_x: &[f32], row: &mut [f32]) -> usize {
    assert!(taps >= 1 && padded.len() + 1 >= row.len() + taps && inv_x.len() >= row.len());
    // SAFETY: the CPU has AVX2 (the caller's promise); the lengths are asserted above.
    unsafe {
        match taps {
            3 => box_row_taps::<3>(padded, 3, inv_x, row),
            5 => box_row_taps::<5>(padded, 5, inv_x, row),
            7 => box_row_taps::<7>(padded, 7, inv_x, row),
            _ => box_row_taps::<0>(padded, taps, inv_x, row),
        }
    }
}

/// [`box_row_avx2`] with `TAPS` taps known at compile time (`0`: `taps` at run time).
///
/// # Safety
/// The CPU has AVX2; `padded.len() + 1 ≥ row.len() + taps`, `inv_x.len() ≥ row.len()`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn box_row_taps<const TAPS: usize>(
    padded: &[f32],
    taps: usize,
    inv_x: &[f32],
    row: &mut [f32],
) -> usize {
    use std::arch::x86_64::*;
    let taps = if TAPS > 0 { TAPS } else { taps };
    let w = row.len();
    let (p, iv, o) = (padded.as_ptr(), inv_x.as_ptr(), row.as_mut_ptr());
    let mut x = 0;
    while x + 8 <= w {
        // SAFETY: `x + 8 ≤ w`, so every load reads `padded[x + k ..][..8]` with
        // `x + k + 8 ≤ w + taps − 1 ≤ padded.len()`, `inv_x[x..x + 8]` and writes `row[x..x + 8]`.
        unsafe {
            let mut acc = _mm256_loadu_ps(p.add(x));
            for k in 1..taps {
                acc = _mm256_add_ps(acc, _mm256_loadu_ps(p.add(x + k)));
            }
            _mm256_storeu_ps(o.add(x), _mm256_mul_ps(acc, _mm256_loadu_ps(iv.add(x))));
        }
        x += 8;
    }
    x
}

/// The vertical means' levels of one output row of one plane for the first `8·⌊w/8⌋` pixels, 8
/// at a time in one register: `out[x] = quant(k · (rows[lo][x] + rows[lo + 1][x] + … +
/// rows[last][x]))`, `rows` holding `w`-value rows up to `last` (its length), added in that
/// order and quantised as [`Quantiser::quantise_row`] does, so the same levels as the plain
/// passes without writing the sums back. The common window heights (3, 5, 7 rows) are
/// unrolled. Returns the pixels done.
///
/// # Safety
/// The CPU has AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn vertical_levels_avx2(
    rows: &[f32],
    w: usize,
    lo: usize,
    k: f32,
    quant: &Quantiser,
    out: &mut [u16],
) -> usize {
    let last = rows.len() / w - 1;
    assert!(lo <= last && rows.len() == (last + 1) * w && out.len() >= w);
    let rows = &rows[lo * w..];
    // SAFETY: the CPU has AVX2 (the caller's promise); `rows` holds `last − lo + 1` rows of
    // `w` values (asserted above).
    unsafe {
        match last - lo + 1 {
            3 => vertical_levels_rows::<3>(rows, w, 3, k, quant, out),
            5 => vertical_levels_rows::<5>(rows, w, 5, k, quant, out),
            7 => vertical_levels_rows::<7>(rows, w, 7, k, quant, out),
            n => vertical_levels_rows::<0>(rows, w, n, k, quant, out),
        }
    }
}

/// [`vertical_levels_avx2`] of the `n` rows of `rows` (`ROWS` known at compile time, `0`: at
/// run time).
///
/// # Safety
/// The CPU has AVX2; `rows.len() ≥ n·w`, `out.len() ≥ w`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn vertical_levels_rows<const ROWS: usize>(
    rows: &[f32],
    w: usize,
    n: usize,
    k: f32,
    quant: &Quantiser,
    out: &mut [u16],
) -> usize {
    use std::arch::x86_64::*;
    let n = if ROWS > 0 { ROWS } else { n };
    let (per_unit, top) = quant.factors();
    let (kv, unit, half, zero, topv) = (
        _mm256_set1_ps(k),
        _mm256_set1_ps(per_unit),
        _mm256_set1_ps(0.5),
        _mm256_setzero_ps(),
        _mm256_set1_ps(top),
    );
    let (p, o) = (rows.as_ptr(), out.as_mut_ptr());
    let mut x = 0;
    while x + 8 <= w {
        // SAFETY: `x + 8 ≤ w`, so the loads read `rows[i·w + x..][..8]` for `i < n` and the
        // store writes `out[x..x + 8]`.
        unsafe {
            let mut acc = _mm256_loadu_ps(p.add(x));
            for i in 1..n {
                acc = _mm256_add_ps(acc, _mm256_loadu_ps(p.add(i * w + x)));
            }
            // [`Quantiser::level`]: `c·k_q + ½` clamped to `[0, Q]` (`max` and `min` take
            // their second operand unless the first is greater, resp. less, as the plain
            // comparisons do, NaN included), then truncated.
            let v = _mm256_add_ps(_mm256_mul_ps(_mm256_mul_ps(acc, kv), unit), half);
            let v = _mm256_min_ps(_mm256_max_ps(v, zero), topv);
            let q = _mm256_cvttps_epi32(v);
            // Levels are at most `Q < 2¹⁵`, so the unsigned saturation never binds.
            let q = _mm_packus_epi32(_mm256_castsi256_si128(q), _mm256_extracti128_si256::<1>(q));
            _mm_storeu_si128(o.add(x).cast(), q);
        }
        x += 8;
    }
    x
}

/// `dst[x·n + j] = levels[j·w + x]` for the `g` plane rows `j` of `levels` and the `w` pixels
/// `x`: a group of [`LEVEL_GROUP`] planes goes 8 pixels at a time through an 8×8 transpose of
/// `u16` in SSE2 registers (8 loads and 8 stores of a pixel's group instead of 64 scalar ones).
///
/// # Safety
/// `dst[x·n + j]` is writable for every `x < w`, `j < g`.
#[inline(always)]
unsafe fn write_group(levels: &[u16], w: usize, g: usize, n: usize, dst: *mut u16) {
    debug_assert_eq!(levels.len(), g * w);
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if g == LEVEL_GROUP {
        use std::arch::x86_64::*;
        const _: () = assert!(LEVEL_GROUP == 8, "an 8x8 transpose");
        let src = levels.as_ptr();
        while done + 8 <= w {
            let x = done;
            // SAFETY: rows `j < 8` of `levels` hold `w` values and `x + 8 ≤ w`; each store writes
            // `dst[(x + k)·n ..][..8]`, writable by the caller's promise. SSE2 is part of x86_64.
            unsafe {
                let load = |j: usize| _mm_loadu_si128(src.add(j * w + x).cast());
                let (r0, r1, r2, r3) = (load(0), load(1), load(2), load(3));
                let (r4, r5, r6, r7) = (load(4), load(5), load(6), load(7));
                // Interleave pairs of planes, then pairs of pairs, then quadruples.
                let a0 = _mm_unpacklo_epi16(r0, r1);
                let a1 = _mm_unpackhi_epi16(r0, r1);
                let a2 = _mm_unpacklo_epi16(r2, r3);
                let a3 = _mm_unpackhi_epi16(r2, r3);
                let a4 = _mm_unpacklo_epi16(r4, r5);
                let a5 = _mm_unpackhi_epi16(r4, r5);
                let a6 = _mm_unpacklo_epi16(r6, r7);
                let a7 = _mm_unpackhi_epi16(r6, r7);
                let b0 = _mm_unpacklo_epi32(a0, a2);
                let b1 = _mm_unpackhi_epi32(a0, a2);
                let b2 = _mm_unpacklo_epi32(a1, a3);
                let b3 = _mm_unpackhi_epi32(a1, a3);
                let b4 = _mm_unpacklo_epi32(a4, a6);
                let b5 = _mm_unpackhi_epi32(a4, a6);
                let b6 = _mm_unpacklo_epi32(a5, a7);
                let b7 = _mm_unpackhi_epi32(a5, a7);
                let pixels = [
                    _mm_unpacklo_epi64(b0, b4),
                    _mm_unpackhi_epi64(b0, b4),
                    _mm_unpacklo_epi64(b1, b5),
                    _mm_unpackhi_epi64(b1, b5),
                    _mm_unpacklo_epi64(b2, b6),
                    _mm_unpackhi_epi64(b2, b6),
                    _mm_unpacklo_epi64(b3, b7),
                    _mm_unpackhi_epi64(b3, b7),
                ];
                for (k, p) in pixels.into_iter().enumerate() {
                    _mm_storeu_si128(dst.add((x + k) * n).cast(), p);
                }
            }
            done += 8;
        }
    }
    for x in done..w {
        for j in 0..g {
            // SAFETY: `x < w`, `j < g` (the caller's promise).
            unsafe { *dst.add(x * n + j) = levels[j * w + x] };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Weights, box mean and transpose read directly off their definitions.
    fn reference(
        data: &[f32],
        weights: &[f32],
        w: usize,
        h: usize,
        n: usize,
        r: usize,
    ) -> Vec<f32> {
        let mut out = vec![0.0f32; w * h * n];
        for i in 0..n {
            for y in 0..h {
                for x in 0..w {
                    let (mut s, mut cnt) = (0.0f64, 0);
                    for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
                        for xx in x.saturating_sub(r)..(x + r + 1).min(w) {
                            let k = if weights.is_empty() {
                                1.0
                            } else {
                                weights[yy * w + xx]
                            };
                            s += f64::from(data[(i * h + yy) * w + xx] * k);
                            cnt += 1;
                        }
                    }
                    out[(y * w + x) * n + i] = (s / f64::from(cnt)) as f32;
                }
            }
        }
        out
    }

    /// [`window_to_levels`] of the whole `(w, h, n, r)` volume `data`, with the plain loops
    /// when `scalar`.
    fn whole_levels(
        data: &[f32],
        weights: &[f32],
        (w, h, n, r): (usize, usize, usize, usize),
        quant: &Quantiser,
        scalar: bool,
    ) -> Vec<u16> {
        crate::cpu::force_scalar(scalar);
        let mut out = vec![0u16; data.len()];
        window_to_levels(
            &mut data.to_vec(),
            weights,
            w,
            h,
            n,
            r,
            quant,
            &mut out,
            &Monitor::noop(),
        )
        .unwrap();
        crate::cpu::force_scalar(false);
        out
    }

    /// A volume windowed band by band, each band's costs prepared group by group and the rows
    /// both bands read kept filtered from the last band (moved to the front as [`super::Band`]
    /// does), is the whole volume windowed at once, bit for bit (AVX2 and plain code).
    #[test]
    fn bands_window_like_the_whole_volume() {
        for (w, h, n, r, band) in [
            (13, 40, 11, 2, 8),
            (9, 37, 8, 3, 5),
            (20, 17, 17, 0, 4),
            (7, 30, 3, 5, 9),
            (16, 12, 9, 1, 12),
            (5, 9, 2, 2, 1),
            (137, 11, 25, 2, 4),
        ] {
            let data: Vec<f32> = (0..w * h * n)
                .map(|i| ((i * 53) % 17) as f32 * 0.07)
                .collect();
            let weights: Vec<f32> = (0..w * h)
                .map(|i| 1.0 + ((i * 11) % 7) as f32 * 0.4)
                .collect();
            let quant = Quantiser::new(largest_weighted(&data, &weights, w, h, n), 0.3, 8);
            for scalar in [false, true] {
                let whole = whole_levels(&data, &weights, (w, h, n, r), &quant, scalar);
                crate::cpu::force_scalar(scalar);
                let mut banded = vec![u16::MAX; data.len()];
                let stride = (band + 2 * r) * w;
                // Anything but costs where `prepare` writes none.
                let mut costs = vec![f32::NAN; n * stride];
                let mut kept: Option<std::ops::Range<usize>> = None;
                for y0 in (0..h).step_by(band) {
                    let own = y0..(y0 + band).min(h);
                    let read = own.start.saturating_sub(r)..(own.end + r).min(h);
                    let (have, shift) = match &kept {
                        Some(p) if p.start <= read.start && read.start < p.end => {
                            (p.end.min(read.end) - read.start, read.start - p.start)
                        }
                        _ => (0, 0),
                    };
                    window_groups_to_levels(
                        &mut costs,
                        stride,
                        GroupRows {
                            data_rows: read.clone(),
                            filtered: have,
                            out_rows: own.clone(),
                        },
                        &weights,
                        (w, h, n, r),
                        &quant,
                        &mut banded[own.start * w * n..own.end * w * n],
                        || (),
                        |_, g0, group| {
                            for (j, plane) in group.chunks_exact_mut(stride).enumerate() {
                                plane.copy_within(shift * w..(shift + have) * w, 0);
                                let i = g0 + j;
                                plane[have * w..read.len() * w].copy_from_slice(
                                    &data[(i * h + read.start + have) * w..(i * h + read.end) * w],
                                );
                            }
                            Ok(())
                        },
                        &Monitor::noop(),
                    )
                    .unwrap();
                    kept = Some(read);
                }
                crate::cpu::force_scalar(false);
                assert_eq!(banded, whole, "{w}x{h}x{n} r={r} bands of {band}");
            }
        }
    }

    /// The AVX2 window (the fused box sums along the row, and the vertical sums quantised in
    /// registers, [`box_row_avx2`], [`vertical_levels_avx2`]) writes the plain passes' levels bit
    /// for bit: windows of 1 to 11 taps (the unrolled 3, 5, 7 and the rest), rows clipped at
    /// the image's top and bottom, widths around the 8 lanes, with and without weights, and
    /// costs above the quantiser's largest, which take the top level.
    #[test]
    fn avx2_window_is_the_plain_window() {
        if !crate::cpu::avx2_enabled() {
            eprintln!("skipped: this CPU has no AVX2");
            return;
        }
        for (w, h, n, r) in [
            (37, 9, 8, 2),
            (8, 12, 3, 1),
            (64, 7, 9, 3),
            (5, 6, 2, 2),
            (29, 14, 8, 0),
            (41, 13, 4, 4),
            (70, 16, 8, 5),
            (16, 3, 5, 2),
        ] {
            let data: Vec<f32> = (0..w * h * n)
                .map(|i| ((i * 2654435761) % 1009) as f32 * 0.003)
                .collect();
            for weighted in [false, true] {
                let weights: Vec<f32> = if weighted {
                    (0..w * h)
                        .map(|i| 1.0 + ((i * 13) % 5) as f32 * 0.3)
                        .collect()
                } else {
                    Vec::new()
                };
                // A third of the largest weighted cost: the largest means take the top level.
                let top = largest_weighted(&data, &weights, w, h, n) / 3.0;
                let quant = Quantiser::new(top, 0.2, 5);
                let levels = |scalar| whole_levels(&data, &weights, (w, h, n, r), &quant, scalar);
                let (plain, avx2) = (levels(true), levels(false));
                assert!(plain.contains(&quant.levels()), "some levels at the top");
                assert_eq!(avx2, plain, "{w}x{h}x{n} r={r} weighted {weighted}");
            }
        }
    }

    #[test]
    fn window_to_levels_matches_direct_sum() {
        // Heights beyond one band, plane counts around the plane group, windows wider than the
        // image, with and without weights.
        for (w, h, n, r) in [
            (7, 5, 3, 2),
            (9, 2, 8, 3),
            (3, 70, 11, 1),
            (1, 1, 1, 4),
            (16, 40, 17, 5),
            (5, 33, 9, 0),
            (70, 3, 2, 1),
            // A width that is not a multiple of the 8-pixel transpose.
            (301, 6, 9, 3),
        ] {
            let data: Vec<f32> = (0..w * h * n)
                .map(|i| ((i * 37) % 11) as f32 * 0.1)
                .collect();
            let weights: Vec<f32> = (0..w * h)
                .map(|i| 1.0 + ((i * 7) % 5) as f32 * 0.5)
                .collect();
            for wts in [&weights[..], &[]] {
                let largest = largest_weighted(&data, wts, w, h, n);
                let direct = (0..w * h * n)
                    .map(|k| data[k] * wts.get(k % (w * h)).copied().unwrap_or(1.0))
                    .fold(0.0f32, f32::max);
                assert_eq!(largest, direct, "{w}x{h}x{n}");
                let quant = Quantiser::new(largest, 0.1, 8);
                let per_level = quant.scaled(1.0);
                let mut out = vec![u16::MAX; data.len()];
                window_to_levels(
                    &mut data.clone(),
                    wts,
                    w,
                    h,
                    n,
                    r,
                    &quant,
                    &mut out,
                    &Monitor::noop(),
                )
                .unwrap();
                let want = reference(&data, wts, w, h, n, r);
                for (k, (&a, &b)) in out.iter().zip(&want).enumerate() {
                    // Rounded to the nearest level (a mean's last-bit difference from the
                    // direct sum may round the other way at a half level).
                    assert!(
                        (f32::from(a) - b * per_level).abs() <= 0.5 + 1e-3,
                        "{w}x{h}x{n} r={r} voxel {k}: level {a} for mean {b}"
                    );
                    assert!(a <= quant.levels());
                }
                crate::cpu::force_scalar(true);
                let mut plain = vec![0u16; data.len()];
                window_to_levels(
                    &mut data.clone(),
                    wts,
                    w,
                    h,
                    n,
                    r,
                    &quant,
                    &mut plain,
                    &Monitor::noop(),
                )
                .unwrap();
                let plain_largest = largest_weighted(&data, wts, w, h, n);
                crate::cpu::force_scalar(false);
                assert_eq!(plain, out);
                assert_eq!(plain_largest, largest);
            }
        }
    }
}
