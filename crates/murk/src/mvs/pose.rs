//! Rigid camera poses, COLMAP convention: world-to-camera, `x_cam = R·x_world + t` (scene units),
//! rotation from a Hamilton unit quaternion `(qw, qx, qy, qz)`.
//!
//! The plane sweep needs the reference-to-source transform `(R_{r→s}, t_{r→s})` of Eq. 3.2;
//! [`Pose::relative`] builds it from two world-to-camera poses.

use nalgebra::{
    IsometryMatrix3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3,
};

use crate::error::{MurkError, Result};

/// Largest accepted `max |RᵀR − I|` entry. COLMAP writes quaternions with ~16 digits, so a
/// rotation that misses orthonormality by more than this was not produced by a rotation.
pub const ROTATION_TOLERANCE: f64 = 1e-6;

/// World-to-camera rigid transform: `x_cam = R·x_world + t` (scene units).
///
/// A validated [`IsometryMatrix3`]: the rotation is kept as the matrix it was given (a file's or
/// a request's nine numbers, or the matrix of a COLMAP quaternion), so poses round-trip through
/// the API and the model files without a quaternion in between.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    iso: IsometryMatrix3<f64>,
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
            iso: IsometryMatrix3::identity(),
        }
    }

    /// Pose from a rotation and translation (scene units), validated (see [`Pose::validate`]).
    pub fn new(rotation: Matrix3<f64>, translation: Vector3<f64>) -> Result<Self> {
        check_finite(&rotation, &translation)?;
        check_rotation(&rotation)?;
        Ok(Self {
            iso: IsometryMatrix3::from_parts(
                Translation3::from(translation),
                Rotation3::from_matrix_unchecked(rotation),
            ),
        })
    }

    /// [`Pose::new`] from a row-major rotation `rows[row][col]` and a translation, the layout of
    /// the API's and the model files' nine numbers.
    pub fn from_rows(rows: [[f64; 3]; 3], translation: [f64; 3]) -> Result<Self> {
        Self::new(Matrix3::from(rows).transpose(), Vector3::from(translation))
    }

    /// A camera that is only moved: identity rotation, `x_cam = x_world + t`.
    pub fn translation_only(translation: [f64; 3]) -> Result<Self> {
        Self::new(Matrix3::identity(), Vector3::from(translation))
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
        // Normalised in COLMAP's order of additions ((w² + x²) + y²) + z², for the same bits.
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
        Ok(Self {
            iso: IsometryMatrix3::from_parts(
                Translation3::from(Vector3::from(tvec)),
                colmap_rotation(qvec.map(|v| v / n)),
            ),
        })
    }

    /// The rotation as a unit quaternion.
    pub fn unit_quaternion(&self) -> UnitQuaternion<f64> {
        UnitQuaternion::from_rotation_matrix(&self.iso.rotation)
    }

    /// COLMAP's `(qw, qx, qy, qz)` of the rotation, with `qw ≥ 0` (q and −q are the same
    /// rotation; COLMAP does not normalise the sign either, so compare rotations, not
    /// quaternions).
    pub fn colmap_qvec(&self) -> [f64; 4] {
        let q = self.unit_quaternion();
        let sign = if q.w < 0.0 { -1.0 } else { 1.0 };
        [q.w, q.i, q.j, q.k].map(|v| sign * v)
    }

    /// The rotation matrix `R`.
    pub fn rotation(&self) -> &Matrix3<f64> {
        self.iso.rotation.matrix()
    }

    /// The translation `t`, scene units.
    pub fn translation(&self) -> &Vector3<f64> {
        &self.iso.translation.vector
    }

    /// The rotation row-major, `rows[row][col]` (the API's layout).
    pub fn rotation_rows(&self) -> [[f64; 3]; 3] {
        self.rotation().transpose().into()
    }

    /// The transform as an isometry.
    pub fn isometry(&self) -> &IsometryMatrix3<f64> {
        &self.iso
    }

    /// The same rotation with the translation multiplied by `s`: the pose of the camera in a
    /// world scaled by `s` about the origin.
    pub fn scaled(&self, s: f64) -> Self {
        let mut iso = self.iso;
        iso.translation.vector *= s;
        Self { iso }
    }

    /// Fails unless every entry is finite and `R` is a proper rotation (orthonormal within
    /// [`ROTATION_TOLERANCE`], determinant +1), naming `rotation` or `translation`.
    pub fn validate(&self) -> Result<()> {
        check_finite(self.rotation(), self.translation())?;
        check_rotation(self.rotation())
    }

    /// Applies the transform: `R·p + t`.
    #[inline]
    pub fn transform(&self, p: impl Into<Point3<f64>>) -> Point3<f64> {
        self.iso.transform_point(&p.into())
    }

    /// Rotates a direction: `R·d` (no translation).
    #[inline]
    pub fn rotate(&self, d: impl Into<Vector3<f64>>) -> Vector3<f64> {
        self.iso.transform_vector(&d.into())
    }

    /// The inverse transform (camera-to-world for a world-to-camera pose): `(Rᵀ, −Rᵀt)`.
    pub fn inverse(&self) -> Self {
        Self {
            iso: self.iso.inverse(),
        }
    }

    /// `self ∘ other`: applies `other` first, then `self` (`x ↦ R_s(R_o x + t_o) + t_s`).
    pub fn compose(&self, other: &Pose) -> Self {
        Self {
            iso: self.iso * other.iso,
        }
    }

    /// The transform from the reference camera's frame to the source camera's frame,
    /// `(R_{r→s}, t_{r→s})` of Eq. 3.2, given both world-to-camera poses:
    /// `x_s = R_s R_rᵀ x_r + (t_s − R_s R_rᵀ t_r)`.
    pub fn relative(reference: &Pose, source: &Pose) -> Self {
        source.compose(&reference.inverse())
    }

    /// Camera centre in world coordinates, `−Rᵀt` (scene units).
    pub fn camera_center(&self) -> Point3<f64> {
        Point3::from(self.inverse().iso.translation.vector)
    }
}

/// The rotation matrix of a unit quaternion `(w, x, y, z)` as COLMAP computes it (Eigen's `toRotationMatrix`:
/// `1 − 2(y² + z²)`, `2(xy − wz)`, …), bit for bit. nalgebra's
/// [`UnitQuaternion::to_rotation_matrix`] forms the diagonal as `w² + x² − y² − z²`, which is
/// the same rotation but rounds differently, so a model read by murk would sit an ulp away from
/// the one COLMAP wrote.
fn colmap_rotation([w, x, y, z]: [f64; 4]) -> Rotation3<f64> {
    Rotation3::from_matrix_unchecked(Matrix3::new(
        1.0 - 2.0 * (y * y + z * z),
        2.0 * (x * y - w * z),
        2.0 * (x * z + w * y),
        2.0 * (x * y + w * z),
        1.0 - 2.0 * (x * x + z * z),
        2.0 * (y * z - w * x),
        2.0 * (x * z - w * y),
        2.0 * (y * z + w * x),
        1.0 - 2.0 * (x * x + y * y),
    ))
}

fn check_finite(rotation: &Matrix3<f64>, translation: &Vector3<f64>) -> Result<()> {
    if rotation.iter().any(|v| !v.is_finite()) {
        return Err(MurkError::invalid(
            "rotation",
            format!(
                "rotation must be finite, got {:?}",
                <[[f64; 3]; 3]>::from(rotation.transpose())
            ),
        ));
    }
    if translation.iter().any(|v| !v.is_finite()) {
        return Err(MurkError::invalid(
            "translation",
            format!(
                "translation must be finite, got {:?}",
                <[f64; 3]>::from(*translation)
            ),
        ));
    }
    Ok(())
}

fn check_rotation(r: &Matrix3<f64>) -> Result<()> {
    let worst = (r.transpose() * r - Matrix3::identity()).amax();
    if worst > ROTATION_TOLERANCE {
        return Err(MurkError::invalid(
            "rotation",
            format!(
                "rotation is not orthonormal: max |RᵀR − I| = {worst:.3e} > {ROTATION_TOLERANCE:e}"
            ),
        ));
    }
    if r.determinant() < 0.0 {
        return Err(MurkError::invalid(
            "rotation",
            "rotation has determinant −1 (a reflection, not a rotation)",
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn max_diff(a: &Pose, b: &Pose) -> f64 {
        (a.rotation() - b.rotation())
            .amax()
            .max((a.translation() - b.translation()).amax())
    }

    use crate::error::field_of;

    #[test]
    fn quaternion_matches_known_rotation() {
        // 90° about +z: x → y.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let p = Pose::from_colmap([h, 0.0, 0.0, h], [1.0, 2.0, 3.0]).unwrap();
        let x = p.rotate([1.0, 0.0, 0.0]);
        // Row-major in and out.
        assert_eq!(p.rotation_rows()[1][0], p.rotation()[(1, 0)]);
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
    fn colmap_quaternions_give_colmaps_matrix_bit_for_bit() {
        // 1 − 2(y² + z²) and 2(xy − wz), …: Eigen's toRotationMatrix, which COLMAP uses.
        let q = [0.9, 0.1, -0.3, 0.2];
        let n = (q.iter().map(|v| v * v).sum::<f64>()).sqrt();
        let [w, x, y, z] = q.map(|v| v / n);
        let r = Pose::from_colmap(q, [0.0; 3]).unwrap();
        assert_eq!(r.rotation()[(0, 0)], 1.0 - 2.0 * (y * y + z * z));
        assert_eq!(r.rotation()[(0, 1)], 2.0 * (x * y - w * z));
        assert_eq!(r.rotation()[(2, 1)], 2.0 * (y * z + w * x));
        let ulp_apart =
            UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(0.9, 0.1, -0.3, 0.2))
                .to_rotation_matrix();
        assert!((ulp_apart.matrix() - r.rotation()).amax() < 1e-15);
    }

    #[test]
    fn rows_round_trip_and_scaling_moves_only_the_camera() {
        let p = Pose::from_colmap([0.9, 0.1, -0.3, 0.2], [0.5, -1.0, 2.0]).unwrap();
        let q = Pose::from_rows(p.rotation_rows(), [0.5, -1.0, 2.0]).unwrap();
        assert_eq!(p, q, "row-major in, row-major out, bit for bit");
        // Row-major: R·e_x is the first column, rows[·][0].
        let rows = p.rotation_rows();
        let x = p.rotate([1.0, 0.0, 0.0]);
        assert_eq!([x[0], x[1], x[2]], [rows[0][0], rows[1][0], rows[2][0]]);
        let s = p.scaled(2.5);
        assert_eq!(s.rotation(), p.rotation());
        let (c, cs) = (p.camera_center(), s.camera_center());
        assert!((cs.coords - c.coords * 2.5).amax() < 1e-12);
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
        let mut r = Matrix3::identity();
        r[(0, 0)] = 1.1;
        let err = Pose::new(r, Vector3::zeros()).unwrap_err();
        assert_eq!(field_of(err), "rotation");
        r[(0, 0)] = -1.0; // orthonormal but a reflection
        assert_eq!(
            field_of(Pose::new(r, Vector3::zeros()).unwrap_err()),
            "rotation"
        );
        r[(0, 0)] = f64::NAN;
        assert_eq!(
            field_of(Pose::new(r, Vector3::zeros()).unwrap_err()),
            "rotation"
        );
        let err = Pose::translation_only([0.0, 0.0, f64::NAN]).unwrap_err();
        assert_eq!(field_of(err), "translation");
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
            let q2 = p.colmap_qvec();
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
