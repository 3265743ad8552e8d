//! In-memory image type shared by every method: row-major, interleaved channels, `f32` samples.

use crate::error::{MurkError, Result};

/// A dense `f32` image, row-major with interleaved channels (`data[(y·w + x)·c + ch]`).
#[derive(Clone, Debug, PartialEq)]
pub struct ImageF32 {
    width: usize,
    height: usize,
    channels: usize,
    data: Vec<f32>,
}

impl ImageF32 {
    /// Wraps `data`; fails if its length is not `width·height·channels` or any dimension is zero.
    pub fn from_vec(width: usize, height: usize, channels: usize, data: Vec<f32>) -> Result<Self> {
        if width == 0 || height == 0 || channels == 0 {
            return Err(MurkError::invalid(
                "",
                format!("image dimensions must be positive, got {width}x{height}x{channels}"),
            ));
        }
        let expected = width
            .checked_mul(height)
            .and_then(|n| n.checked_mul(channels))
            .ok_or_else(|| MurkError::invalid("", "image dimensions overflow"))?;
        if data.len() != expected {
            return Err(MurkError::invalid(
                "",
                format!(
                    "expected {expected} samples for {width}x{height}x{channels}, got {}",
                    data.len()
                ),
            ));
        }
        Ok(Self {
            width,
            height,
            channels,
            data,
        })
    }

    /// A `width×height×channels` image filled with `value`.
    ///
    /// # Panics
    /// If a dimension is zero (programming error; use [`ImageF32::from_vec`] for untrusted sizes).
    pub fn filled(width: usize, height: usize, channels: usize, value: f32) -> Self {
        assert!(
            width > 0 && height > 0 && channels > 0,
            "zero image dimension"
        );
        Self {
            width,
            height,
            channels,
            data: vec![value; width * height * channels],
        }
    }

    /// Builds a single-channel image from `f(x, y)`.
    pub fn from_fn(width: usize, height: usize, mut f: impl FnMut(usize, usize) -> f32) -> Self {
        let mut img = Self::filled(width, height, 1, 0.0);
        for y in 0..height {
            for x in 0..width {
                img.data[y * width + x] = f(x, y);
            }
        }
        img
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }
    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }
    /// Number of interleaved channels.
    pub fn channels(&self) -> usize {
        self.channels
    }
    /// `(width, height)`.
    pub fn dims(&self) -> (usize, usize) {
        (self.width, self.height)
    }
    /// Number of pixels (`width·height`).
    pub fn pixel_count(&self) -> usize {
        self.width * self.height
    }
    /// All samples.
    pub fn data(&self) -> &[f32] {
        &self.data
    }
    /// All samples, mutable.
    pub fn data_mut(&mut self) -> &mut [f32] {
        &mut self.data
    }
    /// Consumes the image, returning its samples.
    pub fn into_vec(self) -> Vec<f32> {
        self.data
    }
    /// Sample at `(x, y, ch)`. Panics when out of bounds (caller's indices, not user data).
    #[inline]
    pub fn get(&self, x: usize, y: usize, ch: usize) -> f32 {
        self.data[(y * self.width + x) * self.channels + ch]
    }
    /// Sets the sample at `(x, y, ch)`.
    #[inline]
    pub fn set(&mut self, x: usize, y: usize, ch: usize, v: f32) {
        self.data[(y * self.width + x) * self.channels + ch] = v;
    }

    /// Fails with the first non-finite sample's position, naming no field (callers add it).
    pub fn ensure_finite(&self) -> Result<()> {
        // Whole blocks tested without an early exit (a vector loop), then the first bad value
        // looked for in the first block that has one: every call scans the whole image, and a
        // scalar scan that stops at the first bad value took about 1 ms per 640×480 RGB view.
        const BLOCK: usize = 256;
        let first_bad = self
            .data
            .chunks(BLOCK)
            .position(|block| !block.iter().fold(true, |ok, v| ok & v.is_finite()))
            .and_then(|b| {
                let block = &self.data[b * BLOCK..];
                block
                    .iter()
                    .position(|v| !v.is_finite())
                    .map(|i| b * BLOCK + i)
            });
        if let Some(i) = first_bad {
            let px = i / self.channels;
            return Err(MurkError::invalid(
                "",
                format!(
                    "non-finite sample {} at pixel ({}, {})",
                    self.data[i],
                    px % self.width,
                    px / self.width
                ),
            ));
        }
        Ok(())
    }

    /// Fails unless the image has exactly `channels` channels.
    pub fn ensure_channels(&self, channels: usize) -> Result<()> {
        if self.channels != channels {
            return Err(MurkError::invalid(
                "",
                format!("expected {channels} channel(s), got {}", self.channels),
            ));
        }
        Ok(())
    }

    /// The image as one channel, for inputs that are single-channel by nature (ToF amplitude
    /// and phase, photometric-stereo images and masks). The rule: one channel is kept; grey +
    /// alpha (2 channels) keeps the grey channel; RGB or RGBA (3 or 4 channels) is accepted when
    /// R, G and B are equal at every pixel (a grey image saved as colour) and gives that
    /// channel, alpha ignored. Differing colour channels are an error naming the first pixel
    /// where they differ, since averaging them would silently change the measurement.
    pub fn into_mono(self) -> Result<ImageF32> {
        match self.channels {
            1 => Ok(self),
            2 => Ok(self.channel(0)),
            3 | 4 => {
                let c = self.channels;
                let differs = self.data.chunks_exact(c).position(|px| {
                    px[0].to_bits() != px[1].to_bits() || px[0].to_bits() != px[2].to_bits()
                });
                match differs {
                    None => Ok(self.channel(0)),
                    Some(i) => Err(MurkError::invalid(
                        "",
                        format!(
                            "a single-channel image is needed; this one has {c} channels whose \
                             R, G, B differ (first at pixel ({}, {})). Store it as one channel \
                             (grey PNG/TIFF, OpenEXR `Y`, `Z`, `R` or any single channel) or as \
                             three equal channels",
                            i % self.width,
                            i / self.width
                        ),
                    )),
                }
            }
            c => Err(MurkError::invalid(
                "",
                format!("a single-channel image is needed; this one has {c} channels"),
            )),
        }
    }

    /// Single channel `ch` as a new one-channel image.
    pub fn channel(&self, ch: usize) -> ImageF32 {
        let data = self
            .data
            .chunks_exact(self.channels)
            .map(|p| p[ch])
            .collect();
        ImageF32 {
            width: self.width,
            height: self.height,
            channels: 1,
            data,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn into_mono_accepts_equal_colour_channels_only() {
        let grey = ImageF32::from_vec(2, 1, 3, vec![0.5, 0.5, 0.5, 0.25, 0.25, 0.25]).unwrap();
        assert_eq!(grey.into_mono().unwrap().data(), &[0.5, 0.25]);
        let rgba = ImageF32::from_vec(1, 1, 4, vec![0.5, 0.5, 0.5, 1.0]).unwrap();
        assert_eq!(rgba.into_mono().unwrap().data(), &[0.5]);
        let ya = ImageF32::from_vec(1, 1, 2, vec![0.7, 1.0]).unwrap();
        assert_eq!(ya.into_mono().unwrap().data(), &[0.7]);
        let colour = ImageF32::from_vec(2, 1, 3, vec![0.5, 0.5, 0.5, 0.2, 0.3, 0.2]).unwrap();
        let e = colour.into_mono().unwrap_err().to_string();
        assert!(e.contains("(1, 0)"), "{e}");
        let one = ImageF32::filled(2, 2, 1, 3.0);
        assert_eq!(one.clone().into_mono().unwrap(), one);
    }

    #[test]
    fn rejects_wrong_length_and_zero_size() {
        assert!(ImageF32::from_vec(2, 2, 1, vec![0.0; 3]).is_err());
        assert!(ImageF32::from_vec(0, 2, 1, vec![]).is_err());
        assert!(ImageF32::from_vec(2, 2, 1, vec![0.0; 4]).is_ok());
    }

    #[test]
    fn finite_check_reports_position() {
        let mut img = ImageF32::filled(3, 2, 1, 1.0);
        img.set(2, 1, 0, f32::NAN);
        let err = img.ensure_finite().unwrap_err().to_string();
        assert!(err.contains("(2, 1)"), "{err}");
        // Past the first block of the scan, with a later block bad too: the first is named.
        let mut big = ImageF32::filled(300, 4, 3, 0.5);
        big.set(7, 1, 2, f32::INFINITY);
        big.set(250, 3, 0, f32::NAN);
        let err = big.ensure_finite().unwrap_err().to_string();
        assert!(err.contains("inf at pixel (7, 1)"), "{err}");
        big.set(7, 1, 2, 0.5);
        let err = big.ensure_finite().unwrap_err().to_string();
        assert!(err.contains("NaN at pixel (250, 3)"), "{err}");
        big.set(250, 3, 0, 0.5);
        assert!(big.ensure_finite().is_ok());
    }
}

/// The sRGB electro-optical transfer function (IEC 61966-2-1): an sRGB-encoded value in `[0, 1]`
/// to linear light. Values outside `[0, 1]` follow the formula's pieces (linear below the knee).
#[inline]
pub fn srgb_to_linear(v: f32) -> f32 {
    if v <= 0.04045 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

/// Decodes every sample of an sRGB-encoded `image` to linear light ([`srgb_to_linear`]): the
/// scattering models hold for light, and cameras store 8-bit images encoded.
pub fn decode_srgb(image: &mut ImageF32) {
    for v in image.data_mut() {
        *v = srgb_to_linear(*v);
    }
}

#[cfg(test)]
mod srgb_tests {
    use super::*;

    #[test]
    fn srgb_decoding_matches_the_standard() {
        assert_eq!(srgb_to_linear(0.0), 0.0);
        assert!((srgb_to_linear(1.0) - 1.0).abs() < 1e-6);
        // Mid-grey 0.5 encoded is 21.4 % of the light; the knee is continuous.
        assert!((srgb_to_linear(0.5) - 0.21404).abs() < 1e-4);
        let knee = 0.04045f32;
        assert!((srgb_to_linear(knee) - srgb_to_linear(knee + 1e-6)).abs() < 1e-6);
        let mut img = ImageF32::from_vec(2, 1, 1, vec![0.0, 0.5]).unwrap();
        decode_srgb(&mut img);
        assert!((img.data()[1] - 0.21404).abs() < 1e-4);
    }
}
