//! The bounds every image decode is held to ([`DecodeLimits`]), checked against a file's
//! header before its pixels are allocated.

use crate::error::{MurkError, Result};

/// Bounds applied to every decode, checked against the header before pixel memory is allocated.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DecodeLimits {
    /// Largest accepted `width·height`.
    pub max_pixels: u64,
    /// Largest accepted number of channels in the decoded image.
    pub max_channels: usize,
}

impl Default for DecodeLimits {
    /// 64 Mpx and 4 channels: a 16-bit RGBA image of that size already needs 1 GiB as f32.
    fn default() -> Self {
        Self {
            max_pixels: 64 * 1024 * 1024,
            max_channels: 4,
        }
    }
}

impl DecodeLimits {
    /// Bytes of `f32` output the limits allow, the basis of every allocation budget.
    pub(crate) fn max_output_bytes(&self) -> u64 {
        self.max_pixels
            .saturating_mul(self.max_channels as u64)
            .saturating_mul(4)
    }

    /// Fails unless a `width × height` image with `channels` channels fits the limits.
    pub(crate) fn check(&self, width: u64, height: u64, channels: usize) -> Result<()> {
        if width == 0 || height == 0 {
            return Err(MurkError::invalid(
                "",
                format!("image has an empty size {width}x{height}"),
            ));
        }
        let pixels = width.saturating_mul(height);
        if pixels > self.max_pixels {
            return Err(MurkError::invalid(
                "",
                format!(
                    "image of {width}x{height} = {pixels} pixels exceeds the limit of {} pixels",
                    self.max_pixels
                ),
            ));
        }
        if channels == 0 || channels > self.max_channels {
            return Err(MurkError::invalid(
                "",
                format!(
                    "image has {channels} channel(s); at most {} supported",
                    self.max_channels
                ),
            ));
        }
        Ok(())
    }
}
