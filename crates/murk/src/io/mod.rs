//! Image codecs: decoding untrusted PNG / TIFF / OpenEXR bytes into [`ImageF32`](crate::ImageF32)
//! under explicit size limits, and writing EXR, 16-bit PNG and colour-mapped PNG previews.
//!
//! Decoding errors are `MurkError::InvalidArgument` with an empty field, so callers prefix the
//! request field (`err.within("tof.amplitude")`); file errors are `MurkError::Io`.

mod colormap;
mod decode;
mod exr;
mod limits;
mod png;

pub use colormap::{colorize, preview_range, turbo, write_colormap_png, MASKED_RGB};
pub use decode::{decode_image, read_image, sniff_format, ImageFormat};
pub use exr::{encode_exr, write_exr};
pub use limits::DecodeLimits;
pub use png::{
    encode_png16, encode_png_grey, encode_png_rgb8, write_png16, write_png_rgb8, PngEffort,
};

use crate::error::MurkError;
use std::path::Path;

/// `MurkError::Io` for `path`.
pub(crate) fn io_error(path: &Path, err: impl std::fmt::Display) -> MurkError {
    MurkError::Io {
        path: path.display().to_string(),
        reason: err.to_string(),
    }
}

/// Writes `bytes` to `path`, mapping failures to `MurkError::Io`.
pub(crate) fn write_file(path: &Path, bytes: &[u8]) -> crate::Result<()> {
    std::fs::write(path, bytes).map_err(|e| io_error(path, e))
}
