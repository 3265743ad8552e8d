//! The dark-channel prior's airlight rule (He et al. \[17\], reference §2.4): among the pixels
//! whose dark channel is in the top fraction (0.1 %), the haze-opaque ones, the brightest
//! pixel of the input is taken as the airlight.

use crate::error::{MurkError, Result};
use crate::image::ImageF32;

/// Settings of [`dark_channel_airlight`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DarkChannelParams {
    /// Half-width of the square patch of the minimum filter, pixels (He et al.: 7, a 15×15 patch).
    pub patch_radius: usize,
    /// Fraction of pixels with the largest dark channel that are candidates (He et al.: 0.001).
    pub top_fraction: f64,
}

impl Default for DarkChannelParams {
    fn default() -> Self {
        Self {
            patch_radius: 7,
            top_fraction: 0.001,
        }
    }
}

impl DarkChannelParams {
    /// Fails naming the first bad field.
    pub fn validate(&self) -> Result<()> {
        if self.patch_radius > 64 {
            return Err(MurkError::invalid(
                "patch_radius",
                format!("must be <= 64 pixels, got {}", self.patch_radius),
            ));
        }
        if !(self.top_fraction > 0.0 && self.top_fraction <= 1.0) {
            return Err(MurkError::invalid(
                "top_fraction",
                format!("must be in (0, 1], got {}", self.top_fraction),
            ));
        }
        Ok(())
    }
}

/// Sliding minimum over `[i − r, i + r]` (clamped to the row) of `src` into `dst`.
fn min_filter_1d(src: &[f32], dst: &mut [f32], r: usize) {
    let n = src.len();
    for (i, d) in dst.iter_mut().enumerate() {
        let lo = i.saturating_sub(r);
        let hi = (i + r + 1).min(n);
        *d = src[lo..hi].iter().copied().fold(f32::INFINITY, f32::min);
    }
}

/// The dark channel `min_{y ∈ Ω(x)} min_c I_c(y)` over a `(2r+1)²` patch (clamped at the
/// borders), one channel. Separable: the minimum over a square is the minimum of row minima.
pub fn dark_channel(image: &ImageF32, patch_radius: usize) -> ImageF32 {
    let (w, h) = image.dims();
    let c = image.channels();
    let data = image.data();
    let per_pixel: Vec<f32> = data
        .chunks_exact(c)
        .map(|px| px.iter().copied().fold(f32::INFINITY, f32::min))
        .collect();
    let mut rows = vec![0.0f32; w * h];
    for y in 0..h {
        min_filter_1d(
            &per_pixel[y * w..(y + 1) * w],
            &mut rows[y * w..(y + 1) * w],
            patch_radius,
        );
    }
    let mut out = vec![0.0f32; w * h];
    let mut col = vec![0.0f32; h];
    let mut col_out = vec![0.0f32; h];
    for x in 0..w {
        for y in 0..h {
            col[y] = rows[y * w + x];
        }
        min_filter_1d(&col, &mut col_out, patch_radius);
        for y in 0..h {
            out[y * w + x] = col_out[y];
        }
    }
    ImageF32::from_vec(w, h, 1, out).expect("dimensions come from a valid image")
}

/// Grey airlight `A` by the dark-channel rule: the channel mean of the brightest (by channel
/// mean) pixel among the `top_fraction` of pixels with the largest dark channel, clamped to
/// `[1e-3, 1]`. Fails on non-finite pixels.
pub fn dark_channel_airlight(image: &ImageF32, params: &DarkChannelParams) -> Result<f32> {
    params.validate()?;
    image.ensure_finite()?;
    let dark = dark_channel(image, params.patch_radius);
    let n = dark.pixel_count();
    let k = ((n as f64 * params.top_fraction).ceil() as usize).clamp(1, n);
    let mut order: Vec<u32> = (0..n as u32).collect();
    let d = dark.data();
    // Partial selection: only the top k matter, their order does not.
    order.select_nth_unstable_by(k - 1, |&a, &b| d[b as usize].total_cmp(&d[a as usize]));
    let c = image.channels();
    let brightness = |i: usize| image.data()[i * c..(i + 1) * c].iter().sum::<f32>() / c as f32;
    let best = order[..k]
        .iter()
        .map(|&i| brightness(i as usize))
        .fold(f32::NEG_INFINITY, f32::max);
    Ok(best.clamp(1e-3, 1.0))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::atmosphere::haze;

    #[test]
    fn dark_channel_is_patch_minimum_of_channel_minimum() {
        let img = ImageF32::from_fn(9, 7, |x, y| ((x * 7 + y * 3) % 11) as f32 / 10.0);
        let mut rgb = ImageF32::filled(9, 7, 3, 1.0);
        for y in 0..7 {
            for x in 0..9 {
                rgb.set(x, y, 1, img.get(x, y, 0));
            }
        }
        let dc = dark_channel(&rgb, 1);
        for y in 0..7usize {
            for x in 0..9usize {
                let mut m = f32::INFINITY;
                for yy in y.saturating_sub(1)..=(y + 1).min(6) {
                    for xx in x.saturating_sub(1)..=(x + 1).min(8) {
                        m = m.min(img.get(xx, yy, 0));
                    }
                }
                assert_eq!(dc.get(x, y, 0), m, "({x}, {y})");
            }
        }
    }

    #[test]
    fn recovers_airlight_of_a_scene_with_a_far_region() {
        // A textured scene whose top third is very far (t ≈ 0): the haze-opaque region the
        // rule relies on.
        let (w, h) = (64, 48);
        let clear = ImageF32::from_fn(w, h, |x, y| {
            0.2 + 0.6 * (((x / 3 + y / 5) % 4) as f32 / 3.0)
        });
        let mut rgb = ImageF32::filled(w, h, 3, 0.0);
        for y in 0..h {
            for x in 0..w {
                for c in 0..3 {
                    rgb.set(x, y, c, clear.get(x, y, 0) * (0.8 + 0.1 * c as f32));
                }
            }
        }
        let depth = ImageF32::from_fn(w, h, |_, y| if y < h / 3 { 40.0 } else { 3.0 });
        let a = 0.83;
        let hazy = haze(&rgb, &depth, a, 0.5).unwrap();
        let est = dark_channel_airlight(&hazy, &DarkChannelParams::default()).unwrap();
        assert!((est - a).abs() < 0.01, "estimated {est}, true {a}");
    }

    #[test]
    fn rejects_bad_input() {
        let mut img = ImageF32::filled(8, 8, 3, 0.5);
        let p = DarkChannelParams {
            top_fraction: 0.0,
            ..Default::default()
        };
        assert_eq!(
            dark_channel_airlight(&img, &p).unwrap_err().field(),
            Some("top_fraction")
        );
        img.set(1, 1, 0, f32::NAN);
        assert!(dark_channel_airlight(&img, &DarkChannelParams::default()).is_err());
    }
}
