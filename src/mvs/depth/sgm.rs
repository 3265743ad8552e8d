//! Semi-global aggregation (Hirschmüller 2008) of a plane-sweep cost volume over the plane
//! index.
//!
//! Along each path direction `r` the path cost is
//!
//! `L_r(p, i) = C(p, i) + min(L_r(p−r, i), L_r(p−r, i±1) + P1, min_k L_r(p−r, k) + P2) − min_k L_r(p−r, k)`
//!
//! and the aggregated volume is `S(p, i) = Σ_r L_r(p, i)` over 4 or 8 directions. Subtracting
//! `min_k L_r(p−r, k)` keeps `L_r ≤ C_max + P2`, so the values stay bounded: `u16` levels of a
//! quantised volume ([`PathCost`], [`super::quantise`]) never saturate. A path starts at the
//! image border with `L_r = C`.
//!
//! Layout and memory: costs and `S` are **pixel-major** `[y][x][plane]` (the caller
//! transposes once), so each path update is a contiguous, vectorisable loop over planes, and
//! every direction adds straight into the one `S` volume — no per-direction volumes. The
//! directions run in three sweeps ([`aggregate_into`]): both horizontal ones on each row (one
//! rayon task per row, two-curve buffers), then those with `dy = +1` and those with `dy = −1`,
//! each a sweep of rows in path order (each row depends on the previous) whose pixels are split
//! across rayon tasks, with two `W·N` row buffers per direction. A cancellation checkpoint
//! precedes each sweep and each row of the row sweeps.

use rayon::prelude::*;

use crate::error::Result;
use crate::image::ImageF32;
use crate::monitor::Monitor;

/// The 8 path directions `(dx, dy)` (the path steps from `p − r` to `p`); the first 4 are the
/// 4-path subset (horizontal and vertical).
pub const DIRECTIONS: [(i32, i32); 8] = [
    (1, 0),
    (-1, 0),
    (0, 1),
    (0, -1),
    (1, 1),
    (-1, 1),
    (1, -1),
    (-1, -1),
];

/// Pixels per rayon task in the row-sweeping directions: enough work per task (16 curves of N
/// planes) to hide scheduling overhead, small enough to balance over 2+ cores.
const PIXEL_CHUNK: usize = 16;

/// Penalties of one aggregation run.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Penalties {
    /// `P1`: cost of a ±1 plane step between neighbours (cost units).
    pub p1: f32,
    /// `P2`: cost of any larger jump (cost units), before adaptation.
    pub p2: f32,
    /// When `> 0`, `P2` at a path step `p − r → p` becomes `max(P1, P2 / (1 + g/τ))` with `g` the
    /// mean absolute channel difference of the guide image between the two pixels and `τ` this
    /// value: depth jumps are cheaper across image edges. `0` = constant `P2`.
    pub p2_gradient_scale: f32,
}

/// Guide-image access for the adaptive `P2`: the reference image, or the rows of it that a
/// strip of the volume covers (without copying them).
#[derive(Clone, Copy)]
pub struct Guide<'a> {
    data: &'a [f32],
    channels: usize,
    width: usize,
}

impl<'a> Guide<'a> {
    /// The whole image.
    pub fn new(img: &'a ImageF32) -> Self {
        Self::rows(img, 0..img.height())
    }

    /// Rows `rows` of the image (row 0 of the guide is image row `rows.start`).
    pub fn rows(img: &'a ImageF32, rows: std::ops::Range<usize>) -> Self {
        let row_len = img.width() * img.channels();
        Self {
            data: &img.data()[rows.start * row_len..rows.end * row_len],
            channels: img.channels(),
            width: img.width(),
        }
    }
}

impl Penalties {
    /// `P2` for the step from pixel `(xa, ya)` to `(xb, yb)`.
    #[inline]
    fn p2_at(&self, guide: Option<Guide<'_>>, xa: usize, ya: usize, xb: usize, yb: usize) -> f32 {
        match guide {
            Some(g) if self.p2_gradient_scale > 0.0 => {
                let c = g.channels;
                let a = &g.data[(ya * g.width + xa) * c..][..c];
                let b = &g.data[(yb * g.width + xb) * c..][..c];
                let diff: f32 = a.iter().zip(b).map(|(u, v)| (u - v).abs()).sum::<f32>() / c as f32;
                (self.p2 / (1.0 + diff / self.p2_gradient_scale)).max(self.p1)
            }
            _ => self.p2.max(self.p1),
        }
    }
}

/// The value type of an aggregation: `f32` (cost units, the plain arithmetic the tests check
/// against) or `u16` (integer levels of a quantised volume, [`super::quantise`]; as in SGBM).
/// On integers below 2²⁴ both give the same sums, so the `u16` run is the `f32` run of the
/// quantised costs, at half the memory traffic and twice the lanes per instruction.
pub trait PathCost:
    Copy + Send + Sync + PartialEq + PartialOrd + std::fmt::Debug + 'static
{
    /// Larger than every path cost: the identity of [`PathCost::lesser`].
    const MAX: Self;
    /// Zero.
    const ZERO: Self;
    /// `self + o`; saturating at `u16::MAX` for `u16`, so an overflow can only merge the
    /// largest sums, never wrap (with [`super::quantise`]'s levels none occurs).
    fn add(self, o: Self) -> Self;
    /// `self − o` for `self ≥ o` (the recursion's subtraction of the previous minimum).
    fn sub(self, o: Self) -> Self;
    /// The smaller value, without NaN handling: one vector `min` instead of `minnum`'s
    /// compare-and-blend. Costs are finite: `depth_from_costs` rejects non-finite ones before
    /// aggregation, and [`aggregate`] documents the requirement.
    #[inline(always)]
    fn lesser(self, o: Self) -> Self {
        if self < o {
            self
        } else {
            o
        }
    }
    /// A penalty given in this type's units as `f32` (`u16` rounds to the nearest level).
    fn penalty(p: f32) -> Self;
    /// The value as `f32`.
    fn to_f32(self) -> f32;
    /// The value as an integer level when the type holds levels (`u16`), `None` for `f32`.
    fn level(self) -> Option<u16>;
}

impl PathCost for f32 {
    const MAX: Self = f32::INFINITY;
    const ZERO: Self = 0.0;
    #[inline(always)]
    fn add(self, o: Self) -> Self {
        self + o
    }
    #[inline(always)]
    fn sub(self, o: Self) -> Self {
        self - o
    }
    #[inline(always)]
    fn penalty(p: f32) -> Self {
        p
    }
    #[inline(always)]
    fn to_f32(self) -> f32 {
        self
    }
    #[inline(always)]
    fn level(self) -> Option<u16> {
        None
    }
}

impl PathCost for u16 {
    const MAX: Self = u16::MAX;
    const ZERO: Self = 0;
    #[inline(always)]
    fn add(self, o: Self) -> Self {
        self.saturating_add(o)
    }
    #[inline(always)]
    fn sub(self, o: Self) -> Self {
        // `self ≥ o` where the recursion subtracts; wrapping keeps a debug build from checking
        // what the caller guarantees.
        self.wrapping_sub(o)
    }
    #[inline(always)]
    fn penalty(p: f32) -> Self {
        // `as` saturates: a penalty beyond the range is `u16::MAX`, a NaN 0 (validated away).
        // `+ ½` and truncation round a non-negative penalty like `round` without a libm call.
        (p + 0.5) as u16
    }
    #[inline(always)]
    fn to_f32(self) -> f32 {
        f32::from(self)
    }
    #[inline(always)]
    fn level(self) -> Option<u16> {
        Some(self)
    }
}

/// Lanes of the explicitly unrolled plane loop in [`path_step`]: independent running minima let
/// LLVM keep the min-reduction in vector registers (a single scalar accumulator is a
/// loop-carried dependency it will not reassociate for floats). 16 fills one AVX2 register of
/// `u16` (two of `f32`).
const LANES: usize = 16;

/// The recursion for one interior plane. `m − prev_min ≥ 0` is taken first so that `u16` never
/// leaves its range between the two operations.
#[inline(always)]
fn path_value<T: PathCost>(c: T, below: T, at: T, above: T, p1: T, jump: T, prev_min: T) -> T {
    c.add(
        at.lesser(below.lesser(above).add(p1))
            .lesser(jump)
            .sub(prev_min),
    )
}

/// [`path_step`] through a copy compiled with AVX2 when `avx2` (the CPU has it): the same
/// operations on wider registers, so the same results bit for bit (no fused multiply-adds are
/// introduced: the recursion has only additions and minima).
#[inline]
#[allow(clippy::too_many_arguments)]
fn path_step_fast<T: PathCost, const SET: bool>(
    avx2: bool,
    c: &[T],
    prev: &[T],
    prev_min: T,
    p1: T,
    p2: T,
    out: &mut [T],
    sum: &mut [T],
) -> T {
    #[cfg(target_arch = "x86_64")]
    {
        #[target_feature(enable = "avx2")]
        #[allow(clippy::too_many_arguments)]
        unsafe fn with_avx2<T: PathCost, const SET: bool>(
            c: &[T],
            prev: &[T],
            prev_min: T,
            p1: T,
            p2: T,
            out: &mut [T],
            sum: &mut [T],
        ) -> T {
            path_step::<T, SET>(c, prev, prev_min, p1, p2, out, sum)
        }
        if avx2 {
            // SAFETY: the caller detected AVX2 on this CPU ([`crate::cpu::avx2_enabled`]).
            return unsafe { with_avx2::<T, SET>(c, prev, prev_min, p1, p2, out, sum) };
        }
    }
    let _ = avx2;
    path_step::<T, SET>(c, prev, prev_min, p1, p2, out, sum)
}

/// `sum += l`, or `sum = l` for the first direction of a sweep that initialises `S` (`SET`), which
/// saves clearing the volume first.
#[inline(always)]
fn accumulate<T: PathCost, const SET: bool>(sum: &mut T, l: T) {
    if SET {
        *sum = l;
    } else {
        *sum = sum.add(l);
    }
}

/// One path step (the recursion in the module docs) for one pixel: writes `L_r(p, ·)` into
/// `out`, adds it to `sum` (or sets `sum` to it: `SET`) and returns `min_i L_r(p, i)`.
#[inline(always)]
fn path_step<T: PathCost, const SET: bool>(
    c: &[T],
    prev: &[T],
    prev_min: T,
    p1: T,
    p2: T,
    out: &mut [T],
    sum: &mut [T],
) -> T {
    let n = c.len();
    let jump = prev_min.add(p2);
    if n == 1 {
        let l = c[0].add(prev[0].lesser(jump).sub(prev_min));
        out[0] = l;
        accumulate::<T, SET>(&mut sum[0], l);
        return l;
    }
    let first = c[0].add(prev[0].lesser(prev[1].add(p1)).lesser(jump).sub(prev_min));
    out[0] = first;
    accumulate::<T, SET>(&mut sum[0], first);
    let last = c[n - 1].add(
        prev[n - 1]
            .lesser(prev[n - 2].add(p1))
            .lesser(jump)
            .sub(prev_min),
    );
    out[n - 1] = last;
    accumulate::<T, SET>(&mut sum[n - 1], last);
    let mut m = first.lesser(last);
    // Interior planes 1..n−1 as three shifted views of `prev`, in fixed-size chunks: the
    // chunk bodies have no bounds checks and vectorise, with one running minimum per lane.
    let inner = n - 2;
    let (c_in, below, at, above) = (&c[1..n - 1], &prev[..n - 2], &prev[1..n - 1], &prev[2..]);
    let (out_in, sum_in) = (&mut out[1..n - 1], &mut sum[1..n - 1]);
    let full = inner / LANES * LANES;
    let mut acc = [T::MAX; LANES];
    for (((((cc, lo), mid), hi), oo), ss) in c_in[..full]
        .chunks_exact(LANES)
        .zip(below[..full].chunks_exact(LANES))
        .zip(at[..full].chunks_exact(LANES))
        .zip(above[..full].chunks_exact(LANES))
        .zip(out_in[..full].chunks_exact_mut(LANES))
        .zip(sum_in[..full].chunks_exact_mut(LANES))
    {
        for j in 0..LANES {
            let l = path_value(cc[j], lo[j], mid[j], hi[j], p1, jump, prev_min);
            oo[j] = l;
            accumulate::<T, SET>(&mut ss[j], l);
            acc[j] = acc[j].lesser(l);
        }
    }
    if full < inner && inner >= LANES {
        // The remainder as one more full chunk ending at the last interior plane: its first
        // planes were done above, so their values are recomputed (the same, from the same
        // inputs) and written again, but added to `sum` only once.
        let t = inner - LANES;
        for (j, a) in acc.iter_mut().enumerate() {
            let k = t + j;
            let l = path_value(c_in[k], below[k], at[k], above[k], p1, jump, prev_min);
            out_in[k] = l;
            let s = &mut sum_in[k];
            let fresh = k >= full;
            *s = match (SET, fresh) {
                (_, false) => *s,
                (true, true) => l,
                (false, true) => s.add(l),
            };
            *a = a.lesser(l);
        }
    } else {
        for j in full..inner {
            let l = path_value(c_in[j], below[j], at[j], above[j], p1, jump, prev_min);
            out_in[j] = l;
            accumulate::<T, SET>(&mut sum_in[j], l);
            m = m.lesser(l);
        }
    }
    acc.iter().fold(m, |a, &b| a.lesser(b))
}

/// Starts a path at the border: `L_r = C` (added to `sum`, or set: `SET`).
#[inline]
fn path_start<T: PathCost, const SET: bool>(c: &[T], out: &mut [T], sum: &mut [T]) -> T {
    let mut m = T::MAX;
    for ((&ci, o), s) in c.iter().zip(out.iter_mut()).zip(sum.iter_mut()) {
        *o = ci;
        accumulate::<T, SET>(s, ci);
        m = m.lesser(ci);
    }
    m
}

/// Aggregates the pixel-major cost volume `costs` (`[y][x][plane]`, `w·h·n` values) along the
/// first `num_paths` (4 or 8) of [`DIRECTIONS`] and returns `S` in the same layout.
/// `guide` (the reference image's `h` rows of this volume, [`Guide::rows`]) enables the adaptive
/// `P2`. Costs must be finite (a NaN cost makes the minima along its paths unspecified, never a
/// panic). `T = f32` aggregates in cost units; `u16` takes integer levels and penalties in
/// levels (see [`PathCost`]).
#[allow(clippy::too_many_arguments)]
pub fn aggregate<T: PathCost>(
    costs: &[T],
    w: usize,
    h: usize,
    n: usize,
    num_paths: usize,
    pen: &Penalties,
    guide: Option<Guide<'_>>,
    monitor: &Monitor,
) -> Result<Vec<T>> {
    let mut sum = vec![T::ZERO; w * h * n];
    aggregate_into(costs, &mut sum, w, h, n, num_paths, pen, guide, monitor)?;
    Ok(sum)
}

/// [`aggregate`] into `sum` (`w·h·n` values, whatever they hold: every value is overwritten), so
/// that a caller estimating depth strip by strip reuses one buffer instead of faulting in a
/// fresh one per strip.
///
/// The directions that share a sweep run together so each sweep streams the volumes through
/// memory once: both horizontal directions on a row while it is in cache (one rayon task per
/// row), then the directions with `dy = +1` in one top-to-bottom sweep and those with `dy = −1`
/// in one bottom-to-top sweep, each pixel's curves of all of them updated back to back. The
/// volumes are read and written 3 times instead of once per direction (8); only the order of
/// the additions into `S` differs from one direction at a time.
#[allow(clippy::too_many_arguments)]
pub fn aggregate_into<T: PathCost>(
    costs: &[T],
    sum: &mut [T],
    w: usize,
    h: usize,
    n: usize,
    num_paths: usize,
    pen: &Penalties,
    guide: Option<Guide<'_>>,
    monitor: &Monitor,
) -> Result<()> {
    assert_eq!(
        costs.len(),
        w * h * n,
        "costs must hold one value per voxel"
    );
    assert_eq!(sum.len(), costs.len(), "sum must hold one value per voxel");
    let avx2 = crate::cpu::avx2_enabled();
    let dirs = &DIRECTIONS[..num_paths.min(DIRECTIONS.len())];
    let along = |dy: i32| -> Vec<i32> { dirs.iter().filter(|d| d.1 == dy).map(|d| d.0).collect() };
    monitor.checkpoint()?;
    // Every listing of directions starts with both horizontal ones, which initialise `S`.
    horizontal(costs, sum, w, n, &along(0), pen, guide, avx2);
    monitor.progress("mvs.sgm", 1.0 / 3.0);
    for (k, dy) in [1, -1].into_iter().enumerate() {
        let dxs = along(dy);
        if !dxs.is_empty() {
            row_sweep(costs, sum, w, h, n, &dxs, dy, pen, guide, avx2, monitor)?;
        }
        monitor.progress("mvs.sgm", (k + 2) as f32 / 3.0);
    }
    Ok(())
}

/// The horizontal directions `dxs` (`±1`): rows are independent paths. Each row's `S` is set to
/// the sum of the directions' path costs (the first direction writes it, so it need not be
/// cleared first).
#[allow(clippy::too_many_arguments)]
fn horizontal<T: PathCost>(
    costs: &[T],
    sum: &mut [T],
    w: usize,
    n: usize,
    dxs: &[i32],
    pen: &Penalties,
    guide: Option<Guide<'_>>,
    avx2: bool,
) {
    let p1 = T::penalty(pen.p1);
    sum.par_chunks_mut(w * n)
        .zip(costs.par_chunks(w * n))
        .enumerate()
        .for_each_init(
            || (vec![T::MAX; n], vec![T::MAX; n]),
            |(prev, cur), (y, (srow, crow))| {
                for (k, &dx) in dxs.iter().enumerate() {
                    let mut prev_min = T::MAX;
                    for step in 0..w {
                        let x = if dx > 0 { step } else { w - 1 - step };
                        let c = &crow[x * n..(x + 1) * n];
                        let s = &mut srow[x * n..(x + 1) * n];
                        // The row's first direction sets `S`, the others add to it.
                        let m = match (step, k) {
                            (0, 0) => path_start::<T, true>(c, cur, s),
                            (0, _) => path_start::<T, false>(c, cur, s),
                            _ => {
                                let xp = if dx > 0 { x - 1 } else { x + 1 };
                                let p2 = T::penalty(pen.p2_at(guide, xp, y, x, y));
                                if k == 0 {
                                    path_step_fast::<T, true>(
                                        avx2, c, prev, prev_min, p1, p2, cur, s,
                                    )
                                } else {
                                    path_step_fast::<T, false>(
                                        avx2, c, prev, prev_min, p1, p2, cur, s,
                                    )
                                }
                            }
                        };
                        prev_min = m;
                        std::mem::swap(prev, cur);
                    }
                }
                if dxs.is_empty() {
                    srow.fill(T::ZERO);
                }
            },
        );
}

/// The directions `(dx, dy)` for `dx` in `dxs`, all with the same `dy = ±1`: rows in path
/// order, pixels of a row in parallel, each pixel's curves of every direction updated back to
/// back while its cost and `S` curves are in cache. Row buffers are `[x][direction][plane]`.
#[allow(clippy::too_many_arguments)]
fn row_sweep<T: PathCost>(
    costs: &[T],
    sum: &mut [T],
    w: usize,
    h: usize,
    n: usize,
    dxs: &[i32],
    dy: i32,
    pen: &Penalties,
    guide: Option<Guide<'_>>,
    avx2: bool,
    monitor: &Monitor,
) -> Result<()> {
    let row_len = w * n;
    let k = dxs.len();
    let p1 = T::penalty(pen.p1);
    let mut prev = vec![T::MAX; k * row_len];
    let mut cur = vec![T::MAX; k * row_len];
    let mut prev_min = vec![T::MAX; k * w];
    let mut cur_min = vec![T::MAX; k * w];
    for step in 0..h {
        monitor.checkpoint()?;
        let y = if dy > 0 { step } else { h - 1 - step };
        let yp = if dy > 0 { y.wrapping_sub(1) } else { y + 1 };
        let crow = &costs[y * row_len..(y + 1) * row_len];
        let srow = &mut sum[y * row_len..(y + 1) * row_len];
        let (prev_r, prev_min_r) = (&prev[..], &prev_min[..]);
        srow.par_chunks_mut(PIXEL_CHUNK * n)
            .zip(cur.par_chunks_mut(PIXEL_CHUNK * k * n))
            .zip(cur_min.par_chunks_mut(PIXEL_CHUNK * k))
            .enumerate()
            .for_each(|(chunk, ((s_chunk, cur_chunk), min_chunk))| {
                let x0 = chunk * PIXEL_CHUNK;
                let parts = s_chunk
                    .chunks_exact_mut(n)
                    .zip(cur_chunk.chunks_exact_mut(k * n))
                    .zip(min_chunk.chunks_exact_mut(k));
                for (j, ((s, outs), mins)) in parts.enumerate() {
                    let x = x0 + j;
                    let c = &crow[x * n..(x + 1) * n];
                    for (d, ((&dx, out), m)) in dxs
                        .iter()
                        .zip(outs.chunks_exact_mut(n))
                        .zip(mins.iter_mut())
                        .enumerate()
                    {
                        let xp = x as i64 - dx as i64;
                        *m = if step == 0 || xp < 0 || xp >= w as i64 {
                            path_start::<T, false>(c, out, s)
                        } else {
                            let xp = xp as usize;
                            let p2 = T::penalty(pen.p2_at(guide, xp, yp, x, y));
                            let at = (xp * k + d) * n;
                            path_step_fast::<T, false>(
                                avx2,
                                c,
                                &prev_r[at..at + n],
                                prev_min_r[xp * k + d],
                                p1,
                                p2,
                                out,
                                s,
                            )
                        };
                    }
                }
            });
        std::mem::swap(&mut prev, &mut cur);
        std::mem::swap(&mut prev_min, &mut cur_min);
    }
    Ok(())
}
