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

/// Planes handled together by the horizontal pass: each pixel's values of a group are written as
/// one contiguous run of the pixel-major row (32 bytes), not one scattered float per plane.
const PLANE_GROUP: usize = 8;

/// The fewest and most output rows per rayon task. Each task also filters the `r` rows above and
/// below its rows, so taller tasks waste less; a band of a few dozen rows still gets one task
/// per worker.
const MIN_TASK_ROWS: usize = 8;
/// See [`MIN_TASK_ROWS`].
const MAX_TASK_ROWS: usize = 32;

/// Columns windowed together: a task's ring of `2r + 1` filtered rows then holds this many
/// pixels' curves (443 KB for 128 pixels of 173 planes and `r = 2`), which stays in L2, where
/// a ring of whole 640-pixel rows (2.2 MB) did not.
const TILE_PX: usize = 128;

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

/// The contrast weights, box mean, transpose and quantisation of step 2 of [`super`] in one
/// pass: from the `[plane][y][x]` volume `data` (`n` planes of `w·h`) into the pixel-major
/// `[y][x][plane]` volume of `u16` levels `out` (same length; every value is overwritten, so it
/// may hold anything):
///
/// `out[y][x][i] = quant(mean over the (2r+1)² window, clipped at the border, of weights[y'][x']·data[i][y'][x'])`
///
/// with `weights` row-major `w·h` (empty = all 1), `r = 0` meaning no window and `quant`
/// [`Quantiser::quantise_row`]. Reading the plane-major volume once and writing the pixel-major
/// levels once replaces four passes over it (weights, window, transpose, quantisation). Each
/// task keeps `2r + 1` horizontally filtered pixel-major rows in a ring, so the vertical mean is
/// a contiguous, vectorised sum over planes. Both sums add `2r + 1` `f32` values directly (no
/// running sums, so no drift along a row): the horizontal one along each plane row, the vertical
/// one 64 values at a time in L1, where they are quantised: the `f32` means never reach memory.
#[allow(clippy::too_many_arguments)]
pub fn window_to_levels(
    data: &[f32],
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
    window_rows_to_levels(data, 0..h, weights, w, h, n, r, 0..h, quant, out, monitor)
}

/// [`window_to_levels`] of the output rows `out_rows` of an `h`-row volume whose rows
/// `data_rows` only are in `data` (`[plane][row][x]`, `n` planes of `w · data_rows.len()`):
/// `out` gets those rows' levels (`[row][x][plane]`, `out_rows.len() · w · n` values), the same
/// as the rows of the whole volume's [`window_to_levels`]. `data_rows` must hold every row the
/// windows of `out_rows` read (`r` rows above and below, clipped at `0` and `h`). `weights` cover
/// all `h` rows (row-major `w·h`, empty = all 1). A strip is windowed band by band this way, each
/// band's costs computed just before and still in cache.
#[allow(clippy::too_many_arguments)]
pub fn window_rows_to_levels(
    data: &[f32],
    data_rows: std::ops::Range<usize>,
    weights: &[f32],
    w: usize,
    h: usize,
    n: usize,
    r: usize,
    out_rows: std::ops::Range<usize>,
    quant: &Quantiser,
    out: &mut [u16],
    monitor: &Monitor,
) -> Result<()> {
    let npix = w * data_rows.len();
    assert_eq!(data.len(), npix * n, "volume size");
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
    let (inv_x, inv_y) = (inv_counts(w), inv_counts(h));
    let row_len = w * n;
    let ring_len = 2 * r + 1;
    let avx2 = crate::cpu::avx2_enabled();
    // Unit weights for every row when none are given.
    let ones = if weights.is_empty() {
        vec![1.0f32; w]
    } else {
        Vec::new()
    };
    // At least one task per worker for a band of a few dozen rows, each refiltering `2r` rows.
    let tile = TILE_PX.min(w);
    let task_rows = out_rows
        .len()
        .div_ceil(rayon::current_num_threads())
        .clamp(MIN_TASK_ROWS, MAX_TASK_ROWS);
    out.par_chunks_mut(task_rows * row_len)
        .enumerate()
        .for_each_init(
            || {
                (
                    vec![0.0f32; ring_len * tile * n],
                    HorizontalScratch::new(tile, r),
                )
            },
            |(ring, scratch), (task, out_task)| {
                let y0 = out_rows.start + task * task_rows;
                let y1 = (y0 + task_rows).min(out_rows.end);
                for x0 in (0..w).step_by(tile) {
                    let cols = x0..(x0 + tile).min(w);
                    let tile_len = cols.len() * n;
                    let ring = &mut ring[..ring_len * tile_len];
                    // The next row to filter into the ring.
                    let mut next = y0.saturating_sub(r);
                    for y in y0..y1 {
                        let last = (y + r).min(h - 1);
                        while next <= last {
                            let slot = &mut ring[(next % ring_len) * tile_len..][..tile_len];
                            let row_weights = if weights.is_empty() {
                                &ones[..]
                            } else {
                                &weights[next * w..(next + 1) * w]
                            };
                            horizontal_row_fast(
                                avx2,
                                data,
                                row_weights,
                                w,
                                npix,
                                n,
                                r,
                                next - data_rows.start,
                                cols.clone(),
                                &inv_x,
                                scratch,
                                slot,
                            );
                            next += 1;
                        }
                        let dst = &mut out_task[(y - y0) * row_len + x0 * n..][..tile_len];
                        let lo = y.saturating_sub(r);
                        let k = inv_y[y];
                        vertical_mean_fast(avx2, ring, tile_len, lo..=last, k, quant, dst);
                    }
                }
            },
        );
    Ok(())
}

/// Values of a pixel-major row summed together by [`vertical_mean`]: 256 bytes, which stay in
/// L1 while every ring row adds to them.
const VERTICAL_CHUNK: usize = 64;

/// [`vertical_mean`] compiled for AVX2 when `avx2` (the CPU has it): the same additions on wider
/// registers, so the same results.
#[inline]
fn vertical_mean_fast(
    avx2: bool,
    ring: &[f32],
    row_len: usize,
    rows: std::ops::RangeInclusive<usize>,
    k: f32,
    quant: &Quantiser,
    dst: &mut [u16],
) {
    #[cfg(target_arch = "x86_64")]
    {
        #[target_feature(enable = "avx2")]
        unsafe fn with_avx2(
            ring: &[f32],
            row_len: usize,
            rows: std::ops::RangeInclusive<usize>,
            k: f32,
            quant: &Quantiser,
            dst: &mut [u16],
        ) {
            vertical_mean(ring, row_len, rows, k, quant, dst)
        }
        if avx2 {
            // SAFETY: the caller detected AVX2 on this CPU ([`crate::cpu::avx2_enabled`]).
            return unsafe { with_avx2(ring, row_len, rows, k, quant, dst) };
        }
    }
    let _ = avx2;
    vertical_mean(ring, row_len, rows, k, quant, dst)
}

/// `dst = quant((row[lo] + row[lo+1] + … + row[last]) · k)` over the ring's horizontally
/// filtered rows (image row `y` in slot `y mod (ring length)`), in chunks of
/// [`VERTICAL_CHUNK`] summed in L1: each ring row is read once and `dst` written once. The
/// additions happen in row order.
#[inline(always)]
fn vertical_mean(
    ring: &[f32],
    row_len: usize,
    rows: std::ops::RangeInclusive<usize>,
    k: f32,
    quant: &Quantiser,
    dst: &mut [u16],
) {
    let ring_len = ring.len() / row_len;
    let (lo, last) = (*rows.start(), *rows.end());
    let row = |yy: usize| &ring[(yy % ring_len) * row_len..][..row_len];
    let mut means = [0.0f32; VERTICAL_CHUNK];
    for (c, d) in dst.chunks_mut(VERTICAL_CHUNK).enumerate() {
        let span = c * VERTICAL_CHUNK..c * VERTICAL_CHUNK + d.len();
        let m = &mut means[..d.len()];
        m.copy_from_slice(&row(lo)[span.clone()]);
        for yy in lo + 1..=last {
            for (o, &v) in m.iter_mut().zip(&row(yy)[span.clone()]) {
                *o += v;
            }
        }
        for o in m.iter_mut() {
            *o *= k;
        }
        quant.quantise_row(m, d);
    }
}

/// [`horizontal_row`] compiled for AVX2 when `avx2` (the CPU has it): the same operations on
/// wider registers, so the same results (no fused multiply-adds are introduced).
#[allow(clippy::too_many_arguments)]
#[inline]
fn horizontal_row_fast(
    avx2: bool,
    data: &[f32],
    weights: &[f32],
    w: usize,
    npix: usize,
    n: usize,
    r: usize,
    y: usize,
    cols: std::ops::Range<usize>,
    inv_x: &[f32],
    scratch: &mut HorizontalScratch,
    slot: &mut [f32],
) {
    #[cfg(target_arch = "x86_64")]
    {
        #[target_feature(enable = "avx2")]
        #[allow(clippy::too_many_arguments)]
        unsafe fn with_avx2(
            data: &[f32],
            weights: &[f32],
            w: usize,
            npix: usize,
            n: usize,
            r: usize,
            y: usize,
            cols: std::ops::Range<usize>,
            inv_x: &[f32],
            scratch: &mut HorizontalScratch,
            slot: &mut [f32],
        ) {
            horizontal_row::<true>(data, weights, w, npix, n, r, y, cols, inv_x, scratch, slot)
        }
        if avx2 {
            // SAFETY: the caller detected AVX2 on this CPU ([`crate::cpu::avx2_enabled`]).
            return unsafe {
                with_avx2(data, weights, w, npix, n, r, y, cols, inv_x, scratch, slot)
            };
        }
    }
    let _ = avx2;
    horizontal_row::<false>(data, weights, w, npix, n, r, y, cols, inv_x, scratch, slot)
}

/// Per-task buffers of [`horizontal_row`]: one padded weighted plane row of a tile and the box
/// means of a [`PLANE_GROUP`] of plane rows, all in L1.
struct HorizontalScratch {
    /// The weighted row of the tile's columns and `r` more on each side, zeros where those lie
    /// outside the image: the clipped window's missing pixels add 0.
    padded: Vec<f32>,
    /// The group's box means, plane row after plane row (`PLANE_GROUP · tile`).
    means: Vec<f32>,
}

impl HorizontalScratch {
    fn new(tile: usize, r: usize) -> Self {
        Self {
            padded: vec![0.0; tile + 2 * r],
            means: vec![0.0; PLANE_GROUP * tile],
        }
    }
}

/// Row `y` of every plane, weighted by that row's `weights` (`w` values) and box-summed along
/// the row (mean over the window, clipped at the image's columns), at the columns `cols`, into
/// the pixel-major tile row `slot` (`[x − cols.start][plane]`).
///
/// Each plane row's window is `2r + 1` shifted additions of the padded weighted row, 8
/// columns per AVX2 instruction and exact to `f32` rounding with no running-sum drift (the same
/// additions in the same order whatever the tile); the means of a [`PLANE_GROUP`] of planes are
/// then written transposed, each pixel's group as one contiguous run of `slot` (with `AVX2`,
/// which only a caller compiled for AVX2 may set, 8 pixels' groups at a time by an 8×8
/// transpose in registers).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn horizontal_row<const AVX2: bool>(
    data: &[f32],
    weights: &[f32],
    w: usize,
    npix: usize,
    n: usize,
    r: usize,
    y: usize,
    cols: std::ops::Range<usize>,
    inv_x: &[f32],
    scratch: &mut HorizontalScratch,
    slot: &mut [f32],
) {
    let HorizontalScratch { padded, means } = scratch;
    let tw = cols.len();
    // `padded[i]` is column `cols.start + i − r`: zeros before column 0 and from column `w`.
    let (lo, hi) = (cols.start.saturating_sub(r), (cols.end + r).min(w));
    let lead = r - (cols.start - lo);
    let padded = &mut padded[..tw + 2 * r];
    padded[..lead].fill(0.0);
    padded[lead + hi - lo..].fill(0.0);
    let mut g0 = 0;
    while g0 < n {
        let g = PLANE_GROUP.min(n - g0);
        for j in 0..g {
            let src = &data[(g0 + j) * npix + y * w..][lo..hi];
            for ((o, &c), &wt) in padded[lead..lead + hi - lo]
                .iter_mut()
                .zip(src)
                .zip(&weights[lo..hi])
            {
                *o = c * wt;
            }
            let m = &mut means[j * tw..][..tw];
            m.copy_from_slice(&padded[..tw]);
            for k in 1..=2 * r {
                for (o, &v) in m.iter_mut().zip(&padded[k..k + tw]) {
                    *o += v;
                }
            }
            for (o, &k) in m.iter_mut().zip(&inv_x[cols.clone()]) {
                *o *= k;
            }
        }
        if g == PLANE_GROUP {
            let mut done = 0;
            #[cfg(target_arch = "x86_64")]
            if AVX2 {
                // SAFETY: `AVX2` is set only by the caller compiled for AVX2 after detecting it.
                done = unsafe { transpose_groups_avx2(means, tw, n, g0, slot) };
            }
            // Fixed-size groups, one pixel at a time.
            for (x, px) in slot.chunks_exact_mut(n).enumerate().skip(done) {
                let dst: &mut [f32; PLANE_GROUP] = (&mut px[g0..g0 + PLANE_GROUP])
                    .try_into()
                    .expect("group of PLANE_GROUP planes");
                for (j, o) in dst.iter_mut().enumerate() {
                    *o = means[j * tw + x];
                }
            }
        } else {
            for (x, px) in slot.chunks_exact_mut(n).enumerate() {
                for (j, o) in px[g0..g0 + g].iter_mut().enumerate() {
                    *o = means[j * tw + x];
                }
            }
        }
        g0 += g;
    }
}

/// `slot[x·n + g0 + j] = means[j·w + x]` for the [`PLANE_GROUP`] rows `j` of `means` and the
/// pixels `x` of every whole block of 8: each block is 8 loads, an 8×8 transpose in registers
/// and 8 stores of a pixel's group, instead of 64 scalar loads and stores. Returns the pixels
/// done (a multiple of 8); the caller does the rest.
///
/// # Safety
/// The CPU has AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn transpose_groups_avx2(
    means: &[f32],
    w: usize,
    n: usize,
    g0: usize,
    slot: &mut [f32],
) -> usize {
    use std::arch::x86_64::*;
    const _: () = assert!(PLANE_GROUP == 8, "an 8x8 transpose");
    assert!(means.len() >= PLANE_GROUP * w && slot.len() >= w * n && g0 + PLANE_GROUP <= n);
    let blocks = w / 8;
    let m = means.as_ptr();
    let out = slot.as_mut_ptr();
    for b in 0..blocks {
        let x = b * 8;
        // SAFETY: rows `j < 8` of `means` hold `w` values and `x + 8 ≤ w`; each store writes
        // `slot[(x + k)·n + g0 ..][..8]`, inside `slot` since `x + k < w` and `g0 + 8 ≤ n`
        // (asserted above).
        unsafe {
            let r0 = _mm256_loadu_ps(m.add(x));
            let r1 = _mm256_loadu_ps(m.add(w + x));
            let r2 = _mm256_loadu_ps(m.add(2 * w + x));
            let r3 = _mm256_loadu_ps(m.add(3 * w + x));
            let r4 = _mm256_loadu_ps(m.add(4 * w + x));
            let r5 = _mm256_loadu_ps(m.add(5 * w + x));
            let r6 = _mm256_loadu_ps(m.add(6 * w + x));
            let r7 = _mm256_loadu_ps(m.add(7 * w + x));
            // Interleave pairs of rows, then pairs of pairs, then swap 128-bit halves.
            let t0 = _mm256_unpacklo_ps(r0, r1);
            let t1 = _mm256_unpackhi_ps(r0, r1);
            let t2 = _mm256_unpacklo_ps(r2, r3);
            let t3 = _mm256_unpackhi_ps(r2, r3);
            let t4 = _mm256_unpacklo_ps(r4, r5);
            let t5 = _mm256_unpackhi_ps(r4, r5);
            let t6 = _mm256_unpacklo_ps(r6, r7);
            let t7 = _mm256_unpackhi_ps(r6, r7);
            let u0 = _mm256_shuffle_ps::<0x44>(t0, t2);
            let u1 = _mm256_shuffle_ps::<0xEE>(t0, t2);
            let u2 = _mm256_shuffle_ps::<0x44>(t1, t3);
            let u3 = _mm256_shuffle_ps::<0xEE>(t1, t3);
            let u4 = _mm256_shuffle_ps::<0x44>(t4, t6);
            let u5 = _mm256_shuffle_ps::<0xEE>(t4, t6);
            let u6 = _mm256_shuffle_ps::<0x44>(t5, t7);
            let u7 = _mm256_shuffle_ps::<0xEE>(t5, t7);
            let cols = [
                _mm256_permute2f128_ps::<0x20>(u0, u4),
                _mm256_permute2f128_ps::<0x20>(u1, u5),
                _mm256_permute2f128_ps::<0x20>(u2, u6),
                _mm256_permute2f128_ps::<0x20>(u3, u7),
                _mm256_permute2f128_ps::<0x31>(u0, u4),
                _mm256_permute2f128_ps::<0x31>(u1, u5),
                _mm256_permute2f128_ps::<0x31>(u2, u6),
                _mm256_permute2f128_ps::<0x31>(u3, u7),
            ];
            for (k, c) in cols.into_iter().enumerate() {
                _mm256_storeu_ps(out.add((x + k) * n + g0), c);
            }
        }
    }
    blocks * 8
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

    /// A volume windowed band by band, each band's rows and the rows its windows read given
    /// alone, is the whole volume windowed at once, bit for bit (AVX2 and plain code).
    #[test]
    fn bands_window_like_the_whole_volume() {
        for (w, h, n, r, band) in [
            (13, 40, 11, 2, 8),
            (9, 37, 8, 3, 5),
            (20, 17, 17, 0, 4),
            (7, 30, 3, 5, 9),
            (16, 12, 9, 1, 12),
            (5, 9, 2, 2, 1),
            (TILE_PX + 9, 11, 8, 2, 4),
        ] {
            let data: Vec<f32> = (0..w * h * n)
                .map(|i| ((i * 53) % 17) as f32 * 0.07)
                .collect();
            let weights: Vec<f32> = (0..w * h)
                .map(|i| 1.0 + ((i * 11) % 7) as f32 * 0.4)
                .collect();
            let quant = Quantiser::new(largest_weighted(&data, &weights, w, h, n), 0.3, 8);
            for scalar in [false, true] {
                crate::cpu::force_scalar(scalar);
                let mut whole = vec![0u16; data.len()];
                window_to_levels(
                    &data,
                    &weights,
                    w,
                    h,
                    n,
                    r,
                    &quant,
                    &mut whole,
                    &Monitor::noop(),
                )
                .unwrap();
                let mut banded = vec![u16::MAX; data.len()];
                for y0 in (0..h).step_by(band) {
                    let own = y0..(y0 + band).min(h);
                    let read = own.start.saturating_sub(r)..(own.end + r).min(h);
                    let part: Vec<f32> = (0..n)
                        .flat_map(|i| &data[(i * h + read.start) * w..(i * h + read.end) * w])
                        .copied()
                        .collect();
                    window_rows_to_levels(
                        &part,
                        read,
                        &weights,
                        w,
                        h,
                        n,
                        r,
                        own.clone(),
                        &quant,
                        &mut banded[own.start * w * n..own.end * w * n],
                        &Monitor::noop(),
                    )
                    .unwrap();
                }
                crate::cpu::force_scalar(false);
                assert_eq!(banded, whole, "{w}x{h}x{n} r={r} bands of {band}");
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
            // Several column tiles, the last one partial, windows reaching across tiles.
            (2 * TILE_PX + 45, 6, 9, 3),
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
                window_to_levels(&data, wts, w, h, n, r, &quant, &mut out, &Monitor::noop())
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
                window_to_levels(&data, wts, w, h, n, r, &quant, &mut plain, &Monitor::noop())
                    .unwrap();
                let plain_largest = largest_weighted(&data, wts, w, h, n);
                crate::cpu::force_scalar(false);
                assert_eq!(plain, out);
                assert_eq!(plain_largest, largest);
            }
        }
    }
}
