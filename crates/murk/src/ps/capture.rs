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

/// Farthest a light may be from the camera along any axis, mm (1 km). Photometric stereo needs
/// near lights; a larger value is a unit slip or garbage, and would overflow `1/d²` terms.
pub const MAX_LIGHT_COORDINATE_MM: f64 = 1e6;

/// Range of a light's radiant intensity `I0`, image units × mm². `I0/d²` must stay a normal
/// f32 in image units for every distance murk accepts; the reference's rigs sit near 1e5.
pub const LIGHT_INTENSITY_RANGE: (f64, f64) = (1e-15, 1e20);

/// Largest |sample| of a capture's images, image units. The pipeline sums squared samples over
/// every pixel and light; an image offset to 3e38 overflowed its right-hand side. Cameras give
/// 16-bit counts or normalised floats, far inside.
pub const MAX_SAMPLE_MAGNITUDE: f32 = 1e20;

/// An isotropic near point light (Eq. 4.31: irradiance `I0/d²` before attenuation).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PointLight {
    /// Position in the camera frame, mm.
    pub position_mm: [f64; 3],
    /// Radiant intensity `I0`, in the image's units × mm² (so `I0/d²` is in image units).
    pub intensity: f64,
}

/// One photometric-stereo capture: per light an image with the object and one without it (same
/// light, same medium; the backscatter-saturation trick of Tsiotsios et al. \[15\], §4.3.1).
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
                let largest = img.data().iter().fold(0.0f32, |m, v| m.max(v.abs()));
                if largest > MAX_SAMPLE_MAGNITUDE {
                    return Err(MurkError::invalid(
                        field,
                        format!(
                            "a sample of magnitude {largest:e} is above {MAX_SAMPLE_MAGNITUDE:e}: \
                             rescale the images (e.g. with Image.value_scale)"
                        ),
                    ));
                }
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
            if l.position_mm
                .iter()
                .any(|v| v.abs() > MAX_LIGHT_COORDINATE_MM)
            {
                return Err(MurkError::invalid(
                    format!("lights[{i}].position_mm"),
                    format!(
                        "{:?} mm is more than {MAX_LIGHT_COORDINATE_MM:e} mm from the camera: \
                         photometric stereo needs near lights, in millimetres",
                        l.position_mm
                    ),
                ));
            }
            if !l.intensity.is_finite() || l.intensity <= 0.0 {
                return Err(MurkError::invalid(
                    format!("lights[{i}].intensity"),
                    format!("must be finite and > 0, got {}", l.intensity),
                ));
            }
            let (lo, hi) = LIGHT_INTENSITY_RANGE;
            if !(lo..=hi).contains(&l.intensity) {
                return Err(MurkError::invalid(
                    format!("lights[{i}].intensity"),
                    format!(
                        "{} is outside [{lo:e}, {hi:e}] (image units × mm²)",
                        l.intensity
                    ),
                ));
            }
        }
        self.check_units(object_distance_mm)?;
        match object_distance_mm {
            Some(d) => self.check_light_directions(d),
            None => Ok(()),
        }
    }

    /// Refuses the unit slips a finite, positive value cannot catch, naming the likely mistake:
    /// lights given in metres (all within [`MIN_RIG_SIZE_MM`] of each other and of the camera),
    /// and β or σ given per metre (the medium would hide the object: transmission below e^{−30}
    /// over the scene's scale, the object distance or else the rig's size).
    fn check_units(&self, object_distance_mm: Option<f64>) -> Result<()> {
        let rig = rig_size_mm(&self.lights);
        if rig < MIN_RIG_SIZE_MM {
            return Err(MurkError::invalid(
                "lights",
                format!(
                    "every light lies within {rig:.3} mm of the others and of the camera: \
                     light positions are in millimetres (values in metres must be multiplied \
                     by 1000)"
                ),
            ));
        }
        let scale = object_distance_mm.unwrap_or(rig);
        for (field, v) in [
            ("medium.sigma_per_mm", self.medium.sigma_per_mm),
            ("medium.beta_per_mm", self.medium.beta_per_mm),
        ] {
            if v * scale > MAX_OPTICAL_DEPTH {
                return Err(MurkError::invalid(
                    field,
                    format!(
                        "{v} per mm over the scene's {scale:.0} mm is an optical depth of {:.0}: \
                         the medium would hide the object completely. Coefficients are per \
                         millimetre (values per metre must be divided by 1000)",
                        v * scale
                    ),
                ));
            }
        }
        Ok(())
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

/// Smallest rig accepted: the largest distance between two lights or between a light and the
/// camera, mm. Near-light photometric stereo rigs span centimetres to metres; a rig below 5 mm
/// is a rig given in metres.
pub const MIN_RIG_SIZE_MM: f64 = 5.0;

/// Largest σ·(scene scale) accepted: e^{−30} ≈ 10⁻¹³ leaves nothing of the object to see in
/// any image format.
pub const MAX_OPTICAL_DEPTH: f64 = 30.0;

/// The largest distance between two lights, or between a light and the camera, mm.
pub fn rig_size_mm(lights: &[PointLight]) -> f64 {
    let mut size = 0.0f64;
    for (i, a) in lights.iter().enumerate() {
        size = size.max(norm(a.position_mm));
        for b in &lights[i + 1..] {
            let d = [
                a.position_mm[0] - b.position_mm[0],
                a.position_mm[1] - b.position_mm[1],
                a.position_mm[2] - b.position_mm[2],
            ];
            size = size.max(norm(d));
        }
    }
    size
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::monitor::Monitor;
    use crate::simulate::ps::{simulate_ps, PsSimConfig};

    fn capture() -> PsCapture {
        simulate_ps(&PsSimConfig::with_size(24, 24), &Monitor::noop())
            .unwrap()
            .capture
    }

    /// Unit slips get an error that names the field and the likely mistake.
    #[test]
    fn unit_mistakes_name_the_likely_unit() {
        let good = capture();
        assert!(good.validate(Some(212.0)).is_ok());
        assert!(good.validate(None).is_ok());

        let mut metres = good.clone();
        for l in &mut metres.lights {
            l.position_mm = l.position_mm.map(|v| v / 1000.0);
        }
        for d in [Some(0.212), None] {
            let e = metres.validate(d).unwrap_err();
            assert!(e.to_string().contains("multiplied by 1000"), "{e}");
            assert_eq!(crate::error::field_of(e), "lights");
        }

        // β = σ = 5 per metre given as 5 per mm.
        let mut per_metre = good.clone();
        per_metre.medium.beta_per_mm = 5.0;
        per_metre.medium.sigma_per_mm = 5.0;
        for d in [Some(212.0), None] {
            let e = per_metre.validate(d).unwrap_err();
            assert!(e.to_string().contains("divided by 1000"), "{e}");
            assert_eq!(crate::error::field_of(e), "medium.sigma_per_mm");
        }
        // Turbid but plausible water passes: σ = 0.05 /mm over 212 mm is an optical depth of 11.
        let mut turbid = good;
        turbid.medium.sigma_per_mm = 0.05;
        assert!(turbid.validate(Some(212.0)).is_ok());
    }
}
