//! Which neighbours q of a pixel p the truncated kernel K̂ (Eq. 4.51) stores, and at what
//! resolution.
//!
//! The reference keeps every q of an r×r window S(p). Far from p, K_pq is smooth (Fig. 4.9: a
//! slow, nearly isotropic decay), so murk can instead keep the near part of the window per
//! pixel and the far part per *cell* of s×s pixels: K_pq for every q of a far cell is taken as
//! K evaluated at the cell's mean geometry (a midpoint quadrature of Eq. 4.48), and the operator
//! multiplies it with the cell's sum of L_s. With s = 3 and a near radius of 9 px this stores
//! 1 121 instead of 6 561 entries per pixel at r = 81: the build and every BiCGStab product
//! shrink by ≈ 5.9× (docs/benchmarks.md), at a measured accuracy cost given in
//! docs/accuracy.md. s = 1 is the reference's exact window.
//!
//! Geometry (all image-aligned, so neighbouring pixels share cells):
//! - cells are the blocks [cx·s, cx·s + s) × [cy·s, cy·s + s); pixel p lies in cell
//!   (⌊px/s⌋, ⌊py/s⌋);
//! - the *near block* of p is the (2M + 1)s × (2M + 1)s pixels of the cells within Chebyshev
//!   cell distance M of p's cell, stored per pixel; M = ⌈near_radius/s⌉, so every q within
//!   `near_radius` px of p is in it;
//! - the *far window* is the cells within cell distance K of p's cell, minus the near block,
//!   stored per cell; K = round((r/s − 1)/2), so the support spans (2K + 1)s ≈ r pixels.
//!
//! With s = 1 the near block is the r×r window centred on p and there is no far window.

use crate::error::{MurkError, Result};

/// Largest far-cell size accepted.
pub const MAX_FAR_CELL: usize = 15;

/// The storage layout of K̂: see the module documentation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct KernelLayout {
    support_r: usize,
    cell: usize,
    near_cells: usize,
    far_cells: usize,
}

impl KernelLayout {
    /// The reference's layout: every q of the r×r window centred on p (`support_r` odd, ≥ 3).
    pub fn exact(support_r: usize) -> Result<KernelLayout> {
        check_support(support_r)?;
        Ok(KernelLayout {
            support_r,
            cell: 1,
            near_cells: support_r / 2,
            far_cells: support_r / 2,
        })
    }

    /// Near block of radius ≥ `near_radius_px` per pixel, the rest of the r×r support in cells
    /// of `cell`×`cell` pixels. Falls back to [`KernelLayout::exact`] when `cell` is 1 or the
    /// near block would already cover the support.
    pub fn coarse_far(
        support_r: usize,
        cell: usize,
        near_radius_px: usize,
    ) -> Result<KernelLayout> {
        check_support(support_r)?;
        if cell == 0 || cell > MAX_FAR_CELL {
            return Err(MurkError::invalid(
                "far_cell",
                format!("must be in 1..={MAX_FAR_CELL}, got {cell}"),
            ));
        }
        if near_radius_px == 0 {
            return Err(MurkError::invalid(
                "near_radius_px",
                "must be >= 1 (the near block holds p and its neighbours)",
            ));
        }
        if cell == 1 || support_r / 2 <= near_radius_px {
            return KernelLayout::exact(support_r);
        }
        let near_cells = near_radius_px.div_ceil(cell);
        // round((r/s − 1)/2) = ⌊(r − s)/(2s) + 1/2⌋ = ⌊r/(2s)⌋.
        let far_cells = support_r / (2 * cell);
        Ok(KernelLayout {
            support_r,
            cell,
            near_cells,
            far_cells: far_cells.max(near_cells),
        })
    }

    /// The requested support r.
    pub fn support_r(&self) -> usize {
        self.support_r
    }

    /// Cell size s in pixels (1: the exact window).
    pub fn cell(&self) -> usize {
        self.cell
    }

    /// Side of the near block in pixels, (2M + 1)s.
    pub fn near_width(&self) -> usize {
        (2 * self.near_cells + 1) * self.cell
    }

    /// Side of the far window in cells, 2K + 1, or 0 when there is no far window.
    pub fn far_width(&self) -> usize {
        if self.far_cells > self.near_cells {
            2 * self.far_cells + 1
        } else {
            0
        }
    }

    /// Cell radius M of the near block.
    pub fn near_cells(&self) -> usize {
        self.near_cells
    }

    /// Cell radius K of the whole support.
    pub fn far_cells(&self) -> usize {
        self.far_cells
    }

    /// Side of the support actually covered, pixels: (2K + 1)s (r itself for the exact layout).
    pub fn effective_support(&self) -> usize {
        (2 * self.far_cells + 1) * self.cell
    }

    /// f32 entries stored per object pixel: the near block plus the far window (whose inner
    /// cells, covered by the near block, are stored as zeros to keep rows contiguous).
    pub fn entries_per_pixel(&self) -> usize {
        let nb = self.near_width();
        let fw = self.far_width();
        nb * nb + fw * fw
    }

    /// Bytes of kernel entries for `object_pixels` pixels (saturating).
    pub fn entry_bytes(&self, object_pixels: usize) -> usize {
        object_pixels
            .saturating_mul(self.entries_per_pixel())
            .saturating_mul(4)
    }
}

fn check_support(support_r: usize) -> Result<()> {
    if support_r < 3 || support_r.is_multiple_of(2) {
        return Err(MurkError::invalid(
            "support_r",
            format!("kernel support must be odd and >= 3, got {support_r}"),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::field_of;

    #[test]
    fn exact_layout_is_the_centred_window() {
        let l = KernelLayout::exact(81).unwrap();
        assert_eq!(l.near_width(), 81);
        assert_eq!(l.far_width(), 0);
        assert_eq!(l.entries_per_pixel(), 81 * 81);
        assert_eq!(l.effective_support(), 81);
    }

    #[test]
    fn coarse_layout_sizes() {
        let l = KernelLayout::coarse_far(81, 3, 9).unwrap();
        assert_eq!((l.near_cells(), l.far_cells()), (3, 13));
        assert_eq!(l.near_width(), 21);
        assert_eq!(l.far_width(), 27);
        assert_eq!(l.effective_support(), 81);
        assert_eq!(l.entries_per_pixel(), 21 * 21 + 27 * 27);
        // r = 61 is not a multiple of 3: the support is rounded to whole cells.
        let l = KernelLayout::coarse_far(61, 3, 9).unwrap();
        assert_eq!(l.far_cells(), 10);
        assert_eq!(l.effective_support(), 63);
        let l = KernelLayout::coarse_far(61, 5, 9).unwrap();
        assert_eq!(l.far_cells(), 6);
        assert_eq!(l.effective_support(), 65);
        // Near radius covering the support, or s = 1: the exact layout.
        assert_eq!(
            KernelLayout::coarse_far(15, 3, 9).unwrap(),
            KernelLayout::exact(15).unwrap()
        );
        assert_eq!(
            KernelLayout::coarse_far(81, 1, 9).unwrap(),
            KernelLayout::exact(81).unwrap()
        );
    }

    #[test]
    fn bad_layouts_name_their_field() {
        for r in [0, 1, 2, 80] {
            assert_eq!(field_of(KernelLayout::exact(r).unwrap_err()), "support_r");
            assert_eq!(
                field_of(KernelLayout::coarse_far(r, 3, 9).unwrap_err()),
                "support_r"
            );
        }
        for s in [0, MAX_FAR_CELL + 1] {
            assert_eq!(
                field_of(KernelLayout::coarse_far(81, s, 9).unwrap_err()),
                "far_cell"
            );
        }
        assert_eq!(
            field_of(KernelLayout::coarse_far(81, 3, 0).unwrap_err()),
            "near_radius_px"
        );
    }
}
