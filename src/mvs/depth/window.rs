//! Optional per-plane box aggregation of the raw matching cost before SGM.
//!
//! The pixel-wise L1 cost of Eq. 3.1 / 3.7 is noisy, more so for the dehazing volume, whose
//! residuals are the camera noise amplified by `1/t` (Eq. 3.5). A small box mean over each
//! plane (the classical "window" of block matching) averages that noise out before the
//! semi-global smoothness term sees it, at the price of slightly fattened depth edges.

use rayon::prelude::*;

use crate::error::Result;
use crate::monitor::Monitor;

/// Replaces each plane of a `[plane][y][x]` volume (`w·h` values per plane) by its box mean
/// over a `(2r+1)²` window, clipped at the image border (the mean is over the pixels inside).
/// `r = 0` leaves the volume untouched. Separable running sums: `O(1)` per voxel, one scratch
/// row buffer per worker, no per-voxel allocation.
pub fn box_filter_planes(
    data: &mut [f32],
    w: usize,
    h: usize,
    r: usize,
    monitor: &Monitor,
) -> Result<()> {
    if r == 0 || w == 0 || h == 0 {
        return Ok(());
    }
    monitor.checkpoint()?;
    // 1 / (pixels of the clipped window) along each axis: a multiply per voxel, not a divide.
    let inv_counts = |n: usize| -> Vec<f64> {
        (0..n)
            .map(|i| 1.0 / ((i + r + 1).min(n) - i.saturating_sub(r)) as f64)
            .collect()
    };
    let (inv_x, inv_y) = (inv_counts(w), inv_counts(h));
    data.par_chunks_mut(w * h).for_each_init(
        || (vec![0.0f32; w * h], vec![0.0f64; w + 1], vec![0.0f64; w]),
        |(tmp, prefix, colsum), plane| {
            // Horizontal pass into `tmp`, then vertical pass back into `plane`. Sums in f64 so
            // long rows and columns do not lose the small differences that make the cost curve.
            for (src, dst) in plane.chunks_exact(w).zip(tmp.chunks_exact_mut(w)) {
                prefix[0] = 0.0;
                for (i, &v) in src.iter().enumerate() {
                    prefix[i + 1] = prefix[i] + f64::from(v);
                }
                for (x, d) in dst.iter_mut().enumerate() {
                    let lo = x.saturating_sub(r);
                    let hi = (x + r + 1).min(w);
                    *d = ((prefix[hi] - prefix[lo]) * inv_x[x]) as f32;
                }
            }
            // Vertical: running column sums over whole rows (contiguous, vectorised over x)
            // instead of a prefix down each column (a stride of `w` per step).
            colsum.iter_mut().for_each(|c| *c = 0.0);
            for row in tmp.chunks_exact(w).take(r.min(h - 1) + 1) {
                for (c, &v) in colsum.iter_mut().zip(row) {
                    *c += f64::from(v);
                }
            }
            for y in 0..h {
                let k = inv_y[y];
                for (o, &c) in plane[y * w..(y + 1) * w].iter_mut().zip(colsum.iter()) {
                    *o = (c * k) as f32;
                }
                if y + r + 1 < h {
                    let add = &tmp[(y + r + 1) * w..(y + r + 2) * w];
                    for (c, &v) in colsum.iter_mut().zip(add) {
                        *c += f64::from(v);
                    }
                }
                if y >= r {
                    let sub = &tmp[(y - r) * w..(y - r + 1) * w];
                    for (c, &v) in colsum.iter_mut().zip(sub) {
                        *c -= f64::from(v);
                    }
                }
            }
        },
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_mean_matches_direct_sum() {
        for (w, h, r) in [(7, 5, 2), (9, 2, 3), (3, 11, 1), (1, 1, 4), (16, 13, 5)] {
            check_box_mean(w, h, r);
        }
    }

    fn check_box_mean(w: usize, h: usize, r: usize) {
        let orig: Vec<f32> = (0..2 * w * h)
            .map(|i| ((i * 37) % 11) as f32 * 0.1)
            .collect();
        let mut data = orig.clone();
        box_filter_planes(&mut data, w, h, r, &Monitor::noop()).unwrap();
        for p in 0..2 {
            for y in 0..h {
                for x in 0..w {
                    let (mut s, mut n) = (0.0, 0);
                    for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
                        for xx in x.saturating_sub(r)..(x + r + 1).min(w) {
                            s += orig[(p * h + yy) * w + xx];
                            n += 1;
                        }
                    }
                    let got = data[(p * h + y) * w + x];
                    assert!(
                        (got - s / n as f32).abs() < 1e-5,
                        "{got} vs {}",
                        s / n as f32
                    );
                }
            }
        }
    }
}
