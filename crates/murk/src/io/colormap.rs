//! False-colour previews with the Turbo colormap (Mikhailov 2019), via its published degree-5
//! polynomial fit, accurate to a few 8-bit levels — plenty for previews.

use std::path::Path;
use std::sync::OnceLock;

use super::png::write_png_rgb8;
use crate::error::{MurkError, Result};
use crate::image::ImageF32;

/// Colour of masked-out and non-finite pixels (dark grey).
pub const MASKED_RGB: [u8; 3] = [48, 48, 48];

/// Turbo colour of `t ∈ [0, 1]` (clamped; NaN maps to 0) as RGB8: dark blue → cyan → green →
/// yellow → red.
pub fn turbo(t: f32) -> [u8; 3] {
    let x = if t.is_nan() {
        0.0
    } else {
        t.clamp(0.0, 1.0) as f64
    };
    let poly = |c: [f64; 6]| c[0] + x * (c[1] + x * (c[2] + x * (c[3] + x * (c[4] + x * c[5]))));
    let r = poly([
        0.135_721_38,
        4.615_392_6,
        -42.660_322_58,
        132.131_082_34,
        -152.942_393_96,
        59.286_379_43,
    ]);
    let g = poly([
        0.091_402_61,
        2.194_188_39,
        4.842_966_58,
        -14.185_033_33,
        4.277_298_57,
        2.829_566_04,
    ]);
    let b = poly([
        0.106_673_3,
        12.641_946_08,
        -60.582_048_36,
        110.362_767_71,
        -89.903_109_12,
        27.348_249_73,
    ]);
    let q = |v: f64| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
    [q(r), q(g), q(b)]
}

/// Entries of [`turbo_table`]: [`turbo`] at `i / (TURBO_TABLE_LEN − 1)`. Looking a value up at the
/// nearest entry moves `t` by at most 1/8190, and no channel's polynomial changes by more than
/// 13 per unit of `t` (blue's, at 0): under 0.4 of an 8-bit level, so within one level once
/// rounded (tested).
const TURBO_TABLE_LEN: usize = 4096;

/// [`turbo`] tabulated once: [`colorize`] looks every pixel up instead of evaluating three
/// degree-5 polynomials and rounding them (a stream's client colours a preview per frame).
fn turbo_table() -> &'static [[u8; 3]; TURBO_TABLE_LEN] {
    static TABLE: OnceLock<[[u8; 3]; TURBO_TABLE_LEN]> = OnceLock::new();
    TABLE.get_or_init(|| std::array::from_fn(|i| turbo(i as f32 / (TURBO_TABLE_LEN - 1) as f32)))
}

/// [`turbo`] of `t` from [`turbo_table`], `t` finite.
#[inline]
fn turbo_lookup(table: &[[u8; 3]; TURBO_TABLE_LEN], t: f32) -> [u8; 3] {
    let i = (t.clamp(0.0, 1.0) * (TURBO_TABLE_LEN - 1) as f32 + 0.5) as usize;
    table[i.min(TURBO_TABLE_LEN - 1)]
}

/// A mask sample marks a valid pixel when > 0.5.
fn mask_set(v: f32) -> bool {
    v > 0.5
}

/// Maps channel 0 of `img` through Turbo with `lo → 0` and `hi → 1`, returning interleaved RGB8.
///
/// Non-finite samples, and pixels where `mask` (same size, > 0.5 = valid) is not valid, become
/// [`MASKED_RGB`]. A mask of another size is ignored; a degenerate range (`hi ≤ lo` or non-finite)
/// paints every finite pixel mid-scale. Colours come from a table of [`turbo`], within one level
/// of it.
pub fn colorize(img: &ImageF32, lo: f32, hi: f32, mask: Option<&ImageF32>) -> Vec<u8> {
    let mask = mask.filter(|m| m.dims() == img.dims());
    let valid_range = lo.is_finite() && hi.is_finite() && hi > lo;
    let table = turbo_table();
    let c = img.channels();
    let mut out = Vec::with_capacity(img.pixel_count() * 3);
    for i in 0..img.pixel_count() {
        let v = img.data()[i * c];
        // NaN in the mask means invalid, hence `!(v > 0.5)` rather than `v <= 0.5`.
        let masked = mask.is_some_and(|m| !mask_set(m.data()[i * m.channels()]));
        let rgb = if masked || !v.is_finite() {
            MASKED_RGB
        } else if valid_range {
            turbo_lookup(table, (v - lo) / (hi - lo))
        } else {
            turbo_lookup(table, 0.5)
        };
        out.extend_from_slice(&rgb);
    }
    out
}

/// The colour scale of a preview that a few outliers do not flatten: the 2nd and 98th
/// percentiles (ranks `n / 50` and `49·n / 50` in sorted order) of channel 0's `n` finite samples
/// of `img` where `mask` (same size, > 0.5 = valid; ignored when of another size) is set.
/// `(lo, lo + 1)` when the two are equal, `(0, 1)` when no sample counts. Two selections instead
/// of a sort: a streaming client takes the scale of every frame it writes.
pub fn preview_range(img: &ImageF32, mask: Option<&ImageF32>) -> (f32, f32) {
    let mask = mask.filter(|m| m.dims() == img.dims());
    let c = img.channels();
    let mut v: Vec<f32> = (0..img.pixel_count())
        .filter(|&i| mask.is_none_or(|m| mask_set(m.data()[i * m.channels()])))
        .map(|i| img.data()[i * c])
        .filter(|x| x.is_finite())
        .collect();
    let n = v.len();
    if n == 0 {
        return (0.0, 1.0);
    }
    let (lo_rank, hi_rank) = (n / 50, n * 49 / 50);
    let (below, &mut hi, _) = v.select_nth_unstable_by(hi_rank, f32::total_cmp);
    // Everything before the high rank is at most `hi`, so the low rank is found among it.
    let lo = if lo_rank < hi_rank {
        *below.select_nth_unstable_by(lo_rank, f32::total_cmp).1
    } else {
        hi
    };
    if hi > lo {
        (lo, hi)
    } else {
        (lo, lo + 1.0)
    }
}

/// Writes [`colorize`] as an 8-bit RGB PNG. Unlike `colorize`, a mask of the wrong size is an
/// error (field `mask`).
pub fn write_colormap_png(
    path: &Path,
    img: &ImageF32,
    lo: f32,
    hi: f32,
    mask: Option<&ImageF32>,
) -> Result<()> {
    if let Some(m) = mask {
        if m.dims() != img.dims() {
            return Err(MurkError::invalid(
                "mask",
                format!(
                    "size {}x{} differs from the image's {}x{}",
                    m.width(),
                    m.height(),
                    img.width(),
                    img.height()
                ),
            ));
        }
    }
    let rgb = colorize(img, lo, hi, mask);
    write_png_rgb8(path, img.width(), img.height(), &rgb)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn turbo_runs_blue_green_red() {
        let lo = turbo(0.05);
        let mid = turbo(0.5);
        let hi = turbo(0.95);
        assert!(lo[2] > lo[0] && lo[2] > lo[1], "{lo:?}");
        assert!(mid[1] > mid[2] && mid[1] > 150, "{mid:?}");
        assert!(hi[0] > hi[1] && hi[0] > hi[2], "{hi:?}");
        assert_eq!(turbo(f32::NAN), turbo(0.0));
        assert_eq!(turbo(7.0), turbo(1.0));
    }

    #[test]
    fn the_table_is_within_one_level_of_turbo() {
        let table = turbo_table();
        for k in 0..=20_000 {
            let t = k as f32 / 20_000.0;
            let (a, b) = (turbo_lookup(table, t), turbo(t));
            for c in 0..3 {
                assert!(a[c].abs_diff(b[c]) <= 1, "t {t}: {a:?} against {b:?}");
            }
        }
        assert_eq!(turbo_lookup(table, 0.0), turbo(0.0));
        assert_eq!(turbo_lookup(table, 1.0), turbo(1.0));
        assert_eq!(turbo_lookup(table, -3.0), turbo(0.0));
        assert_eq!(turbo_lookup(table, 7.0), turbo(1.0));
    }

    #[test]
    fn colorize_masks_and_non_finite() {
        let img = ImageF32::from_vec(3, 1, 1, vec![0.0, f32::INFINITY, 1.0]).unwrap();
        let mask = ImageF32::from_vec(3, 1, 1, vec![0.0, 1.0, 1.0]).unwrap();
        let rgb = colorize(&img, 0.0, 1.0, Some(&mask));
        assert_eq!(&rgb[0..3], &MASKED_RGB);
        assert_eq!(&rgb[3..6], &MASKED_RGB);
        assert_eq!(&rgb[6..9], &turbo(1.0));
        let dir = tempfile::tempdir().unwrap();
        let bad = ImageF32::filled(2, 1, 1, 1.0);
        assert!(write_colormap_png(&dir.path().join("c.png"), &img, 0.0, 1.0, Some(&bad)).is_err());
        write_colormap_png(&dir.path().join("c.png"), &img, 0.0, 1.0, None).unwrap();
    }

    /// [`preview_range`] by sorting, as it is specified.
    fn sorted_range(img: &ImageF32, mask: Option<&ImageF32>) -> (f32, f32) {
        let mut v: Vec<f32> = img
            .data()
            .iter()
            .enumerate()
            .filter(|&(i, x)| x.is_finite() && mask.is_none_or(|m| m.data()[i] > 0.5))
            .map(|(_, &x)| x)
            .collect();
        if v.is_empty() {
            return (0.0, 1.0);
        }
        v.sort_by(f32::total_cmp);
        let (lo, hi) = (v[v.len() / 50], v[v.len() * 49 / 50]);
        if hi > lo {
            (lo, hi)
        } else {
            (lo, lo + 1.0)
        }
    }

    #[test]
    fn preview_range_edge_cases() {
        let none = ImageF32::from_vec(2, 1, 1, vec![f32::NAN, f32::INFINITY]).unwrap();
        assert_eq!(preview_range(&none, None), (0.0, 1.0));
        let flat = ImageF32::filled(4, 4, 1, 2.5);
        assert_eq!(preview_range(&flat, None), (2.5, 3.5));
        let one = ImageF32::from_vec(1, 1, 1, vec![-3.0]).unwrap();
        assert_eq!(preview_range(&one, None), (-3.0, -2.0));
        // 100 samples: ranks 2 and 98, so the outliers at both ends fall outside.
        let mut data: Vec<f32> = (0..100).map(|i| i as f32).collect();
        (data[0], data[99]) = (-1e9, 1e9);
        let img = ImageF32::from_vec(10, 10, 1, data).unwrap();
        assert_eq!(preview_range(&img, None), (2.0, 98.0));
        // A mask of another size is ignored, as `colorize` ignores it.
        let odd = ImageF32::filled(3, 3, 1, 0.0);
        assert_eq!(preview_range(&img, Some(&odd)), (2.0, 98.0));
    }

    proptest::proptest! {
        /// The selections find the ranks a sort finds, with and without a mask.
        #[test]
        fn preview_range_is_the_sorted_percentiles(
            data in proptest::collection::vec(
                proptest::prop_oneof![-1e3f32..1e3, proptest::strategy::Just(f32::NAN)],
                1..600,
            ),
            keep in proptest::collection::vec(proptest::bool::ANY, 600),
        ) {
            let n = data.len();
            let img = ImageF32::from_vec(n, 1, 1, data).unwrap();
            let mask = ImageF32::from_fn(n, 1, |x, _| f32::from(u8::from(keep[x])));
            proptest::prop_assert_eq!(preview_range(&img, None), sorted_range(&img, None));
            proptest::prop_assert_eq!(
                preview_range(&img, Some(&mask)),
                sorted_range(&img, Some(&mask))
            );
        }
    }
}
