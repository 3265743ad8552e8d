//! One entry K_pq of the surface-camera forward-scatter kernel (Eq. 4.41–4.46): the forward
//! scatter collected along pixel p's viewing ray from the facet seen by pixel q, per unit
//! radiance of that facet. The kernel's build ([`super::forward_kernel`]), its batched rows
//! ([`super::kernel_batch`]) and the far field ([`super::far_field`]) all evaluate entries here.
//!
//! Model choices (our reading of the reference, each used consistently below):
//! - Facet area (Eq. 4.44): dA_q = Ω_q·d_vq²/(v_q·n_q), where Ω_q is the solid angle of pixel q
//!   ([`pixel_solid_angle`]); "dI, the area of the camera pixel" is taken as the pixel's
//!   footprint Ω_q·d_vq² on a surface normal to the ray, foreshortened by the facet's tilt.
//!   v_q·n_q is clamped below at [`MIN_COS_VIEW`]: at grazing views the tangent-plane
//!   footprint diverges although the real facet is bounded by its neighbours, and noisy
//!   normals would otherwise produce arbitrarily large (or negative) kernel entries.
//! - With [`FacetEmission::Isotropic`] the facet acts as an isotropic point source of intensity
//!   L_s(q)·dA_q, so K_pq is the scatter integral of Eq. 4.41 with I₀ = dA_q, evaluated in
//!   closed form like Eq. 4.33 with q in place of the source:
//!   K_pq = dA_q·H₀(T_vq, γ)[F(H₁, H₂(T_vp′, T_vq, γ)) − F(H₁, γ/2)] (Eq. 4.43/4.46), γ the
//!   angle at the camera between p's and q's rays. With [`FacetEmission::Lambertian`] (the
//!   default) the facet's intensity toward each scattering point carries the cosine to its
//!   normal, and F is replaced by the cosine-weighted brackets of [`super::facet_emission`].
//! - Integration length d_vp′ (Eq. 4.43 text): the ray of p is integrated from the camera up to
//!   where it first crosses q's tangent plane, at most d_vp. The text's "p′ behind the camera ⇒
//!   d_vp′ = 0" is not followed: for a facet facing the camera p′ lies behind the camera exactly
//!   when p's ray moves away from q's plane, i.e. never enters the half-space behind q, so all
//!   of [0, d_vp] is lit by q and we use d_vp′ = d_vp. A ray parallel to the plane likewise
//!   never crosses it: d_vp′ = d_vp.
//! - The view ray of a pixel is the direction of its surface point (points lie on their pixel
//!   rays for geometry from a depth map, and this keeps d_vp and the ray consistent).

use nalgebra::Vector3;

use super::f_table::FTable;
use super::facet_emission::{lambertian_scatter_cs, lambertian_scatter_cs_fast, FacetEmission};
use super::h::{scatter_cs, scatter_cs_fast};
use super::Medium;
use crate::camera::Intrinsics;

/// Lower clamp of v_q·n_q in the facet area of Eq. 4.44 (≈ 87°).
pub const MIN_COS_VIEW: f64 = 0.05;

/// Solid angle of pixel (u, v): cos³θ/(fx·fy), θ the angle of its ray to the optical axis.
/// Skew needs no special care: the pixel's area in normalised image coordinates is
/// 1/det([[fx, skew], [0, fy]]) = 1/(fx·fy) with or without it, and cos θ comes from the
/// skew-aware ray.
pub fn pixel_solid_angle(intrinsics: &Intrinsics, u: f64, v: f64) -> f64 {
    let c = intrinsics.ray(u, v)[2];
    c * c * c / (intrinsics.fx * intrinsics.fy)
}

/// Everything about a pixel that K_pq needs, whether it plays p or q.
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct Pre {
    /// Unit view ray (direction of the point).
    pub(super) ray: Vector3<f64>,
    /// Distance camera–point, mm.
    pub(super) d: f64,
    /// Unit normal.
    pub(super) n: Vector3<f64>,
    /// n·point: the tangent plane is {x : n·x = nq}.
    pub(super) nq: f64,
    /// Facet area dA (Eq. 4.44), mm².
    pub(super) da: f64,
    /// e^{−σ d}, filled in by the kernel build (0 elsewhere).
    pub(super) att: f64,
}

impl Pre {
    pub(super) fn new(point: Vector3<f64>, n: Vector3<f64>, omega: f64) -> Pre {
        let d = point.norm();
        let ray = point / d;
        let vn = (-ray.dot(&n)).max(MIN_COS_VIEW);
        Pre {
            ray,
            d,
            n,
            nq: n.dot(&point),
            da: omega * d * d / vn,
            att: 0.0,
        }
    }

    /// The mean geometry of `count` pixels from the sums of their points (`point_sum`, mm) and
    /// unit normals (`normal_sum`), with facet area `da` (mm²) and the attenuation e^{−σd}.
    pub(super) fn mean(
        point_sum: Vector3<f64>,
        normal_sum: Vector3<f64>,
        count: usize,
        da: f64,
        sigma: f64,
    ) -> Pre {
        let point = point_sum / count as f64;
        let nl = normal_sum.norm();
        let n = if nl > 0.0 {
            normal_sum / nl
        } else {
            Vector3::new(0.0, 0.0, -1.0)
        };
        let d = point.norm();
        Pre {
            ray: point / d,
            d,
            n,
            nq: n.dot(&point),
            da,
            att: (-sigma * d).exp(),
        }
    }
}

/// The medium and facet model every kernel entry needs.
#[derive(Clone, Copy)]
pub(super) struct Physics<'a> {
    pub(super) ft: &'a FTable,
    pub(super) beta: f64,
    pub(super) sigma: f64,
    pub(super) emission: FacetEmission,
}

impl<'a> Physics<'a> {
    pub(super) fn new(ft: &'a FTable, medium: &Medium, emission: FacetEmission) -> Self {
        Physics {
            ft,
            beta: medium.beta_per_mm,
            sigma: medium.sigma_per_mm,
            emission,
        }
    }
}

/// K_pq from precomputed pixel data (see the module documentation for the model).
#[inline(always)]
pub(super) fn k_entry(ph: &Physics, p: &Pre, q: &Pre) -> f64 {
    let (cos_g, sin_g, len) = k_geometry(p, q);
    let Physics {
        ft, beta, sigma, ..
    } = *ph;
    match ph.emission {
        FacetEmission::Isotropic => scatter_cs(ft, beta, sigma, q.da, q.d, cos_g, sin_g, len),
        FacetEmission::Lambertian => lambertian_scatter_cs(
            ft,
            beta,
            sigma,
            q.da,
            q.d,
            cos_g,
            sin_g,
            len,
            q.n.dot(&p.ray),
            q.n.dot(&q.ray),
        ),
    }
}

/// [`k_entry`] with the fast bracket of the kernel build (see `h::bracket_fast`); the
/// simulator's dense sum and [`kernel_entry`] keep the accurate one.
#[inline(always)]
pub(super) fn k_entry_fast(ph: &Physics, p: &Pre, q: &Pre) -> f64 {
    let (cos_g, sin_g, len) = k_geometry(p, q);
    let Physics {
        ft, beta, sigma, ..
    } = *ph;
    match ph.emission {
        FacetEmission::Isotropic => {
            scatter_cs_fast(ft, beta, sigma, q.da, q.d, q.att, cos_g, sin_g, len)
        }
        FacetEmission::Lambertian => lambertian_scatter_cs_fast(
            ft,
            beta,
            sigma,
            q.da,
            q.d,
            q.att,
            cos_g,
            sin_g,
            len,
            q.n.dot(&p.ray),
            q.n.dot(&q.ray),
        ),
    }
}

/// cos γ, sin γ and the lit ray length d_vp′ of K_pq.
#[inline(always)]
fn k_geometry(p: &Pre, q: &Pre) -> (f64, f64, f64) {
    let cos_g = p.ray.dot(&q.ray);
    let sin_g = p.ray.cross(&q.ray).norm();
    let t = q.nq / q.n.dot(&p.ray);
    // NaN (parallel ray on the plane) and t ≤ 0 (never crosses ahead) both mean "no crossing".
    let len = if t > 0.0 { t.min(p.d) } else { p.d };
    (cos_g, sin_g, len)
}

/// K_pq for p ≠ q (Eq. 4.46, second case): the forward scatter collected along p's viewing ray
/// (unit `ray_p`, surface at `d_vp_mm`) from the facet at `q_mm` with unit normal `n_q` and
/// pixel solid angle `pixel_solid_angle_q`, per unit L_s(q), for a facet that radiates as
/// `emission` says. The diagonal is e^{−σ d_vp}.
#[allow(clippy::too_many_arguments)]
pub fn kernel_entry(
    ft: &FTable,
    medium: &Medium,
    emission: FacetEmission,
    ray_p: Vector3<f64>,
    d_vp_mm: f64,
    q_mm: Vector3<f64>,
    n_q: Vector3<f64>,
    pixel_solid_angle_q: f64,
) -> f64 {
    let p = Pre {
        ray: ray_p,
        d: d_vp_mm,
        ..Pre::default()
    };
    let q = Pre::new(q_mm, n_q, pixel_solid_angle_q);
    k_entry(&Physics::new(ft, medium, emission), &p, &q)
}
