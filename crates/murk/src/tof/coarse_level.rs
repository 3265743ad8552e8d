//! Algorithm 2's coarse level (Eq. 5.16) and the held-out check that follows it
//! ([`HELD_OUT_ROUNDS`]), written against the solves they judge ([`CoarseSolve`]): the scatter
//! is solved either on the judged pixels themselves ([`super::irls`]) or on a grid of their
//! block means and interpolated back (a stream's cold frame, [`super::grid_coarse`]). Either
//! way the blocks' residuals, their scale σ₂ and the check's statistic are the judged pixels'.

use rayon::prelude::*;

use super::irls_settings::{weight_change, Convergence, IrlsConfig};
use super::quadratic_prior::PatchGrid;
use super::tukey::{self, median_in_place};
use crate::error::{MurkError, Result};
use crate::monitor::Monitor;

/// Rounds of the held-out check that follows the coarse level. Algorithm 2 starts from "no
/// object" (every weight 1), so the first x-step bends over a large near object; where the bend
/// is enough for some of its blocks to fit, the coarse level accepts them, and the fine level
/// then keeps the object's band as background (cluttered thick seed 1 at 512×424,
/// docs/accuracy.md). The check judges every accepted block against the estimate its
/// neighbours imply: two x-steps in which the accepted blocks of one colour of a checkerboard
/// have no weight. A block whose held-out RMS residual lies more than `c_coarse` robust
/// deviations (1.4826·MAD) above the median of the accepted blocks' is rejected; the estimate
/// is then solved again and the check repeated, until a round rejects nothing. The scale comes
/// from the held-out residuals themselves, because they are larger than in-sample ones wherever
/// the scatter curves; object blocks, already rejected, have no weight in either solve and so
/// do not pull the held-out estimates.
pub const HELD_OUT_ROUNDS: usize = 3;

/// The solves the coarse level judges, and the residuals it judges them by, over the judged
/// pixels (`weights` and `out` have one value per pixel).
pub(super) trait CoarseSolve {
    /// The scatter's x- and a-steps under `weights`, at CG tolerance multiplier `tol_scale`;
    /// returns the CG iterations.
    fn solve(&mut self, weights: &[f64], tol_scale: f64) -> Result<usize>;

    /// Each pixel's squared residual norm against the current scatter, relative to its noise
    /// level, into `out`; the noise levels first follow the scatter.
    fn residuals2(&mut self, out: &mut [f64]) -> Result<()>;

    /// The same against the scatter solved under `held` from the current one (whose own state is
    /// left as it is), at the levels of the current scatter; returns the CG iterations.
    fn held_out_residuals2(&mut self, held: &[f64], out: &mut [f64]) -> Result<usize>;

    /// The scatter solved again under `weights` after the check rejected blocks, at the check's
    /// tolerance, and the noise levels following it; returns the CG iterations.
    fn resolve(&mut self, weights: &[f64]) -> Result<usize>;
}

/// What the coarse level and its check leave for the fine level.
pub(super) struct CoarseOutcome {
    /// The judged pixels' weights: each block's Tukey weight, spread over its pixels.
    pub(super) weights: Vec<f64>,
    /// The scale σ₂, from the first iteration's block residuals.
    pub(super) sigma: Option<f64>,
    /// Coarse iterations run.
    pub(super) iterations_run: usize,
    /// Blocks the held-out check rejected.
    pub(super) held_out_rejected: usize,
    /// CG iterations spent.
    pub(super) cg_iterations: usize,
}

/// Up to `cfg.coarse_iterations` iterations of the coarse level over the `blocks`, from "no
/// object" (every weight at 1), then the held-out check; `floor` bounds σ₂ from below.
/// `tick(stage)` follows every iteration; cancellation is checked every iteration and round.
pub(super) fn coarse_level(
    solver: &mut impl CoarseSolve,
    blocks: &PatchGrid,
    cfg: &IrlsConfig,
    floor: f64,
    stage: &str,
    monitor: &Monitor,
    tick: &(dyn Fn(&str) + Sync),
) -> Result<CoarseOutcome> {
    let n = blocks.width() * blocks.height();
    let k = blocks.count();
    let mut weights = vec![1.0; n];
    let mut res2 = vec![0.0; n];
    let mut row_sums = vec![0.0; blocks.height() * blocks.patches_x()];
    let mut patch_rms = vec![0.0; k];
    let mut patch_weight = vec![1.0; k];
    let mut prev_patch_weight = vec![1.0; k];
    let mut scratch = vec![0.0; k];
    let (mut sigma, mut iterations_run, mut cg_iterations) = (None, 0, 0);
    let mut conv = Convergence::new();
    for it in 0..cfg.coarse_iterations {
        monitor.checkpoint()?;
        cg_iterations += solver.solve(&weights, conv.tol_scale())?;
        iterations_run += 1;
        solver.residuals2(&mut res2)?;
        patch_rms_residuals(blocks, &res2, &mut row_sums, &mut patch_rms);
        if it == 0 {
            // The patch residual is an RMS, i.e. already a per-pixel deviation about the ideal
            // zero residual, so its median over patches is the robust scale (a "median absolute
            // deviation" about zero): background patches sit near r = 1 and an object patch at
            // r ≫ 1, independent of patch size (the last patches are larger). (A pixel-level
            // MAD instead was tried: it ignores the quadratic misfit of background patches and
            // flagged whole background patches as outliers on several simulated frames.)
            scratch.copy_from_slice(&patch_rms);
            let med = quantile_in_place(&mut scratch, cfg.coarse_quantile).ok_or_else(|| {
                MurkError::Numerical("non-finite residual at the coarse level".into())
            })?;
            sigma = Some(med.max(floor));
        }
        let s2 = sigma.unwrap_or(floor);
        for (pw, &rms) in patch_weight.iter_mut().zip(&patch_rms) {
            *pw = tukey::weight(rms / s2, cfg.channel.c_coarse);
        }
        spread_patch_weights(blocks, &patch_weight, &mut weights);
        tick(stage);
        let (dw, flipped) = weight_change(&prev_patch_weight, &patch_weight, cfg.mask_threshold);
        prev_patch_weight.copy_from_slice(&patch_weight);
        if it > 0 && conv.update(dw, flipped, cfg.weight_tolerance) {
            break;
        }
    }

    let mut held_out_rejected = 0;
    if cfg.coarse_iterations > 0 {
        for _ in 0..HELD_OUT_ROUNDS {
            monitor.checkpoint()?;
            let (outliers, cg) = held_out_outliers(
                solver,
                &weights,
                blocks,
                &patch_weight,
                cfg.channel.c_coarse,
            )?;
            cg_iterations += cg;
            if outliers.is_empty() {
                break;
            }
            held_out_rejected += outliers.len();
            for b in outliers {
                patch_weight[b] = 0.0;
            }
            spread_patch_weights(blocks, &patch_weight, &mut weights);
            cg_iterations += solver.resolve(&weights)?;
        }
    }
    Ok(CoarseOutcome {
        weights,
        sigma,
        iterations_run,
        held_out_rejected,
        cg_iterations,
    })
}

/// The accepted blocks (`patch_weight` ≥ 0.5) whose held-out residual is an outlier among the
/// accepted blocks' ([`HELD_OUT_ROUNDS`]), and the CG iterations spent; none when fewer than 8
/// blocks are accepted. `weights` are the coarse level's pixel weights.
fn held_out_outliers(
    solver: &mut impl CoarseSolve,
    weights: &[f64],
    blocks: &PatchGrid,
    patch_weight: &[f64],
    c_coarse: f64,
) -> Result<(Vec<usize>, usize)> {
    let (n, w) = (weights.len(), blocks.width());
    let k = blocks.count();
    let accepted: Vec<bool> = patch_weight.iter().map(|&pw| pw >= 0.5).collect();
    if accepted.iter().filter(|&&a| a).count() < 8 {
        return Ok((Vec::new(), 0));
    }
    let mut col_block = vec![0usize; w];
    for (b, &(x0, x1)) in blocks.col_ranges().iter().enumerate() {
        col_block[x0..x1].fill(b);
    }
    let pxn = blocks.patches_x();
    let (mut cv_res2, mut held_res2) = (vec![0.0; n], vec![0.0; n]);
    let mut cg = 0;
    for colour in 0..2 {
        let held: Vec<f64> = (0..n)
            .map(|i| {
                let (bx, by) = (col_block[i % w], blocks.patch_row_of(i / w));
                if accepted[by * pxn + bx] && (bx + by) % 2 == colour {
                    0.0
                } else {
                    weights[i]
                }
            })
            .collect();
        cg += solver.held_out_residuals2(&held, &mut cv_res2)?;
        for i in 0..n {
            if held[i] == 0.0 && weights[i] > 0.0 {
                held_res2[i] = cv_res2[i];
            }
        }
    }
    let mut row_sums = vec![0.0; blocks.height() * pxn];
    let mut rms = vec![0.0; k];
    patch_rms_residuals(blocks, &held_res2, &mut row_sums, &mut rms);
    let mut acc: Vec<f64> = (0..k).filter(|&b| accepted[b]).map(|b| rms[b]).collect();
    let med = median_in_place(&mut acc).unwrap_or(0.0);
    let mut dev: Vec<f64> = acc.iter().map(|v| (v - med).abs()).collect();
    let mad = 1.4826 * median_in_place(&mut dev).unwrap_or(0.0);
    let cut = med + c_coarse * mad;
    let out = (0..k)
        .filter(|&b| accepted[b] && rms[b] > cut && rms[b].is_finite())
        .collect();
    Ok((out, cg))
}

/// RMS of x − x̃ over every patch (Eq. 5.16's ‖x_k − x̃_k‖ divided by √N_k), from each pixel's
/// squared residual `res2`.
fn patch_rms_residuals(grid: &PatchGrid, res2: &[f64], row_sums: &mut [f64], out: &mut [f64]) {
    let w = grid.width();
    let pxn = grid.patches_x();
    let cols = grid.col_ranges();
    row_sums
        .par_chunks_mut(pxn)
        .zip(res2.par_chunks(w))
        .for_each(|(sums, rr)| {
            for (s, &(x0, x1)) in sums.iter_mut().zip(cols) {
                *s = rr[x0..x1].iter().sum();
            }
        });
    for (py, &(y0, y1)) in grid.row_ranges().iter().enumerate() {
        for (px, &(x0, x1)) in cols.iter().enumerate() {
            let ss: f64 = (y0..y1).map(|y| row_sums[y * pxn + px]).sum();
            out[py * pxn + px] = (ss / ((y1 - y0) * (x1 - x0)) as f64).sqrt();
        }
    }
}

/// The `q`-quantile (0–1) of `values` by selection, reordering them; `None` when empty or NaN.
fn quantile_in_place(values: &mut [f64], q: f64) -> Option<f64> {
    if values.is_empty() || values.iter().any(|v| v.is_nan()) {
        return None;
    }
    let k = ((values.len() - 1) as f64 * q.clamp(0.0, 1.0)).round() as usize;
    let (_, v, _) = values.select_nth_unstable_by(k, f64::total_cmp);
    Some(*v)
}

/// The coarse level's blocks: each quadratic patch split `subdivision` times along each axis
/// (never below 3 pixels a side). With 1 they are the patches, as in Eq. 5.16. The robust scale
/// σ₂ is the median block RMS, which measures the background only while most blocks hold no
/// object: a large near object covering parts of over half the 4 × 4 patches drives it up to the
/// object's residuals, and a rejected patch then also discards the background beside the object.
pub(super) fn coarse_blocks(grid: &PatchGrid, subdivision: usize) -> PatchGrid {
    let (w, h) = (grid.width(), grid.height());
    let s = subdivision.max(1);
    let bx = (grid.patches_x() * s).min(w / 3).max(1);
    let by = (grid.patches_y() * s).min(h / 3).max(1);
    PatchGrid::new(w, h, bx, by)
}

/// Every pixel of a patch shares the patch's coarse weight (Eq. 5.16).
fn spread_patch_weights(grid: &PatchGrid, patch_weight: &[f64], weights: &mut [f64]) {
    let pxn = grid.patches_x();
    let cols = grid.col_ranges();
    weights
        .par_chunks_mut(grid.width())
        .enumerate()
        .for_each(|(y, row)| {
            let py = grid.patch_row_of(y);
            for (px, &(x0, x1)) in cols.iter().enumerate() {
                row[x0..x1].fill(patch_weight[py * pxn + px]);
            }
        });
}
