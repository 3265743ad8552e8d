//! Plane-sweep geometry (reference §3.2.2, Eq. 3.2 and 3.6).
//!
//! Fronto-parallel planes `z = z_i` in the reference camera are sampled uniformly in inverse depth
//! ([`PlaneSet`]). For plane `i`, reference pixel `(u, v)` is back-projected to the 3D point at
//! z-depth `z_i`, moved into the source camera with `(R_{r→s}, t_{r→s})` and projected:
//! `π_{r→s}(u, v; z_i)` (Eq. 3.2). The same point's z-depth in the source camera is `ζ_{s,i}`
//! (Eq. 3.6), the depth used to dehaze the source sample.
//!
//! Per plane the whole map is one homography `H_i = K_s (R + t nᵀ / z_i) K_r⁻¹`, `n = (0, 0, 1)`,
//! and because `K_s`'s last row is `(0, 0, 1)` the homogeneous coordinate of `H_i·(u, v, 1)` is
//! exactly `ζ / z_i`: [`PlaneWarp::map`] gets `ζ` for free, with no per-pixel back-projection.

use nalgebra::{Matrix3, Vector3};

use crate::camera::Intrinsics;
use crate::error::{MurkError, Result};
use crate::mvs::pose::Pose;

/// Largest accepted number of planes. The cost volume holds `W·H·N` `f32`s (256×192×1024 is
/// 200 MB) and more planes than pixels of disparity range add cost without resolving anything.
pub const MAX_PLANES: usize = 1024;

/// `N` fronto-parallel planes in the reference camera, uniform in **inverse** depth between
/// `1/far` and `1/near` (scene units). Plane `0` is the **farthest** (inverse depth `1/far`),
/// plane `N − 1` the nearest (`1/near`), i.e. the index grows with inverse depth (disparity).
/// With `N = 1` the single plane sits at the mean inverse depth.
///
/// Defaults follow the reference (§3.2.3): inverse depth 0.02 … 2 (z 50 … 0.5), `N = 256`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlaneSet {
    /// Nearest plane's z-depth, scene units, finite and `> 0`.
    pub near: f64,
    /// Farthest plane's z-depth, scene units, finite and `> near`.
    pub far: f64,
    /// Number of planes, `1 ..= MAX_PLANES`.
    pub num_planes: usize,
}

impl Default for PlaneSet {
    fn default() -> Self {
        Self {
            near: 0.5,
            far: 50.0,
            num_planes: 256,
        }
    }
}

impl PlaneSet {
    /// A validated plane set.
    pub fn new(near: f64, far: f64, num_planes: usize) -> Result<Self> {
        let p = Self {
            near,
            far,
            num_planes,
        };
        p.validate()?;
        Ok(p)
    }

    /// Fails naming `near`, `far` or `num_planes` unless `0 < near < far < ∞` and
    /// `1 ≤ num_planes ≤ MAX_PLANES`.
    pub fn validate(&self) -> Result<()> {
        if !self.near.is_finite() || self.near <= 0.0 {
            return Err(MurkError::invalid(
                "near",
                format!(
                    "near plane depth must be finite and > 0 (scene units), got {}",
                    self.near
                ),
            ));
        }
        if !self.far.is_finite() || self.far <= self.near {
            return Err(MurkError::invalid(
                "far",
                format!(
                    "far plane depth must be finite and > near = {}, got {}",
                    self.near, self.far
                ),
            ));
        }
        if self.num_planes == 0 || self.num_planes > MAX_PLANES {
            return Err(MurkError::invalid(
                "num_planes",
                format!(
                    "number of planes must be in 1..={MAX_PLANES}, got {}",
                    self.num_planes
                ),
            ));
        }
        Ok(())
    }

    /// Number of planes.
    pub fn len(&self) -> usize {
        self.num_planes
    }

    /// True when there are no planes (never for a validated set).
    pub fn is_empty(&self) -> bool {
        self.num_planes == 0
    }

    /// Spacing between consecutive planes in inverse depth (per scene unit); 0 for `N = 1`.
    pub fn inverse_depth_step(&self) -> f64 {
        if self.num_planes <= 1 {
            0.0
        } else {
            (1.0 / self.near - 1.0 / self.far) / (self.num_planes - 1) as f64
        }
    }

    /// Inverse depth of plane `i` (per scene unit); `i` may be fractional (sub-plane refinement).
    pub fn inverse_depth(&self, i: f64) -> f64 {
        if self.num_planes <= 1 {
            0.5 * (1.0 / self.near + 1.0 / self.far)
        } else {
            1.0 / self.far + i * self.inverse_depth_step()
        }
    }

    /// z-depth of plane `i` (scene units); `i` may be fractional.
    pub fn depth(&self, i: f64) -> f64 {
        1.0 / self.inverse_depth(i)
    }

    /// z-depths of all planes, index order (far to near).
    pub fn depths(&self) -> Vec<f64> {
        (0..self.num_planes).map(|i| self.depth(i as f64)).collect()
    }

    /// Continuous plane index of inverse depth `inv_z` (may lie outside `[0, N − 1]`); the inverse
    /// of [`PlaneSet::inverse_depth`]. `0` for `N = 1`.
    pub fn index_of_inverse_depth(&self, inv_z: f64) -> f64 {
        let step = self.inverse_depth_step();
        if step == 0.0 {
            0.0
        } else {
            (inv_z - 1.0 / self.far) / step
        }
    }
}

/// The reference→source map for one plane `z = z_i` (Eq. 3.2 and 3.6), precomputed as the plane
/// homography `H_i = K_s (R + t nᵀ / z_i) K_r⁻¹`.
///
/// Inputs are trusted (validate intrinsics, poses and planes first); the map is pure arithmetic.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlaneWarp {
    h: Matrix3<f64>,
    depth: f64,
}

impl PlaneWarp {
    /// Warp for the plane at z-depth `depth` (scene units, `> 0`) of the reference camera `k_ref`,
    /// seen by the source camera `k_src` whose frame is `relative` = `(R_{r→s}, t_{r→s})` away
    /// (see [`Pose::relative`]).
    pub fn new(k_ref: &Intrinsics, k_src: &Intrinsics, relative: &Pose, depth: f64) -> Self {
        let n = Vector3::z();
        let m = relative.rotation() + relative.translation() * n.transpose() / depth;
        let h = k_src.matrix() * m * k_ref.inverse_matrix();
        Self { h, depth }
    }

    /// The homography `H_i`, normalised so that its homogeneous output is `ζ / z_i`.
    pub fn homography(&self) -> &Matrix3<f64> {
        &self.h
    }

    /// The plane's z-depth `z_i` in the reference camera (scene units).
    pub fn depth(&self) -> f64 {
        self.depth
    }

    /// Maps reference pixel `(u, v)` to `(u', v', ζ)`: the source pixel `π_{r→s}(u, v; z_i)` and
    /// the plane point's z-depth in the source camera (scene units). When `ζ ≤ 0` the point is
    /// behind the source camera and `(u', v')` is meaningless: callers must treat it as invalid.
    #[inline]
    pub fn map(&self, u: f64, v: f64) -> (f64, f64, f64) {
        let h = &self.h;
        let x = h[(0, 0)] * u + h[(0, 1)] * v + h[(0, 2)];
        let y = h[(1, 0)] * u + h[(1, 1)] * v + h[(1, 2)];
        let w = h[(2, 0)] * u + h[(2, 1)] * v + h[(2, 2)];
        // One reciprocal instead of two divisions: this sits in the cost volume's inner loop.
        let r = 1.0 / w;
        (x * r, y * r, w * self.depth)
    }

    /// The map restricted to row `v`, for loops that sweep `u` along a row.
    #[inline]
    pub fn row(&self, v: f64) -> RowWarp {
        let h = &self.h;
        RowWarp {
            slope: [h[(0, 0)], h[(1, 0)], h[(2, 0)]],
            offset: [
                h[(0, 1)] * v + h[(0, 2)],
                h[(1, 1)] * v + h[(1, 2)],
                h[(2, 1)] * v + h[(2, 2)],
            ],
            depth: self.depth,
        }
    }
}

/// [`PlaneWarp`] on one reference row: the homogeneous source coordinates are affine in `u`,
/// so each pixel costs three multiply-adds and one reciprocal.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RowWarp {
    slope: [f64; 3],
    offset: [f64; 3],
    depth: f64,
}

impl RowWarp {
    /// `(slope, offset, depth)`: the homogeneous source coordinates at `u` are
    /// `slope·u + offset`, and `ζ = (slope[2]·u + offset[2])·depth`.
    pub fn coefficients(&self) -> ([f64; 3], [f64; 3], f64) {
        (self.slope, self.offset, self.depth)
    }

    /// The coefficients in `f32`, for the per-voxel loops ([`RowWarpF32`]).
    pub fn to_f32(&self) -> RowWarpF32 {
        RowWarpF32 {
            slope: self.slope.map(|v| v as f32),
            offset: self.offset.map(|v| v as f32),
        }
    }

    /// `(du, v)` when this row maps to the source as a horizontal shift, `u ↦ (u + du, v)`, to
    /// within `tolerance_px` pixels over the `width` columns of the row, and lies in front of the
    /// source camera: no rotation between the views (`slope[2] = 0`), the same horizontal scale
    /// and no vertical slope, as for a rectified pair (the views of a rig that translates along
    /// its rows). `du` and `v` are the fit at the row's centre, finite. `None` otherwise.
    pub fn shift(&self, width: usize, tolerance_px: f64) -> Option<(f64, f64)> {
        let [s0, s1, s2] = self.slope;
        let [o0, o1, o2] = self.offset;
        if s2 != 0.0 || o2.is_nan() || o2 <= 0.0 {
            return None;
        }
        let half = width.saturating_sub(1) as f64 / 2.0;
        let (scale, tilt) = (s0 / o2 - 1.0, s1 / o2);
        // The affine map `u(x) = (1 + scale)·x + o0/o2` against `x + du` with `du` fitted at the
        // centre differs by at most |scale|·half at either end (likewise `v`).
        let (du, v) = (o0 / o2 + scale * half, o1 / o2 + tilt * half);
        (scale.abs() * half <= tolerance_px
            && tilt.abs() * half <= tolerance_px
            && du.is_finite()
            && v.is_finite())
        .then_some((du, v))
    }

    /// Same as [`PlaneWarp::map`]`(u, v)` for this row's `v`.
    #[inline]
    pub fn map(&self, u: f64) -> (f64, f64, f64) {
        let x = self.slope[0] * u + self.offset[0];
        let y = self.slope[1] * u + self.offset[1];
        let w = self.slope[2] * u + self.offset[2];
        let r = 1.0 / w;
        (x * r, y * r, w * self.depth)
    }
}

/// [`RowWarp`] in `f32`: an `f32` reciprocal per voxel instead of an `f64` division, so the
/// per-voxel loops (the cost volume's source coordinates, the consistency check's claims)
/// vectorise. For images up to 4096 px the rounding moves a point by < 0.01 px.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RowWarpF32 {
    slope: [f32; 3],
    offset: [f32; 3],
}

impl RowWarpF32 {
    /// Source coordinates `(u, v)` of column `x` and the homogeneous scale `w` of the point: it
    /// lies in front of the source camera when `w > 0` (`ζ = w·depth` with a positive depth).
    #[inline(always)]
    pub fn project(&self, x: f32) -> (f32, f32, f32) {
        let hw = self.slope[2] * x + self.offset[2];
        let r = 1.0 / hw;
        (
            (self.slope[0] * x + self.offset[0]) * r,
            (self.slope[1] * x + self.offset[1]) * r,
            hw,
        )
    }

    /// `1 / w` when the homogeneous scale `w` is the same positive value along the whole row
    /// (`slope[2] = 0`: no rotation between the views, as in a rectified pair or a rig that only
    /// translates), else `None`.
    #[inline(always)]
    pub fn constant_reciprocal(&self) -> Option<f32> {
        (self.slope[2] == 0.0 && self.offset[2] > 0.0).then(|| 1.0 / self.offset[2])
    }

    /// [`Self::project`] of a row whose [`Self::constant_reciprocal`] is `r`: no division per
    /// column, and the same values to the bit (`0·x + offset[2]` is `offset[2]` for `x ≥ 0`).
    #[inline(always)]
    pub fn project_with(&self, x: f32, r: f32) -> (f32, f32, f32) {
        (
            (self.slope[0] * x + self.offset[0]) * r,
            (self.slope[1] * x + self.offset[1]) * r,
            self.offset[2],
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    use crate::error::field_of;

    /// Back-project, transform, project: the direct reading of Eq. 3.2 / 3.6.
    fn reference_map(
        k_ref: &Intrinsics,
        k_src: &Intrinsics,
        rel: &Pose,
        z: f64,
        u: f64,
        v: f64,
    ) -> (f64, f64, f64) {
        let ray = k_ref.ray(u, v);
        let p = [ray[0] / ray[2] * z, ray[1] / ray[2] * z, z];
        let q = rel.transform(p);
        let (us, vs) = k_src.project(q).expect("in front of the source camera");
        (us, vs, q[2])
    }

    #[test]
    fn plane_set_defaults_and_spacing() {
        let p = PlaneSet::default();
        p.validate().unwrap();
        assert_eq!(p.len(), 256);
        assert!((p.inverse_depth(0.0) - 0.02).abs() < 1e-15);
        assert!((p.inverse_depth(255.0) - 2.0).abs() < 1e-12);
        assert!((p.depth(0.0) - 50.0).abs() < 1e-9 && (p.depth(255.0) - 0.5).abs() < 1e-12);
        assert!((p.index_of_inverse_depth(p.inverse_depth(17.25)) - 17.25).abs() < 1e-9);
        let d = p.depths();
        assert!(d.windows(2).all(|w| w[0] > w[1]));
        let one = PlaneSet::new(1.0, 3.0, 1).unwrap();
        assert!((one.depth(0.0) - 1.5).abs() < 1e-12);
    }

    #[test]
    fn plane_set_validation_names_fields() {
        assert_eq!(field_of(PlaneSet::new(0.0, 1.0, 8).unwrap_err()), "near");
        assert_eq!(
            field_of(PlaneSet::new(f64::NAN, 1.0, 8).unwrap_err()),
            "near"
        );
        assert_eq!(field_of(PlaneSet::new(2.0, 2.0, 8).unwrap_err()), "far");
        assert_eq!(field_of(PlaneSet::new(2.0, 1.0, 8).unwrap_err()), "far");
        assert_eq!(
            field_of(PlaneSet::new(1.0, f64::INFINITY, 8).unwrap_err()),
            "far"
        );
        assert_eq!(
            field_of(PlaneSet::new(1.0, 2.0, 0).unwrap_err()),
            "num_planes"
        );
        assert_eq!(
            field_of(PlaneSet::new(1.0, 2.0, MAX_PLANES + 1).unwrap_err()),
            "num_planes"
        );
        assert!(PlaneSet::new(1.0, 2.0, MAX_PLANES).is_ok());
    }

    #[test]
    fn identity_pose_maps_pixel_to_itself() {
        let k = Intrinsics::new(200.0, 210.0, 127.5, 95.5);
        for z in [0.5, 3.0, 50.0] {
            let w = PlaneWarp::new(&k, &k, &Pose::identity(), z);
            for (u, v) in [(0.0, 0.0), (255.0, 191.0), (13.25, 77.5)] {
                let (us, vs, zeta) = w.map(u, v);
                assert!((us - u).abs() < 1e-12 && (vs - v).abs() < 1e-12);
                assert!((zeta - z).abs() < 1e-12 * z);
            }
        }
    }

    #[test]
    fn known_baseline_gives_expected_disparity() {
        // Source camera shifted by b along +x: x_s = x_r − b, so u' = u − fx·b/z, ζ = z.
        let k = Intrinsics::new(250.0, 250.0, 128.0, 96.0);
        let b = 0.2;
        let rel = Pose::translation_only([-b, 0.0, 0.0]).unwrap();
        for z in [1.0, 2.5, 10.0] {
            let w = PlaneWarp::new(&k, &k, &rel, z);
            let (us, vs, zeta) = w.map(100.0, 40.0);
            assert!((100.0 - us - 250.0 * b / z).abs() < 1e-12, "z = {z}");
            assert!((vs - 40.0).abs() < 1e-12 && (zeta - z).abs() < 1e-12);
        }
        // Moving the source camera forward along +z changes ζ by the same amount.
        let fwd = Pose::translation_only([0.0, 0.0, -0.5]).unwrap();
        let (_, _, zeta) = PlaneWarp::new(&k, &k, &fwd, 3.0).map(10.0, 20.0);
        assert!((zeta - 2.5).abs() < 1e-12);
    }

    /// Views that only translate (a rectified pair, a rig moving forward, with different
    /// intrinsics) have one homogeneous scale along each row, and projecting with its reciprocal
    /// gives the general projection's values to the bit; a rotation between the views has none.
    #[test]
    fn translation_only_rows_project_with_one_reciprocal_bit_for_bit() {
        let k_ref = Intrinsics::new(250.0, 240.0, 128.0, 96.0);
        let k_src = Intrinsics::new(230.0, 235.0, 120.5, 99.0);
        for t in [[-0.2, 0.0, 0.0], [0.05, -0.1, -0.4], [0.0, 0.0, 0.3]] {
            let rel = Pose::translation_only(t).unwrap();
            for z in [0.7, 3.0, 40.0] {
                let warp = PlaneWarp::new(&k_ref, &k_src, &rel, z);
                for y in [0.0, 17.0, 191.0] {
                    let row = warp.row(y).to_f32();
                    let r = row.constant_reciprocal().expect("no rotation");
                    for x in (0..256).map(|x| x as f32) {
                        let (a, b, c) = row.project(x);
                        let (d, e, f) = row.project_with(x, r);
                        assert_eq!(
                            (a.to_bits(), b.to_bits(), c.to_bits()),
                            (d.to_bits(), e.to_bits(), f.to_bits()),
                            "t {t:?} z {z} row {y} column {x}"
                        );
                    }
                }
            }
        }
        let turned = Pose::from_colmap([1.0, 0.0, 0.05, 0.0], [-0.2, 0.0, 0.0]).unwrap();
        let row = PlaneWarp::new(&k_ref, &k_src, &turned, 3.0)
            .row(10.0)
            .to_f32();
        assert_eq!(row.constant_reciprocal(), None);
    }

    /// A rectified pair's rows are shifts: `map` moves every column by `du` and keeps `v`; a
    /// vertical baseline, a forward baseline (a zoom), other focal lengths and a rotation are not.
    #[test]
    fn rectified_rows_are_shifts_and_others_are_not() {
        let k = Intrinsics::new(250.0, 240.0, 128.0, 96.0);
        let side = Pose::translation_only([-0.2, 0.0, 0.0]).unwrap();
        for z in [0.7, 3.0, 40.0] {
            let warp = PlaneWarp::new(&k, &k, &side, z);
            for y in [0.0, 17.0, 191.0] {
                let row = warp.row(y);
                let (du, v) = row.shift(256, 1e-3).expect("a rectified row");
                for x in [0.0, 100.0, 255.0] {
                    let (u, vv, _) = row.map(x);
                    assert!((u - (x + du)).abs() < 1e-9 && (vv - v).abs() < 1e-9);
                }
                assert!((du - (-0.2 * 250.0 / z)).abs() < 1e-9 && (v - y).abs() < 1e-9);
            }
        }
        let other_k = Intrinsics::new(230.0, 240.0, 128.0, 96.0);
        let turned = Pose::from_colmap([1.0, 0.0, 0.05, 0.0], [-0.2, 0.0, 0.0]).unwrap();
        // A vertical baseline moves whole rows (a shift by 0 columns to another `v`); a forward
        // baseline zooms, another focal length scales, a rotation turns.
        for (k_src, rel, is_shift) in [
            (k, Pose::translation_only([0.0, -0.2, 0.0]).unwrap(), true),
            (k, Pose::translation_only([-0.2, 0.0, 0.3]).unwrap(), false),
            (other_k, side, false),
            (k, turned, false),
        ] {
            let row = PlaneWarp::new(&k, &k_src, &rel, 3.0).row(10.0);
            assert_eq!(row.shift(256, 1e-3).is_some(), is_shift, "{rel:?}");
            // The oracle: whether some column leaves `x + du`, `v` by more than the tolerance.
            let (u0, v0, _) = row.map(0.0);
            let moves = (0..256).any(|x| {
                let (u, v, _) = row.map(x as f64);
                ((u - u0) - x as f64).abs() > 1e-3 || (v - v0).abs() > 1e-3
            });
            assert_eq!(is_shift, !moves, "{rel:?}");
        }
    }

    proptest! {
        #[test]
        fn homography_matches_explicit_projection(
            q in proptest::array::uniform4(-1.0f64..1.0),
            t in proptest::array::uniform3(-0.5f64..0.5),
            f in 100.0f64..600.0,
            skew in -2.0f64..2.0,
            z in 0.5f64..50.0,
            u in 0.0f64..256.0,
            v in 0.0f64..192.0,
        ) {
            // Small rotations only, so the plane point stays in front of the source camera.
            let qn = [1.0, 0.1 * q[0], 0.1 * q[1], 0.1 * q[2]];
            let rel = Pose::from_colmap(qn, t).unwrap();
            let k_ref = Intrinsics { fx: f, fy: f * 1.05, cx: 128.0, cy: 96.0, skew };
            let k_src = Intrinsics { fx: f * 0.9, fy: f * 0.95, cx: 120.0, cy: 100.0, skew: 0.3 };
            let ray = k_ref.ray(u, v);
            let p = [ray[0] / ray[2] * z, ray[1] / ray[2] * z, z];
            prop_assume!(rel.transform(p)[2] > 0.05);
            let warp = PlaneWarp::new(&k_ref, &k_src, &rel, z);
            let (a, b, c) = warp.map(u, v);
            let (ra, rb, rc) = warp.row(v).map(u);
            prop_assert!((ra - a).abs() <= 1e-9 * a.abs().max(1.0));
            prop_assert!((rb - b).abs() <= 1e-9 * b.abs().max(1.0));
            prop_assert!((rc - c).abs() <= 1e-9 * c.abs().max(1.0));
            let (ea, eb, ec) = reference_map(&k_ref, &k_src, &rel, z, u, v);
            // Scale tolerances with magnitudes: pixel coordinates can grow large near the
            // source camera's plane, depths span 0.5 … 50.
            prop_assert!((a - ea).abs() <= 1e-9 * ea.abs().max(1.0), "u': {a} vs {ea}");
            prop_assert!((b - eb).abs() <= 1e-9 * eb.abs().max(1.0), "v': {b} vs {eb}");
            prop_assert!((c - ec).abs() <= 1e-9 * ec.abs().max(1.0), "zeta: {c} vs {ec}");
        }
    }
}
