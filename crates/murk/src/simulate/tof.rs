//! Physically based CW-ToF frames in homogeneous fog (single scattering, reference §2.2 and §5.2).
//!
//! # Model
//! Per pixel (ray `d` through the pixel centre, nearest surface at camera distance `s*`, light at
//! `L`, `r_l(p) = |p − L|`), the received signal is the phasor sum of Eq. 5.3:
//!
//! * direct (Eq. 5.18 generalised to an offset, limited beam):
//!   `α_d = I₀·beam(p*)·(ρ/π)·max(0, n·l)·e^{−β(r_l+s*)}/r_l²` at phase `2πf(r_l+s*)/c`,
//!   zero when another object shadows `p*` from the light;
//! * scattered (Eq. 2.13 / 5.17 with the offset light and beam):
//!   `∫_{s0}^{s*} I₀·beam(p)·β·P_HG(θ)·e^{−β(r_l(p)+s)}/r_l(p)² ds` at phase `2πf(r_l+s)/c`, where
//!   `P_HG` is Eq. 2.10, `θ` is the angle between the light's propagation direction `(p−L)/r_l`
//!   and the direction back to the camera `−d`, and points the objects shadow from the light
//!   contribute nothing.
//!
//! Both terms are radiances; the pixel's solid angle, aperture and `cos⁴` vignetting multiply
//! both alike, so they are folded into `I₀` (no vignetting is modelled). Extinction equals
//! scattering (`σ = β`, no absorption) and multiple scattering is neglected, as in the reference.
//!
//! # Beam
//! The source emits along +z with intensity `I₀·beam(ψ)`, `ψ` the angle from +z as seen from
//! `L`: `beam = 1` for `ψ ≤ ψ_h − w/2`, `0` for `ψ ≥ ψ_h + w/2`, and a raised cosine in `ψ` in
//! between (`ψ_h` = [`TofSimConfig::beam_half_angle_deg`], the 50 % point; `w` =
//! [`TofSimConfig::beam_edge_width_deg`]). The raised cosine keeps the integrand C¹, which the
//! quadrature relies on, and darkens the image corners as a real ToF illuminator does (Fig. 5.3).
//!
//! # Quadrature
//! Composite Simpson in `u = ln s` (geometric steps in `s`): the integrand falls like `1/s²`, so
//! equal steps in `ln s` spend samples where the signal is. The number of intervals is
//! `samples_per_efold·ln(s*/s0)` rounded up to even (default 48 per e-fold, ≈ 330 samples for a
//! 9 m ray); doubling it changes the scatter phasor by far less than 0.1 % (tested).
//!
//! # Noise
//! Additive complex Gaussian noise on the total phasor with per-component variance
//! `σ² = noise_shot²·|signal| + noise_read²`: photon shot noise (variance proportional to the
//! signal) and read noise are independent, so their variances add. Drawn from a ChaCha8 stream
//! per image row so the result is independent of thread scheduling.

use std::f64::consts::PI;
use std::fmt;
use std::str::FromStr;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::scene::{Scene, SceneLayout, V3};
use crate::camera::Intrinsics;
use crate::error::{MurkError, Result};
use crate::image::ImageF32;
use crate::monitor::Monitor;
use crate::tof::SPEED_OF_LIGHT_M_PER_S;

/// Largest accepted image side, pixels.
pub const MAX_SIM_SIDE: usize = 8192;
/// Largest accepted pixel count (16 Mpx): the frame holds nine f32 images.
pub const MAX_SIM_PIXELS: usize = 1 << 24;

/// Reference resolution of [`TofSimConfig::default`] (Kinect v2 depth camera).
const DEFAULT_WIDTH: usize = 512;
const DEFAULT_HEIGHT: usize = 424;
const DEFAULT_FOCAL_PX: f64 = 365.0;

/// Fog density presets. β is both the scattering and the extinction coefficient.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FogPreset {
    /// β = 1·10⁻⁴ /mm (visibility ≈ 30 m).
    Thin,
    /// β = 3·10⁻⁴ /mm, close to the reference's measured 3.2–3.5·10⁻⁴ /mm (§5.4).
    Medium,
    /// β = 6·10⁻⁴ /mm.
    Thick,
}

impl FogPreset {
    /// Extinction (= scattering) coefficient, per millimetre.
    pub fn beta_per_mm(self) -> f64 {
        match self {
            FogPreset::Thin => 1e-4,
            FogPreset::Medium => 3e-4,
            FogPreset::Thick => 6e-4,
        }
    }

    /// All presets, thinnest first.
    pub const ALL: [FogPreset; 3] = [FogPreset::Thin, FogPreset::Medium, FogPreset::Thick];
}

impl fmt::Display for FogPreset {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            FogPreset::Thin => "thin",
            FogPreset::Medium => "medium",
            FogPreset::Thick => "thick",
        })
    }
}

impl FromStr for FogPreset {
    type Err = MurkError;
    fn from_str(s: &str) -> Result<Self> {
        match s.trim().to_ascii_lowercase().as_str() {
            "thin" => Ok(FogPreset::Thin),
            "medium" => Ok(FogPreset::Medium),
            "thick" => Ok(FogPreset::Thick),
            other => Err(MurkError::invalid(
                "preset",
                format!("unknown fog preset {other:?}; expected thin, medium or thick"),
            )),
        }
    }
}

/// Everything that defines a simulated frame. [`Default`] is a Kinect v2-like camera in medium fog.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct TofSimConfig {
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels (pixel-centre convention of [`Intrinsics`]).
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// CW modulation frequency, Hz (Kinect v2 uses ≈ 16 MHz among others).
    pub modulation_frequency_hz: f64,
    /// Light source position along the camera's +x (image right), millimetres; the source sits on
    /// the image's horizontal axis as the reference's symmetry prior assumes (Fig. 5.5).
    pub light_offset_mm: f64,
    /// Beam half-angle where the intensity is 50 %, degrees from +z.
    pub beam_half_angle_deg: f64,
    /// Width of the raised-cosine fall-off centred on the half-angle, degrees (> 0).
    pub beam_edge_width_deg: f64,
    /// Henyey–Greenstein asymmetry `g` (Eq. 2.10); 0.9 for fog.
    pub hg_g: f64,
    /// Fog density preset.
    pub preset: FogPreset,
    /// Overrides the preset's β (per mm) when set; `Some(0.0)` renders clear air.
    pub beta_per_mm: Option<f64>,
    /// Source radiant intensity on the beam axis, in sensor units·m² (radiance → signal scale
    /// folded in). 15 000 gives amplitude ≈ 1000 for a 0.5-albedo surface at 1.5 m in clear air.
    pub source_intensity: f64,
    /// Start of the scattering integral along the ray, millimetres (reference: 10 mm).
    pub scatter_start_mm: f64,
    /// Simpson intervals per e-fold of `s*/s0` for the scattering integral.
    pub samples_per_efold: usize,
    /// Shot-noise factor `a` in `σ² = a²·|signal| + b²` (per real/imaginary component): the
    /// shot noise's standard deviation is `a·√|signal|`.
    pub noise_shot: f64,
    /// Read-noise standard deviation `b` in `σ² = a²·|signal| + b²`.
    pub noise_read: f64,
    /// Seeds the scene layout and the noise.
    pub seed: u64,
    /// How objects are placed.
    pub layout: SceneLayout,
}

impl Default for TofSimConfig {
    fn default() -> Self {
        Self {
            width: DEFAULT_WIDTH,
            height: DEFAULT_HEIGHT,
            fx: DEFAULT_FOCAL_PX,
            fy: DEFAULT_FOCAL_PX,
            cx: (DEFAULT_WIDTH as f64 - 1.0) / 2.0,
            cy: (DEFAULT_HEIGHT as f64 - 1.0) / 2.0,
            modulation_frequency_hz: 16e6,
            light_offset_mm: 60.0,
            beam_half_angle_deg: 37.5,
            beam_edge_width_deg: 10.0,
            hg_g: 0.9,
            preset: FogPreset::Medium,
            beta_per_mm: None,
            source_intensity: 15_000.0,
            scatter_start_mm: 10.0,
            samples_per_efold: 48,
            // σ ≈ 0.15·√1000 + 0.5 ≈ 5 on a bright object: SNR ≈ 100-200 on objects.
            noise_shot: 0.15,
            noise_read: 0.5,
            seed: 0,
            layout: SceneLayout::Separated,
        }
    }
}

impl TofSimConfig {
    /// Standard deviation of the noise per phasor component at clean amplitude `amplitude`:
    /// shot and read noise are independent, so their variances add,
    /// `σ = √(noise_shot²·|amplitude| + noise_read²)`.
    pub fn noise_sigma(&self, amplitude: f64) -> f64 {
        (self.noise_shot * self.noise_shot * amplitude.abs() + self.noise_read * self.noise_read)
            .sqrt()
    }

    /// The light source's position in the camera frame, metres.
    pub fn light_position_m(&self) -> [f64; 3] {
        [self.light_offset_mm * 1e-3, 0.0, 0.0]
    }

    /// The default camera at `width × height`, focal lengths scaled so the field of view is the
    /// default's, principal point at the image centre.
    pub fn with_size(width: usize, height: usize) -> Self {
        let d = Self::default();
        Self {
            width,
            height,
            fx: d.fx * width as f64 / DEFAULT_WIDTH as f64,
            fy: d.fy * height as f64 / DEFAULT_HEIGHT as f64,
            cx: (width as f64 - 1.0) / 2.0,
            cy: (height as f64 - 1.0) / 2.0,
            ..d
        }
    }

    /// The β in effect: the override if set, else the preset's. Per millimetre.
    pub fn effective_beta_per_mm(&self) -> f64 {
        self.beta_per_mm.unwrap_or(self.preset.beta_per_mm())
    }

    /// The camera intrinsics.
    pub fn intrinsics(&self) -> Intrinsics {
        Intrinsics::new(self.fx, self.fy, self.cx, self.cy)
    }

    /// Checks every field; errors name it.
    pub fn validate(&self) -> Result<()> {
        for (name, v) in [("width", self.width), ("height", self.height)] {
            if !(2..=MAX_SIM_SIDE).contains(&v) {
                return Err(MurkError::invalid(
                    name,
                    format!("must be in 2..={MAX_SIM_SIDE} pixels, got {v}"),
                ));
            }
        }
        if self.width * self.height > MAX_SIM_PIXELS {
            return Err(MurkError::invalid(
                "width",
                format!(
                    "{}x{} exceeds the {MAX_SIM_PIXELS}-pixel limit",
                    self.width, self.height
                ),
            ));
        }
        self.intrinsics().validate()?;
        let checks: [(&str, f64, f64, f64); 9] = [
            (
                "modulation_frequency_hz",
                self.modulation_frequency_hz,
                1e3,
                1e10,
            ),
            ("light_offset_mm", self.light_offset_mm, -1000.0, 1000.0),
            ("beam_half_angle_deg", self.beam_half_angle_deg, 1.0, 85.0),
            ("beam_edge_width_deg", self.beam_edge_width_deg, 0.5, 60.0),
            ("hg_g", self.hg_g, -0.99, 0.99),
            ("source_intensity", self.source_intensity, 1e-12, 1e12),
            ("scatter_start_mm", self.scatter_start_mm, 1e-3, 1000.0),
            ("noise_shot", self.noise_shot, 0.0, 1e3),
            ("noise_read", self.noise_read, 0.0, 1e6),
        ];
        for (name, v, lo, hi) in checks {
            if !v.is_finite() || v < lo || v > hi {
                return Err(MurkError::invalid(
                    name,
                    format!("must be finite and in [{lo}, {hi}], got {v}"),
                ));
            }
        }
        if self.beam_half_angle_deg + self.beam_edge_width_deg / 2.0 >= 90.0 {
            return Err(MurkError::invalid(
                "beam_edge_width_deg",
                "beam_half_angle_deg + beam_edge_width_deg/2 must stay below 90°",
            ));
        }
        if let Some(b) = self.beta_per_mm {
            if !b.is_finite() || !(0.0..=0.1).contains(&b) {
                return Err(MurkError::invalid(
                    "beta_per_mm",
                    format!("must be finite and in [0, 0.1] per mm, got {b}"),
                ));
            }
        }
        if !(4..=4096).contains(&self.samples_per_efold) {
            return Err(MurkError::invalid(
                "samples_per_efold",
                format!("must be in 4..=4096, got {}", self.samples_per_efold),
            ));
        }
        Ok(())
    }
}

/// A complex signal `re + j·im` (Eq. 5.1).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Phasor {
    /// Real part.
    pub re: f64,
    /// Imaginary part.
    pub im: f64,
}

impl Phasor {
    /// `amplitude·e^{j·phase}`.
    pub fn from_polar(amplitude: f64, phase: f64) -> Self {
        let (s, c) = phase.sin_cos();
        Self {
            re: amplitude * c,
            im: amplitude * s,
        }
    }
    /// Modulus.
    pub fn amplitude(self) -> f64 {
        self.re.hypot(self.im)
    }
    /// Argument wrapped to `[0, 2π)`.
    pub fn phase(self) -> f64 {
        wrap_phase(self.im.atan2(self.re))
    }
}

impl std::ops::Add for Phasor {
    type Output = Phasor;
    fn add(self, o: Phasor) -> Phasor {
        Phasor {
            re: self.re + o.re,
            im: self.im + o.im,
        }
    }
}

/// Wraps an angle to `[0, 2π)`.
pub fn wrap_phase(phi: f64) -> f64 {
    let w = phi.rem_euclid(2.0 * PI);
    // rem_euclid can round up to exactly 2π for tiny negative inputs.
    if w >= 2.0 * PI {
        0.0
    } else {
        w
    }
}

/// One simulated frame plus its ground truth. All images are one-channel, `width × height`.
#[derive(Clone, Debug, PartialEq)]
pub struct TofSimFrame {
    /// The configuration that produced the frame.
    pub config: TofSimConfig,
    /// Camera intrinsics (pixel-centre convention).
    pub intrinsics: Intrinsics,
    /// The generated scene (metres, camera frame).
    pub scene: Scene,
    /// Observed amplitude `α̃` in fog, with noise (sensor units).
    pub amplitude: ImageF32,
    /// Observed phase `φ̃` in fog, with noise, radians in `[0, 2π)`.
    pub phase: ImageF32,
    /// Amplitude of the same scene without fog and without noise.
    pub amplitude_clear: ImageF32,
    /// Phase of the same scene without fog and without noise, radians in `[0, 2π)`.
    ///
    /// The phase encodes the optical path `r_l + s*`, so Eq. 5.2 yields `(r_l + s*)/2`, which
    /// differs from `gt_range_m` by at most half the light offset (30 mm by default): the floor
    /// of any estimator that ignores the offset.
    pub phase_clear: ImageF32,
    /// Amplitude `α_s` of the fog-only phasor (ground-truth scattering component, noise-free).
    pub scatter_amplitude: ImageF32,
    /// Phase `φ_s` of the fog-only phasor, radians in `[0, 2π)`.
    pub scatter_phase: ImageF32,
    /// Ground-truth distance along the viewing ray to the surface, metres.
    pub gt_range_m: ImageF32,
    /// Ground-truth z-depth of the surface, metres.
    pub gt_z_depth_m: ImageF32,
    /// 1 where the pixel sees an object that the camera's own light reaches (its clear-air
    /// direct return is above the sensor's read-noise floor), 0 elsewhere. Object pixels in
    /// shadow or outside the beam return no direct light: no ToF method can measure them, so
    /// accuracy is evaluated on this mask.
    pub gt_mask: ImageF32,
    /// 1 where the pixel sees an object at all (lit or not), 0 where it sees the wall.
    pub gt_object_mask: ImageF32,
}

/// Precomputed constants of the signal model.
struct Model<'a> {
    scene: &'a Scene,
    light: V3,
    beta: f64,
    /// Phase per metre of optical path: 2πf/c.
    k_path: f64,
    i0: f64,
    s0: f64,
    samples_per_efold: usize,
    hg_num: f64,
    hg_a: f64,
    hg_b: f64,
    cos_in: f64,
    cos_out: f64,
    psi_in: f64,
    edge: f64,
    /// Points closer to the light than this cannot be shadowed by any object.
    min_shadow_rl: f64,
}

impl<'a> Model<'a> {
    fn new(cfg: &TofSimConfig, scene: &'a Scene, beta_per_mm: f64) -> Self {
        let light = V3::new(cfg.light_offset_mm * 1e-3, 0.0, 0.0);
        let psi_h = cfg.beam_half_angle_deg.to_radians();
        let edge = cfg.beam_edge_width_deg.to_radians();
        let psi_in = psi_h - edge / 2.0;
        let g = cfg.hg_g;
        let min_shadow_rl = scene
            .objects
            .iter()
            .map(|o| {
                let (c, r) = o.shape.bounding_sphere();
                let lc = c - light;
                lc.norm() - r
            })
            .fold(f64::INFINITY, f64::min)
            .max(0.0);
        Model {
            scene,
            light,
            beta: beta_per_mm * 1e3,
            k_path: 2.0 * PI * cfg.modulation_frequency_hz / SPEED_OF_LIGHT_M_PER_S,
            i0: cfg.source_intensity,
            s0: cfg.scatter_start_mm * 1e-3,
            samples_per_efold: cfg.samples_per_efold,
            hg_num: (1.0 - g * g) / (4.0 * PI),
            hg_a: 1.0 + g * g,
            hg_b: 2.0 * g,
            cos_in: psi_in.max(0.0).cos(),
            cos_out: (psi_h + edge / 2.0).cos(),
            psi_in,
            edge,
            min_shadow_rl,
        }
    }

    /// Relative beam intensity for a direction from the light with z-component `cos_psi`.
    #[inline]
    fn beam(&self, cos_psi: f64) -> f64 {
        if cos_psi >= self.cos_in {
            1.0
        } else if cos_psi <= self.cos_out {
            0.0
        } else {
            let t = (cos_psi.clamp(-1.0, 1.0).acos() - self.psi_in) / self.edge;
            0.5 * (1.0 + (PI * t.clamp(0.0, 1.0)).cos())
        }
    }

    /// Henyey–Greenstein phase function, Eq. 2.10.
    #[inline]
    fn hg(&self, cos_theta: f64) -> f64 {
        let den = self.hg_a - self.hg_b * cos_theta;
        self.hg_num / (den * den.sqrt())
    }

    /// Direct phasor from surface point `p` (normal `n`, albedo `rho`) seen at camera distance
    /// `s` with extinction `beta` (per m). Eq. 5.18 with the offset, limited beam.
    fn direct(&self, p: V3, n: V3, rho: f64, s: f64, beta: f64, shadowed: bool) -> Phasor {
        let lp = self.light - p;
        let rl2 = lp.norm_squared();
        let rl = rl2.sqrt();
        let cos_i = n.dot(&lp) / rl;
        if cos_i <= 0.0 || shadowed {
            return Phasor::default();
        }
        // Direction from the light to p has z-component −lp_z / r_l.
        let b = self.beam(-lp[2] / rl);
        let amp = self.i0 * b * (rho / PI) * cos_i * (-beta * (rl + s)).exp() / rl2;
        Phasor::from_polar(amp, self.k_path * (rl + s))
    }

    /// Single-scattering phasor along the camera ray `d` (unit) from `s0` to `s_end` (m).
    fn scatter(&self, d: V3, s_end: f64, shadows: bool) -> Phasor {
        if self.beta <= 0.0 || s_end <= self.s0 {
            return Phasor::default();
        }
        let (u0, u1) = (self.s0.ln(), s_end.ln());
        let efolds = u1 - u0;
        let mut n = (efolds * self.samples_per_efold as f64).ceil() as usize;
        n = n.max(8);
        n += n % 2;
        let h = efolds / n as f64;
        let (mut re, mut im) = (0.0, 0.0);
        for i in 0..=n {
            let s = (u0 + h * i as f64).exp();
            let w = if i == 0 || i == n {
                1.0
            } else if i % 2 == 1 {
                4.0
            } else {
                2.0
            };
            let p = d * s;
            let v = p - self.light;
            let rl2 = v.norm_squared();
            let rl = rl2.sqrt();
            let b = self.beam(v[2] / rl);
            if b == 0.0 {
                continue;
            }
            if shadows && rl > self.min_shadow_rl && self.scene.occluded(self.light, p) {
                continue;
            }
            // Scattering angle between propagation (p−L)/r_l and the way back to the camera −d.
            let cos_theta = -v.dot(&d) / rl;
            // ds = s·du in log space.
            let f = w
                * s
                * self.i0
                * b
                * self.beta
                * self.hg(cos_theta)
                * (-self.beta * (rl + s)).exp()
                / rl2;
            let (sn, cs) = (self.k_path * (rl + s)).sin_cos();
            re += f * cs;
            im += f * sn;
        }
        let k = h / 3.0;
        Phasor {
            re: re * k,
            im: im * k,
        }
    }
}

/// The fog-only phasor along the unit camera ray `ray` from `scatter_start_mm` to `s_end_m`
/// metres, without objects (no shadowing). Used to study saturation (Eq. 5.4–5.5).
pub fn scatter_along_ray(cfg: &TofSimConfig, ray: impl Into<V3>, s_end_m: f64) -> Result<Phasor> {
    cfg.validate()?;
    let ray = ray.into();
    let n = ray.norm();
    if !n.is_finite() || n <= 0.0 {
        return Err(MurkError::invalid(
            "ray",
            "must be a finite non-zero vector",
        ));
    }
    if !s_end_m.is_finite() || s_end_m < 0.0 {
        return Err(MurkError::invalid(
            "s_end_m",
            format!("must be finite and ≥ 0, got {s_end_m}"),
        ));
    }
    let scene = Scene {
        wall_z_m: f64::INFINITY,
        wall_albedo: 0.0,
        objects: Vec::new(),
    };
    let model = Model::new(cfg, &scene, cfg.effective_beta_per_mm());
    Ok(model.scatter(ray * (1.0 / n), s_end_m, false))
}

/// Per-pixel result, laid out so one allocation holds the whole frame.
#[derive(Clone, Copy, Default)]
struct PixelOut {
    amplitude: f32,
    phase: f32,
    amplitude_clear: f32,
    phase_clear: f32,
    scatter_amplitude: f32,
    scatter_phase: f32,
    range: f32,
    z: f32,
    mask: f32,
    object: f32,
}

/// Standard normal pair by Box–Muller (rand 0.9 has no normal distribution without rand_distr).
fn gaussian_pair(rng: &mut ChaCha8Rng) -> (f64, f64) {
    let u1: f64 = 1.0 - rng.random::<f64>(); // (0, 1]: ln is finite
    let u2: f64 = rng.random();
    let r = (-2.0 * u1.ln()).sqrt();
    let (s, c) = (2.0 * PI * u2).sin_cos();
    (r * c, r * s)
}

/// Renders a foggy CW-ToF frame with ground truth; see the module docs for the model.
///
/// The scene is drawn from `cfg.seed`; the same configuration always gives the identical frame.
pub fn simulate_tof(cfg: &TofSimConfig, monitor: &Monitor) -> Result<TofSimFrame> {
    cfg.validate()?;
    let k = cfg.intrinsics();
    // Stream 0 of the seed lays out the scene; rows' noise uses streams 1 + y.
    let mut scene_rng = ChaCha8Rng::seed_from_u64(cfg.seed);
    let scene = Scene::generate_layout(cfg.layout, &mut scene_rng, &k, cfg.width, cfg.height);
    render_tof(cfg, scene, 0, monitor)
}

/// Renders `scene` as `cfg`'s camera sees it in `cfg`'s fog; row `y`'s noise comes from stream
/// `noise_streams + 1 + y` of `cfg.seed`.
pub(crate) fn render_tof(
    cfg: &TofSimConfig,
    scene: Scene,
    noise_streams: u64,
    monitor: &Monitor,
) -> Result<TofSimFrame> {
    cfg.validate()?;
    monitor.checkpoint()?;
    let (w, h) = (cfg.width, cfg.height);
    let k = cfg.intrinsics();
    let beta_mm = cfg.effective_beta_per_mm();
    let model = Model::new(cfg, &scene, beta_mm);

    let mut out = vec![PixelOut::default(); w * h];
    let cancelled = AtomicBool::new(false);
    let rows_done = AtomicUsize::new(0);
    let report_every = (h / 50).max(1);
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        if cancelled.load(Ordering::Relaxed) || monitor.is_cancelled() {
            cancelled.store(true, Ordering::Relaxed);
            return;
        }
        let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
        rng.set_stream(noise_streams.wrapping_add(1 + y as u64));
        for (x, px) in row.iter_mut().enumerate() {
            let d = k.ray(x as f64, y as f64);
            *px = render_pixel(&model, cfg, d, &mut rng);
        }
        let done = rows_done.fetch_add(1, Ordering::Relaxed) + 1;
        if done.is_multiple_of(report_every) {
            monitor.progress("simulate_tof", done as f32 / h as f32);
        }
    });
    if cancelled.load(Ordering::Relaxed) {
        return Err(MurkError::Cancelled);
    }
    monitor.checkpoint()?;

    let img = |f: fn(&PixelOut) -> f32| -> Result<ImageF32> {
        ImageF32::from_vec(w, h, 1, out.iter().map(f).collect())
    };
    let frame = TofSimFrame {
        config: cfg.clone(),
        intrinsics: k,
        amplitude: img(|p| p.amplitude)?,
        phase: img(|p| p.phase)?,
        amplitude_clear: img(|p| p.amplitude_clear)?,
        phase_clear: img(|p| p.phase_clear)?,
        scatter_amplitude: img(|p| p.scatter_amplitude)?,
        scatter_phase: img(|p| p.scatter_phase)?,
        gt_range_m: img(|p| p.range)?,
        gt_z_depth_m: img(|p| p.z)?,
        gt_mask: img(|p| p.mask)?,
        gt_object_mask: img(|p| p.object)?,
        scene,
    };
    monitor.progress("simulate_tof", 1.0);
    Ok(frame)
}

/// Phase in `[0, 2π)` after rounding to f32 (which can round 2π − ε up to 2π).
fn phase_f32(p: Phasor) -> f32 {
    let v = p.phase() as f32;
    if v >= std::f32::consts::TAU {
        0.0
    } else {
        v
    }
}

fn render_pixel(model: &Model<'_>, cfg: &TofSimConfig, d: V3, rng: &mut ChaCha8Rng) -> PixelOut {
    let (direct_fog, direct_clear, scatter, range, z, mask) = match model.scene.cast(d) {
        Some(hit) => {
            let p = d * hit.t;
            let shadowed = model.scene.occluded(p, model.light);
            let fog = model.direct(p, hit.normal, hit.albedo, hit.t, model.beta, shadowed);
            let clear = model.direct(p, hit.normal, hit.albedo, hit.t, 0.0, shadowed);
            let sc = model.scatter(d, hit.t, true);
            let mask = if hit.is_object { 1.0 } else { 0.0 };
            (fog, clear, sc, hit.t, hit.t * d[2], mask)
        }
        // Only reachable for rays parallel to the wall; no surface, fog to a far horizon.
        None => (
            Phasor::default(),
            Phasor::default(),
            model.scatter(d, 100.0, true),
            f64::INFINITY,
            f64::INFINITY,
            0.0,
        ),
    };
    let clean = direct_fog + scatter;
    let sigma = cfg.noise_sigma(clean.amplitude());
    // Always draw, so the noise of a pixel does not depend on σ being zero elsewhere.
    let (n_re, n_im) = gaussian_pair(rng);
    let noisy = Phasor {
        re: clean.re + sigma * n_re,
        im: clean.im + sigma * n_im,
    };
    PixelOut {
        amplitude: noisy.amplitude() as f32,
        phase: phase_f32(noisy),
        amplitude_clear: direct_clear.amplitude() as f32,
        phase_clear: phase_f32(direct_clear),
        scatter_amplitude: scatter.amplitude() as f32,
        scatter_phase: phase_f32(scatter),
        range: range as f32,
        z: z as f32,
        // Measurable: lit well enough in clear air to stand out of the read noise.
        mask: if mask > 0.5 && direct_clear.amplitude() > 3.0 * cfg.noise_read.max(1e-9) {
            1.0
        } else {
            0.0
        },
        object: mask,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small(preset: FogPreset, seed: u64) -> TofSimConfig {
        TofSimConfig {
            preset,
            seed,
            ..TofSimConfig::with_size(128, 106)
        }
    }

    fn range_from_phase(phi: f32, f_hz: f64) -> f64 {
        SPEED_OF_LIGHT_M_PER_S * f64::from(phi) / (4.0 * PI * f_hz)
    }

    /// The noise the simulator draws is the model murk fits (`tof::noise_model`): independent
    /// shot and read noise, σ² = a²·|s| + b². Fitted back from a frame's second differences,
    /// both terms come out near the configured ones, and σ at a dark and at a bright level
    /// within 15 %.
    #[test]
    fn frame_noise_is_shot_plus_read_variance() {
        let cfg = small(FogPreset::Medium, 2);
        let f = simulate_tof(&cfg, &Monitor::noop()).unwrap();
        let (amp, ph) = (f.amplitude.data(), f.phase.data());
        let (re, im): (Vec<f32>, Vec<f32>) = amp
            .iter()
            .zip(ph)
            .map(|(&a, &p)| (a * p.cos(), a * p.sin()))
            .unzip();
        let fit = crate::tof::noise_model::NoiseModel::fit(&re, &im, amp, cfg.width).unwrap();
        eprintln!(
            "fitted {fit:?}; configured read variance {:.3}, shot gain {:.4}",
            cfg.noise_read.powi(2),
            cfg.noise_shot.powi(2)
        );
        // Adding standard deviations instead, (a√s + b)², would put a 2ab√s cross term into
        // the fit and nearly double the shot gain at these brightnesses.
        let (read, shot) = (cfg.noise_read.powi(2), cfg.noise_shot.powi(2));
        assert!((fit.read_variance / read - 1.0).abs() < 0.2, "{fit:?}");
        assert!((fit.shot_gain / shot - 1.0).abs() < 0.2, "{fit:?}");
        for level in [2.0, 50.0] {
            let (got, want) = (fit.sigma(level), cfg.noise_sigma(level));
            assert!(
                (got / want - 1.0).abs() < 0.15,
                "σ({level}): fitted {got}, drawn {want}"
            );
        }
        let want = cfg.noise_sigma(0.0);
        assert!((want - cfg.noise_read).abs() < 1e-12);
        let (a, b) = (cfg.noise_shot, cfg.noise_read);
        assert!((cfg.noise_sigma(100.0).powi(2) - (a * a * 100.0 + b * b)).abs() < 1e-9);
    }

    #[test]
    fn presets_parse_and_display() {
        for p in FogPreset::ALL {
            assert_eq!(p.to_string().parse::<FogPreset>().unwrap(), p);
        }
        assert_eq!(" Thick ".parse::<FogPreset>().unwrap(), FogPreset::Thick);
        assert!("soup".parse::<FogPreset>().is_err());
        let json = serde_json::to_string(&TofSimConfig::default()).unwrap();
        assert!(json.contains("\"medium\""), "{json}");
        let back: TofSimConfig = serde_json::from_str(&json).unwrap();
        assert_eq!(back, TofSimConfig::default());
    }

    #[test]
    fn validation_names_fields() {
        let field = |c: TofSimConfig| match simulate_tof(&c, &Monitor::noop()) {
            Err(MurkError::InvalidArgument { field, .. }) => field,
            other => panic!("expected invalid, got {:?}", other.map(|_| ())),
        };
        let d = TofSimConfig::with_size(32, 24);
        assert_eq!(
            field(TofSimConfig {
                width: 100_000,
                ..d.clone()
            }),
            "width"
        );
        assert_eq!(
            field(TofSimConfig {
                width: 8192,
                height: 8192,
                ..d.clone()
            }),
            "width"
        );
        assert_eq!(
            field(TofSimConfig {
                beta_per_mm: Some(-1.0),
                ..d.clone()
            }),
            "beta_per_mm"
        );
        assert_eq!(
            field(TofSimConfig {
                hg_g: 1.0,
                ..d.clone()
            }),
            "hg_g"
        );
        assert_eq!(
            field(TofSimConfig {
                modulation_frequency_hz: f64::NAN,
                ..d.clone()
            }),
            "modulation_frequency_hz"
        );
        assert_eq!(field(TofSimConfig { fx: 0.0, ..d }), "fx");
    }

    #[test]
    fn cancellation_is_honoured() {
        let m = Monitor::noop();
        m.cancel();
        assert_eq!(
            simulate_tof(&small(FogPreset::Medium, 1), &m).map(|_| ()),
            Err(MurkError::Cancelled)
        );
    }

    #[test]
    fn same_seed_gives_identical_frame() {
        let a = simulate_tof(&small(FogPreset::Medium, 7), &Monitor::noop()).unwrap();
        let b = simulate_tof(&small(FogPreset::Medium, 7), &Monitor::noop()).unwrap();
        assert_eq!(a, b);
        let c = simulate_tof(&small(FogPreset::Medium, 8), &Monitor::noop()).unwrap();
        assert_ne!(a.gt_range_m, c.gt_range_m);
        let mask_share = a.gt_mask.data().iter().sum::<f32>() / a.gt_mask.pixel_count() as f32;
        assert!(mask_share > 0.01 && mask_share < 0.4, "{mask_share}");
        for img in [&a.phase, &a.phase_clear, &a.scatter_phase] {
            assert!(img
                .data()
                .iter()
                .all(|p| (0.0..std::f32::consts::TAU).contains(p)));
        }
    }

    #[test]
    fn fog_free_limit_has_no_scatter_and_clear_range_matches_gt() {
        let cfg = TofSimConfig {
            beta_per_mm: Some(0.0),
            ..small(FogPreset::Medium, 3)
        };
        let f = simulate_tof(&cfg, &Monitor::noop()).unwrap();
        assert!(f.scatter_amplitude.data().iter().all(|&a| a == 0.0));
        let half_offset = cfg.light_offset_mm * 1e-3 / 2.0;
        let mut checked = 0;
        for i in 0..f.gt_range_m.pixel_count() {
            if f.amplitude_clear.data()[i] <= 0.0 {
                continue; // outside the beam or in shadow: no signal, no phase
            }
            let r = range_from_phase(f.phase_clear.data()[i], cfg.modulation_frequency_hz);
            let gt = f64::from(f.gt_range_m.data()[i]);
            // Phase encodes (r_l + s)/2 and |r_l − s| ≤ |L|: the range is off by ≤ |L|/2.
            assert!(
                (r - gt).abs() <= half_offset + 1e-4,
                "pixel {i}: {r} vs {gt}"
            );
            checked += 1;
            // Without fog, the observed frame is the clear one plus noise.
            let a = f64::from(f.amplitude.data()[i]);
            let ac = f64::from(f.amplitude_clear.data()[i]);
            assert!((a - ac).abs() < 6.0 * cfg.noise_sigma(ac));
        }
        assert!(checked > f.gt_range_m.pixel_count() / 2);
    }

    /// Eq. 5.4: the scatter integral saturates, so the phasor of a ray to the background at 6 m is
    /// close to that of the same ray cut at 2 m.
    #[test]
    fn scatter_saturates_along_the_ray() {
        let cfg = TofSimConfig::default();
        let k = cfg.intrinsics();
        for preset in FogPreset::ALL {
            let cfg = TofSimConfig {
                preset,
                ..cfg.clone()
            };
            for (u, v) in [(255.5, 211.5), (100.0, 100.0), (450.0, 380.0)] {
                let d = k.ray(u, v);
                let s6 = scatter_along_ray(&cfg, d, 6.0).unwrap();
                let s2 = scatter_along_ray(&cfg, d, 2.0).unwrap();
                let s1 = scatter_along_ray(&cfg, d, 1.0).unwrap();
                let rel = |a: Phasor| {
                    Phasor {
                        re: a.re - s6.re,
                        im: a.im - s6.im,
                    }
                    .amplitude()
                        / s6.amplitude()
                };
                println!(
                    "{preset} pixel ({u}, {v}): |s(6m)| = {:.3} φ = {:.4} rad; cut at 2 m: \
                     |Δ|/|s| = {:.4}, Δφ = {:.4} rad; cut at 1 m: |Δ|/|s| = {:.4}, Δφ = {:.4} rad",
                    s6.amplitude(),
                    s6.phase(),
                    rel(s2),
                    s6.phase() - s2.phase(),
                    rel(s1),
                    s6.phase() - s1.phase(),
                );
                assert!(s6.amplitude() > 0.0);
                assert!(rel(s2) < 0.1, "{preset} ({u},{v}): {}", rel(s2));
            }
        }
    }

    /// With the light on the image's horizontal axis, rays mirrored about the principal row see
    /// the same scatter (the reference's global symmetrical prior, Fig. 5.5).
    #[test]
    fn scatter_is_symmetric_about_the_principal_row() {
        let cfg = TofSimConfig::default();
        let k = cfg.intrinsics();
        for (u, v) in [(10.0, 10.0), (300.0, 50.0), (500.0, 400.0)] {
            let a = scatter_along_ray(&cfg, k.ray(u, v), 6.0).unwrap();
            let b = scatter_along_ray(&cfg, k.ray(u, 2.0 * cfg.cy - v), 6.0).unwrap();
            let d = Phasor {
                re: a.re - b.re,
                im: a.im - b.im,
            };
            assert!(
                d.amplitude() <= 1e-9 * a.amplitude().max(1e-9),
                "({u}, {v})"
            );
        }
    }

    #[test]
    fn doubling_quadrature_samples_changes_scatter_below_0_1_percent() {
        let base = TofSimConfig {
            preset: FogPreset::Thick,
            ..small(FogPreset::Thick, 5)
        };
        let fine = TofSimConfig {
            samples_per_efold: base.samples_per_efold * 2,
            ..base.clone()
        };
        let a = simulate_tof(&base, &Monitor::noop()).unwrap();
        let b = simulate_tof(&fine, &Monitor::noop()).unwrap();
        let max_amp = a
            .scatter_amplitude
            .data()
            .iter()
            .fold(0f32, |m, &x| m.max(x));
        let mut worst = 0f64;
        for i in 0..a.scatter_amplitude.pixel_count() {
            let pa = Phasor::from_polar(
                a.scatter_amplitude.data()[i].into(),
                a.scatter_phase.data()[i].into(),
            );
            let pb = Phasor::from_polar(
                b.scatter_amplitude.data()[i].into(),
                b.scatter_phase.data()[i].into(),
            );
            if pa.amplitude() < 1e-3 * f64::from(max_amp) {
                continue; // corners outside the beam: relative change is meaningless
            }
            let d = Phasor {
                re: pa.re - pb.re,
                im: pa.im - pb.im,
            };
            worst = worst.max(d.amplitude() / pa.amplitude());
        }
        println!("worst relative scatter change on doubling the samples: {worst:.2e}");
        assert!(worst < 1e-3, "{worst}");
    }

    /// The raw (uncorrected) range in fog is biased towards the camera by the scatter phasor;
    /// report the size of that error per preset. Not tuned: the assertion only checks it is real.
    #[test]
    fn raw_foggy_range_error_on_objects() {
        for preset in FogPreset::ALL {
            let mut errs = Vec::new();
            for seed in 0..3 {
                let cfg = small(preset, seed);
                let f = simulate_tof(&cfg, &Monitor::noop()).unwrap();
                for i in 0..f.gt_mask.pixel_count() {
                    if f.gt_mask.data()[i] > 0.5 && f.amplitude_clear.data()[i] > 0.0 {
                        let r = range_from_phase(f.phase.data()[i], cfg.modulation_frequency_hz);
                        let rc =
                            range_from_phase(f.phase_clear.data()[i], cfg.modulation_frequency_hz);
                        errs.push(((r - rc).abs(), r - f64::from(f.gt_range_m.data()[i])));
                    }
                }
            }
            let n = errs.len() as f64;
            let mae = errs.iter().map(|e| e.0).sum::<f64>() / n;
            let bias = errs.iter().map(|e| e.1).sum::<f64>() / n;
            let mut sorted: Vec<f64> = errs.iter().map(|e| e.0).collect();
            sorted.sort_by(f64::total_cmp);
            println!(
                "{preset}: raw range error vs clear on {} object px: mean {:.3} m, median {:.3} m, \
                 p90 {:.3} m; mean (raw − gt) {:.3} m",
                errs.len(),
                mae,
                sorted[sorted.len() / 2],
                sorted[sorted.len() * 9 / 10],
                bias
            );
            if preset == FogPreset::Medium {
                assert!(mae > 0.03, "medium fog raw error only {mae} m");
            }
        }
    }
}
