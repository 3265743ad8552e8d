//! Rigid camera poses, COLMAP convention: world-to-camera, `x_cam = R·x_world + t` (scene units),
//! rotation from a Hamilton unit quaternion `(qw, qx, qy, qz)`.
//!
//! The plane sweep needs the reference-to-source transform `(R_{r→s}, t_{r→s})` of Eq. 3.2;
//! [`Pose::relative`] builds it from two world-to-camera poses.

use crate::error::{MurkError, Result};

/// Largest accepted `max |RᵀR − I|` entry. COLMAP writes quaternions with ~16 digits, so a
/// rotation that misses orthonormality by more than this was not produced by a rotation.
pub const ROTATION_TOLERANCE: f64 = 1e-6;

/// World-to-camera rigid transform: `x_cam = R·x_world + t` (scene units).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    /// Rotation, row-major: `rotation[row][col]`.
    pub rotation: [[f64; 3]; 3],
    /// Translation, scene units.
    pub translation: [f64; 3],
}

impl Default for Pose {
    fn default() -> Self {
        Self::identity()
    }
}

impl Pose {
    /// The identity transform (camera at the world origin looking along +z).
    pub fn identity() -> Self {
        Self {
            rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            translation: [0.0; 3],
        }
    }

    /// Pose from a rotation and translation, validated (see [`Pose::validate`]).
    pub fn new(rotation: [[f64; 3]; 3], translation: [f64; 3]) -> Result<Self> {
        let p = Self {
            rotation,
            translation,
        };
        p.validate()?;
        Ok(p)
    }

    /// Pose from COLMAP's `QW QX QY QZ TX TY TZ` (world-to-camera). The quaternion is normalised
    /// (COLMAP's are unit up to printing precision); a zero or non-finite quaternion fails naming
    /// `qvec`, a non-finite translation naming `tvec`.
    pub fn from_colmap(qvec: [f64; 4], tvec: [f64; 3]) -> Result<Self> {
        if qvec.iter().any(|v| !v.is_finite()) {
            return Err(MurkError::invalid(
                "qvec",
                format!("quaternion must be finite, got {qvec:?}"),
            ));
        }
        let n = qvec.iter().map(|v| v * v).sum::<f64>().sqrt();
        if n < 1e-12 {
            return Err(MurkError::invalid(
                "qvec",
                format!("quaternion must be non-zero, got {qvec:?}"),
            ));
        }
        if tvec.iter().any(|v| !v.is_finite()) {
            return Err(MurkError::invalid(
                "tvec",
                format!("translation must be finite, got {tvec:?}"),
            ));
        }
        let [w, x, y, z] = qvec.map(|v| v / n);
        let rotation = [
            [
                1.0 - 2.0 * (y * y + z * z),
                2.0 * (x * y - w * z),
                2.0 * (x * z + w * y),
            ],
            [
                2.0 * (x * y + w * z),
                1.0 - 2.0 * (x * x + z * z),
                2.0 * (y * z - w * x),
            ],
            [
                2.0 * (x * z - w * y),
                2.0 * (y * z + w * x),
                1.0 - 2.0 * (x * x + y * y),
            ],
        ];
        Ok(Self {
            rotation,
            translation: tvec,
        })
    }

    /// Unit quaternion `(qw, qx, qy, qz)` of the rotation, with `qw ≥ 0` (q and −q are the same
    /// rotation; COLMAP does not normalise the sign either, so compare rotations, not quaternions).
    pub fn quaternion(&self) -> [f64; 4] {
        let r = &self.rotation;
        let trace = r[0][0] + r[1][1] + r[2][2];
        // Shepperd's method: divide by the largest of the four candidates for accuracy.
        let q = if trace > 0.0 {
            let s = (trace + 1.0).sqrt() * 2.0;
            [
                0.25 * s,
                (r[2][1] - r[1][2]) / s,
                (r[0][2] - r[2][0]) / s,
                (r[1][0] - r[0][1]) / s,
            ]
        } else if r[0][0] > r[1][1] && r[0][0] > r[2][2] {
            let s = (1.0 + r[0][0] - r[1][1] - r[2][2]).sqrt() * 2.0;
            [
                (r[2][1] - r[1][2]) / s,
                0.25 * s,
                (r[0][1] + r[1][0]) / s,
                (r[0][2] + r[2][0]) / s,
            ]
        } else if r[1][1] > r[2][2] {
            let s = (1.0 + r[1][1] - r[0][0] - r[2][2]).sqrt() * 2.0;
            [
                (r[0][2] - r[2][0]) / s,
                (r[0][1] + r[1][0]) / s,
                0.25 * s,
                (r[1][2] + r[2][1]) / s,
            ]
        } else {
            let s = (1.0 + r[2][2] - r[0][0] - r[1][1]).sqrt() * 2.0;
            [
                (r[1][0] - r[0][1]) / s,
                (r[0][2] + r[2][0]) / s,
                (r[1][2] + r[2][1]) / s,
                0.25 * s,
            ]
        };
        let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        let sign = if q[0] < 0.0 { -1.0 } else { 1.0 };
        q.map(|v| sign * v / n)
    }

    /// Fails unless every entry is finite and `R` is a proper rotation (orthonormal within
    /// [`ROTATION_TOLERANCE`], determinant +1), naming `rotation` or `translation`.
    pub fn validate(&self) -> Result<()> {
        if self.rotation.iter().flatten().any(|v| !v.is_finite()) {
            return Err(MurkError::invalid(
                "rotation",
                format!("rotation must be finite, got {:?}", self.rotation),
            ));
        }
        if self.translation.iter().any(|v| !v.is_finite()) {
            return Err(MurkError::invalid(
                "translation",
                format!("translation must be finite, got {:?}", self.translation),
            ));
        }
        let r = &self.rotation;
        let mut worst = 0.0f64;
        for i in 0..3 {
            for j in 0..3 {
                let dot: f64 = (0..3).map(|k| r[k][i] * r[k][j]).sum();
                let target = if i == j { 1.0 } else { 0.0 };
                worst = worst.max((dot - target).abs());
            }
        }
        if worst > ROTATION_TOLERANCE {
            return Err(MurkError::invalid(
                "rotation",
                format!(
                    "rotation is not orthonormal: max |RᵀR − I| = {worst:.3e} > {ROTATION_TOLERANCE:e}"
                ),
            ));
        }
        if det3(r) < 0.0 {
            return Err(MurkError::invalid(
                "rotation",
                "rotation has determinant −1 (a reflection, not a rotation)",
            ));
        }
        Ok(())
    }

    /// Applies the transform: `R·p + t`.
    #[inline]
    pub fn transform(&self, p: [f64; 3]) -> [f64; 3] {
        let r = &self.rotation;
        let t = &self.translation;
        [
            r[0][0] * p[0] + r[0][1] * p[1] + r[0][2] * p[2] + t[0],
            r[1][0] * p[0] + r[1][1] * p[1] + r[1][2] * p[2] + t[1],
            r[2][0] * p[0] + r[2][1] * p[1] + r[2][2] * p[2] + t[2],
        ]
    }

    /// Rotates a direction: `R·d` (no translation).
    #[inline]
    pub fn rotate(&self, d: [f64; 3]) -> [f64; 3] {
        let r = &self.rotation;
        [
            r[0][0] * d[0] + r[0][1] * d[1] + r[0][2] * d[2],
            r[1][0] * d[0] + r[1][1] * d[1] + r[1][2] * d[2],
            r[2][0] * d[0] + r[2][1] * d[1] + r[2][2] * d[2],
        ]
    }

    /// The inverse transform (camera-to-world for a world-to-camera pose): `(Rᵀ, −Rᵀt)`.
    pub fn inverse(&self) -> Self {
        let r = &self.rotation;
        let rt = [
            [r[0][0], r[1][0], r[2][0]],
            [r[0][1], r[1][1], r[2][1]],
            [r[0][2], r[1][2], r[2][2]],
        ];
        let t = &self.translation;
        let mut ti = [0.0; 3];
        for (i, row) in rt.iter().enumerate() {
            ti[i] = -(row[0] * t[0] + row[1] * t[1] + row[2] * t[2]);
        }
        Self {
            rotation: rt,
            translation: ti,
        }
    }

    /// `self ∘ other`: applies `other` first, then `self` (`x ↦ R_s(R_o x + t_o) + t_s`).
    pub fn compose(&self, other: &Pose) -> Self {
        let a = &self.rotation;
        let b = &other.rotation;
        let mut r = [[0.0; 3]; 3];
        for (i, row) in r.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                *v = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
            }
        }
        Self {
            rotation: r,
            translation: self.transform(other.translation),
        }
    }

    /// The transform from the reference camera's frame to the source camera's frame,
    /// `(R_{r→s}, t_{r→s})` of Eq. 3.2, given both world-to-camera poses:
    /// `x_s = R_s R_rᵀ x_r + (t_s − R_s R_rᵀ t_r)`.
    pub fn relative(reference: &Pose, source: &Pose) -> Self {
        source.compose(&reference.inverse())
    }

    /// Camera centre in world coordinates, `−Rᵀt` (scene units).
    pub fn camera_center(&self) -> [f64; 3] {
        self.inverse().translation
    }
}

fn det3(r: &[[f64; 3]; 3]) -> f64 {
    r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1])
        - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
        + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0])
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn max_diff(a: &Pose, b: &Pose) -> f64 {
        let r = a
            .rotation
            .iter()
            .flatten()
            .zip(b.rotation.iter().flatten())
            .map(|(x, y)| (x - y).abs());
        let t = a
            .translation
            .iter()
            .zip(&b.translation)
            .map(|(x, y)| (x - y).abs());
        r.chain(t).fold(0.0, f64::max)
    }

    use crate::error::field_of;

    #[test]
    fn quaternion_matches_known_rotation() {
        // 90° about +z: x → y.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let p = Pose::from_colmap([h, 0.0, 0.0, h], [1.0, 2.0, 3.0]).unwrap();
        let x = p.rotate([1.0, 0.0, 0.0]);
        assert!((x[0]).abs() < 1e-12 && (x[1] - 1.0).abs() < 1e-12 && x[2].abs() < 1e-12);
        assert!(p.validate().is_ok());
        // Camera centre maps to the origin of the camera frame.
        let c = p.camera_center();
        let o = p.transform(c);
        assert!(o.iter().all(|v| v.abs() < 1e-12), "{o:?}");
    }

    #[test]
    fn inverse_compose_relative() {
        let a = Pose::from_colmap([0.9, 0.1, -0.3, 0.2], [0.5, -1.0, 2.0]).unwrap();
        let b = Pose::from_colmap([0.2, 0.7, 0.1, -0.4], [-0.3, 0.2, 1.0]).unwrap();
        assert!(max_diff(&a.compose(&a.inverse()), &Pose::identity()) < 1e-12);
        assert!(max_diff(&Pose::relative(&a, &a), &Pose::identity()) < 1e-12);
        // A world point seen from a, carried by relative(a, b), lands where b sees it.
        let xw = [0.3, -0.7, 4.0];
        let rel = Pose::relative(&a, &b);
        let via = rel.transform(a.transform(xw));
        let direct = b.transform(xw);
        for k in 0..3 {
            assert!((via[k] - direct[k]).abs() < 1e-12);
        }
    }

    #[test]
    fn validation_names_fields() {
        assert_eq!(
            field_of(Pose::from_colmap([0.0; 4], [0.0; 3]).unwrap_err()),
            "qvec"
        );
        assert_eq!(
            field_of(Pose::from_colmap([1.0, f64::NAN, 0.0, 0.0], [0.0; 3]).unwrap_err()),
            "qvec"
        );
        assert_eq!(
            field_of(
                Pose::from_colmap([1.0, 0.0, 0.0, 0.0], [0.0, f64::INFINITY, 0.0]).unwrap_err()
            ),
            "tvec"
        );
        let mut p = Pose::identity();
        p.rotation[0][0] = 1.1;
        assert_eq!(field_of(p.validate().unwrap_err()), "rotation");
        p.rotation[0][0] = -1.0; // orthonormal but a reflection
        assert_eq!(field_of(p.validate().unwrap_err()), "rotation");
        let mut p = Pose::identity();
        p.translation[2] = f64::NAN;
        assert_eq!(field_of(p.validate().unwrap_err()), "translation");
    }

    proptest! {
        #[test]
        fn quaternion_round_trip(
            q in proptest::array::uniform4(-1.0f64..1.0),
            t in proptest::array::uniform3(-10.0f64..10.0),
        ) {
            let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
            prop_assume!(n > 1e-3);
            let p = Pose::from_colmap(q, t).unwrap();
            prop_assert!(p.validate().is_ok());
            let q2 = p.quaternion();
            // Same rotation up to the sign of q.
            let sign = if q[0] < 0.0 { -1.0 } else { 1.0 };
            for k in 0..4 {
                prop_assert!((q2[k] - sign * q[k] / n).abs() < 1e-9 || q[0].abs() < 1e-9,
                    "{q:?} -> {q2:?}");
            }
            let p2 = Pose::from_colmap(q2, t).unwrap();
            prop_assert!(max_diff(&p, &p2) < 1e-12);
        }
    }
}
