//! Pixels beside the objects that the scatter alone does not explain well enough to call them
//! background: the mask's "uncertain" value.
//!
//! The IRLS calls a pixel object when its residual against the scattering estimate is an
//! outlier (Algorithm 2), and the thin-structure check (`tof::irls::THIN_ROUNDS`) claims dim
//! strips whose 3 × 3 window is coherent. What neither can claim is a part whose direct return
//! is within a few noise σ of the fog: a panel seen edge-on in thick fog, the first column of an
//! object beside a nearer occluder, a pixel that the object's edge covers only in part. On the
//! simulated obstacles frames (docs/accuracy.md) these pixels return 1.5–4 σ against the true
//! scatter, so calling them object would invent objects in the noise; calling them background
//! gives them the wall's depth, metres too far, which for a robot is an obstacle it does not see.
//!
//! Such a pixel is reported as neither. Beside the objects (within [`REACH`] pixels, where the
//! IRLS held the background out of the scatter's fit, so the estimate does not follow them), a
//! background pixel is *uncertain* when the raw phasor less the scatter estimate is larger than
//! the noise allows for background, judged two ways:
//! - on its own: `‖r_i‖ / σ_i >` [`PIXEL_THRESHOLD`];
//! - along a line: for one of four orientations (rows, columns, both diagonals), the coherent
//!   sum of the residuals over [`LINE_LENGTH`] consecutive pixels of the line through it, less
//!   the object pixels, `‖Σ r_j / σ_j‖ / √N >` [`LINE_THRESHOLD`]; the pixel may sit anywhere
//!   in those pixels, so that a strip's ends count as its middle does. Thin structures are
//!   lines: a pole, a panel's edge, the rim beside an occluder. Seven pixels of a strip at
//!   2 σ each sum to 5.3.
//!
//! and it is 8-connected to an object through other uncertain pixels (hysteresis, as in Canny's
//! edge linking): a dim part belongs to an object next to it; an isolated noise pixel does not.
//! The raw phasor is judged, not the bilateral-filtered one the IRLS sees: the filter averages a
//! one-pixel strip with the background around it, and would hide it.

use rayon::prelude::*;

use crate::tof::noise_model::NoiseModel;

/// How far from an object (pixels, Chebyshev distance) a background pixel may be uncertain:
/// 3, the width of the band that the IRLS holds out of its last scatter fit
/// (`tof::irls::HELD_OUT_RING`), so that every pixel judged is judged against a scatter that
/// did not follow it.
pub const REACH: usize = 3;

/// A pixel alone is uncertain above 2.5 noise σ: pure noise (two phasor components, `‖r‖/σ`
/// Rayleigh) exceeds it at 4.4 % of the pixels, which the hysteresis limits to those touching
/// an object.
pub const PIXEL_THRESHOLD: f64 = 2.5;

/// A line is uncertain above 4: pure noise exceeds it in one window at 0.03 % of the pixels
/// (χ² with two degrees of freedom); over the 28 windows of [`LINE_LENGTH`] pixels through a
/// pixel, which overlap, at 0.8 % (measured, `pure_noise_rarely_makes_a_line`).
pub const LINE_THRESHOLD: f64 = 4.0;

/// Pixels of the line windows: 7.
pub const LINE_LENGTH: usize = 7;

/// Fewest non-object pixels a line must hold to be judged.
const MIN_LINE: usize = 3;

/// Fewest pixels of an object (8-connected) that uncertain pixels may extend: 4. A smaller
/// one is no part of a structure but an outlier of the noise or of the scatter model's misfit
/// (at the corners of a frame, where the model misfits most), and growing from it would surround
/// a misfit with more of the same.
pub const MIN_OBJECT_PIXELS: usize = 4;

/// The uncertain pixels of a frame. `raw_re`/`raw_im` are the raw phasor, `scatter_re`/
/// `scatter_im` the scattering estimate, `object` the mask, all `width` wide. `border` is the
/// width of the image border left alone (`tof::irls::thin_border_band`: where the illuminator's
/// beam falls off, the scatter model misfits the background by 2–4 σ over a few rows). Without
/// a noise model there is no scale to judge by, and no pixel is uncertain.
#[allow(clippy::too_many_arguments)]
pub fn uncertain_pixels(
    raw_re: &[f32],
    raw_im: &[f32],
    scatter_re: &[f64],
    scatter_im: &[f64],
    object: &[bool],
    noise: Option<&NoiseModel>,
    width: usize,
    border: usize,
) -> Vec<bool> {
    let n = object.len();
    let Some(noise) = noise else {
        return vec![false; n];
    };
    let r = normalised_residuals(raw_re, raw_im, scatter_re, scatter_im, noise);
    let near = dilate(object, width, REACH);
    let h = n / width.max(1);
    let inside = |j: usize| {
        let (x, y) = (j % width, j / width);
        x >= border && y >= border && x + border < width && y + border < h
    };
    let candidates: Vec<usize> = (0..n)
        .filter(|&j| near[j] && !object[j] && inside(j))
        .collect();
    let line = line_statistic(&r, object, width, &candidates);
    let mut passes = vec![false; n];
    for (&j, &t) in candidates.iter().zip(&line) {
        passes[j] = r[j][0].hypot(r[j][1]) > PIXEL_THRESHOLD || t > LINE_THRESHOLD;
    }
    let seed = large_components(object, width, MIN_OBJECT_PIXELS);
    grow_from(&seed, object, width, |j| passes[j])
}

/// Per pixel, the raw phasor less the scatter, divided by the noise σ (per component) at the
/// raw brightness.
pub fn normalised_residuals(
    raw_re: &[f32],
    raw_im: &[f32],
    scatter_re: &[f64],
    scatter_im: &[f64],
    noise: &NoiseModel,
) -> Vec<[f64; 2]> {
    (raw_re, raw_im, scatter_re, scatter_im)
        .into_par_iter()
        .map(|(&re, &im, &sr, &si)| {
            let (re, im) = (f64::from(re), f64::from(im));
            // Amplitudes are bounded (`crate::tof::AMPLITUDE_RANGE`): no overflow to guard
            // against with `hypot`, which took most of this pass.
            let s = noise
                .sigma((re * re + im * im).sqrt())
                .max(f64::MIN_POSITIVE);
            [(re - sr) / s, (im - si) / s]
        })
        .collect()
}

/// For each of `pixels`, the largest `‖Σ r_j‖ / √N` over the windows of [`LINE_LENGTH`]
/// consecutive pixels that hold it, along rows, columns and both diagonals, counting the N
/// pixels of a window that are not `object` (0 where no window counts [`MIN_LINE`]). On pure
/// noise of unit σ each window's value squared is χ² with two degrees of freedom.
pub fn line_statistic(r: &[[f64; 2]], object: &[bool], width: usize, pixels: &[usize]) -> Vec<f64> {
    let n = r.len();
    let (w, h) = (width as isize, (n / width.max(1)) as isize);
    let len = LINE_LENGTH as isize;
    const ORIENTATIONS: [(isize, isize); 4] = [(1, 0), (0, 1), (1, 1), (1, -1)];
    pixels
        .par_iter()
        .map(|&i| {
            let (x, y) = ((i % width) as isize, (i / width) as isize);
            let mut best = 0.0f64;
            for (dx, dy) in ORIENTATIONS {
                // The window's first pixel runs from len − 1 steps back to the pixel itself.
                for start in (1 - len)..=0 {
                    let (mut s, mut count) = ([0.0; 2], 0usize);
                    for k in start..start + len {
                        let (xx, yy) = (x + k * dx, y + k * dy);
                        if xx < 0 || yy < 0 || xx >= w || yy >= h {
                            continue;
                        }
                        let j = (yy * w + xx) as usize;
                        if object[j] {
                            continue;
                        }
                        s[0] += r[j][0];
                        s[1] += r[j][1];
                        count += 1;
                    }
                    if count >= MIN_LINE {
                        best = best.max(s[0].hypot(s[1]) / (count as f64).sqrt());
                    }
                }
            }
            best
        })
        .collect()
}

/// `mask` grown by `reach` pixels in Chebyshev distance (a square structuring element, applied
/// as a row pass and a column pass).
pub fn dilate(mask: &[bool], width: usize, reach: usize) -> Vec<bool> {
    let n = mask.len();
    let h = n / width.max(1);
    if reach == 0 || n == 0 {
        return mask.to_vec();
    }
    let mut rows = vec![false; n];
    rows.par_chunks_mut(width).enumerate().for_each(|(y, row)| {
        let src = &mask[y * width..(y + 1) * width];
        for (x, o) in row.iter_mut().enumerate() {
            let (a, b) = (x.saturating_sub(reach), (x + reach + 1).min(width));
            *o = src[a..b].contains(&true);
        }
    });
    let mut out = vec![false; n];
    out.par_chunks_mut(width).enumerate().for_each(|(y, row)| {
        let (a, b) = (y.saturating_sub(reach), (y + reach + 1).min(h));
        for (x, o) in row.iter_mut().enumerate() {
            *o = (a..b).any(|yy| rows[yy * width + x]);
        }
    });
    out
}

/// The 8-neighbours of pixel `i` in a `width`-wide image of `n` pixels.
fn neighbours(i: usize, width: usize, n: usize) -> impl Iterator<Item = usize> {
    let h = n / width.max(1);
    let (x, y) = (i % width, i / width);
    (y.saturating_sub(1)..(y + 2).min(h))
        .flat_map(move |yy| {
            (x.saturating_sub(1)..(x + 2).min(width)).map(move |xx| yy * width + xx)
        })
        .filter(move |&j| j != i)
}

/// The pixels of `mask` whose 8-connected component holds at least `min_pixels`.
pub fn large_components(mask: &[bool], width: usize, min_pixels: usize) -> Vec<bool> {
    let n = mask.len();
    let mut out = vec![false; n];
    let mut seen = vec![false; n];
    let mut component = Vec::new();
    for start in 0..n {
        if !mask[start] || seen[start] {
            continue;
        }
        seen[start] = true;
        component.clear();
        component.push(start);
        let mut k = 0;
        while k < component.len() {
            for j in neighbours(component[k], width, n) {
                if mask[j] && !seen[j] {
                    seen[j] = true;
                    component.push(j);
                }
            }
            k += 1;
        }
        if component.len() >= min_pixels {
            for &i in &component {
                out[i] = true;
            }
        }
    }
    out
}

/// The pixels that are not `object`, for which `judged` holds and that are 8-connected to a
/// `seed` pixel through such pixels.
fn grow_from(
    seed: &[bool],
    object: &[bool],
    width: usize,
    judged: impl Fn(usize) -> bool,
) -> Vec<bool> {
    let n = seed.len();
    let mut out = vec![false; n];
    let mut stack: Vec<usize> = (0..n).filter(|&i| seed[i]).collect();
    while let Some(i) = stack.pop() {
        for j in neighbours(i, width, n) {
            if !object[j] && !out[j] && judged(j) {
                out[j] = true;
                stack.push(j);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::simulate::mvs::gaussian;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    const W: usize = 64;
    const H: usize = 48;

    /// Read noise alone, σ = 1 per component.
    fn unit_noise() -> NoiseModel {
        NoiseModel {
            read_variance: 1.0,
            shot_gain: 0.0,
        }
    }

    /// A frame of zero scatter and unit noise with an object block at columns 20..30, and
    /// `strip` added to column 19 (the block's left neighbour) along the real axis.
    fn frame(seed: u64, strip: f64) -> (Vec<f32>, Vec<f32>, Vec<bool>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut object = vec![false; W * H];
        let mut re = vec![0.0f32; W * H];
        let mut im = vec![0.0f32; W * H];
        for i in 0..W * H {
            let (x, y) = (i % W, i / W);
            let inside = (20..30).contains(&x) && (10..40).contains(&y);
            object[i] = inside;
            let signal = if inside {
                30.0
            } else if x == 19 && (10..40).contains(&y) {
                strip
            } else {
                0.0
            };
            re[i] = (signal + gaussian(&mut rng)) as f32;
            im[i] = gaussian(&mut rng) as f32;
        }
        (re, im, object)
    }

    #[test]
    fn a_dim_strip_beside_an_object_is_uncertain_where_pixels_alone_are_not() {
        let noise = unit_noise();
        let zero = vec![0.0; W * H];
        let (re, im, object) = frame(1, 2.0);
        let u = uncertain_pixels(&re, &im, &zero, &zero, &object, Some(&noise), W, 2);
        let strip: Vec<usize> = (10..40).map(|y| y * W + 19).collect();
        let found = strip.iter().filter(|&&i| u[i]).count();
        let r = normalised_residuals(&re, &im, &zero, &zero, &noise);
        let alone = strip
            .iter()
            .filter(|&&i| r[i][0].hypot(r[i][1]) > PIXEL_THRESHOLD)
            .count();
        // 2 σ per pixel: alone, about a third of the strip passes 2.5 σ; along the column seven
        // pixels sum to 5.3 σ. Only the two pixels at each end, whose lines reach past the
        // strip, may be missed.
        assert!(alone <= 15, "{alone} of 30 strip pixels pass alone");
        assert!(found >= 26, "{found} of 30 strip pixels uncertain");
        for (i, &ui) in u.iter().enumerate() {
            assert!(!(ui && object[i]), "object pixel {i} reported uncertain");
        }
    }

    #[test]
    fn pure_noise_beside_an_object_is_rarely_uncertain_and_never_away_from_it() {
        let noise = unit_noise();
        let zero = vec![0.0; W * H];
        let near = dilate(&frame(0, 0.0).2, W, REACH);
        let (mut flagged, mut judged) = (0usize, 0usize);
        for seed in 10..20 {
            let (re, im, object) = frame(seed, 0.0);
            let u = uncertain_pixels(&re, &im, &zero, &zero, &object, Some(&noise), W, 2);
            for i in 0..W * H {
                assert!(
                    !u[i] || near[i],
                    "pixel {i} away from the object is uncertain"
                );
                judged += (near[i] && !object[i]) as usize;
                flagged += u[i] as usize;
            }
        }
        let rate = flagged as f64 / judged as f64;
        // Per pixel 4.4 % pass 2.5 σ and 0.9 % a line; the hysteresis keeps those touching the
        // object through others.
        assert!(rate < 0.06, "{:.1} % of the band uncertain", rate * 100.0);
    }

    #[test]
    fn no_noise_model_no_uncertain_pixels() {
        let zero = vec![0.0; W * H];
        let (re, im, object) = frame(1, 5.0);
        let u = uncertain_pixels(&re, &im, &zero, &zero, &object, None, W, 2);
        assert!(!u.contains(&true));
    }

    #[test]
    fn a_lone_object_pixel_is_not_extended() {
        let noise = unit_noise();
        let zero = vec![0.0; W * H];
        // Every pixel 3 σ: all would be uncertain beside a real object.
        let re = vec![3.0f32; W * H];
        let im = vec![0.0f32; W * H];
        let mut object = vec![false; W * H];
        object[20 * W + 30] = true;
        object[30 * W + 10] = true;
        object[30 * W + 11] = true;
        let u = uncertain_pixels(&re, &im, &zero, &zero, &object, Some(&noise), W, 2);
        assert!(!u.contains(&true));
        let big = large_components(&object, W, 2);
        assert!(!big[20 * W + 30] && big[30 * W + 10] && big[30 * W + 11]);
    }

    #[test]
    fn dilation_is_the_chebyshev_ball() {
        let mut m = vec![false; W * H];
        m[20 * W + 30] = true;
        let d = dilate(&m, W, 2);
        for (i, &di) in d.iter().enumerate() {
            let (x, y) = ((i % W) as isize, (i / W) as isize);
            let inside = (x - 30).abs() <= 2 && (y - 20).abs() <= 2;
            assert_eq!(di, inside, "pixel ({x}, {y})");
        }
    }

    #[test]
    fn pure_noise_rarely_makes_a_line() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let r: Vec<[f64; 2]> = (0..W * H * 16)
            .map(|_| [gaussian(&mut rng), gaussian(&mut rng)])
            .collect();
        let none = vec![false; r.len()];
        let all: Vec<usize> = (0..r.len()).collect();
        let t = line_statistic(&r, &none, W, &all);
        let rate = t.iter().filter(|&&v| v > LINE_THRESHOLD).count() as f64 / t.len() as f64;
        // One window: e^{−8} = 0.034 %; 28 overlapping ones: 0.83 % measured.
        assert!(
            rate < 0.012,
            "{:.3} % of noise pixels on a line",
            rate * 100.0
        );
        // A line of seven pixels at 2 σ along a column does pass.
        let mut r = vec![[0.0; 2]; W * H];
        for y in 10..17 {
            r[y * W + 5] = [2.0, 0.0];
        }
        let none = vec![false; W * H];
        let t = line_statistic(&r, &none, W, &[10 * W + 5, 16 * W + 5, 13 * W + 5]);
        assert!(
            t.iter().all(|&v| (v - 14.0 / 7f64.sqrt()).abs() < 1e-12),
            "{t:?}"
        );
    }
}
