//! `murk.v1.Image` ↔ [`ImageF32`].

use crate::service::proto::v1 as pb;
use murk::error::{MurkError, Result};
use murk::image::ImageF32;
use murk::io::{decode_image, DecodeLimits};

/// Limits applied to every image in a request.
#[derive(Clone, Copy, Debug)]
pub struct ImageLimits {
    /// Largest accepted `width·height`.
    pub max_pixels: u64,
    /// Largest accepted channel count.
    pub max_channels: usize,
}

impl Default for ImageLimits {
    fn default() -> Self {
        Self {
            max_pixels: 16 << 20,
            max_channels: 4,
        }
    }
}

/// Decodes a request image. Errors name sub-fields relative to the image (`width`,
/// `raw_f32_le`, `encoded`, ...); callers prefix the image's own field name.
/// [`image_from_proto`] for inputs that are single-channel by nature, under the rule of
/// [`ImageF32::into_mono`] (3 equal channels are one): the declared `channels` may be 1 for such
/// a file.
pub fn mono_image_from_proto(img: &pb::Image, limits: &ImageLimits) -> Result<ImageF32> {
    decode_proto(img, limits, true)?.into_mono()
}

/// Decodes (or unpacks) an image message, checking declared sizes and limits, and applies its
/// value mapping.
pub fn image_from_proto(img: &pb::Image, limits: &ImageLimits) -> Result<ImageF32> {
    decode_proto(img, limits, false)
}

fn decode_proto(img: &pb::Image, limits: &ImageLimits, mono: bool) -> Result<ImageF32> {
    let decoded = match &img.data {
        None => {
            return Err(MurkError::invalid(
                "",
                "no pixel data: set `encoded`, `raw_f32_le`, `raw_f16_le` or `raw_u8`",
            ))
        }
        Some(pb::image::Data::RawF32Le(bytes)) => raw_from_proto(img, bytes, Raw::F32, limits)?,
        Some(pb::image::Data::RawF16Le(bytes)) => raw_from_proto(img, bytes, Raw::F16, limits)?,
        Some(pb::image::Data::RawU8(bytes)) => raw_from_proto(img, bytes, Raw::U8, limits)?,
        Some(pb::image::Data::Encoded(bytes)) => {
            let dl = DecodeLimits {
                max_pixels: limits.max_pixels,
                max_channels: limits.max_channels,
            };
            let decoded = decode_image(bytes, &dl).map_err(|e| e.within("encoded"))?;
            for (name, declared, actual) in [
                ("width", img.width as usize, decoded.width()),
                ("height", img.height as usize, decoded.height()),
                ("channels", img.channels as usize, decoded.channels()),
            ] {
                // A mono input may declare 1 channel for a file with equal colour channels.
                let mono_ok = mono && name == "channels" && declared == 1;
                if declared != 0 && declared != actual && !mono_ok {
                    return Err(MurkError::invalid(
                        name,
                        format!("declared {declared} but the encoded image has {actual}"),
                    ));
                }
            }
            decoded
        }
    };
    let mut out = apply_value_mapping(decoded, img.value_scale, img.value_offset)?;
    match pb::Transfer::try_from(img.transfer) {
        Ok(pb::Transfer::Unspecified | pb::Transfer::Linear) => {}
        Ok(pb::Transfer::Srgb) => murk::image::decode_srgb(&mut out),
        Err(_) => {
            return Err(MurkError::invalid(
                "transfer",
                format!(
                    "unknown transfer function {} (0 = LINEAR, 1 = SRGB)",
                    img.transfer
                ),
            ))
        }
    }
    Ok(out)
}

/// The sample type of a raw image.
#[derive(Clone, Copy)]
enum Raw {
    F32,
    F16,
    U8,
}

impl Raw {
    fn field(self) -> &'static str {
        match self {
            Raw::F32 => "raw_f32_le",
            Raw::F16 => "raw_f16_le",
            Raw::U8 => "raw_u8",
        }
    }

    fn bytes(self) -> usize {
        match self {
            Raw::F32 => 4,
            Raw::F16 => 2,
            Raw::U8 => 1,
        }
    }

    fn sample(self, b: &[u8]) -> f32 {
        match self {
            Raw::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
            Raw::F16 => half::f16::from_le_bytes([b[0], b[1]]).to_f32(),
            // As an 8-bit PNG decodes (`murk::io::decode_image`).
            Raw::U8 => f32::from(b[0]) / 255.0,
        }
    }
}

fn raw_from_proto(
    img: &pb::Image,
    bytes: &[u8],
    raw: Raw,
    limits: &ImageLimits,
) -> Result<ImageF32> {
    let (w, h) = (img.width as u64, img.height as u64);
    let c = if img.channels == 0 {
        1
    } else {
        img.channels as usize
    };
    if w == 0 || h == 0 {
        return Err(MurkError::invalid(
            if w == 0 { "width" } else { "height" },
            format!("raw images need positive width and height, got {w}x{h}"),
        ));
    }
    if w * h > limits.max_pixels {
        return Err(MurkError::invalid(
            "width",
            format!(
                "{w}x{h} = {} pixels exceeds the limit of {} pixels",
                w * h,
                limits.max_pixels
            ),
        ));
    }
    if c > limits.max_channels {
        return Err(MurkError::invalid(
            "channels",
            format!("{c} exceeds the limit of {}", limits.max_channels),
        ));
    }
    let n = (w * h) as usize;
    let expected = n * c * raw.bytes();
    if bytes.len() != expected {
        return Err(MurkError::invalid(
            raw.field(),
            format!(
                "expected {expected} bytes for {w}x{h}x{c} samples of {} bytes, got {}",
                raw.bytes(),
                bytes.len()
            ),
        ));
    }
    let mut data = vec![0f32; n * c];
    // Planar on the wire (one plane per channel), interleaved in memory; one loop per sample
    // type, so that no match runs per sample.
    fn unpack(
        data: &mut [f32],
        bytes: &[u8],
        c: usize,
        size: usize,
        sample: impl Fn(&[u8]) -> f32,
    ) {
        let n = data.len() / c;
        for (ch, plane) in bytes.chunks_exact(n * size).enumerate() {
            for (out, chunk) in data[ch..]
                .iter_mut()
                .step_by(c)
                .zip(plane.chunks_exact(size))
            {
                *out = sample(chunk);
            }
        }
    }
    match raw {
        Raw::U8 => {
            // 256 values, each as `Raw::sample` gives it.
            let table: Vec<f32> = (0..=255u8).map(|b| Raw::U8.sample(&[b])).collect();
            unpack(&mut data, bytes, c, 1, |b| table[usize::from(b[0])]);
        }
        Raw::F16 => unpack(&mut data, bytes, c, 2, |b| Raw::F16.sample(b)),
        Raw::F32 => unpack(&mut data, bytes, c, 4, |b| Raw::F32.sample(b)),
    }
    ImageF32::from_vec(w as usize, h as usize, c, data)
}

fn apply_value_mapping(mut img: ImageF32, scale: f32, offset: f32) -> Result<ImageF32> {
    let scale = if scale == 0.0 { 1.0 } else { scale };
    if !scale.is_finite() {
        return Err(MurkError::invalid(
            "value_scale",
            format!("must be finite, got {scale}"),
        ));
    }
    if !offset.is_finite() {
        return Err(MurkError::invalid(
            "value_offset",
            format!("must be finite, got {offset}"),
        ));
    }
    let mapped = scale != 1.0 || offset != 0.0;
    let mut overflow = None;
    for v in img.data_mut() {
        if mapped {
            let m = offset + scale * *v;
            if v.is_finite() && !m.is_finite() && overflow.is_none() {
                overflow = Some(*v);
            }
            *v = m;
        }
        // Subnormal samples (below 1.2e-38) become 0: no sensor resolves them, arithmetic on
        // them is slow, and their reciprocals overflow (a ToF phase scaled by 1e-45 broke the
        // method's solver, where a phase of exactly 0 is merely a range of 0).
        if v.is_subnormal() {
            *v = 0.0;
        }
    }
    if let Some(v) = overflow {
        return Err(MurkError::invalid(
            if scale != 1.0 {
                "value_scale"
            } else {
                "value_offset"
            },
            format!(
                "{offset} + {scale}·{v} is not a finite f32: the mapping overflows; rescale the \
                 samples or the mapping"
            ),
        ));
    }
    Ok(img)
}

/// Encodes an image as raw planar little-endian f32.
pub fn image_to_proto(img: &ImageF32) -> pb::Image {
    let c = img.channels();
    let n = img.pixel_count();
    let mut bytes = Vec::with_capacity(n * c * 4);
    for ch in 0..c {
        for px in 0..n {
            bytes.extend_from_slice(&img.data()[px * c + ch].to_le_bytes());
        }
    }
    pb::Image {
        width: img.width() as u32,
        height: img.height() as u32,
        channels: c as u32,
        data: Some(pb::image::Data::RawF32Le(bytes)),
        value_scale: 0.0,
        value_offset: 0.0,
        transfer: pb::Transfer::Unspecified as i32,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn raw_round_trip_multichannel() {
        let img = ImageF32::from_vec(3, 2, 2, (0..12).map(|v| v as f32).collect()).unwrap();
        let back = image_from_proto(&image_to_proto(&img), &ImageLimits::default()).unwrap();
        assert_eq!(back, img);
    }

    /// Planar 8-bit samples decode as the same 8-bit PNG does, bit for bit, with the transfer
    /// function applied; a wrong length names `raw_u8`.
    #[test]
    fn raw_u8_decodes_as_an_8_bit_png() {
        let (w, h) = (5usize, 3usize);
        let rgb: Vec<u8> = (0..w * h * 3).map(|i| (i * 37 % 256) as u8).collect();
        let planar: Vec<u8> = (0..3)
            .flat_map(|c| (0..w * h).map(move |px| (c, px)))
            .map(|(c, px)| rgb[px * 3 + c])
            .collect();
        for transfer in [pb::Transfer::Unspecified, pb::Transfer::Srgb] {
            let png = pb::Image {
                data: Some(pb::image::Data::Encoded(
                    murk::io::encode_png_rgb8(w, h, &rgb).unwrap(),
                )),
                transfer: transfer as i32,
                ..Default::default()
            };
            let raw = pb::Image {
                width: w as u32,
                height: h as u32,
                channels: 3,
                data: Some(pb::image::Data::RawU8(planar.clone())),
                transfer: transfer as i32,
                ..Default::default()
            };
            let limits = ImageLimits::default();
            assert_eq!(
                image_from_proto(&raw, &limits).unwrap(),
                image_from_proto(&png, &limits).unwrap()
            );
        }
        let short = pb::Image {
            width: w as u32,
            height: h as u32,
            channels: 3,
            data: Some(pb::image::Data::RawU8(planar[1..].to_vec())),
            ..Default::default()
        };
        let e = image_from_proto(&short, &ImageLimits::default()).unwrap_err();
        assert!(matches!(e, MurkError::InvalidArgument { ref field, .. } if field == "raw_u8"));
    }

    #[test]
    fn raw_errors_name_fields() {
        let mut p = image_to_proto(&ImageF32::filled(4, 4, 1, 1.0));
        p.height = 5;
        let e = image_from_proto(&p, &ImageLimits::default()).unwrap_err();
        assert!(matches!(e, MurkError::InvalidArgument { ref field, .. } if field == "raw_f32_le"));
        p.height = 0;
        let e = image_from_proto(&p, &ImageLimits::default()).unwrap_err();
        assert!(matches!(e, MurkError::InvalidArgument { ref field, .. } if field == "height"));
        let limits = ImageLimits {
            max_pixels: 8,
            max_channels: 4,
        };
        p.height = 4;
        let e = image_from_proto(&p, &limits).unwrap_err();
        assert!(e.to_string().contains("exceeds the limit"));
    }

    #[test]
    fn value_mapping_applies() {
        let mut p = image_to_proto(&ImageF32::filled(2, 2, 1, 0.5));
        p.value_scale = 2.0;
        p.value_offset = 1.0;
        let img = image_from_proto(&p, &ImageLimits::default()).unwrap();
        assert_eq!(img.data(), &[2.0; 4]);
    }

    /// An sRGB-encoded image arrives in linear light, after the affine mapping; an unknown
    /// transfer function is refused naming the field.
    #[test]
    fn srgb_images_are_decoded_to_linear_light() {
        let mut p = image_to_proto(&ImageF32::filled(2, 2, 1, 0.25));
        p.value_scale = 2.0;
        p.transfer = pb::Transfer::Srgb as i32;
        let img = image_from_proto(&p, &ImageLimits::default()).unwrap();
        for v in img.data() {
            assert!((v - 0.21404).abs() < 1e-4, "{v}");
        }
        p.transfer = 7;
        let e = image_from_proto(&p, &ImageLimits::default()).unwrap_err();
        assert!(matches!(e, MurkError::InvalidArgument { ref field, .. } if field == "transfer"));
    }
}
