//! The object's absolute distance from the lights' 1/d² fall-off.
//!
//! Perspective normal integration (Eq. 4.60–4.62) recovers the shape only up to scale: every
//! scaled copy z(p) = s·ẑ(p) has the same normals. The reference fixes s with a known initial
//! distance. With near point lights of known position and intensity the scale is observable:
//! the shading rows of Eq. 4.59, D_i(x) = I0_i·(e^{−σ d_i}/d_i² + βσ/(2π T_i)·G(T_i, 1))·l̂_i,
//! depend on where the point x is, and at the wrong distance no normal and albedo explain all of
//! a pixel's observations at once. With m ≥ 4 lit observations the per-pixel least-squares fit
//! L_i ≈ D_i(x)·ñ leaves m − 3 residual degrees of freedom.
//!
//! [`fit_mean_depth`] scales a given shape to mean z-depth D and minimises over D the trimmed
//! mean (over pixels) of each pixel's residual relative to its observations,
//! Σ_i (L_i − D_i·ñ)²/Σ_i L_i², which does not depend on the pixel's albedo or on any
//! per-pixel factor common to all lights (such as the camera-path attenuation e^{−σ d_vp}). The
//! search is a log-spaced grid followed by Brent's method in the best bracket
//! ([`crate::minimise::grid_then_brent`]).

use nalgebra::Vector3;
use rayon::prelude::*;

use crate::minimise::grid_then_brent;

use crate::ps::capture::{rig_size_mm, PointLight};
use crate::ps::near_light::{
    exact_shading, normal_equations, refine_exact_g, solve3, ShadingModel, MAX_LIT,
};
use crate::ps::physics::{GTable, Medium};

/// At most this many pixels (an even stride over the object) enter the objective: enough to
/// average out noise, cheap enough for ~35 evaluations per iteration.
const MAX_PIXELS: usize = 4096;

/// Share of the worst pixels left out of the objective (cast shadows misread as lit,
/// silhouette pixels whose forward-scatter removal is least accurate).
const TRIM: f64 = 0.1;

/// Spacing of the log-distance grid searched before Brent's refinement (6 %: the
/// objective is smooth and unimodal on that scale in every run measured).
const GRID_STEP: f64 = 0.06;

/// Every this many pixels enter the grid search, when at least [`MIN_COARSE_PIXELS`] remain.
const COARSE_STRIDE: usize = 4;

/// Fewest pixels the grid search reads before it falls back to all of them.
const MIN_COARSE_PIXELS: usize = 256;

/// Brent's refinement stops when the minimum is bracketed to this in log-distance (10⁻⁴: a
/// hundredth of the distance's own error in every run measured).
const LOG_TOLERANCE: f64 = 1e-4;

/// What the distance search found.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DistanceFit {
    /// Mean z-depth of the object's visible surface that fits the observations best, mm.
    pub mean_depth_mm: f64,
    /// Trimmed mean relative residual at that distance.
    pub objective: f64,
    /// Pixels with at least four lit observations that entered the objective.
    pub pixels: usize,
    /// The best grid point was an end of the searched range: the true distance may lie outside.
    pub at_bound: bool,
}

/// One pixel's data: its point at unit mean depth and its lit observations.
struct PixelObs {
    unit_point: [f64; 3],
    lit: Vec<(usize, f64)>,
}

/// Fits the mean z-depth of `points_mm` (the shape at any scale; only masked pixels are read)
/// to the reflected components `reflected[i]` under `lights`, searching `range_mm` (lo, hi; mean
/// depths in mm). An observation counts as lit when it exceeds `shadow_ratio` times the pixel's
/// brightest (as in [`crate::ps::near_light::solve_normals`]). `None` when fewer than 16 pixels
/// have four lit observations or the range is empty.
#[allow(clippy::too_many_arguments)]
pub fn fit_mean_depth(
    points_mm: &[[f32; 3]],
    mask: &[bool],
    reflected: &[Vec<f32>],
    lights: &[PointLight],
    medium: &Medium,
    g: &GTable,
    model: ShadingModel,
    shadow_ratio: f64,
    range_mm: (f64, f64),
) -> Option<DistanceFit> {
    let (lo, hi) = range_mm;
    if !(lo.is_finite() && hi.is_finite() && lo > 0.0 && hi > lo) {
        return None;
    }
    let masked: Vec<usize> = (0..mask.len())
        .filter(|&p| mask[p] && points_mm[p].iter().all(|v| v.is_finite()))
        .collect();
    if masked.is_empty() {
        return None;
    }
    let mean_z = masked
        .iter()
        .map(|&p| f64::from(points_mm[p][2]))
        .sum::<f64>()
        / masked.len() as f64;
    if !(mean_z.is_finite() && mean_z > 0.0) {
        return None;
    }
    let stride = masked.len().div_ceil(MAX_PIXELS).max(1);
    let pixels: Vec<PixelObs> = masked
        .iter()
        .step_by(stride)
        .filter_map(|&p| {
            let max_obs = reflected
                .iter()
                .map(|img| f64::from(img[p]))
                .fold(0.0f64, f64::max);
            let thresh = (shadow_ratio * max_obs).max(0.0);
            let lit: Vec<(usize, f64)> = reflected
                .iter()
                .enumerate()
                .map(|(i, img)| (i, f64::from(img[p])))
                .filter(|&(_, o)| o > thresh && o.is_finite())
                .collect();
            (lit.len() >= 4).then(|| PixelObs {
                unit_point: points_mm[p].map(|v| f64::from(v) / mean_z),
                lit,
            })
        })
        .collect();
    if pixels.len() < 16 {
        return None;
    }
    // The grid only has to find the bracket: it reads every COARSE_STRIDE-th pixel (the
    // objective is a trimmed mean, smooth in d, and a quarter of 4096 pixels locates its
    // minimum to within a grid step). The refinement reads them all.
    let coarse: Vec<&PixelObs> = if pixels.len() >= COARSE_STRIDE * MIN_COARSE_PIXELS {
        pixels.iter().step_by(COARSE_STRIDE).collect()
    } else {
        pixels.iter().collect()
    };
    let all: Vec<&PixelObs> = pixels.iter().collect();
    let objective = |set: &[&PixelObs], d: f64| -> f64 {
        let mut r: Vec<f64> = set
            .par_iter()
            .map(|px| pixel_residual(px, d, lights, medium, g, model))
            .collect();
        let keep = ((1.0 - TRIM) * r.len() as f64).ceil().max(1.0) as usize;
        r.select_nth_unstable_by(keep - 1, f64::total_cmp);
        r[..keep].iter().sum::<f64>() / keep as f64
    };
    // Brent's minimisation in log-distance over the best grid point's neighbours, on every pixel.
    let m = grid_then_brent(
        |x| objective(&coarse, x.exp()),
        |x| objective(&all, x.exp()),
        lo.ln(),
        hi.ln(),
        GRID_STEP,
        LOG_TOLERANCE,
    );
    let (x, fx, at_bound) = (m.x, m.value, m.at_bound);
    Some(DistanceFit {
        mean_depth_mm: x.exp(),
        objective: fx,
        pixels: pixels.len(),
        at_bound,
    })
}

/// Σ_i (L_i − ρ·S_i(n))²/Σ_i L_i² for the pixel's point at mean depth `d`, with (n, ρ) the
/// least-squares fit: Eq. 4.57's linear solution, refined on the exact `G(T, n·l)` of Eq. 4.54
/// for [`ShadingModel::ForwardScatter`]. The linearisation G(T, c) ≈ G(T, 1)·c is too coarse
/// here: its misfit (a few 1e-5 of the observations) is as large as the distance signal, and
/// on the true reflected component of a simulated sphere it put the distance at 121 mm
/// instead of 212 mm. 1 when no fit exists (no normal explains the observations).
fn pixel_residual(
    px: &PixelObs,
    d: f64,
    lights: &[PointLight],
    medium: &Medium,
    g: &GTable,
    model: ShadingModel,
) -> f64 {
    let x = Vector3::from(px.unit_point) * d;
    let lit = &px.lit[..px.lit.len().min(MAX_LIT)];
    let (ata, atb) = normal_equations(lights, medium, g, model, &x, lit);
    let Some(sol) = solve3(&ata, &atb) else {
        return 1.0;
    };
    let ll: f64 = lit.iter().map(|&(_, o)| o * o).sum();
    let res: f64 = match model {
        // Σ (L − D·ñ)² = LᵀL − 2 ñᵀDᵀL + ñᵀDᵀD ñ: the normal equations already hold it.
        ShadingModel::DirectOnly => {
            let quad = sol.dot(&(ata * sol));
            (ll - 2.0 * sol.dot(&atb) + quad).max(0.0)
        }
        ShadingModel::ForwardScatter => {
            let len = sol.norm();
            if !(len.is_finite() && len > 0.0) {
                return 1.0;
            }
            let n0 = sol / len;
            let (n, rho) = refine_exact_g(lights, medium, g, &x, lit, n0, len).unwrap_or((n0, len));
            lit.iter()
                .map(|&(i, obs)| {
                    let pred = rho * exact_shading(&lights[i], medium, g, &x, &n);
                    (obs - pred) * (obs - pred)
                })
                .sum()
        }
    };
    (res / ll.max(f64::MIN_POSITIVE)).min(1.0)
}

/// A search range for the object's mean distance when none is known: from a tenth of the
/// rig's size ([`rig_size_mm`]: the largest distance between two lights or of a light from the
/// camera) to a hundred times it. Near-light photometric stereo needs the object within a few
/// rig sizes of the lights, so this brackets every setting where the method works at all.
pub fn default_range_mm(lights: &[PointLight]) -> (f64, f64) {
    let size = rig_size_mm(lights);
    (0.1 * size, 100.0 * size)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::monitor::Monitor;
    use crate::ps::pipeline::back_project;
    use crate::simulate::ps::{simulate_ps, PsSimConfig};

    /// On a simulated sphere with the reflected component known (no scatter to remove: β = 0),
    /// the true shape scaled to a wrong distance is pulled back to the true one from ±30 %,
    /// and from a wide range when no distance is known.
    #[test]
    fn recovers_the_distance_of_a_known_shape() {
        let cfg = PsSimConfig {
            beta_per_mm: 0.0,
            sigma_per_mm: 0.0,
            ..PsSimConfig::with_size(64, 64)
        };
        let sim = simulate_ps(&cfg, &Monitor::noop()).unwrap();
        let cap = &sim.capture;
        let (w, _) = cap.dims();
        let reflected: Vec<Vec<f32>> = cap.images.iter().map(|i| i.data().to_vec()).collect();
        let masked: Vec<usize> = (0..cap.mask.len()).filter(|&p| cap.mask[p]).collect();
        let truth = masked
            .iter()
            .map(|&p| f64::from(sim.gt_depth_mm[p]))
            .sum::<f64>()
            / masked.len() as f64;
        for scale in [0.7f64, 1.0, 1.3] {
            let depth: Vec<f32> = sim
                .gt_depth_mm
                .iter()
                .map(|&z| (f64::from(z) * scale) as f32)
                .collect();
            let pts = back_project(&cap.intrinsics, w, &depth, &cap.mask);
            for range in [
                (truth * scale / 1.5, truth * scale * 1.5),
                default_range_mm(&cap.lights),
            ] {
                let fit = fit_mean_depth(
                    &pts,
                    &cap.mask,
                    &reflected,
                    &cap.lights,
                    &cap.medium,
                    GTable::global(),
                    ShadingModel::DirectOnly,
                    0.05,
                    range,
                )
                .unwrap();
                let rel = fit.mean_depth_mm / truth - 1.0;
                eprintln!("scale {scale} range {range:?}: {fit:?} ({rel:+.4})");
                assert!(rel.abs() < 0.01, "{fit:?} vs {truth}");
                assert!(!fit.at_bound);
            }
        }
    }

    #[test]
    fn empty_or_bad_ranges_give_none() {
        let mask = vec![true; 4];
        let pts = vec![[0.0f32, 0.0, 100.0]; 4];
        let refl = vec![vec![1.0f32; 4]; 4];
        let lights = vec![
            PointLight {
                position_mm: [10.0, 0.0, 0.0],
                intensity: 1.0,
            };
            4
        ];
        let m = Medium {
            beta_per_mm: 0.0,
            sigma_per_mm: 0.0,
        };
        let g = GTable::global();
        for range in [(0.0, 10.0), (10.0, 5.0), (f64::NAN, 1.0)] {
            assert!(fit_mean_depth(
                &pts,
                &mask,
                &refl,
                &lights,
                &m,
                g,
                ShadingModel::DirectOnly,
                0.05,
                range
            )
            .is_none());
        }
        // Too few pixels.
        assert!(fit_mean_depth(
            &pts,
            &mask,
            &refl,
            &lights,
            &m,
            g,
            ShadingModel::DirectOnly,
            0.05,
            (10.0, 1000.0)
        )
        .is_none());
    }
}
