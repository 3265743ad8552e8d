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

/// Rows per rayon task. Each task also filters the `r` rows above and below its band, so taller
/// bands waste less; 32 rows leave several tasks per strip for 2+ cores.
const BAND_ROWS: usize = 32;

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
/// a contiguous, vectorised sum over planes. Horizontal sums run in `f64` (running sums along a
/// row); the vertical sum adds `2r + 1` `f32` values, 64 at a time in L1, which are quantised
/// there: the `f32` means never reach memory.
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
    let npix = w * h;
    assert_eq!(data.len(), npix * n, "volume size");
    assert_eq!(out.len(), data.len(), "output size");
    assert!(weights.is_empty() || weights.len() == npix, "weights size");
    if npix == 0 || n == 0 {
        return Ok(());
    }
    monitor.checkpoint()?;
    // 1 / (pixels of the clipped window) along each axis: a multiply per voxel, not a divide.
    let inv_counts = |len: usize| -> Vec<f64> {
        (0..len)
            .map(|i| 1.0 / ((i + r + 1).min(len) - i.saturating_sub(r)) as f64)
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
    out.par_chunks_mut(BAND_ROWS * row_len)
        .enumerate()
        .for_each_init(
            || vec![0.0f32; ring_len * row_len],
            |ring, (band, out_band)| {
                let y0 = band * BAND_ROWS;
                let y1 = (y0 + BAND_ROWS).min(h);
                // The next row to filter into the ring.
                let mut next = y0.saturating_sub(r);
                for y in y0..y1 {
                    let last = (y + r).min(h - 1);
                    while next <= last {
                        let slot = &mut ring[(next % ring_len) * row_len..][..row_len];
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
                            next,
                            &inv_x,
                            slot,
                        );
                        next += 1;
                    }
                    let dst = &mut out_band[(y - y0) * row_len..][..row_len];
                    let lo = y.saturating_sub(r);
                    let k = inv_y[y] as f32;
                    vertical_mean_fast(avx2, ring, row_len, lo..=last, k, quant, dst);
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
    inv_x: &[f64],
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
            inv_x: &[f64],
            slot: &mut [f32],
        ) {
            horizontal_row(data, weights, w, npix, n, r, y, inv_x, slot)
        }
        if avx2 {
            // SAFETY: the caller detected AVX2 on this CPU ([`crate::cpu::avx2_enabled`]).
            return unsafe { with_avx2(data, weights, w, npix, n, r, y, inv_x, slot) };
        }
    }
    let _ = avx2;
    horizontal_row(data, weights, w, npix, n, r, y, inv_x, slot)
}

/// Row `y` of every plane, weighted by that row's `weights` (`w` values) and box-summed along
/// the row (mean over the clipped window), into the pixel-major row `slot` (`[x][plane]`).
/// Planes go in groups of
/// [`PLANE_GROUP`] with one running `f64` sum per plane: independent lanes, so the loop over `x`
/// vectorises across the group's planes and writes each pixel's group contiguously.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn horizontal_row(
    data: &[f32],
    weights: &[f32],
    w: usize,
    npix: usize,
    n: usize,
    r: usize,
    y: usize,
    inv_x: &[f64],
    slot: &mut [f32],
) {
    let mut g0 = 0;
    while g0 < n {
        let g = PLANE_GROUP.min(n - g0);
        let rows: [&[f32]; PLANE_GROUP] =
            std::array::from_fn(|j| &data[(g0 + j.min(g - 1)) * npix + y * w..][..w]);
        let mut acc = [0.0f64; PLANE_GROUP];
        // The first window, up to but excluding column r.
        for x in 0..r.min(w) {
            for j in 0..PLANE_GROUP {
                acc[j] += f64::from(rows[j][x] * weights[x]);
            }
        }
        for (x, px) in slot.chunks_exact_mut(n).enumerate() {
            if x + r < w {
                let xi = x + r;
                for j in 0..PLANE_GROUP {
                    acc[j] += f64::from(rows[j][xi] * weights[xi]);
                }
            }
            let k = inv_x[x];
            for (j, o) in px[g0..g0 + g].iter_mut().enumerate() {
                *o = (acc[j] * k) as f32;
            }
            if x >= r {
                let xo = x - r;
                for j in 0..PLANE_GROUP {
                    acc[j] -= f64::from(rows[j][xo] * weights[xo]);
                }
            }
        }
        g0 += g;
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
