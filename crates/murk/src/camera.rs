//! Pinhole camera model shared by every method. Pixel coordinates: x to the right, y down, origin
//! at the centre of the top-left pixel; camera frame: +z forward (optical axis), +x right, +y down.

use nalgebra::{Matrix3, Point3, Vector3};

use crate::error::{MurkError, Result};

/// Range of a focal length, pixels. Below 1e-3 px a pixel would span more than the whole field
/// of view; above 1e7 px (a 10 m lens on 1 µm pixels) rays lose precision in f32 images and the
/// values are unit slips (focal lengths in metres, or in micrometres) rather than cameras.
pub const FOCAL_LENGTH_RANGE_PX: (f64, f64) = (1e-3, 1e7);

/// Largest |cx|, |cy| and |skew|, pixels: far beyond any image murk accepts.
pub const MAX_PRINCIPAL_OFFSET_PX: f64 = 1e7;

/// Pinhole intrinsics in pixels: `u = fx·x/z + skew·y/z + cx`, `v = fy·y/z + cy`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Intrinsics {
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Skew, pixels (0 for almost every real camera).
    pub skew: f64,
}

impl Intrinsics {
    /// Intrinsics without skew.
    pub fn new(fx: f64, fy: f64, cx: f64, cy: f64) -> Self {
        Self {
            fx,
            fy,
            cx,
            cy,
            skew: 0.0,
        }
    }

    /// Fails unless the focal lengths lie in [`FOCAL_LENGTH_RANGE_PX`] and the other entries
    /// are finite and within [`MAX_PRINCIPAL_OFFSET_PX`].
    pub fn validate(&self) -> Result<()> {
        let (lo, hi) = FOCAL_LENGTH_RANGE_PX;
        for (name, v) in [("fx", self.fx), ("fy", self.fy)] {
            if !v.is_finite() || v <= 0.0 {
                return Err(MurkError::invalid(
                    name,
                    format!("focal length must be finite and > 0, got {v}"),
                ));
            }
            if !(lo..=hi).contains(&v) {
                return Err(MurkError::invalid(
                    name,
                    format!("focal length {v} px is outside [{lo:e}, {hi:e}] px (in pixels)"),
                ));
            }
        }
        for (name, v) in [("cx", self.cx), ("cy", self.cy), ("skew", self.skew)] {
            if !v.is_finite() {
                return Err(MurkError::invalid(name, format!("must be finite, got {v}")));
            }
            if v.abs() > MAX_PRINCIPAL_OFFSET_PX {
                return Err(MurkError::invalid(
                    name,
                    format!("{v} px is beyond ±{MAX_PRINCIPAL_OFFSET_PX:e} px"),
                ));
            }
        }
        Ok(())
    }

    /// Intrinsics of the image box-downsampled by `factor` (each pixel the mean of a
    /// `factor × factor` block): coarse pixel `i` covers fine pixels `factor·i … factor·i +
    /// factor − 1`, whose centre is `factor·i + (factor − 1)/2`, so it sees along that centre's
    /// ray.
    pub fn box_downsampled(&self, factor: usize) -> Self {
        let f = factor as f64;
        let shift = (f - 1.0) / 2.0;
        Self {
            fx: self.fx / f,
            fy: self.fy / f,
            cx: (self.cx - shift) / f,
            cy: (self.cy - shift) / f,
            skew: self.skew / f,
        }
    }

    /// Unit-length viewing ray (camera frame) through pixel `(u, v)`.
    pub fn ray(&self, u: f64, v: f64) -> Vector3<f64> {
        let y = (v - self.cy) / self.fy;
        let x = (u - self.cx - self.skew * y) / self.fx;
        // Normalised by hand: the third component is 1 before normalising, so `x² + y² + 1`
        // saves a square.
        let n = (x * x + y * y + 1.0).sqrt();
        Vector3::new(x / n, y / n, 1.0 / n)
    }

    /// `K` (pixels): `(u, v, 1)ᵀ ∝ K·(x, y, z)ᵀ`.
    pub fn matrix(&self) -> Matrix3<f64> {
        Matrix3::new(
            self.fx, self.skew, self.cx, //
            0.0, self.fy, self.cy, //
            0.0, 0.0, 1.0,
        )
    }

    /// `K⁻¹` in closed form (upper triangular, last row `(0, 0, 1)`).
    pub fn inverse_matrix(&self) -> Matrix3<f64> {
        let (fx, fy, s) = (self.fx, self.fy, self.skew);
        Matrix3::new(
            1.0 / fx,
            -s / (fx * fy),
            (s * self.cy - self.cx * fy) / (fx * fy),
            0.0,
            1.0 / fy,
            -self.cy / fy,
            0.0,
            0.0,
            1.0,
        )
    }

    /// Projects a camera-frame point to pixel coordinates; `None` behind the camera.
    pub fn project(&self, p: impl Into<Point3<f64>>) -> Option<(f64, f64)> {
        let p = p.into();
        if p[2] <= 0.0 {
            return None;
        }
        let x = p[0] / p[2];
        let y = p[1] / p[2];
        Some((self.fx * x + self.skew * y + self.cx, self.fy * y + self.cy))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A Kinect-like camera with a little skew.
    fn skewed() -> Intrinsics {
        Intrinsics {
            fx: 365.0,
            fy: 360.0,
            cx: 256.3,
            cy: 211.7,
            skew: 0.5,
        }
    }

    #[test]
    fn a_downsampled_pixel_sees_along_its_blocks_centre() {
        let k = skewed();
        for factor in [1, 2, 3, 4] {
            let c = k.box_downsampled(factor);
            let f = factor as f64;
            for (i, j) in [(0.0, 0.0), (17.0, 5.0), (63.0, 52.0)] {
                let coarse = c.ray(i, j);
                let fine = k.ray(f * i + (f - 1.0) / 2.0, f * j + (f - 1.0) / 2.0);
                assert!(
                    (coarse - fine).norm() < 1e-12,
                    "factor {factor} at ({i}, {j})"
                );
            }
        }
    }

    #[test]
    fn ray_projects_back_to_pixel() {
        let k = skewed();
        let r = k.ray(100.0, 300.0);
        let (u, v) = k.project([r[0] * 2.0, r[1] * 2.0, r[2] * 2.0]).unwrap();
        assert!((u - 100.0).abs() < 1e-9 && (v - 300.0).abs() < 1e-9);
        assert!(((r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn inverse_matrix_is_the_inverse() {
        let k = Intrinsics {
            fx: 310.0,
            fy: 290.0,
            cx: 127.3,
            cy: 95.1,
            skew: 1.7,
        };
        assert!((k.matrix() * k.inverse_matrix() - Matrix3::identity()).amax() < 1e-12);
    }

    #[test]
    fn rejects_bad_focal_length() {
        assert!(Intrinsics::new(0.0, 1.0, 0.0, 0.0).validate().is_err());
        assert!(Intrinsics::new(f64::NAN, 1.0, 0.0, 0.0).validate().is_err());
    }
}
