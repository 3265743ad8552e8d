//! Semi-global aggregation (Hirschmüller 2008) of a plane-sweep cost volume over the plane
//! index.
//!
//! Along each path direction `r` the path cost is
//!
//! `L_r(p, i) = C(p, i) + min(L_r(p−r, i), L_r(p−r, i±1) + P1, min_k L_r(p−r, k) + P2) − min_k L_r(p−r, k)`
//!
//! and the aggregated volume is `S(p, i) = Σ_r L_r(p, i)` over 4, 5 ([`ONE_PASS_DIRECTIONS`],
//! aggregated row by row by [`OnePass`]) or 8 directions. Subtracting
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
//! across rayon tasks, with two `W·(N+2)` row buffers per direction. A cancellation checkpoint
//! precedes each sweep and each row of the row sweeps.
//!
//! Every path-cost curve in those buffers has a sentinel `MAX` before its first and after its
//! last plane, so the recursion's `±1` neighbours need no special first and last plane: every
//! plane takes the same vector operations. With AVX-512 (16-bit lanes and masks) the `u16` step
//! is one masked loop of 32 planes at a time, the last chunk masked too, with no scalar code per
//! pixel ([`path_step_u16_avx512`]).

use rayon::prelude::*;

use crate::cpu::Isa;
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

/// The 5 directions of one top-to-bottom pass (OpenCV's `MODE_SGBM`): both horizontal ones and
/// the three with `dy = +1`. Every path then reaches a pixel from rows already swept, so
/// [`OnePass`] aggregates a row as soon as its costs exist, keeping one row of path costs per
/// direction instead of the volumes of costs and sums that the upward paths need.
pub const ONE_PASS_DIRECTIONS: [(i32, i32); 5] = [(1, 0), (-1, 0), (0, 1), (1, 1), (-1, 1)];

/// The `dx` of [`ONE_PASS_DIRECTIONS`]' three downward directions, in their order (the order
/// [`aggregate_into`]'s top-to-bottom sweep adds them to `S`).
const ONE_PASS_DOWNWARD_DX: [i32; 3] = [0, 1, -1];

/// The directions of a `num_paths` aggregation: the first 4 of [`DIRECTIONS`] (horizontal and
/// vertical), [`ONE_PASS_DIRECTIONS`] for 5, all 8 for 8.
pub fn directions(num_paths: usize) -> &'static [(i32, i32)] {
    match num_paths {
        5 => &ONE_PASS_DIRECTIONS,
        n => &DIRECTIONS[..n.min(DIRECTIONS.len())],
    }
}

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
    /// The values as `u16` levels when the type holds levels, `None` for `f32`.
    #[inline(always)]
    fn as_levels(values: &[Self]) -> Option<&[u16]> {
        let _ = values;
        None
    }
    /// [`path_step`] through this type's AVX-512 copy, `None` when it has none (`f32`).
    ///
    /// # Safety
    /// The CPU has AVX-512 F, BW and VL ([`crate::cpu::avx512bw_enabled`]).
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    unsafe fn path_step_avx512<const SET: bool>(
        _c: &[Self],
        _prev: &[Self],
        _prev_min: Self,
        _p1: Self,
        _p2: Self,
        _out: &mut [Self],
        _sum: &mut [Self],
    ) -> Option<Self> {
        None
    }
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
    fn as_levels(values: &[Self]) -> Option<&[u16]> {
        Some(values)
    }
    #[inline(always)]
    unsafe fn path_step_avx512<const SET: bool>(
        c: &[Self],
        prev: &[Self],
        prev_min: Self,
        p1: Self,
        p2: Self,
        out: &mut [Self],
        sum: &mut [Self],
    ) -> Option<Self> {
        #[cfg(target_arch = "x86_64")]
        {
            // SAFETY: the caller's contract (the CPU has AVX-512 F, BW and VL).
            Some(unsafe { path_step_u16_avx512::<SET>(c, prev, prev_min, p1, p2, out, sum) })
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            let _ = (c, prev, prev_min, p1, p2, out, sum);
            None
        }
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

/// [`path_step`] through the AVX-512 copy of `T` when `isa` allows and `T` has one, else a copy
/// compiled with AVX2 when the CPU has it: the same operations on wider registers, so the same
/// results bit for bit (no fused multiply-adds are introduced: the recursion has only additions
/// and minima).
#[inline]
#[allow(clippy::too_many_arguments)]
fn path_step_fast<T: PathCost, const SET: bool>(
    isa: Isa,
    c: &[T],
    prev: &[T],
    prev_min: T,
    p1: T,
    p2: T,
    out: &mut [T],
    sum: &mut [T],
) -> T {
    if isa.avx512 {
        // SAFETY: `isa.avx512` is set only where the CPU has AVX-512 F, BW and VL.
        if let Some(m) = unsafe { T::path_step_avx512::<SET>(c, prev, prev_min, p1, p2, out, sum) }
        {
            return m;
        }
    }
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
        if isa.avx2 {
            // SAFETY: the caller detected AVX2 on this CPU ([`crate::cpu::avx2_enabled`]).
            return unsafe { with_avx2::<T, SET>(c, prev, prev_min, p1, p2, out, sum) };
        }
    }
    path_step::<T, SET>(c, prev, prev_min, p1, p2, out, sum)
}

/// [`path_step`] for `u16` levels with AVX-512: 32 planes per instruction, the last chunk
/// masked (loads, stores and the running minimum), so a curve of any length runs without a
/// scalar remainder. `prev` and `out` are padded curves (`n + 2`, sentinels `MAX` at both ends,
/// [`path_step`]); the masked-off lanes are neither stored nor in the minimum.
///
/// # Safety
/// The CPU has AVX-512 F, BW and VL.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512vl,avx2,sse4.1")]
#[allow(clippy::too_many_arguments)]
unsafe fn path_step_u16_avx512<const SET: bool>(
    c: &[u16],
    prev: &[u16],
    prev_min: u16,
    p1: u16,
    p2: u16,
    out: &mut [u16],
    sum: &mut [u16],
) -> u16 {
    use std::arch::x86_64::*;
    let n = c.len();
    // Checked, not assumed: the masked accesses below stay inside these lengths.
    assert!(
        prev.len() == n + 2 && out.len() == n + 2 && sum.len() == n,
        "padded curves of n + 2 values and n sums"
    );
    let jump = _mm512_set1_epi16(prev_min.saturating_add(p2) as i16);
    let vp1 = _mm512_set1_epi16(p1 as i16);
    let vmin = _mm512_set1_epi16(prev_min as i16);
    let mut acc = _mm512_set1_epi16(-1);
    let (cp, pp) = (c.as_ptr().cast::<i16>(), prev.as_ptr().cast::<i16>());
    let (op, sp) = (
        out.as_mut_ptr().cast::<i16>().wrapping_add(1),
        sum.as_mut_ptr().cast::<i16>(),
    );
    let mut i = 0;
    while i < n {
        let left = n - i;
        let k: __mmask32 = if left >= 32 { !0 } else { (1u32 << left) - 1 };
        // SAFETY: lane `j` of a chunk is touched only where `i + j < n` (mask `k`): `c[i + j]`,
        // `sum[i + j]`, `prev[i + j ..= i + j + 2]` (length n + 2) and `out[1 + i + j]`.
        unsafe {
            let cc = _mm512_maskz_loadu_epi16(k, cp.add(i));
            let below = _mm512_maskz_loadu_epi16(k, pp.add(i));
            let at = _mm512_maskz_loadu_epi16(k, pp.add(i + 1));
            let above = _mm512_maskz_loadu_epi16(k, pp.add(i + 2));
            // The order of `path_value`: min, saturating + P1, min, min, wrapping − prev_min,
            // saturating + C.
            let m = _mm512_min_epu16(at, _mm512_adds_epu16(_mm512_min_epu16(below, above), vp1));
            let l = _mm512_adds_epu16(cc, _mm512_sub_epi16(_mm512_min_epu16(m, jump), vmin));
            _mm512_mask_storeu_epi16(op.add(i), k, l);
            let s = if SET {
                l
            } else {
                _mm512_adds_epu16(_mm512_maskz_loadu_epi16(k, sp.add(i)), l)
            };
            _mm512_mask_storeu_epi16(sp.add(i), k, s);
            acc = _mm512_mask_min_epu16(acc, k, acc, l);
        }
        i += 32;
    }
    let half = _mm256_min_epu16(
        _mm512_castsi512_si256(acc),
        _mm512_extracti64x4_epi64::<1>(acc),
    );
    let quarter = _mm_min_epu16(
        _mm256_castsi256_si128(half),
        _mm256_extracti128_si256::<1>(half),
    );
    (_mm_cvtsi128_si32(_mm_minpos_epu16(quarter)) & 0xFFFF) as u16
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
///
/// `prev` and `out` are padded curves of `n + 2` values (`n = c.len()`): the curve at `1..=n`
/// and `MAX` at `0` and `n + 1` (never written here), which no minimum takes, so every plane is
/// an interior one.
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
    let (below, at, above) = (&prev[..n], &prev[1..n + 1], &prev[2..n + 2]);
    let (out, sum) = (&mut out[1..n + 1], &mut sum[..n]);
    // In fixed-size chunks: the chunk bodies have no bounds checks and vectorise, with one
    // running minimum per lane.
    let full = n / LANES * LANES;
    let mut acc = [T::MAX; LANES];
    for (((((cc, lo), mid), hi), oo), ss) in c[..full]
        .chunks_exact(LANES)
        .zip(below[..full].chunks_exact(LANES))
        .zip(at[..full].chunks_exact(LANES))
        .zip(above[..full].chunks_exact(LANES))
        .zip(out[..full].chunks_exact_mut(LANES))
        .zip(sum[..full].chunks_exact_mut(LANES))
    {
        for j in 0..LANES {
            let l = path_value(cc[j], lo[j], mid[j], hi[j], p1, jump, prev_min);
            oo[j] = l;
            accumulate::<T, SET>(&mut ss[j], l);
            acc[j] = acc[j].lesser(l);
        }
    }
    let mut m = T::MAX;
    for j in full..n {
        let l = path_value(c[j], below[j], at[j], above[j], p1, jump, prev_min);
        out[j] = l;
        accumulate::<T, SET>(&mut sum[j], l);
        m = m.lesser(l);
    }
    acc.iter().fold(m, |a, &b| a.lesser(b))
}

/// Starts a path at the border: `L_r = C` (added to `sum`, or set: `SET`) into the padded
/// curve `out` ([`path_step`]).
#[inline]
fn path_start<T: PathCost, const SET: bool>(c: &[T], out: &mut [T], sum: &mut [T]) -> T {
    let mut m = T::MAX;
    for ((&ci, o), s) in c.iter().zip(out[1..].iter_mut()).zip(sum.iter_mut()) {
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
    let isa = Isa::detect();
    let dirs = directions(num_paths);
    let along = |dy: i32| -> Vec<i32> { dirs.iter().filter(|d| d.1 == dy).map(|d| d.0).collect() };
    monitor.checkpoint()?;
    // Every listing of directions starts with both horizontal ones, which initialise `S`.
    horizontal(costs, sum, w, n, &along(0), pen, guide, isa);
    monitor.progress("mvs.sgm", 1.0 / 3.0);
    for (k, dy) in [1, -1].into_iter().enumerate() {
        let dxs = along(dy);
        if !dxs.is_empty() {
            row_sweep(costs, sum, w, h, n, &dxs, dy, pen, guide, isa, monitor)?;
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
    isa: Isa,
) {
    sum.par_chunks_mut(w * n)
        .zip(costs.par_chunks(w * n))
        .enumerate()
        .for_each_init(
            || HorizontalCurves::new(n),
            |curves, (y, (srow, crow))| {
                horizontal_row(crow, srow, y, w, n, dxs, pen, guide, isa, curves)
            },
        );
}

/// The two padded curves ([`path_step`]) a horizontal path carries from pixel to pixel.
struct HorizontalCurves<T> {
    prev: Vec<T>,
    cur: Vec<T>,
}

impl<T: PathCost> HorizontalCurves<T> {
    fn new(n: usize) -> Self {
        Self {
            prev: vec![T::MAX; n + 2],
            cur: vec![T::MAX; n + 2],
        }
    }
}

/// [`horizontal`] on row `y` (`crow` its costs, `srow` its `S`, both `[x][plane]`).
#[allow(clippy::too_many_arguments)]
#[inline]
fn horizontal_row<T: PathCost>(
    crow: &[T],
    srow: &mut [T],
    y: usize,
    w: usize,
    n: usize,
    dxs: &[i32],
    pen: &Penalties,
    guide: Option<Guide<'_>>,
    isa: Isa,
    curves: &mut HorizontalCurves<T>,
) {
    let p1 = T::penalty(pen.p1);
    let HorizontalCurves { prev, cur } = curves;
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
                        path_step_fast::<T, true>(isa, c, prev, prev_min, p1, p2, cur, s)
                    } else {
                        path_step_fast::<T, false>(isa, c, prev, prev_min, p1, p2, cur, s)
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
}

/// The directions `(dx, dy)` for `dx` in `dxs`, all with the same `dy = ±1`: rows in path
/// order, pixels of a row in parallel, each pixel's curves of every direction updated back to
/// back while its cost and `S` curves are in cache. Row buffers are `[x][direction][plane]`,
/// each curve padded ([`path_step`]: `n + 2` values).
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
    isa: Isa,
    monitor: &Monitor,
) -> Result<()> {
    let row_len = w * n;
    let mut curves = RowCurves::new(w, n, dxs.len());
    for step in 0..h {
        monitor.checkpoint()?;
        let y = if dy > 0 { step } else { h - 1 - step };
        let yp = if dy > 0 { y.wrapping_sub(1) } else { y + 1 };
        sweep_row(
            &costs[y * row_len..(y + 1) * row_len],
            &mut sum[y * row_len..(y + 1) * row_len],
            y,
            (step > 0).then_some(yp),
            w,
            n,
            dxs,
            pen,
            guide,
            isa,
            &mut curves,
        );
    }
    Ok(())
}

/// The padded path-cost curves (`[x][direction][plane]`, [`path_step`]: `n + 2` values each) and
/// their minima of the previous and the current row of a row sweep.
struct RowCurves<T> {
    prev: Vec<T>,
    cur: Vec<T>,
    prev_min: Vec<T>,
    cur_min: Vec<T>,
}

impl<T: PathCost> RowCurves<T> {
    fn new(w: usize, n: usize, directions: usize) -> Self {
        let len = directions * w * (n + 2);
        Self {
            prev: vec![T::MAX; len],
            cur: vec![T::MAX; len],
            prev_min: vec![T::MAX; directions * w],
            cur_min: vec![T::MAX; directions * w],
        }
    }
}

/// One row `y` of [`row_sweep`] (`crow` its costs, `srow` its `S` added to): each pixel's curves
/// of every direction `(dx, dy)`, `dx` in `dxs`, continued from the previous row `yp` of the
/// sweep in `curves` (`None`: the paths start here), pixels split across rayon tasks. The row's
/// curves become `curves`' previous ones.
#[allow(clippy::too_many_arguments)]
fn sweep_row<T: PathCost>(
    crow: &[T],
    srow: &mut [T],
    y: usize,
    yp: Option<usize>,
    w: usize,
    n: usize,
    dxs: &[i32],
    pen: &Penalties,
    guide: Option<Guide<'_>>,
    isa: Isa,
    curves: &mut RowCurves<T>,
) {
    let k = dxs.len();
    let np = n + 2;
    let p1 = T::penalty(pen.p1);
    let RowCurves {
        prev,
        cur,
        prev_min,
        cur_min,
    } = curves;
    let (prev_r, prev_min_r) = (&prev[..], &prev_min[..]);
    srow.par_chunks_mut(PIXEL_CHUNK * n)
        .zip(cur.par_chunks_mut(PIXEL_CHUNK * k * np))
        .zip(cur_min.par_chunks_mut(PIXEL_CHUNK * k))
        .enumerate()
        .for_each(|(chunk, ((s_chunk, cur_chunk), min_chunk))| {
            let x0 = chunk * PIXEL_CHUNK;
            let parts = s_chunk
                .chunks_exact_mut(n)
                .zip(cur_chunk.chunks_exact_mut(k * np))
                .zip(min_chunk.chunks_exact_mut(k));
            for (j, ((s, outs), mins)) in parts.enumerate() {
                let x = x0 + j;
                let c = &crow[x * n..(x + 1) * n];
                for (d, ((&dx, out), m)) in dxs
                    .iter()
                    .zip(outs.chunks_exact_mut(np))
                    .zip(mins.iter_mut())
                    .enumerate()
                {
                    let xp = x as i64 - dx as i64;
                    *m = match yp {
                        Some(yp) if xp >= 0 && xp < w as i64 => {
                            let xp = xp as usize;
                            let p2 = T::penalty(pen.p2_at(guide, xp, yp, x, y));
                            let at = (xp * k + d) * np;
                            path_step_fast::<T, false>(
                                isa,
                                c,
                                &prev_r[at..at + np],
                                prev_min_r[xp * k + d],
                                p1,
                                p2,
                                out,
                                s,
                            )
                        }
                        _ => path_start::<T, false>(c, out, s),
                    };
                }
            }
        });
    std::mem::swap(prev, cur);
    std::mem::swap(prev_min, cur_min);
}

/// `sum[i] = sum[i] ⊕ add[i]` ([`PathCost::add`]), compiled for AVX2 where `isa` has it: 16
/// `u16` lanes per instruction instead of SSE2's 8 (the same saturating additions).
#[inline]
fn add_row<T: PathCost>(isa: Isa, sum: &mut [T], add: &[T]) {
    #[inline(always)]
    fn body<T: PathCost>(sum: &mut [T], add: &[T]) {
        for (s, &a) in sum.iter_mut().zip(add) {
            *s = s.add(a);
        }
    }
    #[cfg(target_arch = "x86_64")]
    {
        #[target_feature(enable = "avx2")]
        unsafe fn with_avx2<T: PathCost>(sum: &mut [T], add: &[T]) {
            body(sum, add)
        }
        if isa.avx2 {
            // SAFETY: `isa.avx2` is set only where the CPU has AVX2.
            return unsafe { with_avx2(sum, add) };
        }
    }
    let _ = isa;
    body(sum, add)
}

/// Aggregation over [`ONE_PASS_DIRECTIONS`] one row at a time, top to bottom: each row's `S` is
/// known as soon as its costs are, so a caller streams costs in and takes `S` out row by row and
/// no volume is kept. Rows given to [`OnePass::row`] are `y₀, y₀ + 1, …`; the vertical and
/// diagonal paths start at `y₀`. The same sums as [`aggregate_into`] with 5 paths on those rows,
/// bit for bit (tested).
pub(crate) struct OnePass<T> {
    w: usize,
    /// The rows' planes: `n` from `first` on ([`Self::set_planes`]).
    first: usize,
    n: usize,
    isa: Isa,
    /// The left-to-right and the right-to-left path's curves: the two run side by side.
    rightward: HorizontalCurves<T>,
    leftward: HorizontalCurves<T>,
    /// The right-to-left path's costs of the row, added to `S` when both are done.
    leftward_row: Vec<T>,
    vertical: RowCurves<T>,
    /// The last row aggregated.
    last: Option<usize>,
}

impl<T: PathCost> OnePass<T> {
    /// A pass over `w`-pixel rows of `n` planes, with the instruction sets `isa` (detected on the
    /// caller's thread: [`Isa::detect`]).
    pub(crate) fn new(w: usize, n: usize, isa: Isa) -> Self {
        Self {
            w,
            first: 0,
            n,
            isa,
            rightward: HorizontalCurves::new(n),
            leftward: HorizontalCurves::new(n),
            leftward_row: vec![T::ZERO; w * n],
            vertical: RowCurves::new(w, n, 3),
            last: None,
        }
    }

    /// The next rows search the planes `planes` (of a set whose first `n` planes a new pass
    /// searches), so their costs and sums hold `planes.len()` values per pixel. The downward
    /// paths keep the previous row's costs of the planes both runs hold, and their steps stay
    /// among those planes; a plane the previous run lacked starts from the path's jump,
    /// `min_k L(p−r, k) + P2` (the minimum over all the previous run's planes), which is what
    /// the recursion gives where the previous row's cost is unbounded (see
    /// [`super::windows`]). The same run as before changes nothing.
    pub(crate) fn set_planes(&mut self, planes: std::ops::Range<usize>) {
        let (first, n) = (planes.start, planes.len());
        if (first, n) == (self.first, self.n) {
            return;
        }
        let (w, k) = (self.w, ONE_PASS_DOWNWARD_DX.len());
        if n != self.n {
            self.rightward = HorizontalCurves::new(n);
            self.leftward = HorizontalCurves::new(n);
            self.leftward_row = vec![T::ZERO; w * n];
        }
        let mut vertical = RowCurves::new(w, n, k);
        if self.last.is_some() {
            // The planes both runs hold, as offsets into each run's curves (after the
            // sentinel).
            let (lo, hi) = (first.max(self.first), (first + n).min(self.first + self.n));
            if lo < hi {
                let (from, to, len) = (1 + lo - self.first, 1 + lo - first, hi - lo);
                let old = &self.vertical.prev;
                for (o, c) in old
                    .chunks_exact(self.n + 2)
                    .zip(vertical.prev.chunks_exact_mut(n + 2))
                {
                    c[to..to + len].copy_from_slice(&o[from..from + len]);
                }
            }
            // Each curve's minimum is over all the planes its row had: the jump's base.
            vertical.prev_min = std::mem::take(&mut self.vertical.prev_min);
        }
        self.vertical = vertical;
        (self.first, self.n) = (first, n);
    }

    /// `S` of row `y` into `srow` (every value overwritten) from its costs `crow` (both
    /// `[x][plane]`, `w · n` values); `y` follows the previous row given, `guide` (rows from 0)
    /// enables the adaptive `P2`.
    pub(crate) fn row(
        &mut self,
        crow: &[T],
        srow: &mut [T],
        y: usize,
        pen: &Penalties,
        guide: Option<Guide<'_>>,
    ) {
        let (w, n) = (self.w, self.n);
        assert!(
            crow.len() == w * n && srow.len() == w * n,
            "one row of costs and of sums"
        );
        assert!(
            self.last.is_none_or(|l| l + 1 == y),
            "rows in order, one after another"
        );
        let isa = self.isa;
        // Both horizontal paths at once, each in its own row: `L→ + L←` is the same sum as the
        // second added to the first in place.
        let (right, left, left_row) = (
            &mut self.rightward,
            &mut self.leftward,
            &mut self.leftward_row,
        );
        rayon::join(
            || horizontal_row(crow, srow, y, w, n, &[1], pen, guide, isa, right),
            || horizontal_row(crow, left_row, y, w, n, &[-1], pen, guide, isa, left),
        );
        add_row(isa, srow, left_row);
        sweep_row(
            crow,
            srow,
            y,
            self.last,
            w,
            n,
            &ONE_PASS_DOWNWARD_DX,
            pen,
            guide,
            isa,
            &mut self.vertical,
        );
        self.last = Some(y);
    }
}
