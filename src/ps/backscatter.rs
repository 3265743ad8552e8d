//! Backscatter removal (§4.3.1): subtract the no-object image taken under the same light
//! (Tsiotsios et al. [15] rely on backscatter saturating close to the camera, so the no-object
//! image carries almost the same backscatter), then a 3×3 median against the noise the
//! subtraction amplifies (§4.3.4).

use rayon::prelude::*;

/// `image − background` inside the mask, 3×3-median filtered over the masked neighbours when
/// `median` is set (so background pixels never leak into object pixels at the silhouette);
/// 0 outside the mask.
pub fn remove_backscatter(
    image: &[f32],
    background: &[f32],
    mask: &[bool],
    width: usize,
    median: bool,
) -> Vec<f32> {
    let n = image.len();
    let height = n / width.max(1);
    let diff: Vec<f32> = (0..n)
        .map(|p| {
            if mask[p] {
                image[p] - background[p]
            } else {
                0.0
            }
        })
        .collect();
    if !median {
        return diff;
    }
    let mut out = vec![0.0f32; n];
    out.par_chunks_mut(width).enumerate().for_each(|(y, row)| {
        let mut window = [0.0f32; 9];
        for (x, o) in row.iter_mut().enumerate() {
            let p = y * width + x;
            if !mask[p] {
                continue;
            }
            let mut k = 0;
            for ny in y.saturating_sub(1)..=(y + 1).min(height - 1) {
                for nx in x.saturating_sub(1)..=(x + 1).min(width - 1) {
                    let q = ny * width + nx;
                    if mask[q] {
                        window[k] = diff[q];
                        k += 1;
                    }
                }
            }
            let w = &mut window[..k];
            w.sort_unstable_by(f32::total_cmp);
            *o = if k % 2 == 1 {
                w[k / 2]
            } else {
                0.5 * (w[k / 2 - 1] + w[k / 2])
            };
        }
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn subtracts_and_removes_an_outlier_without_leaking_background() {
        let w = 5;
        let mut image = vec![10.0f32; 25];
        let background = vec![1.0f32; 25];
        image[12] = 100.0; // a hot pixel in the middle
        let mut mask = vec![true; 25];
        mask[0] = false;
        image[0] = 1e6; // unmasked garbage must not reach masked pixels
        let out = remove_backscatter(&image, &background, &mask, w, true);
        assert_eq!(out[0], 0.0);
        for (p, v) in out.iter().enumerate().skip(1) {
            assert_eq!(*v, 9.0, "pixel {p}");
        }
        let raw = remove_backscatter(&image, &background, &mask, w, false);
        assert_eq!(raw[12], 99.0);
    }
}
