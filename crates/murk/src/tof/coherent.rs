//! The coherent-residual statistic of the fine level's thin-structure check (see
//! `tof::irls::THIN_ROUNDS`).
//!
//! A pixel's Tukey weight judges its residual alone, so an object part whose direct return is
//! only a few noise σ above the fog (a panel seen at a grazing angle, a pole in thick fog, a
//! strip beside a nearer occluder) passes as background one pixel at a time. Over a few
//! neighbouring pixels, though, its residuals point the same way — the direct phasor of one
//! surface — while noise points anywhere. The statistic sums the residual vectors of a window
//! and divides by the noise of the sum:
//!
//! `t_i = ‖Σ_{j ∈ W(i), j background} r_j‖ / (σ √N_i)`,
//!
//! with `r_j` the pixel's residual over the components (already divided by its relative noise
//! level) and `N_i` the background pixels of the window. On pure noise `t²` follows a χ² with as
//! many degrees of freedom as components, so `t > 5` happens to fewer than 4 pixels in a million
//! (two components: e^{−12.5}).

use rayon::prelude::*;

/// Half-width of the window: 3 × 3 pixels, the widest a 2-pixel strip still fills by two
/// thirds.
pub const WINDOW_RADIUS: usize = 1;

/// Half-width of the ring around the window that [`coherent_contrast`] compares it with: the
/// 7 × 7 pixels less the 3 × 3 window.
pub const RING_RADIUS: usize = 3;

/// Fewest ring pixels with which [`coherent_contrast`] compares.
pub const MIN_RING: usize = 8;

/// The statistic `t_i` for every pixel of a `w`-wide image: `residuals` holds one image per
/// component, `background` marks the pixels whose residuals count, and `sigma` is the residual
/// scale. Pixels whose window holds no background get 0.
pub fn coherent_residual(
    residuals: &[Vec<f64>],
    background: &[bool],
    w: usize,
    sigma: f64,
) -> Vec<f64> {
    let mut out = vec![0.0; background.len()];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, o) in row.iter_mut().enumerate() {
            *o = window_statistic(residuals, background, w, sigma, x, y);
        }
    });
    out
}

/// `t_i` of the pixel at (`x`, `y`) (see [`coherent_residual`]).
fn window_statistic(
    residuals: &[Vec<f64>],
    background: &[bool],
    w: usize,
    sigma: f64,
    x: usize,
    y: usize,
) -> f64 {
    let h = background.len() / w.max(1);
    let r = WINDOW_RADIUS;
    let (y0, y1) = (y.saturating_sub(r), (y + r + 1).min(h));
    let (x0, x1) = (x.saturating_sub(r), (x + r + 1).min(w));
    // The phasor's two components (or one) in a single pass over the window, each summed in the
    // same row-major order as the general form below: the same value, without its iterator
    // chains three times per pixel over the whole image.
    if residuals.len() <= 2 {
        let (mut count, mut sums) = (0usize, [0.0f64; 2]);
        for yy in y0..y1 {
            for j in yy * w + x0..yy * w + x1 {
                if background[j] {
                    count += 1;
                    for (s, comp) in sums.iter_mut().zip(residuals) {
                        *s += comp[j];
                    }
                }
            }
        }
        if count == 0 {
            return 0.0;
        }
        let norm2: f64 = sums[..residuals.len()].iter().map(|s| s.powi(2)).sum();
        return norm2.sqrt() / (sigma * (count as f64).sqrt());
    }
    let counted = || {
        (y0..y1)
            .flat_map(move |yy| (x0..x1).map(move |xx| yy * w + xx))
            .filter(|&j| background[j])
    };
    let count = counted().count();
    if count == 0 {
        return 0.0;
    }
    let norm2: f64 = residuals
        .iter()
        .map(|comp| counted().map(|j| comp[j]).sum::<f64>().powi(2))
        .sum();
    norm2.sqrt() / (sigma * (count as f64).sqrt())
}

/// Pixels of the 7 × 7 neighbourhood ([`RING_RADIUS`]).
const NEIGHBOURHOOD: usize = (2 * RING_RADIUS + 1) * (2 * RING_RADIUS + 1);

/// [`coherent_residual`] against the surroundings, at `pixels` only: the window's mean residual
/// less the median residual of the ring around it ([`RING_RADIUS`]), per component, divided by
/// the noise of that difference, `σ·√(1/N_window + (π/2)/N_ring)` (the median of N normal
/// values has π/2 times the variance of their mean). The window counts the `background`
/// pixels; the ring only those that are not also `suspects`, which stand under the same
/// suspicion as the pixel judged.
///
/// Where the scatter model misfits the background — its smoothness prior leaves a bias of
/// about 2 σ in the outermost rows where the illuminator's beam falls off steeply — window and
/// ring share the bias and the difference cancels it. A strip a few pixels wide fills most of
/// the window but only a minority of the ring, whose median it hardly moves. A pixel with fewer
/// than 3 counted pixels in its window, or fewer than [`MIN_RING`] in its ring, has no
/// surroundings to compare with (a strip squeezed between objects): it gets the plain window
/// statistic of [`coherent_residual`].
pub fn coherent_contrast(
    residuals: &[Vec<f64>],
    background: &[bool],
    suspects: &[bool],
    w: usize,
    sigma: f64,
    pixels: &[usize],
) -> Vec<f64> {
    let h = background.len() / w.max(1);
    pixels
        .par_iter()
        .map(|&i| {
            let (x, y) = (i % w, i / w);
            let (y0, y1) = (y.saturating_sub(RING_RADIUS), (y + RING_RADIUS + 1).min(h));
            let (x0, x1) = (x.saturating_sub(RING_RADIUS), (x + RING_RADIUS + 1).min(w));
            // Fixed-size buffers: this runs once per candidate pixel.
            let (mut inner, mut n_inner) = ([0usize; NEIGHBOURHOOD], 0);
            let (mut ring, mut n_ring) = ([0usize; NEIGHBOURHOOD], 0);
            for yy in y0..y1 {
                for xx in x0..x1 {
                    let j = yy * w + xx;
                    let in_window =
                        xx.abs_diff(x) <= WINDOW_RADIUS && yy.abs_diff(y) <= WINDOW_RADIUS;
                    if in_window && background[j] {
                        inner[n_inner] = j;
                        n_inner += 1;
                    } else if !in_window && background[j] && !suspects[j] {
                        ring[n_ring] = j;
                        n_ring += 1;
                    }
                }
            }
            if n_inner < 3 || n_ring < MIN_RING {
                return window_statistic(residuals, background, w, sigma, x, y);
            }
            let (inner, ring) = (&inner[..n_inner], &ring[..n_ring]);
            let mut values = [0.0f64; NEIGHBOURHOOD];
            let mut norm2 = 0.0;
            for comp in residuals {
                let mean = inner.iter().map(|&j| comp[j]).sum::<f64>() / n_inner as f64;
                for (v, &j) in values.iter_mut().zip(ring) {
                    *v = comp[j];
                }
                let (_, median, _) =
                    values[..n_ring].select_nth_unstable_by(n_ring / 2, f64::total_cmp);
                norm2 += (mean - *median).powi(2);
            }
            let var = 1.0 / n_inner as f64 + std::f64::consts::FRAC_PI_2 / n_ring as f64;
            norm2.sqrt() / (sigma * var.sqrt())
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// `n` standard normal samples (Box–Muller).
    fn noise(n: usize, seed: u64) -> Vec<f64> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..n)
            .map(|_| {
                let u: f64 = rng.random_range(f64::MIN_POSITIVE..1.0);
                let v: f64 = rng.random();
                (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
            })
            .collect()
    }

    #[test]
    fn pure_noise_rarely_exceeds_five() {
        let (w, h) = (200, 200);
        let res = vec![noise(w * h, 1), noise(w * h, 2)];
        let t = coherent_residual(&res, &vec![true; w * h], w, 1.0);
        let over = t.iter().filter(|&&v| v > 5.0).count();
        assert_eq!(over, 0, "{over} of {} noise pixels over 5", w * h);
        // t² is χ² with 2 degrees of freedom: its mean is 2.
        let mean2 = t.iter().map(|v| v * v).sum::<f64>() / t.len() as f64;
        assert!((mean2 - 2.0).abs() < 0.1, "{mean2}");
    }

    #[test]
    fn a_strip_of_weak_coherent_residuals_stands_out() {
        // A 2-pixel strip whose pixels are each 4 σ off, all in the same direction.
        let (w, h) = (40, 40);
        let mut re = noise(w * h, 3);
        let im = noise(w * h, 4);
        for y in 5..35 {
            for x in 20..22 {
                re[y * w + x] += 4.0;
            }
        }
        let t = coherent_residual(&[re, im], &vec![true; w * h], w, 1.0);
        let strip_min = (6..34)
            .flat_map(|y| (20..22).map(move |x| (x, y)))
            .map(|(x, y)| t[y * w + x])
            .fold(f64::INFINITY, f64::min);
        assert!(strip_min > 5.0, "{strip_min}");
    }

    #[test]
    fn contrast_cancels_a_shared_bias_and_keeps_a_strip() {
        // Every pixel biased by 3 σ (a model misfit), plus a 2-pixel strip 5 σ further off.
        let (w, h) = (40, 40);
        let mut re = noise(w * h, 5);
        let im = noise(w * h, 6);
        for (i, v) in re.iter_mut().enumerate() {
            *v += 3.0;
            if (20..22).contains(&(i % w)) && (5..35).contains(&(i / w)) {
                *v += 5.0;
            }
        }
        let res = [re, im];
        let background = vec![true; w * h];
        let all: Vec<usize> = (0..w * h).collect();
        // Against noise alone, the bias makes every pixel coherent.
        let t = coherent_residual(&res, &background, w, 1.0);
        assert!(t.iter().filter(|&&v| v > 5.0).count() > w * h / 2);
        // The ring compares with the background that is not itself under suspicion: here
        // everything but the strip's columns.
        let suspects: Vec<bool> = (0..w * h).map(|i| (20..22).contains(&(i % w))).collect();
        let c = coherent_contrast(&res, &background, &suspects, w, 1.0, &all);
        let strip = |i: usize| (20..22).contains(&(i % w)) && (8..32).contains(&(i / w));
        let off_strip = |i: usize| (i % w) < 17 || (i % w) > 24;
        let worst_off = all
            .iter()
            .filter(|&&i| off_strip(i))
            .map(|&i| c[i])
            .fold(0.0, f64::max);
        let weakest_on = all
            .iter()
            .filter(|&&i| strip(i))
            .map(|&i| c[i])
            .fold(f64::INFINITY, f64::min);
        assert!(worst_off < 5.0, "{worst_off}");
        assert!(weakest_on > 5.0, "{weakest_on}");
    }

    #[test]
    fn pixels_outside_the_background_do_not_count() {
        let (w, h) = (5, 5);
        let mut res = vec![0.0; w * h];
        res[12] = 100.0;
        let mut background = vec![true; w * h];
        background[12] = false;
        let t = coherent_residual(&[res], &background, w, 1.0);
        assert!(t.iter().all(|&v| v == 0.0));
        // With nothing counted, 0.
        let t = coherent_residual(&[vec![1.0; 4]], &[false; 4], 2, 1.0);
        assert_eq!(t, vec![0.0; 4]);
    }

    #[test]
    fn without_surroundings_the_contrast_is_the_window_statistic() {
        // Every pixel a suspect: no ring to compare with, as for a strip between objects.
        let (w, h) = (9, 9);
        let res = vec![noise(w * h, 7), noise(w * h, 8)];
        let background = vec![true; w * h];
        let all: Vec<usize> = (0..w * h).collect();
        let c = coherent_contrast(&res, &background, &vec![true; w * h], w, 1.0, &all);
        assert_eq!(c, coherent_residual(&res, &background, w, 1.0));
    }
}
