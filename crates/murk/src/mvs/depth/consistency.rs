//! Source–reference consistency: the left–right check of semi-global matching (Hirschmüller
//! 2008, §3.4 and §4.3), generalised from a rectified pair to the plane sweep's homographies.
//!
//! For a rectified pair SGBM computes the right image's disparity from the same aggregated
//! volume (`D_m(q) = argmin_d S(q + d, d)`) and rejects a left pixel whose match disagrees. Here
//! the reference pixel `p` on plane `i` lands on source pixel `q = round(π_{r→s}(p; z_i))`
//! (Eq. 3.2). The source's winner at `q` is the plane of the lowest aggregated cost over every
//! `(p, i)` that lands there: one pass over the aggregated volume, with a 64-bit atomic minimum
//! per source pixel that packs the cost's bits (non-negative `f32`s order like their bit
//! patterns) above the plane index. On a rectified pair, whose rows land on one source row by a
//! whole-pixel shift per plane, a row's claims are first reduced per source column with vector
//! minima and take one atomic minimum per column ([`SourceClaims::add_row`]). Reference pixel
//! `p` with winner `i*` is **consistent** with a source when the source's winner at
//! `q* = round(π(p; z_{i*}))` is within `tolerance` planes of `i*`. When the source pixel is
//! claimed by a nearer plane (a larger index) by more than the tolerance, a nearer surface
//! hides `p` from that source: **occluded**; any other disagreement is a **mismatch**. With
//! several sources a pixel is kept when it is consistent with at least one (each source sees
//! different occlusions), and it is occluded when every source that sees it says so.
//!
//! Rejected pixels are filled as in Hirschmüller's §4.4 so the depth map stays dense (the
//! confidence output carries the rejection): the nearest accepted pixel along each of 8
//! directions is found, and an occluded pixel takes the second-smallest of those inverse depths
//! (it belongs to the background), a mismatched one their median.
//!
//! Speckles ([`reject_speckles`]): 4-connected regions in which neighbouring plane indices differ
//! by at most `range` planes and that are smaller than `max_size` pixels are isolated mistakes
//! of the winner-take-all (OpenCV's `filterSpeckles`); they are rejected and filled like
//! mismatches.

use std::sync::atomic::{AtomicU64, Ordering};

use rayon::prelude::*;

use super::sgm::PathCost;
use super::shift_claims::{inside_columns, reduce_shift_levels, shift_key_parts};
use crate::camera::Intrinsics;
use crate::mvs::cost_volume::SHIFT_TOLERANCE_PX;
use crate::mvs::plane_sweep::{PlaneSet, PlaneWarp, RowWarpF32};
use crate::mvs::pose::Pose;

/// Geometry of one source view relative to the reference, for the consistency check.
#[derive(Clone, Copy, Debug)]
pub struct SourceGeometry {
    /// Reference intrinsics (pixels).
    pub k_ref: Intrinsics,
    /// Source intrinsics (pixels).
    pub k_src: Intrinsics,
    /// `(R_{r→s}, t_{r→s})`, see [`Pose::relative`].
    pub relative: Pose,
    /// Source image size, pixels.
    pub width: usize,
    /// Source image size, pixels.
    pub height: usize,
}

/// Outcome of the check for one reference pixel.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Verdict {
    /// Consistent with at least one source (or no source sees the pixel: nothing to check).
    Consistent,
    /// Every source that sees the pixel has it hidden by a nearer surface.
    Occluded,
    /// Inconsistent for another reason (or a speckle).
    Mismatch,
}

/// Marker of a target outside the source image (or behind the source camera).
const OUTSIDE: u32 = u32::MAX;

/// The row-major index of the source pixel nearest to where column `x` lands in a `w×h` source
/// under `warp`, [`OUTSIDE`] outside it or behind the camera. In `f32` ([`RowWarpF32`]): ample
/// for a nearest-pixel decision, and the claims pass runs 8 planes per AVX2 instruction. Rounds
/// by truncating `u + ½` after the bounds check, and computes an index for every input so the
/// caller's loop vectorises.
#[inline(always)]
fn target(warp: &RowWarpF32, x: f32, w: f32, h: f32) -> u32 {
    let (u, v, hw) = warp.project(x);
    target_at(u, v, hw, w, h)
}

/// [`target`] from the projected point `(u, v)` and its homogeneous scale `hw`.
#[inline(always)]
fn target_at(u: f32, v: f32, hw: f32, w: f32, h: f32) -> u32 {
    let inside = hw > 0.0 && u >= -0.5 && u < w - 0.5 && v >= -0.5 && v < h - 0.5;
    let (u, v) = if inside {
        (u + 0.5, v + 0.5)
    } else {
        (0.0, 0.0)
    };
    // SAFETY: `u` and `v` are finite and in [0, 2³¹): either 0, or in [0, w) and [0, h) by the
    // bounds check. The saturating `as u32` (NaN and range checks per lane, and no f32 → u32
    // vector instruction before AVX-512) left the claims' loop scalar; this truncation is the
    // same value and one vector instruction.
    let (ui, vi) = unsafe { (u.to_int_unchecked::<i32>(), v.to_int_unchecked::<i32>()) };
    let q = vi as u32 * w as u32 + ui as u32;
    if inside {
        q
    } else {
        OUTSIDE
    }
}

/// One reference row's warps into a `w×h` source, for [`targets_of`].
#[derive(Clone, Copy)]
struct RowTargets<'a> {
    /// Every plane's warp on the row.
    warps: &'a [RowWarpF32],
    /// Every warp's [`RowWarpF32::constant_reciprocal`] when all have one (a rectified pair: no
    /// division per voxel, the same targets), else empty.
    reciprocals: &'a [f32],
    /// Source width, pixels.
    w: f32,
    /// Source height, pixels.
    h: f32,
}

/// [`target`] of every plane's warp at column `x` into `out[i]`.
fn targets_of(avx2: bool, row: RowTargets<'_>, x: f32, out: &mut [u32]) {
    #[inline(always)]
    fn plain(row: RowTargets<'_>, x: f32, out: &mut [u32]) {
        let (w, h) = (row.w, row.h);
        if row.reciprocals.is_empty() {
            for (o, t) in out.iter_mut().zip(row.warps) {
                *o = target(t, x, w, h);
            }
        } else {
            for ((o, t), &r) in out.iter_mut().zip(row.warps).zip(row.reciprocals) {
                let (u, v, hw) = t.project_with(x, r);
                *o = target_at(u, v, hw, w, h);
            }
        }
    }
    #[cfg(target_arch = "x86_64")]
    {
        #[target_feature(enable = "avx2")]
        unsafe fn with_avx2(row: RowTargets<'_>, x: f32, out: &mut [u32]) {
            plain(row, x, out)
        }
        if avx2 {
            // SAFETY: the caller detected AVX2 on this CPU ([`crate::cpu::avx2_enabled`]).
            return unsafe { with_avx2(row, x, out) };
        }
    }
    let _ = avx2;
    plain(row, x, out)
}

/// Where a reference row's voxels land when every plane's warp moves the row onto one source
/// row as a horizontal shift (a rectified pair): the voxel `(x, i)` lands on source pixel
/// `start + x + offsets[i]` when `0 ≤ x + offsets[i] < w_src`, else outside. `offsets[i]` is
/// `du_i` rounded and the row `v` rounded, so a target differs from the projection's rounding
/// only where `x + du_i` lies within the shift's tolerance of a half pixel (the cost volume's
/// [`SHIFT_TOLERANCE_PX`], so the sweep and the claims agree on which rows are shifts). The claims and the
/// check use this same rule for such rows, so a voxel and its check agree on the pixel.
fn shift_targets(
    warps: &[PlaneWarp],
    y: usize,
    w_ref: usize,
    g: &SourceGeometry,
    offsets: &mut Vec<i32>,
) -> Option<usize> {
    offsets.clear();
    let mut row = None;
    for wp in warps {
        let (du, v) = wp.row(y as f64).shift(w_ref, SHIFT_TOLERANCE_PX)?;
        let v = (v + 0.5).floor();
        if !(0.0..g.height as f64).contains(&v) || row.is_some_and(|r| r != v) {
            return None;
        }
        row = Some(v);
        offsets.push(
            (du + 0.5)
                .floor()
                .clamp(-(1 << 30) as f64, (1 << 30) as f64) as i32,
        );
    }
    row.map(|v| v as usize * g.width)
}

/// Per-task buffers of [`SourceClaims::add_row`], reused from row to row.
#[derive(Default)]
pub struct ClaimScratch {
    warps: Vec<RowWarpF32>,
    reciprocals: Vec<f32>,
    targets: Vec<u32>,
    offsets: Vec<i32>,
    /// A shift row's best `(level, plane)` key per source column.
    local: Vec<u32>,
}

/// Marker of a source pixel that no reference voxel lands on.
const UNCLAIMED: u64 = u64::MAX;

/// A claim of plane `i` (of the set) at aggregated `cost` as one `u64`: smaller is better, and
/// of equal costs the higher plane wins ([`SourceClaims`]). Costs are `≥ 0`, so their bits order
/// like their values.
#[inline(always)]
fn claim_key(cost: f32, i: usize) -> u64 {
    (u64::from(cost.max(0.0).to_bits()) << 32) | u64::from(!(i as u32))
}

/// The source's winner-take-all plane at every source pixel, accumulated over the reference
/// rows as their aggregated costs become available (depth is estimated in strips): the
/// `argmin` over the reference voxels `(p, i)` that project to the source pixel of their
/// aggregated cost (costs `≥ 0`). Ties go to the higher plane index, the nearer surface: of two
/// surfaces that explain a source pixel equally well, the nearer one hides the other.
pub struct SourceClaims {
    geometry: SourceGeometry,
    warps: Vec<PlaneWarp>,
    best: Vec<AtomicU64>,
}

impl SourceClaims {
    /// No claims yet, for the planes `planes` of a reference seen by `geometry`'s source.
    pub fn new(geometry: &SourceGeometry, planes: &PlaneSet) -> Self {
        let warps = (0..planes.num_planes)
            .map(|i| {
                PlaneWarp::new(
                    &geometry.k_ref,
                    &geometry.k_src,
                    &geometry.relative,
                    planes.depth(i as f64),
                )
            })
            .collect();
        let best = (0..geometry.width * geometry.height)
            .map(|_| AtomicU64::new(UNCLAIMED))
            .collect();
        Self {
            geometry: *geometry,
            warps,
            best,
        }
    }

    /// Adds the claims of reference rows `rows`, whose aggregated costs are `sum`
    /// (pixel-major `[row][x][plane]`, `w` pixels wide, one curve of `n` planes per pixel,
    /// `sum`'s first row being reference row `rows.start`).
    pub fn add(&self, sum: &[f32], n: usize, w: usize, rows: std::ops::Range<usize>) {
        let y0 = rows.start;
        rows.into_par_iter()
            .for_each_init(ClaimScratch::default, |scratch, y| {
                self.add_row(y, &sum[(y - y0) * w * n..][..w * n], 0, n, 1.0, scratch)
            });
    }

    /// [`Self::add`] for one reference row `y` whose aggregated costs are `row` (`[x][plane]`,
    /// `n` planes per pixel, the planes `first..first + n` of the set), for a caller that has
    /// the row in cache for other work too. `unit` converts `row`'s values to cost units (1 for
    /// `f32` costs; [`super::quantise::Quantiser::unit`] for a strip's `u16` levels), so that
    /// claims of rows from different strips compare.
    pub fn add_row<T: PathCost>(
        &self,
        y: usize,
        row: &[T],
        first: usize,
        n: usize,
        unit: f32,
        scratch: &mut ClaimScratch,
    ) {
        let g = &self.geometry;
        let plane_warps = &self.warps[first..first + n];
        let avx2 = crate::cpu::avx2_enabled();
        let ClaimScratch {
            warps,
            reciprocals,
            targets: q,
            offsets,
            local,
        } = scratch;
        let w = row.len() / n.max(1);
        if let Some(start) = shift_targets(plane_warps, y, w, g, offsets) {
            self.add_shift_row(row, first, n, unit, start, offsets, local);
            return;
        }
        warps.clear();
        warps.extend(plane_warps.iter().map(|wp| wp.row(y as f64).to_f32()));
        reciprocals.clear();
        reciprocals.extend(warps.iter().map_while(|t| t.constant_reciprocal()));
        if reciprocals.len() != warps.len() {
            reciprocals.clear();
        }
        q.resize(n, OUTSIDE);
        let targets = RowTargets {
            warps,
            reciprocals,
            w: g.width as f32,
            h: g.height as f32,
        };
        for (x, curve) in row.chunks_exact(n).enumerate() {
            targets_of(avx2, targets, x as f32, q);
            for (i, (&q, &c)) in q.iter().zip(curve).enumerate() {
                if q == OUTSIDE {
                    continue;
                }
                let key = claim_key(c.to_f32() * unit, first + i);
                // Most claims lose: a plain load first skips the locked read-modify-write for
                // them.
                let slot = &self.best[q as usize];
                if key < slot.load(Ordering::Relaxed) {
                    slot.fetch_min(key, Ordering::Relaxed);
                }
            }
        }
    }

    /// [`Self::add_row`] of a row whose voxels land on one source row at `start` by the
    /// whole-pixel `offsets` ([`shift_targets`]). For `u16` levels the row's claims are first
    /// reduced per source column as `u32` keys ([`reduce_shift_levels`]: vector minima, no
    /// atomics), and the source row then takes one
    /// atomic minimum per column: the same winners, because the cost `level · unit` orders like
    /// the level and ties still go to the higher plane. `f32` costs take the per-voxel loop.
    #[allow(clippy::too_many_arguments)]
    fn add_shift_row<T: PathCost>(
        &self,
        row: &[T],
        first: usize,
        n: usize,
        unit: f32,
        start: usize,
        offsets: &[i32],
        local: &mut Vec<u32>,
    ) {
        let w = row.len() / n.max(1);
        let w_src = self.geometry.width;
        // `i` is the plane within the row's planes; the key names the set's plane.
        let claim = |q: usize, cost: f32, i: usize| {
            let key = claim_key(cost, first + i);
            let slot = &self.best[start + q];
            if key < slot.load(Ordering::Relaxed) {
                slot.fetch_min(key, Ordering::Relaxed);
            }
        };
        let Some(levels) = T::as_levels(row) else {
            for (i, &o) in offsets.iter().enumerate() {
                for x in inside_columns(o, w, w_src) {
                    claim(
                        (x as i64 + o as i64) as usize,
                        row[x * n + i].to_f32() * unit,
                        i,
                    );
                }
            }
            return;
        };
        local.clear();
        local.resize(w_src, u32::MAX);
        reduce_shift_levels(crate::cpu::avx512bw_enabled(), levels, n, offsets, local);
        for (q, &k) in local.iter().enumerate() {
            if k != u32::MAX {
                let (level, i) = shift_key_parts(k);
                claim(q, f32::from(level) * unit, i);
            }
        }
    }

    /// The winning plane at every source pixel, with the warps the check needs again.
    pub fn winners(self) -> SourceWinners {
        let wins = self
            .best
            .into_iter()
            .map(|a| {
                let k = a.into_inner();
                if k == UNCLAIMED {
                    u32::MAX
                } else {
                    !((k & 0xffff_ffff) as u32)
                }
            })
            .collect();
        SourceWinners {
            geometry: self.geometry,
            warps: self.warps,
            wins,
        }
    }
}

/// One source's winner-take-all planes ([`SourceClaims::winners`]).
pub struct SourceWinners {
    geometry: SourceGeometry,
    /// The reference→source warp of every plane (shared with the claims pass).
    warps: Vec<PlaneWarp>,
    /// Row-major over the source's pixels, `u32::MAX` where nothing landed.
    wins: Vec<u32>,
}

/// The verdict for every reference pixel (row-major `w×h`) from its winning plane
/// `winner[p]` (an integer plane index) and each source's winners.
pub fn check(winner: &[u32], w: usize, sources: &[SourceWinners], tolerance: f32) -> Vec<Verdict> {
    let mut verdicts = vec![Verdict::Consistent; winner.len()];
    verdicts
        .par_chunks_mut(w.max(1))
        .zip(winner.par_chunks(w.max(1)))
        .enumerate()
        .for_each_init(
            || {
                (
                    vec![Vec::new(); sources.len()],
                    Vec::with_capacity(sources.len()),
                )
            },
            |(offsets, shifts), (y, (out, row))| {
                // Each source's shift targets of this row, as its claims had them.
                shifts.clear();
                shifts.extend(
                    sources
                        .iter()
                        .zip(offsets.iter_mut())
                        .map(|(s, o)| shift_targets(&s.warps, y, w, &s.geometry, o)),
                );
                for (x, (v, &i)) in out.iter_mut().zip(row).enumerate() {
                    *v = verdict_of(x, y, i, sources, shifts, offsets, tolerance);
                }
            },
        );
    verdicts
}

/// [`check`]'s verdict for reference pixel `(x, y)` with winner `i`, given each source's
/// [`shift_targets`] of row `y` (start and offsets).
fn verdict_of(
    x: usize,
    y: usize,
    i: u32,
    sources: &[SourceWinners],
    shifts: &[Option<usize>],
    offsets: &[Vec<i32>],
    tolerance: f32,
) -> Verdict {
    let (mut seen, mut occluded) = (0usize, 0usize);
    for ((s, shift), offsets) in sources.iter().zip(shifts).zip(offsets) {
        let g = &s.geometry;
        // The claims' targets, so a voxel and its check agree on the pixel.
        let q = match shift {
            Some(start) => {
                let c = x as i64 + i64::from(offsets[i as usize]);
                if (0..g.width as i64).contains(&c) {
                    (start + c as usize) as u32
                } else {
                    OUTSIDE
                }
            }
            None => {
                let warp = s.warps[i as usize].row(y as f64).to_f32();
                target(&warp, x as f32, g.width as f32, g.height as f32)
            }
        };
        if q == OUTSIDE {
            continue;
        }
        let j = s.wins[q as usize];
        if j == u32::MAX {
            continue;
        }
        seen += 1;
        let d = j as f32 - i as f32;
        if d.abs() <= tolerance {
            return Verdict::Consistent;
        }
        if d > tolerance {
            occluded += 1;
        }
    }
    match (seen, occluded) {
        (0, _) => Verdict::Consistent,
        (s, o) if s == o => Verdict::Occluded,
        _ => Verdict::Mismatch,
    }
}

/// Rejects speckles (see the module docs) as mismatches: the pixels of 4-connected regions of
/// fewer than `max_size` pixels in which neighbours' fractional plane indices `index` differ by
/// at most `range`. Pixels already rejected neither join nor bridge regions; `max_size` 0 turns
/// the filter off.
pub fn reject_speckles(
    index: &[f32],
    verdict: &mut [Verdict],
    w: usize,
    h: usize,
    max_size: usize,
    range: f32,
) {
    if max_size == 0 || w == 0 || h == 0 {
        return;
    }
    // Union-find over runs: a row's consistent pixels joined to their left neighbour form a
    // run, and a pixel joined to the one above merges their runs. Two comparisons and a label
    // per pixel, where a flood fill pushed and popped every pixel (a 640×480 pair: 3.5 ms).
    const NONE: u32 = u32::MAX;
    let joined = |p: usize, q: usize| (index[q] - index[p]).abs() <= range;
    let mut label = vec![NONE; w * h];
    let mut parent: Vec<u32> = Vec::new();
    let mut pixels: Vec<u32> = Vec::new();
    fn root(parent: &mut [u32], mut r: u32) -> u32 {
        while parent[r as usize] != r {
            // Path halving.
            let up = parent[parent[r as usize] as usize];
            parent[r as usize] = up;
            r = up;
        }
        r
    }
    for y in 0..h {
        for x in 0..w {
            let p = y * w + x;
            if verdict[p] != Verdict::Consistent {
                continue;
            }
            let run = if x > 0 && label[p - 1] != NONE && joined(p - 1, p) {
                label[p - 1]
            } else {
                parent.push(parent.len() as u32);
                pixels.push(0);
                (parent.len() - 1) as u32
            };
            label[p] = run;
            pixels[run as usize] += 1;
            if y > 0 && label[p - w] != NONE && joined(p - w, p) {
                let (a, b) = (root(&mut parent, run), root(&mut parent, label[p - w]));
                if a != b {
                    parent[a as usize] = b;
                }
            }
        }
    }
    // Each run's region size, through its root.
    let roots: Vec<u32> = (0..parent.len() as u32)
        .map(|r| root(&mut parent, r))
        .collect();
    let mut region = vec![0usize; parent.len()];
    for (r, &n) in pixels.iter().enumerate() {
        region[roots[r] as usize] += n as usize;
    }
    for (v, &l) in verdict.iter_mut().zip(&label) {
        if l != NONE && region[roots[l as usize] as usize] < max_size {
            *v = Verdict::Mismatch;
        }
    }
}

/// Fills rejected pixels of the inverse-depth map `inv` (row-major `w×h`) from the accepted
/// ones (see the module docs); pixels with no accepted pixel in any direction keep their value.
pub fn fill_rejected(inv: &mut [f32], verdict: &[Verdict], w: usize, h: usize) {
    // The fill looks along SGM's 8 path directions for the nearest accepted pixel. Walking
    // each direction from each rejected pixel costs the length of the rejected run (an
    // occluded band tens of pixels wide: 11-16 ms at 640×480); instead one sweep of the rows
    // against each vertical sense carries, per column, the nearest accepted pixel along the
    // three directions of that sense, and each row finds its horizontal ones itself.
    if w == 0 || h == 0 {
        return;
    }
    let accepted = |q: usize| verdict[q] == Verdict::Consistent;
    // Rejected pixels numbered row by row: `slots[y]` is the first of row `y`.
    let mut slots = Vec::with_capacity(h + 1);
    slots.push(0usize);
    for row in verdict.chunks_exact(w) {
        let rejected = row.iter().filter(|&&v| v != Verdict::Consistent).count();
        slots.push(slots[slots.len() - 1] + rejected);
    }
    if slots[h] == 0 {
        return;
    }
    // For each rejected pixel, the nearest accepted pixel along `(dx, dy)` for `dx = −1, 0, 1`
    // ([`NONE`] where the walk leaves the image first): the rows swept from the side the
    // directions point to, `reach[x][k]` the first accepted pixel at or beyond column `x` of
    // the row swept last along direction `k` (all [`NONE`] before the first row: off the image).
    let sweep = |dy: isize| -> Vec<[usize; 3]> {
        let mut nearest = vec![[NONE; 3]; slots[h]];
        let (mut reach, mut next) = (vec![[NONE; 3]; w], vec![[NONE; 3]; w]);
        let mut row = |y: usize| {
            let mut slot = slots[y];
            for (x, out) in next.iter_mut().enumerate() {
                let p = y * w + x;
                if accepted(p) {
                    *out = [p; 3];
                    continue;
                }
                let mut near = [NONE; 3];
                for (k, n) in near.iter_mut().enumerate() {
                    if let Some(xx) = (x + k).checked_sub(1).filter(|&xx| xx < w) {
                        *n = reach[xx][k];
                    }
                }
                *out = near;
                nearest[slot] = near;
                slot += 1;
            }
            std::mem::swap(&mut reach, &mut next);
        };
        if dy > 0 {
            (0..h).rev().for_each(&mut row);
        } else {
            (0..h).for_each(&mut row);
        }
        nearest
    };
    let (below, above) = rayon::join(|| sweep(1), || sweep(-1));
    let src: Vec<f32> = inv.to_vec();
    inv.par_chunks_mut(w).enumerate().for_each_init(
        || vec![NONE; w],
        |right, (y, row)| {
            let first = y * w;
            // The nearest accepted pixel right of each column, then the left one on the way.
            let mut reach = NONE;
            for x in (0..w).rev() {
                right[x] = reach;
                if accepted(first + x) {
                    reach = first + x;
                }
            }
            let (mut left, mut slot) = (NONE, slots[y]);
            for (x, out) in row.iter_mut().enumerate() {
                let v = verdict[first + x];
                if v == Verdict::Consistent {
                    left = first + x;
                    continue;
                }
                let mut found = [0.0f32; 8];
                let mut k = 0;
                let candidates = [right[x], left].into_iter();
                for q in candidates.chain(below[slot]).chain(above[slot]) {
                    if q != NONE {
                        found[k] = src[q];
                        k += 1;
                    }
                }
                slot += 1;
                if k == 0 {
                    continue;
                }
                let vals = &mut found[..k];
                vals.sort_unstable_by(f32::total_cmp);
                *out = match v {
                    // The background: the second-smallest inverse depth (the smallest may be an
                    // outlier), as Hirschmüller's occlusion fill.
                    Verdict::Occluded => vals[1.min(k - 1)],
                    _ => vals[k / 2],
                };
            }
        },
    );
}

/// No accepted pixel in that direction ([`fill_rejected`]).
const NONE: usize = usize::MAX;

#[cfg(test)]
mod tests {
    use super::*;

    /// The definition of the regions [`reject_speckles`] finds by joining runs: a flood fill of
    /// each region from its pixels' 4-neighbours.
    fn flood_fill_speckles(
        index: &[f32],
        verdict: &mut [Verdict],
        w: usize,
        h: usize,
        max_size: usize,
        range: f32,
    ) {
        let npix = w * h;
        if max_size == 0 {
            return;
        }
        // A pixel's column travels with it on the stack: a division per visited pixel (`p % w`)
        // was most of the fill's time.
        let mut seen = vec![false; npix];
        let mut stack: Vec<(usize, usize)> = Vec::new();
        let mut region: Vec<usize> = Vec::new();
        for start in 0..npix {
            if seen[start] || verdict[start] != Verdict::Consistent {
                continue;
            }
            region.clear();
            stack.push((start, start % w));
            seen[start] = true;
            while let Some((p, x)) = stack.pop() {
                region.push(p);
                let mut visit = |q: usize, x: usize| {
                    if !seen[q]
                        && verdict[q] == Verdict::Consistent
                        && (index[q] - index[p]).abs() <= range
                    {
                        seen[q] = true;
                        stack.push((q, x));
                    }
                };
                if x > 0 {
                    visit(p - 1, x - 1);
                }
                if x + 1 < w {
                    visit(p + 1, x + 1);
                }
                if p >= w {
                    visit(p - w, x);
                }
                if p + w < npix {
                    visit(p + w, x);
                }
            }
            // Marking in place is safe: these pixels are seen and never visited again.
            if region.len() < max_size {
                for &p in &region {
                    verdict[p] = Verdict::Mismatch;
                }
            }
        }
    }

    proptest::proptest! {
        /// Joining runs finds the flood fill's regions: the same verdicts on random maps with
        /// rejected pixels, plateaus and NaN.
        #[test]
        fn speckle_runs_match_the_flood_fill(
            w in 1usize..24,
            h in 1usize..16,
            seed in 0u64..10_000,
            max_size in 0usize..12,
        ) {
            let n = w * h;
            let mut state = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            let mut next = || {
                state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                (state >> 33) as u32
            };
            let index: Vec<f32> = (0..n)
                .map(|_| match next() % 16 {
                    0 => f32::NAN,
                    k => (k % 5) as f32 * 0.8,
                })
                .collect();
            let verdict: Vec<Verdict> = (0..n)
                .map(|_| match next() % 6 {
                    0 => Verdict::Occluded,
                    1 => Verdict::Mismatch,
                    _ => Verdict::Consistent,
                })
                .collect();
            let (mut a, mut b) = (verdict.clone(), verdict);
            reject_speckles(&index, &mut a, w, h, max_size, 1.0);
            flood_fill_speckles(&index, &mut b, w, h, max_size, 1.0);
            proptest::prop_assert_eq!(a, b);
        }
    }

    const W: usize = 48;
    const H: usize = 8;
    const N: usize = 16;

    /// A rectified pair: the source sits `baseline` to the right (`t_{r→s} = (−b, 0, 0)`), so
    /// reference pixel `x` on plane `i` lands on source column `x − f·b/z_i`.
    fn rectified(planes: &PlaneSet) -> SourceGeometry {
        let k = Intrinsics {
            fx: 20.0,
            fy: 20.0,
            cx: W as f64 / 2.0,
            cy: H as f64 / 2.0,
            skew: 0.0,
        };
        // Disparity f·b/z is 1 px per plane: b = step / (f · Δ(1/z)).
        let b = 1.0 / (20.0 * planes.inverse_depth_step());
        SourceGeometry {
            k_ref: k,
            k_src: k,
            relative: Pose::translation_only([-b, 0.0, 0.0]).unwrap(),
            width: W,
            height: H,
        }
    }

    /// The disparity (px) of plane `i` in [`rectified`]'s geometry.
    fn disparity(planes: &PlaneSet, g: &SourceGeometry, i: usize) -> f64 {
        let w = PlaneWarp::new(&g.k_ref, &g.k_src, &g.relative, planes.depth(i as f64));
        10.0 - w.map(10.0, 3.0).0
    }

    /// Aggregated costs `|i − truth(p)|`: every pixel's curve has its minimum at its true plane.
    fn curves(truth: &[usize]) -> Vec<f32> {
        truth
            .iter()
            .flat_map(|&t| (0..N).map(move |i| (i as f32 - t as f32).abs()))
            .collect()
    }

    /// The claims' shortcut for rows without a rotation (one reciprocal per plane) gives every
    /// voxel the target the general projection gives it.
    #[test]
    fn targets_with_constant_reciprocals_match_the_general_ones() {
        let planes = PlaneSet::new(1.0, 10.0, N).unwrap();
        let g = rectified(&planes);
        let claims = SourceClaims::new(&g, &planes);
        let avx2 = crate::cpu::avx2_enabled();
        let (mut general, mut fast) = (vec![0u32; N], vec![0u32; N]);
        let mut inside = 0;
        for y in 0..H {
            let rows: Vec<RowWarpF32> = claims
                .warps
                .iter()
                .map(|wp| wp.row(y as f64).to_f32())
                .collect();
            let reciprocals: Vec<f32> = rows
                .iter()
                .filter_map(|r| r.constant_reciprocal())
                .collect();
            assert_eq!(reciprocals.len(), N);
            let row = |reciprocals| RowTargets {
                warps: &rows,
                reciprocals,
                w: W as f32,
                h: H as f32,
            };
            for x in 0..W {
                targets_of(avx2, row(&[]), x as f32, &mut general);
                targets_of(avx2, row(&reciprocals), x as f32, &mut fast);
                assert_eq!(general, fast, "row {y} column {x}");
                inside += general.iter().filter(|&&q| q != OUTSIDE).count();
            }
        }
        assert!(inside > W * H * N / 2, "{inside}");
    }

    /// On a rectified pair every row is a shift row, and its targets are the projection's (the
    /// test geometry's disparities are whole pixels, so no target sits at a half pixel); a
    /// forward baseline has no shift rows.
    #[test]
    fn shift_targets_are_the_projections_targets() {
        let planes = PlaneSet::new(1.0, 10.0, N).unwrap();
        let g = rectified(&planes);
        let claims = SourceClaims::new(&g, &planes);
        let mut offsets = Vec::new();
        let mut inside = 0;
        for y in 0..H {
            let start = shift_targets(&claims.warps, y, W, &g, &mut offsets).expect("shift row");
            assert_eq!(start, y * W);
            for (i, wp) in claims.warps.iter().enumerate() {
                let row = wp.row(y as f64).to_f32();
                for x in 0..W {
                    let want = target(&row, x as f32, W as f32, H as f32);
                    let c = x as i64 + i64::from(offsets[i]);
                    let got = if (0..W as i64).contains(&c) {
                        (start + c as usize) as u32
                    } else {
                        OUTSIDE
                    };
                    assert_eq!(got, want, "row {y} plane {i} column {x}");
                    inside += usize::from(got != OUTSIDE);
                }
            }
        }
        assert!(inside > W * H * N / 2, "{inside}");
        let forward = SourceGeometry {
            relative: Pose::translation_only([0.0, 0.0, -0.5]).unwrap(),
            ..g
        };
        let claims = SourceClaims::new(&forward, &planes);
        assert!(shift_targets(&claims.warps, 1, W, &forward, &mut offsets).is_none());
    }

    /// A shift row's `u16` claims, reduced per source column as `(level, plane)` keys before one
    /// atomic minimum per column, give the winners of the per-voxel loop over the same costs
    /// in cost units, ties included (levels drawn from a few values, so many tie).
    #[test]
    fn u16_shift_claims_equal_per_voxel_claims() {
        let planes = PlaneSet::new(1.0, 10.0, N).unwrap();
        let g = rectified(&planes);
        let mut s = 12345u64;
        let levels: Vec<u16> = (0..W * H * N)
            .map(|_| {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((s >> 33) % 7) as u16 * 300
            })
            .collect();
        let unit = 0.37f32;
        let costs: Vec<f32> = levels.iter().map(|&l| f32::from(l) * unit).collect();
        let (fast, plain) = (
            SourceClaims::new(&g, &planes),
            SourceClaims::new(&g, &planes),
        );
        let mut scratch = ClaimScratch::default();
        for y in 0..H {
            let r = y * W * N..(y + 1) * W * N;
            fast.add_row(y, &levels[r.clone()], 0, N, unit, &mut scratch);
            plain.add_row(y, &costs[r], 0, N, 1.0, &mut scratch);
        }
        let (fast, plain) = (fast.winners(), plain.winners());
        assert_eq!(fast.wins, plain.wins);
        assert!(fast.wins.iter().filter(|&&j| j != u32::MAX).count() > W * H / 2);
    }

    #[test]
    fn plane_step_is_one_pixel_of_disparity() {
        let planes = PlaneSet::new(1.0, 10.0, N).unwrap();
        let g = rectified(&planes);
        for i in 0..N - 1 {
            let d = disparity(&planes, &g, i + 1) - disparity(&planes, &g, i);
            assert!((d - 1.0).abs() < 1e-9, "plane {i}: {d}");
        }
    }

    /// A rectified pair's planes, one pixel of disparity apart or less (down to just over half
    /// a pixel), give every row offsets that the sliding reduction takes
    /// ([`super::super::shift_claims::sliding_offsets`]), whole plane set or any run of it.
    #[test]
    fn rectified_offsets_take_the_sliding_reduction() {
        use super::super::shift_claims::sliding_offsets;
        let planes = PlaneSet::new(1.0, 10.0, N).unwrap();
        for step_px in [1.0, 0.93, 0.7, 0.51] {
            let mut g = rectified(&planes);
            let b = step_px / (20.0 * planes.inverse_depth_step());
            g.relative = Pose::translation_only([-b, 0.0, 0.0]).unwrap();
            let claims = SourceClaims::new(&g, &planes);
            let mut offsets = Vec::new();
            for y in 0..H {
                for (first, end) in [(0, N), (3, 11), (N - 1, N)] {
                    let start = shift_targets(&claims.warps[first..end], y, W, &g, &mut offsets);
                    assert!(start.is_some(), "step {step_px}, row {y}: a shift row");
                    assert!(
                        sliding_offsets(&offsets),
                        "step {step_px}, row {y}, planes {first}..{end}: {offsets:?}"
                    );
                }
            }
        }
    }

    /// A foreground strip (plane 12) in front of a background (plane 2): the background just
    /// left of the strip is hidden from the source (which sits to the right, so it sees the strip
    /// shifted further left than the background), a planted wrong winner is a mismatch, and
    /// everything else is consistent.
    #[test]
    fn occlusion_mismatch_and_consistent_pixels() {
        let planes = PlaneSet::new(1.0, 10.0, N).unwrap();
        let g = rectified(&planes);
        let (d_bg, d_fg) = (disparity(&planes, &g, 2), disparity(&planes, &g, 12));
        let gap = (d_fg - d_bg).round() as usize;
        assert_eq!(gap, 10);
        let (x0, x1) = (30, 40);
        let mut truth = vec![2usize; W * H];
        for y in 0..H {
            for x in x0..x1 {
                truth[y * W + x] = 12;
            }
        }
        let sum = curves(&truth);
        let claims = SourceClaims::new(&g, &planes);
        claims.add(&sum[..N * W * 3], N, W, 0..3);
        claims.add(&sum[N * W * 3..], N, W, 3..H);
        let wins = claims.winners();
        let mut winner: Vec<u32> = truth.iter().map(|&t| t as u32).collect();
        let bad = 3 * W + 12;
        winner[bad] = 9;
        let v = check(&winner, W, &[wins], 1.0);
        for y in 0..H {
            for x in 0..W {
                let p = y * W + x;
                let expect = if p == bad {
                    Verdict::Mismatch
                } else if (x0 - gap..x0).contains(&x) {
                    Verdict::Occluded
                } else {
                    Verdict::Consistent
                };
                // Pixels that land outside the source have nothing to check against.
                assert_eq!(v[p], expect, "pixel ({x}, {y})");
            }
        }
    }

    #[test]
    fn small_islands_are_speckles_large_regions_are_not() {
        let (w, h) = (20, 10);
        let mut index = vec![3.0f32; w * h];
        // A 2x2 island 5 planes away, and a smooth ramp (steps of 0.5) that stays one region.
        for (y, x) in [(2, 2), (2, 3), (3, 2), (3, 3)] {
            index[y * w + x] = 8.0;
        }
        for y in 0..h {
            for x in 10..w {
                index[y * w + x] = 3.0 + 0.5 * (x - 9) as f32;
            }
        }
        let speckles = |max_size| {
            let mut verdict = vec![Verdict::Consistent; w * h];
            reject_speckles(&index, &mut verdict, w, h, max_size, 1.0);
            (0..w * h)
                .filter(|&p| verdict[p] != Verdict::Consistent)
                .collect::<Vec<usize>>()
        };
        assert_eq!(
            speckles(10),
            vec![2 * w + 2, 2 * w + 3, 3 * w + 2, 3 * w + 3]
        );
        // Size 0 turns the filter off.
        assert!(speckles(0).is_empty());
    }

    #[test]
    fn occluded_pixels_take_the_background_mismatches_the_median() {
        let (w, h) = (7, 5);
        // Left half background (0.1), right half foreground (0.5); the column between rejected.
        let mut inv: Vec<f32> = (0..w * h)
            .map(|p| if p % w < 3 { 0.1 } else { 0.5 })
            .collect();
        let mut verdict = vec![Verdict::Consistent; w * h];
        for y in 0..h {
            inv[y * w + 3] = 9.0;
            verdict[y * w + 3] = if y == 2 {
                Verdict::Mismatch
            } else {
                Verdict::Occluded
            };
        }
        fill_rejected(&mut inv, &verdict, w, h);
        // The middle row sees 0.1 (left, two left diagonals) and 0.5 (right, two right
        // diagonals) and the rejected column above/below: median of 6 values is 0.5.
        assert_eq!(inv[2 * w + 3], 0.5);
        for y in [0, 1, 3, 4] {
            assert_eq!(inv[y * w + 3], 0.1, "row {y}");
        }
        assert_eq!(inv[0], 0.1);
    }

    /// The fill as first written: a walk along each of the 8 directions from each rejected
    /// pixel until an accepted one.
    fn fill_by_walking(inv: &mut [f32], verdict: &[Verdict], w: usize, h: usize) {
        use crate::mvs::depth::sgm::DIRECTIONS;
        let src: Vec<f32> = inv.to_vec();
        for y in 0..h {
            for x in 0..w {
                let v = verdict[y * w + x];
                if v == Verdict::Consistent {
                    continue;
                }
                let mut found = Vec::new();
                for &(dx, dy) in &DIRECTIONS {
                    let (dx, dy) = (i64::from(dx), i64::from(dy));
                    let (mut xx, mut yy) = (x as i64 + dx, y as i64 + dy);
                    while xx >= 0 && yy >= 0 && (xx as usize) < w && (yy as usize) < h {
                        let q = yy as usize * w + xx as usize;
                        if verdict[q] == Verdict::Consistent {
                            found.push(src[q]);
                            break;
                        }
                        xx += dx;
                        yy += dy;
                    }
                }
                if found.is_empty() {
                    continue;
                }
                found.sort_unstable_by(f32::total_cmp);
                let k = found.len();
                inv[y * w + x] = match v {
                    Verdict::Occluded => found[1.min(k - 1)],
                    _ => found[k / 2],
                };
            }
        }
    }

    /// The sweeps fill every rejected pixel as the walks do, on random maps with rejected
    /// runs and blobs of every size, single rows and columns, and maps with nothing accepted.
    #[test]
    fn fill_matches_the_walks() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        for (w, h) in [(37usize, 23usize), (1, 9), (12, 1), (64, 40), (3, 3)] {
            for density in [0.05f64, 0.3, 0.7, 1.0] {
                let verdict: Vec<Verdict> = (0..w * h)
                    .map(|_| {
                        if rng.random_bool(density) {
                            if rng.random_bool(0.5) {
                                Verdict::Occluded
                            } else {
                                Verdict::Mismatch
                            }
                        } else {
                            Verdict::Consistent
                        }
                    })
                    .collect();
                let inv: Vec<f32> = (0..w * h).map(|_| rng.random_range(0.1f32..2.0)).collect();
                let (mut fast, mut walked) = (inv.clone(), inv);
                fill_rejected(&mut fast, &verdict, w, h);
                fill_by_walking(&mut walked, &verdict, w, h);
                for (i, (a, b)) in fast.iter().zip(&walked).enumerate() {
                    assert_eq!(
                        a.to_bits(),
                        b.to_bits(),
                        "{w}x{h} density {density}, pixel {i}"
                    );
                }
            }
        }
    }
}
