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
    let spatial = spatial_kernel(params);
    let rows = Rows::new(src, width, height, params, &spatial);
    out.par_chunks_mut(width).enumerate().for_each_init(
        || vec![0.0f32; width],
        |den, (y, row)| rows.filter(y, den, row),
    );
}

/// The filter's input and kernel, shared by every row.
#[derive(Clone, Copy)]
struct Rows<'a> {
    src: &'a [f32],
    width: usize,
    height: usize,
    radius: usize,
    /// The spatial kernel, `(2r+1)²` taps, row by row.
    spatial: &'a [f32],
    /// 1 / (2σ_r²).
    inv_2sr2: f32,
}

/// The spatial kernel of `params`: `(2r+1)²` taps, row by row.
fn spatial_kernel(params: &BilateralParams) -> Vec<f32> {
    let r = params.radius as isize;
    let d = 2 * params.radius + 1;
    let inv_2ss2 = 1.0 / (2.0 * params.sigma_space_px * params.sigma_space_px);
    (0..d * d)
        .map(|k| {
            let dy = (k / d) as isize - r;
            let dx = (k % d) as isize - r;
            (-((dx * dx + dy * dy) as f32) * inv_2ss2).exp()
        })
        .collect()
}

impl<'a> Rows<'a> {
    /// The filter of `src` with `params` and their `spatial` kernel ([`spatial_kernel`]).
    fn new(
        src: &'a [f32],
        width: usize,
        height: usize,
        params: &BilateralParams,
        spatial: &'a [f32],
    ) -> Self {
        let magnitude = src.iter().fold(0.0f64, |m, &v| m.max((v as f64).abs()));
        let spread = robust_noise_sigma(src, width).max(scale_floor(magnitude));
        let sigma_r = (params.sigma_range_rel as f64 * spread) as f32;
        Rows {
            src,
            width,
            height,
            radius: params.radius,
            spatial,
            inv_2sr2: 1.0 / (2.0 * sigma_r * sigma_r),
        }
    }
    /// Filters row `y` into `out`, with `den` (one row) as scratch; through a copy compiled for
    /// AVX2 where the CPU has it (the same operations on wider registers, so the same results).
    fn filter(self, y: usize, den: &mut [f32], out: &mut [f32]) {
        #[cfg(target_arch = "x86_64")]
        {
            #[target_feature(enable = "avx2")]
            unsafe fn with_avx2(rows: Rows, y: usize, den: &mut [f32], out: &mut [f32]) {
                rows.filter_generic(y, den, out)
            }
            if crate::cpu::avx2_enabled() {
                // SAFETY: the CPU has AVX2.
                return unsafe { with_avx2(self, y, den, out) };
            }
        }
        self.filter_generic(y, den, out)
    }

    /// The body of [`Rows::filter`]. Tap by tap, each over the whole row, so that the range
    /// kernel's exponential runs across contiguous pixels and vectorises; every pixel still sums
    /// its taps in the window's row-major order. Out-of-image taps are skipped.
    #[inline(always)]
    fn filter_generic(self, y: usize, den: &mut [f32], out: &mut [f32]) {
        let Rows {
            src,
            width: w,
            height: h,
            radius: r,
            spatial,
            inv_2sr2,
        } = self;
        let d = 2 * r + 1;
        let centre = &src[y * w..(y + 1) * w];
        // `out` holds the numerator until the last step.
        out.fill(0.0);
        den.fill(0.0);
        for ky in 0..d {
            let Some(yy) = (y + ky).checked_sub(r).filter(|&yy| yy < h) else {
                continue;
            };
            let srow = &src[yy * w..(yy + 1) * w];
            for kx in 0..d {
                // Output pixels x whose tap x + kx − r lies inside the row.
                let (x0, x1) = (r.saturating_sub(kx), (w + r).saturating_sub(kx).min(w));
                if x0 >= x1 {
                    continue;
                }
                let k = spatial[ky * d + kx];
                let taps = &srow[x0 + kx - r..x1 + kx - r];
                for (((num, dn), &v), &c) in out[x0..x1]
                    .iter_mut()
                    .zip(&mut den[x0..x1])
                    .zip(taps)
                    .zip(&centre[x0..x1])
                {
                    let diff = v - c;
                    let wgt = k * exp_neg(diff * diff * inv_2sr2);
                    *num += wgt * v;
                    *dn += wgt;
                }
            }
        }
        // The centre tap has weight 1, so den ≥ 1.
        for (o, &dn) in out.iter_mut().zip(den.iter()) {
            *o /= dn;
        }
    }
}

/// e^{−t} for t ≥ 0 in plain f32 arithmetic, so that it vectorises: Cody–Waite reduction by
/// ln 2 and Cephes' degree-5 polynomial for `expf` (within 2 units in the last place of the
/// exact value, tested), NaN for NaN, and 0 where e^{−t} falls below f32's normal range (t > 87). The
/// bilateral filter takes 25 of these per pixel and channel; the library call kept it from
/// vectorising and was most of a 512 × 424 frame's pre-filter.
#[inline(always)]
fn exp_neg(t: f32) -> f32 {
    // 1.5·2²³: adding it rounds a value of magnitude below 2²² to an integer, which its low
    // mantissa bits then hold.
    const ROUND: f32 = 12_582_912.0;
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    let u = -t.min(87.0);
    let shifted = u * std::f32::consts::LOG2_E + ROUND;
    let n = shifted.to_bits() as i32 - ROUND.to_bits() as i32;
    let nf = shifted - ROUND;
    let f = (u - nf * LN2_HI) - nf * LN2_LO;
    let p = ((((1.987_569_2e-4 * f + 1.398_199_9e-3) * f + 8.333_452e-3) * f + 4.166_579_6e-2) * f
        + 1.666_666_5e-1)
        * f
        + 0.5;
    let e = p * (f * f) + f + 1.0;
    // n ≥ −126, so 2ⁿ is a normal number.
    let scale = f32::from_bits(((n + 127) as u32) << 23);
    // The clamp above would turn a NaN into e⁻⁸⁷.
    if t.is_nan() {
        t
    } else if t > 87.0 {
        0.0
    } else {
        e * scale
    }
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
    fn exp_neg_matches_exp() {
        let mut worst = 0.0f64;
        for i in 0..=1_000_000 {
            let t = i as f32 * 8.7e-5;
            let exact = (-(t as f64)).exp();
            let got = exp_neg(t) as f64;
            worst = worst.max((got - exact).abs() / exact);
        }
        // Two units in the last place of f32 (2⁻²³ ≈ 1.2e-7 each).
        assert!(worst < 2.4e-7, "relative error {worst}");
        assert_eq!(exp_neg(0.0), 1.0);
        assert_eq!(exp_neg(88.0), 0.0);
        assert_eq!(exp_neg(f32::INFINITY), 0.0);
        assert!(exp_neg(f32::NAN).is_nan());
        assert!((exp_neg(86.9) as f64 / (-(86.9f32 as f64)).exp() - 1.0).abs() < 1e-6);
    }

    /// The filter as it is defined: every pixel's window, tap by tap, with the library's exp.
    fn reference_filter(src: &[f32], w: usize, h: usize, p: &BilateralParams) -> Vec<f32> {
        let magnitude = src.iter().fold(0.0f64, |m, &v| m.max((v as f64).abs()));
        let spread = robust_noise_sigma(src, w).max(scale_floor(magnitude));
        let sigma_r = p.sigma_range_rel as f64 * spread;
        let r = p.radius as isize;
        let mut out = vec![0.0; w * h];
        for y in 0..h as isize {
            for x in 0..w as isize {
                let c = src[(y * w as isize + x) as usize] as f64;
                let (mut num, mut den) = (0.0f64, 0.0f64);
                for dy in -r..=r {
                    for dx in -r..=r {
                        let (yy, xx) = (y + dy, x + dx);
                        if yy < 0 || yy >= h as isize || xx < 0 || xx >= w as isize {
                            continue;
                        }
                        let v = src[(yy * w as isize + xx) as usize] as f64;
                        let s2 = (dx * dx + dy * dy) as f64;
                        let ss = p.sigma_space_px as f64;
                        let wgt = (-s2 / (2.0 * ss * ss)
                            - (v - c).powi(2) / (2.0 * sigma_r * sigma_r))
                            .exp();
                        num += wgt * v;
                        den += wgt;
                    }
                }
                out[(y * w as isize + x) as usize] = (num / den) as f32;
            }
        }
        out
    }

    #[test]
    fn matches_the_definition_and_the_plain_loop() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let (w, h) = (37, 23);
        // A ramp with a step and noise, so that the range kernel spans most of its values.
        let img: Vec<f32> = (0..w * h)
            .map(|i| {
                let x = i % w;
                0.02 * x as f32 + if x > 18 { 3.0 } else { 0.0 } + 0.1 * rng.random::<f32>()
            })
            .collect();
        for radius in [1, 2, 4] {
            let p = BilateralParams {
                radius,
                sigma_range_rel: 2.0,
                ..BilateralParams::default()
            };
            let mut out = vec![0.0; w * h];
            bilateral_filter(&img, w, h, &p, &mut out);
            let reference = reference_filter(&img, w, h, &p);
            for (a, b) in out.iter().zip(&reference) {
                assert!((a - b).abs() <= 2e-6 * b.abs().max(1.0), "{a} vs {b}");
            }
            // Row by row on this thread, whose plain loops the test can force.
            crate::cpu::force_scalar(true);
            let spatial = spatial_kernel(&p);
            let rows = Rows::new(&img, w, h, &p, &spatial);
            let mut plain = vec![0.0; w * h];
            let mut den = vec![0.0; w];
            for (y, row) in plain.chunks_mut(w).enumerate() {
                rows.filter(y, &mut den, row);
            }
            crate::cpu::force_scalar(false);
            assert_eq!(
                out.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                plain.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                "radius {radius}"
            );
        }
    }

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
