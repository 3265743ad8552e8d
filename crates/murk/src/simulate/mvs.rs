//! `murk simulate mvs` backend: hazy multi-view captures of procedural indoor scenes with ground
//! truth, for the dehazing cost volume (reference Ch. 3.2) and the scattering-parameter search
//! that needs a sparse SfM cloud.
//!
//! **Scene.** A closed box room (floor, ceiling, back wall at z ∈ [10, 12], side walls at
//! x = ±3, a wall behind the cameras) holding boxes resting on the floor and spheres. Every
//! camera ray hits a surface (no sky). Surfaces carry solid procedural textures — multi-scale
//! value noise, checkers, or both mixed — evaluated at the 3D hit point, so the texture is the
//! same from every view; the ceiling and one box are only weakly textured. Radiance is
//! Lambertian (`albedo · (0.3 + 0.7 max(0, n·l))`, one fixed directional light), hence
//! view-independent and photo-consistent. Scene units are arbitrary ("metres").
//!
//! **Cameras.** World frame = reference camera frame (+x right, +y down, +z forward; the floor is
//! at y = +1.5). `num_views` pinhole cameras (default 5, 256×192 like the reference's input)
//! along a horizontal trajectory of length `trajectory_length` with small jitter and a yaw
//! towards the room centre; the reference is the middle view. With `rectified_pair` there are
//! exactly two cameras with identical orientation, the source shifted by `trajectory_length`
//! along +x (pure x translation), and the left one is the reference.
//!
//! **Haze** (Eq. 3.3, [`crate::atmosphere::haze`]): `A ~ U(airlight_range)`, a target median
//! transmission `t_med ~ U(median_transmission_range)` over the reference view, and
//! `β = −ln(t_med) / median(z_ref)`; every view is hazed with its own z-depth. With
//! `beta_range`, `β` is drawn from that range instead and the scene is scaled to match (the
//! images do not change, lengths do). Then additive
//! Gaussian noise of `noise_sigma` on clear and hazy images alike, clipped to `[0, 1]`.
//! Images are rendered with `supersample²` rays per pixel; depth is the z-depth of the pixel
//! centre ray.
//!
//! **Sparse cloud.** On a jittered grid of pixels (step `point_stride_px`) of each view on
//! textured surfaces, back-project with the GT depth, keep points visible (in the image and
//! passing a 2 % depth test against that view's GT depth) in ≥ 2 views; their 2D observations
//! are the exact projections (COLMAP pixel convention), their 3D positions get Gaussian noise
//! of `point_noise` (scene units), the recorded error is the resulting mean reprojection error.
//!
//! Determinism: one ChaCha8 stream for the scene and per (view, row) noise streams, so the output
//! depends only on the config, not on thread scheduling.
//!
//! Folder layout ([`write_mvs_scene`] / [`read_mvs_scene`]):
//!
//! ```text
//! <dir>/
//!   meta.json            format "murk.mvs_scene" v1: config, reference image name, view names,
//!                        airlight A, beta (per scene unit), median transmission, units
//!   images/view_XX.png   hazy RGB input, 16-bit PNG (values in [0, 1] → 0..65535)
//!   clear/view_XX.png    the same view without haze (noise included), 16-bit RGB PNG
//!   depth/view_XX.exr    GT z-depth, scene units, 1 channel f32
//!   sparse/cameras.txt   COLMAP text model: one PINHOLE camera (COLMAP's +0.5 px principal
//!   sparse/images.txt    point convention), world-to-camera poses, 2D observations, and the
//!   sparse/points3D.txt  sparse cloud with tracks
//! ```

use std::collections::BTreeMap;
use std::path::Path;

use nalgebra::Matrix3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::atmosphere::haze;
use crate::camera::Intrinsics;
use crate::error::{MurkError, Result};
use crate::image::ImageF32;
use crate::io::{self, DecodeLimits};
use crate::monitor::Monitor;
use crate::mvs::colmap::{
    read_colmap_dir, write_colmap_text, ColmapCamera, ColmapImage, ColmapModel, Point2D, Point3D,
    TrackElement,
};
use crate::mvs::pose::Pose;
use crate::mvs::View;
use crate::params::pose_error::SfmTracks;
use crate::params::sparse::{PointSelection, SparseDepth};
use crate::simulate::scene::{Shape, V3};

/// `format` tag of `meta.json`.
pub const MVS_SCENE_FORMAT: &str = "murk.mvs_scene";
/// Largest accepted image side, pixels.
pub const MAX_MVS_SIDE: usize = 4096;
/// Largest accepted number of views.
pub const MAX_MVS_VIEWS: usize = 64;

/// Room bounds: x ∈ [−ROOM_X, ROOM_X], y ∈ [CEILING_Y, FLOOR_Y], z ∈ [BEHIND_Z, back wall].
const ROOM_X: f64 = 3.0;
const FLOOR_Y: f64 = 1.5;
const CEILING_Y: f64 = -2.0;
const BEHIND_Z: f64 = -1.0;

/// Simulation settings. Lengths in scene units, pixel values in `[0, 1]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct MvsSimConfig {
    /// Seed of every random choice.
    pub seed: u64,
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
    /// Focal length (fx = fy), pixels.
    pub focal_px: f64,
    /// Number of views (≥ 2; exactly 2 with `rectified_pair`).
    pub num_views: usize,
    /// Length of the camera trajectory (scene units): the largest baseline.
    pub trajectory_length: f64,
    /// Spread of the camera centres along the optical axis (scene units; 0 = a purely lateral
    /// trajectory): the views before the reference stand behind it, those after it ahead, as on
    /// a vehicle or a walking camera. Only with such depth differences between the views does
    /// the same point show different transmissions, the multi-view evidence for β.
    pub forward_motion: f64,
    /// Two cameras, same orientation, pure x translation (rectified stereo).
    pub rectified_pair: bool,
    /// Airlight `A` is drawn uniformly from this range, within `(0, 1]`.
    pub airlight_range: [f32; 2],
    /// Target median transmission over the reference view, drawn uniformly, within `(0, 1)`.
    pub median_transmission_range: [f64; 2],
    /// When set, `β` (per scene unit) is drawn uniformly from this range instead of being
    /// derived from the room's size, and the whole scene (geometry, camera positions, sparse
    /// cloud, depth) is scaled so that the median transmission still meets its drawn target:
    /// a pinhole image does not change when the world is scaled about the origin, so the
    /// images are the same and only lengths change. The reference's setting for indoor scenes
    /// is `[0.4, 0.8]`.
    pub beta_range: Option<[f32; 2]>,
    /// Standard deviation of the additive Gaussian image noise (pixel-value units).
    pub noise_sigma: f32,
    /// Rays per pixel along each axis (anti-aliasing).
    pub supersample: usize,
    /// Number of boxes on the floor.
    pub num_boxes: usize,
    /// Number of spheres.
    pub num_spheres: usize,
    /// Grid step of the pixels sampled for the sparse cloud, pixels.
    pub point_stride_px: usize,
    /// Standard deviation of the noise on sparse 3D points, scene units.
    pub point_noise: f64,
    /// Factor on every surface's albedo before the radiance is clipped to `[0.02, 0.98]`: how
    /// bright the scene is against the airlight. 1 keeps the rooms as they were; above 1, lit
    /// surfaces can be brighter than a dim airlight, as white walls are in real haze.
    pub albedo_scale: f64,
}

impl Default for MvsSimConfig {
    fn default() -> Self {
        Self {
            seed: 0,
            width: 256,
            height: 192,
            focal_px: 200.0,
            num_views: 5,
            trajectory_length: 0.4,
            forward_motion: 0.0,
            rectified_pair: false,
            airlight_range: [0.7, 1.0],
            median_transmission_range: [0.2, 0.4],
            beta_range: None,
            noise_sigma: 0.01,
            supersample: 2,
            num_boxes: 3,
            num_spheres: 2,
            point_stride_px: 8,
            point_noise: 0.005,
            albedo_scale: 1.0,
        }
    }
}

fn bad(field: &str, reason: String) -> MurkError {
    MurkError::invalid(field, reason)
}

impl MvsSimConfig {
    /// Default config at another image size, focal length scaled with the width.
    pub fn with_size(width: usize, height: usize) -> Self {
        let d = Self::default();
        Self {
            width,
            height,
            focal_px: d.focal_px * width as f64 / d.width as f64,
            ..d
        }
    }

    /// Fails naming the first bad field.
    pub fn validate(&self) -> Result<()> {
        for (name, v) in [("width", self.width), ("height", self.height)] {
            if !(8..=MAX_MVS_SIDE).contains(&v) {
                return Err(bad(name, format!("must be in 8..={MAX_MVS_SIDE}, got {v}")));
            }
        }
        if !self.focal_px.is_finite() || self.focal_px <= 0.0 {
            return Err(bad(
                "focal_px",
                format!("must be finite and > 0, got {}", self.focal_px),
            ));
        }
        if self.rectified_pair {
            if self.num_views != 2 {
                return Err(bad(
                    "num_views",
                    format!("a rectified pair has 2 views, got {}", self.num_views),
                ));
            }
        } else if !(2..=MAX_MVS_VIEWS).contains(&self.num_views) {
            return Err(bad(
                "num_views",
                format!("must be in 2..={MAX_MVS_VIEWS}, got {}", self.num_views),
            ));
        }
        if !self.trajectory_length.is_finite()
            || self.trajectory_length <= 0.0
            || self.trajectory_length > 2.0
        {
            return Err(bad(
                "trajectory_length",
                format!(
                    "must be in (0, 2] scene units (the room is 6 wide), got {}",
                    self.trajectory_length
                ),
            ));
        }
        if !self.forward_motion.is_finite() || !(0.0..=1.5).contains(&self.forward_motion) {
            return Err(bad(
                "forward_motion",
                format!(
                    "must be in [0, 1.5] scene units (the wall behind the cameras is 1 \
                     behind the reference), got {}",
                    self.forward_motion
                ),
            ));
        }
        let [a0, a1] = self.airlight_range;
        if !(a0 > 0.0 && a0 <= a1 && a1 <= 1.0) {
            return Err(bad(
                "airlight_range",
                format!("need 0 < lo <= hi <= 1, got [{a0}, {a1}]"),
            ));
        }
        let [t0, t1] = self.median_transmission_range;
        if !(t0 > 0.0 && t0 <= t1 && t1 <= 1.0) {
            return Err(bad(
                "median_transmission_range",
                format!("need 0 < lo <= hi <= 1, got [{t0}, {t1}]"),
            ));
        }
        if let Some([b0, b1]) = self.beta_range {
            if !(b0.is_finite() && b1.is_finite() && b0 > 0.0 && b0 <= b1 && b1 <= 100.0) {
                return Err(bad(
                    "beta_range",
                    format!("need 0 < lo <= hi <= 100 per scene unit, got [{b0}, {b1}]"),
                ));
            }
        }
        if !self.albedo_scale.is_finite() || !(0.05..=10.0).contains(&self.albedo_scale) {
            return Err(bad(
                "albedo_scale",
                format!("must be in [0.05, 10], got {}", self.albedo_scale),
            ));
        }
        if !self.noise_sigma.is_finite() || !(0.0..=0.5).contains(&self.noise_sigma) {
            return Err(bad(
                "noise_sigma",
                format!("must be in [0, 0.5], got {}", self.noise_sigma),
            ));
        }
        if !(1..=8).contains(&self.supersample) {
            return Err(bad(
                "supersample",
                format!("must be in 1..=8, got {}", self.supersample),
            ));
        }
        if self.num_boxes > 32 || self.num_spheres > 32 {
            return Err(bad(
                if self.num_boxes > 32 {
                    "num_boxes"
                } else {
                    "num_spheres"
                },
                "at most 32 objects of each kind".into(),
            ));
        }
        if self.point_stride_px == 0 {
            return Err(bad("point_stride_px", "must be >= 1".into()));
        }
        if !self.point_noise.is_finite() || self.point_noise < 0.0 {
            return Err(bad(
                "point_noise",
                format!("must be finite and >= 0, got {}", self.point_noise),
            ));
        }
        Ok(())
    }

    /// Pinhole intrinsics (principal point at the image centre, murk convention).
    pub fn intrinsics(&self) -> Intrinsics {
        Intrinsics::new(
            self.focal_px,
            self.focal_px,
            (self.width as f64 - 1.0) / 2.0,
            (self.height as f64 - 1.0) / 2.0,
        )
    }
}

/// One simulated view.
#[derive(Clone, Debug, PartialEq)]
pub struct MvsView {
    /// Image name (file stem plus `.png`), as in the COLMAP model.
    pub name: String,
    /// Clear RGB image in `[0, 1]` (noise included).
    pub clear: ImageF32,
    /// Hazy RGB image in `[0, 1]`.
    pub hazy: ImageF32,
    /// GT z-depth, scene units, one channel.
    pub depth: ImageF32,
    /// Intrinsics, pixels (murk convention).
    pub intrinsics: Intrinsics,
    /// World-to-camera pose.
    pub pose: Pose,
}

/// A simulated multi-view capture.
#[derive(Clone, Debug, PartialEq)]
pub struct MvsScene {
    /// The config it was made with.
    pub config: MvsSimConfig,
    /// All views.
    pub views: Vec<MvsView>,
    /// Index of the reference view.
    pub reference: usize,
    /// Airlight `A`.
    pub airlight: f32,
    /// Scattering coefficient `β`, per scene unit.
    pub beta: f32,
    /// Median transmission over the reference view, `median(e^{−β z_ref})`.
    pub median_transmission: f64,
    /// Sparse SfM-like model: cameras, images (poses + observations), points with tracks.
    pub sparse: ColmapModel,
}

impl MvsScene {
    /// The reference's hazy view and every other hazy view as a source, nearest along the
    /// trajectory first.
    pub fn reference_and_sources(&self) -> (View<'_>, Vec<View<'_>>) {
        let views = self.hazy_views();
        let sources = self
            .source_indices()
            .into_iter()
            .map(|i| views[i])
            .collect();
        (views[self.reference], sources)
    }

    /// The indices of the views [`Self::reference_and_sources`] returns as sources, in its
    /// order: every view but the reference, nearest along the trajectory first.
    pub fn source_indices(&self) -> Vec<usize> {
        let r = self.reference;
        let mut others: Vec<usize> = (0..self.views.len()).filter(|&i| i != r).collect();
        others.sort_by_key(|&i| i.abs_diff(r));
        others
    }

    /// The sparse depth of Eq. 3.8 in the reference view: the SfM points whose track includes
    /// it.
    pub fn sparse_depth(&self) -> Result<SparseDepth> {
        SparseDepth::from_colmap(
            &self.sparse,
            &self.views[self.reference].name,
            self.config.width,
            self.config.height,
            PointSelection::ObservedInReference,
        )
    }

    /// The points of [`Self::sparse_depth`] with their observations in the reference and the
    /// first `sources` views of [`Self::source_indices`] (the search's tracks, for the poses'
    /// share of the errors). `sources` beyond the scene's count take them all.
    pub fn sfm_tracks(&self, sources: usize) -> Result<SfmTracks> {
        let indices = self.source_indices();
        let names: Vec<&str> = indices
            .iter()
            .take(sources)
            .map(|&i| self.views[i].name.as_str())
            .collect();
        SfmTracks::from_colmap(
            &self.sparse,
            &self.views[self.reference].name,
            PointSelection::ObservedInReference,
            &names,
        )
    }

    /// Every view as the library's [`View`] of its *hazy* image, in order.
    pub fn hazy_views(&self) -> Vec<View<'_>> {
        self.views
            .iter()
            .map(|v| View {
                image: &v.hazy,
                intrinsics: v.intrinsics,
                pose: v.pose,
            })
            .collect()
    }
}

// ---------------------------------------------------------------------------------------------
// Procedural textures

fn hash3(i: i64, j: i64, k: i64, seed: u64) -> f64 {
    // SplitMix64 finaliser over the lattice coordinates: a cheap, well-mixed hash.
    let mut z = seed
        ^ (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (j as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
        ^ (k as u64).wrapping_mul(0x1656_67B1_9E37_79F9);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    (z >> 11) as f64 / (1u64 << 53) as f64
}

/// Trilinear value noise with smoothstep weights, in `[0, 1]`.
fn value_noise(p: V3, seed: u64) -> f64 {
    let f = p.map(f64::floor);
    let i = f.map(|v| v as i64);
    let w = [p[0] - f[0], p[1] - f[1], p[2] - f[2]].map(|t| t * t * (3.0 - 2.0 * t));
    let mut acc = 0.0;
    for c in 0..8 {
        let (a, b, d) = (c & 1, (c >> 1) & 1, (c >> 2) & 1);
        let wt = (if a == 1 { w[0] } else { 1.0 - w[0] })
            * (if b == 1 { w[1] } else { 1.0 - w[1] })
            * (if d == 1 { w[2] } else { 1.0 - w[2] });
        acc += wt * hash3(i[0] + a, i[1] + b, i[2] + d, seed);
    }
    acc
}

/// Four-octave fractal value noise, in `[0, 1]`; `scale` is the coarsest feature size.
fn fbm(p: V3, scale: f64, seed: u64) -> f64 {
    let (mut sum, mut amp, mut norm, mut freq) = (0.0, 1.0, 0.0, 1.0 / scale);
    for o in 0..4 {
        sum += amp * value_noise(p.map(|v| v * freq), seed.wrapping_add(o));
        norm += amp;
        amp *= 0.6;
        freq *= 2.1;
    }
    sum / norm
}

/// Texture of a surface.
#[derive(Clone, Copy, Debug)]
enum Pattern {
    Noise { scale: f64 },
    Checker { size: f64 },
    Mix { scale: f64, size: f64 },
}

#[derive(Clone, Copy, Debug)]
struct Material {
    base: [f64; 3],
    /// Relative amplitude of the pattern; below [`TEXTURED_CONTRAST`] the surface counts as
    /// weakly textured (no sparse points).
    contrast: f64,
    pattern: Pattern,
    seed: u64,
}

const TEXTURED_CONTRAST: f64 = 0.1;

impl Material {
    fn random(rng: &mut ChaCha8Rng, weak: bool) -> Self {
        let base = [0; 3].map(|_| rng.random_range(0.35..0.9));
        let pattern = match rng.random_range(0..3) {
            0 => Pattern::Noise {
                scale: rng.random_range(0.25..0.8),
            },
            1 => Pattern::Checker {
                size: rng.random_range(0.15..0.5),
            },
            _ => Pattern::Mix {
                scale: rng.random_range(0.25..0.8),
                size: rng.random_range(0.2..0.6),
            },
        };
        Self {
            base,
            contrast: if weak {
                rng.random_range(0.02..0.05)
            } else {
                rng.random_range(0.35..0.6)
            },
            pattern,
            seed: rng.random(),
        }
    }

    fn albedo(&self, p: V3) -> [f64; 3] {
        let checker = |size: f64| {
            let s: i64 = p.iter().map(|v| (v / size).floor() as i64).sum();
            if s.rem_euclid(2) == 0 {
                0.0
            } else {
                1.0
            }
        };
        let v = match self.pattern {
            Pattern::Noise { scale } => fbm(p, scale, self.seed),
            Pattern::Checker { size } => 0.3 * checker(size) + 0.7 * fbm(p, size, self.seed),
            Pattern::Mix { scale, size } => 0.5 * checker(size) + 0.5 * fbm(p, scale, self.seed),
        };
        // Per-channel noise phases so colour, not only brightness, varies.
        let tint = fbm(p, 1.5, self.seed ^ 0xABCD);
        let k = 1.0 + self.contrast * (2.0 * v - 1.0);
        [
            self.base[0] * k * (0.85 + 0.3 * tint),
            self.base[1] * k,
            self.base[2] * k * (1.15 - 0.3 * tint),
        ]
    }
}

// ---------------------------------------------------------------------------------------------
// Scene geometry

pub(super) struct World {
    back_z: f64,
    /// Materials of the six room faces: −x, +x, −y (ceiling), +y (floor), −z (behind), +z (back).
    room: [Material; 6],
    objects: Vec<(Shape, Material)>,
}

struct SurfaceHit {
    t: f64,
    normal: V3,
    material: Material,
}

const LIGHT: [f64; 3] = [-0.27, -0.87, -0.41];

impl World {
    pub(super) fn random(cfg: &MvsSimConfig, rng: &mut ChaCha8Rng) -> Self {
        let back_z = rng.random_range(10.0..12.0);
        let mut room = [0; 6].map(|_| Material::random(rng, false));
        room[2] = Material::random(rng, true);
        let mut objects = Vec::new();
        for b in 0..cfg.num_boxes {
            let sx = rng.random_range(0.4..1.2);
            let sy = rng.random_range(0.4..1.4);
            let sz = rng.random_range(0.4..1.2);
            let x = rng.random_range(-2.2..2.2);
            let z = rng.random_range(3.5..9.0);
            let shape = Shape::Box {
                min: V3::new(x - sx / 2.0, FLOOR_Y - sy, z - sz / 2.0),
                max: V3::new(x + sx / 2.0, FLOOR_Y, z + sz / 2.0),
            };
            objects.push((shape, Material::random(rng, b == 0)));
        }
        for _ in 0..cfg.num_spheres {
            let r = rng.random_range(0.3..0.7);
            let x = rng.random_range(-2.0..2.0);
            let z = rng.random_range(3.0..8.0);
            let y = if rng.random_bool(0.5) {
                FLOOR_Y - r
            } else {
                rng.random_range(-1.0..0.5)
            };
            objects.push((
                Shape::Sphere {
                    centre: V3::new(x, y, z),
                    radius: r,
                },
                Material::random(rng, false),
            ));
        }
        Self {
            back_z,
            room,
            objects,
        }
    }

    /// First surface along `o + t·d` (`|d| = 1`, `o` inside the room): the room is closed, so
    /// there is always a hit.
    fn cast(&self, o: V3, d: V3) -> SurfaceHit {
        let lo = [-ROOM_X, CEILING_Y, BEHIND_Z];
        let hi = [ROOM_X, FLOOR_Y, self.back_z];
        let mut best = SurfaceHit {
            t: f64::INFINITY,
            normal: V3::new(0.0, 0.0, -1.0),
            material: self.room[5],
        };
        for a in 0..3 {
            if d[a].abs() < 1e-12 {
                continue;
            }
            let (bound, face) = if d[a] > 0.0 {
                (hi[a], 2 * a + 1)
            } else {
                (lo[a], 2 * a)
            };
            let t = (bound - o[a]) / d[a];
            if t > 0.0 && t < best.t {
                let mut n = V3::zeros();
                n[a] = -d[a].signum();
                best = SurfaceHit {
                    t,
                    normal: n,
                    material: self.room[face],
                };
            }
        }
        for (shape, m) in &self.objects {
            if let Some((t, n)) = shape.intersect(o, d, 1e-9, best.t) {
                best = SurfaceHit {
                    t,
                    normal: n,
                    material: *m,
                };
            }
        }
        best
    }

    /// Lambertian radiance at the hit of a ray, RGB, clamped to `[0.02, 0.98]`; the albedo is
    /// scaled by `albedo_scale` ([`MvsSimConfig::albedo_scale`]).
    fn radiance(&self, o: V3, d: V3, hit: &SurfaceHit, albedo_scale: f64) -> [f64; 3] {
        let p = o + d * hit.t;
        let n = V3::from(LIGHT).normalize();
        let shade = 0.3 + 0.7 * hit.normal.dot(&n).max(0.0);
        hit.material
            .albedo(p)
            .map(|a| (a * albedo_scale * shade).clamp(0.02, 0.98))
    }
}

/// Camera-frame unit ray through pixel `(u, v)` and world-frame origin/direction.
fn world_ray(k: &Intrinsics, cam_to_world: &Pose, u: f64, v: f64) -> (V3, V3, f64) {
    let d_cam = k.ray(u, v);
    (
        *cam_to_world.translation(),
        cam_to_world.rotate(d_cam),
        d_cam[2],
    )
}

fn yaw_pose(centre: V3, yaw: f64, pitch: f64) -> Result<Pose> {
    // Camera-to-world rotation: yaw about +y, then pitch about +x.
    let (cy, sy) = (yaw.cos(), yaw.sin());
    let (cp, sp) = (pitch.cos(), pitch.sin());
    let ry = Matrix3::new(cy, 0.0, sy, 0.0, 1.0, 0.0, -sy, 0.0, cy);
    let rx = Matrix3::new(1.0, 0.0, 0.0, 0.0, cp, -sp, 0.0, sp, cp);
    let r = (ry * rx).transpose();
    Pose::new(r, -(r * centre))
}

fn poses(cfg: &MvsSimConfig, rng: &mut ChaCha8Rng) -> Result<(Vec<Pose>, usize)> {
    let b = cfg.trajectory_length;
    if cfg.rectified_pair {
        return Ok((
            vec![Pose::identity(), Pose::translation_only([-b, 0.0, 0.0])?],
            0,
        ));
    }
    let k = cfg.num_views;
    let reference = k / 2;
    let mut out = Vec::with_capacity(k);
    for i in 0..k {
        if i == reference {
            out.push(Pose::identity());
            continue;
        }
        let along = i as f64 / (k - 1) as f64 - reference as f64 / (k - 1) as f64;
        let x = b * along;
        let jitter = 0.05 * b;
        let c = [
            x,
            rng.random_range(-jitter..=jitter),
            cfg.forward_motion * along + rng.random_range(-jitter..=jitter),
        ];
        // Look roughly at the room centre (z ≈ 7) with ±0.3° of random wobble.
        let wobble = 0.3f64.to_radians();
        let yaw = (-x / 7.0).atan() + rng.random_range(-wobble..=wobble);
        let pitch = rng.random_range(-wobble..=wobble);
        out.push(yaw_pose(c.into(), yaw, pitch)?);
    }
    Ok((out, reference))
}

pub(crate) fn gaussian(rng: &mut ChaCha8Rng) -> f64 {
    // Box–Muller; `1 − u` keeps the logarithm finite.
    let u1: f64 = 1.0 - rng.random::<f64>();
    let u2: f64 = rng.random();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// Renders clear RGB and z-depth of one view.
pub(super) fn render_view(
    world: &World,
    cfg: &MvsSimConfig,
    pose: &Pose,
) -> Result<(ImageF32, ImageF32)> {
    let (w, h, s) = (cfg.width, cfg.height, cfg.supersample);
    let k = cfg.intrinsics();
    let c2w = pose.inverse();
    let mut rgb = vec![0.0f32; w * h * 3];
    let mut depth = vec![0.0f32; w * h];
    rgb.par_chunks_mut(w * 3)
        .zip(depth.par_chunks_mut(w))
        .enumerate()
        .for_each(|(y, (row, drow))| {
            for x in 0..w {
                let (o, d, dz) = world_ray(&k, &c2w, x as f64, y as f64);
                drow[x] = (world.cast(o, d).t * dz) as f32;
                let mut acc = [0.0; 3];
                for sy in 0..s {
                    for sx in 0..s {
                        let u = x as f64 + (sx as f64 + 0.5) / s as f64 - 0.5;
                        let v = y as f64 + (sy as f64 + 0.5) / s as f64 - 0.5;
                        let (o, d, _) = world_ray(&k, &c2w, u, v);
                        let hit = world.cast(o, d);
                        let r = world.radiance(o, d, &hit, cfg.albedo_scale);
                        for c in 0..3 {
                            acc[c] += r[c];
                        }
                    }
                }
                let n = (s * s) as f64;
                for c in 0..3 {
                    row[x * 3 + c] = (acc[c] / n) as f32;
                }
            }
        });
    Ok((
        ImageF32::from_vec(w, h, 3, rgb)?,
        ImageF32::from_vec(w, h, 1, depth)?,
    ))
}

/// Adds Gaussian noise of `sigma` and clips to `[0, 1]`; one ChaCha8 stream per row.
pub(super) fn add_noise(img: &mut ImageF32, sigma: f32, seed: u64) {
    let row_len = img.width() * img.channels();
    img.data_mut()
        .par_chunks_mut(row_len)
        .enumerate()
        .for_each(|(y, row)| {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            rng.set_stream(y as u64);
            for v in row {
                let n = if sigma > 0.0 {
                    sigma * gaussian(&mut rng) as f32
                } else {
                    0.0
                };
                *v = (*v + n).clamp(0.0, 1.0);
            }
        });
}

pub(super) fn median(v: &[f32]) -> f64 {
    let mut s: Vec<f32> = v.to_vec();
    let mid = s.len() / 2;
    let (_, m, _) = s.select_nth_unstable_by(mid, f32::total_cmp);
    f64::from(*m)
}

/// A hazy room at 128×96 with a walking trajectory (forward motion 0.5) and β ∈ [0.4, 0.8]:
/// enough depth differences between views for the points' ratio fit at reduced size
/// ([`crate::params::point_ratio`]).
#[cfg(test)]
pub(crate) fn walking_test_scene(seed: u64) -> MvsScene {
    let cfg = MvsSimConfig {
        seed,
        beta_range: Some([0.4, 0.8]),
        forward_motion: 0.5,
        ..MvsSimConfig::with_size(128, 96)
    };
    simulate_mvs(&cfg, &Monitor::noop()).expect("simulate")
}

/// Simulates a hazy multi-view capture (see the module docs). Errors name config fields;
/// cancellation through `monitor` returns `Cancelled`.
pub fn simulate_mvs(cfg: &MvsSimConfig, monitor: &Monitor) -> Result<MvsScene> {
    cfg.validate()?;
    let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
    let world = World::random(cfg, &mut rng);
    let (poses, reference) = poses(cfg, &mut rng)?;
    let airlight = rng.random_range(cfg.airlight_range[0]..=cfg.airlight_range[1]);
    let t_target =
        rng.random_range(cfg.median_transmission_range[0]..=cfg.median_transmission_range[1]);
    let k = cfg.intrinsics();
    let mut rendered = Vec::with_capacity(poses.len());
    for (i, p) in poses.iter().enumerate() {
        monitor.checkpoint()?;
        rendered.push(render_view(&world, cfg, p)?);
        monitor.progress("simulate.mvs", 0.8 * (i + 1) as f32 / poses.len() as f32);
    }
    let z_med = median(rendered[reference].1.data());
    let beta = (-t_target.ln() / z_med) as f32;
    let median_transmission = median(
        &rendered[reference]
            .1
            .data()
            .iter()
            .map(|&z| (-beta * z).exp())
            .collect::<Vec<f32>>(),
    );
    let mut views = Vec::with_capacity(poses.len());
    for (i, ((clear, depth), pose)) in rendered.into_iter().zip(&poses).enumerate() {
        let mut hazy = haze(&clear, &depth, airlight, beta)?;
        let mut clear = clear;
        let base = cfg.seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ (i as u64) << 32;
        add_noise(&mut clear, cfg.noise_sigma, base ^ 1);
        add_noise(&mut hazy, cfg.noise_sigma, base ^ 2);
        views.push(MvsView {
            name: format!("view_{i:02}.png"),
            clear,
            hazy,
            depth,
            intrinsics: k,
            pose: *pose,
        });
    }
    monitor.checkpoint()?;
    let sparse = sparse_model(&world, cfg, &views, &mut rng)?;
    monitor.progress("simulate.mvs", 1.0);
    let mut scene = MvsScene {
        config: cfg.clone(),
        views,
        reference,
        airlight,
        beta,
        median_transmission,
        sparse,
    };
    // Drawn last so that scenes without `beta_range` keep their seeds' content.
    if let Some([b0, b1]) = cfg.beta_range {
        let target = rng.random_range(b0..=b1);
        scale_scene(&mut scene, f64::from(beta / target))?;
        scene.beta = target;
    }
    Ok(scene)
}

/// Scales every length of `scene` by `s` (> 0) about the world origin: depth maps, camera
/// translations (world-to-camera `t` scales with the world), sparse points. Images, rotations,
/// intrinsics and 2D observations are unchanged; `β` must be divided by `s` by the caller so
/// that `β·z` (the haze) is unchanged.
fn scale_scene(scene: &mut MvsScene, s: f64) -> Result<()> {
    for v in &mut scene.views {
        for z in v.depth.data_mut() {
            *z = (f64::from(*z) * s) as f32;
        }
        v.pose = v.pose.scaled(s);
    }
    for img in scene.sparse.images.values_mut() {
        let pose = img.pose.scaled(s);
        *img = ColmapImage::new(
            img.id,
            img.camera_id,
            img.name.clone(),
            &pose,
            std::mem::take(&mut img.points2d),
        )?;
    }
    for p in scene.sparse.points.values_mut() {
        p.xyz = p.xyz.map(|c| c * s);
    }
    Ok(())
}

/// The sparse cloud and COLMAP model (see the module docs).
fn sparse_model(
    world: &World,
    cfg: &MvsSimConfig,
    views: &[MvsView],
    rng: &mut ChaCha8Rng,
) -> Result<ColmapModel> {
    let (w, h) = (cfg.width, cfg.height);
    let k = cfg.intrinsics();
    let stride = cfg.point_stride_px;
    let mut points2d: Vec<Vec<Point2D>> = vec![Vec::new(); views.len()];
    let mut points = BTreeMap::new();
    let mut next_id = 1u64;
    for (vi, view) in views.iter().enumerate() {
        let c2w = view.pose.inverse();
        let (ox, oy) = (rng.random_range(0..stride), rng.random_range(0..stride));
        for y in (oy..h).step_by(stride) {
            for x in (ox..w).step_by(stride) {
                let (o, d, dz) = world_ray(&k, &c2w, x as f64, y as f64);
                let hit = world.cast(o, d);
                if hit.material.contrast < TEXTURED_CONTRAST {
                    continue;
                }
                let z = view.depth.get(x, y, 0) as f64;
                let t = z / dz;
                let p = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
                // Visibility in every view: in the image and passing the depth test.
                let mut obs: Vec<(usize, [f64; 2])> = Vec::new();
                for (vj, other) in views.iter().enumerate() {
                    let q = other.pose.transform(p);
                    let Some((u, v)) = k.project(q) else { continue };
                    if !(0.0..=(w - 1) as f64).contains(&u) || !(0.0..=(h - 1) as f64).contains(&v)
                    {
                        continue;
                    }
                    let zg = other.depth.get(u.round() as usize, v.round() as usize, 0) as f64;
                    if (zg - q[2]).abs() <= 0.02 * q[2] {
                        obs.push((vj, [u, v]));
                    }
                }
                if obs.len() < 2 || !obs.iter().any(|(vj, _)| *vj == vi) {
                    continue;
                }
                let noisy = p.map(|c| c + cfg.point_noise * gaussian(rng));
                let mut err = 0.0;
                let mut track = Vec::with_capacity(obs.len());
                for &(vj, [u, v]) in &obs {
                    if let Some((un, vn)) = k.project(views[vj].pose.transform(noisy)) {
                        err += ((un - u).powi(2) + (vn - v).powi(2)).sqrt();
                    }
                    track.push(TrackElement {
                        image_id: vj as u32 + 1,
                        point2d_idx: points2d[vj].len() as u32,
                    });
                    // COLMAP's pixel convention puts the top-left pixel centre at (0.5, 0.5).
                    points2d[vj].push(Point2D {
                        xy: [u + 0.5, v + 0.5],
                        point3d_id: Some(next_id),
                    });
                }
                let c = &view.clear;
                let rgb =
                    [0, 1, 2].map(|ch| (c.get(x, y, ch) * 255.0).round().clamp(0.0, 255.0) as u8);
                points.insert(
                    next_id,
                    Point3D {
                        id: next_id,
                        xyz: noisy,
                        rgb,
                        error: err / obs.len() as f64,
                        track,
                    },
                );
                next_id += 1;
            }
        }
    }
    let camera = ColmapCamera::from_intrinsics(1, &k, w as u64, h as u64)?;
    let mut images = BTreeMap::new();
    for (i, (view, p2d)) in views.iter().zip(points2d).enumerate() {
        let id = i as u32 + 1;
        images.insert(
            id,
            ColmapImage::new(id, 1, view.name.clone(), &view.pose, p2d)?,
        );
    }
    Ok(ColmapModel {
        cameras: BTreeMap::from([(1, camera)]),
        images,
        points,
    })
}

// ---------------------------------------------------------------------------------------------
// Folder I/O

#[derive(Serialize, Deserialize)]
struct MvsMeta {
    format: String,
    version: u32,
    config: MvsSimConfig,
    reference: String,
    views: Vec<String>,
    airlight: f32,
    beta: f32,
    median_transmission: f64,
    #[serde(default)]
    units: Option<serde_json::Value>,
}

pub(super) fn encode_rgb16(img: &ImageF32) -> Result<Vec<u8>> {
    use image::{ExtendedColorType, ImageEncoder};
    let mut buf = Vec::with_capacity(img.data().len() * 2);
    for &v in img.data() {
        let q = (f64::from(v).clamp(0.0, 1.0) * 65535.0).round() as u16;
        // The encoder takes native-endian samples.
        buf.extend_from_slice(&q.to_ne_bytes());
    }
    let mut out = Vec::new();
    image::codecs::png::PngEncoder::new(&mut out)
        .write_image(
            &buf,
            img.width() as u32,
            img.height() as u32,
            ExtendedColorType::Rgb16,
        )
        .map_err(|e| MurkError::Numerical(format!("PNG encoding failed: {e}")))?;
    Ok(out)
}

fn stem(name: &str) -> &str {
    name.strip_suffix(".png").unwrap_or(name)
}

/// Writes `scene` into `dir` (created if missing) in the layout of the module docs.
pub fn write_mvs_scene(dir: &Path, scene: &MvsScene) -> Result<()> {
    for sub in ["images", "clear", "depth", "sparse"] {
        let d = dir.join(sub);
        std::fs::create_dir_all(&d).map_err(|e| io::io_error(&d, e))?;
    }
    for v in &scene.views {
        io::write_file(&dir.join("images").join(&v.name), &encode_rgb16(&v.hazy)?)?;
        io::write_file(&dir.join("clear").join(&v.name), &encode_rgb16(&v.clear)?)?;
        io::write_exr(
            &dir.join("depth").join(format!("{}.exr", stem(&v.name))),
            &v.depth,
        )?;
    }
    write_colmap_text(dir.join("sparse"), &scene.sparse)?;
    let reference = scene
        .views
        .get(scene.reference)
        .ok_or_else(|| MurkError::invalid("reference", "index out of range"))?;
    let meta = MvsMeta {
        format: MVS_SCENE_FORMAT.into(),
        version: 1,
        config: scene.config.clone(),
        reference: reference.name.clone(),
        views: scene.views.iter().map(|v| v.name.clone()).collect(),
        airlight: scene.airlight,
        beta: scene.beta,
        median_transmission: scene.median_transmission,
        units: Some(serde_json::json!({
            "depth": "z-depth along the optical axis, scene units",
            "beta": "per scene unit",
            "images": "16-bit PNG, [0, 1] -> [0, 65535]",
            "poses": "COLMAP world-to-camera; world = reference camera frame",
        })),
    };
    let json = serde_json::to_vec_pretty(&meta)
        .map_err(|e| MurkError::Numerical(format!("serialising meta.json: {e}")))?;
    io::write_file(&dir.join("meta.json"), &json)
}

/// Reads a scene written by [`write_mvs_scene`]. Images come back quantised to 16 bits
/// (within `0.5/65535`); poses and intrinsics come from the COLMAP model.
pub fn read_mvs_scene(dir: &Path) -> Result<MvsScene> {
    let path = dir.join("meta.json");
    let text = std::fs::read(&path).map_err(|e| io::io_error(&path, e))?;
    let meta: MvsMeta = serde_json::from_slice(&text)
        .map_err(|e| MurkError::invalid("meta.json", format!("not valid scene metadata: {e}")))?;
    if meta.format != MVS_SCENE_FORMAT {
        return Err(MurkError::invalid(
            "meta.json.format",
            format!("expected {MVS_SCENE_FORMAT:?}, got {:?}", meta.format),
        ));
    }
    meta.config
        .validate()
        .map_err(|e| e.within("meta.json.config"))?;
    let sparse = read_colmap_dir(dir.join("sparse")).map_err(|e| e.within("sparse"))?;
    let limits = DecodeLimits {
        max_pixels: (MAX_MVS_SIDE * MAX_MVS_SIDE) as u64,
        max_channels: 3,
    };
    let dims = (meta.config.width, meta.config.height);
    let load = |sub: &str, name: &str, channels: usize| -> Result<ImageF32> {
        let field = format!("{sub}/{name}");
        let img =
            io::read_image(&dir.join(sub).join(name), &limits).map_err(|e| e.within(&field))?;
        if img.dims() != dims || img.channels() != channels {
            return Err(MurkError::invalid(
                field,
                format!(
                    "expected {}x{}x{channels}, got {}x{}x{}",
                    dims.0,
                    dims.1,
                    img.width(),
                    img.height(),
                    img.channels()
                ),
            ));
        }
        Ok(img)
    };
    let mut views = Vec::with_capacity(meta.views.len());
    for name in &meta.views {
        let image = sparse.image_by_name(name).ok_or_else(|| {
            MurkError::invalid("sparse.images", format!("no image named {name:?}"))
        })?;
        views.push(MvsView {
            name: name.clone(),
            hazy: load("images", name, 3)?,
            clear: load("clear", name, 3)?,
            depth: load("depth", &format!("{}.exr", stem(name)), 1)?,
            intrinsics: sparse.intrinsics_of(image)?,
            pose: image.pose,
        });
    }
    let reference = meta
        .views
        .iter()
        .position(|n| *n == meta.reference)
        .ok_or_else(|| {
            MurkError::invalid(
                "meta.json.reference",
                format!("{:?} is not one of the views", meta.reference),
            )
        })?;
    Ok(MvsScene {
        config: meta.config,
        views,
        reference,
        airlight: meta.airlight,
        beta: meta.beta,
        median_transmission: meta.median_transmission,
        sparse,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small(seed: u64) -> MvsSimConfig {
        MvsSimConfig {
            seed,
            ..MvsSimConfig::with_size(64, 48)
        }
    }

    #[test]
    fn deterministic_and_seed_dependent() {
        let a = simulate_mvs(&small(3), &Monitor::noop()).unwrap();
        let b = simulate_mvs(&small(3), &Monitor::noop()).unwrap();
        assert_eq!(a, b);
        let c = simulate_mvs(&small(4), &Monitor::noop()).unwrap();
        assert_ne!(a.views[0].hazy, c.views[0].hazy);
    }

    #[test]
    fn haze_and_depth_in_range() {
        for seed in 0..4 {
            let s = simulate_mvs(&small(seed), &Monitor::noop()).unwrap();
            assert!((0.2..=0.4).contains(&s.median_transmission), "{s:?}");
            assert!((0.7..=1.0).contains(&s.airlight));
            assert_eq!(s.views.len(), 5);
            assert_eq!(s.views[s.reference].pose, Pose::identity());
            for v in &s.views {
                assert!(v
                    .depth
                    .data()
                    .iter()
                    .all(|z| z.is_finite() && *z > 0.5 && *z < 13.0));
                assert!(v.hazy.data().iter().all(|x| (0.0..=1.0).contains(x)));
            }
        }
    }

    #[test]
    fn beta_range_scales_the_scene_not_the_images() {
        let plain = simulate_mvs(&small(5), &Monitor::noop()).unwrap();
        let cfg = MvsSimConfig {
            beta_range: Some([0.4, 0.8]),
            ..small(5)
        };
        let scaled = simulate_mvs(&cfg, &Monitor::noop()).unwrap();
        assert!((0.4..=0.8).contains(&scaled.beta), "{}", scaled.beta);
        assert_eq!(scaled.median_transmission, plain.median_transmission);
        let s = f64::from(plain.beta / scaled.beta);
        for (a, b) in plain.views.iter().zip(&scaled.views) {
            assert_eq!(a.hazy, b.hazy);
            assert_eq!(a.pose.rotation(), b.pose.rotation());
            for (za, zb) in a.depth.data().iter().zip(b.depth.data()) {
                assert!((f64::from(*za) * s - f64::from(*zb)).abs() < 1e-4 * f64::from(*zb));
            }
        }
        // The scaled sparse model still projects onto its observations.
        let k = scaled.views[0].intrinsics;
        for p in scaled.sparse.points.values().take(50) {
            for t in &p.track {
                let img = &scaled.sparse.images[&t.image_id];
                let (u, v) = k.project(img.pose.transform(p.xyz)).unwrap();
                let obs = img.points2d[t.point2d_idx as usize].xy;
                assert!((u + 0.5 - obs[0]).abs() < 1.0 && (v + 0.5 - obs[1]).abs() < 1.0);
            }
        }
        let bad = MvsSimConfig {
            beta_range: Some([0.8, 0.4]),
            ..small(5)
        };
        assert_eq!(
            simulate_mvs(&bad, &Monitor::noop()).unwrap_err().field(),
            Some("beta_range")
        );
    }

    #[test]
    fn points_project_onto_observations() {
        let s = simulate_mvs(&small(5), &Monitor::noop()).unwrap();
        s.sparse.validate_references().unwrap();
        assert!(s.sparse.points.len() > 20, "{}", s.sparse.points.len());
        for p in s.sparse.points.values() {
            assert!(p.track.len() >= 2);
            for t in &p.track {
                let img = &s.sparse.images[&t.image_id];
                let k = s.sparse.intrinsics_of(img).unwrap();
                let (u, v) = k.project(img.pose.transform(p.xyz)).unwrap();
                let obs = img.points2d[t.point2d_idx as usize];
                assert_eq!(obs.point3d_id, Some(p.id));
                // COLMAP convention on the observation, murk's on `k`: the +0.5 cancels.
                let e = ((u + 0.5 - obs.xy[0]).powi(2) + (v + 0.5 - obs.xy[1]).powi(2)).sqrt();
                assert!(e < 1.0, "reprojection error {e} px");
            }
        }
    }

    #[test]
    fn rectified_pair_is_pure_x_translation() {
        let cfg = MvsSimConfig {
            rectified_pair: true,
            num_views: 2,
            ..small(1)
        };
        let s = simulate_mvs(&cfg, &Monitor::noop()).unwrap();
        let rel = Pose::relative(&s.views[0].pose, &s.views[1].pose);
        assert_eq!(rel.rotation(), Pose::identity().rotation());
        assert_eq!(
            rel.translation().as_slice(),
            [-cfg.trajectory_length, 0.0, 0.0]
        );
        let bad = MvsSimConfig {
            rectified_pair: true,
            ..small(1)
        };
        match bad.validate() {
            Err(MurkError::InvalidArgument { field, .. }) => assert_eq!(field, "num_views"),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn albedo_scale_brightens_the_scene_and_leaves_the_rest() {
        let plain = simulate_mvs(&small(4), &Monitor::noop()).unwrap();
        let bright = MvsSimConfig {
            albedo_scale: 1.5,
            ..small(4)
        };
        let bright = simulate_mvs(&bright, &Monitor::noop()).unwrap();
        let mean = |s: &MvsScene| {
            let d = s.views[s.reference].clear.data();
            d.iter().map(|&v| f64::from(v)).sum::<f64>() / d.len() as f64
        };
        assert!(mean(&bright) > 1.2 * mean(&plain));
        assert_eq!(bright.airlight, plain.airlight);
        assert_eq!(bright.beta, plain.beta);
        assert_eq!(bright.views[0].depth, plain.views[0].depth);
    }

    #[test]
    fn validation_names_fields() {
        let field = |c: MvsSimConfig| match c.validate() {
            Err(MurkError::InvalidArgument { field, .. }) => field,
            other => panic!("{other:?}"),
        };
        assert_eq!(
            field(MvsSimConfig {
                width: 2,
                ..small(0)
            }),
            "width"
        );
        assert_eq!(
            field(MvsSimConfig {
                num_views: 1,
                ..small(0)
            }),
            "num_views"
        );
        for albedo_scale in [0.0, 11.0, f64::NAN] {
            assert_eq!(
                field(MvsSimConfig {
                    albedo_scale,
                    ..small(0)
                }),
                "albedo_scale"
            );
        }
        for forward_motion in [-0.1, 1.6, f64::NAN] {
            assert_eq!(
                field(MvsSimConfig {
                    forward_motion,
                    ..small(0)
                }),
                "forward_motion"
            );
        }
        assert_eq!(
            field(MvsSimConfig {
                airlight_range: [0.0, 1.0],
                ..small(0)
            }),
            "airlight_range"
        );
        assert_eq!(
            field(MvsSimConfig {
                median_transmission_range: [0.5, 0.4],
                ..small(0)
            }),
            "median_transmission_range"
        );
        assert_eq!(
            field(MvsSimConfig {
                focal_px: f64::NAN,
                ..small(0)
            }),
            "focal_px"
        );
    }

    #[test]
    fn write_read_round_trip_and_colmap_loads() {
        let s = simulate_mvs(&small(7), &Monitor::noop()).unwrap();
        let dir = tempfile::tempdir().unwrap();
        write_mvs_scene(dir.path(), &s).unwrap();
        let model = read_colmap_dir(dir.path().join("sparse")).unwrap();
        assert_eq!(model.images.len(), 5);
        assert_eq!(model.points.len(), s.sparse.points.len());
        let k = model.intrinsics_of(&model.images[&1]).unwrap();
        assert!((k.cx - s.views[0].intrinsics.cx).abs() < 1e-9);
        let back = read_mvs_scene(dir.path()).unwrap();
        assert_eq!(back.reference, s.reference);
        assert_eq!(back.beta, s.beta);
        for (a, b) in back.views.iter().zip(&s.views) {
            assert_eq!(a.depth, b.depth);
            let worst = a
                .hazy
                .data()
                .iter()
                .zip(b.hazy.data())
                .map(|(x, y)| (x - y).abs())
                .fold(0.0f32, f32::max);
            assert!(worst <= 1.0 / 65535.0, "{worst}");
            assert!((a.pose.rotation() - b.pose.rotation()).amax() < 1e-9);
        }
    }
}
