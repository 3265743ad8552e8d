//! The iterative algorithm of §4.3.4: backscatter removal, then repeatedly surface-camera
//! forward-scatter removal (Eq. 4.52, BiCGStab), near-light photometric stereo (Eq. 4.56–4.59),
//! perspective normal integration (Eq. 4.15–4.27, 4.60–4.62) and a normal update from the
//! shape, until the shape stops changing.

use std::time::Instant;

use crate::error::{MurkError, Result};
use crate::monitor::Monitor;
use crate::ps::backscatter::{backscatter_tail, remove_backscatter};
use crate::ps::bicgstab::{bicgstab_block, BicgstabParams, BlockOperator};
use crate::ps::capture::PsCapture;
use crate::ps::distance::{default_range_mm, fit_mean_depth, DistanceFit};
use crate::ps::integrate::{
    depth_from_log, integrate_normals, normals_from_depth, IntegrationParams,
};
use crate::ps::near_light::{solve_normals, ShadingModel};
use crate::ps::physics::{
    FTable, FacetEmission, FarField, ForwardKernel, GTable, KernelLayout, Medium, SurfaceGeometry,
};

/// Largest kernel support `r` accepted (an r×r window per pixel is stored; 201² f32 = 160 kB
/// per object pixel).
pub const MAX_SUPPORT_R: usize = 201;
/// Largest iteration cap accepted.
pub const MAX_ITERATIONS: usize = 100;

/// Farthest initial object distance, mm (1 km), the same bound as the lights' coordinates
/// (`capture::MAX_LIGHT_COORDINATE_MM`): beyond it the value is a unit slip.
pub const MAX_OBJECT_DISTANCE_MM: f64 = 1e6;
/// Default bound on the stored kernel K̂ (`object pixels × r² × 4` bytes), the method's memory
/// peak: 4 GiB, four times what the exact r×r window needs at 300×300 with r = 81 (1.0 GiB).
pub const DEFAULT_MAX_KERNEL_BYTES: usize = 4 << 30;

/// Default [`PsParams::far_cell`] (measured in docs/accuracy.md and docs/benchmarks.md).
pub const DEFAULT_FAR_CELL: usize = 3;
/// Default [`PsParams::near_radius_px`].
pub const DEFAULT_NEAR_RADIUS_PX: usize = 9;

/// How the pipeline fixes the shape's absolute scale.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum DistanceMode {
    /// Fit the mean distance to the lights' 1/d² fall-off after every integration; the given
    /// distance is a starting guess (murk's default).
    #[default]
    Estimate,
    /// Keep the mean z-depth at `initial_distance_mm` (the reference as published).
    Fixed,
}

/// Each iteration's distance fit searches within this factor of the previous mean depth.
const DISTANCE_STEP: f64 = 1.6;

/// Share (in log-distance) of each distance fit's step that is taken.
const DISTANCE_RELAXATION: f64 = 0.6;

/// Which scattering effects the pipeline removes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum PsMode {
    /// The reference's method: backscatter, surface-camera and source-surface forward scatter.
    Full,
    /// The baseline \[15\]: backscatter subtraction and attenuation only.
    BackscatterOnly,
}

/// Settings of [`photometric_stereo`]. Defaults follow the reference.
#[derive(Clone, Debug, PartialEq)]
pub struct PsParams {
    /// z-distance of the initial fronto-parallel plane, mm (§4.4.4 initialises with a plane):
    /// the mean z-depth of the object's visible surface as well as the rig knows it, or 0 when
    /// it is not known. Perspective integration fixes the shape only up to scale; with
    /// [`DistanceMode::Estimate`] (the default) every iteration fits the scale to the lights'
    /// 1/d² fall-off ([`crate::ps::distance`]) and this is only the starting guess (0: found
    /// by a search over [`crate::ps::distance::default_range_mm`] before the first iteration).
    /// With [`DistanceMode::Fixed`] it sets the absolute scale and must be > 0.
    pub initial_distance_mm: f64,
    /// Whether the object's distance is estimated or fixed at `initial_distance_mm`.
    pub distance: DistanceMode,
    /// An initial shape instead of the plane: z-depth per pixel, mm (finite and > 0 on the
    /// mask). With the true shape this is the reference's "Input GT" experiment.
    pub initial_depth_mm: Option<Vec<f32>>,
    /// Kernel support `r` (odd, ≥ 3): K̂ keeps an r×r window per pixel (Eq. 4.51). The
    /// reference found 61–81 effective.
    pub support_r: usize,
    /// Iteration cap for steps 3–5.
    pub max_iterations: usize,
    /// Stop when the mean |Δz| between iterations falls below this fraction of the mean depth.
    pub tolerance: f64,
    /// Reuse the kernel K̂ of an earlier iteration while the mean |Δz| between the shape it was
    /// built from and the current shape stays below this fraction of the mean depth; 0 rebuilds
    /// it every iteration. K̂ depends smoothly on the shape (points and normals), so a shape that
    /// moved by 10⁻³ of its distance changes the forward scatter it removes (about a tenth of
    /// the signal) by about 10⁻⁴ of the signal, far below the noise, while a build is most of an
    /// iteration's time (docs/benchmarks.md).
    pub kernel_rebuild_tolerance: f64,
    /// Far-field cell size s of K̂ in pixels ([`KernelLayout`]): beyond `near_radius_px` the
    /// support is stored per s×s cell. 1 keeps the reference's exact r×r window.
    pub far_cell: usize,
    /// Radius (pixels) around each pixel within which K̂ is kept per pixel when `far_cell` > 1.
    pub near_radius_px: usize,
    /// How the forward scatter from outside the support enters Eq. 4.52: summed on coarse
    /// blocks (the default), murk's per-pixel far field, or the reference's constant ε
    /// (Eq. 4.53) ([`FarField`]).
    pub far_field: FarField,
    /// How a facet radiates into the medium in the surface-camera forward scatter: the
    /// physical Lambertian cosine (default) or Eq. 4.41's isotropic facet ([`FacetEmission`]).
    pub facet_emission: FacetEmission,
    /// Full model or the backscatter-only baseline.
    pub mode: PsMode,
    /// Apply the 3×3 median after backscatter subtraction (§4.3.4).
    pub median_filter: bool,
    /// Add back the backscatter beyond the surface that subtracting the no-object image
    /// removed in excess ([`crate::ps::backscatter::backscatter_tail`]), from each iteration's
    /// shape. Off reproduces the reference, which neglects it.
    pub backscatter_tail: bool,
    /// Observations below this fraction of a pixel's brightest one count as shadowed.
    pub shadow_ratio: f64,
    /// Refine each pixel's Eq. 4.57 solution by Gauss–Newton on the exact `G(T, n·l)` of
    /// Eq. 4.54 instead of keeping Eq. 4.55's linearisation (see
    /// [`crate::ps::near_light::solve_normals`]). Off reproduces the reference exactly.
    pub exact_g: bool,
    /// `s` of the integration weights (Eq. 4.61–4.62).
    pub smoothness_s: f64,
    /// BiCGStab settings for Eq. 4.52.
    pub solver: BicgstabParams,
    /// Refuse captures whose kernel K̂ would exceed this many bytes.
    pub max_kernel_bytes: usize,
}

impl Default for PsParams {
    fn default() -> Self {
        Self {
            initial_distance_mm: 300.0,
            distance: DistanceMode::default(),
            initial_depth_mm: None,
            support_r: 61,
            far_cell: DEFAULT_FAR_CELL,
            near_radius_px: DEFAULT_NEAR_RADIUS_PX,
            far_field: FarField::default(),
            facet_emission: FacetEmission::default(),
            max_iterations: 5,
            tolerance: 1e-3,
            kernel_rebuild_tolerance: 1e-3,
            mode: PsMode::Full,
            median_filter: true,
            backscatter_tail: true,
            shadow_ratio: 0.05,
            exact_g: true,
            smoothness_s: 0.02,
            solver: BicgstabParams::default(),
            max_kernel_bytes: DEFAULT_MAX_KERNEL_BYTES,
        }
    }
}

/// Every check [`photometric_stereo`] makes before it starts, for callers that validate at
/// submission: the settings, the capture, and the kernel's memory bound.
pub fn validate_request(capture: &PsCapture, params: &PsParams) -> Result<()> {
    let (width, height) = capture.dims();
    params.validate(width, height)?;
    // An unknown distance (0) is searched for first; the light directions are judged there.
    capture.validate((params.initial_distance_mm > 0.0).then_some(params.initial_distance_mm))?;
    if let Some(d) = &params.initial_depth_mm {
        if d.len() != width * height {
            return Err(MurkError::invalid(
                "initial_depth_mm",
                format!("{} values for a {width}x{height} image", d.len()),
            ));
        }
        if d.iter()
            .zip(&capture.mask)
            .any(|(z, &m)| m && !(z.is_finite() && *z > 0.0))
        {
            return Err(MurkError::invalid(
                "initial_depth_mm",
                "must be finite and > 0 on every object pixel",
            ));
        }
    }
    let object_pixels = capture.mask.iter().filter(|&&b| b).count();
    let bytes = params.kernel_layout()?.entry_bytes(object_pixels);
    if params.mode == PsMode::Full && bytes > params.max_kernel_bytes {
        return Err(MurkError::over_limit(
            "support_r",
            format!(
                "the kernel for {object_pixels} object pixels at r = {} (far cell {}) needs \
                 {bytes} bytes, over the limit of {} bytes: use a smaller support, a larger \
                 far cell or a smaller image",
                params.support_r, params.far_cell, params.max_kernel_bytes
            ),
        ));
    }
    Ok(())
}

impl PsParams {
    /// The storage layout of K̂ these settings ask for.
    pub fn kernel_layout(&self) -> Result<KernelLayout> {
        KernelLayout::coarse_far(self.support_r, self.far_cell, self.near_radius_px)
    }

    /// Checks the settings against an image of `width × height`; errors name the field.
    pub fn validate(&self, width: usize, height: usize) -> Result<()> {
        let d = self.initial_distance_mm;
        let needs_distance =
            self.distance == DistanceMode::Fixed && self.initial_depth_mm.is_none();
        if !d.is_finite() || d < 0.0 || (d == 0.0 && needs_distance) || d > MAX_OBJECT_DISTANCE_MM {
            return Err(MurkError::invalid(
                "initial_distance_mm",
                if d > MAX_OBJECT_DISTANCE_MM {
                    format!(
                        "{d} mm is beyond {MAX_OBJECT_DISTANCE_MM:e} mm: photometric stereo \
                         sees objects near its lights (distances are in millimetres)"
                    )
                } else if needs_distance {
                    format!("must be finite and > 0 when the distance is fixed, got {d}")
                } else {
                    format!("must be finite and > 0 (or 0: unknown, estimated), got {d}")
                },
            ));
        }
        let r = self.support_r;
        if r < 3 || r.is_multiple_of(2) {
            return Err(MurkError::invalid(
                "support_r",
                format!("must be odd and ≥ 3, got {r}"),
            ));
        }
        if r > MAX_SUPPORT_R || r > width.max(height) {
            return Err(MurkError::invalid(
                "support_r",
                format!(
                    "{r} exceeds the limit min({MAX_SUPPORT_R}, image size {})",
                    width.max(height)
                ),
            ));
        }
        self.kernel_layout()?;
        if self.max_iterations == 0 || self.max_iterations > MAX_ITERATIONS {
            return Err(MurkError::invalid(
                "max_iterations",
                format!(
                    "must be in 1..={MAX_ITERATIONS}, got {}",
                    self.max_iterations
                ),
            ));
        }
        if !self.tolerance.is_finite() || self.tolerance < 0.0 {
            return Err(MurkError::invalid(
                "tolerance",
                format!("must be finite and ≥ 0, got {}", self.tolerance),
            ));
        }
        let k = self.kernel_rebuild_tolerance;
        if !k.is_finite() || !(0.0..1.0).contains(&k) {
            return Err(MurkError::invalid(
                "kernel_rebuild_tolerance",
                format!("must be in [0, 1) (a fraction of the mean depth), got {k}"),
            ));
        }
        if !self.shadow_ratio.is_finite() || !(0.0..1.0).contains(&self.shadow_ratio) {
            return Err(MurkError::invalid(
                "shadow_ratio",
                format!("must be in [0, 1), got {}", self.shadow_ratio),
            ));
        }
        if !self.smoothness_s.is_finite() || self.smoothness_s <= 0.0 {
            return Err(MurkError::invalid(
                "smoothness_s",
                format!("must be finite and > 0, got {}", self.smoothness_s),
            ));
        }
        let s = &self.solver;
        if !s.rel_tolerance.is_finite() || s.rel_tolerance <= 0.0 || s.rel_tolerance >= 1.0 {
            return Err(MurkError::invalid(
                "solver.rel_tolerance",
                format!("must be in (0, 1), got {}", s.rel_tolerance),
            ));
        }
        if s.max_iterations == 0 || s.max_iterations > 10_000 {
            return Err(MurkError::invalid(
                "solver.max_iterations",
                format!("must be in 1..=10000, got {}", s.max_iterations),
            ));
        }
        Ok(())
    }
}

/// What one pass of steps 3–5 did.
#[derive(Clone, Debug, PartialEq)]
pub struct PsIterationStats {
    /// 1-based iteration number.
    pub iteration: usize,
    /// Mean |Δz| against the previous shape over the mean depth.
    pub relative_depth_change: f64,
    /// Mean depth of the shape after this iteration, mm.
    pub mean_depth_mm: f64,
    /// BiCGStab iterations per light (empty in backscatter-only mode).
    pub solver_iterations: Vec<usize>,
    /// Largest final relative residual over the lights (0 in backscatter-only mode).
    pub solver_residual: f64,
    /// ε of Eq. 4.53 (0 in backscatter-only mode).
    pub epsilon: f64,
    /// The constant term `C` of Eq. 4.52 per light; empty with [`FarField::Blocks`], which has
    /// none.
    pub constant_term: Vec<f64>,
    /// Bytes of the stored kernel K̂.
    pub kernel_bytes: usize,
    /// Pixels whose normal was filled from neighbours.
    pub filled_pixels: usize,
    /// Seconds spent building K̂ (0 when it was reused).
    pub kernel_s: f64,
    /// K̂ was an earlier iteration's: the shape had moved less than
    /// [`PsParams::kernel_rebuild_tolerance`] since it was built.
    pub kernel_reused: bool,
    /// Seconds in BiCGStab.
    pub solve_s: f64,
    /// Seconds in photometric stereo.
    pub normals_s: f64,
    /// Seconds in integration, scale choice and the normal update.
    pub integrate_s: f64,
    /// Seconds computing the backscatter tail from the current shape (0 without it).
    pub tail_s: f64,
    /// The distance fit that set this iteration's scale (`None` with a fixed distance, or
    /// when the fit had too few usable pixels and the previous mean depth was kept).
    pub distance_fit: Option<DistanceFit>,
}

/// Output of [`photometric_stereo`].
#[derive(Clone, Debug)]
pub struct PsResult {
    /// Image width.
    pub width: usize,
    /// Image height.
    pub height: usize,
    /// Unit normals (camera frame, towards the camera) from the last iteration's photometric
    /// stereo; `[0, 0, -1]` outside the mask.
    pub normals: Vec<[f32; 3]>,
    /// Albedo from the last iteration (Eq. 4.58), 0 outside the mask.
    pub albedo: Vec<f32>,
    /// z-depth of the integrated shape, mm; NaN outside the mask.
    pub depth_mm: Vec<f32>,
    /// The mask the pipeline worked on.
    pub mask: Vec<bool>,
    /// Per-iteration statistics.
    pub iterations: Vec<PsIterationStats>,
    /// Photometric-stereo normals after each iteration (for Table 4.1-style error tables).
    pub normals_history: Vec<Vec<[f32; 3]>>,
    /// Seconds for backscatter removal.
    pub backscatter_s: f64,
    /// Total seconds.
    pub total_s: f64,
    /// Kernel support r the run used, pixels.
    pub support_r: usize,
    /// Far-field cell size the run used, pixels: 1 for the exact window, also when a support
    /// within the near radius made the requested cells moot ([`KernelLayout::coarse_far`]).
    pub far_cell: usize,
    /// The search before the first iteration when no distance was given (its mean depth is
    /// where the initial plane was put).
    pub initial_distance_fit: Option<DistanceFit>,
}

/// The augmented operator of Eq. 4.52 over K̂.
struct Augmented<'a>(&'a ForwardKernel);

impl BlockOperator for Augmented<'_> {
    fn dim(&self) -> usize {
        self.0.dim()
    }
    fn apply_block(&self, xs: &[f64], ys: &mut [f64], k: usize) {
        self.0.apply_block(xs, ys, k);
    }
}

/// Runs the method of §4.3.4 on `capture`. Progress is reported per stage and iteration;
/// `monitor` cancellation stops it between (and inside) stages.
pub fn photometric_stereo(
    capture: &PsCapture,
    params: &PsParams,
    monitor: &Monitor,
) -> Result<PsResult> {
    let started = Instant::now();
    let (width, height) = capture.dims();
    validate_request(capture, params)?;
    let mask = capture.mask.clone();
    let n = width * height;
    let intr = capture.intrinsics;
    let medium = capture.medium;
    let masked: Vec<usize> = (0..n).filter(|&p| mask[p]).collect();
    let model = match params.mode {
        PsMode::Full => ShadingModel::ForwardScatter,
        PsMode::BackscatterOnly => ShadingModel::DirectOnly,
    };
    let ft = FTable::global();
    let gt = GTable::global();

    // Step 2.
    monitor.progress("backscatter removal", 0.0);
    let t0 = Instant::now();
    let observed: Vec<Vec<f32>> = capture
        .images
        .iter()
        .zip(&capture.backgrounds)
        .map(|(img, bg)| {
            remove_backscatter(img.data(), bg.data(), &mask, width, params.median_filter)
        })
        .collect();
    let backscatter_s = t0.elapsed().as_secs_f64();
    monitor.checkpoint()?;

    // Step 1: a fronto-parallel plane, or the given shape. An unknown distance is searched
    // for with the plane and the observations as they are (the forward scatter still in them):
    // a rough start that the fits after each integration refine.
    let estimate = params.distance == DistanceMode::Estimate;
    let mut initial_distance_fit = None;
    let plane_distance = if params.initial_distance_mm > 0.0 || params.initial_depth_mm.is_some() {
        params.initial_distance_mm
    } else {
        monitor.progress("distance search", 0.0);
        let unit: Vec<f32> = (0..n)
            .map(|p| if mask[p] { 1.0 } else { f32::NAN })
            .collect();
        let pts = back_project(&intr, width, &unit, &mask);
        let fit = fit_mean_depth(
            &pts,
            &mask,
            &observed,
            &capture.lights,
            &medium,
            gt,
            model,
            params.shadow_ratio,
            default_range_mm(&capture.lights),
        )
        .ok_or_else(|| {
            MurkError::invalid(
                "initial_distance_mm",
                "no distance was given and too few object pixels have four lit observations \
                 to estimate one: give the object's approximate distance",
            )
        })?;
        initial_distance_fit = Some(fit);
        capture.check_light_directions(fit.mean_depth_mm)?;
        fit.mean_depth_mm
    };
    let mut depth: Vec<f32> = (0..n)
        .map(|p| match (&params.initial_depth_mm, mask[p]) {
            (_, false) => f32::NAN,
            (Some(d), true) => d[p],
            (None, true) => plane_distance as f32,
        })
        .collect();
    let mut shape_normals = match &params.initial_depth_mm {
        Some(_) => normals_from_depth(&intr, width, height, &depth, &mask),
        None => vec![[0.0f32, 0.0, -1.0]; n],
    };
    let mut iterations = Vec::new();
    let mut normals_history = Vec::new();
    let mut last = None;
    let total = params.max_iterations as f32;
    // The kernel with the depth it was built from, and the last solve's unknowns (BiCGStab's
    // start in the next iteration: the shape, and so the solution, moves little between
    // iterations).
    let mut kernel_cache: Option<(ForwardKernel, Vec<f32>)> = None;
    let mut last_solution: Option<Vec<f64>> = None;

    for it in 0..params.max_iterations {
        let stage = |name: &str, frac: f32| {
            monitor.progress(
                &format!("iteration {}/{}: {name}", it + 1, params.max_iterations),
                (it as f32 + frac) / total,
            )
        };
        let points = back_project(&intr, width, &depth, &mask);
        let tail_corrected;
        let t = Instant::now();
        let observed: &[Vec<f32>] = if params.backscatter_tail && medium.beta_per_mm > 0.0 {
            let tail = backscatter_tail(ft, &medium, &capture.lights, &points, &mask);
            tail_corrected = observed
                .iter()
                .zip(tail)
                .map(|(obs, t)| obs.iter().zip(t).map(|(o, t)| o + t).collect())
                .collect::<Vec<Vec<f32>>>();
            &tail_corrected
        } else {
            &observed
        };
        let tail_s = t.elapsed().as_secs_f64();
        let mut stats = PsIterationStats {
            iteration: it + 1,
            relative_depth_change: 0.0,
            mean_depth_mm: 0.0,
            solver_iterations: Vec::new(),
            solver_residual: 0.0,
            epsilon: 0.0,
            constant_term: Vec::new(),
            kernel_bytes: 0,
            filled_pixels: 0,
            kernel_s: 0.0,
            kernel_reused: false,
            solve_s: 0.0,
            normals_s: 0.0,
            integrate_s: 0.0,
            tail_s,
            distance_fit: None,
        };

        // Step 3: reflected component L_s per light.
        // Without scattering (β = 0) K is diagonal and the solve is a division.
        let use_kernel = params.mode == PsMode::Full && medium.beta_per_mm > 0.0;
        let reflected: Vec<Vec<f32>> = match use_kernel {
            false => observed
                .iter()
                .map(|obs| {
                    (0..n)
                        .map(|p| {
                            if mask[p] {
                                let d = norm(points[p]);
                                obs[p] * (medium.sigma_per_mm * d).exp() as f32
                            } else {
                                0.0
                            }
                        })
                        .collect()
                })
                .collect(),
            true => {
                stage("forward-scatter kernel", 0.0);
                let t = Instant::now();
                let reuse = kernel_cache.as_ref().is_some_and(|(_, built_from)| {
                    relative_change(built_from, &depth, &masked) < params.kernel_rebuild_tolerance
                });
                if !reuse {
                    // The old kernel goes first: two at once would double the peak memory.
                    drop(kernel_cache.take());
                    let geom = SurfaceGeometry {
                        width,
                        height,
                        intrinsics: intr,
                        points_mm: points.clone(),
                        normals: shape_normals.clone(),
                        mask: mask.clone(),
                        emission: params.facet_emission,
                    };
                    let kernel = ForwardKernel::build_monitored(
                        ft,
                        &medium,
                        &geom,
                        &params.kernel_layout()?,
                        params.far_field,
                        monitor,
                    )?;
                    kernel_cache = Some((kernel, depth.clone()));
                    stats.kernel_s = t.elapsed().as_secs_f64();
                }
                let (kernel, _) = kernel_cache.as_ref().expect("built above or kept");
                stats.kernel_reused = reuse;
                stats.kernel_bytes = kernel.bytes();
                stats.epsilon = kernel.epsilon();
                monitor.checkpoint()?;
                stage("forward-scatter removal", 0.3);
                let t = Instant::now();
                let solved = solve_reflected(
                    kernel,
                    observed,
                    &points,
                    &medium,
                    &params.solver,
                    last_solution.as_deref(),
                    &monitor.sub((it as f32 + 0.3) / total, (it as f32 + 0.6) / total),
                )?;
                stats.solve_s = t.elapsed().as_secs_f64();
                stats.solver_residual = solved
                    .report
                    .rel_residuals
                    .iter()
                    .copied()
                    .fold(0.0, f64::max);
                stats.solver_iterations = solved.report.iterations;
                stats.constant_term = solved.constant_term;
                last_solution = Some(solved.solution);
                solved.reflected
            }
        };
        monitor.checkpoint()?;

        // Step 4: normals and albedo.
        stage("photometric stereo", 0.6);
        let t = Instant::now();
        let est = solve_normals(
            &reflected,
            &capture.lights,
            &medium,
            gt,
            model,
            &points,
            &mask,
            width,
            params.shadow_ratio,
            params.exact_g,
        );
        stats.filled_pixels = masked.iter().filter(|&&p| !est.solved[p]).count();
        stats.normals_s = t.elapsed().as_secs_f64();
        monitor.checkpoint()?;

        // Step 5: integrate, fix the scale, update normals from the shape.
        stage("normal integration", 0.8);
        let t = Instant::now();
        let g = integrate_normals(
            &intr,
            width,
            height,
            &est.normals,
            &mask,
            &IntegrationParams {
                smoothness_s: params.smoothness_s,
            },
        )?;
        let prev_mean = mean_masked(&depth, &masked);
        let mut new_depth = depth_from_log(&g, &mask, prev_mean);
        if estimate {
            // The new shape at the distance its observations fit best; the range is wide
            // enough for a 20 % error in the starting guess to be corrected in one step, and
            // later iterations can move further.
            let fit = fit_mean_depth(
                &back_project(&intr, width, &new_depth, &mask),
                &mask,
                &reflected,
                &capture.lights,
                &medium,
                gt,
                model,
                params.shadow_ratio,
                (prev_mean / DISTANCE_STEP, prev_mean * DISTANCE_STEP),
            );
            if let Some(f) = fit {
                // Under-relaxed: the fit is made with this iteration's reflected component,
                // which still carries the previous distance's errors, and the full step
                // overshoots by about 1.6× (docs/accuracy.md).
                let s = (f.mean_depth_mm / prev_mean).powf(DISTANCE_RELAXATION) as f32;
                for z in new_depth.iter_mut() {
                    *z *= s;
                }
            }
            stats.distance_fit = fit;
        }
        stats.relative_depth_change = relative_change(&depth, &new_depth, &masked);
        depth = new_depth;
        shape_normals = normals_from_depth(&intr, width, height, &depth, &mask);
        stats.mean_depth_mm = mean_masked(&depth, &masked);
        stats.integrate_s = t.elapsed().as_secs_f64();
        tracing::debug!(?stats, "photometric stereo iteration");
        let converged = stats.relative_depth_change < params.tolerance;
        iterations.push(stats);
        normals_history.push(est.normals.clone());
        last = Some(est);
        if converged {
            break;
        }
    }
    monitor.progress("done", 1.0);
    let est = last.ok_or_else(|| MurkError::Internal("no iteration ran".into()))?;
    Ok(PsResult {
        width,
        height,
        normals: est.normals,
        albedo: est.albedo,
        depth_mm: depth,
        mask,
        iterations,
        normals_history,
        backscatter_s,
        total_s: started.elapsed().as_secs_f64(),
        support_r: params.support_r,
        far_cell: params.kernel_layout()?.cell(),
        initial_distance_fit,
    })
}

/// What [`solve_reflected`] returns.
pub(crate) struct ReflectedSolve {
    /// L_s per light over the full image (0 off the mask).
    pub(crate) reflected: Vec<Vec<f32>>,
    /// The extra unknown of Eq. 4.52 per light (empty without one).
    pub(crate) constant_term: Vec<f64>,
    /// BiCGStab's iterations and residuals.
    pub(crate) report: crate::ps::bicgstab::BicgstabReport,
    /// The unknowns as solved (per light: the masked pixels' L_s, then the constant term), to
    /// start the next solve from.
    pub(crate) solution: Vec<f64>,
}

/// Step 3: the reflected component L_s of every light from its backscatter-removed image
/// `observed[i]` by block BiCGStab on Eq. 4.52 with `kernel` (built over `kernel`'s masked
/// pixels at `points_mm`), started from `start` (an earlier [`ReflectedSolve::solution`] over
/// the same mask) or else from the observations with the camera-path attenuation e^{−σ d}
/// undone.
pub(crate) fn solve_reflected(
    kernel: &ForwardKernel,
    observed: &[Vec<f32>],
    points_mm: &[[f32; 3]],
    medium: &Medium,
    solver: &BicgstabParams,
    start: Option<&[f64]>,
    monitor: &Monitor,
) -> Result<ReflectedSolve> {
    let m = observed.len();
    let n = observed.first().map_or(0, Vec::len);
    let count = kernel.masked_count();
    let dim = kernel.dim();
    let mut b = vec![0.0f64; dim * m];
    for (i, obs) in observed.iter().enumerate() {
        for k in 0..count {
            b[i * dim + k] = f64::from(obs[kernel.pixel_index(k)]);
        }
    }
    let mut x = match start.filter(|s| s.len() == b.len() && s.iter().all(|v| v.is_finite())) {
        Some(s) => s.to_vec(),
        None => {
            let mut x = vec![0.0f64; dim * m];
            for i in 0..m {
                for k in 0..count {
                    let p = kernel.pixel_index(k);
                    let diag = (-medium.sigma_per_mm * norm(points_mm[p])).exp();
                    x[i * dim + k] = b[i * dim + k] / diag;
                }
            }
            x
        }
    };
    let report = bicgstab_block(&Augmented(kernel), &b, &mut x, m, solver, monitor)?;
    let reflected = (0..m)
        .map(|i| {
            let mut ls = vec![0.0f32; n];
            for k in 0..count {
                ls[kernel.pixel_index(k)] = x[i * dim + k] as f32;
            }
            ls
        })
        .collect();
    Ok(ReflectedSolve {
        reflected,
        // Eq. 4.52's C (the first extra unknown); none when the far field is summed in blocks.
        constant_term: if kernel.extra_unknowns() > 0 {
            (0..m).map(|i| x[i * dim + count]).collect()
        } else {
            Vec::new()
        },
        report,
        solution: x,
    })
}

fn norm(v: [f32; 3]) -> f64 {
    let [x, y, z] = v.map(f64::from);
    (x * x + y * y + z * z).sqrt()
}

/// Mean |b − a| over `masked` divided by b's mean there.
fn relative_change(a: &[f32], b: &[f32], masked: &[usize]) -> f64 {
    let change = masked
        .iter()
        .map(|&p| f64::from((b[p] - a[p]).abs()))
        .sum::<f64>()
        / masked.len().max(1) as f64;
    change / mean_masked(b, masked).max(1e-9)
}

fn mean_masked(v: &[f32], masked: &[usize]) -> f64 {
    masked.iter().map(|&p| f64::from(v[p])).sum::<f64>() / masked.len().max(1) as f64
}

/// Camera-frame points of a z-depth map (zeros outside the mask).
pub fn back_project(
    intr: &crate::camera::Intrinsics,
    width: usize,
    depth_mm: &[f32],
    mask: &[bool],
) -> Vec<[f32; 3]> {
    depth_mm
        .iter()
        .enumerate()
        .map(|(p, &z)| {
            if !mask[p] {
                return [0.0; 3];
            }
            let r = intr.ray((p % width) as f64, (p / width) as f64);
            let s = f64::from(z) / r[2];
            [(r[0] * s) as f32, (r[1] * s) as f32, (r[2] * s) as f32]
        })
        .collect()
}
