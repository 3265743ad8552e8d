//! ROS images in and out: a `sensor_msgs/Image` or `CompressedImage` becomes the API's
//! [`pb::Image`] (samples in the API's convention: integers to [0, 1], floats as stored); a
//! result image becomes a `32FC1` or `mono8` `sensor_msgs/Image` (REP 118: depth in metres, NaN
//! where there is no measurement).

use murk::ImageF32;

use super::msgs::{CompressedImage, Header, Image};
use crate::service::proto::v1 as pb;

/// An image message as read from a bag.
#[derive(Debug, Clone)]
pub enum RosImage {
    /// `sensor_msgs/Image`.
    Raw(Image),
    /// `sensor_msgs/CompressedImage`.
    Compressed(CompressedImage),
}

impl RosImage {
    /// The message's header.
    pub fn header(&self) -> &Header {
        match self {
            RosImage::Raw(i) => &i.header,
            RosImage::Compressed(i) => &i.header,
        }
    }
}

/// How samples map to the values a method expects.
#[derive(Clone, Copy, Debug)]
pub struct SampleMapping {
    /// Multiplies every decoded sample (after integers are mapped to [0, 1]).
    pub scale: f32,
    /// 8-bit images are sRGB-encoded: decode them to linear light.
    pub srgb: bool,
}

/// A decoded image for the API, with its size.
#[derive(Debug, Clone)]
pub struct ApiImage {
    /// The image as a request carries it.
    pub image: pb::Image,
    /// Width and height, pixels.
    pub dims: (usize, usize),
}

/// Converts an image message; the error says what is wrong with it (the caller names the topic
/// and the stamp).
pub fn to_api_image(img: &RosImage, mapping: SampleMapping) -> Result<ApiImage, String> {
    let Planes {
        width: w,
        height: h,
        planes,
    } = match img {
        RosImage::Raw(m) => raw_planes(m)?,
        RosImage::Compressed(m) => compressed_planes(m)?,
    };
    // 8-bit samples travel as they are (a quarter of the bytes of f32), and the server maps
    // them to [0, 1] as it maps an 8-bit file.
    let (channels, data, eight_bit) = match planes {
        Samples::U8(planes) => (planes.len(), pb::image::Data::RawU8(planes.concat()), true),
        Samples::F32(planes) => {
            let mut bytes = Vec::with_capacity(w * h * planes.len() * 4);
            for v in planes.iter().flatten() {
                bytes.extend_from_slice(&v.to_le_bytes());
            }
            (planes.len(), pb::image::Data::RawF32Le(bytes), false)
        }
    };
    Ok(ApiImage {
        image: pb::Image {
            width: w as u32,
            height: h as u32,
            channels: channels as u32,
            data: Some(data),
            value_scale: mapping.scale,
            value_offset: 0.0,
            transfer: if mapping.srgb && eight_bit {
                pb::Transfer::Srgb
            } else {
                pb::Transfer::Unspecified
            } as i32,
        },
        dims: (w, h),
    })
}

/// A decoded image: 1 or 3 planes of samples.
struct Planes {
    width: usize,
    height: usize,
    planes: Samples,
}

/// The planes' samples.
enum Samples {
    /// 8-bit samples as recorded (a camera usually stores them sRGB-encoded).
    U8(Vec<Vec<u8>>),
    /// Other samples, integers mapped to [0, 1].
    F32(Vec<Vec<f32>>),
}

/// Planes of a raw image.
fn raw_planes(m: &Image) -> Result<Planes, String> {
    let (w, h) = (m.width as usize, m.height as usize);
    if w == 0 || h == 0 {
        return Err(format!("{w}×{h} image"));
    }
    // (bytes per sample, channels, order of r, g, b among them)
    let (bytes, channels, order): (usize, usize, [usize; 3]) = match m.encoding.as_str() {
        "mono8" | "8UC1" => (1, 1, [0; 3]),
        "rgb8" => (1, 3, [0, 1, 2]),
        "bgr8" => (1, 3, [2, 1, 0]),
        "rgba8" => (1, 4, [0, 1, 2]),
        "bgra8" => (1, 4, [2, 1, 0]),
        "mono16" | "16UC1" => (2, 1, [0; 3]),
        "32FC1" => (4, 1, [0; 3]),
        other => {
            return Err(format!(
                "encoding `{other}` is not read (mono8, 8UC1, rgb8, bgr8, rgba8, bgra8, mono16, \
                 16UC1, 32FC1 are)"
            ))
        }
    };
    let row = w * bytes * channels;
    let step = m.step as usize;
    if step < row {
        return Err(format!(
            "step {step} is shorter than a row of {w} {} pixels ({row} bytes)",
            m.encoding
        ));
    }
    let need = step * (h - 1) + row;
    if m.data.len() < need {
        return Err(format!(
            "{} data bytes, {w}×{h} {} with step {step} needs {need}",
            m.data.len(),
            m.encoding
        ));
    }
    let big = m.is_bigendian != 0;
    // Samples wider than 8 bits (8-bit ones are sent as they are).
    let sample = |p: &[u8]| -> f32 {
        match bytes {
            2 => {
                let v = if big {
                    u16::from_be_bytes([p[0], p[1]])
                } else {
                    u16::from_le_bytes([p[0], p[1]])
                };
                f32::from(v) / 65535.0
            }
            _ => {
                let b = [p[0], p[1], p[2], p[3]];
                if big {
                    f32::from_be_bytes(b)
                } else {
                    f32::from_le_bytes(b)
                }
            }
        }
    };
    let planes = if bytes == 1 {
        Samples::U8(planes_of(m, step, row, channels, order, 1, |p| p[0]))
    } else {
        Samples::F32(planes_of(m, step, row, channels, order, bytes, sample))
    };
    Ok(Planes {
        width: w,
        height: h,
        planes,
    })
}

/// The planes of `m`'s rows (`row` bytes of pixels every `step` bytes): plane `c` holds each
/// pixel's sample `order[c]` (its only one for grey; alpha is left out), `size` bytes converted
/// by `sample`.
fn planes_of<T>(
    m: &Image,
    step: usize,
    row: usize,
    channels: usize,
    order: [usize; 3],
    size: usize,
    sample: impl Fn(&[u8]) -> T,
) -> Vec<Vec<T>> {
    let h = m.height as usize;
    let out_channels = channels.min(3);
    let mut planes: Vec<Vec<T>> = (0..out_channels)
        .map(|_| Vec::with_capacity(m.width as usize * h))
        .collect();
    for y in 0..h {
        for px in m.data[y * step..y * step + row].chunks_exact(size * channels) {
            for (c, plane) in planes.iter_mut().enumerate() {
                let k = if channels == 1 { 0 } else { order[c] };
                plane.push(sample(&px[k * size..(k + 1) * size]));
            }
        }
    }
    planes
}

/// The three planes of an RGB image.
fn rgb_planes<P: image::Pixel>(
    img: &image::ImageBuffer<P, Vec<P::Subpixel>>,
) -> Vec<Vec<P::Subpixel>> {
    (0..3)
        .map(|c| img.pixels().map(|p| p.channels()[c]).collect())
        .collect()
}

/// Planes of a PNG or JPEG `CompressedImage` (the format string is only a hint: the bytes'
/// magic decides).
fn compressed_planes(m: &CompressedImage) -> Result<Planes, String> {
    let format = if m.data.starts_with(b"\x89PNG\r\n\x1a\n") {
        image::ImageFormat::Png
    } else if m.data.starts_with(&[0xFF, 0xD8, 0xFF]) {
        image::ImageFormat::Jpeg
    } else {
        return Err(format!(
            "format `{}`: the data is neither PNG nor JPEG (compressedDepth and other \
             image_transport formats are not read)",
            m.format
        ));
    };
    let decoded = image::load_from_memory_with_format(&m.data, format)
        .map_err(|e| format!("format `{}`: {e}", m.format))?;
    let (w, h) = (decoded.width() as usize, decoded.height() as usize);
    let eight_bit = matches!(
        decoded.color(),
        image::ColorType::L8 | image::ColorType::Rgb8 | image::ColorType::Rgba8
    );
    let grey = decoded.color().channel_count() <= 2;
    let planes = match (eight_bit, grey) {
        (true, true) => Samples::U8(vec![decoded.to_luma8().into_raw()]),
        (true, false) => Samples::U8(rgb_planes(&decoded.into_rgb8())),
        (false, true) => Samples::F32(vec![decoded.to_luma32f().into_raw()]),
        (false, false) => Samples::F32(rgb_planes(&decoded.into_rgb32f())),
    };
    Ok(Planes {
        width: w,
        height: h,
        planes,
    })
}

/// A one-channel result image as `32FC1` (little-endian), with `invalid` pixels NaN.
pub fn float_image(header: &Header, img: &ImageF32, invalid: impl Fn(usize) -> bool) -> Image {
    let (w, h) = img.dims();
    let mut data = Vec::with_capacity(w * h * 4);
    for (i, v) in img.data().iter().enumerate() {
        let v = if invalid(i) { f32::NAN } else { *v };
        data.extend_from_slice(&v.to_le_bytes());
    }
    Image {
        header: header.clone(),
        height: h as u32,
        width: w as u32,
        encoding: "32FC1".into(),
        is_bigendian: 0,
        step: (w * 4) as u32,
        data,
    }
}

/// A [0, 1] result image (a mask) as `mono8`, 0 and 255 for a binary mask.
pub fn mono8_image(header: &Header, img: &ImageF32) -> Image {
    let (w, h) = img.dims();
    Image {
        header: header.clone(),
        height: h as u32,
        width: w as u32,
        encoding: "mono8".into(),
        is_bigendian: 0,
        step: w as u32,
        data: img
            .data()
            .iter()
            .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::convert::{image_from_proto, ImageLimits};

    fn decode(img: &RosImage, scale: f32) -> ImageF32 {
        let api = to_api_image(img, SampleMapping { scale, srgb: false }).unwrap();
        image_from_proto(
            &api.image,
            &ImageLimits {
                max_pixels: 1 << 20,
                max_channels: 4,
            },
        )
        .unwrap()
    }

    fn raw(encoding: &str, w: u32, h: u32, step: u32, data: Vec<u8>) -> RosImage {
        RosImage::Raw(Image {
            encoding: encoding.into(),
            width: w,
            height: h,
            step,
            data,
            ..Image::default()
        })
    }

    #[test]
    fn bgr8_with_row_padding_becomes_rgb_in_unit_range() {
        // 1×2 pixels, rows padded to 4 bytes: (b, g, r) = (0, 51, 255) and (255, 0, 0)
        let img = raw("bgr8", 1, 2, 4, vec![0, 51, 255, 9, 255, 0, 0, 9]);
        let d = decode(&img, 1.0);
        assert_eq!(d.channels(), 3);
        assert_eq!(d.data(), &[1.0, 0.2, 0.0, 0.0, 0.0, 1.0]);
    }

    #[test]
    fn sixteen_bit_and_float_samples_take_the_scale() {
        let be = raw("mono16", 1, 1, 2, vec![0xFF, 0xFF]);
        let RosImage::Raw(mut m) = be else {
            unreachable!()
        };
        m.is_bigendian = 1;
        assert_eq!(decode(&RosImage::Raw(m), 2.0).data(), &[2.0]);
        let f = raw("32FC1", 1, 1, 4, 1.5f32.to_le_bytes().to_vec());
        assert_eq!(decode(&f, 2.0).data(), &[3.0]);
    }

    #[test]
    fn unknown_encodings_and_short_data_are_named() {
        let e = to_api_image(
            &raw("yuv422", 2, 2, 4, vec![0; 8]),
            SampleMapping {
                scale: 1.0,
                srgb: false,
            },
        )
        .unwrap_err();
        assert!(e.contains("`yuv422`"), "{e}");
        let e = to_api_image(
            &raw("mono8", 4, 4, 4, vec![0; 15]),
            SampleMapping {
                scale: 1.0,
                srgb: false,
            },
        )
        .unwrap_err();
        assert!(e.contains("15 data bytes"), "{e}");
        let e = to_api_image(
            &RosImage::Compressed(CompressedImage {
                format: "16UC1; compressedDepth png".into(),
                data: vec![0; 20],
                ..CompressedImage::default()
            }),
            SampleMapping {
                scale: 1.0,
                srgb: false,
            },
        )
        .unwrap_err();
        assert!(e.contains("neither PNG nor JPEG"), "{e}");
    }

    #[test]
    fn a_png_compressed_image_decodes() {
        let mut png = Vec::new();
        image::DynamicImage::ImageLuma8(image::GrayImage::from_raw(2, 1, vec![0, 255]).unwrap())
            .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .unwrap();
        let d = decode(
            &RosImage::Compressed(CompressedImage {
                format: "png".into(),
                data: png,
                ..CompressedImage::default()
            }),
            1.0,
        );
        assert_eq!(d.data(), &[0.0, 1.0]);
    }

    #[test]
    fn results_become_float_and_mono8_images() {
        let img = ImageF32::from_vec(2, 1, 1, vec![1.25, 0.0]).unwrap();
        let f = float_image(&Header::default(), &img, |i| i == 1);
        assert_eq!(f.step, 8);
        assert_eq!(f32::from_le_bytes(f.data[..4].try_into().unwrap()), 1.25);
        assert!(f32::from_le_bytes(f.data[4..].try_into().unwrap()).is_nan());
        let m = mono8_image(
            &Header::default(),
            &ImageF32::from_vec(2, 1, 1, vec![1.0, 0.0]).unwrap(),
        );
        assert_eq!(m.data, vec![255, 0]);
    }
}
