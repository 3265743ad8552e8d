//! What a photometric-stereo capture in a medium consists of, and the rules it must satisfy
//! before any work starts.

use crate::camera::Intrinsics;
use crate::error::{MurkError, Result};
use crate::image::ImageF32;
use crate::ps::physics::Medium;

/// Most lights a capture may have; the reference uses 8.
pub const MAX_LIGHTS: usize = 64;

/// Smallest |det| of the normalised light-direction scatter matrix seen from the scene centre
/// for the light positions to count as non-coplanar. A ring of lights in one plane *through the
/// object* gives 0; any practical rig (lights around the camera, object in front) is ≫ 1e-3.
pub const MIN_LIGHT_SPREAD: f64 = 1e-3;

/// An isotropic near point light (Eq. 4.31: irradiance `I0/d²` before attenuation).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PointLight {
    /// Position in the camera frame, mm.
    pub position_mm: [f64; 3],
    /// Radiant intensity `I0`, in the image's units × mm² (so `I0/d²` is in image units).
    pub intensity: f64,
}

/// One photometric-stereo capture: per light an image with the object and one without it (same
/// light, same medium; the backscatter-saturation trick of Tsiotsios et al. [15], §4.3.1).
#[derive(Clone, Debug)]
pub struct PsCapture {
    /// Images with the object, one single-channel linear image per light.
    pub images: Vec<ImageF32>,
    /// Images without the object under the same light (backscatter only), same order.
    pub backgrounds: Vec<ImageF32>,
    /// The lights, same order.
    pub lights: Vec<PointLight>,
    /// Object mask (true = object), row-major, `width × height`.
    pub mask: Vec<bool>,
    /// Camera intrinsics, pixels.
    pub intrinsics: Intrinsics,
    /// The medium: β and σ per mm.
    pub medium: Medium,
}

impl PsCapture {
    /// Image width and height (of the first image).
    pub fn dims(&self) -> (usize, usize) {
        self.images.first().map(|i| i.dims()).unwrap_or((0, 0))
    }

    /// Checks every rule the pipeline relies on; errors name the field (`images[2]`,
    /// `lights[1].intensity`, `mask`, `medium.sigma_per_mm`, ...). `object_distance_mm` is
    /// where the object is expected (the initial plane); light directions are judged from there
    /// ([`PsCapture::check_light_directions`]), or not at all when it is unknown (`None`).
    pub fn validate(&self, object_distance_mm: Option<f64>) -> Result<()> {
        let m = self.lights.len();
        if m < 3 {
            return Err(MurkError::invalid(
                "lights",
                format!("photometric stereo needs at least 3 lights, got {m}"),
            ));
        }
        if m > MAX_LIGHTS {
            return Err(MurkError::invalid(
                "lights",
                format!("at most {MAX_LIGHTS} lights, got {m}"),
            ));
        }
        if self.images.len() != m {
            return Err(MurkError::invalid(
                "images",
                format!("{} images for {m} lights", self.images.len()),
            ));
        }
        if self.backgrounds.len() != m {
            return Err(MurkError::invalid(
                "backgrounds",
                format!("{} no-object images for {m} lights", self.backgrounds.len()),
            ));
        }
        let (w, h) = self.dims();
        for (name, list) in [("images", &self.images), ("backgrounds", &self.backgrounds)] {
            for (i, img) in list.iter().enumerate() {
                let field = format!("{name}[{i}]");
                if img.dims() != (w, h) {
                    return Err(MurkError::invalid(
                        field,
                        format!(
                            "size {}x{} differs from images[0] {w}x{h}",
                            img.width(),
                            img.height()
                        ),
                    ));
                }
                img.ensure_channels(1).map_err(|e| e.within(&field))?;
                img.ensure_finite().map_err(|e| e.within(&field))?;
            }
        }
        if self.mask.len() != w * h {
            return Err(MurkError::invalid(
                "mask",
                format!("{} entries for a {w}x{h} image", self.mask.len()),
            ));
        }
        if !self.mask.iter().any(|&b| b) {
            return Err(MurkError::invalid("mask", "the object mask is empty"));
        }
        self.intrinsics
            .validate()
            .map_err(|e| e.within("intrinsics"))?;
        self.medium.validate().map_err(|e| e.within("medium"))?;
        for (i, l) in self.lights.iter().enumerate() {
            if l.position_mm.iter().any(|v| !v.is_finite()) {
                return Err(MurkError::invalid(
                    format!("lights[{i}].position_mm"),
                    "must be finite",
                ));
            }
            if !l.intensity.is_finite() || l.intensity <= 0.0 {
                return Err(MurkError::invalid(
                    format!("lights[{i}].intensity"),
                    format!("must be finite and > 0, got {}", l.intensity),
                ));
            }
        }
        match object_distance_mm {
            Some(d) => self.check_light_directions(d),
            None => Ok(()),
        }
    }

    /// Fails when the lights' directions, seen from the mask's centre at z-depth
    /// `object_distance_mm`, are (nearly) coplanar: normals are then not determined.
    pub fn check_light_directions(&self, object_distance_mm: f64) -> Result<()> {
        let spread = light_spread(&self.lights, self.mask_centre_at(object_distance_mm));
        if spread < MIN_LIGHT_SPREAD {
            return Err(MurkError::invalid(
                "lights",
                format!(
                    "light directions are (nearly) coplanar as seen from the object \
                     (spread {spread:.2e} < {MIN_LIGHT_SPREAD:e}); normals are not determined"
                ),
            ));
        }
        Ok(())
    }

    /// The point at z-depth `z_mm` on the ray through the mask's centroid.
    fn mask_centre_at(&self, z_mm: f64) -> [f64; 3] {
        let (w, _) = self.dims();
        let (mut su, mut sv, mut n) = (0.0f64, 0.0f64, 0.0f64);
        for (i, _) in self.mask.iter().enumerate().filter(|(_, &b)| b) {
            su += (i % w.max(1)) as f64;
            sv += (i / w.max(1)) as f64;
            n += 1.0;
        }
        let ray = self.intrinsics.ray(su / n.max(1.0), sv / n.max(1.0));
        [ray[0] / ray[2] * z_mm, ray[1] / ray[2] * z_mm, z_mm]
    }
}

fn norm(v: [f64; 3]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

/// det of `(1/m)·Σ l_i l_iᵀ` for the unit directions from `point` to each light: 0 when the
/// directions are coplanar (the PS system is rank-deficient), 1/27 at best for m → ∞ evenly
/// spread on a sphere.
pub fn light_spread(lights: &[PointLight], point: [f64; 3]) -> f64 {
    let mut s = [[0.0f64; 3]; 3];
    for l in lights {
        let d = [
            l.position_mm[0] - point[0],
            l.position_mm[1] - point[1],
            l.position_mm[2] - point[2],
        ];
        let n = norm(d);
        if n == 0.0 {
            continue;
        }
        let u = [d[0] / n, d[1] / n, d[2] / n];
        for r in 0..3 {
            for c in 0..3 {
                s[r][c] += u[r] * u[c];
            }
        }
    }
    let m = lights.len().max(1) as f64;
    for row in &mut s {
        for v in row {
            *v /= m;
        }
    }
    s[0][0] * (s[1][1] * s[2][2] - s[1][2] * s[2][1])
        - s[0][1] * (s[1][0] * s[2][2] - s[1][2] * s[2][0])
        + s[0][2] * (s[1][0] * s[2][1] - s[1][1] * s[2][0])
}
