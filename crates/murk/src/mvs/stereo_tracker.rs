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
//! - **Windows by rows.** A scene is layered by image row (the floor near at the bottom, far
//!   walls at the horizon), so within the band each group of [`WINDOW_ROWS`] rows searches only
//!   its own window ([`crate::mvs::PlaneWindows`]): the quantiles of the previous pair's
//!   confident disparities in those rows and [`WINDOW_REACH_ROWS`] rows above and below (the
//!   scene moves between pairs), widened by the same margins. Rows where fewer than
//!   [`MIN_CONFIDENT_FRACTION`] of the pixels were confident (low texture, a region just
//!   uncovered) search the whole band. A window inside the last one and narrower by less than
//!   two margins stays as it was, so that a still scene settles on one set of windows (and one
//!   depth) instead of alternating between two.
//! - **When the prior is wrong.** Surfaces outside the band (an object that came closer, a scene
//!   cut) pile their winners onto the band's ends. When more than [`EDGE_FRACTION`] of the
//!   confident pixels of the image, or of any group of rows, sit within one plane of an end of
//!   their window that is not the configured range's, the pair is computed again over the whole
//!   range, and the tracker starts over from that result.
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
//! What is carried between pairs is the band (two numbers), two numbers per
//! [`WINDOW_ROWS`]` / 2` rows, and the corrections (a gain per channel and two fall-offs), so a
//! tracker's memory does not grow with the stream.

use crate::error::Result;
use crate::image::ImageF32;
use crate::monitor::Monitor;
use crate::mvs::depth::{DepthPrior, PhotometricPrior, PhotometricSearch, PlaneWindows};
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
/// Rows per group that searches its own window of the band.
pub const WINDOW_ROWS: usize = 32;
/// Rows above and below a group whose previous disparities its window also holds.
pub const WINDOW_REACH_ROWS: usize = 16;
/// Windows whose planes, summed over the rows, exceed this share of the band's are not worth
/// it: the whole band is searched.
pub const MAX_WINDOW_SHARE: f64 = 0.9;
/// Pairs in a row whose photometric corrections are carried before the next pair searches them
/// from scratch (3 s at 10 Hz): a fall-off misjudged on one pair does not stay for the session.
pub const REFRESH_PAIRS: usize = 30;

/// How a pair's depth was searched.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Search {
    /// The whole configured range (the first pair, or no usable prior).
    Full,
    /// The band around the previous pair's disparities, each group of rows within its window
    /// where the previous pair saw its rows' depths.
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
    /// The windows of `depth.planes` the rows searched ([`WINDOW_ROWS`] rows each); `None`
    /// where every row searched every plane.
    pub windows: Option<PlaneWindows>,
}

/// Depth of a stream of rectified pairs from one rig (see the module documentation).
#[derive(Clone, Debug)]
pub struct StereoTracker {
    rig: RectifiedRig,
    options: RectifiedOptions,
    /// The previous pair's confident disparities at [`PRIOR_QUANTILE`] and its complement,
    /// pixels.
    prior: Option<(f64, f64)>,
    /// The same quantiles over each [`SPAN_ROWS`] rows of the previous pair, `None` where too
    /// few of their pixels were confident.
    row_spans: Vec<Option<(f64, f64)>>,
    /// The windows the previous pair searched, disparities per group of [`WINDOW_ROWS`] rows
    /// (`None`: the whole band); empty when it searched without windows.
    window_spans: Vec<Option<(f64, f64)>>,
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
            row_spans: Vec::new(),
            window_spans: Vec::new(),
            photometric: None,
            carried: 0,
        })
    }

    /// Forgets the priors, the band and the photometric corrections: the next pair is a cold
    /// start (a known scene cut, a moved rig).
    pub fn reset(&mut self) {
        self.prior = None;
        self.row_spans.clear();
        self.window_spans.clear();
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
        let (range, count) = band.map_or((full, grid.count), |b| grid.snap(b));
        let (windows, spans) = self.windows(range, count, grid.step, left.height()).unzip();
        let (depth, search, windows) = if band.is_none() && windows.is_none() {
            (
                self.run(left, right, full, grid.count, None, monitor)?,
                Search::Full,
                None,
            )
        } else {
            let out = self.run(left, right, range, count, windows.as_ref(), monitor)?;
            if piled_at_ends(&out, range, full, windows.as_ref()) {
                (
                    self.run(left, right, full, grid.count, None, monitor)?,
                    Search::Restarted,
                    None,
                )
            } else {
                (out, Search::Band, windows)
            }
        };
        self.window_spans = match (&windows, spans) {
            (Some(_), Some(spans)) => spans,
            _ => Vec::new(),
        };
        let searched_max = self.rig.disparity_of_depth(depth.planes.near);
        let border = searched_max.max(0.0).ceil() as usize;
        self.prior = confident_span(&depth, border);
        self.row_spans = if self.prior.is_some() {
            row_spans(&depth, border)
        } else {
            Vec::new()
        };
        self.carried = match depth.depth.photometric_search {
            PhotometricSearch::Carried => self.carried + 1,
            _ => 0,
        };
        self.photometric = Some(depth.depth.photometric_prior());
        Ok(TrackedDepth {
            depth,
            search,
            windows,
        })
    }

    /// The windows of the `count` planes from disparity `range.0` on (`step` pixels apart) for
    /// an `h`-row pair, from the previous pair's spans by rows, and each group's window in
    /// disparities (`None`: the whole band); `None` without spans, or when they would search
    /// most of the planes anyway.
    fn windows(
        &self,
        range: (f64, f64),
        count: usize,
        step: f64,
        h: usize,
    ) -> Option<(PlaneWindows, Vec<Span>)> {
        let margin = self.prior.map(margin_of)?;
        if self.row_spans.is_empty() || count < 2 || step <= 0.0 {
            return None;
        }
        let groups = h.div_ceil(WINDOW_ROWS).max(1);
        let spans: Vec<Span> = (0..groups)
            .map(|g| {
                let rows = (g * WINDOW_ROWS).saturating_sub(WINDOW_REACH_ROWS)
                    ..((g + 1) * WINDOW_ROWS + WINDOW_REACH_ROWS).min(h);
                let spans = (rows.start / SPAN_ROWS..rows.end.div_ceil(SPAN_ROWS))
                    .map(|k| self.row_spans.get(k).copied().flatten());
                let mut union: Option<(f64, f64)> = None;
                for span in spans {
                    // A group that cannot see its rows' depths searches the whole band.
                    let (lo, hi) = span?;
                    union = Some(union.map_or((lo, hi), |(a, b)| (a.min(lo), b.max(hi))));
                }
                let (lo, hi) = union?;
                let new = (lo - margin, hi + margin);
                // A window inside the last one, narrower by less than two margins, stays as it
                // was. Without this a still scene's windows alternate between two sets, and so
                // do its depths: a narrow window holds some pixels at its end, which widens the
                // next one, which frees them, which narrows the one after (hazy Aloe).
                match self.window_spans.get(g).copied().flatten() {
                    Some(old) if old.0 <= new.0 && new.1 <= old.1 => {
                        Some(if (new.0 - old.0) + (old.1 - new.1) <= 2.0 * margin {
                            old
                        } else {
                            new
                        })
                    }
                    _ => Some(new),
                }
            })
            .collect();
        let last = count - 1;
        let windows: Vec<std::ops::Range<usize>> = spans
            .iter()
            .map(|span| match span {
                Some((lo, hi)) => {
                    let i0 = (((lo - range.0) / step).floor().max(0.0) as usize).min(last);
                    let i1 = (((hi - range.0) / step).ceil().max(0.0) as usize).min(last);
                    i0..i1.max(i0) + 1
                }
                None => 0..count,
            })
            .collect();
        let windows = PlaneWindows::new(WINDOW_ROWS, windows).ok()?;
        let share = windows.planes_searched(h) as f64 / (h * count) as f64;
        (share <= MAX_WINDOW_SHARE).then_some((windows, spans))
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
        let margin = margin_of((lo, hi));
        let band = ((lo - margin).max(full.0), (hi + margin).min(full.1));
        (band.1 - band.0 < MAX_BAND_SHARE * (full.1 - full.0) && band.1 > band.0).then_some(band)
    }

    fn run(
        &self,
        left: &ImageF32,
        right: &ImageF32,
        (min_px, max_px): (f64, f64),
        num_planes: usize,
        windows: Option<&PlaneWindows>,
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
        let prior = DepthPrior {
            photometric,
            windows,
        };
        estimate_rectified_from_prior(left, right, &self.rig, &options, &prior, monitor)
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

/// Whether more than [`EDGE_FRACTION`] of the confident pixels of the image, or of all the
/// pixels of any group of `windows`' rows, won within one plane of an end of their window (the
/// band's, without windows) that is not also an end of `full`. The left border, whose matches leave the right
/// image for the band's larger disparities, has no complete cost curve and is not counted: a
/// real change of the scene shows across the image.
fn piled_at_ends(
    out: &RectifiedDepth,
    band: (f64, f64),
    full: (f64, f64),
    windows: Option<&PlaneWindows>,
) -> bool {
    let step = (band.1 - band.0) / (out.planes.num_planes.max(2) - 1) as f64;
    let (w, h) = out.disparity.dims();
    let border = (band.1.max(0.0).ceil() as usize).min(w);
    let group_rows = windows.map_or(h.max(1), |p| p.group_rows());
    let (mut confident, mut at_ends) = (0usize, 0usize);
    let mut piled_group = false;
    for rows in (0..h).step_by(group_rows.max(1)) {
        let plane = windows.map_or(0..out.planes.num_planes, |p| p.of_row(rows));
        let lo = band.0 + step * plane.start as f64;
        let hi = band.0 + step * (plane.end - 1) as f64;
        let (low_open, high_open) = (lo > full.0, hi < full.1);
        let (mut c, mut e) = (0usize, 0usize);
        for y in rows..(rows + group_rows).min(h) {
            for x in border..w {
                if out.depth.confidence.get(x, y, 0) <= 0.0 {
                    continue;
                }
                c += 1;
                let d = f64::from(out.disparity.get(x, y, 0));
                if (low_open && d <= lo + step) || (high_open && d >= hi - step) {
                    e += 1;
                }
            }
        }
        // A group's share is of all its pixels, so a group with few confident ones does not
        // restart the pair on a handful of them.
        let pixels = ((rows + group_rows).min(h) - rows) * (w - border);
        piled_group |= e as f64 > EDGE_FRACTION * pixels as f64;
        confident += c;
        at_ends += e;
    }
    piled_group || (confident > 0 && at_ends as f64 > EDGE_FRACTION * confident as f64)
}

/// The margin on each side of a band around the disparities `lo..hi`: [`BAND_MARGIN_FRACTION`]
/// of their span, at least [`BAND_MARGIN_PX`]. The windows take the band's margin: how far a
/// surface moves between pairs does not depend on how many depths its rows hold.
fn margin_of((lo, hi): (f64, f64)) -> f64 {
    (BAND_MARGIN_FRACTION * (hi - lo)).max(BAND_MARGIN_PX)
}

/// A span of disparities, pixels (`None`: unknown, or the whole band).
type Span = Option<(f64, f64)>;

/// Rows per span of [`row_spans`].
const SPAN_ROWS: usize = 16;

/// [`confident_span`] of every [`SPAN_ROWS`] rows, from the top; `None` where fewer than
/// [`MIN_CONFIDENT_FRACTION`] of their pixels right of the border are confident.
fn row_spans(out: &RectifiedDepth, border: usize) -> Vec<Option<(f64, f64)>> {
    let (w, h) = out.disparity.dims();
    let from = border.min(w);
    let mut d = Vec::with_capacity(SPAN_ROWS * w);
    (0..h)
        .step_by(SPAN_ROWS)
        .map(|y0| {
            d.clear();
            for y in y0..(y0 + SPAN_ROWS).min(h) {
                let disparity = &out.disparity.data()[y * w..(y + 1) * w];
                let confidence = &out.depth.confidence.data()[y * w..(y + 1) * w];
                for (&v, &c) in disparity[from..].iter().zip(&confidence[from..]) {
                    if c > 0.0 && v.is_finite() {
                        d.push(v);
                    }
                }
            }
            let pixels = (y0 + SPAN_ROWS).min(h) - y0;
            let enough = !d.is_empty()
                && d.len() as f64 >= MIN_CONFIDENT_FRACTION * (pixels * (w - from)) as f64;
            enough.then(|| quantile_pair(&mut d, PRIOR_QUANTILE))
        })
        .collect()
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

    /// A textured ground: the disparity of row `y` of the 128×128 pair is `disparity(y)`.
    /// The texture is value noise (hashed lattice values, linear along the row), so no
    /// disparity but the true one matches.
    fn ground(disparity: impl Fn(usize) -> f64, phase: f64) -> (ImageF32, ImageF32) {
        let lattice = |i: i64, y: f64| {
            let k = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
                ^ (y as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
            let k = (k ^ (k >> 29)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            0.15 + 0.7 * ((k >> 40) as f64 / (1u64 << 24) as f64)
        };
        let texture = |x: f64, y: f64| {
            let x = x + 7.0 * phase;
            let (i, f) = (x.floor(), x - x.floor());
            ((1.0 - f) * lattice(i as i64, y) + f * lattice(i as i64 + 1, y)) as f32
        };
        let (w, h) = (128, 128);
        (
            ImageF32::from_fn(w, h, |x, y| texture(x as f64, y as f64)),
            ImageF32::from_fn(w, h, |x, y| texture(x as f64 + disparity(y), y as f64)),
        )
    }

    /// Median over the pixels right of `border` of |disparity − truth|.
    fn median_error(t: &TrackedDepth, truth: impl Fn(usize) -> f64, border: usize) -> f64 {
        let (w, h) = t.depth.disparity.dims();
        let mut e: Vec<f64> = (0..h)
            .flat_map(|y| (border..w).map(move |x| (x, y)))
            .map(|(x, y)| (f64::from(t.depth.disparity.get(x, y, 0)) - truth(y)).abs())
            .collect();
        e.sort_by(f64::total_cmp);
        e[e.len() / 2]
    }

    /// Rows whose depths differ search windows of their own: the ground's second pair searches
    /// under two thirds of the band's planes, as accurately as a pair that searches them all;
    /// a near object in the top rows, inside the band but outside their window, restarts the
    /// pair.
    #[test]
    fn rows_search_their_own_windows_and_a_surface_outside_one_restarts() {
        let slope = |y: usize| 6.0 + 34.0 * y as f64 / 127.0;
        let mut t = tracker();
        let (l, r) = ground(slope, 0.0);
        let first = t.estimate(&l, &r, &Monitor::noop()).unwrap();
        assert_eq!(
            (first.search, first.windows.is_none()),
            (Search::Full, true)
        );

        let (l, r) = ground(slope, 0.3);
        let second = t.estimate(&l, &r, &Monitor::noop()).unwrap();
        assert_eq!(second.search, Search::Band);
        let windows = second.windows.as_ref().expect("the rows have windows");
        let all = 128 * second.depth.planes.num_planes;
        let share = windows.planes_searched(128) as f64 / all as f64;
        assert!(share < 0.67, "{share}: {windows:?}");
        let mut every = tracker();
        let whole = every.estimate(&l, &r, &Monitor::noop()).unwrap();
        let (a, b) = (
            median_error(&second, slope, 45),
            median_error(&whole, slope, 45),
        );
        assert!(a <= b + 0.05, "windows {a} px, every plane {b} px");
        // The same pair again and again: the windows and the depth settle.
        let third = t.estimate(&l, &r, &Monitor::noop()).unwrap();
        let fourth = t.estimate(&l, &r, &Monitor::noop()).unwrap();
        assert_eq!(third.windows, fourth.windows);
        assert_eq!(third.depth.disparity.data(), fourth.depth.disparity.data());

        // The top rows come near: within the band, above their own window.
        let (l, r) = ground(|y| if y < 40 { 42.0 } else { slope(y) }, 0.6);
        let cut = t.estimate(&l, &r, &Monitor::noop()).unwrap();
        assert_eq!(cut.search, Search::Restarted);
        assert!(median_error(&cut, |y| if y < 40 { 42.0 } else { slope(y) }, 45) < 0.3);
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
