//! The normalised radius of a pixel, by which a lens's fall-off is modelled
//! ([`super::vignetting`]) and recorded with the exposure search's samples ([`super::exposure`]).

/// `r²` of pixel `(x, y)` of a `w×h` image: squared distance from the image centre over the
/// squared half-diagonal (1 at the corner pixels' centres).
#[inline]
pub fn radius2(x: f32, y: f32, w: usize, h: usize) -> f32 {
    let (cx, cy) = ((w as f32 - 1.0) / 2.0, (h as f32 - 1.0) / 2.0);
    let d2 = (cx * cx + cy * cy).max(f32::MIN_POSITIVE);
    ((x - cx) * (x - cx) + (y - cy) * (y - cy)) / d2
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn radius_is_one_at_the_corners_and_zero_at_the_centre() {
        assert_eq!(radius2(0.0, 0.0, 5, 3), 1.0);
        assert_eq!(radius2(4.0, 2.0, 5, 3), 1.0);
        assert_eq!(radius2(2.0, 1.0, 5, 3), 0.0);
        assert!((radius2(4.0, 1.0, 5, 3) - 0.8).abs() < 1e-6);
    }
}
