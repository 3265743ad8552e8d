//! Per-pixel noise level of a CW-ToF frame. Photon shot noise makes a phasor's noise grow with
//! its brightness, σ² = σ_read² + k·|phasor| (the simulator's and real sensors' model, §2.2), so
//! one global scale in the IRLS makes bright background (the scatter near the emitter reaches
//! 3× the median brightness) look like outliers and dark corners like inliers. The model is fitted
//! to the frame itself, from second differences along rows binned by brightness.

use rayon::prelude::*;

use super::tukey::mad_sigma_in_place;

/// Brightness bins of the fit (equal pixel counts).
const BINS: usize = 16;
/// Variance of `v_i − (v_{i−1} + v_{i+1})/2` for white noise of variance σ²: 1.5σ².
const SECOND_DIFFERENCE_VARIANCE: f64 = 1.5;

/// σ² = `read_variance` + `shot_gain`·amplitude, per component of the phasor.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NoiseModel {
    /// σ² at zero amplitude (read noise), squared input units.
    pub read_variance: f64,
    /// Growth of σ² per unit amplitude (shot noise).
    pub shot_gain: f64,
}

impl NoiseModel {
    /// Fits the model to one frame given as a phasor (`re`, `im`) and its `amplitude`, all
    /// row-major `width` wide: in each of [`BINS`] brightness bins the robust (MAD) σ of the
    /// row-wise second differences of `re` and `im`, then least squares of σ² on the bins' mean
    /// amplitude, with both coefficients kept ≥ 0. Object edges fall in few pixels and do not
    /// move the MAD. `None` when the image is too small (under 3 columns, or fewer than 2·BINS
    /// interior pixels) or the inputs' lengths differ.
    pub fn fit(re: &[f32], im: &[f32], amplitude: &[f32], width: usize) -> Option<NoiseModel> {
        if width < 3 || re.len() != amplitude.len() || im.len() != amplitude.len() {
            return None;
        }
        // (amplitude, normalised second difference of re, of im) per interior pixel.
        let norm = (1.0 / SECOND_DIFFERENCE_VARIANCE).sqrt();
        let inner = width - 2;
        let mut samples = vec![(0.0, 0.0, 0.0); inner * (re.len() / width)];
        samples
            .par_chunks_mut(inner)
            .zip(re.par_chunks(width))
            .zip(im.par_chunks(width))
            .zip(amplitude.par_chunks(width))
            .for_each(|(((out, r), i), a)| {
                for (x, o) in (1..width - 1).zip(out.iter_mut()) {
                    let d = |v: &[f32]| {
                        (v[x] as f64 - 0.5 * (v[x - 1] as f64 + v[x + 1] as f64)) * norm
                    };
                    *o = (a[x] as f64, d(r), d(i));
                }
            });
        if samples.len() < 2 * BINS {
            return None;
        }
        let per = samples.len() / BINS;
        // The bins are the samples ranked by brightness, `per` to a bin (the last takes the
        // rest). Selecting the cuts finds the same bins as a sort, in a fraction of its time.
        let cuts: Vec<usize> = (1..BINS).map(|b| b * per).collect();
        partition_at(&mut samples, &cuts);
        let mut scratch = Vec::with_capacity(2 * (per + BINS));
        let mut points = Vec::with_capacity(BINS);
        for b in 0..BINS {
            let end = if b + 1 == BINS {
                samples.len()
            } else {
                (b + 1) * per
            };
            let bin = &samples[b * per..end];
            scratch.clear();
            scratch.extend(bin.iter().flat_map(|s| [s.1, s.2]));
            let sigma = mad_sigma_in_place(&mut scratch)?;
            let mean_a = bin.iter().map(|s| s.0).sum::<f64>() / bin.len() as f64;
            points.push((mean_a, sigma * sigma));
        }
        Some(fit_line_nonnegative(&points))
    }

    /// σ per phasor component at `amplitude` (clamped at 0).
    #[inline]
    pub fn sigma(&self, amplitude: f64) -> f64 {
        (self.read_variance + self.shot_gain * amplitude.max(0.0)).sqrt()
    }
}

/// Reorders `samples` so that every cut `c` of the increasing `cuts` holds the sample of rank
/// `c` by brightness (the first field), with no brighter sample before it and no dimmer one
/// after: each run between cuts is a brightness bin, in no particular order inside.
fn partition_at(samples: &mut [(f64, f64, f64)], cuts: &[usize]) {
    if cuts.is_empty() {
        return;
    }
    let mid = cuts.len() / 2;
    let at = cuts[mid];
    samples.select_nth_unstable_by(at, |p, q| p.0.total_cmp(&q.0));
    let (below, above) = samples.split_at_mut(at);
    let upper: Vec<usize> = cuts[mid + 1..].iter().map(|&c| c - at).collect();
    rayon::join(
        || partition_at(below, &cuts[..mid]),
        || partition_at(above, &upper),
    );
}

/// Weighted least squares `y = c0 + c1·x` over `points` (bin amplitude, bin σ²), both
/// coefficients ≥ 0 (the better of the unconstrained fit when feasible and the two
/// one-coefficient fits).
///
/// Each bin's σ² comes from the same number of samples, so its standard error is a fixed
/// fraction of σ² itself: the weights are 1/σ⁴, i.e. the fit is in relative terms. Unweighted,
/// the bright bins, whose σ² is largest, set the line and its intercept; where σ² grows more
/// slowly than linearly in amplitude at the bright end, that drove the read noise to 0 and
/// halved σ in the dark corners, whose background then came out as objects (separated thin
/// seed 5: 281 background pixels flagged).
fn fit_line_nonnegative(points: &[(f64, f64)]) -> NoiseModel {
    let floor = points.iter().fold(0.0f64, |m, p| m.max(p.1)) * 1e-6;
    let weight = |y: f64| 1.0 / y.max(floor).max(f64::MIN_POSITIVE).powi(2);
    let (mut sw, mut sx, mut sy) = (0.0, 0.0, 0.0);
    for &(x, y) in points {
        let w = weight(y);
        sw += w;
        sx += w * x;
        sy += w * y;
    }
    let (mx, my) = (sx / sw, sy / sw);
    let (mut sxx, mut sxy, mut sxx0, mut sxy0) = (0.0, 0.0, 0.0, 0.0);
    for &(x, y) in points {
        let w = weight(y);
        sxx += w * (x - mx) * (x - mx);
        sxy += w * (x - mx) * (y - my);
        sxx0 += w * x * x;
        sxy0 += w * x * y;
    }
    let sse = |c0: f64, c1: f64| {
        points
            .iter()
            .map(|&(x, y)| weight(y) * (y - c0 - c1 * x).powi(2))
            .sum::<f64>()
    };
    let mut best = NoiseModel {
        read_variance: my.max(0.0),
        shot_gain: 0.0,
    };
    let mut best_sse = sse(best.read_variance, 0.0);
    let through_origin = if sxx0 > 0.0 {
        (sxy0 / sxx0).max(0.0)
    } else {
        0.0
    };
    let mut candidates = vec![(0.0, through_origin)];
    if sxx > 0.0 {
        let c1 = sxy / sxx;
        let c0 = my - c1 * mx;
        if c0 >= 0.0 && c1 >= 0.0 {
            candidates.push((c0, c1));
        }
    }
    for (c0, c1) in candidates {
        let e = sse(c0, c1);
        if e < best_sse {
            best_sse = e;
            best = NoiseModel {
                read_variance: c0,
                shot_gain: c1,
            };
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    proptest! {
        /// The bins between the cuts are those of a sort by brightness (ties aside, the same
        /// multiset of brightnesses in each), and no sample is lost.
        #[test]
        fn partition_at_gives_the_sorted_bins(
            values in prop::collection::vec(0u8..40, 1..300),
            bins in 1usize..20,
        ) {
            let mut samples: Vec<(f64, f64, f64)> =
                values.iter().enumerate().map(|(i, &v)| (v as f64, i as f64, 0.0)).collect();
            let per = samples.len() / bins;
            let cuts: Vec<usize> = if per == 0 { Vec::new() } else { (1..bins).map(|b| b * per).collect() };
            partition_at(&mut samples, &cuts);
            let mut sorted: Vec<f64> = values.iter().map(|&v| v as f64).collect();
            sorted.sort_by(f64::total_cmp);
            let mut bounds = vec![0];
            bounds.extend(&cuts);
            bounds.push(samples.len());
            for run in bounds.windows(2) {
                let mut got: Vec<f64> = samples[run[0]..run[1]].iter().map(|s| s.0).collect();
                got.sort_by(f64::total_cmp);
                prop_assert_eq!(&got[..], &sorted[run[0]..run[1]]);
            }
            let mut ids: Vec<usize> = samples.iter().map(|s| s.1 as usize).collect();
            ids.sort_unstable();
            prop_assert_eq!(ids, (0..values.len()).collect::<Vec<_>>());
        }
    }

    fn gauss(rng: &mut ChaCha8Rng) -> f64 {
        let u1: f64 = 1.0 - rng.random::<f64>();
        let u2: f64 = rng.random();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    /// A `w × h` phasor frame of amplitude `amplitude(x, y)` and phase `phase(x)` with
    /// independent Gaussian noise of σ = shot·√a + read per component (the simulator's form).
    fn noisy_frame(
        (w, h): (usize, usize),
        (read_sd, shot): (f64, f64),
        seed: u64,
        amplitude: impl Fn(usize, usize) -> f64,
        phase: impl Fn(usize) -> f64,
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let (mut re, mut im, mut amp) = (vec![], vec![], vec![]);
        for y in 0..h {
            for x in 0..w {
                let (a, p) = (amplitude(x, y), phase(x));
                let sd = shot * a.sqrt() + read_sd;
                let (r, i) = (
                    a * p.cos() + sd * gauss(&mut rng),
                    a * p.sin() + sd * gauss(&mut rng),
                );
                re.push(r as f32);
                im.push(i as f32);
                amp.push(r.hypot(i) as f32);
            }
        }
        (re, im, amp)
    }

    /// A smooth phasor field from amplitude 20 to 400 with shot + read noise: the fit recovers
    /// both coefficients, and a step edge through the image does not move them much.
    #[test]
    fn recovers_shot_and_read_noise() {
        let (w, h) = (160, 120);
        let (read_sd, shot) = (0.5f64, 0.15f64);
        let amplitude = |x: usize, y: usize| {
            let a = 20.0 + 380.0 * (x as f64 / w as f64).powi(2) + y as f64 * 0.2;
            // An object.
            a + if x > w / 2 && y > h / 2 { 300.0 } else { 0.0 }
        };
        let phase = |x: usize| 0.2 + 0.001 * x as f64;
        let (re, im, amp) = noisy_frame((w, h), (read_sd, shot), 3, amplitude, phase);
        let m = NoiseModel::fit(&re, &im, &amp, w).unwrap();
        for a in [30.0, 100.0, 300.0, 600.0] {
            let truth = shot * f64::sqrt(a) + read_sd;
            let got = m.sigma(a);
            assert!(
                (got / truth - 1.0).abs() < 0.12,
                "a {a}: {got} vs {truth} ({m:?})"
            );
        }
    }

    /// A frame like a thin-fog one: a dim scatter field (amplitude 0.5–35, a tenth of the
    /// pixels under 3) and bright objects (150–360) on a fifth of it, with σ growing like
    /// a√s + b, so σ² is concave in s. The fit must keep the read noise that dominates the dark
    /// corner (an unweighted line through the bins misses it by 15 % here; on separated thin
    /// seed 5 it put the read noise at 0 and σ at amplitude 2 at half its true value, which
    /// flagged the corner as objects).
    #[test]
    fn dark_pixels_keep_their_read_noise() {
        let (w, h) = (160, 120);
        let (read_sd, shot) = (0.5f64, 0.15f64);
        let amplitude = |x: usize, y: usize| {
            let t = x as f64 / (w - 1) as f64;
            let a = 0.5 + 35.0 * t * t * (1.0 - 0.3 * (y as f64 / h as f64));
            if (40..80).contains(&y) && x > w / 3 {
                // Bright objects, as bright as near ones in fog.
                a + 150.0 + 2.0 * (x - w / 3) as f64
            } else {
                a
            }
        };
        let phase = |x: usize| 0.4 + 0.002 * x as f64;
        let (re, im, amp) = noisy_frame((w, h), (read_sd, shot), 11, amplitude, phase);
        let m = NoiseModel::fit(&re, &im, &amp, w).unwrap();
        for a in [1.0, 2.0, 5.0, 20.0, 200.0] {
            let truth = shot * f64::sqrt(a) + read_sd;
            let got = m.sigma(a);
            assert!(
                (got / truth - 1.0).abs() < 0.15,
                "a {a}: {got} vs {truth} ({m:?})"
            );
        }
    }

    #[test]
    fn constant_noise_gives_no_shot_term_and_tiny_images_none() {
        let (w, h) = (64, 64);
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let re: Vec<f32> = (0..w * h)
            .map(|i| (50.0 + (i % w) as f64 + gauss(&mut rng)) as f32)
            .collect();
        let im: Vec<f32> = (0..w * h).map(|_| gauss(&mut rng) as f32).collect();
        let amp: Vec<f32> = re.iter().zip(&im).map(|(a, b)| a.hypot(*b)).collect();
        let m = NoiseModel::fit(&re, &im, &amp, w).unwrap();
        assert!(
            (m.sigma(50.0) - 1.0).abs() < 0.1 && (m.sigma(110.0) - 1.0).abs() < 0.1,
            "{m:?}"
        );
        assert!(NoiseModel::fit(&[1.0; 4], &[1.0; 4], &[1.0; 4], 2).is_none());
    }
}
