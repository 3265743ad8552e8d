//! Optional edge-aware post-filter: a guided, confidence-weighted median of inverse depth.
//!
//! Each output pixel is the weighted median of the inverse depths in a `(2r+1)²` window with
//! weights `w_q = exp(−‖I_q − I_p‖₁ / (C·σ)) · (κ_q + ε)`: neighbours of similar colour (likely
//! the same surface) and with confident estimates dominate, so isolated mismatches are replaced
//! while depth edges that coincide with image edges are kept. A median (not a mean) never
//! invents depths between two surfaces. `ε = 0.01` keeps the weights positive where every
//! neighbour has zero confidence.

use rayon::prelude::*;

/// Weighted median filter of `inv` (`w×h`, row-major) guided by `guide` (`w×h×c`, interleaved)
/// and weighted by `confidence` (`w×h`). `radius` in pixels, `sigma` in pixel-value units per
/// channel (`> 0`).
#[allow(clippy::too_many_arguments)]
pub fn weighted_median(
    inv: &[f32],
    confidence: &[f32],
    guide: &[f32],
    c: usize,
    w: usize,
    h: usize,
    radius: usize,
    sigma: f32,
) -> Vec<f32> {
    let mut out = vec![0.0f32; w * h];
    let k = (2 * radius + 1) * (2 * radius + 1);
    let inv_scale = 1.0 / (c as f32 * sigma.max(1e-6));
    out.par_chunks_mut(w).enumerate().for_each_init(
        || Vec::<(f32, f32)>::with_capacity(k),
        |buf, (y, row)| {
            for (x, o) in row.iter_mut().enumerate() {
                buf.clear();
                let gp = &guide[(y * w + x) * c..][..c];
                let mut total = 0.0f32;
                for yy in y.saturating_sub(radius)..(y + radius + 1).min(h) {
                    for xx in x.saturating_sub(radius)..(x + radius + 1).min(w) {
                        let q = yy * w + xx;
                        let gq = &guide[q * c..][..c];
                        let d: f32 = gp.iter().zip(gq).map(|(a, b)| (a - b).abs()).sum();
                        let wt = (-d * inv_scale).exp() * (confidence[q] + 0.01);
                        total += wt;
                        buf.push((inv[q], wt));
                    }
                }
                buf.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
                let half = 0.5 * total;
                let mut acc = 0.0f32;
                *o = inv[y * w + x];
                for &(v, wt) in buf.iter() {
                    acc += wt;
                    if acc >= half {
                        *o = v;
                        break;
                    }
                }
            }
        },
    );
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn removes_outlier_keeps_edge() {
        let (w, h) = (9, 9);
        // Two surfaces split at x = 4.5 in colour and inverse depth, plus one outlier.
        let mut inv: Vec<f32> = (0..w * h)
            .map(|i| if i % w < 5 { 0.2 } else { 0.5 })
            .collect();
        inv[4 * w + 2] = 0.9;
        let guide: Vec<f32> = (0..w * h)
            .map(|i| if i % w < 5 { 0.1 } else { 0.8 })
            .collect();
        let conf = vec![0.5; w * h];
        let out = weighted_median(&inv, &conf, &guide, 1, w, h, 2, 0.05);
        assert_eq!(out[4 * w + 2], 0.2);
        for y in 0..h {
            assert_eq!(out[y * w + 4], 0.2);
            assert_eq!(out[y * w + 5], 0.5);
        }
    }
}
