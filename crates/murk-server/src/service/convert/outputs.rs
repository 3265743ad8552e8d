//! `OutputOptions` → [`OutputSelection`]: which images a result carries and how each is encoded
//! (raw f32, raw f16, or a lossless PNG of quantised values).
//!
//! A robot streaming frames wants the depth and a mask, small, not twelve float images; a one-shot
//! caller keeps getting everything exact unless it asks otherwise. Every encoding is an ordinary
//! `Image` whose decoding rules (`value_scale`, `value_offset`) say how to read it, so clients
//! need no setting to decode a compact result.

use std::f64::consts::TAU;

use super::image::image_to_proto;
use crate::service::proto::v1 as pb;
use murk::error::{MurkError, Result};
use murk::image::ImageF32;
use murk::io::{encode_png_grey, PngEffort};

/// Who receives the result, which decides what an unset `OutputOptions` means.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Delivery {
    /// A one-shot request: every image, raw f32.
    OneShot,
    /// A sensor session's frame: the compact set, PNG.
    Session,
}

/// How result images are encoded on the wire.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Encoding {
    /// `raw_f32_le`, exact.
    F32,
    /// `raw_f16_le`, relative error at most 2⁻¹¹.
    F16,
    /// A greyscale PNG of values quantised on a range chosen by [`Quantity`]: 8-bit for
    /// [`Quantity::UnitInterval`], 16-bit otherwise.
    Png,
}

impl Encoding {
    fn to_proto(self) -> pb::ImageEncoding {
        match self {
            Encoding::F32 => pb::ImageEncoding::F32,
            Encoding::F16 => pb::ImageEncoding::F16,
            Encoding::Png => pb::ImageEncoding::Png,
        }
    }
}

/// What a result image measures, which fixes the PNG quantisation step where the unit is
/// known (1 mm for metres, 1/255 for [0, 1] quantities, 2π/65535 for phases).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Quantity {
    /// Lengths in metres: 1 mm steps on [0, 65.535] m, the u16-millimetre convention of ROS depth
    /// images (REP 118's 16UC1).
    Metres,
    /// Masks, IRLS weights and confidences, on [0, 1]: 8 bits, steps of 1/255 (masks exact).
    UnitInterval,
    /// Phases in radians, on [0, 2π].
    Radians,
    /// Anything else (sensor amplitudes, disparities, depths in a caller's unit): the image's own
    /// `[min, max]`.
    Unbounded,
}

impl Quantity {
    /// The fixed range of the quantity, if it has one.
    fn fixed_range(self) -> Option<(f64, f64)> {
        match self {
            Quantity::Metres => Some((0.0, 65.535)),
            Quantity::UnitInterval => Some((0.0, 1.0)),
            Quantity::Radians => Some((0.0, TAU)),
            Quantity::Unbounded => None,
        }
    }
}

/// One image field of a result message.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct OutputField {
    /// The field's name in the result message.
    pub name: &'static str,
    /// What it measures.
    pub quantity: Quantity,
}

/// The result images a request asked for, and their encoding.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct OutputSelection {
    fields: Vec<OutputField>,
    encoding: Encoding,
}

/// Largest finite magnitude of IEEE binary16.
const F16_MAX: f32 = 65504.0;

impl OutputSelection {
    /// Validates `opts` against the result's `catalog`; unset fields take `delivery`'s defaults,
    /// with `compact` the session's default set (names in `catalog`). Errors name `fields[i]` or
    /// `encoding`; callers prefix `outputs`.
    pub fn from_proto(
        opts: Option<&pb::OutputOptions>,
        catalog: &[OutputField],
        compact: &[&str],
        delivery: Delivery,
    ) -> Result<Self> {
        let default = pb::OutputOptions::default();
        let opts = opts.unwrap_or(&default);
        let encoding = match pb::ImageEncoding::try_from(opts.encoding) {
            Ok(pb::ImageEncoding::Unspecified) => match delivery {
                Delivery::OneShot => Encoding::F32,
                Delivery::Session => Encoding::Png,
            },
            Ok(pb::ImageEncoding::F32) => Encoding::F32,
            Ok(pb::ImageEncoding::F16) => Encoding::F16,
            Ok(pb::ImageEncoding::Png) => Encoding::Png,
            Err(_) => {
                return Err(MurkError::invalid(
                    "encoding",
                    format!(
                        "unknown image encoding {} (1 = F32, 2 = F16, 3 = PNG)",
                        opts.encoding
                    ),
                ))
            }
        };
        let fields = if opts.fields.is_empty() {
            match delivery {
                Delivery::OneShot => catalog.to_vec(),
                Delivery::Session => catalog
                    .iter()
                    .filter(|f| compact.contains(&f.name))
                    .copied()
                    .collect(),
            }
        } else {
            let mut chosen = Vec::with_capacity(opts.fields.len());
            for (i, name) in opts.fields.iter().enumerate() {
                let field = catalog.iter().find(|f| f.name == name).ok_or_else(|| {
                    let known: Vec<&str> = catalog.iter().map(|f| f.name).collect();
                    MurkError::invalid(
                        format!("fields[{i}]"),
                        format!("unknown output {name:?}; the result's images are {known:?}"),
                    )
                })?;
                if chosen.contains(field) {
                    return Err(MurkError::invalid(
                        format!("fields[{i}]"),
                        format!("{name:?} is listed twice"),
                    ));
                }
                chosen.push(*field);
            }
            // In the result message's order, so equal selections compare (and hash) equal.
            catalog
                .iter()
                .filter(|f| chosen.contains(f))
                .copied()
                .collect()
        };
        Ok(Self { fields, encoding })
    }

    /// The selection as a message with every default written out: the canonical form a job id
    /// hashes, so that an unset and an explicit default selection share one job.
    pub fn to_proto(&self) -> pb::OutputOptions {
        pb::OutputOptions {
            fields: self.fields.iter().map(|f| f.name.to_string()).collect(),
            encoding: self.encoding.to_proto() as i32,
        }
    }

    /// Whether the result carries `name`.
    pub fn wants(&self, name: &str) -> bool {
        self.fields.iter().any(|f| f.name == name)
    }

    /// The encoding in force.
    pub fn encoding(&self) -> Encoding {
        self.encoding
    }

    /// `img` as result field `name`, encoded; `None` when the caller did not ask for it.
    pub fn encode(&self, name: &str, img: &ImageF32) -> Result<Option<pb::Image>> {
        let Some(field) = self.fields.iter().find(|f| f.name == name) else {
            return Ok(None);
        };
        encode_image(img, self.encoding, field.quantity).map(Some)
    }
}

/// Encodes `img` with `encoding`, falling back to raw f32 where the encoding cannot carry it (see
/// `ImageEncoding` in common.proto).
fn encode_image(img: &ImageF32, encoding: Encoding, quantity: Quantity) -> Result<pb::Image> {
    match encoding {
        Encoding::F32 => Ok(image_to_proto(img)),
        Encoding::F16 => Ok(f16_image(img).unwrap_or_else(|| image_to_proto(img))),
        Encoding::Png => Ok(png_image(img, quantity)?.unwrap_or_else(|| image_to_proto(img))),
    }
}

/// Raw planar f16, or `None` when a finite sample overflows binary16.
fn f16_image(img: &ImageF32) -> Option<pb::Image> {
    if img
        .data()
        .iter()
        .any(|v| v.is_finite() && v.abs() > F16_MAX)
    {
        return None;
    }
    let (c, n) = (img.channels(), img.pixel_count());
    let mut bytes = Vec::with_capacity(n * c * 2);
    for ch in 0..c {
        for px in 0..n {
            let h = half::f16::from_f32(img.data()[px * c + ch]);
            bytes.extend_from_slice(&h.to_le_bytes());
        }
    }
    Some(pb::Image {
        width: img.width() as u32,
        height: img.height() as u32,
        channels: c as u32,
        data: Some(pb::image::Data::RawF16Le(bytes)),
        ..Default::default()
    })
}

/// A quantised greyscale PNG, or `None` for images a PNG cannot carry (non-finite samples, more
/// than one channel).
fn png_image(img: &ImageF32, quantity: Quantity) -> Result<Option<pb::Image>> {
    if img.channels() != 1 {
        return Ok(None);
    }
    let Some((min, max)) = finite_bounds(img.data()) else {
        return Ok(None);
    };
    let (lo, hi, bits) = match quantity.fixed_range() {
        Some((lo, hi)) if min >= lo && max <= hi => (
            lo,
            hi,
            if quantity == Quantity::UnitInterval {
                8
            } else {
                16
            },
        ),
        // A constant image: any positive span decodes it exactly (every sample quantises to 0).
        _ if max == min => (min, min + 1.0, 16),
        _ => (min, max, 16),
    };
    let (lo32, hi32) = (lo as f32, hi as f32);
    // f32 rounding must not collapse the span (an image near ±1e38 with a tiny spread).
    if hi32 <= lo32 || !(hi32 - lo32).is_finite() {
        return Ok(None);
    }
    // Metric depth from ToF is noise where the fog returns no signal, which deflates 20 % better
    // unpredicted; disparities, stereo depth and confidences are smooth enough for PNG's row
    // predictors to pay (10-15 %).
    let predict = quantity != Quantity::Metres;
    let bytes = encode_png_grey(img, lo32, hi32, bits, PngEffort::Small { predict })?;
    Ok(Some(pb::Image {
        width: img.width() as u32,
        height: img.height() as u32,
        channels: 1,
        data: Some(pb::image::Data::Encoded(bytes)),
        value_scale: hi32 - lo32,
        value_offset: lo32,
        transfer: pb::Transfer::Unspecified as i32,
    }))
}

/// `(min, max)` of the samples as f64, or `None` if any is non-finite (or there are none).
fn finite_bounds(data: &[f32]) -> Option<(f64, f64)> {
    let mut bounds: Option<(f64, f64)> = None;
    for &v in data {
        if !v.is_finite() {
            return None;
        }
        let v = f64::from(v);
        bounds = Some(bounds.map_or((v, v), |(lo, hi)| (lo.min(v), hi.max(v))));
    }
    bounds
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::convert::image::{image_from_proto, ImageLimits};
    use proptest::prelude::*;
    use proptest::test_runner::TestCaseError;

    const CATALOG: &[OutputField] = &[
        OutputField {
            name: "depth_m",
            quantity: Quantity::Metres,
        },
        OutputField {
            name: "mask",
            quantity: Quantity::UnitInterval,
        },
        OutputField {
            name: "amplitude",
            quantity: Quantity::Unbounded,
        },
    ];

    fn opts(fields: &[&str], encoding: pb::ImageEncoding) -> pb::OutputOptions {
        pb::OutputOptions {
            fields: fields.iter().map(|s| s.to_string()).collect(),
            encoding: encoding as i32,
        }
    }

    fn decode(img: &pb::Image) -> ImageF32 {
        image_from_proto(img, &ImageLimits::default()).unwrap()
    }

    fn image(w: usize, h: usize, f: impl Fn(usize) -> f32) -> ImageF32 {
        ImageF32::from_vec(w, h, 1, (0..w * h).map(f).collect()).unwrap()
    }

    fn field_of(e: MurkError) -> String {
        match e {
            MurkError::InvalidArgument { field, .. } => field,
            other => panic!("expected InvalidArgument, got {other:?}"),
        }
    }

    #[test]
    fn defaults_depend_on_the_delivery() {
        let one_shot =
            OutputSelection::from_proto(None, CATALOG, &["mask"], Delivery::OneShot).unwrap();
        assert_eq!(one_shot.to_proto().fields, ["depth_m", "mask", "amplitude"]);
        assert_eq!(one_shot.encoding(), Encoding::F32);
        let session =
            OutputSelection::from_proto(None, CATALOG, &["mask"], Delivery::Session).unwrap();
        assert!(session.wants("mask") && !session.wants("depth_m"));
        assert_eq!(session.encoding(), Encoding::Png);
    }

    #[test]
    fn selections_are_canonical_in_result_order() {
        let a = OutputSelection::from_proto(
            Some(&opts(&["mask", "depth_m"], pb::ImageEncoding::F16)),
            CATALOG,
            &[],
            Delivery::OneShot,
        )
        .unwrap();
        let b = OutputSelection::from_proto(Some(&a.to_proto()), CATALOG, &[], Delivery::Session)
            .unwrap();
        assert_eq!(a, b);
        assert_eq!(a.to_proto().fields, ["depth_m", "mask"]);
    }

    #[test]
    fn unknown_and_repeated_fields_and_encodings_are_named() {
        let bad = |o: pb::OutputOptions| {
            field_of(
                OutputSelection::from_proto(Some(&o), CATALOG, &[], Delivery::OneShot).unwrap_err(),
            )
        };
        assert_eq!(
            bad(opts(&["mask", "range"], pb::ImageEncoding::F32)),
            "fields[1]"
        );
        assert_eq!(
            bad(opts(&["mask", "mask"], pb::ImageEncoding::F32)),
            "fields[1]"
        );
        let mut o = opts(&[], pb::ImageEncoding::F32);
        o.encoding = 9;
        assert_eq!(bad(o), "encoding");
    }

    #[test]
    fn unselected_fields_are_not_encoded() {
        let sel = OutputSelection::from_proto(
            Some(&opts(&["mask"], pb::ImageEncoding::F32)),
            CATALOG,
            &[],
            Delivery::OneShot,
        )
        .unwrap();
        let img = image(3, 2, |i| i as f32);
        assert!(sel.encode("depth_m", &img).unwrap().is_none());
        assert!(sel.encode("mask", &img).unwrap().is_some());
    }

    #[test]
    fn metres_are_whole_millimetres_in_png() {
        let depth = image(64, 48, |i| 0.5 + 0.000_7 * i as f32);
        let wire = encode_image(&depth, Encoding::Png, Quantity::Metres).unwrap();
        assert!(matches!(wire.data, Some(pb::image::Data::Encoded(_))));
        assert_eq!((wire.value_scale, wire.value_offset), (65.535, 0.0));
        let back = decode(&wire);
        for (a, b) in depth.data().iter().zip(back.data()) {
            assert!((a - b).abs() <= 0.000_5 + 1e-6, "{a} vs {b}");
            // Each decoded value is a whole number of millimetres.
            assert!((b * 1000.0 - (b * 1000.0).round()).abs() < 1e-3);
        }
    }

    #[test]
    fn out_of_range_metres_use_their_own_range_and_masks_stay_exact() {
        let far = image(8, 8, |i| 10.0 + 20.0 * i as f32);
        let wire = encode_image(&far, Encoding::Png, Quantity::Metres).unwrap();
        assert_eq!(wire.value_offset, 10.0);
        let back = decode(&wire);
        let step = (far.data()[63] - 10.0) / 65535.0;
        for (a, b) in far.data().iter().zip(back.data()) {
            assert!((a - b).abs() <= step, "{a} vs {b}");
        }
        let mask = image(8, 8, |i| (i % 3 == 0) as u8 as f32);
        let back = decode(&encode_image(&mask, Encoding::Png, Quantity::UnitInterval).unwrap());
        assert_eq!(back.data(), mask.data());
        let flat = image(4, 4, |_| -3.25);
        let back = decode(&encode_image(&flat, Encoding::Png, Quantity::Unbounded).unwrap());
        assert_eq!(back.data(), flat.data());
    }

    #[test]
    fn what_an_encoding_cannot_carry_goes_as_f32() {
        let mut nan = image(4, 4, |i| i as f32);
        nan.data_mut()[5] = f32::NAN;
        let wire = encode_image(&nan, Encoding::Png, Quantity::Unbounded).unwrap();
        assert!(matches!(wire.data, Some(pb::image::Data::RawF32Le(_))));
        let big = image(4, 4, |i| 1e5 * i as f32);
        let wire = encode_image(&big, Encoding::F16, Quantity::Unbounded).unwrap();
        assert!(matches!(wire.data, Some(pb::image::Data::RawF32Le(_))));
        assert_eq!(decode(&wire).data(), big.data());
    }

    /// PNG quantisation error: at most half a step, plus the f32 rounding of the affine decode
    /// `offset + scale·q`, whose terms are as large as the image's largest magnitude (a value
    /// near 0 in an image spanning ±6e5 is the difference of two numbers of 6e5).
    fn png_within_half_a_step(values: Vec<f32>) -> Result<(), TestCaseError> {
        let img = ImageF32::from_vec(4, 3, 1, values).unwrap();
        let wire = encode_image(&img, Encoding::Png, Quantity::Unbounded).unwrap();
        let step = wire.value_scale / 65535.0;
        let magnitude = img.data().iter().fold(1.0f32, |m, v| m.max(v.abs()));
        for (a, b) in img.data().iter().zip(decode(&wire).data()) {
            prop_assert!(
                (a - b).abs() <= 0.5 * step + 1e-6 * magnitude,
                "{a} decoded as {b}, step {step}"
            );
        }
        Ok(())
    }

    #[test]
    fn png_of_a_wide_image_keeps_values_near_zero() {
        // A case a random run found: zeros in an image spanning ±6e5.
        let mut values = vec![0.0f32; 9];
        values.extend([-285.46243, -601379.2, 605485.8]);
        png_within_half_a_step(values).unwrap();
    }

    proptest! {
        #[test]
        fn f16_round_trips_within_its_precision(
            values in prop::collection::vec(-60000.0f32..60000.0, 12)
        ) {
            let img = ImageF32::from_vec(4, 3, 1, values).unwrap();
            let wire = encode_image(&img, Encoding::F16, Quantity::Unbounded).unwrap();
            prop_assert!(matches!(wire.data, Some(pb::image::Data::RawF16Le(_))));
            for (a, b) in img.data().iter().zip(decode(&wire).data()) {
                // Half an ulp of binary16 (11 significant bits), or its subnormal step.
                prop_assert!((a - b).abs() <= (a.abs() * 2f32.powi(-11)).max(2f32.powi(-25)));
            }
        }

        #[test]
        fn png_round_trips_within_half_a_step(
            values in prop::collection::vec(-1e6f32..1e6, 12)
        ) {
            png_within_half_a_step(values)?;
        }
    }
}
