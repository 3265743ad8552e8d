//! Inputs, parameters and outputs of ToF depth in fog (reference Ch. 5, Algorithm 2).
//! Defaults are the reference's (§5.4.1).

use crate::camera::Intrinsics;
use crate::error::{MurkError, Result};
use crate::image::ImageF32;

/// Speed of light in vacuum, m/s (Eq. 5.2).
pub const SPEED_OF_LIGHT_M_PER_S: f64 = 299_792_458.0;

/// Hard limits on per-request parameters, so absurd values are rejected instead of running forever.
pub const MAX_ITERATIONS: usize = 10_000;

/// Default cap on the fine IRLS iterations: 150, three times the reference's 50. Algorithm 2
/// repeats the fine level "until converged", and a level stops as soon as its weights settle,
/// which every frame of the 54-frame survey but one does within 50 (docs/accuracy.md). The one,
/// cluttered thick seed 1 at 512 × 424, peels a band of the panel that the estimate first bent
/// over off its edges a few pixels per iteration and converges after about 105: 24.7 mm and
/// IoU 0.999 there, against 40.0 mm and 0.980 when cut off at 50 (3.6 s instead of 2.0 s).
pub const DEFAULT_FINE_ITERATIONS: usize = 150;
/// Largest patch grid per axis for the local quadratic prior.
pub const MAX_PATCHES_PER_AXIS: usize = 64;

/// Image size (the larger side, pixels) at which the γ′ of [`IrlsChannelParams`] are defined:
/// the reference's Kinect v2 frames are 512 × 424.
pub const REFERENCE_SIZE_PX: f64 = 512.0;

/// Default of `TofParams::convergence_tolerance`, the IRLS levels' convergence test
/// (`tof::irls::IrlsConfig::weight_tolerance`): a level stops once no weight moves by more.
pub const DEFAULT_WEIGHT_TOLERANCE: f64 = 1e-3;

/// IRLS settings for one image (amplitude or phase): Eq. 5.12 weights and Tukey's `c` (Eq. 5.15).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IrlsChannelParams {
    /// `[γ′₁, γ′₂, γ′₃]`: local quadratic prior, vertical-symmetry prior, smoothness (Eq. 5.12),
    /// as defined at the reference resolution ([`REFERENCE_SIZE_PX`] on the larger side).
    ///
    /// The solver uses [`IrlsChannelParams::effective_gamma`]: γ′₃ is scaled by
    /// (max(w, h)/512)² so the prior means the same on any image size. Reason: for a smooth field
    /// seen at pixel spacing h, the data term Σ w(x − x̃)² has one term per pixel (∝ h⁻²), while
    /// the smoothness Σ(Δx)² has one term per edge, each ∝ h² (a difference across one pixel):
    /// their ratio grows as h². Unscaled, γ′₃ = 50 at 128 × 106 would smooth 16× harder than the
    /// reference, enough to let the scatter estimate run away under large objects.
    /// γ′₁ and γ′₂ need no scaling: the quadratic-fit residual x − Ua (with patch-normalised
    /// coordinates and a fixed patch grid) and the mirror residual Fx − x are per-pixel
    /// differences of values, not of neighbours, so both sums scale with the pixel count exactly
    /// like the data term.
    pub gamma: [f64; 3],
    /// Tukey tuning constant at the coarse (patch-wise) level, Eq. 5.16.
    pub c_coarse: f64,
    /// Tukey tuning constant at the fine (pixel-wise) level, Eq. 5.11.
    pub c_fine: f64,
}

impl IrlsChannelParams {
    /// Reference defaults for the amplitude image: γ′ = [0.1, 0.1, 10], c = 4 / 7.
    pub const AMPLITUDE: Self = Self {
        gamma: [0.1, 0.1, 10.0],
        c_coarse: 4.0,
        c_fine: 7.0,
    };
    /// The phasor's real and imaginary parts: the amplitude's γ′ (both parts are in amplitude
    /// units) and c = 4 / 8. Tukey's c applies to the residual's norm over the two parts, which
    /// for Gaussian noise is Rayleigh-distributed: a pixel is flagged at weight 0.5, i.e. beyond
    /// 0.54c noise σ, and c = 8 keeps the pure-noise false-alarm rate at the amplitude channel's
    /// (≈ 1.5e-4 per pixel; c = 7 would give 7.6e-4).
    pub const PHASOR: Self = Self {
        gamma: [0.1, 0.1, 10.0],
        c_coarse: 4.0,
        c_fine: 8.0,
    };
    /// Reference defaults for the phase image: γ′ = [0.01, 0.1, 50], c = 2 / 3.
    pub const PHASE: Self = Self {
        gamma: [0.01, 0.1, 50.0],
        c_coarse: 2.0,
        c_fine: 3.0,
    };

    /// `[γ′₁, γ′₂, γ′₃·(max(w, h)/512)²]`: the weights applied to a `width × height` image (see
    /// [`IrlsChannelParams::gamma`]).
    pub fn effective_gamma(&self, width: usize, height: usize) -> [f64; 3] {
        let s = width.max(height) as f64 / REFERENCE_SIZE_PX;
        [self.gamma[0], self.gamma[1], self.gamma[2] * s * s]
    }

    fn validate(&self) -> Result<()> {
        for (i, g) in self.gamma.iter().enumerate() {
            if !g.is_finite() || *g < 0.0 || *g > 1e6 {
                return Err(MurkError::invalid(
                    format!("gamma[{i}]"),
                    format!("must be finite and in [0, 1e6], got {g}"),
                ));
            }
        }
        for (name, c) in [("c_coarse", self.c_coarse), ("c_fine", self.c_fine)] {
            if !c.is_finite() || c <= 0.0 || c > 1e3 {
                return Err(MurkError::invalid(
                    name,
                    format!("must be finite and in (0, 1e3], got {c}"),
                ));
            }
        }
        Ok(())
    }
}

/// Edge-preserving pre-filter applied to amplitude and phase before estimation (§5.4.1).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BilateralParams {
    /// Window radius in pixels (window is `(2r+1)²`).
    pub radius: usize,
    /// Spatial Gaussian σ in pixels.
    pub sigma_space_px: f32,
    /// Range Gaussian σ relative to the image's robust pixel-noise σ (1.4826·MAD of horizontal
    /// neighbour differences / √2, see `bilateral::robust_noise_sigma`), dimensionless: the
    /// filter averages differences of noise size and keeps object edges.
    pub sigma_range_rel: f32,
}

impl Default for BilateralParams {
    fn default() -> Self {
        Self {
            radius: 2,
            sigma_space_px: 1.5,
            sigma_range_rel: 0.5,
        }
    }
}

/// All tunables of the ToF method.
#[derive(Clone, Debug, PartialEq)]
pub struct TofParams {
    /// Modulation frequency of the CW-ToF camera, Hz (> 0).
    pub modulation_frequency_hz: f64,
    /// Patch grid for the local quadratic prior (Eq. 5.10), columns × rows; reference 4 × 4.
    pub patches_x: usize,
    /// See `patches_x`.
    pub patches_y: usize,
    /// Row (pixels, may be fractional) about which the vertical flip `F` mirrors the image.
    /// `None`: the principal point's row when intrinsics are given, else the image centre.
    pub symmetry_row: Option<f64>,
    /// Amplitude-image IRLS settings.
    pub amplitude: IrlsChannelParams,
    /// Phase-image IRLS settings.
    pub phase: IrlsChannelParams,
    /// Cap on coarse (patch-wise) IRLS iterations; reference 5. Algorithm 2 repeats "until
    /// converged": a level stops earlier once its weights have settled (no weight moving by
    /// more than 1e-3 and no pixel crossing `mask_threshold`, two iterations in a row).
    pub coarse_iterations: usize,
    /// Cap on fine (pixel-wise) IRLS iterations; reference 50, default
    /// [`DEFAULT_FINE_ITERATIONS`]. Stops early like the coarse level.
    pub fine_iterations: usize,
    /// Pre-filter; `None` disables it.
    pub bilateral: Option<BilateralParams>,
    /// A pixel is object (outlier) when its final IRLS weight is below this, in (0, 1).
    pub mask_threshold: f32,
    /// Position of the camera's light source in the camera frame, metres (e.g. `[0.06, 0, 0]`
    /// for an emitter 6 cm to the right of the lens). The phase measures the optical path
    /// camera ← surface ← light, so without it range is taken as half the path, which is off
    /// by up to half the baseline. Requires intrinsics (the ray direction enters the
    /// correction).
    pub light_position_m: Option<[f64; 3]>,
    /// IRLS convergence test ("repeat … until converged", Algorithm 2): a level stops early once
    /// no weight moves by more than this for two iterations and the mask is unchanged, so the
    /// iteration counts are caps. 0 disables early stopping (always run the caps).
    pub convergence_tolerance: f64,
    /// How the patch quadratics of Eq. 5.12 are solved for together with x.
    pub prior_coupling: PriorCoupling,
    /// Which images Algorithm 2 runs on.
    pub channels: ScatterChannels,
    /// IRLS settings of the phasor's real and imaginary parts ([`ScatterChannels::Phasor`]).
    pub phasor: IrlsChannelParams,
    /// Coarse-level weight blocks per quadratic patch along each axis (1..=16); the reference's
    /// Eq. 5.16 uses the patches themselves (1). Default 4: a 4 × 4 grid of patches gives
    /// 16 × 16 blocks, so a rejected block discards the object and little background beside it.
    pub coarse_subdivision: usize,
    /// Quantile of the coarse blocks' RMS residuals taken as the robust scale σ₂, in (0, 1).
    /// The reference's median (0.5) assumes most blocks hold no object; a large near object
    /// touching more than half of them (and the quadratic misfit it causes in the first x-step)
    /// lifted σ₂ 30× above the noise on a simulated cluttered frame, after which the level
    /// accepted the object. Default 0.25: a quarter of the blocks must be background.
    pub coarse_quantile: f64,
}

/// Which images the scattering component is estimated on.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ScatterChannels {
    /// The reference's §5.3.4: amplitude and phase separately, each with its own IRLS weights;
    /// object = outlier in both.
    AmplitudePhase,
    /// The phasor's real and imaginary parts, two smooth fields with one shared set of IRLS
    /// weights from the complex residual |x̃ − x| (see [`super::irls::run_irls_vector`]). An
    /// object is a pixel whose phasor departs from the scatter phasor in any direction, so a
    /// near object whose phase is close to the scatter's, or whose amplitude is, is still an
    /// outlier, and noise is isotropic (the phase's noise grows as 1/amplitude in dark
    /// corners). No phase wrapping either.
    #[default]
    Phasor,
}

/// How the x- and a-steps of Eq. 5.12 are solved.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum PriorCoupling {
    /// Minimise over x and the quadratics together (the a-step eliminated; see
    /// `wls::XStepSystem::with_joint_prior`). Under a large object the scatter estimate is the
    /// background's quadratics and smoothness carried across it, whatever the starting point.
    #[default]
    Joint,
    /// The reference's alternation of x-step and a-step, with the a-step fitting the patch
    /// quadratics with the IRLS weights (murk ≤ 0.x; kept to compare). Under an object covering
    /// whole patches x only diffuses slowly away from Algorithm 2's start, the observation itself,
    /// so the scatter there stays close to the object's brightness.
    Alternating,
}

impl Default for TofParams {
    fn default() -> Self {
        Self {
            modulation_frequency_hz: 16e6,
            patches_x: 4,
            patches_y: 4,
            symmetry_row: None,
            amplitude: IrlsChannelParams::AMPLITUDE,
            phase: IrlsChannelParams::PHASE,
            coarse_iterations: 5,
            fine_iterations: DEFAULT_FINE_ITERATIONS,
            bilateral: Some(BilateralParams::default()),
            mask_threshold: 0.5,
            light_position_m: None,
            convergence_tolerance: DEFAULT_WEIGHT_TOLERANCE,
            prior_coupling: PriorCoupling::Joint,
            channels: ScatterChannels::Phasor,
            phasor: IrlsChannelParams::PHASOR,
            coarse_subdivision: 4,
            coarse_quantile: 0.25,
        }
    }
}

impl TofParams {
    /// Checks every parameter against its documented range; the error names the field.
    pub fn validate(&self, width: usize, height: usize) -> Result<()> {
        let f = self.modulation_frequency_hz;
        if !f.is_finite() || !(MIN_MODULATION_HZ..=MAX_MODULATION_HZ).contains(&f) {
            return Err(MurkError::invalid(
                "modulation_frequency_hz",
                format!(
                    "must be in [{MIN_MODULATION_HZ:e}, {MAX_MODULATION_HZ:e}] Hz (CW-ToF cameras \
                     modulate at 10-200 MHz, e.g. 16e6), got {f}{}",
                    if f > 0.0 && f < 1e4 {
                        " (MHz given for Hz?)"
                    } else {
                        ""
                    }
                ),
            ));
        }
        for (name, p, dim) in [
            ("patches_x", self.patches_x, width),
            ("patches_y", self.patches_y, height),
        ] {
            if p == 0 || p > MAX_PATCHES_PER_AXIS {
                return Err(MurkError::invalid(
                    name,
                    format!("must be in 1..={MAX_PATCHES_PER_AXIS}, got {p}"),
                ));
            }
            // A quadratic has 6 coefficients: each patch needs at least 3 pixels per axis.
            if dim / p < 3 {
                return Err(MurkError::invalid(
                    name,
                    format!(
                        "{p} patches leave fewer than 3 pixels per patch along an axis of {dim}"
                    ),
                ));
            }
        }
        if let Some(r) = self.symmetry_row {
            if !r.is_finite() || r < 0.0 || r > (height as f64 - 1.0) {
                return Err(MurkError::invalid(
                    "symmetry_row",
                    format!(
                        "must be a row inside the image [0, {}], got {r}",
                        height - 1
                    ),
                ));
            }
        }
        self.amplitude
            .validate()
            .map_err(|e| e.within("amplitude"))?;
        self.phase.validate().map_err(|e| e.within("phase"))?;
        self.phasor.validate().map_err(|e| e.within("phasor"))?;
        for (name, n) in [
            ("coarse_iterations", self.coarse_iterations),
            ("fine_iterations", self.fine_iterations),
        ] {
            if n > MAX_ITERATIONS {
                return Err(MurkError::invalid(
                    name,
                    format!("must be at most {MAX_ITERATIONS}, got {n}"),
                ));
            }
        }
        if let Some(b) = &self.bilateral {
            if b.radius > 16 {
                return Err(MurkError::invalid(
                    "bilateral.radius",
                    format!("must be at most 16, got {}", b.radius),
                ));
            }
            for (name, v) in [
                ("bilateral.sigma_space_px", b.sigma_space_px),
                ("bilateral.sigma_range_rel", b.sigma_range_rel),
            ] {
                // Below 1e-3 the Gaussian weights' 2σ² underflows towards 0 and the filter
                // divides 0 by 0; it would be the identity long before.
                if !v.is_finite() || !(1e-3..=1e3).contains(&v) {
                    return Err(MurkError::invalid(
                        name,
                        format!("must be in [1e-3, 1e3], got {v}"),
                    ));
                }
            }
        }
        if let Some(l) = self.light_position_m {
            if l.iter().any(|v| !v.is_finite()) || l.iter().map(|v| v * v).sum::<f64>() > 100.0 {
                return Err(MurkError::invalid(
                    "light_position_m",
                    format!("must be finite and within 10 m of the camera, got {l:?}"),
                ));
            }
        }
        let tol = self.convergence_tolerance;
        if !tol.is_finite() || !(0.0..=1.0).contains(&tol) {
            return Err(MurkError::invalid(
                "convergence_tolerance",
                format!("must be in [0, 1], got {tol}"),
            ));
        }
        if !(1..=16).contains(&self.coarse_subdivision) {
            return Err(MurkError::invalid(
                "coarse_subdivision",
                format!("must be in 1..=16, got {}", self.coarse_subdivision),
            ));
        }
        let q = self.coarse_quantile;
        if !q.is_finite() || q <= 0.0 || q >= 1.0 {
            return Err(MurkError::invalid(
                "coarse_quantile",
                format!("must be in (0, 1), got {q}"),
            ));
        }
        let t = self.mask_threshold;
        if !t.is_finite() || t <= 0.0 || t >= 1.0 {
            return Err(MurkError::invalid(
                "mask_threshold",
                format!("must be in (0, 1), got {t}"),
            ));
        }
        Ok(())
    }
}

/// Lowest modulation frequency accepted, Hz: below it the unambiguous range exceeds 1500 km, and
/// a value this small is a unit slip (16 for 16 MHz gave ranges of 9.4e6 m).
pub const MIN_MODULATION_HZ: f64 = 1e5;
/// Highest modulation frequency accepted, Hz.
pub const MAX_MODULATION_HZ: f64 = 1e10;

impl TofParams {
    /// [`TofParams::validate`] plus the checks that need the input (image size, intrinsics).
    pub fn validate_for(&self, input: &TofInput) -> Result<()> {
        let (w, h) = input.amplitude.dims();
        self.validate_for_frames(w, h, input.intrinsics.is_some())
    }

    /// [`TofParams::validate_for`] before any frame exists: for frames of `width × height`,
    /// with or without intrinsics (a stream's settings, checked once).
    pub fn validate_for_frames(&self, width: usize, height: usize, intrinsics: bool) -> Result<()> {
        self.validate(width, height)?;
        if self.light_position_m.is_some() && !intrinsics {
            return Err(MurkError::invalid(
                "light_position_m",
                "needs intrinsics: the range correction depends on each pixel's ray",
            ));
        }
        Ok(())
    }
}

/// How far outside [0, 2π) a phase sample may lie (radians): rounding and calibration offsets.
pub const PHASE_TOLERANCE_RAD: f32 = 0.01;

/// The range of the brightest amplitude the method computes with, sensor units. Its solves
/// square and sum amplitudes in f32: on the simulated frames a brightest pixel near 1e23 (the
/// frame scaled by 1e20, or one pixel with a flipped exponent bit) broke the x-step, and one
/// near 1e-12 changed the mask, though the method is otherwise indifferent to the scale.
/// Cameras report 16-bit counts or normalised floats, far inside.
pub const AMPLITUDE_RANGE: (f32, f32) = (1e-6, 1e15);

/// One CW-ToF frame: amplitude (arbitrary linear units) and phase (radians, wrapped to [0, 2π)).
#[derive(Clone, Debug)]
pub struct TofInput {
    /// Amplitude image α̃, one channel.
    pub amplitude: ImageF32,
    /// Phase image φ̃ in radians, one channel, same size as `amplitude`.
    pub phase: ImageF32,
    /// Intrinsics; when given, z-depth is produced too and the default symmetry row is `cy`.
    pub intrinsics: Option<Intrinsics>,
}

impl TofInput {
    /// Checks sizes, channel counts and finiteness; errors name `amplitude`, `phase`, `intrinsics`.
    pub fn validate(&self) -> Result<()> {
        self.amplitude
            .ensure_channels(1)
            .and_then(|_| self.amplitude.ensure_finite())
            .map_err(|e| e.within("amplitude"))?;
        self.phase
            .ensure_channels(1)
            .and_then(|_| self.phase.ensure_finite())
            .map_err(|e| e.within("phase"))?;
        // Radians wrapped to [0, 2π): degrees (up to 360) would otherwise be taken as radians
        // and give plausible-looking wrong depths.
        let (lo, hi) = self
            .phase
            .data()
            .iter()
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &v| {
                (lo.min(v), hi.max(v))
            });
        let tau = std::f32::consts::TAU;
        if lo < -PHASE_TOLERANCE_RAD || hi > tau + PHASE_TOLERANCE_RAD {
            return Err(MurkError::invalid(
                "phase",
                format!(
                    "must be radians in [0, 2pi), got values in [{lo}, {hi}]{}",
                    if hi > 7.0 {
                        " (degrees? scale by pi/180, e.g. with Image.value_scale)"
                    } else {
                        ""
                    }
                ),
            ));
        }
        let brightest = self
            .amplitude
            .data()
            .iter()
            .fold(0.0f32, |m, v| m.max(v.abs()));
        let (lo, hi) = AMPLITUDE_RANGE;
        if !(lo..=hi).contains(&brightest) {
            return Err(MurkError::invalid(
                "amplitude",
                format!(
                    "the brightest pixel is {brightest:e}, outside the {lo:e} to {hi:e} sensor \
                     units the method computes with: rescale the amplitudes (e.g. with \
                     Image.value_scale){}",
                    if brightest == 0.0 {
                        "; an all-zero frame has no return to measure"
                    } else {
                        ""
                    }
                ),
            ));
        }
        if self.amplitude.dims() != self.phase.dims() {
            return Err(MurkError::invalid(
                "phase",
                format!(
                    "size {}x{} differs from amplitude {}x{}",
                    self.phase.width(),
                    self.phase.height(),
                    self.amplitude.width(),
                    self.amplitude.height()
                ),
            ));
        }
        if let Some(k) = &self.intrinsics {
            k.validate().map_err(|e| e.within("intrinsics"))?;
        }
        Ok(())
    }
}

/// [`TofOutput::mask`] of an object pixel.
pub const MASK_OBJECT: f32 = 1.0;

/// [`TofOutput::mask`] of a pixel beside an object that is neither clearly object nor clearly
/// background (see [`crate::tof::ambiguous`]): 127/255 ≈ 0.498. An 8-bit step, so that the
/// 8-bit encodings (PNG results, `mono8` bag images) carry it exactly, and below 0.5, so that
/// `mask > 0.5` still means "object" and `mask > 0` means "object or uncertain".
pub const MASK_UNCERTAIN: f32 = 127.0 / 255.0;

/// [`TofOutput::mask`] of a background pixel (scatter only).
pub const MASK_BACKGROUND: f32 = 0.0;

/// Everything the ToF method returns. All images are one-channel and input-sized.
#[derive(Clone, Debug)]
pub struct TofOutput {
    /// Corrected range along the viewing ray, metres (Eq. 5.2 on the direct phase, Eq. 5.9).
    pub range_m: ImageF32,
    /// Corrected z-depth, metres (only with intrinsics).
    pub z_depth_m: Option<ImageF32>,
    /// Range computed from the raw (foggy) phase, metres, for comparison.
    pub raw_range_m: ImageF32,
    /// z-depth from the raw phase, metres (only with intrinsics), for comparison.
    pub raw_z_depth_m: Option<ImageF32>,
    /// Standard deviation of `range_m`, metres: the frame's sensor noise (its shot + read noise
    /// model at the observed brightness) plus one noise σ of uncertainty in the scatter
    /// estimate (at the scatter's brightness), carried through the direct phasor's phase,
    /// σ_φ ≈ σ/|direct| (Eq. 5.8–5.9), and capped at a quarter of the ambiguity interval. Large
    /// where the direct return is weak against the noise, i.e. where the corrected range is no
    /// better than the raw one; threshold it together with `mask`.
    pub range_std_m: ImageF32,
    /// Object mask: 1 ([`MASK_OBJECT`]) where the IRLS marks an outlier (the phasor's residual
    /// by default; with `ScatterChannels::AmplitudePhase`, both the amplitude's and the
    /// phase's); 127/255 ≈ 0.498 ([`MASK_UNCERTAIN`]) beside an object where the scatter alone does not
    /// explain the observation well enough to call the pixel background, yet the evidence is
    /// too weak to call it object ([`crate::tof::ambiguous`]); else 0 ([`MASK_BACKGROUND`]).
    /// An uncertain pixel's range is the object hypothesis's, with the large `range_std_m` of
    /// its weak direct return: treat it as a possible obstacle, not as background.
    pub mask: ImageF32,
    /// Estimated scattering amplitude α_s.
    pub scatter_amplitude: ImageF32,
    /// Estimated scattering phase φ_s, radians.
    pub scatter_phase: ImageF32,
    /// Final IRLS weights of the amplitude image, in [0, 1] (the phasor's shared weights by
    /// default, then equal to `weight_phase`).
    pub weight_amplitude: ImageF32,
    /// Final IRLS weights of the phase image, in [0, 1].
    pub weight_phase: ImageF32,
    /// Direct amplitude α_d (Eq. 5.8).
    pub corrected_amplitude: ImageF32,
    /// Direct phase φ_d (Eq. 5.9), radians in [0, 2π).
    pub corrected_phase: ImageF32,
    /// Sentences for the caller: an IRLS whose fine level stopped at its iteration cap before
    /// converging. Empty when the estimate converged.
    pub warnings: Vec<String>,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn input(phase: f32) -> TofInput {
        TofInput {
            amplitude: ImageF32::filled(8, 6, 1, 100.0),
            phase: ImageF32::filled(8, 6, 1, phase),
            intrinsics: None,
        }
    }

    /// Unit slips are refused with the field named: MHz given for Hz, phase in degrees.
    #[test]
    fn unit_slips_are_refused_naming_the_field() {
        let mhz = TofParams {
            modulation_frequency_hz: 16.0,
            ..TofParams::default()
        };
        let err = mhz.validate(64, 48).unwrap_err();
        assert_eq!(err.field(), Some("modulation_frequency_hz"));
        assert!(err.to_string().contains("MHz given for Hz"), "{err}");
        assert!(TofParams::default().validate(64, 48).is_ok());

        let err = input(180.0).validate().unwrap_err();
        assert_eq!(err.field(), Some("phase"));
        assert!(err.to_string().contains("degrees"), "{err}");
        assert_eq!(input(-0.5).validate().unwrap_err().field(), Some("phase"));
        // The ends of [0, 2π) and a rounding step past them are fine.
        assert!(input(0.0).validate().is_ok());
        assert!(input(std::f32::consts::TAU + 0.005).validate().is_ok());
    }

    /// Finite amplitudes the solver cannot represent are the caller's field, not a numerical
    /// failure: a frame scaled by 1e20, one pixel with a flipped exponent bit, subnormals, zero.
    #[test]
    fn amplitudes_outside_the_computable_range_name_the_field() {
        let scaled = |s: f32| {
            let mut i = input(1.0);
            for v in i.amplitude.data_mut() {
                *v *= s;
            }
            i.validate()
        };
        for s in [1e20, 1e-45, 1e-40, 0.0] {
            let err = scaled(s).unwrap_err();
            assert_eq!(err.field(), Some("amplitude"), "{s:e}: {err}");
            assert!(err.to_string().contains("value_scale"), "{err}");
        }
        for s in [1e-8, 1.0, 1e12] {
            assert!(scaled(s).is_ok(), "{s:e}");
        }
        let mut flipped = input(1.0);
        flipped.amplitude.data_mut()[7] = 1e33;
        assert_eq!(flipped.validate().unwrap_err().field(), Some("amplitude"));
    }
}
