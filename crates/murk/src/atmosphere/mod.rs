//! Atmospheric scattering model (reference §2.3, Eq. 2.23; §3.2, Eq. 3.3 and 3.5):
//!
//! `I = J·t + A·(1 − t)`, `t = e^{−β z}`,
//!
//! with `I` the observed (hazy) image, `J` the latent clear image, `A` the airlight (an achromatic
//! scalar shared by every channel, as in the reference's MVS chapter), `β` the scattering
//! coefficient **per scene unit** and `z` the **z-depth** (distance along the optical axis, scene
//! units) — the reference applies the model with z-depth in its plane sweep (Eq. 3.5, 3.6), so murk
//! does everywhere for consistency. Pixel values are nominally in `[0, 1]`.
//!
//! Whole-image functions ([`haze`], [`dehaze`]) validate their inputs; the per-pixel helpers
//! ([`transmission`], [`haze_value`], [`dehaze_value`], [`inverse_transmission`]) are `#[inline]`
//! and unchecked so hot loops (the dehazing cost volume) can use them.

use crate::error::{MurkError, Result};
use crate::image::ImageF32;

/// Smallest transmission used when dehazing. Dividing by `t` amplifies noise by `1/t`, and
/// `t → 0` (large `β·z`) would produce infinities; the reference code adds `1e-6` to `t`, murk
/// instead clamps `t` to at least this value. For every `t ≫ 1e-6` the two agree to a relative
/// `1e-6`, and the clamp keeps `β = 0` (t = 1) an exact identity, which the cost-volume invariant
/// "β = 0 ⇒ dehazing volume = ordinary volume" relies on.
pub const MIN_TRANSMISSION: f32 = 1e-6;

/// Scattering parameters of the medium (Eq. 3.3).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AtmosphereParams {
    /// Airlight `A` (achromatic, same units as pixel values), in `(0, 1]`.
    pub airlight: f32,
    /// Scattering coefficient `β` per scene unit, finite and `≥ 0` (0 = clear air).
    pub beta: f32,
}

impl AtmosphereParams {
    /// Fails with a field-named `InvalidArgument` unless `A ∈ (0, 1]` and `β` is finite and `≥ 0`.
    pub fn validate(&self) -> Result<()> {
        let a = self.airlight;
        // `!(a > 0.0)` also rejects NaN.
        if !(a > 0.0 && a <= 1.0) {
            return Err(MurkError::invalid(
                "airlight",
                format!("airlight A must be in (0, 1], got {a}"),
            ));
        }
        let b = self.beta;
        if !b.is_finite() || b < 0.0 {
            return Err(MurkError::invalid(
                "beta",
                format!("scattering coefficient beta must be finite and >= 0, got {b}"),
            ));
        }
        Ok(())
    }

    /// Transmission `t = e^{−β z}` at z-depth `z` (scene units).
    #[inline]
    pub fn transmission(&self, z: f32) -> f32 {
        transmission(self.beta, z)
    }
}

/// Transmission `t = e^{−β z}` (Eq. 2.23) for `β` per scene unit and z-depth `z` in scene units.
#[inline]
pub fn transmission(beta: f32, z: f32) -> f32 {
    (-beta * z).exp()
}

/// Hazy value `J·t + A·(1 − t)` of one sample (Eq. 3.3).
#[inline]
pub fn haze_value(j: f32, t: f32, a: f32) -> f32 {
    j * t + a * (1.0 - t)
}

/// `1 / max(t, MIN_TRANSMISSION)`: the factor dehazing multiplies by. Exposed so hot loops can
/// hoist it out of the per-channel work.
#[inline]
pub fn inverse_transmission(t: f32) -> f32 {
    1.0 / t.max(MIN_TRANSMISSION)
}

/// Dehazed value of one sample, Eq. 3.5 `J = (I − A)/t + A`, written as `I·(1/t) + A·(1 − 1/t)`
/// so that `t = 1` returns `I` bit-exactly (the subtract-then-add form can move `I` by an ulp and
/// push a value of exactly 0 or 1 outside `[0, 1]`, which Eq. 3.7 would punish). `t` is clamped
/// to [`MIN_TRANSMISSION`].
#[inline]
pub fn dehaze_value(i: f32, t: f32, a: f32) -> f32 {
    let inv_t = inverse_transmission(t);
    i * inv_t + a * (1.0 - inv_t)
}

/// Checks the depth map shared by [`haze`] and [`dehaze`] against the image.
fn check_inputs(image: &ImageF32, depth_z: &ImageF32, a: f32, beta: f32) -> Result<()> {
    AtmosphereParams { airlight: a, beta }.validate()?;
    image.ensure_finite().map_err(|e| e.within("image"))?;
    depth_z
        .ensure_channels(1)
        .map_err(|e| e.within("depth_z"))?;
    if depth_z.dims() != image.dims() {
        return Err(MurkError::invalid(
            "depth_z",
            format!(
                "depth map is {}x{} but the image is {}x{}",
                depth_z.width(),
                depth_z.height(),
                image.width(),
                image.height()
            ),
        ));
    }
    if let Some(i) = depth_z
        .data()
        .iter()
        .position(|z| !z.is_finite() || *z < 0.0)
    {
        return Err(MurkError::invalid(
            "depth_z",
            format!(
                "z-depth must be finite and >= 0 (scene units), got {} at pixel ({}, {})",
                depth_z.data()[i],
                i % depth_z.width(),
                i / depth_z.width()
            ),
        ));
    }
    Ok(())
}

/// Applies the atmospheric scattering model (Eq. 2.23 / 3.3) to the clear image `j` (any number
/// of channels) given its per-pixel z-depth `depth_z` (one channel, same size, scene units),
/// airlight `a ∈ (0, 1]` and `beta ≥ 0` per scene unit.
///
/// Errors name `image`, `depth_z`, `airlight` or `beta`.
pub fn haze(j: &ImageF32, depth_z: &ImageF32, a: f32, beta: f32) -> Result<ImageF32> {
    check_inputs(j, depth_z, a, beta)?;
    let c = j.channels();
    let mut out = j.clone();
    for (px, &z) in out.data_mut().chunks_exact_mut(c).zip(depth_z.data()) {
        let t = transmission(beta, z);
        for v in px {
            *v = haze_value(*v, t, a);
        }
    }
    Ok(out)
}

/// Inverts the scattering model (Eq. 3.5): `J = (I − A)/t + A` per channel, with `t` clamped to
/// [`MIN_TRANSMISSION`]. The result is not clipped to `[0, 1]`: a value outside it is evidence of
/// a wrong depth or wrong `A, β` (Eq. 3.7 uses exactly that), so callers decide.
///
/// Errors name `image`, `depth_z`, `airlight` or `beta`.
pub fn dehaze(i: &ImageF32, depth_z: &ImageF32, a: f32, beta: f32) -> Result<ImageF32> {
    check_inputs(i, depth_z, a, beta)?;
    let c = i.channels();
    let mut out = i.clone();
    for (px, &z) in out.data_mut().chunks_exact_mut(c).zip(depth_z.data()) {
        let t = transmission(beta, z);
        for v in px {
            *v = dehaze_value(*v, t, a);
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    use crate::error::field_of;

    #[test]
    fn params_validation_names_fields() {
        let ok = AtmosphereParams {
            airlight: 0.8,
            beta: 0.5,
        };
        assert!(ok.validate().is_ok());
        assert!(AtmosphereParams {
            airlight: 1.0,
            beta: 0.0
        }
        .validate()
        .is_ok());
        for a in [0.0, -0.1, 1.01, f32::NAN, f32::INFINITY] {
            let e = AtmosphereParams { airlight: a, ..ok }
                .validate()
                .unwrap_err();
            assert_eq!(field_of(e), "airlight", "A = {a}");
        }
        for b in [-1e-3, f32::NAN, f32::INFINITY] {
            let e = AtmosphereParams { beta: b, ..ok }.validate().unwrap_err();
            assert_eq!(field_of(e), "beta", "beta = {b}");
        }
    }

    #[test]
    fn beta_zero_is_identity() {
        let j = ImageF32::from_vec(3, 2, 3, (0..18).map(|k| k as f32 / 17.0).collect()).unwrap();
        let z = ImageF32::from_fn(3, 2, |x, y| 1.0 + (x + 3 * y) as f32);
        assert_eq!(haze(&j, &z, 0.7, 0.0).unwrap(), j);
        assert_eq!(dehaze(&j, &z, 0.7, 0.0).unwrap(), j);
    }

    #[test]
    fn known_values() {
        // J = 0.2, A = 0.9, β z = ln 2 → t = 0.5 → I = 0.1 + 0.45.
        let j = ImageF32::filled(1, 1, 1, 0.2);
        let z = ImageF32::filled(1, 1, 1, std::f32::consts::LN_2);
        let i = haze(&j, &z, 0.9, 1.0).unwrap();
        assert!((i.get(0, 0, 0) - 0.55).abs() < 1e-6);
        // Infinite-depth limit: everything turns into airlight.
        assert!((haze_value(0.3, transmission(1.0, 1e3), 0.8) - 0.8).abs() < 1e-6);
        // The clamp keeps dehazing finite even where t underflows to 0.
        assert!(dehaze_value(0.5, 0.0, 0.8).is_finite());
    }

    #[test]
    fn size_and_depth_errors_name_fields() {
        let j = ImageF32::filled(4, 3, 3, 0.5);
        let z_bad = ImageF32::filled(3, 4, 1, 1.0);
        assert_eq!(field_of(haze(&j, &z_bad, 0.8, 0.1).unwrap_err()), "depth_z");
        assert_eq!(
            field_of(dehaze(&j, &z_bad, 0.8, 0.1).unwrap_err()),
            "depth_z"
        );
        let z3 = ImageF32::filled(4, 3, 3, 1.0);
        assert_eq!(field_of(haze(&j, &z3, 0.8, 0.1).unwrap_err()), "depth_z");
        let mut z_neg = ImageF32::filled(4, 3, 1, 1.0);
        z_neg.set(1, 2, 0, -1.0);
        let msg = haze(&j, &z_neg, 0.8, 0.1).unwrap_err().to_string();
        assert!(msg.contains("depth_z") && msg.contains("(1, 2)"), "{msg}");
        let mut j_nan = j.clone();
        j_nan.set(0, 0, 1, f32::NAN);
        let z = ImageF32::filled(4, 3, 1, 1.0);
        assert_eq!(field_of(haze(&j_nan, &z, 0.8, 0.1).unwrap_err()), "image");
        assert_eq!(field_of(haze(&j, &z, 1.5, 0.1).unwrap_err()), "airlight");
        assert_eq!(field_of(dehaze(&j, &z, 0.8, -0.1).unwrap_err()), "beta");
    }

    proptest! {
        /// dehaze(haze(J)) = J while t is not tiny: the round trip only loses the rounding of
        /// `I`, amplified by 1/t (≤ 20 here).
        #[test]
        fn dehaze_inverts_haze(
            w in 1usize..6,
            h in 1usize..6,
            seed_j in proptest::collection::vec(0.0f32..=1.0, 75),
            seed_z in proptest::collection::vec(0.0f32..=1.0, 25),
            a in 0.05f32..=1.0,
            beta in 0.0f32..2.0,
            z_max in 0.01f32..10.0,
        ) {
            // Keep t = e^{−β z} ≥ 0.05 so 1/t amplification stays bounded.
            let z_cap = if beta > 0.0 { (3.0f32 / beta).min(z_max) } else { z_max };
            let j = ImageF32::from_vec(w, h, 3, seed_j[..w * h * 3].to_vec()).unwrap();
            let z = ImageF32::from_vec(w, h, 1, seed_z[..w * h].iter().map(|s| s * z_cap).collect())
                .unwrap();
            let i = haze(&j, &z, a, beta).unwrap();
            let back = dehaze(&i, &z, a, beta).unwrap();
            for (p, q) in j.data().iter().zip(back.data()) {
                prop_assert!((p - q).abs() < 2e-5, "J = {p}, round trip = {q}");
            }
        }
    }
}
