//! Edge-preserving bilateral pre-filter (§5.4.1: "to compensate for high frequency noise").

use rayon::prelude::*;

use super::params::BilateralParams;
use super::tukey::{mad_sigma_in_place, scale_floor};

/// Bilateral filter of a one-channel `width × height` image into `out`.
///
/// The range σ is `sigma_range_rel` times the image's robust noise σ ([`robust_noise_sigma`]),
/// so the filter behaves the same whatever the amplitude units and only averages differences of
/// noise size: object edges are kept. (Scaling by the spread of the image *values* instead made
/// σ_r comparable to object/background steps on simulated fog, blurring object signal into the
/// background, which the IRLS then declared outlier and drifted in.)
/// Out-of-image taps are dropped and the remaining weights renormalised.
pub fn bilateral_filter(
    src: &[f32],
    width: usize,
    height: usize,
    params: &BilateralParams,
    out: &mut [f32],
) {
    let magnitude = src.iter().fold(0.0f64, |m, &v| m.max((v as f64).abs()));
    let spread = robust_noise_sigma(src, width).max(scale_floor(magnitude));
    let sigma_r = (params.sigma_range_rel as f64 * spread) as f32;
    let inv_2sr2 = 1.0 / (2.0 * sigma_r * sigma_r);
    let r = params.radius as isize;
    let d = 2 * params.radius + 1;
    let inv_2ss2 = 1.0 / (2.0 * params.sigma_space_px * params.sigma_space_px);
    let spatial: Vec<f32> = (0..d * d)
        .map(|k| {
            let dy = (k / d) as isize - r;
            let dx = (k % d) as isize - r;
            (-((dx * dx + dy * dy) as f32) * inv_2ss2).exp()
        })
        .collect();
    let (w, h) = (width as isize, height as isize);
    out.par_chunks_mut(width).enumerate().for_each(|(y, row)| {
        let y = y as isize;
        for (x, o) in row.iter_mut().enumerate() {
            let x = x as isize;
            let centre = src[(y * w + x) as usize];
            let (mut num, mut den) = (0.0f32, 0.0f32);
            for dy in -r..=r {
                let yy = y + dy;
                if yy < 0 || yy >= h {
                    continue;
                }
                let srow = &src[(yy * w) as usize..((yy + 1) * w) as usize];
                let krow = &spatial[((dy + r) as usize) * d..((dy + r) as usize + 1) * d];
                for dx in -r..=r {
                    let xx = x + dx;
                    if xx < 0 || xx >= w {
                        continue;
                    }
                    let v = srow[xx as usize];
                    let diff = v - centre;
                    let wgt = krow[(dx + r) as usize] * (-diff * diff * inv_2sr2).exp();
                    num += wgt * v;
                    den += wgt;
                }
            }
            // The centre tap has weight 1, so den ≥ 1.
            *o = num / den;
        }
    });
}

/// Robust pixel-noise σ: 1.4826·MAD of horizontal neighbour differences, divided by √2 (a
/// difference of two independent samples has twice the variance). Smooth scene structure and the
/// few differences that straddle edges barely move the median, so this measures noise, not the
/// image's dynamic range.
pub fn robust_noise_sigma(src: &[f32], width: usize) -> f64 {
    let mut d: Vec<f64> = src
        .chunks_exact(width.max(1))
        .flat_map(|row| row.windows(2).map(|p| (p[1] - p[0]) as f64))
        .collect();
    mad_sigma_in_place(&mut d).unwrap_or(0.0) / std::f64::consts::SQRT_2
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn keeps_constant_and_step_smooths_noise() {
        let p = BilateralParams::default();
        let c = vec![3.5f32; 16 * 10];
        let mut out = vec![0.0; 16 * 10];
        bilateral_filter(&c, 16, 10, &p, &mut out);
        assert!(out.iter().all(|v| (v - 3.5).abs() < 1e-5));
        // Gentle ramp with Gaussian noise (σ = 0.05) plus a step of 10 from column 12 on.
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let (w, h) = (32, 24);
        let noise: Vec<f32> = (0..w * h)
            .map(|_| {
                let u1: f32 = 1.0 - rng.random::<f32>();
                let u2: f32 = rng.random();
                0.05 * (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
            })
            .collect();
        let clean = |x: usize| x as f32 * 0.1 + if x >= 12 { 10.0 } else { 0.0 };
        let img: Vec<f32> = (0..w * h).map(|i| clean(i % w) + noise[i]).collect();
        // An edge-preserving setting that smooths noise: σ_r = 2σ_noise (the default 0.5 is
        // deliberately gentle).
        let p = BilateralParams {
            sigma_range_rel: 2.0,
            ..p
        };
        let mut out = vec![0.0; w * h];
        bilateral_filter(&img, w, h, &p, &mut out);
        let (mut e_in, mut e_out, mut n) = (0.0, 0.0, 0.0);
        for y in 2..h - 2 {
            for x in (2..9).chain(15..w - 2) {
                let i = y * w + x;
                e_in += (img[i] - clean(x)).powi(2);
                e_out += (out[i] - clean(x)).powi(2);
                n += 1.0;
            }
            // The step survives: pixels beside the edge stay on their side.
            assert!(
                (out[y * w + 11] - clean(11)).abs() < 0.15,
                "{}",
                out[y * w + 11]
            );
            assert!(
                (out[y * w + 12] - clean(12)).abs() < 0.15,
                "{}",
                out[y * w + 12]
            );
        }
        let (rin, rout) = ((e_in / n).sqrt(), (e_out / n).sqrt());
        assert!(rout < 0.9 * rin, "noise {rin} -> {rout}");
        assert!((robust_noise_sigma(&img, w) - 0.05).abs() < 0.02);
    }
}
