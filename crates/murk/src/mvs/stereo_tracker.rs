//! Rectified stereo over a stream of pairs from one rig, with the previous pair's depth as a
//! prior: each pair searches only a band of disparities around those the previous pair found,
//! instead of the whole configured range.
//!
//! A robot's scene changes little between frames, while the configured range must hold every
//! depth the rig may ever see (OpenCV users set `numDisparities` for the worst case). The work of
//! the plane sweep and of SGM is proportional to the number of planes, so a pair whose depths
//! span half the range costs about half as much.
//!
//! - **The band.** The previous pair's confident disparities from the [`PRIOR_QUANTILE`] to the
//!   `1 − PRIOR_QUANTILE` quantile, widened by [`BAND_MARGIN_FRACTION`] of their span (at least
//!   [`BAND_MARGIN_PX`] pixels) on each side, within the configured range, with the configured
//!   plane density. The quantiles are extreme on purpose: a near object that fills 0.3 % of the
//!   image must stay inside the band, because a surface outside it is not always seen at its
//!   ends (the consistency check rejects it, and the fill hides it).
//! - **When the prior is wrong.** Surfaces outside the band (an object that came closer, a scene
//!   cut) pile their winners onto the band's ends. When more than [`EDGE_FRACTION`] of the
//!   confident pixels sit within one plane of an end that is not the configured range's, the pair
//!   is computed again over the whole range, and the tracker starts over from that result.
//! - **Cold starts.** The first pair, the pair after [`StereoTracker::reset`], and a pair after
//!   one with fewer than [`MIN_CONFIDENT_FRACTION`] of its pixels confident search the whole
//!   range; so does a pair whose band would cover most of it.
//!
//! - **The photometric corrections.** The right camera's gains and both fall-offs start from the
//!   previous pair's ([`crate::mvs::depth::photometric`]): the fall-offs are kept and the gains
//!   confirmed on the new pair, or searched again where the exposure changed. Every
//!   [`REFRESH_PAIRS`] pairs carried, and after [`StereoTracker::reset`], they are searched from
//!   scratch.
//!
//! What is carried between pairs is the band (two numbers) and the corrections (a gain per
//! channel and two fall-offs), so a tracker's memory does not grow with the stream.

use crate::error::Result;
use crate::image::ImageF32;
use crate::monitor::Monitor;
use crate::mvs::depth::{PhotometricPrior, PhotometricSearch};
use crate::mvs::rectified::{
    estimate_rectified_from_prior, RectifiedDepth, RectifiedOptions, RectifiedRig, StereoRange,
};

/// Quantile of the previous pair's confident disparities at which the band starts (and, from
/// the top, ends): one pixel in a thousand may lie outside it.
pub const PRIOR_QUANTILE: f64 = 0.001;
/// The band's margin on each side, as a fraction of the previous disparities' span.
pub const BAND_MARGIN_FRACTION: f64 = 0.15;
/// The band's smallest margin on each side, pixels of disparity.
pub const BAND_MARGIN_PX: f64 = 4.0;
/// Share of confident pixels at a band end (one that is not the configured range's) above which
/// the pair is computed again over the whole range.
pub const EDGE_FRACTION: f64 = 0.01;
/// Share of pixels that must be confident for a result to seed the next band.
pub const MIN_CONFIDENT_FRACTION: f64 = 0.05;
/// A band that covers more than this share of the configured range is not worth narrowing.
pub const MAX_BAND_SHARE: f64 = 0.9;
/// Pairs in a row whose photometric corrections are carried before the next pair searches them
/// from scratch (3 s at 10 Hz): a fall-off misjudged on one pair does not stay for the session.
pub const REFRESH_PAIRS: usize = 30;

/// How a pair's depth was searched.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Search {
    /// The whole configured range (the first pair, or no usable prior).
    Full,
    /// The band around the previous pair's disparities.
    Band,
    /// The band was rejected (winners piled at its ends) and the whole range searched again.
    Restarted,
}

/// A pair's depth and how it was searched.
#[derive(Clone, Debug, PartialEq)]
pub struct TrackedDepth {
    /// The depth, disparity, confidence and plane set of the search that was kept.
    pub depth: RectifiedDepth,
    /// How it was searched.
    pub search: Search,
}

/// Depth of a stream of rectified pairs from one rig (see the module documentation).
#[derive(Clone, Debug)]
pub struct StereoTracker {
    rig: RectifiedRig,
    options: RectifiedOptions,
    /// The previous pair's confident disparities at [`PRIOR_QUANTILE`] and its complement,
    /// pixels.
    prior: Option<(f64, f64)>,
    /// The previous pair's photometric corrections.
    photometric: Option<PhotometricPrior>,
    /// Pairs in a row that carried the corrections.
    carried: usize,
}

impl StereoTracker {
    /// A tracker for `rig` whose pairs are searched over `options.range` (the whole range a
    /// cold start searches) with `options`' cost and parameters. Errors as
    /// [`RectifiedRig::validate`].
    pub fn new(rig: RectifiedRig, options: RectifiedOptions) -> Result<Self> {
        rig.validate()?;
        Ok(Self {
            rig,
            options,
            prior: None,
            photometric: None,
            carried: 0,
        })
    }

    /// Forgets the priors, the band and the photometric corrections: the next pair is a cold
    /// start (a known scene cut, a moved rig).
    pub fn reset(&mut self) {
        self.prior = None;
        self.photometric = None;
        self.carried = 0;
    }

    /// The band the next pair will search, disparities in pixels; `None` for the whole range.
    pub fn prior(&self) -> Option<(f64, f64)> {
        self.prior
    }

    /// The depth of the next pair. Errors as [`crate::mvs::estimate_rectified`]; an error
    /// leaves the priors as they were.
    pub fn estimate(
        &mut self,
        left: &ImageF32,
        right: &ImageF32,
        monitor: &Monitor,
    ) -> Result<TrackedDepth> {
        let grid = self.full_grid(left.width())?;
        let full = (grid.first, grid.last());
        let band = self.prior.and_then(|p| self.band(p, full));
        let (depth, search) = match band {
            None => (
                self.run(left, right, full, grid.count, monitor)?,
                Search::Full,
            ),
            Some(band) => {
                let (band, count) = grid.snap(band);
                let out = self.run(left, right, band, count, monitor)?;
                if piled_at_ends(&out, band, full) {
                    (
                        self.run(left, right, full, grid.count, monitor)?,
                        Search::Restarted,
                    )
                } else {
                    (out, Search::Band)
                }
            }
        };
        let searched_max = self.rig.disparity_of_depth(depth.planes.near);
        self.prior = confident_span(&depth, searched_max.max(0.0).ceil() as usize);
        self.carried = match depth.depth.photometric_search {
            PhotometricSearch::Carried => self.carried + 1,
            _ => 0,
        };
        self.photometric = Some(depth.depth.photometric_prior());
        Ok(TrackedDepth { depth, search })
    }

    /// The configured planes as disparities: the grid every band is cut from.
    fn full_grid(&self, width: usize) -> Result<Grid> {
        let range = self
            .options
            .range
            .unwrap_or_else(|| StereoRange::default_for_width(width));
        let planes = self.rig.planes(range, self.options.num_planes)?;
        let first = self.rig.disparity_of_depth(planes.far);
        let count = planes.num_planes.max(2);
        Ok(Grid {
            first,
            step: (self.rig.disparity_of_depth(planes.near) - first) / (count - 1) as f64,
            count,
        })
    }

    /// The band around the prior, within `full`; `None` when it would cover most of `full`.
    fn band(&self, (lo, hi): (f64, f64), full: (f64, f64)) -> Option<(f64, f64)> {
        let margin = (BAND_MARGIN_FRACTION * (hi - lo)).max(BAND_MARGIN_PX);
        let band = ((lo - margin).max(full.0), (hi + margin).min(full.1));
        (band.1 - band.0 < MAX_BAND_SHARE * (full.1 - full.0) && band.1 > band.0).then_some(band)
    }

    fn run(
        &self,
        left: &ImageF32,
        right: &ImageF32,
        (min_px, max_px): (f64, f64),
        num_planes: usize,
        monitor: &Monitor,
    ) -> Result<RectifiedDepth> {
        let options = RectifiedOptions {
            range: Some(StereoRange::Disparity { min_px, max_px }),
            num_planes: Some(num_planes),
            ..self.options
        };
        let photometric = self
            .photometric
            .as_ref()
            .filter(|_| self.carried < REFRESH_PAIRS);
        estimate_rectified_from_prior(left, right, &self.rig, &options, photometric, monitor)
    }
}

/// The configured planes in disparity (uniform: planes uniform in inverse depth are).
#[derive(Clone, Copy, Debug)]
struct Grid {
    first: f64,
    step: f64,
    count: usize,
}

impl Grid {
    fn last(&self) -> f64 {
        self.first + self.step * (self.count - 1) as f64
    }

    /// The smallest run of the grid's planes that covers `band`, and its plane count: a band
    /// searches the very planes the whole range would, so a pixel inside it gets the same
    /// candidates.
    fn snap(&self, (lo, hi): (f64, f64)) -> ((f64, f64), usize) {
        let last = self.count - 1;
        let i0 = (((lo - self.first) / self.step).floor().max(0.0) as usize).min(last);
        let i1 = (((hi - self.first) / self.step).ceil().max(0.0) as usize).clamp(i0 + 1, last);
        let i0 = i0.min(i1 - 1);
        (
            (
                self.first + self.step * i0 as f64,
                self.first + self.step * i1 as f64,
            ),
            i1 - i0 + 1,
        )
    }
}

/// Whether more than [`EDGE_FRACTION`] of the confident pixels won within one plane of a band
/// end that is not also an end of `full`. The left border, whose matches leave the right image
/// for the band's larger disparities, has no complete cost curve and is not counted: a real
/// change of the scene shows across the image.
fn piled_at_ends(out: &RectifiedDepth, band: (f64, f64), full: (f64, f64)) -> bool {
    let step = (band.1 - band.0) / (out.planes.num_planes.max(2) - 1) as f64;
    let (low_open, high_open) = (band.0 > full.0, band.1 < full.1);
    let (w, h) = out.disparity.dims();
    let border = (band.1.max(0.0).ceil() as usize).min(w);
    let (mut confident, mut at_ends) = (0usize, 0usize);
    for y in 0..h {
        for x in border..w {
            if out.depth.confidence.get(x, y, 0) <= 0.0 {
                continue;
            }
            confident += 1;
            let d = f64::from(out.disparity.get(x, y, 0));
            if (low_open && d <= band.0 + step) || (high_open && d >= band.1 - step) {
                at_ends += 1;
            }
        }
    }
    confident > 0 && at_ends as f64 > EDGE_FRACTION * confident as f64
}

/// The [`PRIOR_QUANTILE`] and `1 − PRIOR_QUANTILE` quantiles of the confident disparities right
/// of the left border of
/// `border` pixels (see [`piled_at_ends`]); `None` when fewer than [`MIN_CONFIDENT_FRACTION`] of
/// the pixels are confident.
fn confident_span(out: &RectifiedDepth, border: usize) -> Option<(f64, f64)> {
    let (w, h) = out.disparity.dims();
    let mut d = Vec::with_capacity(w * h);
    let rows = out.disparity.data().chunks_exact(w);
    for (disparity, confidence) in rows.zip(out.depth.confidence.data().chunks_exact(w)) {
        let from = border.min(w);
        for (&v, &c) in disparity[from..].iter().zip(&confidence[from..]) {
            if c > 0.0 && v.is_finite() {
                d.push(v);
            }
        }
    }
    if d.is_empty() || (d.len() as f64) < MIN_CONFIDENT_FRACTION * (w * h) as f64 {
        return None;
    }
    Some(quantile_pair(&mut d, PRIOR_QUANTILE))
}

/// The `q` and `1 − q` quantiles of non-empty `d` (`q ≤ ½`), the samples of ranks
/// `round((n − 1)·q)` and `round((n − 1)·(1 − q))` in ascending order; `d` is reordered. Two
/// selections, linear: sorting a 640×480 pair's disparities took 3 ms.
fn quantile_pair(d: &mut [f32], q: f64) -> (f64, f64) {
    let at = |p: f64| ((d.len() - 1) as f64 * p).round() as usize;
    let (lo, hi) = (at(q), at(1.0 - q));
    let (_, &mut low, above) = d.select_nth_unstable_by(lo, f32::total_cmp);
    let high = if hi > lo {
        *above.select_nth_unstable_by(hi - lo - 1, f32::total_cmp).1
    } else {
        low
    };
    (f64::from(low), f64::from(high))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Intrinsics;

    /// A textured plane at disparity `d` (a shift of the texture by `d` pixels).
    fn pair(d: f64, phase: f64) -> (ImageF32, ImageF32) {
        let texture = |x: f64, y: f64| {
            (0.5 + 0.2 * (x * 0.9 + phase).sin() * (y * 0.7).cos()
                + 0.15 * (x * 0.31 + y * 0.23 + phase).sin()) as f32
        };
        let (w, h) = (128, 64);
        (
            ImageF32::from_fn(w, h, |x, y| texture(x as f64, y as f64)),
            ImageF32::from_fn(w, h, |x, y| texture(x as f64 + d, y as f64)),
        )
    }

    fn tracker() -> StereoTracker {
        let rig = RectifiedRig::new(Intrinsics::new(100.0, 100.0, 63.5, 31.5), 0.1);
        StereoTracker::new(
            rig,
            RectifiedOptions {
                range: Some(StereoRange::Disparity {
                    min_px: 1.0,
                    max_px: 60.0,
                }),
                ..RectifiedOptions::default()
            },
        )
        .unwrap()
    }

    fn median_disparity(t: &TrackedDepth) -> f64 {
        let mut d: Vec<f32> = t.depth.disparity.data().to_vec();
        d.sort_by(f32::total_cmp);
        f64::from(d[d.len() / 2])
    }

    #[test]
    fn a_steady_scene_searches_a_band_and_a_jump_restarts_the_full_range() {
        let mut t = tracker();
        let (l, r) = pair(10.0, 0.0);
        let first = t.estimate(&l, &r, &Monitor::noop()).unwrap();
        assert_eq!(first.search, Search::Full);
        assert_eq!(first.depth.planes.num_planes, 60);
        let (lo, hi) = t.prior().expect("a confident first pair seeds the band");
        assert!(lo <= 10.0 && hi >= 10.0, "{lo}..{hi}");

        // The scene moves a little: the band holds it, with far fewer planes and the same answer.
        let (l, r) = pair(11.0, 0.3);
        let second = t.estimate(&l, &r, &Monitor::noop()).unwrap();
        assert_eq!(second.search, Search::Band);
        assert!(
            second.depth.planes.num_planes < 20,
            "{}",
            second.depth.planes.num_planes
        );
        assert!((median_disparity(&second) - 11.0).abs() < 0.3);

        // A cut to a much nearer scene: the winners pile at the band's top, and the pair is
        // computed again over the whole range.
        let (l, r) = pair(40.0, 1.0);
        let cut = t.estimate(&l, &r, &Monitor::noop()).unwrap();
        assert_eq!(cut.search, Search::Restarted);
        assert_eq!(cut.depth.planes.num_planes, 60);
        assert!((median_disparity(&cut) - 40.0).abs() < 0.3);
        assert!(t.prior().is_some_and(|(lo, hi)| lo <= 40.0 && hi >= 40.0));

        t.reset();
        assert_eq!(t.prior(), None);
    }

    #[test]
    fn bands_are_runs_of_the_configured_planes() {
        let g = Grid {
            first: 1.0,
            step: 0.5,
            count: 119,
        };
        assert_eq!(g.last(), 60.0);
        assert_eq!(g.snap((10.2, 20.1)), ((10.0, 20.5), 22));
        assert_eq!(g.snap((0.0, 2.0)), ((1.0, 2.0), 3));
        assert_eq!(g.snap((59.9, 70.0)), ((59.5, 60.0), 2));
    }

    #[test]
    fn a_band_covering_most_of_the_range_is_not_worth_it() {
        let t = tracker();
        assert_eq!(t.band((2.0, 58.0), (1.0, 60.0)), None);
        assert_eq!(t.band((20.0, 30.0), (1.0, 60.0)), Some((16.0, 34.0)));
        // Clamped to the configured range.
        assert_eq!(t.band((1.0, 10.0), (1.0, 60.0)), Some((1.0, 14.0)));
    }

    /// The photometric corrections are carried from the second pair on, searched again after
    /// [`REFRESH_PAIRS`] carried pairs, and after a reset.
    #[test]
    fn photometric_corrections_are_carried_then_refreshed() {
        let mut t = tracker();
        let (l, r) = pair(10.0, 0.0);
        let mut seen = Vec::new();
        for _ in 0..REFRESH_PAIRS + 3 {
            let out = t.estimate(&l, &r, &Monitor::noop()).unwrap();
            seen.push(out.depth.depth.photometric_search);
        }
        let carried = PhotometricSearch::Carried;
        let searched = PhotometricSearch::Searched;
        assert_eq!(seen[0], searched);
        assert!(
            seen[1..=REFRESH_PAIRS].iter().all(|s| *s == carried),
            "{seen:?}"
        );
        assert_eq!(seen[REFRESH_PAIRS + 1], searched);
        assert_eq!(seen[REFRESH_PAIRS + 2], carried);
        t.reset();
        let out = t.estimate(&l, &r, &Monitor::noop()).unwrap();
        assert_eq!(out.depth.depth.photometric_search, searched);
    }

    proptest::proptest! {
        /// The two selections find what sorting finds.
        #[test]
        fn quantile_pair_is_the_sorted_ranks(
            mut d in proptest::collection::vec(-100.0f32..100.0, 1..400),
            q in 0.0f64..0.5,
        ) {
            let mut sorted = d.clone();
            sorted.sort_by(f32::total_cmp);
            let at = |p: f64| f64::from(sorted[((sorted.len() - 1) as f64 * p).round() as usize]);
            proptest::prop_assert_eq!(quantile_pair(&mut d, q), (at(q), at(1.0 - q)));
        }
    }
}
