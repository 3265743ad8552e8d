//! How [`super::estimate_depth`] lays out its work: rows stream from costs to selections a band
//! at a time in stripes that run in parallel (5 paths, one pass), or the volume of levels is
//! built and aggregated in horizontal strips under the memory budget (8 or 4 paths); the
//! sources' consistency claims are gathered alongside.

use rayon::prelude::*;
use std::sync::atomic::{AtomicUsize, Ordering};

use crate::error::Result;
use crate::image::ImageF32;
use crate::monitor::Monitor;
use crate::mvs::cost_volume::census::{self, CensusImage, CensusRows, CensusScratch, CensusSource};
use crate::mvs::cost_volume::{
    penalty_for, validate_inputs, views_over, CostKind, CostRows, CostScratch, SweepImages, View,
};
use crate::mvs::plane_sweep::PlaneSet;

use crate::mvs::pose::Pose;

use super::consistency::{ClaimScratch, SourceClaims, SourceGeometry};
use super::photometric;
use super::quantise::Quantiser;
use super::select::{self, Selection};
use super::windows::PlaneWindows;
use super::{
    contrast, exposure, finish_depth, presmooth, sgm, vignetting, window, DepthParams, DepthPrior,
    DepthResult,
};

/// How [`estimate_depth_in_bands`] lays out its work; the defaults are [`estimate_depth`](super::estimate_depth)'s.
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct Layout {
    /// Own rows per band (default [`band_rows_of`] for strips, [`ONE_PASS_BAND_ROWS`] for the
    /// one pass); the depth does not depend on it (tested).
    pub(super) band_rows: Option<usize>,
    /// Own rows per one-pass stripe (default [`ONE_PASS_STRIPE_ROWS`]).
    pub(super) stripe_rows: Option<usize>,
    /// With 5 paths, aggregate strip volumes ([`strip_pass_selections`]) instead of streaming
    /// rows: the same depth where the one pass has one stripe and the volumes one strip (tested).
    pub(super) volumes: bool,
}

/// [`estimate_depth`](super::estimate_depth) with its work laid out as `layout` says.
#[allow(clippy::too_many_arguments)]
pub(super) fn estimate_depth_in_bands(
    reference: &View<'_>,
    sources: &[View<'_>],
    planes: &PlaneSet,
    kind: CostKind,
    params: &DepthParams,
    prior: &DepthPrior<'_>,
    layout: Layout,
    monitor: &Monitor,
) -> Result<DepthResult> {
    params.validate().map_err(|e| e.within("sgm"))?;
    if let Some(windows) = prior.windows {
        windows.validate(planes.num_planes)?;
    }
    // Invalid images are left to `build_cost_volume` to report; smoothing keeps their sizes and
    // spreads NaN, so the field it names is unchanged.
    let sigma = params.matching.presmooth_sigma_px;
    let smoothed: Option<(ImageF32, Vec<ImageF32>)> = (sigma > 0.0).then(|| {
        (
            presmooth::gaussian_presmooth(reference.image, sigma),
            sources
                .iter()
                .map(|s| presmooth::gaussian_presmooth(s.image, sigma))
                .collect(),
        )
    });
    let (reference, sources) = views_over(reference, sources, &smoothed);
    // Bad views fail before any strip's volume is built.
    validate_inputs(&reference, &sources, planes, kind)?;
    let channels = reference.image.channels();
    let corrections = photometric::corrections(
        &reference,
        &sources,
        planes,
        kind,
        params,
        prior.photometric,
    );
    let (reference, sources) = views_over(&reference, &sources, &corrections.devignetted);
    let (falloff, source_falloffs) = (corrections.falloff, corrections.source_falloffs);
    let (estimated_gains, photometric_search) = (corrections.gains, corrections.search);
    let source_gains: Vec<f32> = estimated_gains
        .iter()
        .copied()
        .map(exposure::applied_gain)
        .collect();
    let compensated: Vec<Option<ImageF32>> = sources
        .iter()
        .zip(source_gains.chunks_exact(channels))
        .zip(&source_falloffs)
        .map(|((s, g), &delta)| {
            let devignetted = (delta != 0.0).then(|| vignetting::compensate(s.image, delta));
            let image = devignetted.as_ref().unwrap_or(s.image);
            if g.iter().any(|&g| g != 1.0) {
                Some(exposure::compensate(image, g))
            } else {
                devignetted
            }
        })
        .collect();
    let sources: Vec<View<'_>> = sources
        .iter()
        .zip(&compensated)
        .map(|(v, img)| match img {
            Some(image) => View { image, ..*v },
            None => *v,
        })
        .collect();
    let geometry: Vec<SourceGeometry> = if params.rejection.consistency_check {
        sources
            .iter()
            .map(|s| SourceGeometry {
                k_ref: reference.intrinsics,
                k_src: s.intrinsics,
                relative: Pose::relative(&reference.pose, &s.pose),
                width: s.image.width(),
                height: s.image.height(),
            })
            .collect()
    } else {
        Vec::new()
    };
    let guide = reference.image;
    let (w, h) = guide.dims();
    let weights = contrast_weights_of(guide, params);
    // Codes of the views as the photometric term sees them (smoothed, gains divided out).
    let census: Option<(CensusImage, Vec<CensusImage>)> = (params.matching.census_weight > 0.0)
        .then(|| {
            (
                census::census_transform(reference.image),
                sources
                    .iter()
                    .map(|s| census::census_transform(s.image))
                    .collect(),
            )
        });
    let census_sources: Vec<CensusSource<'_>> = match &census {
        Some((_, codes)) => sources
            .iter()
            .zip(codes)
            .map(|(s, codes)| CensusSource {
                census: codes,
                intrinsics: s.intrinsics,
                relative: Pose::relative(&reference.pose, &s.pose),
            })
            .collect(),
        None => Vec::new(),
    };
    let claims: Vec<SourceClaims> = geometry
        .iter()
        .map(|g| SourceClaims::new(g, planes))
        .collect();
    let images = SweepImages::new(&reference, &sources, planes, kind)?;
    let source = LevelSource {
        reference: &reference,
        sources: &sources,
        planes,
        kind,
        images: &images,
        census: census
            .as_ref()
            .map(|(codes, _)| (codes, &census_sources[..])),
        weights: &weights,
        census_weight: params.matching.census_weight,
        radius: params.matching.cost_window_radius,
    };
    let selections = if params.sgm.num_paths == 5 && !layout.volumes {
        one_pass_selections(
            &source,
            guide,
            params,
            layout,
            &claims,
            prior.windows,
            monitor,
        )?
    } else {
        let bands = layout.band_rows;
        strip_pass_selections(&source, guide, params, bands, &claims, monitor)?
    };
    let mut depth = finish_depth(selections, w, h, planes, guide, params, claims, monitor)?;
    depth.source_gains = source_gains;
    depth.estimated_gains = estimated_gains;
    depth.photometric_search = photometric_search;
    depth.vignetting_falloff = falloff;
    depth.warnings = bound_warnings(&depth.source_gains, channels, falloff, &source_falloffs);
    depth.source_falloffs = source_falloffs;
    Ok(depth)
}

/// What building rows of `u16` levels needs besides the rows (step 1–2 of the module docs):
/// the views as the cost sees them and their sweep copies, the census codes, and the contrast
/// weights of the whole reference.
pub(super) struct LevelSource<'a> {
    reference: &'a View<'a>,
    sources: &'a [View<'a>],
    planes: &'a PlaneSet,
    kind: CostKind,
    images: &'a SweepImages,
    /// The reference's census codes and the sources' (with their geometry), when the census
    /// term is on.
    census: Option<(&'a CensusImage, &'a [CensusSource<'a>])>,
    /// Contrast weights, row-major over the whole reference (empty = all 1).
    weights: &'a [f32],
    census_weight: f32,
    /// Radius of the box window, pixels.
    radius: usize,
}

impl LevelSource<'_> {
    fn width(&self) -> usize {
        self.reference.image.width()
    }

    fn height(&self) -> usize {
        self.reference.image.height()
    }

    fn planes(&self) -> usize {
        self.planes.num_planes
    }

    /// The contrast weights of the image rows `rows` (empty when there are none).
    fn weights_of(&self, rows: &std::ops::Range<usize>) -> &[f32] {
        if self.weights.is_empty() {
            self.weights
        } else {
            let w = self.width();
            &self.weights[rows.start * w..rows.end * w]
        }
    }
}

/// One band's costs (`[plane][row][x]`, each plane's rows `stride` values apart) and which image
/// rows it holds, reused band after band: a band's first rows are usually the previous band's
/// last ones (the rows both bands' windows read), whose weighted horizontal means are moved to
/// the front of each plane instead of computed again.
pub(super) struct Band {
    costs: Vec<f32>,
    /// Values from one plane's rows to the next plane's: the most rows a band holds.
    stride: usize,
    /// The image rows and the planes of the last band.
    kept: Option<(std::ops::Range<usize>, std::ops::Range<usize>)>,
}

impl Band {
    /// A band of up to `rows` rows of `w`-pixel, `n`-plane costs.
    fn new(rows: usize, w: usize, n: usize) -> Self {
        Self {
            costs: crate::large_buffer::zeroed::<f32>(rows * w * n),
            stride: rows * w,
            kept: None,
        }
    }

    /// The levels of image rows `own` at the planes `planes` (`n` of them) into `out`
    /// (`[row][x][plane]`, `own.len() · w · n` values), scaled by `quant`: their costs and
    /// those of the rows their windows read are built (or their means moved from the last
    /// band), the census term added, and the window run, clipped at the rows `clip` (a strip's
    /// rows, or the whole image's), a group of planes at a time while its rows are in L2
    /// ([`window::window_groups_to_levels`]). The band must hold `own.len() + 2r` rows.
    #[allow(clippy::too_many_arguments)]
    fn levels(
        &mut self,
        src: &LevelSource<'_>,
        clip: std::ops::Range<usize>,
        own: std::ops::Range<usize>,
        planes: std::ops::Range<usize>,
        quant: &Quantiser,
        out: &mut [u16],
        monitor: &Monitor,
    ) -> Result<()> {
        let (w, n, r) = (src.width(), planes.len(), src.radius);
        let first = planes.start;
        let read = own.start.saturating_sub(r).max(clip.start)..(own.end + r).min(clip.end);
        let (held, stride) = (read.len(), self.stride);
        assert!(
            held * w <= stride,
            "the band holds the rows its windows read"
        );
        // A row's horizontal means do not depend on the band or the strip, so any row of the
        // last band is moved when the band had the same planes; with the census term, which
        // adds to whole bands' costs, they are computed again.
        let (have, shift) = match &self.kept {
            Some((prev, kept_planes))
                if src.census.is_none()
                    && *kept_planes == planes
                    && prev.start <= read.start
                    && read.start < prev.end =>
            {
                (prev.end.min(read.end) - read.start, read.start - prev.start)
            }
            _ => (0, 0),
        };
        // The kept means are invalid from here until every group has been rebuilt.
        self.kept = None;
        let costs = (have < held)
            .then(|| {
                CostRows::new(
                    src.reference,
                    src.sources,
                    src.planes,
                    src.kind,
                    read.start + have..read.end,
                    src.images,
                )
            })
            .transpose()?;
        let census = src.census.map(|(codes, sources)| CensusRows {
            reference: codes,
            k_ref: &src.reference.intrinsics,
            sources,
            planes: src.planes,
            rows: read.clone(),
            weight: src.census_weight,
            pixel_weights: src.weights_of(&read),
        });
        let groups = n.div_ceil(window::LEVEL_GROUP);
        let done = AtomicUsize::new(0);
        window::window_groups_to_levels(
            &mut self.costs[..n * stride],
            stride,
            window::GroupRows {
                data_rows: read.start - clip.start..read.end - clip.start,
                filtered: have,
                out_rows: own.start - clip.start..own.end - clip.start,
            },
            src.weights_of(&clip),
            (w, clip.len(), n, r),
            quant,
            out,
            || (CostScratch::default(), CensusScratch::default()),
            |(cost_scratch, census_scratch), g0, group| {
                for (j, plane) in group.chunks_exact_mut(stride).enumerate() {
                    // The set's plane.
                    let i = first + g0 + j;
                    if have > 0 && shift > 0 {
                        plane.copy_within(shift * w..(shift + have) * w, 0);
                    }
                    if let Some(costs) = &costs {
                        costs.fill_plane(i, &mut plane[have * w..held * w], cost_scratch);
                    }
                    if let Some(census) = &census {
                        census.add_to_plane(i, &mut plane[..held * w], census_scratch);
                    }
                }
                let k = done.fetch_add(1, Ordering::Relaxed) + 1;
                monitor.progress("mvs.cost_volume", k as f32 / groups as f32);
                Ok(())
            },
            monitor,
        )?;
        self.kept = Some((read, planes));
        Ok(())
    }
}

/// Steps 1–4 of the module docs with 8 or 4 paths: strip by strip ([`strips_of`]), each strip's
/// levels built band by band ([`band_rows_of`] own rows, or `band_rows`), then SGM over the
/// strip's levels into its sums and the selections of its own rows ([`strip_selections`]).
pub(super) fn strip_pass_selections(
    src: &LevelSource<'_>,
    guide: &ImageF32,
    params: &DepthParams,
    band_rows: Option<usize>,
    claims: &[SourceClaims],
    monitor: &Monitor,
) -> Result<Vec<Selection>> {
    let (w, h, n) = (src.width(), src.height(), src.planes());
    let r = src.radius;
    let strips = strips_of(w, h, n, params.sgm.volume_budget_mib);
    let band_rows = band_rows
        .unwrap_or_else(|| band_rows_of(w, n, r, params.sgm.volume_budget_mib))
        .max(1);
    let mut selections = Vec::with_capacity(w * h);
    let k = strips.len() as f32;
    // The levels and the aggregated costs of the tallest strip, and one band's `f32` costs,
    // reused from strip to strip and band to band.
    let tallest = strips.iter().map(|s| s.rows.len()).max().unwrap_or(0) * w * n;
    let mut levels = crate::large_buffer::zeroed::<u16>(tallest);
    let mut sum = crate::large_buffer::zeroed::<u16>(tallest);
    let mut band = Band::new((band_rows + 2 * r).min(h), w, n);
    let row_len = w * n;
    for (j, strip) in strips.iter().enumerate() {
        let rows = strip.rows.len();
        let quant = Quantiser::new(
            cost_bound(
                src.reference.image.channels(),
                src.weights_of(&strip.rows),
                params.matching.census_weight,
            ),
            params.sgm.p2.max(params.sgm.p1),
            params.sgm.num_paths,
        );
        let m = monitor.sub(j as f32 / k, (j as f32 + 0.5) / k);
        // Bands of equal height, so that the last one is not a sliver that one worker windows.
        let bands = rows.div_ceil(band_rows);
        let band_rows = rows.div_ceil(bands);
        for b in 0..bands {
            let m = m.sub(b as f32 / bands as f32, (b + 1) as f32 / bands as f32);
            // Strip-relative own rows of the band.
            let own = b * band_rows..((b + 1) * band_rows).min(rows);
            band.levels(
                src,
                strip.rows.clone(),
                strip.rows.start + own.start..strip.rows.start + own.end,
                0..n,
                &quant,
                &mut levels[own.start * row_len..own.end * row_len],
                &m,
            )?;
        }
        let m = monitor.sub((j as f32 + 0.5) / k, (j as f32 + 1.0) / k);
        selections.extend(strip_selections(
            &levels[..rows * row_len],
            &mut sum[..rows * row_len],
            &quant,
            strip,
            w,
            src.planes,
            guide,
            params,
            claims,
            &m,
        )?);
    }
    Ok(selections)
}

/// Own rows of a one-pass stripe ([`one_pass_selections`]), about: tall enough that the paths'
/// warm-up rows above each stripe ([`STRIP_OVERLAP_ROWS`](super::STRIP_OVERLAP_ROWS)) are a small share, and fixed, so the
/// depth does not depend on the number of cores.
pub(super) const ONE_PASS_STRIPE_ROWS: usize = 256;

/// The one pass's stripes of an `h`-row image, about `stripe_rows` own rows each: `core` the rows
/// a stripe decides (a partition of the image, in order), `rows` those it aggregates, its core
/// and the [`STRIP_OVERLAP_ROWS`](super::STRIP_OVERLAP_ROWS) above it where its paths start. Every stripe aggregates about
/// the same number of rows (the first, with no rows above it, decides more), so stripes running
/// side by side finish together.
pub(super) fn one_pass_stripes(h: usize, stripe_rows: usize) -> Vec<Strip> {
    let count = h.div_ceil(stripe_rows.max(1)).max(1);
    let ov = STRIP_OVERLAP_ROWS;
    let each = (h + (count - 1) * ov).div_ceil(count);
    let mut out = Vec::with_capacity(count);
    let mut start = 0;
    while start < h {
        let own = if start == 0 {
            each
        } else {
            each.saturating_sub(ov)
        }
        .max(1);
        let core = start..(start + own).min(h);
        out.push(Strip {
            rows: core.start.saturating_sub(ov)..core.end,
            core: core.clone(),
        });
        start = core.end;
    }
    out
}

/// Own rows of a one-pass band. A band's levels (221 KB per row at 640 pixels and 173 planes)
/// are written by the window and read back by SGM, so they should stay in L2 with SGM's own
/// rows: 4 rows were faster than 16 on hazy Aloe (docs/benchmarks.md), and fault in a quarter
/// of the pages.
pub(super) const ONE_PASS_BAND_ROWS: usize = 4;

/// Steps 1–4 of the module docs with the 5 one-pass paths ([`sgm::ONE_PASS_DIRECTIONS`](super::sgm::ONE_PASS_DIRECTIONS)): rows
/// stream from costs to selections, a band at a time, and no volume of the strip or image is
/// kept. The image is split into stripes of about [`ONE_PASS_STRIPE_ROWS`] own rows run in
/// parallel, each stripe's paths starting [`STRIP_OVERLAP_ROWS`](super::STRIP_OVERLAP_ROWS) rows above its own rows (the
/// window is clipped at the image's rows, not the stripe's). One quantiser serves the whole
/// image. With `windows`, each row searches only its group's planes: a band never spans two
/// groups, and the downward paths carry their costs across a group's edge
/// ([`sgm::OnePass::set_planes`]).
pub(super) fn one_pass_selections(
    src: &LevelSource<'_>,
    guide: &ImageF32,
    params: &DepthParams,
    layout: Layout,
    claims: &[SourceClaims],
    windows: Option<&PlaneWindows>,
    monitor: &Monitor,
) -> Result<Vec<Selection>> {
    let (w, h, n_all) = (src.width(), src.height(), src.planes());
    let r = src.radius;
    let window_of = |y: usize| windows.map_or(0..n_all, |p| p.of_row(y));
    let group_end = |y: usize| windows.map_or(usize::MAX, |p| p.group_end(y));
    let n_max = windows.map_or(n_all, |p| p.max_len());
    let quant = Quantiser::new(
        cost_bound(
            src.reference.image.channels(),
            src.weights,
            params.matching.census_weight,
        ),
        params.sgm.p2.max(params.sgm.p1),
        params.sgm.num_paths,
    );
    let pen = quant.penalties(&params.sgm.penalties());
    let isa = crate::cpu::Isa::detect();
    let stripes = one_pass_stripes(h, layout.stripe_rows.unwrap_or(ONE_PASS_STRIPE_ROWS));
    let total = stripes.iter().map(|s| s.rows.len()).sum::<usize>().max(1);
    let done = AtomicUsize::new(0);
    let silent = monitor.silent();
    let mut selections = vec![Selection::NONE; w * h];
    // Each stripe's own rows' selections, split off in order.
    let mut parts = Vec::with_capacity(stripes.len());
    let mut rest = &mut selections[..];
    for stripe in &stripes {
        let (part, tail) = rest.split_at_mut(stripe.core.len() * w);
        parts.push((stripe, part));
        rest = tail;
    }
    parts
        .into_par_iter()
        .try_for_each(|(stripe, selected)| -> Result<()> {
            let Strip { rows, core } = stripe.clone();
            let band_rows = (layout.band_rows)
                .unwrap_or(ONE_PASS_BAND_ROWS)
                .clamp(1, rows.len());
            let mut band = Band::new((band_rows + 2 * r).min(h), w, n_max);
            let mut levels = crate::large_buffer::zeroed::<u16>(band_rows * w * n_max);
            // One row of sums: each row's claims and selection follow its aggregation at once,
            // while its sums are in L2.
            let mut srow = vec![0u16; w * n_max];
            let mut claim_scratch = ClaimScratch::default();
            let mut pass = sgm::OnePass::new(w, window_of(rows.start).len(), isa);
            let mut y0 = rows.start;
            while y0 < rows.end {
                silent.checkpoint()?;
                let planes = window_of(y0);
                let (first, n) = (planes.start, planes.len());
                let row_len = w * n;
                pass.set_planes(planes.clone());
                let y1 = (y0 + band_rows).min(rows.end).min(group_end(y0));
                let levels = &mut levels[..(y1 - y0) * row_len];
                band.levels(src, 0..h, y0..y1, planes, &quant, levels, &silent)?;
                let srow = &mut srow[..row_len];
                for (y, crow) in (y0..y1).zip(levels.chunks_exact(row_len)) {
                    pass.row(crow, srow, y, &pen, Some(sgm::Guide::new(guide)));
                    if core.contains(&y) {
                        let k = y - core.start;
                        claim_and_select_row(
                            srow,
                            y,
                            (first, n),
                            &quant,
                            params,
                            claims,
                            &mut selected[k * w..(k + 1) * w],
                            &mut claim_scratch,
                        );
                    }
                }
                // The job's progress sink never moves backwards, so stripes may report in any
                // order.
                let done = done.fetch_add(y1 - y0, Ordering::Relaxed) + (y1 - y0);
                monitor.progress("mvs.depth", 0.95 * done as f32 / total as f32);
                y0 = y1;
            }
            Ok(())
        })?;
    Ok(selections)
}

/// A sentence for each source gain and each fall-off that ended at a bound of its search
/// ([`exposure::GAIN_RANGE`], [`vignetting::FALLOFF_RANGE`],
/// [`vignetting::RELATIVE_FALLOFF_RANGE`]): the value was applied, but the camera may differ by
/// more. `gains` are source-major, `channels` per source.
pub(super) fn bound_warnings(
    gains: &[f32],
    channels: usize,
    falloff: f32,
    source_falloffs: &[f32],
) -> Vec<String> {
    let (lo, hi) = exposure::GAIN_RANGE;
    let mut out: Vec<String> = gains
        .chunks_exact(channels.max(1))
        .enumerate()
        .flat_map(|(s, g)| {
            g.iter()
                .enumerate()
                .filter(|&(_, &g)| exposure::at_bound(g))
                .map(move |(c, &g)| {
                    format!(
                        "source {s} channel {c}: exposure gain {g:.3} is at the end of the searched \
                         range {lo}..{hi}; the camera may differ by more, and the compensation is \
                         then incomplete"
                    )
                })
        })
        .collect();
    let (flo, fhi) = vignetting::FALLOFF_RANGE;
    if falloff != 0.0
        && ((f64::from(falloff) - flo).abs() < 1e-3 || (f64::from(falloff) - fhi).abs() < 1e-3)
    {
        out.push(format!(
            "lens fall-off {falloff:.3} is at the end of the searched range {flo}..{fhi}; the \
             lens may vignette more, and the compensation is then incomplete"
        ));
    }
    let (rlo, rhi) = vignetting::RELATIVE_FALLOFF_RANGE;
    for (s, &d) in source_falloffs.iter().enumerate() {
        if (f64::from(d) - rlo).abs() < 1e-3 || (f64::from(d) - rhi).abs() < 1e-3 {
            out.push(format!(
                "source {s}: its lens fall-off relative to the reference's, {d:.3}, is at the end \
                 of the searched range {rlo}..{rhi}; the lenses may differ by more, and the \
                 compensation is then incomplete"
            ));
        }
    }
    out
}

/// Rows added above and below a strip's own rows so that the box window, the contrast measure
/// and SGM's vertical and diagonal paths reach the strip's rows with context: the strip's paths
/// start this many rows early.
pub const STRIP_OVERLAP_ROWS: usize = 24;

/// One horizontal strip of the reference: the rows its volume covers and the rows it decides.
#[derive(Clone, Debug, PartialEq)]
pub(super) struct Strip {
    /// Rows of the strip's volume (own rows plus the overlap).
    pub(super) rows: std::ops::Range<usize>,
    /// Rows whose depth this strip decides (a partition of the image over all strips).
    pub(super) core: std::ops::Range<usize>,
}

/// The strips for a `w×h` reference and `n` planes: one strip (the whole image, no overlap) when
/// the `f32` volume fits `budget_mib` MiB, else strips of equal own height (the last may be
/// shorter) whose volume with the overlap fits it; when the budget holds fewer than 16 own rows
/// plus the overlap, strips of about 16 own rows exceed it.
pub(super) fn strips_of(w: usize, h: usize, n: usize, budget_mib: usize) -> Vec<Strip> {
    let row_bytes = (w * n * std::mem::size_of::<f32>()).max(1);
    let strip_budget = budget_mib << 20;
    if h * row_bytes <= strip_budget {
        return vec![Strip {
            rows: 0..h,
            core: 0..h,
        }];
    }
    let own = (strip_budget / row_bytes)
        .saturating_sub(2 * STRIP_OVERLAP_ROWS)
        .max(16);
    let count = h.div_ceil(own);
    let own = h.div_ceil(count);
    (0..count)
        .map(|k| {
            let core = k * own..((k + 1) * own).min(h);
            Strip {
                rows: core.start.saturating_sub(STRIP_OVERLAP_ROWS)
                    ..(core.end + STRIP_OVERLAP_ROWS).min(h),
                core,
            }
        })
        .collect()
}

/// Per-pixel contrast weights of the whole reference (row-major), empty when off. The
/// percentile `c₀` is a property of the whole image, so strips share one set of weights.
pub(super) fn contrast_weights_of(guide: &ImageF32, params: &DepthParams) -> Vec<f32> {
    if params.matching.contrast_max_weight <= 1.0 {
        return Vec::new();
    }
    let c = contrast::local_contrast(
        guide.data(),
        guide.width(),
        guide.height(),
        guide.channels(),
        params.matching.cost_window_radius.max(1),
    );
    contrast::contrast_weights(
        &c,
        params.matching.contrast_percentile,
        params.matching.contrast_max_weight,
    )
}

/// The largest weighted cost a strip's windowed means can reach, known before any cost is
/// computed, so that a strip is quantised band by band as its costs are built: every voxel of
/// the volume is at most `γ` ([`penalty_for`]`(channels)`: the dehazing volume caps its voxels there, the ordinary one reaches it only for images outside `[0, 1]`, which
/// then take the top level, a truncated cost), times the strip's largest contrast weight, plus
/// the census term, which arrives unweighted and is at most `census_weight`. On the hazy Aloe
/// pair every strip's largest weighted cost was exactly this (the out-of-view penalty at the
/// largest weight), so its levels are those of the exact maximum.
pub(super) fn cost_bound(channels: usize, strip_weights: &[f32], census_weight: f32) -> f32 {
    let w_max = strip_weights.iter().copied().fold(1.0f32, f32::max);
    penalty_for(channels) * w_max + census_weight
}

/// Own rows per band of a strip whose costs are built and windowed together (see
/// [`estimate_depth`](super::estimate_depth)): the band's `f32` costs, with the `r` rows above and below that its
/// windows read, take at most a quarter of the volume budget and at most 32 MiB, so they are
/// still in cache when the window reads them; at least 8 rows, so the rows recomputed for the
/// windows stay a small share.
pub(super) fn band_rows_of(w: usize, n: usize, r: usize, budget_mib: usize) -> usize {
    let row_bytes = (w * n * std::mem::size_of::<f32>()).max(1);
    let bytes = ((budget_mib << 20) / 4).min(32 << 20);
    (bytes / row_bytes).saturating_sub(2 * r).max(8)
}

/// Steps 3–4 of the module docs on one strip's `u16` levels (pixel-major `[row][x][plane]`,
/// the strip's rows, scaled by `quant`): SGM into `sum` (same length, contents overwritten),
/// then the selections of the strip's own rows, whose aggregated costs also go to the sources'
/// `claims`.
#[allow(clippy::too_many_arguments)]
pub(super) fn strip_selections(
    levels: &[u16],
    sum: &mut [u16],
    quant: &Quantiser,
    strip: &Strip,
    w: usize,
    planes: &PlaneSet,
    guide: &ImageF32,
    params: &DepthParams,
    claims: &[SourceClaims],
    monitor: &Monitor,
) -> Result<Vec<Selection>> {
    let n = planes.num_planes;
    let rows = strip.rows.len();
    let row_len = w * n;
    monitor.checkpoint()?;
    sgm::aggregate_into(
        levels,
        sum,
        w,
        rows,
        n,
        params.sgm.num_paths,
        &quant.penalties(&params.sgm.penalties()),
        Some(sgm::Guide::rows(guide, strip.rows.clone())),
        &monitor.sub(0.1, 0.9),
    )?;
    monitor.checkpoint()?;
    let own = (strip.core.start - strip.rows.start) * row_len
        ..(strip.core.end - strip.rows.start) * row_len;
    let mut selections = vec![select::Selection::NONE; strip.core.len() * w];
    claim_and_select(
        &sum[own],
        strip.core.start,
        w,
        n,
        quant,
        params,
        claims,
        &mut selections,
    );
    Ok(selections)
}

/// The claims and the selections of consecutive `w`-pixel rows from `first_row` on, whose
/// aggregated costs are `sums` (`[row][x][plane]`, `n` planes, levels of `quant`), into `selected` (`w`
/// per row): each row's claims and selection in one pass while it is in cache (the sums are
/// read once instead of once per source and again for the selection), rows in parallel.
#[allow(clippy::too_many_arguments)]
pub(super) fn claim_and_select(
    sums: &[u16],
    first_row: usize,
    w: usize,
    n: usize,
    quant: &Quantiser,
    params: &DepthParams,
    claims: &[SourceClaims],
    selected: &mut [Selection],
) {
    if w * n == 0 {
        return;
    }
    sums.par_chunks(w * n)
        .zip(selected.par_chunks_mut(w))
        .enumerate()
        .for_each_init(ClaimScratch::default, |scratch, (k, (row, sel))| {
            claim_and_select_row(
                row,
                first_row + k,
                (0, n),
                quant,
                params,
                claims,
                sel,
                scratch,
            );
        });
}

/// [`claim_and_select`] of the one row `y` whose sums are `row`, over the `n` planes from
/// `first` on (`(first, n)`): the claims and the selections name planes of the whole set.
#[allow(clippy::too_many_arguments)]
pub(super) fn claim_and_select_row(
    row: &[u16],
    y: usize,
    (first, n): (usize, usize),
    quant: &Quantiser,
    params: &DepthParams,
    claims: &[SourceClaims],
    selected: &mut [Selection],
    scratch: &mut ClaimScratch,
) {
    let eps = quant.scaled(select::CONFIDENCE_EPS_PER_PATH * params.sgm.num_paths as f32);
    for c in claims {
        c.add_row(y, row, first, n, quant.unit(), scratch);
    }
    select::select_into(row, n, eps, selected);
    if first > 0 {
        for s in selected.iter_mut() {
            s.index += first as f32;
        }
    }
}
