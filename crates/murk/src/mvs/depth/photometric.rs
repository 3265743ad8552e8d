//! Step 0's photometric corrections together: the lens's fall-off shared by every view
//! ([`vignetting`]), each source's fall-off relative to the reference's, and
//! each source's gains ([`exposure`]). They are searched from scratch, or, for
//! the next pair of a stream, carried from the previous pair and confirmed.
//!
//! **Why carry.** A rig's lenses do not change between frames, and its exposure changes far
//! more slowly than its frame rate. The search costs a tenth of a 640×480 stereo pair's time
//! (grids and Brent's method over the gains and both fall-offs, on samples swept over every
//! plane); a stream can start where the previous pair ended.
//!
//! **What is carried, and how it is checked** ([`PhotometricPrior`]):
//! - The fall-offs are taken as they are: they belong to the lenses. A stream searches them
//!   again now and then ([`StereoTracker`](crate::mvs::StereoTracker) every
//!   [`REFRESH_PAIRS`](crate::mvs::stereo_tracker::REFRESH_PAIRS) pairs), so one unlucky first
//!   pair does not decide a whole session.
//! - The gains are confirmed on every pair: the pair's own samples are collected as the search
//!   collects them, and the exact L1 steps of the refinement ([`exposure::refine_gains`]) start
//!   from the carried gains. Where a channel moves by more than [`GAIN_CHANGE`], the exposure has
//!   changed (auto-exposure, a gain switch) and everything is searched from scratch, as for a
//!   first pair. Otherwise the refined gains are this pair's.

use crate::image::ImageF32;
use crate::mvs::cost_volume::{views_over, CostKind, View};
use crate::mvs::plane_sweep::PlaneSet;

use super::{exposure, vignetting, DepthParams};

/// How a result's photometric corrections were found.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum PhotometricSearch {
    /// Searched from scratch: no prior was given, or it did not fit the views, or the
    /// corrections were off.
    #[default]
    Searched,
    /// The prior's fall-offs were kept and its gains confirmed (moved by at most
    /// [`GAIN_CHANGE`]) and refined on this pair.
    Carried,
    /// A prior was given, but a gain moved by more than [`GAIN_CHANGE`]: searched from scratch.
    ExposureChanged,
}

/// The corrections of one result, to start the next pair of the same rig from
/// ([`DepthResult::photometric_prior`](super::DepthResult::photometric_prior)).
#[derive(Clone, Debug, PartialEq)]
pub struct PhotometricPrior {
    /// Each source's gains as estimated, before [`exposure::DEAD_BAND`] (source-major, one per
    /// channel).
    pub estimated_gains: Vec<f32>,
    /// The shared fall-off that was divided out ([`vignetting::applied_falloff`]).
    pub vignetting_falloff: f32,
    /// Each source's relative fall-off that was divided out
    /// ([`vignetting::applied_relative_falloff`]).
    pub source_falloffs: Vec<f32>,
}

/// Largest relative move of a carried gain that confirms it: half of [`exposure::DEAD_BAND`].
/// On a steady stream a pair's own estimate moves by the noise of the data, 0.01–0.14 % on
/// the simulator's scenes; an exposure change of half the dead band or more is searched again.
pub const GAIN_CHANGE: f32 = 0.5 * exposure::DEAD_BAND;

/// The corrections of one pair, before the dead band is applied to the gains.
pub(super) struct Corrections {
    /// The shared fall-off divided out of every view (0: none).
    pub(super) falloff: f32,
    /// The views with `falloff` divided out (reference, then sources), `None` when it is 0.
    pub(super) devignetted: Option<(ImageF32, Vec<ImageF32>)>,
    /// Each source's relative fall-off (0: none).
    pub(super) source_falloffs: Vec<f32>,
    /// Each source's gains as estimated, source-major.
    pub(super) gains: Vec<f32>,
    /// How they were found.
    pub(super) search: PhotometricSearch,
}

/// The corrections of `sources` against `reference` as `params.photometric` asks for them:
/// from `prior` when it is given, fits the views, and its gains hold (module docs), searched
/// otherwise.
pub(super) fn corrections(
    reference: &View<'_>,
    sources: &[View<'_>],
    planes: &PlaneSet,
    kind: CostKind,
    params: &DepthParams,
    prior: Option<&PhotometricPrior>,
) -> Corrections {
    let channels = reference.image.channels();
    let fits = |p: &PhotometricPrior| {
        p.estimated_gains.len() == sources.len() * channels
            && p.source_falloffs.len() == sources.len()
            && p.estimated_gains.iter().all(|g| g.is_finite() && *g > 0.0)
            && p.vignetting_falloff.is_finite()
            && p.source_falloffs.iter().all(|d| d.is_finite())
    };
    let any_on =
        params.photometric.exposure_compensation || params.photometric.vignetting_compensation;
    match prior.filter(|p| any_on && fits(p)) {
        Some(p) => {
            carried(reference, sources, planes, kind, params, p).unwrap_or_else(|| Corrections {
                search: PhotometricSearch::ExposureChanged,
                ..searched(reference, sources, planes, kind, params)
            })
        }
        None => searched(reference, sources, planes, kind, params),
    }
}

/// The prior's fall-offs, and its gains refined on this pair's samples; `None` when a gain moved
/// by more than [`GAIN_CHANGE`].
fn carried(
    reference: &View<'_>,
    sources: &[View<'_>],
    planes: &PlaneSet,
    kind: CostKind,
    params: &DepthParams,
    prior: &PhotometricPrior,
) -> Option<Corrections> {
    let channels = reference.image.channels();
    let (expo, vign) = (
        params.photometric.exposure_compensation,
        params.photometric.vignetting_compensation,
    );
    let falloff = if vign { prior.vignetting_falloff } else { 0.0 };
    let devignetted = devignette(reference, sources, falloff);
    let (reference, sources) = views_over(reference, sources, &devignetted);
    // The relative fall-offs are estimated only with both compensations on (as searched).
    let source_falloffs = if vign && expo {
        prior.source_falloffs.clone()
    } else {
        vec![0.0; sources.len()]
    };
    let mut gains = vec![1.0f32; sources.len() * channels];
    if expo {
        for ((out, start), (source, &delta)) in gains
            .chunks_exact_mut(channels)
            .zip(prior.estimated_gains.chunks_exact(channels))
            .zip(sources.iter().zip(&source_falloffs))
        {
            let samples = exposure::Samples::collect(&reference, source, planes, kind);
            let samples = if delta != 0.0 {
                samples.with_source_falloff(delta)
            } else {
                samples
            };
            let refined = exposure::refine_gains(&samples, start.to_vec(), exposure::REFINE_ROUNDS);
            if refined
                .iter()
                .zip(start)
                .any(|(g, g0)| (g / g0 - 1.0).abs() > GAIN_CHANGE)
            {
                return None;
            }
            out.copy_from_slice(&refined);
        }
    }
    Some(Corrections {
        falloff,
        devignetted,
        source_falloffs,
        gains,
        search: PhotometricSearch::Carried,
    })
}

/// The views with the fall-off `falloff` divided out, `None` when it is 0.
fn devignette(
    reference: &View<'_>,
    sources: &[View<'_>],
    falloff: f32,
) -> Option<(ImageF32, Vec<ImageF32>)> {
    (falloff != 0.0).then(|| {
        (
            vignetting::compensate(reference.image, falloff),
            sources
                .iter()
                .map(|s| vignetting::compensate(s.image, falloff))
                .collect(),
        )
    })
}

/// The corrections searched from scratch.
fn searched(
    reference: &View<'_>,
    sources: &[View<'_>],
    planes: &PlaneSet,
    kind: CostKind,
    params: &DepthParams,
) -> Corrections {
    let channels = reference.image.channels();
    // Each source's samples are collected once for its gains and the fall-off estimate.
    let samples: Vec<exposure::Samples> =
        if params.photometric.exposure_compensation || params.photometric.vignetting_compensation {
            sources
                .iter()
                .map(|s| exposure::Samples::collect(reference, s, planes, kind))
                .collect()
        } else {
            Vec::new()
        };
    let gains_of = |samples: &[exposure::Samples]| -> Vec<f32> {
        if params.photometric.exposure_compensation {
            samples
                .iter()
                .flat_map(exposure::gains_from_samples)
                .collect()
        } else {
            vec![1.0; sources.len() * channels]
        }
    };
    // Each source's own fall-off relative to the reference's (a lens that differs) comes
    // first: a gain that varies over the image, seen without any displacement, so it is
    // estimated with the gains and only where they are. Left in, it would be read as a shared
    // fall-off (only the right lens of the hazy Aloe pair 20 % darker at the corners: 0.10).
    let relative = |samples: &[exposure::Samples], mut gains: Vec<f32>| -> (Vec<f32>, Vec<f32>) {
        // One per source, also when no samples were collected (both compensations off).
        let mut deltas = vec![0.0f32; sources.len()];
        if !(params.photometric.vignetting_compensation && params.photometric.exposure_compensation)
        {
            return (deltas, gains);
        }
        for ((delta, gains), samples) in deltas
            .iter_mut()
            .zip(gains.chunks_exact_mut(channels))
            .zip(samples)
        {
            if gains.iter().any(|&g| exposure::at_bound(g)) {
                continue;
            }
            let (d, refined) = vignetting::estimate_relative_falloff(samples, gains);
            *delta = vignetting::applied_relative_falloff(d);
            if *delta != 0.0 {
                gains.copy_from_slice(&refined);
            }
        }
        (deltas, gains)
    };
    let (raw_falloffs, raw_gains) = relative(&samples, gains_of(&samples));
    // The lens's fall-off shared by every view, with each source's channels divided by the
    // gains and its relative fall-off found without it. A source whose gain stopped at the
    // search's bound is left out: the brightness its gain did not remove would be read as a
    // fall-off (a source 2.5× brighter drove it to the bound).
    let falloff = if params.photometric.vignetting_compensation {
        let relieved: Vec<Option<exposure::Samples>> = samples
            .iter()
            .zip(&raw_falloffs)
            .map(|(s, &d)| (d != 0.0).then(|| s.with_source_falloff(d)))
            .collect();
        let usable: Vec<(&exposure::Samples, &[f32])> = samples
            .iter()
            .zip(&relieved)
            .map(|(s, r)| r.as_ref().unwrap_or(s))
            .zip(raw_gains.chunks_exact(channels))
            .filter(|(_, g)| !g.iter().any(|&g| exposure::at_bound(g)))
            .collect();
        vignetting::applied_falloff(vignetting::estimate_falloff(&usable))
    } else {
        0.0
    };
    let devignetted = devignette(reference, sources, falloff);
    // The samples again once the shared fall-off is out of the views, and the gains and
    // relative fall-offs from them: it had biased them toward its mean.
    let (source_falloffs, gains) = if devignetted.is_some() {
        let (reference, sources) = views_over(reference, sources, &devignetted);
        let samples: Vec<exposure::Samples> = sources
            .iter()
            .map(|s| exposure::Samples::collect(&reference, s, planes, kind))
            .collect();
        relative(&samples, gains_of(&samples))
    } else {
        (raw_falloffs, raw_gains)
    };
    Corrections {
        falloff,
        devignetted,
        source_falloffs,
        gains,
        search: PhotometricSearch::Searched,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::atmosphere::AtmosphereParams;
    use crate::monitor::Monitor;
    use crate::mvs::cost_volume::DehazingOptions;
    use crate::mvs::depth::{estimate_depth, estimate_depth_from_prior, DepthPrior, DepthResult};
    use crate::simulate::mvs::{simulate_mvs, MvsScene, MvsSimConfig};

    /// The simulator's hazy 160×120 rectified pair.
    fn scene() -> MvsScene {
        let cfg = MvsSimConfig {
            seed: 2,
            num_views: 2,
            rectified_pair: true,
            ..MvsSimConfig::with_size(160, 120)
        };
        simulate_mvs(&cfg, &Monitor::noop()).unwrap()
    }

    /// The depth of the scene's pair with the source recorded at `gain`, from `prior`.
    fn depth(scene: &MvsScene, gain: f32, prior: Option<&PhotometricPrior>) -> DepthResult {
        let views = scene.hazy_views();
        let reference = views[scene.reference];
        let mut brighter = views[1 - scene.reference].image.clone();
        brighter.data_mut().iter_mut().for_each(|v| *v *= gain);
        let source = View {
            image: &brighter,
            ..views[1 - scene.reference]
        };
        let planes = PlaneSet::new(1.5, 15.0, 64).unwrap();
        let haze = CostKind::DehazingWith(
            AtmosphereParams {
                airlight: scene.airlight,
                beta: scene.beta,
            },
            DehazingOptions::default(),
        );
        let params = DepthParams::default();
        match prior {
            Some(p) => estimate_depth_from_prior(
                &reference,
                &[source],
                &planes,
                haze,
                &params,
                &DepthPrior {
                    photometric: Some(p),
                    ..DepthPrior::default()
                },
                &Monitor::noop(),
            ),
            None => estimate_depth(
                &reference,
                &[source],
                &planes,
                haze,
                &params,
                &Monitor::noop(),
            ),
        }
        .unwrap()
    }

    /// C.P. (§3.4.3): the share of pixels whose depth is within 10 % of the truth.
    fn cp(scene: &MvsScene, r: &DepthResult) -> f64 {
        let truth = scene.views[scene.reference].depth.data();
        let good = r
            .z_depth
            .data()
            .iter()
            .zip(truth)
            .filter(|(z, t)| (*z - *t).abs() < 0.1 * *t)
            .count();
        good as f64 / truth.len() as f64
    }

    fn within(gains: &[f32], truth: f32, tolerance: f32) -> bool {
        gains.iter().all(|g| (g / truth - 1.0).abs() < tolerance)
    }

    /// A pair of the same exposure carries the corrections to the same answer; a pair whose
    /// exposure changed by 3 % is searched again and gets what a search from scratch gets.
    #[test]
    fn a_steady_exposure_is_carried_and_a_changed_one_searched_again() {
        let scene = scene();
        let first = depth(&scene, 1.08, None);
        assert_eq!(first.photometric_search, PhotometricSearch::Searched);
        assert!(
            within(&first.estimated_gains, 1.08, 0.005),
            "{:?}",
            first.estimated_gains
        );
        let prior = first.photometric_prior();

        let steady = depth(&scene, 1.08, Some(&prior));
        assert_eq!(steady.photometric_search, PhotometricSearch::Carried);
        for (a, b) in steady.estimated_gains.iter().zip(&first.estimated_gains) {
            assert!((a / b - 1.0).abs() < 1e-3, "{a} against {b}");
        }
        // Gains 0.02 % apart flip a few winners on far, hazy surfaces (3 % of the pixels move by
        // more than a plane here), the search's own noise; the accuracy stays.
        let (a, b) = (cp(&scene, &steady), cp(&scene, &first));
        assert!(
            (a - b).abs() < 0.01,
            "C.P. {a} carried against {b} searched"
        );

        let changed = depth(&scene, 1.08 * 1.03, Some(&prior));
        assert_eq!(
            changed.photometric_search,
            PhotometricSearch::ExposureChanged
        );
        let searched = depth(&scene, 1.08 * 1.03, None);
        assert_eq!(changed.estimated_gains, searched.estimated_gains);
        assert_eq!(changed.inverse_depth, searched.inverse_depth);
        assert!(within(&changed.estimated_gains, 1.08 * 1.03, 0.005));
    }

    /// A prior that does not fit the views (another channel count, a gain that is not a gain)
    /// is not used: the result is the search's, bit for bit.
    #[test]
    fn a_prior_of_other_cameras_is_searched_from_scratch() {
        let scene = scene();
        let searched = depth(&scene, 1.0, None);
        for prior in [
            PhotometricPrior {
                estimated_gains: vec![1.0],
                vignetting_falloff: 0.0,
                source_falloffs: vec![0.0],
            },
            PhotometricPrior {
                estimated_gains: vec![1.0, f32::NAN, 1.0],
                vignetting_falloff: 0.0,
                source_falloffs: vec![0.0],
            },
            PhotometricPrior {
                estimated_gains: vec![1.0; 3],
                vignetting_falloff: 0.0,
                source_falloffs: vec![0.0, 0.0],
            },
        ] {
            let out = depth(&scene, 1.0, Some(&prior));
            assert_eq!(out.photometric_search, PhotometricSearch::Searched);
            assert_eq!(out, searched);
        }
    }
}
