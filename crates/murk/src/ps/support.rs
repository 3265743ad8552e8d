//! Choosing the kernel support from the object's size.
//!
//! Eq. 4.50 replaces everything outside the r×r support S(p) by one constant `C = Σ_q ε L_s(q)`.
//! The far field it drops is not constant over the object, though. It is largest where most of
//! the object lies outside the window, at the centre of a large object. The error therefore
//! depends on r *relative to the object's extent in pixels*, not on r alone. On murk's sphere
//! the same 1.86° came from 150×150 at r = 41 and from 300×300 at r = 81 (both about 0.36× the
//! object's width). At about 0.55× it falls to 0.91–1.04° (docs/accuracy.md, support sweep).
//! The far-cell layout ([`KernelLayout`]) makes such supports affordable. The rule is for that
//! constant far field: with the default, the outside summed on coarse blocks
//! ([`super::physics::FarField::Blocks`]), r = 21, 41 and 81 give normals within 0.01° of each
//! other on the simulator's scenes, so the rule over-sizes the support.

use super::physics::KernelLayout;
use super::pipeline::MAX_SUPPORT_R;
use crate::error::{MurkError, Result};

/// Support as a fraction of the object's larger bounding-box side (see the module docs).
pub const SUPPORT_PER_EXTENT: f64 = 0.55;

/// Far-cell sizes tried in order, the first whose kernel fits the memory limit wins: 3×3 up to
/// r = 81, where it is as accurate as the exact window, 5×5 beyond (as accurate at r = 121 and
/// 20 % faster than 3×3); larger cells only when the memory limit demands them.
const FAR_CELLS_SMALL: [usize; 6] = [3, 5, 7, 9, 11, 15];
const FAR_CELLS_LARGE: [usize; 5] = [5, 7, 9, 11, 15];

/// A support chosen for one capture.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SupportChoice {
    /// Kernel support r (odd), pixels.
    pub support_r: usize,
    /// Far-field cell size, pixels.
    pub far_cell: usize,
    /// The object's larger bounding-box side, pixels.
    pub object_extent_px: usize,
}

/// Picks r ≈ [`SUPPORT_PER_EXTENT`] × the mask's larger bounding-box side (odd, within
/// 3…min([`MAX_SUPPORT_R`], image side)). The far cell is the smallest that keeps the kernel
/// of the mask's pixels within `max_kernel_bytes`, given `near_radius_px`.
///
/// Errors name `mask` (empty or the wrong length); no cell size that fits the memory limit is
/// [`MurkError::OverLimit`] naming `support_r`.
pub fn choose_support(
    mask: &[bool],
    width: usize,
    height: usize,
    near_radius_px: usize,
    max_kernel_bytes: usize,
) -> Result<SupportChoice> {
    if mask.len() != width * height {
        return Err(MurkError::invalid(
            "mask",
            format!("{} values for a {width}x{height} image", mask.len()),
        ));
    }
    let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0, 0);
    let mut object_pixels = 0usize;
    for (i, _) in mask.iter().enumerate().filter(|(_, &m)| m) {
        let (x, y) = (i % width, i / width);
        (x0, y0, x1, y1) = (x0.min(x), y0.min(y), x1.max(x), y1.max(y));
        object_pixels += 1;
    }
    if object_pixels == 0 {
        return Err(MurkError::invalid("mask", "no object pixel"));
    }
    let extent = (x1 - x0 + 1).max(y1 - y0 + 1);
    let mut limit = MAX_SUPPORT_R.min(width.max(height));
    if limit.is_multiple_of(2) {
        limit -= 1;
    }
    let mut r = (SUPPORT_PER_EXTENT * extent as f64).ceil() as usize;
    if r.is_multiple_of(2) {
        r += 1;
    }
    let r = r.clamp(3, limit.max(3));
    let cells: &[usize] = if r <= 81 {
        &FAR_CELLS_SMALL
    } else {
        &FAR_CELLS_LARGE
    };
    for &s in cells {
        let layout = KernelLayout::coarse_far(r, s, near_radius_px)?;
        if layout.entry_bytes(object_pixels) <= max_kernel_bytes {
            return Ok(SupportChoice {
                support_r: r,
                far_cell: s,
                object_extent_px: extent,
            });
        }
    }
    Err(MurkError::over_limit(
        "support_r",
        format!(
            "the automatic support r = {r} for an object {extent} px across does not fit the \
             kernel memory limit of {max_kernel_bytes} bytes with any far cell up to 15 px: \
             give support_r explicitly or use a smaller image"
        ),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn disk(w: usize, h: usize, cx: f64, cy: f64, radius: f64) -> Vec<bool> {
        (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f64, (i / w) as f64);
                (x - cx).powi(2) + (y - cy).powi(2) <= radius * radius
            })
            .collect()
    }

    #[test]
    fn support_scales_with_the_object() {
        let big = 1usize << 40;
        // A disk 101 px across in a 150 px image: r = ceil(0.55·101) = 56 → 57, 3×3 cells.
        let c = choose_support(&disk(150, 150, 75.0, 75.0, 50.0), 150, 150, 9, big).unwrap();
        assert_eq!((c.object_extent_px, c.support_r, c.far_cell), (101, 57, 3));
        // The same disk twice as large in a 300 px image: r = ceil(0.55·201) = 111, 5×5 cells.
        let c = choose_support(&disk(300, 300, 150.0, 150.0, 100.0), 300, 300, 9, big).unwrap();
        assert_eq!((c.object_extent_px, c.support_r, c.far_cell), (201, 111, 5));
        // A tiny object still gets the smallest valid support.
        let c = choose_support(&disk(40, 40, 20.0, 20.0, 1.0), 40, 40, 9, big).unwrap();
        assert_eq!(c.support_r, 3);
        // A frame-filling object in a large image is capped at MAX_SUPPORT_R; in an image with
        // an even side below it, at the largest odd support that fits.
        let c = choose_support(&vec![true; 500 * 400], 500, 400, 9, big).unwrap();
        assert_eq!(c.support_r, MAX_SUPPORT_R);
        let c = choose_support(&vec![true; 120 * 100], 120, 100, 9, big).unwrap();
        assert_eq!(c.support_r, 67);
        let c = choose_support(&vec![true; 64 * 64], 64, 64, 9, big).unwrap();
        assert!(c.support_r <= 63 && c.support_r % 2 == 1);
    }

    #[test]
    fn memory_limit_coarsens_cells_or_names_support_r() {
        let mask = disk(300, 300, 150.0, 150.0, 100.0);
        let n = mask.iter().filter(|&&b| b).count();
        let bytes = |s: usize| KernelLayout::coarse_far(111, s, 9).unwrap().entry_bytes(n);
        // Bytes are not monotone in the cell size (larger cells round the near block up), so
        // the choice is the first cell in order that fits.
        let limit = bytes(5) - 1;
        let c = choose_support(&mask, 300, 300, 9, limit).unwrap();
        assert_eq!(c.support_r, 111);
        assert!(c.far_cell > 5 && bytes(c.far_cell) <= limit, "{c:?}");
        let e = choose_support(&mask, 300, 300, 9, 1000).unwrap_err();
        assert!(e.to_string().contains("support_r"), "{e}");
    }

    #[test]
    fn bad_masks_name_the_mask() {
        for (mask, w, h) in [(vec![false; 16], 4, 4), (vec![true; 15], 4, 4)] {
            let e = choose_support(&mask, w, h, 9, 1 << 30).unwrap_err();
            assert!(e.to_string().contains("mask"), "{e}");
        }
    }
}
