//! PNG writers: 16-bit grayscale with an explicit value range, and 8-bit RGB.

use std::path::Path;

use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::{ExtendedColorType, ImageEncoder};

use super::write_file;
use crate::error::{MurkError, Result};
use crate::image::ImageF32;

fn dims_u32(width: usize, height: usize) -> Result<(u32, u32)> {
    match (u32::try_from(width), u32::try_from(height)) {
        (Ok(w), Ok(h)) if w > 0 && h > 0 => Ok((w, h)),
        _ => Err(MurkError::invalid(
            "",
            format!("PNG size {width}x{height} out of range"),
        )),
    }
}

fn encode(buf: &[u8], w: u32, h: u32, ct: ExtendedColorType) -> Result<Vec<u8>> {
    encode_as(PngEffort::Fast, buf, w, h, ct)
}

fn encode_as(
    effort: PngEffort,
    buf: &[u8],
    w: u32,
    h: u32,
    ct: ExtendedColorType,
) -> Result<Vec<u8>> {
    let mut out = Vec::new();
    let encoder = match effort {
        PngEffort::Fast => PngEncoder::new(&mut out),
        PngEffort::Small { predict } => PngEncoder::new_with_quality(
            &mut out,
            // Level 1: within 5-10 % of the default level's size at a sixth of its time (a
            // 512x424 depth map in 5 ms), for images encoded per frame of a stream.
            CompressionType::Level(1),
            if predict {
                FilterType::Adaptive
            } else {
                FilterType::NoFilter
            },
        ),
    };
    encoder
        .write_image(buf, w, h, ct)
        .map_err(|e| MurkError::Numerical(format!("PNG encoding failed: {e}")))?;
    Ok(out)
}

/// How a PNG is compressed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PngEffort {
    /// Quick: files written to a local disk.
    Fast,
    /// Smaller, and a little slower: images sent over a network. `predict` applies PNG's
    /// per-row predictors, which pay on smooth images (depth maps, masks) and cost on noise,
    /// where the plain samples deflate better.
    Small {
        /// Whether to filter rows with PNG's predictors.
        predict: bool,
    },
}

/// Encodes a one-channel image as 8- or 16-bit greyscale PNG, mapping `[lo, hi]` linearly to
/// `[0, 2^bits − 1]` like [`encode_png16`], with the compression `effort`.
pub fn encode_png_grey(
    img: &ImageF32,
    lo: f32,
    hi: f32,
    bits: u8,
    effort: PngEffort,
) -> Result<Vec<u8>> {
    img.ensure_channels(1)?;
    if !lo.is_finite() || !hi.is_finite() || hi <= lo {
        return Err(MurkError::invalid(
            "",
            format!("PNG range must be finite with lo < hi, got [{lo}, {hi}]"),
        ));
    }
    let (w, h) = dims_u32(img.width(), img.height())?;
    let top = match bits {
        8 => 255.0,
        16 => 65535.0,
        _ => {
            return Err(MurkError::invalid(
                "",
                format!("grey PNGs have 8 or 16 bits, got {bits}"),
            ))
        }
    };
    let (lo, span) = (f64::from(lo), f64::from(hi) - f64::from(lo));
    let quantise = |v: f32| {
        if v.is_finite() {
            (((f64::from(v) - lo) / span).clamp(0.0, 1.0) * top).round()
        } else {
            0.0
        }
    };
    if bits == 8 {
        let buf: Vec<u8> = img.data().iter().map(|&v| quantise(v) as u8).collect();
        return encode_as(effort, &buf, w, h, ExtendedColorType::L8);
    }
    let mut buf = Vec::with_capacity(img.pixel_count() * 2);
    for &v in img.data() {
        // ImageEncoder takes native-endian samples.
        buf.extend_from_slice(&(quantise(v) as u16).to_ne_bytes());
    }
    encode_as(effort, &buf, w, h, ExtendedColorType::L16)
}

/// Encodes a one-channel image as 16-bit grayscale PNG, mapping `[lo, hi]` linearly to
/// `[0, 65535]` (clamped; non-finite samples become 0). Decoding with
/// [`decode_image`](super::decode_image) returns `(v − lo)/(hi − lo)` to within 0.5/65535.
pub fn encode_png16(img: &ImageF32, lo: f32, hi: f32) -> Result<Vec<u8>> {
    encode_png_grey(img, lo, hi, 16, PngEffort::Fast)
}

/// Writes [`encode_png16`] to `path`.
pub fn write_png16(path: &Path, img: &ImageF32, lo: f32, hi: f32) -> Result<()> {
    write_file(path, &encode_png16(img, lo, hi)?)
}

/// Encodes interleaved 8-bit RGB (`rgb.len() == 3·width·height`) as PNG.
pub fn encode_png_rgb8(width: usize, height: usize, rgb: &[u8]) -> Result<Vec<u8>> {
    let (w, h) = dims_u32(width, height)?;
    if Some(rgb.len()) != width.checked_mul(height).and_then(|n| n.checked_mul(3)) {
        return Err(MurkError::invalid(
            "",
            format!(
                "RGB buffer of {} bytes does not match {width}x{height}x3",
                rgb.len()
            ),
        ));
    }
    encode(rgb, w, h, ExtendedColorType::Rgb8)
}

/// Writes [`encode_png_rgb8`] to `path`.
pub fn write_png_rgb8(path: &Path, width: usize, height: usize, rgb: &[u8]) -> Result<()> {
    write_file(path, &encode_png_rgb8(width, height, rgb)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::{decode_image, read_image, DecodeLimits};

    #[test]
    fn png16_round_trip_within_one_code() {
        let img = ImageF32::from_fn(37, 11, |x, y| 0.5 + x as f32 * 0.123 - y as f32 * 0.07);
        let (lo, hi) = (-0.5f32, 5.0f32);
        let back = decode_image(
            &encode_png16(&img, lo, hi).unwrap(),
            &DecodeLimits::default(),
        )
        .unwrap();
        assert_eq!(back.dims(), img.dims());
        for (b, v) in back.data().iter().zip(img.data()) {
            let expect = ((v - lo) / (hi - lo)).clamp(0.0, 1.0);
            assert!((b - expect).abs() <= 1.0 / 65535.0, "{b} vs {expect}");
            // And back in the original units.
            let v_back = lo + b * (hi - lo);
            assert!((v_back - v).abs() <= (hi - lo) / 65535.0 + 1e-6);
        }
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.png");
        write_png16(&p, &img, lo, hi).unwrap();
        assert_eq!(read_image(&p, &DecodeLimits::default()).unwrap(), back);
    }

    #[test]
    fn png16_clamps_and_rejects_bad_range() {
        let img = ImageF32::from_vec(3, 1, 1, vec![-10.0, f32::NAN, 10.0]).unwrap();
        let back = decode_image(
            &encode_png16(&img, 0.0, 1.0).unwrap(),
            &DecodeLimits::default(),
        )
        .unwrap();
        assert_eq!(back.data(), &[0.0, 0.0, 1.0]);
        assert!(encode_png16(&img, 1.0, 1.0).is_err());
        assert!(encode_png16(&ImageF32::filled(2, 2, 3, 0.0), 0.0, 1.0).is_err());
    }

    #[test]
    fn grey_pngs_decode_alike_whatever_the_effort() {
        let img = ImageF32::from_fn(40, 9, |x, y| ((x * 7 + y * 3) % 17) as f32 / 16.0);
        let limits = DecodeLimits::default();
        for bits in [8u8, 16] {
            let decoded: Vec<ImageF32> = [
                PngEffort::Fast,
                PngEffort::Small { predict: true },
                PngEffort::Small { predict: false },
            ]
            .into_iter()
            .map(|e| decode_image(&encode_png_grey(&img, 0.0, 1.0, bits, e).unwrap(), &limits))
            .collect::<Result<_>>()
            .unwrap();
            let step = 1.0 / ((1u32 << bits) - 1) as f32;
            for (b, v) in decoded[0].data().iter().zip(img.data()) {
                assert!(
                    (b - v).abs() <= 0.5 * step + 1e-7,
                    "{bits} bits: {b} for {v}"
                );
            }
            assert!(decoded.iter().all(|d| d == &decoded[0]));
        }
        assert!(encode_png_grey(&img, 0.0, 1.0, 12, PngEffort::Fast).is_err());
    }

    #[test]
    fn rgb8_checks_length() {
        assert!(encode_png_rgb8(2, 2, &[0; 12]).is_ok());
        assert!(encode_png_rgb8(2, 2, &[0; 11]).is_err());
        let img = decode_image(
            &encode_png_rgb8(1, 1, &[255, 0, 51]).unwrap(),
            &DecodeLimits::default(),
        )
        .unwrap();
        assert_eq!(img.data(), &[1.0, 0.0, 0.2]);
    }
}
