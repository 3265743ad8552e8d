//! Photometric-stereo captures in a turbid medium (reference §4.4.1) with ground truth.
//!
//! Image formation is the single-scattering model of §4.2 (isotropic phase function,
//! homogeneous medium, near isotropic point lights, Lambertian object), Eq. 4.30:
//! `L = (L_sd + L_sf)·e^{−σ d_vp} + L_b + L_f`, with
//! - `L_sd`: direct light with attached *and cast* shadows (Eq. 4.31);
//! - `L_sf`: source-surface forward scatter with the exact table `G(T, n·l)` (Eq. 4.39–4.40),
//!   not the linearisation `G(T, 1)·n·l` the pipeline uses (Eq. 4.55);
//! - `L_b`: backscatter along the viewing ray up to the surface (Eq. 4.33);
//! - `L_f`: surface-camera forward scatter summed over **every** object pixel (Eq. 4.42), not
//!   the truncated r×r kernel plus constant the pipeline uses (Eq. 4.49–4.52); pixels farther
//!   than 32 px are sampled on a `far_stride` grid (weight `far_stride²`).
//!
//! The no-object image of each light has the medium extend to infinity along every ray, so the
//! backscatter subtraction of §4.3.1 leaves the tail `∫_{d_vp}^∞` in the object pixels, as it
//! would in a tank with a distant back wall.
//!
//! Folder layout written by [`write_ps_capture`] (and read by [`read_ps_capture`] — real
//! captures need only `meta.json` with `medium`, `lights`, `images`, `backgrounds` and either
//! `intrinsics` or a 3×3 `K`; `format`, `version`, `width` and `height` may be left out (the
//! size comes from the images), file names may name subfolders, and `mask` names the mask if
//! it is not `mask.png`):
//!
//! ```text
//! <dir>/
//!   meta.json              format "murk.ps_capture" v1: width, height, intrinsics {fx, fy, cx,
//!                          cy, skew} (pixels), medium {beta_per_mm, sigma_per_mm}, lights
//!                          [{position_mm [x,y,z] camera frame, intensity}], images,
//!                          backgrounds (file names, same order as lights),
//!                          initial_distance_mm (suggested initial plane), units; simulations
//!                          add config
//!   image_00.exr ...       with the object, one per light (1 channel "Y", f32, linear)
//!   background_00.exr ...  without the object, same light (backscatter only)
//!   mask.png               16-bit gray, 65535 = object
//!   gt_normals.exr         R,G,B = camera-frame unit normal towards the camera (simulation only)
//!   gt_depth_mm.exr        z-depth, mm, 0 off the object                         (simulation only)
//!   gt_albedo.exr          Lambertian albedo ρ                                    (simulation only)
//!   gt_reflected_00.exr .. reflected component L_s = L_sd + L_sf per light        (simulation only)
//! ```

use std::path::Path;

use nalgebra::Vector3;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::camera::Intrinsics;
use crate::error::{MurkError, Result};
use crate::image::ImageF32;
use crate::io::{self, DecodeLimits};
use crate::monitor::Monitor;
use crate::ps::capture::{PointLight, PsCapture};
use crate::ps::physics::{
    backscatter, dense_forward_scatter, source_surface_forward, FTable, FacetEmission, GTable,
    Medium, SurfaceGeometry,
};
use crate::simulate::IntrinsicsJson;

/// `format` tag of `meta.json`.
pub const PS_CAPTURE_FORMAT: &str = "murk.ps_capture";
/// Largest simulated or loaded side, pixels.
pub const MAX_PS_SIDE: usize = 2048;

/// The object in front of the camera.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PsShape {
    /// A sphere (the reference's synthetic object).
    Sphere,
    /// A vase: a surface of revolution about the vertical axis with a bulging, waisted
    /// profile; it has concave parts, so it casts shadows on itself and the forward scatter
    /// differs from a sphere's.
    Vase,
    /// A bumpy sphere: the radius varies by ±6 % as sin(6·u_x)·sin(6·u_y) of the direction u
    /// from the centre, so the normals vary on a scale of a few kernel widths.
    Bumps,
}

/// Everything that defines a simulated capture.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PsSimConfig {
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
    /// Focal length, pixels (square pixels, principal point at the image centre).
    pub focal_px: f64,
    /// The object.
    pub shape: PsShape,
    /// Distance from the camera to the object's centre, mm.
    pub object_distance_mm: f64,
    /// Object radius (sphere radius; the vase's mean radius), mm.
    pub object_radius_mm: f64,
    /// Scattering coefficient β, per mm.
    pub beta_per_mm: f64,
    /// Extinction coefficient σ, per mm (σ ≥ β).
    pub sigma_per_mm: f64,
    /// Number of lights, evenly spaced on a ring around the optical axis.
    pub num_lights: usize,
    /// Ring radius, mm.
    pub light_ring_radius_mm: f64,
    /// z of the ring plane, mm (0 = the camera's plane).
    pub light_z_mm: f64,
    /// Mean radiant intensity `I0` of the lights (per-light values vary by ±10 % under the
    /// seed; all are recorded).
    pub intensity: f64,
    /// Albedo of the object (the mean when textured).
    pub albedo: f64,
    /// Give the object a smooth albedo pattern (±40 %).
    pub textured: bool,
    /// Standard deviation of additive Gaussian noise on every image, in image units.
    pub noise_std: f64,
    /// Far-field sampling stride of the forward-scatter sum (1 = every pixel).
    pub far_stride: usize,
    /// Seed of the light intensities, the texture phase and the noise.
    pub seed: u64,
    /// How object facets radiate into the medium in the surface-camera forward scatter: the
    /// physical Lambertian cosine (default) or Eq. 4.41's isotropic facet.
    #[serde(default)]
    pub facet_emission: FacetEmission,
}

impl Default for PsSimConfig {
    /// The reference's synthetic setting (§4.4.1): 300×300, β = σ = 5e-3 /mm, 8 lights.
    fn default() -> Self {
        Self {
            width: 300,
            height: 300,
            focal_px: 550.0,
            shape: PsShape::Sphere,
            object_distance_mm: 250.0,
            object_radius_mm: 50.0,
            beta_per_mm: 5e-3,
            sigma_per_mm: 5e-3,
            num_lights: 8,
            light_ring_radius_mm: 120.0,
            light_z_mm: 0.0,
            intensity: 1.0e5,
            albedo: 0.8,
            textured: false,
            noise_std: 0.0,
            far_stride: 2,
            seed: 0,
            facet_emission: FacetEmission::default(),
        }
    }
}

impl PsSimConfig {
    /// The default setting scaled to `width × height` (focal length scales with the width, so
    /// the object covers the same share of the frame).
    pub fn with_size(width: usize, height: usize) -> Self {
        let d = Self::default();
        Self {
            width,
            height,
            focal_px: d.focal_px * width as f64 / d.width as f64,
            ..d
        }
    }

    /// Camera intrinsics.
    pub fn intrinsics(&self) -> Intrinsics {
        Intrinsics::new(
            self.focal_px,
            self.focal_px,
            (self.width as f64 - 1.0) / 2.0,
            (self.height as f64 - 1.0) / 2.0,
        )
    }

    /// The medium.
    pub fn medium(&self) -> Medium {
        Medium {
            beta_per_mm: self.beta_per_mm,
            sigma_per_mm: self.sigma_per_mm,
        }
    }

    /// Checks the settings; errors name the field.
    pub fn validate(&self) -> Result<()> {
        for (name, v) in [("width", self.width), ("height", self.height)] {
            if !(8..=MAX_PS_SIDE).contains(&v) {
                return Err(MurkError::invalid(
                    name,
                    format!("must be in 8..={MAX_PS_SIDE}, got {v}"),
                ));
            }
        }
        let positive = [
            ("focal_px", self.focal_px),
            ("object_distance_mm", self.object_distance_mm),
            ("object_radius_mm", self.object_radius_mm),
            ("intensity", self.intensity),
            ("albedo", self.albedo),
        ];
        for (name, v) in positive {
            if !v.is_finite() || v <= 0.0 {
                return Err(MurkError::invalid(
                    name,
                    format!("must be finite and > 0, got {v}"),
                ));
            }
        }
        if self.object_radius_mm * 1.5 >= self.object_distance_mm {
            return Err(MurkError::invalid(
                "object_radius_mm",
                "the object must lie well in front of the camera (radius < distance / 1.5)",
            ));
        }
        self.medium().validate()?;
        if !(3..=crate::ps::capture::MAX_LIGHTS).contains(&self.num_lights) {
            return Err(MurkError::invalid(
                "num_lights",
                format!(
                    "must be in 3..={}, got {}",
                    crate::ps::capture::MAX_LIGHTS,
                    self.num_lights
                ),
            ));
        }
        for (name, v) in [
            ("light_ring_radius_mm", self.light_ring_radius_mm),
            ("light_z_mm", self.light_z_mm),
            ("noise_std", self.noise_std),
        ] {
            if !v.is_finite() {
                return Err(MurkError::invalid(name, format!("must be finite, got {v}")));
            }
        }
        if self.light_ring_radius_mm <= 0.0 {
            return Err(MurkError::invalid("light_ring_radius_mm", "must be > 0"));
        }
        if self.light_z_mm >= self.object_distance_mm - self.object_radius_mm * 1.5 {
            return Err(MurkError::invalid(
                "light_z_mm",
                "the lights must be in front of the object (closer to the camera)",
            ));
        }
        if self.noise_std < 0.0 {
            return Err(MurkError::invalid("noise_std", "must be ≥ 0"));
        }
        if self.albedo * if self.textured { 1.4 } else { 1.0 } > 1.0 {
            return Err(MurkError::invalid(
                "albedo",
                "must keep the (textured) albedo ≤ 1",
            ));
        }
        if !(1..=16).contains(&self.far_stride) {
            return Err(MurkError::invalid(
                "far_stride",
                format!("must be in 1..=16, got {}", self.far_stride),
            ));
        }
        Ok(())
    }

    /// The lights: a ring around the optical axis, intensities `I0·(1 ± 10 %)` drawn from the
    /// seed.
    pub fn lights(&self) -> Vec<PointLight> {
        let mut rng = ChaCha8Rng::seed_from_u64(self.seed ^ 0x9e37_79b9_7f4a_7c15);
        (0..self.num_lights)
            .map(|i| {
                let a = 2.0 * std::f64::consts::PI * i as f64 / self.num_lights as f64;
                let jitter: f64 = rand::Rng::random_range(&mut rng, -0.1..0.1);
                PointLight {
                    position_mm: [
                        self.light_ring_radius_mm * a.cos(),
                        self.light_ring_radius_mm * a.sin(),
                        self.light_z_mm,
                    ],
                    intensity: self.intensity * (1.0 + jitter),
                }
            })
            .collect()
    }
}

/// A simulated capture with its ground truth.
#[derive(Clone, Debug)]
pub struct PsSimCapture {
    /// The settings.
    pub config: PsSimConfig,
    /// What the pipeline gets.
    pub capture: PsCapture,
    /// Suggested initial plane distance, mm: the mean z-depth of the object's visible surface
    /// (what a range sensor aimed at the object would report). The pipeline keeps the mean depth,
    /// so this sets the reconstruction's scale.
    pub initial_distance_mm: f64,
    /// Ground-truth unit normals towards the camera (`[0, 0, -1]` off the object).
    pub gt_normals: Vec<[f32; 3]>,
    /// Ground-truth z-depth, mm (0 off the object).
    pub gt_depth_mm: Vec<f32>,
    /// Ground-truth albedo (0 off the object).
    pub gt_albedo: Vec<f32>,
    /// Ground-truth reflected component `L_s` per light.
    pub gt_reflected: Vec<Vec<f32>>,
}

struct Hit {
    point: Vector3<f64>,
    normal: Vector3<f64>,
}

/// The object as a solid for ray casting.
struct Solid {
    shape: PsShape,
    centre: Vector3<f64>,
    radius: f64,
}

impl Solid {
    /// Vase profile radius at height `y` (relative to the centre) and its derivative.
    fn vase_radius(&self, y: f64) -> (f64, f64) {
        let r = self.radius;
        let k = 1.8 / r;
        (
            r * (0.7 + 0.2 * (k * y + 0.3).sin()),
            r * 0.2 * k * (k * y + 0.3).cos(),
        )
    }

    /// Bumpy-sphere radius in the unit direction `u` from the centre, and its gradient with
    /// respect to u (the z component is 0).
    fn bumps_radius(&self, u: Vector3<f64>) -> (f64, Vector3<f64>) {
        const A: f64 = 0.06;
        const K: f64 = 6.0;
        let (sx, cx) = (K * u[0]).sin_cos();
        let (sy, cy) = (K * u[1]).sin_cos();
        let r = self.radius;
        (
            r * (1.0 + A * sx * sy),
            Vector3::new(r * A * K * cx * sy, r * A * K * sx * cy, 0.0),
        )
    }

    fn half_height(&self) -> f64 {
        0.9 * self.radius
    }

    fn inside(&self, p: Vector3<f64>) -> bool {
        let d = p - self.centre;
        match self.shape {
            PsShape::Sphere => d.norm_squared() < self.radius * self.radius,
            PsShape::Vase => {
                if d[1].abs() > self.half_height() {
                    return false;
                }
                let (r, _) = self.vase_radius(d[1]);
                d[0] * d[0] + d[2] * d[2] < r * r
            }
            PsShape::Bumps => {
                let l = d.norm();
                l == 0.0 || l < self.bumps_radius(d / l).0
            }
        }
    }

    fn normal_at(&self, p: Vector3<f64>) -> Vector3<f64> {
        let d = p - self.centre;
        match self.shape {
            PsShape::Sphere => d.normalize(),
            PsShape::Vase => {
                let (r, dr) = self.vase_radius(d[1]);
                Vector3::new(d[0], -r * dr, d[2]).normalize()
            }
            PsShape::Bumps => {
                // ∇(|d| − r(u)) = u − (I − u uᵀ)·∇_u r/|d|.
                let l = d.norm();
                let u = d / l;
                let (_, g) = self.bumps_radius(u);
                let gu = g.dot(&u);
                (u - (g - u * gu) / l).normalize()
            }
        }
    }

    /// First intersection of `origin + t·dir` (unit `dir`) with the solid for t in
    /// `(t_min, t_max)`.
    fn first_hit(
        &self,
        origin: Vector3<f64>,
        dir: Vector3<f64>,
        t_min: f64,
        t_max: f64,
    ) -> Option<f64> {
        let oc = origin - self.centre;
        let bound = self.radius * 1.2;
        // Bounding sphere first: it also gives the sphere's exact answer.
        let b = oc.dot(&dir);
        let c = oc.norm_squared() - bound * bound;
        let disc = b * b - c;
        if disc < 0.0 {
            return None;
        }
        let (t0, t1) = (-b - disc.sqrt(), -b + disc.sqrt());
        if self.shape == PsShape::Sphere {
            let c = oc.norm_squared() - self.radius * self.radius;
            let disc = b * b - c;
            if disc < 0.0 {
                return None;
            }
            let t = -b - disc.sqrt();
            return (t > t_min && t < t_max).then_some(t);
        }
        let lo = t0.max(t_min);
        let hi = t1.min(t_max);
        if lo >= hi {
            return None;
        }
        let at = |t: f64| origin + dir * t;
        let step = self.radius / 400.0;
        let mut t = lo;
        let mut prev = t;
        while t < hi {
            if self.inside(at(t)) {
                let (mut a, mut b) = (prev, t);
                for _ in 0..50 {
                    let m = 0.5 * (a + b);
                    if self.inside(at(m)) {
                        b = m;
                    } else {
                        a = m;
                    }
                }
                return Some(b);
            }
            prev = t;
            t += step;
        }
        None
    }

    fn cast(&self, dir: Vector3<f64>) -> Option<Hit> {
        let t = self.first_hit(Vector3::zeros(), dir, 0.0, f64::INFINITY)?;
        let point = dir * t;
        let mut normal = self.normal_at(point);
        if normal.dot(&dir) > 0.0 {
            normal = -normal;
        }
        Some(Hit { point, normal })
    }
}

fn albedo_at(cfg: &PsSimConfig, p: Vector3<f64>) -> f64 {
    if !cfg.textured {
        return cfg.albedo;
    }
    let phase = (cfg.seed % 1000) as f64 * 0.37;
    let k = 2.0 * std::f64::consts::PI / (cfg.object_radius_mm * 0.6);
    let s = (k * p[0] + phase).sin() * (k * p[1] - phase).sin() * (0.7 * k * p[2]).cos();
    cfg.albedo * (1.0 + 0.4 * s)
}

/// Renders a capture (module docs give the model). Cancellable through `monitor`.
pub fn simulate_ps(cfg: &PsSimConfig, monitor: &Monitor) -> Result<PsSimCapture> {
    cfg.validate()?;
    let (w, h) = (cfg.width, cfg.height);
    let n = w * h;
    let intr = cfg.intrinsics();
    let medium = cfg.medium();
    let lights = cfg.lights();
    let solid = Solid {
        shape: cfg.shape,
        centre: Vector3::new(0.0, 0.0, cfg.object_distance_mm),
        radius: cfg.object_radius_mm,
    };
    let ft = FTable::global();
    let gt = GTable::global();
    // The scattering terms all carry a factor β; skipping them at β = 0 also avoids their
    // 0/0 at σ = 0 (T = 0).
    let scattering = medium.beta_per_mm > 0.0;
    monitor.progress("geometry", 0.0);

    let rays: Vec<Vector3<f64>> = (0..n)
        .map(|p| intr.ray((p % w) as f64, (p / w) as f64))
        .collect();
    let hits: Vec<Option<Hit>> = rays.par_iter().map(|&r| solid.cast(r)).collect();
    let mask: Vec<bool> = hits.iter().map(Option::is_some).collect();
    if !mask.iter().any(|&b| b) {
        return Err(MurkError::invalid(
            "object_distance_mm",
            "the object is not in view",
        ));
    }
    let mut gt_normals = vec![[0.0f32, 0.0, -1.0]; n];
    let mut gt_depth = vec![0.0f32; n];
    let mut gt_albedo = vec![0.0f32; n];
    let mut points = vec![[0.0f32; 3]; n];
    for (p, hit) in hits.iter().enumerate() {
        if let Some(hit) = hit {
            gt_normals[p] = hit.normal.map(|v| v as f32).into();
            gt_depth[p] = hit.point[2] as f32;
            gt_albedo[p] = albedo_at(cfg, hit.point) as f32;
            points[p] = hit.point.map(|v| v as f32).into();
        }
    }
    monitor.checkpoint()?;

    // Reflected component per light.
    monitor.progress("reflected light", 0.05);
    let gt_reflected: Vec<Vec<f32>> = lights
        .iter()
        .map(|light| {
            hits.par_iter()
                .enumerate()
                .map(|(p, hit)| {
                    let Some(hit) = hit else { return 0.0 };
                    let to_light = Vector3::from(light.position_mm) - hit.point;
                    let d = to_light.norm();
                    let l = to_light / d;
                    let cos = hit.normal.dot(&l);
                    let lit = cos > 0.0
                        && solid
                            .first_hit(hit.point, l, 1e-3 * cfg.object_radius_mm, d)
                            .is_none();
                    let direct = if lit {
                        light.intensity * (-medium.sigma_per_mm * d).exp() / (d * d) * cos
                    } else {
                        0.0
                    };
                    let forward = if scattering {
                        source_surface_forward(gt, &medium, light.intensity, d, cos)
                    } else {
                        0.0
                    };
                    (f64::from(gt_albedo[p]) * (direct + forward)) as f32
                })
                .collect()
        })
        .collect();
    monitor.checkpoint()?;

    // Surface-camera forward scatter over every object pixel.
    monitor.progress("forward scatter", 0.15);
    let geom = SurfaceGeometry {
        width: w,
        height: h,
        intrinsics: intr,
        points_mm: points,
        normals: gt_normals.clone(),
        mask: mask.clone(),
        emission: cfg.facet_emission,
    };
    let refs: Vec<&[f32]> = gt_reflected.iter().map(Vec::as_slice).collect();
    let forward = if scattering {
        dense_forward_scatter(ft, &medium, &geom, &refs, cfg.far_stride)
    } else {
        vec![vec![0.0f32; n]; lights.len()]
    };
    monitor.checkpoint()?;

    monitor.progress("backscatter", 0.9);
    let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
    let mut images = Vec::with_capacity(lights.len());
    let mut backgrounds = Vec::with_capacity(lights.len());
    for (i, light) in lights.iter().enumerate() {
        let (img, bg): (Vec<f32>, Vec<f32>) = (0..n)
            .into_par_iter()
            .map(|p| {
                let scatter = |len: f64| {
                    if scattering {
                        backscatter(
                            ft,
                            &medium,
                            light.intensity,
                            light.position_mm,
                            rays[p],
                            len,
                        )
                    } else {
                        0.0
                    }
                };
                let bg = scatter(f64::INFINITY);
                let val = match &hits[p] {
                    None => bg,
                    Some(hit) => {
                        let d_vp = hit.point.norm();
                        f64::from(gt_reflected[i][p]) * (-medium.sigma_per_mm * d_vp).exp()
                            + scatter(d_vp)
                            + f64::from(forward[i][p])
                    }
                };
                (val as f32, bg as f32)
            })
            .unzip();
        let add_noise = |mut v: Vec<f32>, rng: &mut ChaCha8Rng| {
            if cfg.noise_std > 0.0 {
                for x in &mut v {
                    *x += (cfg.noise_std * crate::simulate::mvs::gaussian(rng)) as f32;
                }
            }
            v
        };
        let img = add_noise(img, &mut rng);
        let bg = add_noise(bg, &mut rng);
        images.push(ImageF32::from_vec(w, h, 1, img)?);
        backgrounds.push(ImageF32::from_vec(w, h, 1, bg)?);
    }
    monitor.progress("done", 1.0);
    let initial_distance_mm = {
        let (sum, count) = gt_depth
            .iter()
            .zip(&mask)
            .filter(|(_, &m)| m)
            .fold((0.0f64, 0usize), |(s, c), (z, _)| {
                (s + f64::from(*z), c + 1)
            });
        sum / count as f64
    };
    Ok(PsSimCapture {
        config: cfg.clone(),
        capture: PsCapture {
            images,
            backgrounds,
            lights,
            mask,
            intrinsics: intr,
            medium,
        },
        initial_distance_mm,
        gt_normals,
        gt_depth_mm: gt_depth,
        gt_albedo,
        gt_reflected,
    })
}

// ---------------------------------------------------------------------------------------------
// Folder I/O

#[derive(Serialize, Deserialize)]
struct MediumJson {
    beta_per_mm: f64,
    sigma_per_mm: f64,
}

#[derive(Serialize, Deserialize)]
struct PsMeta {
    /// Optional when reading; must be [`PS_CAPTURE_FORMAT`] when given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    format: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    version: Option<u32>,
    /// Optional when reading (taken from the images); must match them when given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    width: Option<usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    height: Option<usize>,
    /// Either `intrinsics` {fx, fy, cx, cy, skew} or `K`, the 3×3 camera matrix (rows).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    intrinsics: Option<IntrinsicsJson>,
    #[serde(rename = "K", default, skip_serializing_if = "Option::is_none")]
    k: Option<[[f64; 3]; 3]>,
    medium: MediumJson,
    lights: Vec<PointLight>,
    images: Vec<String>,
    backgrounds: Vec<String>,
    /// The mask's file name (default `mask.png`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    mask: Option<String>,
    #[serde(default)]
    initial_distance_mm: Option<f64>,
    #[serde(default)]
    units: Option<serde_json::Value>,
    #[serde(default)]
    config: Option<PsSimConfig>,
}

/// A capture read from a folder, with whatever ground truth it has.
#[derive(Clone, Debug)]
pub struct PsFolder {
    /// The capture.
    pub capture: PsCapture,
    /// `initial_distance_mm` from `meta.json`, if given.
    pub initial_distance_mm: Option<f64>,
    /// The simulation settings, for simulated folders.
    pub config: Option<PsSimConfig>,
    /// Ground-truth normals, when `gt_normals.exr` is present.
    pub gt_normals: Option<Vec<[f32; 3]>>,
    /// Ground-truth depth, when `gt_depth_mm.exr` is present.
    pub gt_depth_mm: Option<Vec<f32>>,
}

fn to_normals_image(w: usize, h: usize, normals: &[[f32; 3]]) -> Result<ImageF32> {
    ImageF32::from_vec(w, h, 3, normals.iter().flatten().copied().collect())
}

/// Writes `sim` into `dir` (created if missing) in the layout of the module docs.
pub fn write_ps_capture(dir: &Path, sim: &PsSimCapture) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| io::io_error(dir, e))?;
    let cap = &sim.capture;
    let (w, h) = cap.dims();
    let mut images = Vec::new();
    let mut backgrounds = Vec::new();
    for (i, (img, bg)) in cap.images.iter().zip(&cap.backgrounds).enumerate() {
        let (a, b) = (
            format!("image_{i:02}.exr"),
            format!("background_{i:02}.exr"),
        );
        io::write_exr(&dir.join(&a), img)?;
        io::write_exr(&dir.join(&b), bg)?;
        io::write_exr(
            &dir.join(format!("gt_reflected_{i:02}.exr")),
            &ImageF32::from_vec(w, h, 1, sim.gt_reflected[i].clone())?,
        )?;
        images.push(a);
        backgrounds.push(b);
    }
    let mask = ImageF32::from_vec(
        w,
        h,
        1,
        cap.mask
            .iter()
            .map(|&b| if b { 1.0 } else { 0.0 })
            .collect(),
    )?;
    io::write_png16(&dir.join("mask.png"), &mask, 0.0, 1.0)?;
    io::write_exr(
        &dir.join("gt_normals.exr"),
        &to_normals_image(w, h, &sim.gt_normals)?,
    )?;
    io::write_exr(
        &dir.join("gt_depth_mm.exr"),
        &ImageF32::from_vec(w, h, 1, sim.gt_depth_mm.clone())?,
    )?;
    io::write_exr(
        &dir.join("gt_albedo.exr"),
        &ImageF32::from_vec(w, h, 1, sim.gt_albedo.clone())?,
    )?;
    let meta = PsMeta {
        format: Some(PS_CAPTURE_FORMAT.into()),
        version: Some(1),
        width: Some(w),
        height: Some(h),
        intrinsics: Some(cap.intrinsics.into()),
        k: None,
        medium: MediumJson {
            beta_per_mm: cap.medium.beta_per_mm,
            sigma_per_mm: cap.medium.sigma_per_mm,
        },
        lights: cap.lights.clone(),
        images,
        backgrounds,
        mask: None,
        initial_distance_mm: Some(sim.initial_distance_mm),
        units: Some(serde_json::json!({
            "lengths": "mm, camera frame (+x right, +y down, +z forward)",
            "medium": "beta and sigma per mm",
            "intensity": "radiant intensity I0 such that I0/d^2 (d in mm) is in image units",
            "images": "linear float, one channel",
            "normals": "unit, camera frame, pointing towards the camera",
        })),
        config: Some(sim.config.clone()),
    };
    let json = serde_json::to_vec_pretty(&meta)
        .map_err(|e| MurkError::Numerical(format!("serialising meta.json: {e}")))?;
    io::write_file(&dir.join("meta.json"), &json)
}

/// Intrinsics from a 3×3 camera matrix K = [[fx, skew, cx], [0, fy, cy], [0, 0, 1]] (pixels).
fn intrinsics_from_matrix(k: &[[f64; 3]; 3]) -> Result<Intrinsics> {
    let tol = 1e-9;
    if k[1][0].abs() > tol
        || k[2][0].abs() > tol
        || k[2][1].abs() > tol
        || (k[2][2] - 1.0).abs() > tol
    {
        return Err(MurkError::invalid(
            "meta.json.K",
            format!(
                "expected [[fx, skew, cx], [0, fy, cy], [0, 0, 1]] in pixels, got {k:?} (a \
                 transposed or unnormalised matrix?)"
            ),
        ));
    }
    let intr = Intrinsics {
        fx: k[0][0],
        fy: k[1][1],
        cx: k[0][2],
        cy: k[1][2],
        skew: k[0][1],
    };
    intr.validate().map_err(|e| e.within("meta.json.K"))?;
    Ok(intr)
}

/// Reads a capture folder (simulated or real) in the layout of the module docs.
pub fn read_ps_capture(dir: &Path) -> Result<PsFolder> {
    let path = dir.join("meta.json");
    let text = std::fs::read(&path).map_err(|e| io::io_error(&path, e))?;
    let meta: PsMeta = serde_json::from_slice(&text)
        .map_err(|e| MurkError::invalid("meta.json", format!("not valid capture metadata: {e}")))?;
    if let Some(format) = &meta.format {
        if format != PS_CAPTURE_FORMAT {
            return Err(MurkError::invalid(
                "meta.json.format",
                format!("expected {PS_CAPTURE_FORMAT:?} (or no format), got {format:?}"),
            ));
        }
    }
    let intrinsics = match (meta.intrinsics, &meta.k) {
        (Some(_), Some(_)) => {
            return Err(MurkError::invalid(
                "meta.json.K",
                "give either intrinsics or K, not both",
            ))
        }
        (None, None) => {
            return Err(MurkError::invalid(
                "meta.json.intrinsics",
                "missing: give intrinsics {fx, fy, cx, cy} or K (3x3, pixels)",
            ))
        }
        (Some(k), None) => Intrinsics::from(k),
        (None, Some(k)) => intrinsics_from_matrix(k)?,
    };
    let load = |name: &str, channels: usize, dims: Option<(usize, usize)>| -> Result<ImageF32> {
        let rel = Path::new(name);
        // Relative paths below the capture folder only: no root, no "..", no drive prefix.
        if name.is_empty()
            || !rel
                .components()
                .all(|c| matches!(c, std::path::Component::Normal(_)))
        {
            return Err(MurkError::invalid(
                name,
                "must be a path relative to the capture folder, without \"..\"",
            ));
        }
        let limits = DecodeLimits {
            max_pixels: (MAX_PS_SIDE * MAX_PS_SIDE) as u64,
            max_channels: channels,
        };
        let img = io::read_image(&dir.join(rel), &limits).map_err(|e| e.within(name))?;
        let dims = dims.unwrap_or(img.dims());
        if img.dims() != dims || img.channels() != channels {
            return Err(MurkError::invalid(
                name,
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
    let first = meta
        .images
        .first()
        .ok_or_else(|| MurkError::invalid("meta.json.images", "no images listed"))?;
    let dims = load(first, 1, None)?.dims();
    for (field, given, actual) in [
        ("meta.json.width", meta.width, dims.0),
        ("meta.json.height", meta.height, dims.1),
    ] {
        if let Some(v) = given {
            if v != actual {
                return Err(MurkError::invalid(
                    field,
                    format!("{v} disagrees with {first} ({actual}); it may be left out"),
                ));
            }
        }
    }
    let dims = Some(dims);
    let images = meta
        .images
        .iter()
        .map(|n| load(n, 1, dims))
        .collect::<Result<Vec<_>>>()?;
    let backgrounds = meta
        .backgrounds
        .iter()
        .map(|n| load(n, 1, dims))
        .collect::<Result<Vec<_>>>()?;
    let mask: Vec<bool> = load(meta.mask.as_deref().unwrap_or("mask.png"), 1, dims)?
        .data()
        .iter()
        .map(|&v| v > 0.5)
        .collect();
    let gt_normals = if dir.join("gt_normals.exr").exists() {
        Some(
            load("gt_normals.exr", 3, dims)?
                .data()
                .chunks_exact(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect(),
        )
    } else {
        None
    };
    let gt_depth_mm = if dir.join("gt_depth_mm.exr").exists() {
        Some(load("gt_depth_mm.exr", 1, dims)?.into_vec())
    } else {
        None
    };
    Ok(PsFolder {
        capture: PsCapture {
            images,
            backgrounds,
            lights: meta.lights,
            mask,
            intrinsics,
            medium: Medium {
                beta_per_mm: meta.medium.beta_per_mm,
                sigma_per_mm: meta.medium.sigma_per_mm,
            },
        },
        initial_distance_mm: meta.initial_distance_mm,
        config: meta.config,
        gt_normals,
        gt_depth_mm,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each shape's analytic normal is the direction in which the solid's inside test flips:
    /// stepping a little along it leaves the solid, against it enters, and a small step
    /// sideways stays on the surface's side within the second-order error.
    #[test]
    fn analytic_normals_match_the_inside_test() {
        for shape in [PsShape::Sphere, PsShape::Vase, PsShape::Bumps] {
            let solid = Solid {
                shape,
                centre: Vector3::new(0.0, 0.0, 250.0),
                radius: 50.0,
            };
            let mut checked = 0;
            for k in 0..200 {
                // Rays from the camera over the object's silhouette.
                let a = k as f64 * 0.731;
                let r = 0.18 * ((k as f64 * 0.37).sin() * 0.5 + 0.5);
                let dir = Vector3::new(r * a.cos(), r * a.sin(), 1.0).normalize();
                let Some(t) = solid.first_hit(Vector3::zeros(), dir, 1e-6, 1e4) else {
                    continue;
                };
                let p = dir * t;
                let n = solid.normal_at(p);
                assert!((n.norm_squared() - 1.0).abs() < 1e-9);
                assert!(
                    n.dot(&dir) < 0.0,
                    "{shape:?}: the visible side faces the camera"
                );
                let h = 0.05;
                let at = |s: f64| p + n * s;
                assert!(!solid.inside(at(h)), "{shape:?}: outside along the normal");
                assert!(solid.inside(at(-h)), "{shape:?}: inside against the normal");
                // Half a millimetre along the tangent plane the surface is within 0.01 mm of
                // it (curvature), so a normal off by more than ~6° fails one of these.
                let t1 = Vector3::new(n[1], -n[0], 0.0).normalize();
                let t2 = n.cross(&t1);
                for t in [t1, t2] {
                    for sgn in [-0.5, 0.5] {
                        let q = |s: f64| p + t * sgn + n * s;
                        if shape == PsShape::Vase && !solid.inside(q(-h)) && !solid.inside(q(h)) {
                            // Off the vase's top or bottom rim.
                            continue;
                        }
                        assert!(
                            !solid.inside(q(h)) && solid.inside(q(-h)),
                            "{shape:?} at {p:?}"
                        );
                    }
                }
                checked += 1;
            }
            assert!(checked > 50, "{shape:?}: {checked}");
        }
    }

    /// A hand-made capture needs no format, version, width or height; it may give `K` instead
    /// of `intrinsics`, keep its files in subfolders and name its mask; it reads back to the
    /// same capture. Paths leaving the folder, a transposed K and a width that contradicts the
    /// images are refused with the field named.
    #[test]
    fn hand_made_meta_json_is_accepted() {
        let sim = simulate_ps(&PsSimConfig::with_size(24, 20), &Monitor::noop()).unwrap();
        let dir = tempfile::tempdir().unwrap();
        write_ps_capture(dir.path(), &sim).unwrap();
        let root = dir.path();
        std::fs::create_dir_all(root.join("raw/bg")).unwrap();
        let mut meta: serde_json::Value =
            serde_json::from_slice(&std::fs::read(root.join("meta.json")).unwrap()).unwrap();
        let m = meta.as_object_mut().unwrap();
        for key in ["format", "version", "width", "height", "units", "config"] {
            m.remove(key);
        }
        let k = sim.capture.intrinsics;
        m.remove("intrinsics");
        m.insert(
            "K".into(),
            serde_json::json!([[k.fx, k.skew, k.cx], [0.0, k.fy, k.cy], [0.0, 0.0, 1.0]]),
        );
        for (list, sub) in [("images", "raw"), ("backgrounds", "raw/bg")] {
            let names: Vec<String> = m[list]
                .as_array()
                .unwrap()
                .iter()
                .map(|n| {
                    let n = n.as_str().unwrap();
                    let to = format!("{sub}/{n}");
                    std::fs::rename(root.join(n), root.join(&to)).unwrap();
                    to
                })
                .collect();
            m.insert(list.into(), serde_json::json!(names));
        }
        std::fs::rename(root.join("mask.png"), root.join("raw/object.png")).unwrap();
        m.insert("mask".into(), serde_json::json!("raw/object.png"));
        let write = |v: &serde_json::Value| {
            std::fs::write(root.join("meta.json"), serde_json::to_vec(v).unwrap()).unwrap()
        };
        write(&meta);
        let read = read_ps_capture(root).unwrap();
        assert_eq!(read.capture.intrinsics, sim.capture.intrinsics);
        assert_eq!(read.capture.mask, sim.capture.mask);
        assert_eq!(read.capture.images, sim.capture.images);
        assert_eq!(read.capture.backgrounds, sim.capture.backgrounds);

        let field = |edit: &dyn Fn(&mut serde_json::Value)| {
            let mut v = meta.clone();
            edit(&mut v);
            write(&v);
            crate::error::field_of(read_ps_capture(root).unwrap_err())
        };
        assert_eq!(
            field(&|v| v["images"][0] = serde_json::json!("../image_00.exr")),
            "../image_00.exr"
        );
        assert_eq!(
            field(&|v| v["images"][0] = serde_json::json!("/etc/passwd")),
            "/etc/passwd"
        );
        assert_eq!(
            field(&|v| v["K"] =
                serde_json::json!([[k.fx, 0.0, 0.0], [0.0, k.fy, 0.0], [k.cx, k.cy, 1.0]])),
            "meta.json.K"
        );
        assert_eq!(
            field(&|v| v["width"] = serde_json::json!(25)),
            "meta.json.width"
        );
        assert_eq!(
            field(&|v| v["intrinsics"] = serde_json::json!({"fx": 1, "fy": 1, "cx": 0, "cy": 0})),
            "meta.json.K"
        );
        assert_eq!(
            field(&|v| {
                v.as_object_mut().unwrap().remove("K");
            }),
            "meta.json.intrinsics"
        );
        assert_eq!(
            field(&|v| v["format"] = serde_json::json!("something.else")),
            "meta.json.format"
        );
    }
}
