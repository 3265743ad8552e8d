//! The share of the joint fit's errors that comes from where SfM put its points: how far `A`
//! and β move when the points are sampled with twice the blur.
//!
//! The equations of [`crate::params::joint_fit`] read each point's intensity in the reference
//! and in a source (Eq. 3.3). SIFT puts SfM's keypoints on blobs and corners, where the sampled
//! value depends most on the blur. The footprint match ([`crate::params::footprint`]) removes
//! most of the difference between the views' footprints; what it leaves depends on the texture
//! at the points, not on the images' noise. It moves every point on one kind of texture the same
//! way, so neither the Gauss–Newton covariance nor the jackknives over sources and points see
//! it. With exact poses and the points on the true surface, COLMAP's keypoints left β 7 % high
//! at a base blur of 1 px and 13 % high at 2 px on forward-moving 512×384 scenes. Random surface
//! points left it within 2 % at either blur (docs/scattering-params.md).
//!
//! So the bias at keypoints grows with the blur, about in proportion, and the move from the base
//! blur σ₀ to 2σ₀ is about the bias left at σ₀. [`sampling_share`] refits the fit's own model on
//! samples at 2σ₀ ([`JointFit::refit`]) and takes `|θ(2σ₀) − θ(σ₀)|` for `θ = A, β` as a
//! further standard error, added in quadrature ([`JointFit::add_sfm_share`]).
//!
//! It is a bound, not a correction. The extrapolation `2θ(σ₀) − θ(2σ₀)` was measured on the
//! COLMAP survey and made both errors larger: the wider blur also mixes in surfaces at other
//! depths, so the move is not all bias.

use crate::mvs::View;
use crate::params::joint_fit::{JointFit, MAX_RELATIVE_BETA_ERROR};
use crate::params::point_ratio::{blurred_ratio_samples_at, sample_blur_sigma_px};
use crate::params::sparse::SparseDepth;

/// The wider blur of [`sampling_share`] over the base blur.
pub const WIDE_BLUR_FACTOR: f64 = 2.0;

/// What sampling the points with a wider blur does to a joint fit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SamplingShare {
    /// The base blur of the fit's samples, pixels ([`sample_blur_sigma_px`]).
    pub base_blur_px: f64,
    /// The wider blur, pixels ([`WIDE_BLUR_FACTOR`] times the base).
    pub wide_blur_px: f64,
    /// `[A, β]` (β per scene unit) of the same model refitted on samples at the wider blur;
    /// `None` when that refit failed (too few equations whose windows stay in the images, or
    /// no convergence).
    pub refit: Option<[f64; 2]>,
    /// The share `[|ΔA|, |Δβ|]` of the standard errors; `None` when the refit failed.
    pub share: Option<[f64; 2]>,
}

impl SamplingShare {
    /// The sentence for a fit whose verdict this share decided: its numbers, what it means and
    /// what would help.
    pub fn describe(&self, fit: &JointFit) -> String {
        let effect = match (self.refit, self.share) {
            (Some([a, b]), Some([_, share_b])) => format!(
                "sampled with a {:.1} px blur instead of {:.1} px they give A = {a:.3} and beta = \
                 {b:.4} instead of {:.3} and {:.4}, so beta's standard error is {:.0} % \
                 (identifiable below {:.0} %; {:.0} % from the sampling alone)",
                self.wide_blur_px,
                self.base_blur_px,
                fit.airlight,
                fit.beta,
                100.0 * fit.beta_std_error / fit.beta,
                100.0 * MAX_RELATIVE_BETA_ERROR,
                100.0 * share_b / fit.beta
            ),
            _ => format!(
                "a refit on samples with a {:.1} px blur failed, so how much the sampling moves \
                 beta is unknown",
                self.wide_blur_px
            ),
        };
        format!(
            "the SfM points' intensities depend on how they are sampled: {effect}. SfM puts its \
             points on blobs and corners, where the blur matters most; more points (a lower \
             SIFT peak threshold) or frames that move towards the scene help"
        )
    }
}

/// The sampling share of `fit`, a joint fit on the samples of `sparse` in `reference` and
/// `sources` at the base blur: see the module docs.
pub fn sampling_share(
    reference: &View<'_>,
    sources: &[View<'_>],
    sparse: &SparseDepth,
    fit: &JointFit,
) -> SamplingShare {
    let base_blur_px = f64::from(sample_blur_sigma_px(reference.image.width()));
    let wide_blur_px = WIDE_BLUR_FACTOR * base_blur_px;
    let wide = blurred_ratio_samples_at(reference, sources, sparse, wide_blur_px);
    let refit = fit.refit(&wide);
    SamplingShare {
        base_blur_px,
        wide_blur_px,
        refit,
        share: refit.map(|[a, b]| [(a - fit.airlight).abs(), (b - fit.beta).abs()]),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::joint_fit::{fit_joint_samples, JointPriors};
    use crate::params::point_ratio::blurred_ratio_samples;
    use crate::simulate::mvs::walking_test_scene;

    /// The simulator's points split by how far the reference's value at each stands out of its
    /// 5×5 neighbourhood: the third that stands out most (where SIFT would put keypoints) and
    /// the third that stands out least.
    fn points_by_contrast(seed: u64) -> [(f64, f64); 2] {
        let scene = walking_test_scene(seed);
        let (reference, sources) = scene.reference_and_sources();
        let sparse = scene.sparse_depth().unwrap();
        let img = reference.image;
        let contrast = |u: f32, v: f32| {
            let (x, y) = (u.round() as isize, v.round() as isize);
            let at = |x: isize, y: isize| {
                let cx = x.clamp(0, img.width() as isize - 1) as usize;
                let cy = y.clamp(0, img.height() as isize - 1) as usize;
                (0..img.channels()).map(|c| img.get(cx, cy, c)).sum::<f32>()
            };
            let mean = (-2..=2)
                .flat_map(|dy| (-2..=2).map(move |dx| (dx, dy)))
                .map(|(dx, dy)| at(x + dx, y + dy))
                .sum::<f32>()
                / 25.0;
            (at(x, y) - mean).abs()
        };
        let mut samples = sparse.samples().to_vec();
        samples.sort_by(|a, b| contrast(b.u, b.v).total_cmp(&contrast(a.u, a.v)));
        let third = samples.len() / 3;
        let priors = JointPriors {
            airlight: f64::from(scene.airlight),
            airlight_sigma: 0.05,
            gain_sigma: 0.2,
            beta_start: 0.5,
            falloff_sigma: 0.0,
            relative_falloff_sigma: 0.0,
        };
        let share_of = |part: Vec<_>| {
            let sparse = SparseDepth::from_samples(img.width(), img.height(), part);
            let fit = fit_joint_samples(
                &blurred_ratio_samples(&reference, &sources, &sparse),
                &sparse,
                &priors,
            )
            .unwrap();
            let s = sampling_share(&reference, &sources, &sparse, &fit);
            assert_eq!(s.wide_blur_px, WIDE_BLUR_FACTOR * s.base_blur_px);
            let [a, b] = s.share.unwrap();
            (a, b / fit.beta)
        };
        [
            share_of(samples[..third].to_vec()),
            share_of(samples[samples.len() - third..].to_vec()),
        ]
    }

    /// The bias the share bounds comes from points on structure: over ten scenes the third of
    /// the points that stands out of its neighbourhood moves β about twice as far with the blur
    /// as the third that does not (0.100 against 0.040 of β on average; more in 8 of 10).
    #[test]
    fn points_that_stand_out_of_their_texture_move_more_with_the_blur() {
        let shares: Vec<[(f64, f64); 2]> = (1..=10).map(points_by_contrast).collect();
        let mean = |k: usize| shares.iter().map(|s| s[k].1).sum::<f64>() / shares.len() as f64;
        let (blob, flat) = (mean(0), mean(1));
        let more = shares.iter().filter(|s| s[0].1 > s[1].1).count();
        assert!(blob > 2.0 * flat && more >= 7, "{shares:?}");
    }
}
