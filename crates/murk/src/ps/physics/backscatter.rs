//! Backscatter L_b along one viewing ray from one point source (Eq. 4.32, closed form Eq. 4.33).

use nalgebra::Vector3;

use super::f_table::FTable;
use super::h::{scatter_cs, scatter_quadrature_cs};
use super::Medium;

/// Distance to the source and cos/sin of the angle γ between `ray` and the source direction,
/// sin γ from the cross product so that small angles keep their relative accuracy.
fn geometry(source_mm: Vector3<f64>, ray: Vector3<f64>) -> (f64, f64, f64) {
    let d = source_mm.norm();
    if d == 0.0 {
        return (0.0, 1.0, 0.0);
    }
    (d, ray.dot(&source_mm) / d, ray.cross(&source_mm).norm() / d)
}

/// Backscatter (Eq. 4.33) at the camera (origin) along the unit viewing ray `ray` of length
/// `ray_length_mm` (+∞ for a ray that meets no surface) from an isotropic point source of
/// radiant intensity `intensity` at `source_mm` (camera frame). Limits as in
/// [`super::point_source_scatter`].
pub fn backscatter(
    table: &FTable,
    medium: &Medium,
    intensity: f64,
    source_mm: impl Into<Vector3<f64>>,
    ray: impl Into<Vector3<f64>>,
    ray_length_mm: f64,
) -> f64 {
    let (d, c, s) = geometry(source_mm.into(), ray.into());
    scatter_cs(
        table,
        medium.beta_per_mm,
        medium.sigma_per_mm,
        intensity,
        d,
        c,
        s,
        ray_length_mm,
    )
}

/// Eq. 4.32 by brute-force adaptive quadrature over the ray (no F table): the reference for
/// [`backscatter`]. Slow; for tests and validation only.
pub fn backscatter_quadrature(
    medium: &Medium,
    intensity: f64,
    source_mm: impl Into<Vector3<f64>>,
    ray: impl Into<Vector3<f64>>,
    ray_length_mm: f64,
) -> f64 {
    let (d, c, s) = geometry(source_mm.into(), ray.into());
    if ray_length_mm.is_nan() || ray_length_mm <= 0.0 || d == 0.0 {
        return if d == 0.0 && ray_length_mm > 0.0 {
            f64::INFINITY
        } else {
            0.0
        };
    }
    scatter_quadrature_cs(medium, intensity, d, c, s, ray_length_mm)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit(v: [f64; 3]) -> [f64; 3] {
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        [v[0] / n, v[1] / n, v[2] / n]
    }

    #[test]
    fn closed_form_matches_quadrature() {
        let t = FTable::global();
        let sources = [
            [60.0, -40.0, 0.0],
            [-100.0, 0.0, 20.0],
            [0.0, 150.0, -30.0],
            [25.0, 25.0, 300.0],
        ];
        let rays = [
            unit([0.0, 0.0, 1.0]),
            unit([0.2, -0.1, 1.0]),
            unit([-0.3, 0.35, 1.0]),
        ];
        let mut worst = 0.0f64;
        // σ chosen so the ray's optical length spans T = 0.1 … 5 (ray lengths 100…500 mm).
        for &sigma in &[0.001, 0.004, 0.01] {
            let m = Medium {
                beta_per_mm: 0.8 * sigma,
                sigma_per_mm: sigma,
            };
            for s in sources {
                for r in rays {
                    for len in [100.0, 250.0, 500.0, f64::INFINITY] {
                        let got = backscatter(t, &m, 2.0, s, r, len);
                        let want = backscatter_quadrature(&m, 2.0, s, r, len);
                        let rel = (got - want).abs() / want;
                        worst = worst.max(rel);
                        assert!(
                            rel < 1e-3,
                            "σ={sigma} s={s:?} r={r:?} L={len}: {got} vs {want}"
                        );
                    }
                }
            }
        }
        eprintln!("backscatter worst relative error {worst:.2e}");
    }

    #[test]
    fn degenerate_geometry_is_handled() {
        let t = FTable::global();
        let m = Medium {
            beta_per_mm: 0.01,
            sigma_per_mm: 0.01,
        };
        // Source exactly behind the camera on the ray's axis: finite.
        let v = backscatter(
            t,
            &m,
            1.0,
            [0.0, 0.0, -50.0],
            [0.0, 0.0, 1.0],
            f64::INFINITY,
        );
        let w = backscatter_quadrature(&m, 1.0, [0.0, 0.0, -50.0], [0.0, 0.0, 1.0], f64::INFINITY);
        assert!((v - w).abs() < 1e-4 * w, "{v} vs {w}");
        assert_eq!(
            backscatter(t, &m, 1.0, [1.0, 0.0, 0.0], [0.0, 0.0, 1.0], 0.0),
            0.0
        );
    }
}
