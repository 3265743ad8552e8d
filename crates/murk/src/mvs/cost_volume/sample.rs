//! Bilinear sampling of interleaved images at sub-pixel positions, murk's pixel convention
//! (pixel `(x, y)`'s centre at integer coordinates, i.e. "align corners").

/// Bilinear sample of a `w×h` image with `C` interleaved channels at `(u, v)`.
///
/// Returns `None` unless `0 ≤ u ≤ w − 1` and `0 ≤ v ≤ h − 1` (NaN included): outside the
/// pixel-centre hull there is no data to interpolate, and the cost volume treats such samples as
/// unobserved rather than inventing values by clamping or zero padding. Needs `w, h ≥ 2`.
#[inline]
pub fn bilinear<const C: usize>(
    data: &[f32],
    w: usize,
    h: usize,
    u: f64,
    v: f64,
) -> Option<[f32; C]> {
    if !(u >= 0.0 && v >= 0.0 && u <= (w - 1) as f64 && v <= (h - 1) as f64) {
        return None;
    }
    // At the right/bottom edge use the last cell with weight 1 on its far side.
    let x0 = (u as usize).min(w - 2);
    let y0 = (v as usize).min(h - 2);
    let fx = (u - x0 as f64) as f32;
    let fy = (v - y0 as f64) as f32;
    let i00 = (y0 * w + x0) * C;
    let i10 = i00 + w * C;
    let top = &data[i00..i00 + 2 * C];
    let bottom = &data[i10..i10 + 2 * C];
    let mut out = [0.0f32; C];
    for (c, o) in out.iter_mut().enumerate() {
        let t = top[c] + fx * (top[C + c] - top[c]);
        let b = bottom[c] + fx * (bottom[C + c] - bottom[c]);
        *o = t + fy * (b - t);
    }
    Some(out)
}

/// [`bilinear`] for a sample already known to lie inside the pixel-centre hull
/// (`0 ≤ u ≤ w − 1`, `0 ≤ v ≤ h − 1`, checked by the caller), in `f32`: the cost volume's inner
/// loop, where the check is shared with the visibility test.
#[inline]
pub fn bilinear_inside<const C: usize>(
    data: &[f32],
    w: usize,
    u: f32,
    v: f32,
    h: usize,
) -> [f32; C] {
    debug_assert!(u >= 0.0 && v >= 0.0 && u <= (w - 1) as f32 && v <= (h - 1) as f32);
    // Non-negative, so the truncating casts are floors; the last cell takes the right/bottom
    // edge with weight 1 on its far side. Through `i32`: x86-64 converts f32 → i32 in one
    // instruction, while f32 → u64 needs a two-range sequence; images are far below 2³¹ px.
    let x0 = (u as i32 as usize).min(w - 2);
    let y0 = (v as i32 as usize).min(h - 2);
    let fx = u - x0 as f32;
    let fy = v - y0 as f32;
    let i00 = (y0 * w + x0) * C;
    let i10 = i00 + w * C;
    let top = &data[i00..i00 + 2 * C];
    let bottom = &data[i10..i10 + 2 * C];
    let mut out = [0.0f32; C];
    for (c, o) in out.iter_mut().enumerate() {
        let t = top[c] + fx * (top[C + c] - top[c]);
        let b = bottom[c] + fx * (bottom[C + c] - bottom[c]);
        *o = t + fy * (b - t);
    }
    out
}

/// Converts a 3-channel interleaved image to one `[f32; 4]` per pixel (RGB minus `offset`, then
/// a zero lane), so that a pixel, and a horizontal pair of pixels, is one vector load for the
/// cost volume's AVX2 loop. The dehazing volume passes the airlight as `offset`.
pub fn pad_rgb4(data: &[f32], offset: f32) -> Vec<[f32; 4]> {
    data.chunks_exact(3)
        .map(|p| [p[0] - offset, p[1] - offset, p[2] - offset, 0.0])
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn interpolates_and_rejects_outside() {
        // 3×2 image, 1 channel: value = 10·x + y.
        let d = [0.0, 10.0, 20.0, 1.0, 11.0, 21.0];
        assert_eq!(bilinear::<1>(&d, 3, 2, 0.0, 0.0), Some([0.0]));
        assert_eq!(bilinear::<1>(&d, 3, 2, 2.0, 1.0), Some([21.0]));
        let [m] = bilinear::<1>(&d, 3, 2, 1.5, 0.25).unwrap();
        assert!((m - 15.25).abs() < 1e-6);
        for (u, v) in [(-0.01, 0.0), (2.01, 0.0), (0.0, 1.01), (f64::NAN, 0.0)] {
            assert_eq!(bilinear::<1>(&d, 3, 2, u, v), None, "({u}, {v})");
        }
        for (u, v) in [(0.0, 0.0), (2.0, 1.0), (1.5, 0.25), (0.7, 0.9)] {
            assert_eq!(
                bilinear_inside::<1>(&d, 3, u as f32, v as f32, 2),
                bilinear::<1>(&d, 3, 2, u, v).unwrap()
            );
        }
        let rgb: Vec<f32> = (0..12).map(|k| k as f32).collect();
        assert_eq!(bilinear::<3>(&rgb, 2, 2, 1.0, 0.0), Some([3.0, 4.0, 5.0]));
    }
}
