//! Algorithm 1 of the reference (§3.3.3–3.3.4): grid search for the airlight `A` and the
//! scattering coefficient `β` (per scene unit) that make the dense dehazing-cost-volume depth
//! `z_{A,β} = F(A, β)` agree with the sparse SfM depth (Eq. 3.8, residual ρ of Eq. 3.9).
//!
//! 1. `β₀ = argmin_β` over `beta_steps` values uniform in `[β_min, β_max]` with `A = A₀`
//!    (Eq. 3.10), `A₀` from an airlight estimator — or, murk's default when the data pin it
//!    down, β₀ from the SfM points' transmission ratios ([`crate::params::point_ratio`]): the
//!    classical depth function barely depends on β (docs/ACCURACY.md), the ratios do;
//! 2. `A*, β* = argmin` over a `grid_steps × grid_steps` grid uniform in
//!    `[A₀ − Δ_A, A₀ + Δ_A] × [β₀ − Δ_β, β₀ + Δ_β]` (clamped to `A ∈ (0, 1]`, `β ≥ 0`); the
//!    step-1 evaluation at `(A₀, β₀)` lies in that box and stays a candidate.
//!
//! The reference's settings are 10 steps, a 4×4 grid, `Δ_A = Δ_β = 0.05`, `δ = 5` px (26 depth
//! evaluations); all are parameters. Two deviations in murk's defaults, both measured
//! (docs/ACCURACY.md): `Δ_A = 0` — with the classical depth function the residual prefers
//! larger `A` systematically (the argmin sat at `A₀ + Δ_A` on 9 of 10 scenes, turning the CNN's
//! MAE_A of 0.008 into 0.039), so `A* = A₀` and step 2 is a 1×4 refinement of β (14
//! evaluations); and a step-2 point replaces `(A₀, β₀)` only if its residual is lower by
//! `min_improvement_t` (3) standard errors of the paired per-point difference (0 = plain argmin). **Speed**: the depth function during the search runs on the images
//! box-downsampled by `search_downsample` (intrinsics and SfM pixels scaled to match, `δ`
//! divided) with `search_planes` planes: the residual is read at a few thousand SfM pixels, so the
//! full resolution buys little there; the caller computes the final depth `z* = F(A*, β*)` at full
//! resolution.

use std::time::Instant;

use crate::atmosphere::AtmosphereParams;
use crate::camera::Intrinsics;
use crate::error::{MurkError, Result};
use crate::image::ImageF32;
use crate::monitor::Monitor;
use crate::mvs::{estimate_depth, CostKind, DehazingOptions, PlaneSet, SgmParams, View};
use crate::params::point_ratio::{beta_from_point_ratios, PointRatioFit};
use crate::params::residual::{paired_improvement_t, sparse_residuals};
use crate::params::sparse::{SparseDepth, SparseSample};

/// Fewest SfM pixels in the reference view the search accepts: below this the residual of
/// Eq. 3.8 is decided by a handful of points (and their outliers).
pub const MIN_SPARSE_POINTS: usize = 10;
/// Most values along one axis of either search stage.
pub const MAX_GRID_STEPS: usize = 64;

/// Settings of [`search_scattering`]. Lengths in scene units, `β` per scene unit.
#[derive(Clone, Debug, PartialEq)]
pub struct SearchParams {
    /// Lower end of the β range of step 1, `≥ 0`.
    pub beta_min: f32,
    /// Upper end of the β range of step 1, `> beta_min`.
    pub beta_max: f32,
    /// Values of β in step 1, `1..=MAX_GRID_STEPS` (reference: 10).
    pub beta_steps: usize,
    /// Values per axis of the step-2 grid, `1..=MAX_GRID_STEPS` (reference: 4).
    pub grid_steps: usize,
    /// Half-width of the step-2 airlight range, `≥ 0` (reference: 0.05; murk's default 0: with
    /// the classical depth function the residual is biased towards larger `A` and the grid made
    /// the CNN's `A₀` worse, MAE 0.008 → 0.034, see docs/ACCURACY.md). With 0 the grid has one
    /// airlight, `A₀`, and `grid_steps` values of β.
    pub delta_airlight: f32,
    /// Half-width of the step-2 β range, `≥ 0`, per scene unit (reference: 0.05).
    pub delta_beta: f32,
    /// δ of Eq. 3.9, pixels at full resolution, `≤ 64` (reference: 5).
    pub delta_px: usize,
    /// Box-downsampling factor of the images during the search, `1..=8`.
    pub search_downsample: usize,
    /// Planes of the depth function during the search (the caller's plane range), `2..=1024`.
    pub search_planes: usize,
    /// Dehazing cost-volume options of the depth function.
    pub cost: DehazingOptions,
    /// Aggregation parameters of the depth function.
    pub sgm: SgmParams,
    /// Step 2 replaces `(A₀, β₀)` only by a grid point whose residual is lower by at least this
    /// many standard errors (paired t over the SfM pixels, [`paired_improvement_t`]); 0 = the
    /// plain argmin of the published algorithm. Finite, `≥ 0`.
    pub min_improvement_t: f64,
    /// Step 1 takes β₀ from the SfM points' transmission ratios
    /// ([`crate::params::point_ratio`]) when that fit is reliable, clamped to
    /// `[beta_min, beta_max]`, and evaluates only `(A₀, β₀)`; otherwise (and with `false`, the
    /// published algorithm) it sweeps Eq. 3.10. With β₀ from the points step 2 keeps β and
    /// searches A only (nothing with `delta_airlight` 0).
    pub beta_from_points: bool,
}

impl Default for SearchParams {
    fn default() -> Self {
        Self {
            beta_min: 0.4,
            beta_max: 0.8,
            beta_steps: 10,
            grid_steps: 4,
            delta_airlight: 0.0,
            delta_beta: 0.05,
            delta_px: 5,
            search_downsample: 2,
            search_planes: 64,
            cost: DehazingOptions::default(),
            sgm: SgmParams::default(),
            min_improvement_t: 3.0,
            beta_from_points: true,
        }
    }
}

impl SearchParams {
    /// Fails naming the first bad field.
    pub fn validate(&self) -> Result<()> {
        let bad = |f: &str, r: String| Err(MurkError::invalid(f, r));
        if !self.beta_min.is_finite() || self.beta_min < 0.0 {
            return bad(
                "beta_min",
                format!("must be finite and >= 0, got {}", self.beta_min),
            );
        }
        if !self.beta_max.is_finite() || self.beta_max <= self.beta_min {
            return bad(
                "beta_max",
                format!(
                    "must be finite and > beta_min ({}), got {} (the β range is empty)",
                    self.beta_min, self.beta_max
                ),
            );
        }
        for (f, v) in [
            ("beta_steps", self.beta_steps),
            ("grid_steps", self.grid_steps),
        ] {
            if !(1..=MAX_GRID_STEPS).contains(&v) {
                return bad(f, format!("must be in 1..={MAX_GRID_STEPS}, got {v}"));
            }
        }
        for (f, v) in [
            ("delta_airlight", self.delta_airlight),
            ("delta_beta", self.delta_beta),
        ] {
            if !v.is_finite() || !(0.0..=1.0).contains(&v) {
                return bad(f, format!("must be in [0, 1], got {v}"));
            }
        }
        if self.delta_px > 64 {
            return bad(
                "delta_px",
                format!("must be <= 64 pixels, got {}", self.delta_px),
            );
        }
        if !(1..=8).contains(&self.search_downsample) {
            return bad(
                "search_downsample",
                format!("must be in 1..=8, got {}", self.search_downsample),
            );
        }
        if !(2..=crate::mvs::MAX_PLANES).contains(&self.search_planes) {
            return bad(
                "search_planes",
                format!(
                    "must be in 2..={}, got {}",
                    crate::mvs::MAX_PLANES,
                    self.search_planes
                ),
            );
        }
        if !self.min_improvement_t.is_finite() || self.min_improvement_t < 0.0 {
            return bad(
                "min_improvement_t",
                format!("must be finite and >= 0, got {}", self.min_improvement_t),
            );
        }
        self.sgm.validate().map_err(|e| e.within("sgm"))
    }

    /// Most depth evaluations of a search: `beta_steps + grid_steps²`, or
    /// `beta_steps + grid_steps` when `delta_airlight` is 0 (step 1 is one evaluation instead
    /// of `beta_steps` when β₀ comes from the points).
    pub fn evaluations(&self) -> usize {
        self.beta_steps + self.airlight_steps() * self.grid_steps
    }

    fn airlight_steps(&self) -> usize {
        if self.delta_airlight == 0.0 {
            1
        } else {
            self.grid_steps
        }
    }
}

/// Which step of Algorithm 1 an evaluation belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SearchStage {
    /// Step 1: β alone, `A = A₀` (Eq. 3.10).
    Beta,
    /// Step 2: the `A × β` grid around `(A₀, β₀)`.
    Joint,
}

/// One evaluation of the objective.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GridEvaluation {
    /// The step it belongs to.
    pub stage: SearchStage,
    /// Airlight evaluated.
    pub airlight: f32,
    /// β evaluated, per scene unit.
    pub beta: f32,
    /// Mean Eq. 3.9 residual over the SfM pixels, scene units.
    pub residual: f64,
}

/// Result of [`search_scattering`].
#[derive(Clone, Debug, PartialEq)]
pub struct ScatteringEstimate {
    /// `A*`.
    pub airlight: f32,
    /// `β*`, per scene unit.
    pub beta: f32,
    /// `A₀`, the airlight estimator's value.
    pub airlight_initial: f32,
    /// `β₀` of step 1.
    pub beta_initial: f32,
    /// The points' transmission-ratio fit when step 1 tried it (reliable or not); β₀ came from
    /// it when [`PointRatioFit::is_reliable`].
    pub point_ratio: Option<PointRatioFit>,
    /// Mean Eq. 3.9 residual at `(A*, β*)`, scene units.
    pub residual: f64,
    /// Every evaluation in order (step 1 then step 2), e.g. to plot the curve of Fig. 3.7c.
    pub grid: Vec<GridEvaluation>,
    /// SfM pixels used (at the search resolution).
    pub num_sparse_points: usize,
    /// Wall time of the search, seconds.
    pub seconds: f64,
}

/// `n` values uniform in `[lo, hi]` (the midpoint when `n = 1`).
fn linspace(lo: f32, hi: f32, n: usize) -> Vec<f32> {
    if n == 1 {
        return vec![0.5 * (lo + hi)];
    }
    (0..n)
        .map(|i| lo + (hi - lo) * i as f32 / (n - 1) as f32)
        .collect()
}

/// Mean over `f×f` blocks (the image cropped to a multiple of `f`).
fn box_downsample(img: &ImageF32, f: usize) -> ImageF32 {
    let (w, h, c) = (img.width() / f, img.height() / f, img.channels());
    let mut out = vec![0.0f32; w * h * c];
    let norm = 1.0 / (f * f) as f32;
    for y in 0..h {
        for x in 0..w {
            for ch in 0..c {
                let mut s = 0.0;
                for dy in 0..f {
                    for dx in 0..f {
                        s += img.get(x * f + dx, y * f + dy, ch);
                    }
                }
                out[(y * w + x) * c + ch] = s * norm;
            }
        }
    }
    ImageF32::from_vec(w, h, c, out).expect("non-empty: checked by the caller")
}

/// Intrinsics of the `f×f` box-downsampled image: coarse pixel `i` covers fine pixels
/// `f·i … f·i + f − 1`, whose centre is `f·i + (f − 1)/2`.
fn downsample_intrinsics(k: &Intrinsics, f: usize) -> Intrinsics {
    let f = f as f64;
    let shift = (f - 1.0) / 2.0;
    Intrinsics {
        fx: k.fx / f,
        fy: k.fy / f,
        cx: (k.cx - shift) / f,
        cy: (k.cy - shift) / f,
        skew: k.skew / f,
    }
}

/// Runs Algorithm 1 (see the module docs) from the initial airlight `airlight_initial` over the
/// plane range of `planes` (its count is replaced by `params.search_planes`). Errors name
/// `params.…` fields, `airlight_initial`, `sparse_points` (fewer than [`MIN_SPARSE_POINTS`]
/// SfM pixels, or a map of another size than the reference), and those of the depth function;
/// cancellation returns `Cancelled`. Progress is reported after every evaluation.
pub fn search_scattering(
    reference: &View<'_>,
    sources: &[View<'_>],
    sparse: &SparseDepth,
    airlight_initial: f32,
    planes: &PlaneSet,
    params: &SearchParams,
    monitor: &Monitor,
) -> Result<ScatteringEstimate> {
    let start = Instant::now();
    params.validate().map_err(|e| e.within("params"))?;
    if !(airlight_initial.is_finite() && airlight_initial > 0.0 && airlight_initial <= 1.0) {
        return Err(MurkError::invalid(
            "airlight_initial",
            format!("must be in (0, 1], got {airlight_initial}"),
        ));
    }
    if (sparse.width(), sparse.height()) != reference.image.dims() {
        return Err(MurkError::invalid(
            "sparse_points",
            format!(
                "sparse depth is {}x{} but the reference image is {}x{}",
                sparse.width(),
                sparse.height(),
                reference.image.width(),
                reference.image.height()
            ),
        ));
    }
    let f = params.search_downsample;
    let (w, h) = reference.image.dims();
    if w / f < 8 || h / f < 8 {
        return Err(MurkError::invalid(
            "params.search_downsample",
            format!("{w}x{h} downsampled by {f} leaves fewer than 8x8 pixels"),
        ));
    }
    // Search-resolution views and sparse map.
    let scaled = |v: &View<'_>| {
        (
            box_downsample(v.image, f),
            downsample_intrinsics(&v.intrinsics, f),
        )
    };
    let ref_small = scaled(reference);
    let src_small: Vec<(ImageF32, Intrinsics)> = sources.iter().map(scaled).collect();
    let sparse_small = sparse.downsampled(f);
    if sparse_small.len() < MIN_SPARSE_POINTS {
        return Err(MurkError::invalid(
            "sparse_points",
            format!(
                "{} SfM points are visible in the reference view ({} distinct pixels at the \
                 search resolution); at least {MIN_SPARSE_POINTS} are needed",
                sparse.len(),
                sparse_small.len()
            ),
        ));
    }
    let reference_view = View {
        image: &ref_small.0,
        intrinsics: ref_small.1,
        pose: reference.pose,
    };
    let source_views: Vec<View<'_>> = src_small
        .iter()
        .zip(sources)
        .map(|((img, k), v)| View {
            image: img,
            intrinsics: *k,
            pose: v.pose,
        })
        .collect();
    let search_planes = PlaneSet::new(planes.near, planes.far, params.search_planes)
        .map_err(|e| e.within("planes"))?;
    let delta = (params.delta_px as f64 / f as f64).round() as usize;
    // Step 1 from the points, at full resolution (the ratios need the images' own pixels).
    let point_ratio = params
        .beta_from_points
        .then(|| beta_from_point_ratios(reference, sources, sparse, airlight_initial))
        .flatten();
    let beta_from_points = point_ratio
        .filter(PointRatioFit::is_reliable)
        .map(|fit| (fit.beta as f32).clamp(params.beta_min, params.beta_max));
    let step1: Vec<f32> = match beta_from_points {
        Some(b) => vec![b],
        None => linspace(params.beta_min, params.beta_max, params.beta_steps),
    };
    let step2 = match (beta_from_points.is_some(), params.airlight_steps()) {
        (true, 1) => 0,
        (true, a) => a,
        (false, a) => a * params.grid_steps,
    };
    let total = (step1.len() + step2) as f32;
    let mut grid: Vec<GridEvaluation> = Vec::with_capacity(params.evaluations());
    let mut evaluate = |stage: SearchStage, airlight: f32, beta: f32| -> Result<(f64, Vec<f32>)> {
        monitor.checkpoint()?;
        let i = grid.len() as f32;
        let kind = CostKind::DehazingWith(AtmosphereParams { airlight, beta }, params.cost);
        let depth = estimate_depth(
            &reference_view,
            &source_views,
            &search_planes,
            kind,
            &params.sgm,
            &monitor.sub(i / total, (i + 1.0) / total),
        )?;
        let per_point = sparse_residuals(&depth.z_depth, &sparse_small, delta)?;
        let residual =
            per_point.iter().map(|&x| f64::from(x)).sum::<f64>() / per_point.len() as f64;
        grid.push(GridEvaluation {
            stage,
            airlight,
            beta,
            residual,
        });
        monitor.progress("params.search", (i + 1.0) / total);
        Ok((residual, per_point))
    };
    // Step 1 (Eq. 3.10).
    let mut best = (f64::INFINITY, airlight_initial, params.beta_min);
    let mut incumbent: Vec<f32> = Vec::new();
    for beta in step1 {
        let (r, per_point) = evaluate(SearchStage::Beta, airlight_initial, beta)?;
        if r < best.0 {
            best = (r, airlight_initial, beta);
            incumbent = per_point;
        }
    }
    let beta_initial = best.2;
    // Step 2 (Eq. 3.8 over Ω_A × Ω_β).
    let a_values = linspace(
        airlight_initial - params.delta_airlight,
        airlight_initial + params.delta_airlight,
        params.airlight_steps(),
    );
    // With β₀ from the points step 2 refines A only: the depth residual's preference in β is
    // a bias of the classical depth function (it moved the points' β₀ by +0.05 on 8 of 10
    // scenes past a paired t of 3, MAE_β 0.032 → 0.154; docs/ACCURACY.md), not information.
    let b_values = if beta_from_points.is_some() {
        vec![beta_initial]
    } else {
        linspace(
            beta_initial - params.delta_beta,
            beta_initial + params.delta_beta,
            params.grid_steps,
        )
    };
    let a_values = if beta_from_points.is_some() && a_values.len() == 1 {
        // (A₀, β₀) is step 1's evaluation already.
        Vec::new()
    } else {
        a_values
    };
    for &a in &a_values {
        let a = a.clamp(1e-3, 1.0);
        for &b in &b_values {
            let b = b.max(0.0);
            let (r, per_point) = evaluate(SearchStage::Joint, a, b)?;
            // Only a significant improvement over (A₀, β₀) moves the estimate: the residual
            // barely depends on A (docs/ACCURACY.md), and an argmin over noise would drift.
            let significant = params.min_improvement_t == 0.0
                || paired_improvement_t(&incumbent, &per_point) >= params.min_improvement_t;
            if r < best.0 && significant {
                best = (r, a, b);
            }
        }
    }
    Ok(ScatteringEstimate {
        airlight: best.1,
        beta: best.2,
        airlight_initial,
        beta_initial,
        point_ratio,
        residual: best.0,
        grid,
        num_sparse_points: sparse_small.len(),
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// A plane range that covers the scene seen by the SfM points: `[0.75·q₀₁, 1.5·q₉₉]` of their
/// z-depth (1st and 99th percentiles, so a few outliers do not stretch it; the margins cover
/// surfaces just outside the points' range, such as an untextured far wall). `None` without points.
pub fn plane_range_from_sparse(sparse: &SparseDepth) -> Option<(f64, f64)> {
    let lo = f64::from(sparse.depth_quantile(0.01)?);
    let hi = f64::from(sparse.depth_quantile(0.99)?);
    Some((0.75 * lo, 1.5 * hi.max(lo * 1.01)))
}

impl SparseDepth {
    /// The map of the `f×f` box-downsampled image: fine pixel `(x, y)` falls in coarse pixel
    /// `(x / f, y / f)` (pixels outside the cropped image are dropped), the nearest point kept.
    pub fn downsampled(&self, f: usize) -> SparseDepth {
        let f = f.max(1);
        let (w, h) = (self.width() / f, self.height() / f);
        let mut samples: Vec<SparseSample> = self
            .samples()
            .iter()
            .map(|s| SparseSample {
                x: s.x / f as u32,
                y: s.y / f as u32,
                z: s.z,
            })
            .filter(|s| (s.x as usize) < w && (s.y as usize) < h)
            .collect();
        samples.sort_by(|a, b| (a.y, a.x, a.z).partial_cmp(&(b.y, b.x, b.z)).unwrap());
        samples.dedup_by(|later, first| later.x == first.x && later.y == first.y);
        SparseDepth::from_samples(w, h, samples)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::simulate::mvs::{simulate_mvs, MvsScene, MvsSimConfig};
    use std::sync::atomic::AtomicBool;
    use std::sync::{Arc, Mutex};

    #[test]
    fn downsampled_intrinsics_match_the_box_downsampled_image() {
        let k = Intrinsics {
            fx: 100.0,
            fy: 90.0,
            cx: 31.5,
            cy: 23.5,
            skew: 0.5,
        };
        for f in [1usize, 2, 3] {
            let kc = downsample_intrinsics(&k, f);
            let p = [0.3, -0.2, 2.0];
            let (u, v) = k.project(p).unwrap();
            let (uc, vc) = kc.project(p).unwrap();
            // Fine pixels f·i … f·i+f−1 average into coarse pixel i, centred at f·i + (f−1)/2.
            assert!((uc * f as f64 + (f as f64 - 1.0) / 2.0 - u).abs() < 1e-9);
            assert!((vc * f as f64 + (f as f64 - 1.0) / 2.0 - v).abs() < 1e-9);
        }
        let img = ImageF32::from_fn(6, 4, |x, y| (x + 10 * y) as f32);
        let d = box_downsample(&img, 2);
        assert_eq!(d.dims(), (3, 2));
        assert_eq!(d.get(1, 1, 0), (22.0 + 23.0 + 32.0 + 33.0) / 4.0);
    }

    #[test]
    fn linspace_covers_the_range() {
        assert_eq!(linspace(0.4, 0.8, 1), vec![0.5 * (0.4f32 + 0.8)]);
        let v = linspace(0.4, 0.8, 5);
        assert_eq!(v.len(), 5);
        assert_eq!(v[0], 0.4);
        assert!((v[4] - 0.8).abs() < 1e-7);
    }

    fn small_scene() -> MvsScene {
        let cfg = MvsSimConfig {
            seed: 7,
            beta_range: Some([0.4, 0.8]),
            ..MvsSimConfig::with_size(64, 48)
        };
        simulate_mvs(&cfg, &Monitor::noop()).unwrap()
    }

    /// murk's default on a simulated room at reduced size (walking trajectory: at 128×96 a
    /// lateral one leaves too few equations for a reliable fit): β₀ from the points' ratios
    /// lands within 0.05 of the true β (MAE 0.032 at full size, docs/ACCURACY.md), step 1 is a
    /// single evaluation and step 2 has nothing to do with `delta_airlight` 0.
    #[test]
    fn default_search_finds_beta_from_the_points() {
        let scene = crate::simulate::mvs::walking_test_scene(5);
        let (reference, sources) = scene.reference_and_sources();
        let sparse = scene.sparse_depth().unwrap();
        let (near, far) = plane_range_from_sparse(&sparse).unwrap();
        let planes = PlaneSet::new(near, far, 32).unwrap();
        let params = SearchParams {
            search_planes: 16,
            ..SearchParams::default()
        };
        let est = search_scattering(
            &reference,
            &sources,
            &sparse,
            scene.airlight,
            &planes,
            &params,
            &Monitor::noop(),
        )
        .unwrap();
        let fit = est.point_ratio.expect("the points were tried");
        assert!(fit.is_reliable(), "{fit:?}");
        assert_eq!(est.grid.len(), 1);
        assert_eq!(est.beta, est.beta_initial);
        assert!(
            (est.beta - scene.beta).abs() < 0.05,
            "β {} vs true {} ({fit:?})",
            est.beta,
            scene.beta
        );
        // The published algorithm on the same data: the full sweep and grid.
        let published = SearchParams {
            beta_from_points: false,
            ..params
        };
        let est = search_scattering(
            &reference,
            &sources,
            &sparse,
            scene.airlight,
            &planes,
            &published,
            &Monitor::noop(),
        )
        .unwrap();
        assert!(est.point_ratio.is_none());
        assert_eq!(est.grid.len(), published.evaluations());
    }

    /// The search's bookkeeping: `beta_steps + grid_steps²` evaluations in order, the step-2
    /// grid centred on (A₀, β₀), the answer the smallest residual seen, progress monotone up to
    /// 1, cancellation honoured. (Whether the minimum is at the true β depends on the depth
    /// function; see docs/ACCURACY.md.)
    #[test]
    fn search_bookkeeping_progress_and_cancel() {
        let scene = small_scene();
        let (reference, sources) = scene.reference_and_sources();
        let sparse = scene.sparse_depth().unwrap();
        let (near, far) = plane_range_from_sparse(&sparse).unwrap();
        let planes = PlaneSet::new(near, far, 32).unwrap();
        let params = SearchParams {
            beta_steps: 4,
            grid_steps: 2,
            delta_airlight: 0.05,
            search_planes: 16,
            // The published plain argmin, so the estimate must be the grid's minimum.
            min_improvement_t: 0.0,
            beta_from_points: false,
            ..SearchParams::default()
        };
        assert_eq!(params.evaluations(), 8);
        assert_eq!(
            SearchParams {
                delta_airlight: 0.0,
                ..params.clone()
            }
            .evaluations(),
            6
        );
        let seen: Arc<Mutex<Vec<f32>>> = Arc::default();
        let sink = {
            let seen = seen.clone();
            Arc::new(move |stage: &str, f: f32| {
                if stage == "params.search" {
                    seen.lock().unwrap().push(f);
                }
            })
        };
        let monitor = Monitor::new(Arc::new(AtomicBool::new(false)), Some(sink));
        let est = search_scattering(
            &reference, &sources, &sparse, 0.85, &planes, &params, &monitor,
        )
        .unwrap();
        assert_eq!(est.grid.len(), 4 + 4);
        assert!(est.grid[..4]
            .iter()
            .all(|g| g.stage == SearchStage::Beta && g.airlight == 0.85));
        let betas: Vec<f32> = est.grid[..4].iter().map(|g| g.beta).collect();
        assert_eq!(betas, linspace(0.4, 0.8, 4));
        let best_step1 = est.grid[..4]
            .iter()
            .min_by(|a, b| a.residual.total_cmp(&b.residual))
            .unwrap();
        assert_eq!(est.beta_initial, best_step1.beta);
        for g in &est.grid[4..] {
            assert_eq!(g.stage, SearchStage::Joint);
            assert!((g.airlight - 0.85).abs() <= 0.05 + 1e-6);
            assert!((g.beta - est.beta_initial).abs() <= 0.05 + 1e-6);
        }
        let best = est
            .grid
            .iter()
            .min_by(|a, b| a.residual.total_cmp(&b.residual))
            .unwrap();
        assert_eq!(
            (est.airlight, est.beta, est.residual),
            (best.airlight, best.beta, best.residual)
        );
        let p = seen.lock().unwrap().clone();
        assert_eq!(p.len(), 8);
        assert!(p.windows(2).all(|w| w[0] <= w[1]));
        assert_eq!(*p.last().unwrap(), 1.0);

        let cancelled = Monitor::new(Arc::new(AtomicBool::new(true)), None);
        assert_eq!(
            search_scattering(&reference, &sources, &sparse, 0.85, &planes, &params, &cancelled)
                .unwrap_err(),
            MurkError::Cancelled
        );
        // Too few points, bad A₀, bad parameters: named.
        let few = SparseDepth::from_samples(64, 48, sparse.samples()[..3].to_vec());
        let err = search_scattering(&reference, &sources, &few, 0.85, &planes, &params, &monitor);
        assert_eq!(err.unwrap_err().field(), Some("sparse_points"));
        let err = search_scattering(
            &reference, &sources, &sparse, 0.0, &planes, &params, &monitor,
        );
        assert_eq!(err.unwrap_err().field(), Some("airlight_initial"));
        let bad = SearchParams {
            beta_max: 0.4,
            ..params.clone()
        };
        let err = search_scattering(&reference, &sources, &sparse, 0.85, &planes, &bad, &monitor);
        assert_eq!(err.unwrap_err().field(), Some("params.beta_max"));
    }
}
