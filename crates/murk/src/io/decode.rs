//! Format sniffing and bounded decoding of untrusted image bytes.
//!
//! Sample scaling: 8-bit integers are divided by 255 and 16-bit integers by 65535, so every
//! integer format decodes to `[0, 1]`; float TIFF and every EXR channel type (half, float, uint)
//! decode to their stored values. Channel order is the file's: gray, gray+alpha, RGB or RGBA for
//! PNG/TIFF; for EXR see [`super::exr`]. TIFF support is that of `image` 0.25: 8/16-bit gray,
//! gray+alpha, RGB(A) and 32-bit float RGB(A); single-channel float TIFF is rejected with an
//! "unsupported" error (store float maps as EXR).

use std::fmt;
use std::io::Cursor;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::Path;

use image::codecs::png::PngDecoder;
use image::codecs::tiff::TiffDecoder;
use image::{ColorType, ImageDecoder, ImageError};

use super::io_error;
use super::limits::DecodeLimits;
use crate::error::{MurkError, Result};
use crate::image::ImageF32;

/// Image container formats recognised by their magic bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ImageFormat {
    /// PNG (`89 50 4E 47 0D 0A 1A 0A`).
    Png,
    /// TIFF or BigTIFF, little- (`II`) or big-endian (`MM`).
    Tiff,
    /// OpenEXR (`76 2F 31 01`).
    Exr,
}

impl fmt::Display for ImageFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            ImageFormat::Png => "PNG",
            ImageFormat::Tiff => "TIFF",
            ImageFormat::Exr => "OpenEXR",
        })
    }
}

/// Recognises the container format from the first bytes; `None` for anything else.
pub fn sniff_format(bytes: &[u8]) -> Option<ImageFormat> {
    const PNG: &[u8] = &[0x89, b'P', b'N', b'G', 0x0D, 0x0A, 0x1A, 0x0A];
    const EXR: &[u8] = &[0x76, 0x2F, 0x31, 0x01];
    if bytes.starts_with(PNG) {
        Some(ImageFormat::Png)
    } else if bytes.starts_with(EXR) {
        Some(ImageFormat::Exr)
    } else if bytes.starts_with(b"II*\0")
        || bytes.starts_with(b"MM\0*")
        || bytes.starts_with(b"II+\0")
        || bytes.starts_with(b"MM\0+")
    {
        Some(ImageFormat::Tiff)
    } else {
        None
    }
}

/// Decodes PNG, TIFF or OpenEXR bytes (format sniffed from the magic bytes) into an f32 image.
///
/// Integer samples are scaled to `[0, 1]`, float samples kept as stored (see the module docs).
/// The header's size and channel count are checked against `limits` before pixel memory is
/// allocated. Every failure — unknown format, truncated or corrupt data, limits exceeded — is
/// `InvalidArgument` with an empty field for the caller to prefix; a panic inside a third-party
/// decoder on hostile input is caught and reported the same way.
pub fn decode_image(bytes: &[u8], limits: &DecodeLimits) -> Result<ImageF32> {
    let format = sniff_format(bytes).ok_or_else(|| {
        MurkError::invalid(
            "",
            format!(
                "unrecognised image format (first bytes {:02x?}); expected PNG, TIFF or OpenEXR",
                &bytes[..bytes.len().min(8)]
            ),
        )
    })?;
    let decoded = catch_unwind(AssertUnwindSafe(|| match format {
        ImageFormat::Png => png_complete(bytes)
            .and_then(|_| PngDecoder::new(Cursor::new(bytes)).map_err(|e| image_error(format, e)))
            .and_then(|d| decode_with(d, format, limits)),
        ImageFormat::Tiff => match float_grey_tiff(bytes, limits) {
            Some(r) => r,
            None => TiffDecoder::new(Cursor::new(bytes))
                .map_err(|e| image_error(format, e))
                .and_then(|d| decode_with(d, format, limits)),
        },
        ImageFormat::Exr => super::exr::decode_exr(bytes, limits),
    }));
    decoded.unwrap_or_else(|_| {
        Err(MurkError::invalid(
            "",
            format!("corrupt {format} data (the decoder rejected it)"),
        ))
    })
}

/// Reads and decodes the image file at `path`; file-system failures are `MurkError::Io`, decoding
/// failures `InvalidArgument` as in [`decode_image`].
pub fn read_image(path: &Path, limits: &DecodeLimits) -> Result<ImageF32> {
    let meta = std::fs::metadata(path).map_err(|e| io_error(path, e))?;
    // Even uncompressed files hold at most ~2× the f32 output; the slack covers headers and
    // offset tables. Refusing larger files keeps a stray multi-gigabyte file out of memory.
    let max_file = limits
        .max_output_bytes()
        .saturating_mul(2)
        .saturating_add(64 << 20);
    if meta.len() > max_file {
        return Err(MurkError::invalid(
            "",
            format!(
                "{} is {} bytes, more than an image within the limits can need ({max_file})",
                path.display(),
                meta.len()
            ),
        ));
    }
    let bytes = std::fs::read(path).map_err(|e| io_error(path, e))?;
    decode_image(&bytes, limits)
}

/// Walks the PNG chunk list to its `IEND`: the decoder stops after the pixel data, so without this
/// a file cut inside its last chunk would pass as complete.
fn png_complete(bytes: &[u8]) -> Result<()> {
    let mut pos = 8usize;
    loop {
        let header = bytes
            .get(pos..pos + 8)
            .ok_or_else(|| MurkError::invalid("", "truncated PNG data (no IEND chunk)"))?;
        let len = u32::from_be_bytes([header[0], header[1], header[2], header[3]]) as usize;
        let end = pos
            .checked_add(12)
            .and_then(|p| p.checked_add(len))
            .filter(|&e| e <= bytes.len())
            .ok_or_else(|| {
                MurkError::invalid("", "truncated PNG data (chunk runs past the end)")
            })?;
        if &header[4..8] == b"IEND" {
            return Ok(());
        }
        pos = end;
    }
}

fn image_error(format: ImageFormat, e: ImageError) -> MurkError {
    match e {
        ImageError::Limits(l) => {
            MurkError::invalid("", format!("{format} image exceeds the decode limits: {l}"))
        }
        other => MurkError::invalid("", format!("corrupt or unsupported {format} data: {other}")),
    }
}

/// Single-channel floating-point TIFF (32- or 64-bit IEEE samples: the usual layout of depth,
/// range and phase maps), which the `image` crate does not decode; `None` for every other TIFF.
fn float_grey_tiff(bytes: &[u8], limits: &DecodeLimits) -> Option<Result<ImageF32>> {
    use tiff::decoder::{Decoder, DecodingResult};
    use tiff::tags::{SampleFormat, Tag};
    let mut d = Decoder::new(Cursor::new(bytes)).ok()?;
    let bits = match d.colortype().ok()? {
        tiff::ColorType::Gray(b @ (32 | 64)) => b,
        _ => return None,
    };
    let float = d
        .get_tag_u32(Tag::SampleFormat)
        .is_ok_and(|f| f == SampleFormat::IEEEFP.to_u16() as u32);
    if !float {
        return None;
    }
    let fail = |e: tiff::TiffError| MurkError::invalid("", format!("corrupt TIFF data: {e}"));
    Some((|| {
        let (w, h) = d.dimensions().map_err(fail)?;
        limits.check(u64::from(w), u64::from(h), 1)?;
        let mut lim = tiff::decoder::Limits::default();
        let budget = (limits.max_output_bytes().saturating_mul(2) as usize).max(64 << 20);
        lim.decoding_buffer_size = budget;
        lim.intermediate_buffer_size = budget;
        let mut d = d.with_limits(lim);
        let data: Vec<f32> = match d.read_image().map_err(fail)? {
            DecodingResult::F32(v) => v,
            DecodingResult::F64(v) => v.into_iter().map(|x| x as f32).collect(),
            _ => {
                return Err(MurkError::invalid(
                    "",
                    format!("unsupported {bits}-bit floating-point TIFF layout"),
                ))
            }
        };
        ImageF32::from_vec(w as usize, h as usize, 1, data)
    })())
}

fn decode_with(
    mut decoder: impl ImageDecoder,
    format: ImageFormat,
    limits: &DecodeLimits,
) -> Result<ImageF32> {
    let (w, h) = decoder.dimensions();
    let color = decoder.color_type();
    let channels = color.channel_count() as usize;
    limits.check(u64::from(w), u64::from(h), channels)?;
    // The decoder's own budget: its output buffer plus the same again for intermediate state,
    // with a floor so tight pixel limits do not starve fixed-size buffers (zlib windows, strips).
    let mut lim = image::Limits::default();
    lim.max_alloc = Some(limits.max_output_bytes().saturating_mul(2).max(64 << 20));
    decoder
        .set_limits(lim)
        .map_err(|e| image_error(format, e))?;
    let total = usize::try_from(decoder.total_bytes())
        .map_err(|_| MurkError::invalid("", format!("{format} image too large")))?;
    let mut buf = vec![0u8; total];
    decoder
        .read_image(&mut buf)
        .map_err(|e| image_error(format, e))?;
    // ImageDecoder output is native-endian.
    let data: Vec<f32> = match color {
        ColorType::L8 | ColorType::La8 | ColorType::Rgb8 | ColorType::Rgba8 => {
            buf.iter().map(|&b| f32::from(b) / 255.0).collect()
        }
        ColorType::L16 | ColorType::La16 | ColorType::Rgb16 | ColorType::Rgba16 => buf
            .chunks_exact(2)
            .map(|b| f32::from(u16::from_ne_bytes([b[0], b[1]])) / 65535.0)
            .collect(),
        ColorType::Rgb32F | ColorType::Rgba32F => buf
            .chunks_exact(4)
            .map(|b| f32::from_ne_bytes([b[0], b[1], b[2], b[3]]))
            .collect(),
        other => {
            return Err(MurkError::invalid(
                "",
                format!("unsupported {format} colour type {other:?}"),
            ))
        }
    };
    ImageF32::from_vec(w as usize, h as usize, channels, data)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::{encode_exr, encode_png16};
    use image::codecs::png::PngEncoder;
    use image::codecs::tiff::TiffEncoder;
    use image::{ExtendedColorType, ImageEncoder};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn gradient(w: usize, h: usize, c: usize) -> ImageF32 {
        let data = (0..w * h * c)
            .map(|i| (i % 97) as f32 / 96.0)
            .collect::<Vec<_>>();
        ImageF32::from_vec(w, h, c, data).unwrap()
    }

    fn encode_png(buf: &[u8], w: u32, h: u32, ct: ExtendedColorType) -> Vec<u8> {
        let mut out = Vec::new();
        PngEncoder::new(&mut out)
            .write_image(buf, w, h, ct)
            .unwrap();
        out
    }

    fn assert_invalid(r: Result<ImageF32>) -> String {
        match r {
            Err(MurkError::InvalidArgument { field, reason }) => {
                assert_eq!(field, "");
                reason
            }
            other => panic!("expected InvalidArgument, got {other:?}"),
        }
    }

    #[test]
    fn png_8_and_16_bit_all_layouts_scale_to_unit_range() {
        let lim = DecodeLimits::default();
        for (ct, c) in [
            (ExtendedColorType::L8, 1),
            (ExtendedColorType::La8, 2),
            (ExtendedColorType::Rgb8, 3),
            (ExtendedColorType::Rgba8, 4),
        ] {
            let raw: Vec<u8> = (0..5 * 3 * c).map(|i| (i * 17 % 256) as u8).collect();
            let img = decode_image(&encode_png(&raw, 5, 3, ct), &lim).unwrap();
            assert_eq!((img.width(), img.height(), img.channels()), (5, 3, c));
            for (a, b) in img.data().iter().zip(&raw) {
                assert_eq!(*a, f32::from(*b) / 255.0);
            }
        }
        for (ct, c) in [
            (ExtendedColorType::L16, 1),
            (ExtendedColorType::La16, 2),
            (ExtendedColorType::Rgb16, 3),
            (ExtendedColorType::Rgba16, 4),
        ] {
            let vals: Vec<u16> = (0..4 * 2 * c).map(|i| (i * 4099 % 65536) as u16).collect();
            let raw: Vec<u8> = vals.iter().flat_map(|v| v.to_ne_bytes()).collect();
            let img = decode_image(&encode_png(&raw, 4, 2, ct), &lim).unwrap();
            assert_eq!(img.channels(), c);
            for (a, b) in img.data().iter().zip(&vals) {
                assert_eq!(*a, f32::from(*b) / 65535.0);
            }
        }
    }

    #[test]
    fn tiff_integer_and_float_decode() {
        let lim = DecodeLimits::default();
        let vals: Vec<u16> = (0..6).map(|i| i * 10000).collect();
        let raw: Vec<u8> = vals.iter().flat_map(|v| v.to_ne_bytes()).collect();
        let mut out = Cursor::new(Vec::new());
        TiffEncoder::new(&mut out)
            .write_image(&raw, 3, 2, ExtendedColorType::L16)
            .unwrap();
        let bytes = out.into_inner();
        assert_eq!(sniff_format(&bytes), Some(ImageFormat::Tiff));
        let img = decode_image(&bytes, &lim).unwrap();
        assert_eq!(img.data()[5], 50000.0 / 65535.0);

        let f: Vec<f32> = vec![-1.5, 0.0, 2.5, 1e3, 0.25, 7.0];
        let raw: Vec<u8> = f.iter().flat_map(|v| v.to_ne_bytes()).collect();
        let mut out = Cursor::new(Vec::new());
        TiffEncoder::new(&mut out)
            .write_image(&raw, 2, 1, ExtendedColorType::Rgb32F)
            .unwrap();
        let img = decode_image(&out.into_inner(), &lim).unwrap();
        assert_eq!(img.data(), &f[..]);

        // Greyscale float32, the usual layout of depth and phase maps.
        let mut out = Cursor::new(Vec::new());
        tiff::encoder::TiffEncoder::new(&mut out)
            .unwrap()
            .write_image::<tiff::encoder::colortype::Gray32Float>(3, 2, &f)
            .unwrap();
        let bytes = out.into_inner();
        let img = decode_image(&bytes, &lim).unwrap();
        assert_eq!((img.width(), img.height(), img.channels()), (3, 2, 1));
        assert_eq!(img.data(), &f[..]);
        let tight = DecodeLimits {
            max_pixels: 5,
            ..lim
        };
        assert!(decode_image(&bytes, &tight).is_err(), "limits apply");
        assert!(decode_image(&bytes[..bytes.len() - 7], &lim).is_err());
    }

    #[test]
    fn limits_are_checked_before_decoding() {
        let png = encode_png(&[0u8; 64 * 64], 64, 64, ExtendedColorType::L8);
        let small = DecodeLimits {
            max_pixels: 1000,
            max_channels: 4,
        };
        let reason = assert_invalid(decode_image(&png, &small));
        assert!(reason.contains("exceeds"), "{reason}");
        let one_ch = DecodeLimits {
            max_pixels: 1 << 20,
            max_channels: 1,
        };
        let rgb = encode_png(&[0u8; 12], 2, 2, ExtendedColorType::Rgb8);
        assert!(assert_invalid(decode_image(&rgb, &one_ch)).contains("channel"));
        let exr = encode_exr(&gradient(64, 64, 1)).unwrap();
        assert!(assert_invalid(decode_image(&exr, &small)).contains("exceeds"));
    }

    /// A PNG header claiming 100000×100000 pixels must be rejected from the header alone.
    #[test]
    fn hostile_png_header_is_rejected_without_allocating() {
        let mut png = encode_png(&[0u8; 4], 2, 2, ExtendedColorType::L8);
        // IHDR width/height live at bytes 16..24; the CRC will then be wrong too, which is fine:
        // either check must reject it.
        png[16..20].copy_from_slice(&100_000u32.to_be_bytes());
        png[20..24].copy_from_slice(&100_000u32.to_be_bytes());
        assert_invalid(decode_image(&png, &DecodeLimits::default()));
    }

    #[test]
    fn unknown_and_empty_inputs_are_invalid() {
        let lim = DecodeLimits::default();
        assert!(assert_invalid(decode_image(b"", &lim)).contains("unrecognised"));
        assert!(assert_invalid(decode_image(b"GIF89a....", &lim)).contains("unrecognised"));
        assert_invalid(decode_image(b"II*\0", &lim));
        assert_invalid(decode_image(&[0x76, 0x2F, 0x31, 0x01], &lim));
    }

    /// Every truncation of valid PNG / EXR / TIFF files, bit flips, and seeded random bytes behind
    /// valid magic must come back as `Err` (or, for harmless flips, `Ok`) — never a panic or abort.
    #[test]
    fn fuzz_truncated_and_random_bytes_never_panic() {
        let lim = DecodeLimits {
            max_pixels: 1 << 16,
            max_channels: 4,
        };
        let img = gradient(13, 7, 1);
        let mut files = vec![
            encode_png16(&img, 0.0, 1.0).unwrap(),
            encode_exr(&img).unwrap(),
            encode_exr(&gradient(9, 5, 3)).unwrap(),
        ];
        let mut tif = Cursor::new(Vec::new());
        TiffEncoder::new(&mut tif)
            .write_image(&[7u8; 13 * 7], 13, 7, ExtendedColorType::L8)
            .unwrap();
        files.push(tif.into_inner());
        for f in &files {
            assert!(decode_image(f, &lim).is_ok());
            for len in 0..f.len() {
                assert!(
                    decode_image(&f[..len], &lim).is_err(),
                    "truncation to {len} of {} bytes decoded",
                    f.len()
                );
            }
        }
        let mut rng = ChaCha8Rng::seed_from_u64(0x5eed);
        for f in &files {
            for _ in 0..300 {
                let mut g = f.clone();
                for _ in 0..rng.random_range(1..8) {
                    let i = rng.random_range(0..g.len());
                    g[i] = rng.random();
                }
                let _ = decode_image(&g, &lim);
            }
        }
        let magics: [&[u8]; 4] = [
            &[0x89, b'P', b'N', b'G', 0x0D, 0x0A, 0x1A, 0x0A],
            &[0x76, 0x2F, 0x31, 0x01],
            b"II*\0",
            b"MM\0*",
        ];
        for _ in 0..500 {
            let n = rng.random_range(0..512);
            let mut g: Vec<u8> = (0..n).map(|_| rng.random()).collect();
            if rng.random_bool(0.8) {
                let m = magics[rng.random_range(0..magics.len())];
                g.splice(0..0, m.iter().copied());
            }
            assert!(decode_image(&g, &lim).is_err());
        }
    }

    #[test]
    fn read_image_reports_missing_file_as_io() {
        let r = read_image(
            Path::new("/nonexistent/murk/none.png"),
            &DecodeLimits::default(),
        );
        assert!(matches!(r, Err(MurkError::Io { .. })));
    }
}
