//! Footprint-matched sampling of a point's intensity in two views.
//!
//! The equations of [`crate::params::point_ratio`] and [`crate::params::joint_fit`] compare a
//! point's intensity in the reference and in a source and read the difference as haze (Eq. 3.3).
//! A pixel, though, integrates the clear radiance `J` over a footprint on the surface that grows
//! with the distance: a source at `z_s > z_r` sees the texture minified by `z_r/z_s`, so at a
//! blob or an edge its value has moved towards the surroundings by an amount that, like the
//! haze, grows with `z_s − z_r`. Random surface points rarely sit on such structure. SfM points
//! always do: SIFT puts its keypoints at blob centres and corners. Measured on 15 simulated
//! 512×384 lateral scenes, with exact geometry at COLMAP's keypoints and the true `A`, β's mean
//! relative error was 0.41 with one 2-px blur for every view, 0.36 with the reference read at
//! the keypoint rather than at its pixel's centre, and 0.12 with the blur matched per point as
//! below; at random surface points it is 0.06–0.08 either way
//! (`clients/python/examples/keypoint_sampling.py`).
//!
//! [`FootprintSampler`] blurs each view by a Gaussian whose width on the surface is the same in
//! both views: with `σ_p` the image's own blur ([`PIXEL_PSF_SIGMA_PX`]) and `s = z/f` the
//! surface length of one pixel, the reference gets `σ_r` and the source `σ_s` with
//! `√(σ_r² + σ_p²)·s_r = √(σ_s² + σ_p²)·s_s`, the view whose pixel covers more surface (the
//! farther) getting the base `σ₀` of [`crate::params::point_ratio::sample_blur_sigma_px`].
//! Each value is a Gaussian-weighted mean around the point's sub-pixel position, so neither view
//! gets the extra low-pass of a bilinear lookup. The surface is taken as facing the cameras: its slant changes the footprints'
//! ratio by the cosines of the two viewing angles, which differ little between nearby views.

use crate::image::ImageF32;

/// Standard deviation of the blur an image already carries, pixels: a box pixel alone is
/// `1/√12 ≈ 0.29`; lenses, demosaicing and the simulator's supersampling add to it. The matched
/// blur adds to this in quadrature, so its exact value matters only where the applied blur is
/// below about a pixel.
pub const PIXEL_PSF_SIGMA_PX: f64 = 0.5;
/// Smallest blur applied to either view, pixels: below it the Gaussian's weights on the pixel
/// grid no longer vary smoothly with the sub-pixel position.
pub const MIN_SAMPLE_SIGMA_PX: f64 = 0.5;
/// Largest blur applied to either view, pixels: eight times the widest base blur. A wider
/// match (a source over eight times as far as the reference) is capped, leaving that pair's
/// footprints unequal.
pub const MAX_SAMPLE_SIGMA_PX: f64 = 8.0;
/// Half-width of the sampling window in standard deviations.
const WINDOW_SIGMAS: f64 = 3.0;
/// Pixels across the widest window, `2·3·MAX_SAMPLE_SIGMA_PX + 1`.
const WINDOW_CAPACITY: usize = 49;
/// Most channels a sample carries (RGB).
pub const MAX_CHANNELS: usize = 3;

/// The blur of each view for one point, pixels: `(σ_r, σ_s)` of the module docs for a point at
/// z-depth `z_ref` in the reference (focal length `focal_ref`, pixels) and `z_src` in the
/// source, with `base_sigma_px` the blur of the view whose pixel covers more surface (the
/// farther one); the other gets a wider blur.
pub fn matched_sigmas(
    base_sigma_px: f64,
    z_ref: f64,
    focal_ref: f64,
    z_src: f64,
    focal_src: f64,
) -> (f64, f64) {
    let p2 = PIXEL_PSF_SIGMA_PX * PIXEL_PSF_SIGMA_PX;
    let base = base_sigma_px.max(MIN_SAMPLE_SIGMA_PX);
    let (sr, ss) = (z_ref / focal_ref, z_src / focal_src);
    // The common width on the surface: the base blur in the view whose pixel covers more
    // surface; the other view needs a wider blur in pixels, so neither falls below the base.
    let target = (base * base + p2).sqrt() * sr.max(ss);
    let sigma = |s: f64| ((target / s).powi(2) - p2).max(0.0).sqrt();
    (sigma(sr), sigma(ss))
}

/// Gaussian-weighted means of an image's channels around sub-pixel positions.
pub struct FootprintSampler<'a> {
    image: &'a ImageF32,
}

impl<'a> FootprintSampler<'a> {
    /// A sampler of `image` (murk's convention: pixel centres at integer coordinates).
    pub fn new(image: &'a ImageF32) -> Self {
        Self { image }
    }

    /// The mean of each channel under a Gaussian of standard deviation `sigma_px` (within
    /// [`MIN_SAMPLE_SIGMA_PX`]..=[`MAX_SAMPLE_SIGMA_PX`]) centred on `(u, v)`, written to `out[..channels]`. `false`,
    /// with `out` untouched, when the window of ±3σ leaves the image or `(u, v)` is not finite:
    /// a mean over a clipped window would be biased towards the inside.
    pub fn sample(&self, u: f64, v: f64, sigma_px: f64, out: &mut [f64; MAX_CHANNELS]) -> bool {
        let img = self.image;
        let (w, h, channels) = (img.width(), img.height(), img.channels());
        if channels > MAX_CHANNELS || !(u.is_finite() && v.is_finite()) {
            return false;
        }
        let sigma = sigma_px.clamp(MIN_SAMPLE_SIGMA_PX, MAX_SAMPLE_SIGMA_PX);
        let r = WINDOW_SIGMAS * sigma;
        let (x0, x1, y0, y1) = (u - r, u + r, v - r, v + r);
        if x0 < 0.0 || y0 < 0.0 || x1 > (w - 1) as f64 || y1 > (h - 1) as f64 {
            return false;
        }
        let (x0, x1) = (x0.ceil() as usize, x1.floor() as usize);
        let (y0, y1) = (y0.ceil() as usize, y1.floor() as usize);
        let k = -0.5 / (sigma * sigma);
        // The weights are separable: one row of x-weights, one y-weight per row.
        let mut wx = [0.0f64; WINDOW_CAPACITY];
        let nx = x1 - x0 + 1;
        for (i, wi) in wx[..nx].iter_mut().enumerate() {
            let d = (x0 + i) as f64 - u;
            *wi = (k * d * d).exp();
        }
        let mut acc = [0.0f64; MAX_CHANNELS];
        let mut total = 0.0;
        let data = img.data();
        for y in y0..=y1 {
            let d = y as f64 - v;
            let wy = (k * d * d).exp();
            let row = &data[(y * w + x0) * channels..];
            for (i, &wxi) in wx[..nx].iter().enumerate() {
                let wgt = wy * wxi;
                total += wgt;
                for (c, a) in acc[..channels].iter_mut().enumerate() {
                    *a += wgt * f64::from(row[i * channels + c]);
                }
            }
        }
        if total <= 0.0 {
            return false;
        }
        for (o, a) in out.iter_mut().zip(&acc[..channels]) {
            *o = a / total;
        }
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn ramp(w: usize, h: usize) -> ImageF32 {
        let data = (0..w * h)
            .flat_map(|i| {
                let (x, y) = ((i % w) as f32, (i / w) as f32);
                [0.01 * x + 0.02 * y, 0.5, 0.3 - 0.01 * y]
            })
            .collect();
        ImageF32::from_vec(w, h, 3, data).unwrap()
    }

    #[test]
    fn equal_depths_and_focals_keep_the_base_blur() {
        let (r, s) = matched_sigmas(1.0, 5.0, 400.0, 5.0, 400.0);
        assert!(
            (r - 1.0).abs() < 1e-12 && (s - 1.0).abs() < 1e-12,
            "{r} {s}"
        );
    }

    #[test]
    fn the_nearer_view_gets_the_wider_blur_and_the_footprints_match() {
        let p2 = PIXEL_PSF_SIGMA_PX * PIXEL_PSF_SIGMA_PX;
        for (zr, zs) in [(5.0, 5.5), (5.0, 4.0), (2.0, 6.0)] {
            let (r, s) = matched_sigmas(1.0, zr, 400.0, zs, 300.0);
            let (fr, fs) = (zr / 400.0, zs / 300.0);
            assert!(
                r.min(s) >= 0.0 && r.max(s) >= 1.0 - 1e-12,
                "{zr} {zs}: {r} {s}"
            );
            let (wr, ws) = ((r * r + p2).sqrt() * fr, (s * s + p2).sqrt() * fs);
            assert!((wr - ws).abs() < 1e-12 * wr, "{zr} {zs}: {wr} {ws}");
            assert_eq!(r > s, fr < fs);
        }
    }

    #[test]
    fn a_linear_image_is_sampled_exactly_at_sub_pixel_positions() {
        // A Gaussian window symmetric about (u, v) averages a linear function to its value
        // there; the clipped tails are symmetric too, as long as the window stays inside.
        let img = ramp(40, 30);
        let sampler = FootprintSampler::new(&img);
        let mut out = [0.0; MAX_CHANNELS];
        assert!(sampler.sample(17.3, 12.8, 1.5, &mut out));
        let expect = [0.01 * 17.3 + 0.02 * 12.8, 0.5, 0.3 - 0.01 * 12.8];
        for (o, e) in out.iter().zip(expect) {
            assert!((o - e).abs() < 1e-4, "{out:?} {expect:?}");
        }
    }

    #[test]
    fn windows_that_leave_the_image_are_refused() {
        let img = ramp(20, 20);
        let sampler = FootprintSampler::new(&img);
        let mut out = [7.0; MAX_CHANNELS];
        assert!(!sampler.sample(2.0, 10.0, 1.0, &mut out));
        assert!(!sampler.sample(10.0, 17.5, 1.0, &mut out));
        assert!(!sampler.sample(f64::NAN, 10.0, 1.0, &mut out));
        assert_eq!(out, [7.0; MAX_CHANNELS]);
        assert!(sampler.sample(3.0, 16.0, 1.0, &mut out));
    }

    proptest! {
        /// A mean of the image's values lies within their range, whatever the position and
        /// the blur.
        #[test]
        fn samples_stay_within_the_images_range(
            u in 10.0f64..30.0, v in 10.0f64..20.0, sigma in 0.0f64..3.0,
        ) {
            let img = ramp(40, 30);
            let mut out = [0.0; MAX_CHANNELS];
            prop_assert!(FootprintSampler::new(&img).sample(u, v, sigma, &mut out));
            prop_assert!(out[0] >= 0.0 && out[0] <= 0.01 * 39.0 + 0.02 * 29.0 + 1e-9);
            prop_assert!((out[1] - 0.5).abs() < 1e-6);
        }
    }
}
