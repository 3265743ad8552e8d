//! Row pairing for the global vertical-symmetry prior γ₂‖Fx − x‖² (Eq. 5.11–5.12, Fig. 5.5).

/// Which row each image row is mirrored onto by the flip matrix `F`.
///
/// The flip axis is snapped to the nearest half row: with `k = round(2·row0)` the partner of row
/// `r` is `k − r`. For an integer `row0` this is the exact mirror; for a fractional `row0` it is
/// `round(2·row0 − r)`, the nearest row to the true mirror position, and — unlike rounding each
/// mirror position independently — it stays an involution, so `(F − I)ᵀ(F − I)` couples rows in
/// symmetric pairs. Rows whose partner falls outside the image carry no symmetry information
/// and are left out of the term (the reference dropped 24 such rows, §5.4.1).
#[derive(Clone, Debug, PartialEq)]
pub struct RowMirror {
    partner: Vec<Option<usize>>,
}

impl RowMirror {
    /// Pairs the rows of an image `height` rows tall about `row0` (pixels, may be fractional or
    /// even outside the image, in which case few or no rows are paired).
    pub fn new(height: usize, row0: f64) -> Self {
        let k = (2.0 * row0).round();
        let partner = (0..height)
            .map(|r| {
                let m = k - r as f64;
                // A row on the axis mirrors onto itself: its (F − I) row is zero, so it is unpaired.
                if m >= 0.0 && m < height as f64 && m as usize != r {
                    Some(m as usize)
                } else {
                    None
                }
            })
            .collect();
        Self { partner }
    }

    /// Partner row of `row`, if it is paired.
    #[inline]
    pub fn partner(&self, row: usize) -> Option<usize> {
        self.partner.get(row).copied().flatten()
    }

    /// Number of rows whose mirror partner falls outside the image (excluded from the prior).
    pub fn excluded_rows(&self) -> usize {
        self.partner.iter().filter(|p| p.is_none()).count()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reference_setting_excludes_24_rows() {
        // Kinect v2: 424 rows flipped about row 200 leaves rows 401..423 without a partner (23)
        // plus the axis row itself.
        let m = RowMirror::new(424, 200.0);
        assert_eq!(m.partner(0), Some(400));
        assert_eq!(m.partner(400), Some(0));
        assert_eq!(m.partner(200), None);
        assert_eq!(m.partner(401), None);
        assert_eq!(m.excluded_rows(), 24);
    }

    #[test]
    fn fractional_axis_is_an_involution() {
        for row0 in [3.3, 3.5, 3.7, 4.0, -2.0, 100.0] {
            let m = RowMirror::new(9, row0);
            for r in 0..9 {
                if let Some(p) = m.partner(r) {
                    assert_eq!(m.partner(p), Some(r), "row0 {row0} row {r}");
                }
            }
        }
        // Axis at 3.5: rows 3 and 4 swap, all 9 rows but row 8 are paired.
        let m = RowMirror::new(9, 3.5);
        assert_eq!(m.partner(3), Some(4));
        assert_eq!(m.excluded_rows(), 1);
    }
}
