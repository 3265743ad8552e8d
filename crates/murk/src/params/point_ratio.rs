//! β from the transmission ratios at the SfM points (Li et al. \[41\], reference §3.3.2).
//!
//! A point seen by the reference at z-depth `z_r` and by a source at `z_s` has, by Eq. 3.3 and
//! with the same clear radiance `J` in both views,
//!
//! `(I_r − A) / (I_s − A) = e^{−β z_r} / e^{−β z_s}`, i.e. `ln((I_r − A)/(I_s − A)) = β (z_s − z_r)`,
//!
//! one linear equation in β per point, source and colour channel, with the depths from the SfM
//! cloud and the camera poses. The reference avoids pixel intensities because a single such
//! equation is fragile: it needs a good `A`, equal radiance across views, and depths that
//! differ. murk uses it only as step 1 of Algorithm 1 (β₀, in place of the sweep of Eq. 3.10)
//! and only when the data carry the information: thousands of equations, fitted through the
//! origin by Tukey-weighted IRLS (occlusions, specularities and mismatches are outliers), with
//! a standard error small against β, and per-source fits that agree with each other (an
//! exposure change between views biases each source differently; a 1 % step already moves β by
//! ≈ 0.1 on a lateral trajectory). Otherwise the caller falls back to the sweep. The depth
//! differences need not be large: their spread over the fit is what counts (docs/accuracy.md
//! measures lateral and forward trajectories).

use crate::image::ImageF32;
use rayon::prelude::*;

use crate::mvs::depth::vignetting::radius2;
use crate::mvs::View;
use crate::params::footprint::{matched_sigmas, FootprintSampler, MAX_CHANNELS};
use crate::params::sparse::SparseDepth;

/// Base σ of the Gaussian each view is blurred by where its intensities are sampled at the SfM
/// points, pixels, for an image `width` pixels wide: one pixel from 256 pixels of width up,
/// and one per 256 of width below (at least 0.5). [`crate::params::footprint`] widens it per
/// point and view so that both views blur the surface alike.
///
/// With the footprints matched, the base blur only has to smooth the pixel grid; a wider one
/// makes the sample more sensitive to what the match misses at SfM keypoints, which sit on
/// blobs of about the blur's size. On 20 forward-moving 512×384 scenes through COLMAP (seeds
/// 700–719, 7 views) a base of 2 px (one per 256 of width) left β 13 %
/// high with exact geometry and exact poses at COLMAP's keypoints; 1 px took the models murk
/// calls identifiable from the truth within two standard errors on 4 of 8 to 5 of 7, MAE_A
/// 0.046 → 0.029 and MAE_β 0.032 → 0.029, and the simulator's own models of the same scenes
/// from MAE_β 0.0039 to 0.0022 (docs/scattering-params.md).
///
/// The equations assume the same `J` at a point in every view, but a pixel integrates `J` over
/// a footprint whose size on the surface changes with the view's distance: on textured
/// surfaces that shifts the slope `e^{β Δz}` of every equation by a source-dependent factor.
/// Blurring both views well past those footprints removes most of it; blurring too far mixes
/// surfaces at other depths into a point's value. Measured with one blur for every view (before
/// the per-point match): one source pair of a forward-moving 512×384 scene, true β 0.379, gave
/// β 0.17 / 0.60 / −0.19 unblurred and 0.37 / 0.41 / 0.35 at σ = 2; the held-out 256×192
/// scenes (seeds 500–519) MAE_β 0.042 at σ = 0, **0.013 at σ = 1**, 0.014 at σ = 2.
pub fn sample_blur_sigma_px(width: usize) -> f32 {
    (width as f32 / 256.0).clamp(0.5, 1.0)
}

/// Channel values closer to `A` than this are skipped: `ln` of a ratio of two small
/// differences is dominated by noise (and its sign by chance).
pub const MIN_AIRLIGHT_CONTRAST: f64 = 0.05;
/// Fewest equations for an estimate.
pub const MIN_RATIO_EQUATIONS: usize = 300;
/// Largest accepted standard error of the estimate, relative to the estimate.
pub const MAX_RELATIVE_STD_ERROR: f64 = 0.1;
/// The airlight error the source-consistency check allows for: about the CNN's held-out MAE_A
/// in dense haze (0.009–0.017 at median transmission below 0.5, docs/airlight.md). A₀ from
/// the dark-channel rule (MAE 0.05–0.09) is worse than this allows, so with it clean captures
/// fail the check more often and fall back.
pub const AIRLIGHT_SIGMA: f32 = 0.015;
/// Tukey's biweight constant (95 % efficiency under Gaussian noise), in robust standard
/// deviations (1.4826 · MAD).
const TUKEY_C: f64 = 4.685;
const IRLS_ITERATIONS: usize = 30;

/// What [`beta_from_point_ratios`] found.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PointRatioFit {
    /// β, per scene unit.
    pub beta: f64,
    /// Standard error of β from the weighted fit, per scene unit.
    pub std_error: f64,
    /// Equations (point × source × channel) that entered the fit.
    pub equations: usize,
    /// Root mean square of `z_s − z_r` over the equations, scene units.
    pub rms_depth_difference: f64,
    /// Sources with a fit of their own.
    pub sources: usize,
    /// Σ_s ((β_s − β)/SE_s)² over the per-source fits: whether the sources agree within their
    /// errors (about `sources − 1` when they do). An exposure change between views biases
    /// each source's β differently, which the joint standard error cannot see. With one source
    /// there is nothing to compare (0).
    pub source_consistency_chi2: f64,
}

/// The 99.9 % quantile of χ² with `dof` degrees of freedom (Wilson–Hilferty; 0 for `dof` 0).
fn chi2_quantile_999(dof: usize) -> f64 {
    if dof == 0 {
        return 0.0;
    }
    let k = dof as f64;
    let a = 2.0 / (9.0 * k);
    k * (1.0 - a + 3.090 * a.sqrt()).powi(3)
}

impl PointRatioFit {
    /// Whether the fit pins β down: enough equations, a standard error below
    /// [`MAX_RELATIVE_STD_ERROR`] of β (β > 0), and sources that agree with each other (χ²
    /// below its 99.9 % quantile).
    pub fn is_reliable(&self) -> bool {
        self.equations >= MIN_RATIO_EQUATIONS
            && self.beta > 0.0
            && self.std_error < MAX_RELATIVE_STD_ERROR * self.beta
            && self.source_consistency_chi2 <= chi2_quantile_999(self.sources.saturating_sub(1))
    }
}

/// One channel of one point seen by the reference and a source: what the equation of the
/// module docs needs before the airlight is chosen.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RatioSample {
    /// Index of the point in [`SparseDepth::samples`]: a point's channels and sources share
    /// its errors (where SfM put it, what texture it sits on).
    pub point: u32,
    /// `z_s − z_r`, scene units.
    pub depth_difference: f64,
    /// `I_r` of the channel.
    pub reference: f64,
    /// `I_s` of the channel.
    pub source: f64,
    /// `r²` of the point in the reference and in the source: the squared distance from the
    /// image centre over the squared half-diagonal ([`crate::mvs::depth::vignetting::radius2`]),
    /// where a lens's fall-off puts it.
    pub reference_r2: f64,
    /// See `reference_r2`.
    pub source_r2: f64,
}

/// [`ratio_samples`] for every source, each view blurred per point to a common footprint
/// ([`crate::params::footprint`]) around the base width [`sample_blur_sigma_px`].
pub fn blurred_ratio_samples(
    reference: &View<'_>,
    sources: &[View<'_>],
    sparse: &SparseDepth,
) -> Vec<Vec<RatioSample>> {
    let base = f64::from(sample_blur_sigma_px(reference.image.width()));
    blurred_ratio_samples_at(reference, sources, sparse, base)
}

/// [`blurred_ratio_samples`] around the base width `base_sigma_px` instead of
/// [`sample_blur_sigma_px`] (see [`crate::params::sampling_share`]).
pub fn blurred_ratio_samples_at(
    reference: &View<'_>,
    sources: &[View<'_>],
    sparse: &SparseDepth,
    base_sigma_px: f64,
) -> Vec<Vec<RatioSample>> {
    // `collect` keeps source order whatever the thread count.
    sources
        .par_iter()
        .enumerate()
        .map(|(i, s)| ratio_samples(reference, s, i, sparse, base_sigma_px))
        .collect()
}

/// Every SfM point of `sparse` back-projected from the reference at its depth and projected
/// into `source`, sampled per channel with footprint-matched blurs of base width
/// `base_sigma_px` ([`crate::params::footprint`]) at its sub-pixel position in both views.
/// Points whose sampling window leaves either image are skipped, and so are points whose
/// [`SparseSample::seen_by`](crate::params::sparse::SparseSample::seen_by) mask lacks
/// `source_index`: SfM did not see them there.
pub fn ratio_samples(
    reference: &View<'_>,
    source: &View<'_>,
    source_index: usize,
    sparse: &SparseDepth,
    base_sigma_px: f64,
) -> Vec<RatioSample> {
    let channels = reference.image.channels();
    if source.image.channels() != channels || channels > MAX_CHANNELS {
        return Vec::new();
    }
    let focal = |v: &View<'_>| (v.intrinsics.fx * v.intrinsics.fy).abs().sqrt();
    let (focal_ref, focal_src) = (focal(reference), focal(source));
    let (ref_sampler, src_sampler) = (
        FootprintSampler::new(reference.image),
        FootprintSampler::new(source.image),
    );
    let to_world = reference.pose.inverse();
    let mut out = Vec::new();
    // A source past the mask's 32 bits has no track information: every point may be used.
    let bit = u32::try_from(source_index)
        .ok()
        .and_then(|i| 1u32.checked_shl(i))
        .unwrap_or(0);
    let (mut ir, mut is) = ([0.0; MAX_CHANNELS], [0.0; MAX_CHANNELS]);
    for (point, s) in sparse.samples().iter().enumerate() {
        if bit != 0 && s.seen_by & bit == 0 {
            // SfM did not match the point in this source: occluded, or not found there.
            continue;
        }
        let (u, v, z_r) = (f64::from(s.u), f64::from(s.v), f64::from(s.z));
        let ray = reference.intrinsics.ray(u, v);
        let cam = [ray[0] * z_r / ray[2], ray[1] * z_r / ray[2], z_r];
        let p = source.pose.transform(to_world.transform(cam));
        let Some((us, vs)) = source.intrinsics.project(p) else {
            continue;
        };
        let (sigma_r, sigma_s) = matched_sigmas(base_sigma_px, z_r, focal_ref, p[2], focal_src);
        if !(ref_sampler.sample(u, v, sigma_r, &mut ir)
            && src_sampler.sample(us, vs, sigma_s, &mut is))
        {
            continue;
        }
        let radius2 = |img: &ImageF32, x: f64, y: f64| {
            f64::from(radius2(x as f32, y as f32, img.width(), img.height()))
        };
        let (reference_r2, source_r2) = (
            radius2(reference.image, u, v),
            radius2(source.image, us, vs),
        );
        for c in 0..channels {
            out.push(RatioSample {
                point: point as u32,
                reference_r2,
                source_r2,
                depth_difference: p[2] - z_r,
                reference: ir[c],
                source: is[c],
            });
        }
    }
    out
}

/// The equations `(z_s − z_r, ln((I_r − A)/(I_s − A)))` of the module docs for airlight
/// `airlight`, skipping samples on opposite sides of `A` or within
/// [`MIN_AIRLIGHT_CONTRAST`] of it.
pub fn ratio_equations(samples: &[RatioSample], airlight: f32) -> Vec<(f64, f64)> {
    let a = f64::from(airlight);
    samples
        .iter()
        .filter_map(|s| {
            let (dr, ds) = (s.reference - a, s.source - a);
            let usable = dr * ds > 0.0
                && dr.abs() >= MIN_AIRLIGHT_CONTRAST
                && ds.abs() >= MIN_AIRLIGHT_CONTRAST;
            usable.then(|| (s.depth_difference, (dr / ds).ln()))
        })
        .collect()
}

/// Fits `y = β x` through the origin with Tukey's biweight (IRLS from least squares, scale from
/// the median absolute residual). `None` without equations or without depth differences.
pub fn fit_through_origin(eqs: &[(f64, f64)]) -> Option<PointRatioFit> {
    let sxx: f64 = eqs.iter().map(|(x, _)| x * x).sum();
    if eqs.is_empty() || sxx <= 0.0 {
        return None;
    }
    let mut beta = eqs.iter().map(|(x, y)| x * y).sum::<f64>() / sxx;
    let mut residuals = vec![0.0f64; eqs.len()];
    let mut scale = 0.0;
    for _ in 0..IRLS_ITERATIONS {
        for (r, (x, y)) in residuals.iter_mut().zip(eqs) {
            *r = (y - beta * x).abs();
        }
        let mid = residuals.len() / 2;
        let mad = *residuals
            .select_nth_unstable_by(mid, |a, b| a.total_cmp(b))
            .1;
        scale = (1.4826 * mad).max(1e-12);
        let c = TUKEY_C * scale;
        let (mut num, mut den) = (0.0, 0.0);
        for (x, y) in eqs {
            let t = (y - beta * x) / c;
            if t.abs() < 1.0 {
                let w = (1.0 - t * t).powi(2);
                num += w * x * y;
                den += w * x * x;
            }
        }
        if den <= 0.0 {
            return None;
        }
        let next = num / den;
        let done = (next - beta).abs() <= 1e-9 * beta.abs().max(1e-9);
        beta = next;
        if done {
            break;
        }
    }
    // Weighted least squares: var(β) ≈ s² / Σ w x² with s the robust residual scale.
    let c = TUKEY_C * scale;
    let (mut swxx, mut kept) = (0.0, 0usize);
    for (x, y) in eqs {
        let t = (y - beta * x) / c;
        if t.abs() < 1.0 {
            swxx += (1.0 - t * t).powi(2) * x * x;
            kept += 1;
        }
    }
    Some(PointRatioFit {
        beta,
        std_error: if swxx > 0.0 {
            scale / swxx.sqrt()
        } else {
            f64::INFINITY
        },
        equations: kept,
        rms_depth_difference: (sxx / eqs.len() as f64).sqrt(),
        sources: 1,
        source_consistency_chi2: 0.0,
    })
}

/// β from the SfM pixels' transmission ratios between the reference and every source (module
/// docs) with airlight `airlight`; check [`PointRatioFit::is_reliable`] before using it.
pub fn beta_from_point_ratios(
    reference: &View<'_>,
    sources: &[View<'_>],
    sparse: &SparseDepth,
    airlight: f32,
) -> Option<PointRatioFit> {
    beta_from_ratio_samples(&blurred_ratio_samples(reference, sources, sparse), airlight)
}

/// [`beta_from_point_ratios`] on samples already taken by [`blurred_ratio_samples`] (one
/// `Vec` per source), so that a caller that also runs the joint fit blurs and samples once.
pub fn beta_from_ratio_samples(
    samples: &[Vec<RatioSample>],
    airlight: f32,
) -> Option<PointRatioFit> {
    // Only the equations depend on A.
    let per_source: Vec<Vec<(f64, f64)>> = samples
        .iter()
        .map(|s| ratio_equations(s, airlight))
        .collect();
    let mut fit = fit_through_origin(&per_source.concat())?;
    // Each source's β with its standard error widened by what an airlight error of
    // ±AIRLIGHT_SIGMA moves it: sources at different depth differences respond differently to
    // a wrong A₀, and that disagreement is not evidence of an exposure change.
    let mut terms = Vec::with_capacity(samples.len());
    for (eqs, samples) in per_source.iter().zip(samples) {
        let Some(f) = fit_through_origin(eqs) else {
            continue;
        };
        let shifted = |da: f32| {
            let a = (airlight + da).clamp(1e-3, 1.0);
            fit_through_origin(&ratio_equations(samples, a)).map(|g| g.beta)
        };
        let spread = match (shifted(AIRLIGHT_SIGMA), shifted(-AIRLIGHT_SIGMA)) {
            (Some(hi), Some(lo)) => 0.5 * (hi - lo),
            _ => 0.0,
        };
        let var = f.std_error.powi(2) + spread * spread;
        if var.is_finite() && var > 0.0 {
            terms.push((f.beta - fit.beta).powi(2) / var);
        }
    }
    fit.sources = terms.len();
    fit.source_consistency_chi2 = terms.iter().sum();
    Some(fit)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::simulate::mvs::walking_test_scene;
    use rand::{Rng, SeedableRng};

    #[test]
    fn chi2_quantile_matches_tables() {
        // 99.9 % points: 10.83 (1 dof), 16.27 (3), 29.59 (10); Wilson–Hilferty is 3 % high at 1.
        for (k, q) in [(1, 10.83), (3, 16.27), (10, 29.59)] {
            let got = chi2_quantile_999(k);
            assert!((got - q).abs() < 0.04 * q, "{k}: {got} vs {q}");
        }
        assert_eq!(chi2_quantile_999(0), 0.0);
    }

    #[test]
    fn robust_fit_ignores_outliers_and_reports_its_uncertainty() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let eqs: Vec<(f64, f64)> = (0..2000)
            .map(|i| {
                let x: f64 = rng.random_range(-0.2..0.2);
                let noise: f64 = rng.random_range(-0.01..0.01);
                // One equation in ten is an occlusion: an unrelated ratio.
                let y = if i % 10 == 0 {
                    rng.random_range(-1.0..1.0)
                } else {
                    0.55 * x + noise
                };
                (x, y)
            })
            .collect();
        let fit = fit_through_origin(&eqs).unwrap();
        assert!((fit.beta - 0.55).abs() < 0.01, "{fit:?}");
        assert!(fit.std_error > 0.0 && fit.std_error < 0.01, "{fit:?}");
        assert!(fit.is_reliable());
        // No depth differences: nothing to fit.
        assert!(fit_through_origin(&[(0.0, 0.1), (0.0, -0.2)]).is_none());
        assert!(fit_through_origin(&[]).is_none());
        // A handful of equations is never reliable, however well they fit.
        let few = fit_through_origin(&eqs[1..50]).unwrap();
        assert!(!few.is_reliable(), "{few:?}");
    }

    /// A simulated hazy room at reduced size with a walking trajectory: β within 0.05 with the
    /// true airlight; an exposure change between the views is caught by the source check.
    #[test]
    fn finds_beta_on_a_simulated_scene() {
        let scene = walking_test_scene(3);
        let (reference, sources) = scene.reference_and_sources();
        let sparse = scene.sparse_depth().unwrap();
        let fit = beta_from_point_ratios(&reference, &sources, &sparse, scene.airlight).unwrap();
        eprintln!("β gt {} fit {fit:?}", scene.beta);
        assert!(fit.is_reliable(), "{fit:?}");
        assert!(
            (fit.beta - f64::from(scene.beta)).abs() < 0.05,
            "gt {} fit {fit:?}",
            scene.beta
        );
        // Without the sources there is nothing to compare.
        assert!(beta_from_point_ratios(&reference, &[], &sparse, scene.airlight).is_none());
        // A 3 % exposure step in every source: the sources disagree and the fit says so.
        let brighter: Vec<ImageF32> = sources
            .iter()
            .map(|v| {
                let mut img = v.image.clone();
                for x in img.data_mut() {
                    *x = (*x * 1.03).min(1.0);
                }
                img
            })
            .collect();
        let exposed: Vec<View<'_>> = sources
            .iter()
            .zip(&brighter)
            .map(|(v, image)| View { image, ..*v })
            .collect();
        let fit = beta_from_point_ratios(&reference, &exposed, &sparse, scene.airlight).unwrap();
        assert!(!fit.is_reliable(), "{fit:?}");
        assert!(fit.source_consistency_chi2 > chi2_quantile_999(fit.sources - 1));
    }
}
