//! Single-scattering physics of Sun et al. used by Ch. 4 (isotropic phase function, homogeneous
//! medium, near point sources).
//!
//! Everything here is the reference's Sec. 4.2–4.3.2: the `F` lookup table behind Eq. 4.33
//! ([`f_table`]), the `H` functions of Eq. 4.34–4.36 and the point-source scatter integral
//! ([`h`]), the backscatter of Eq. 4.32/4.33 ([`mod@backscatter`]), the `G` table of Eq. 4.40 with the
//! source-surface forward scatter of Eq. 4.39 ([`g_table`]), and the surface-camera forward
//! scatter kernel of Eq. 4.41–4.53 ([`forward_kernel`]) with the facet's emission model
//! ([`facet_emission`]: Eq. 4.41's isotropic facet or the Lambertian cosine).
//!
//! Conventions: camera at the origin, +x right, +y down, +z forward; lengths in mm; β and σ per
//! mm; isotropic phase function P = 1/(4π); unit normals point towards the camera.

use crate::error::{MurkError, Result};

pub mod backscatter;
pub mod f_table;
pub mod facet_emission;
pub mod far_field;
pub mod forward_kernel;
pub mod g_table;
pub mod h;
mod kernel_batch;
pub mod kernel_entry;
pub mod kernel_layout;
pub(crate) mod quad;

pub use backscatter::{backscatter, backscatter_quadrature};
pub use f_table::{f_quadrature, facet_quadrature, FTable};
pub use facet_emission::FacetEmission;
pub use far_field::FarField;
pub use forward_kernel::{dense_forward_scatter, ForwardKernel, SurfaceGeometry};
pub use g_table::{source_surface_forward, GTable};
pub use h::{h0, h1, h2, point_source_scatter};
pub use kernel_entry::{kernel_entry, pixel_solid_angle};
pub use kernel_layout::KernelLayout;

/// Homogeneous scattering medium. σ = α + β (Eq. 2.3), so σ ≥ β.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Medium {
    /// Scattering coefficient β, per mm.
    pub beta_per_mm: f64,
    /// Extinction coefficient σ, per mm.
    pub sigma_per_mm: f64,
}

impl Medium {
    /// Fails unless both coefficients are finite and ≥ 0 and σ ≥ β (absorption cannot be
    /// negative).
    pub fn validate(&self) -> Result<()> {
        for (name, v) in [
            ("beta_per_mm", self.beta_per_mm),
            ("sigma_per_mm", self.sigma_per_mm),
        ] {
            if !v.is_finite() || v < 0.0 {
                return Err(MurkError::invalid(
                    name,
                    format!("must be finite and >= 0, got {v}"),
                ));
            }
        }
        if self.sigma_per_mm < self.beta_per_mm {
            return Err(MurkError::invalid(
                "sigma_per_mm",
                format!(
                    "extinction {} must be >= scattering {} (sigma = alpha + beta)",
                    self.sigma_per_mm, self.beta_per_mm
                ),
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::field_of;

    #[test]
    fn medium_validation_names_fields() {
        let ok = Medium {
            beta_per_mm: 0.01,
            sigma_per_mm: 0.02,
        };
        assert!(ok.validate().is_ok());
        let bad_beta = Medium {
            beta_per_mm: -0.1,
            ..ok
        };
        assert_eq!(field_of(bad_beta.validate().unwrap_err()), "beta_per_mm");
        let nan_sigma = Medium {
            sigma_per_mm: f64::NAN,
            ..ok
        };
        assert_eq!(field_of(nan_sigma.validate().unwrap_err()), "sigma_per_mm");
        let sigma_below_beta = Medium {
            beta_per_mm: 0.03,
            sigma_per_mm: 0.02,
        };
        assert_eq!(
            field_of(sigma_below_beta.validate().unwrap_err()),
            "sigma_per_mm"
        );
    }
}
