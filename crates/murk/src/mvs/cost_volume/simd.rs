//! AVX2 versions of the cost-volume rows' loops ([`super::kernel`]), chosen at run time.
//!
//! Why: the scalar loop's bilinear sample is a chain of dependent scalar loads and lerps per
//! voxel, and per-voxel work is all a plane sweep does.
//! - RGB ([`accumulate_rgb4`], [`accumulate_rgb4_eq37`]): images in the 4-lane layout of
//!   [`super::sample::pad_rgb4`]; each sample's corner pairs are two 256-bit loads and the lerps
//!   run on all channels at once. (Gathers of the twelve corner values of eight pixels were
//!   tried first and are slow on Zen 3; see docs/benchmarks.md.)
//! - Grey ([`accumulate`]): eight pixels at a time, corners fetched with gathers.
//! - The per-row passes (source coordinates, `1/t_s`, the dehazed reference, the mean) are the
//!   scalar functions compiled a second time for AVX2 ([`crate::cpu::compiled_for_avx2`]).
//!
//! The arithmetic is the scalar loop's, operation for operation and in the same order (separate
//! multiply and add, no FMA; channels summed from 0 up), so each lane is bit for bit the scalar
//! result (tested) and the ordinary volume stays identical to the dehazing volume at `β = 0`;
//! the observation-space loop alone folds the airlight into its input copies and agrees up to
//! rounding. The loops run only where the CPU reports AVX2; elsewhere, and for the last
//! `width mod 8` pixels of a row, the scalar loop runs.

use super::row::Haze;
use crate::cpu::{avx2_enabled, compiled_for_avx2};
use crate::mvs::plane_sweep::RowWarp;

compiled_for_avx2! {
    /// [`super::row::source_coords`] (the same coordinates bit for bit).
    pub(super) fn source_coords(warp: &RowWarp, width: usize, height: usize, us: &mut [f32], vs: &mut [f32])
        => super::row::source_coords;
}

compiled_for_avx2! {
    /// [`super::row::inverse_transmission_row`].
    pub(super) fn inverse_transmission_row(warp: &RowWarp, beta: f32, out: &mut [f32])
        => super::row::inverse_transmission_row;
}

compiled_for_avx2! {
    /// [`super::row::mean_or_penalty`].
    pub(super) fn mean_or_penalty(out: &mut [f32], sum: &[f32], observed: &[u32], penalty: f32)
        => super::row::mean_or_penalty;
}

compiled_for_avx2! {
    /// The reference row dehazed with the plane's depth (Eq. 3.5,
    /// `J_r = I_r·(1/t_r) + A(1 − 1/t_r)`) in the 4-lane layout, and whether all three channels
    /// lie in `[ref_lo, ref_hi]` (the scalar prelude's operations per pixel).
    pub(super) fn dehaze_reference_rgb4(row: &[f32], haze: Haze, jr4: &mut [[f32; 4]], ok: &mut [bool])
        => dehaze_reference_rgb4_body;
}

/// Inputs of one row × one source for [`accumulate`]: the row's source coordinates (`us` NaN =
/// unobserved) and, for the dehazing volume, `k = t_r/t_s` per pixel and the airlight `A`.
pub(super) struct RowInputs<'a> {
    pub us: &'a [f32],
    pub vs: &'a [f32],
    pub ratio: &'a [f32],
    pub airlight: f32,
}

/// Adds this source's cost to `sum[x]` and 1 to `observed[x]` for every observed pixel in
/// `0..8·⌊width/8⌋` and returns where the caller's scalar loop must continue (`0` without
/// AVX2). `reference` is the reference row deinterleaved, channel `c` at `c·width..`; `source`
/// the interleaved `width × height × C` source image.
#[allow(clippy::too_many_arguments)]
#[inline]
pub(super) fn accumulate<const C: usize, const HAZE: bool>(
    sum: &mut [f32],
    observed: &mut [u32],
    row: &RowInputs<'_>,
    reference: &[f32],
    source: &[f32],
    width: usize,
    height: usize,
    penalty: f32,
) -> usize {
    #[cfg(target_arch = "x86_64")]
    {
        if avx2_enabled() {
            // The gathers read `source` through raw offsets; these checks make every offset
            // they can form (see `avx2::accumulate`) lie inside it.
            assert!(width >= 2 && height >= 2);
            assert!(source.len() >= width * height * C && width * height * C <= i32::MAX as usize);
            assert!(sum.len() >= width && observed.len() >= width && reference.len() >= C * width);
            assert!(row.us.len() >= width && row.vs.len() >= width);
            if HAZE {
                assert!(row.ratio.len() >= width);
            }
            // SAFETY: AVX2 is present (checked above) and the slices have the lengths the
            // function requires (asserted above).
            return unsafe {
                avx2::accumulate::<C, HAZE>(
                    sum, observed, row, reference, source, width, height, penalty,
                )
            };
        }
    }
    let _ = (
        sum, observed, row, reference, source, width, height, penalty,
    );
    0
}

/// [`accumulate`] for RGB in the 4-lane layout of [`super::sample::pad_rgb4`]: instead of twelve
/// gathers per eight pixels, each pixel's two corner pairs are two 256-bit loads
/// (`[p00 | p01]`, `[p10 | p11]`) and the lerps run on all channels at once.
///
/// For the ordinary volume `source` and `reference` are padded with offset 0 and the
/// arithmetic and channel order are the scalar loop's (bit for bit). For the dehazing volume
/// both are padded with offset `A`, so the residual is `(I_r − A) − k(I_s − A)` directly, one
/// multiply and one subtraction per pixel (equal to the scalar loop's form up to rounding).
#[allow(clippy::too_many_arguments)]
#[inline]
pub(super) fn accumulate_rgb4<const HAZE: bool>(
    sum: &mut [f32],
    observed: &mut [u32],
    row: &RowInputs<'_>,
    reference: &[[f32; 4]],
    source: &[[f32; 4]],
    width: usize,
    height: usize,
    penalty: f32,
) -> usize {
    #[cfg(target_arch = "x86_64")]
    {
        if avx2_enabled() {
            assert_rgb4_bounds(source, width, height, sum, observed, row.us, row.vs);
            assert!(reference.len() >= width);
            if HAZE {
                assert!(row.ratio.len() >= width);
            }
            // SAFETY: AVX2 is present and the lengths are as required (both checked above).
            return unsafe {
                avx2::accumulate_rgb4::<HAZE>(
                    sum, observed, row, reference, source, width, height, penalty,
                )
            };
        }
    }
    let _ = (
        sum, observed, row, reference, source, width, height, penalty,
    );
    0
}

#[inline(always)]
fn dehaze_reference_rgb4_body(row: &[f32], haze: Haze, jr4: &mut [[f32; 4]], ok: &mut [bool]) {
    for ((ir, j), ok) in row.chunks_exact(3).zip(jr4.iter_mut()).zip(ok.iter_mut()) {
        let mut inside = true;
        for c in 0..3 {
            j[c] = ir[c] * haze.ref_inv_t + haze.ref_offset;
            inside &= (haze.ref_lo..=haze.ref_hi).contains(&j[c]);
        }
        j[3] = 0.0;
        *ok = inside;
    }
}

/// The bounds the 4-lane loops rely on: every read of `avx2::sample4` is at pixel index
/// ≤ (h−2)·w + (w−2) + w + 1 = w·h − 1, inside `source`, and the row buffers cover the row.
fn assert_rgb4_bounds(
    source: &[[f32; 4]],
    width: usize,
    height: usize,
    sum: &[f32],
    observed: &[u32],
    us: &[f32],
    vs: &[f32],
) {
    assert!(width >= 2 && height >= 2);
    assert!(source.len() >= width * height && width * height <= i32::MAX as usize);
    assert!(sum.len() >= width && observed.len() >= width);
    assert!(us.len() >= width && vs.len() >= width);
}

/// Inputs of one row × one source for [`accumulate_rgb4_eq37`]: source coordinates (`us` NaN =
/// unobserved), `1/t_s` per pixel, the airlight, the source range margin (observation units, 0
/// for Eq. 3.7), the reference's range flags and its dehazed row `J_r` in the 4-lane layout.
pub(super) struct DehazedRow<'a> {
    pub us: &'a [f32],
    pub vs: &'a [f32],
    pub inv_t: &'a [f32],
    pub airlight: f32,
    pub src_margin: f32,
    pub ref_ok: &'a [bool],
    pub jr4: &'a [[f32; 4]],
}

/// The dehazing volume of Eq. 3.7 (residual in dehazed space, penalty `γ` where a dehazed value
/// leaves its range) over `0..8·⌊width/8⌋` for RGB, `source` in the 4-lane layout with offset 0:
/// the source sample is dehazed with `J_s = I_s/t_s + A(1 − 1/t_s)` (Eq. 3.6) on all channels at
/// once. Same operations and order as [`super::kernel::fill_row`] in that mode, so the same
/// costs bit for bit (tested). Returns where the scalar loop continues (`0` without AVX2).
#[inline]
pub(super) fn accumulate_rgb4_eq37(
    sum: &mut [f32],
    observed: &mut [u32],
    row: &DehazedRow<'_>,
    source: &[[f32; 4]],
    width: usize,
    height: usize,
    penalty: f32,
) -> usize {
    #[cfg(target_arch = "x86_64")]
    {
        if avx2_enabled() {
            assert_rgb4_bounds(source, width, height, sum, observed, row.us, row.vs);
            assert!(row.inv_t.len() >= width);
            assert!(row.ref_ok.len() >= width && row.jr4.len() >= width);
            // SAFETY: AVX2 is present and the lengths are as required (both checked above).
            return unsafe {
                avx2::accumulate_rgb4_eq37(sum, observed, row, source, width, height, penalty)
            };
        }
    }
    let _ = (sum, observed, row, source, width, height, penalty);
    0
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use std::arch::x86_64::*;

    use super::{DehazedRow, RowInputs};

    /// # Safety
    /// AVX2 must be available; `source.len() ≥ width·height·C < 2³¹`, `width, height ≥ 2`,
    /// `sum`, `observed`, `row.us`, `row.vs` (and `row.ratio` when `HAZE`) hold at least
    /// `width` elements and `reference` at least `C·width`.
    #[allow(clippy::too_many_arguments)]
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn accumulate<const C: usize, const HAZE: bool>(
        sum: &mut [f32],
        observed: &mut [u32],
        row: &RowInputs<'_>,
        reference: &[f32],
        source: &[f32],
        width: usize,
        height: usize,
        penalty: f32,
    ) -> usize {
        let w = width as i32;
        let (wm2, hm2) = (
            _mm256_set1_epi32(w - 2),
            _mm256_set1_epi32(height as i32 - 2),
        );
        let (w_v, c_v) = (_mm256_set1_epi32(w), _mm256_set1_epi32(C as i32));
        let penalty_v = _mm256_set1_ps(penalty);
        let sign = _mm256_set1_ps(-0.0);
        let (airlight, one) = (_mm256_set1_ps(row.airlight), _mm256_set1_ps(1.0));
        let src = source.as_ptr();
        let below = width * C;
        let mut x = 0usize;
        while x + 8 <= width {
            let u = _mm256_loadu_ps(row.us.as_ptr().add(x));
            let v = _mm256_loadu_ps(row.vs.as_ptr().add(x));
            let valid = _mm256_cmp_ps::<_CMP_ORD_Q>(u, u);
            // Unobserved lanes sample pixel (0, 0) — a valid address — and are masked out below.
            let (u, v) = (_mm256_and_ps(u, valid), _mm256_and_ps(v, valid));
            // u, v ∈ [0, w−1] × [0, h−1] for observed lanes, so truncation is the floor.
            let x0 = _mm256_min_epi32(_mm256_cvttps_epi32(u), wm2);
            let y0 = _mm256_min_epi32(_mm256_cvttps_epi32(v), hm2);
            let fx = _mm256_sub_ps(u, _mm256_cvtepi32_ps(x0));
            let fy = _mm256_sub_ps(v, _mm256_cvtepi32_ps(y0));
            // (y0·w + x0)·C ≤ ((h−2)·w + w−2)·C; the largest offset added below is
            // w·C + C + (C−1), so every read is < w·h·C.
            let idx = _mm256_mullo_epi32(_mm256_add_epi32(_mm256_mullo_epi32(y0, w_v), x0), c_v);
            let (k, b) = if HAZE {
                let k = _mm256_loadu_ps(row.ratio.as_ptr().add(x));
                // A(k − 1), as the scalar loop forms it.
                (k, _mm256_mul_ps(airlight, _mm256_sub_ps(k, one)))
            } else {
                (_mm256_setzero_ps(), _mm256_setzero_ps())
            };
            let mut cost = _mm256_setzero_ps();
            for c in 0..C {
                let p00 = _mm256_i32gather_ps::<4>(src.add(c), idx);
                let p01 = _mm256_i32gather_ps::<4>(src.add(c + C), idx);
                let p10 = _mm256_i32gather_ps::<4>(src.add(c + below), idx);
                let p11 = _mm256_i32gather_ps::<4>(src.add(c + below + C), idx);
                let top = _mm256_add_ps(p00, _mm256_mul_ps(fx, _mm256_sub_ps(p01, p00)));
                let bottom = _mm256_add_ps(p10, _mm256_mul_ps(fx, _mm256_sub_ps(p11, p10)));
                let is = _mm256_add_ps(top, _mm256_mul_ps(fy, _mm256_sub_ps(bottom, top)));
                let ir = _mm256_loadu_ps(reference.as_ptr().add(c * width + x));
                let d = if HAZE {
                    _mm256_add_ps(_mm256_sub_ps(ir, _mm256_mul_ps(k, is)), b)
                } else {
                    _mm256_sub_ps(ir, is)
                };
                cost = _mm256_add_ps(cost, _mm256_andnot_ps(sign, d));
            }
            if HAZE {
                cost = _mm256_min_ps(cost, penalty_v);
            }
            let s = sum.as_mut_ptr().add(x);
            _mm256_storeu_ps(
                s,
                _mm256_add_ps(_mm256_loadu_ps(s), _mm256_and_ps(cost, valid)),
            );
            let o = observed.as_mut_ptr().add(x) as *mut __m256i;
            // `valid` is all ones (−1 as an integer) in observed lanes.
            _mm256_storeu_si256(
                o,
                _mm256_sub_epi32(_mm256_loadu_si256(o), _mm256_castps_si256(valid)),
            );
            x += 8;
        }
        x
    }

    /// # Safety
    /// AVX2 must be available; `source.len() ≥ width·height < 2³¹`, `width, height ≥ 2`, and
    /// `sum`, `observed`, `reference`, `row.us`, `row.vs` (and `row.ratio` when `HAZE`) hold at
    /// least `width` elements.
    #[allow(clippy::too_many_arguments)]
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn accumulate_rgb4<const HAZE: bool>(
        sum: &mut [f32],
        observed: &mut [u32],
        row: &RowInputs<'_>,
        reference: &[[f32; 4]],
        source: &[[f32; 4]],
        width: usize,
        height: usize,
        penalty: f32,
    ) -> usize {
        let sign = _mm_set1_ps(-0.0);
        let penalty_v = _mm_set1_ps(penalty);
        let src = source.as_ptr() as *const f32;
        let mut x = 0usize;
        let (mut idx, mut fxs, mut fys) = ([0i32; 8], [0f32; 8], [0f32; 8]);
        while x + 8 <= width {
            let mask = cells(
                row.us, row.vs, x, width, height, &mut idx, &mut fxs, &mut fys,
            );
            for j in 0..8 {
                if mask & (1 << j) == 0 {
                    continue;
                }
                let is = sample4(src, idx[j] as usize, width, fxs[j], fys[j]);
                let ir = _mm_loadu_ps(reference.as_ptr().add(x + j) as *const f32);
                let d = if HAZE {
                    let k = _mm_set1_ps(*row.ratio.get_unchecked(x + j));
                    _mm_sub_ps(ir, _mm_mul_ps(k, is))
                } else {
                    _mm_sub_ps(ir, is)
                };
                let a = _mm_andnot_ps(sign, d);
                // (|d0| + |d1|) + |d2|: the scalar loop's order (its `0 + |d0|` is exact).
                let c01 = _mm_add_ss(a, _mm_movehdup_ps(a));
                let mut cost = _mm_add_ss(c01, _mm_movehl_ps(a, a));
                if HAZE {
                    cost = _mm_min_ss(cost, penalty_v);
                }
                *sum.get_unchecked_mut(x + j) += _mm_cvtss_f32(cost);
                *observed.get_unchecked_mut(x + j) += 1;
            }
            x += 8;
        }
        x
    }

    /// Eight pixels' bilinear set-up, as `accumulate` does it: the valid-lane mask (0 = no
    /// lane observed), and per lane the cell's pixel index `y0·w + x0 ≤ (h−2)·w + w−2` (so the
    /// reads of [`sample4`] reach at most index `w·h − 1`) and `(fx, fy)`.
    #[allow(clippy::too_many_arguments)]
    #[target_feature(enable = "avx2")]
    #[inline]
    unsafe fn cells(
        us: &[f32],
        vs: &[f32],
        x: usize,
        width: usize,
        height: usize,
        idx: &mut [i32; 8],
        fxs: &mut [f32; 8],
        fys: &mut [f32; 8],
    ) -> i32 {
        let u = _mm256_loadu_ps(us.as_ptr().add(x));
        let v = _mm256_loadu_ps(vs.as_ptr().add(x));
        let valid = _mm256_cmp_ps::<_CMP_ORD_Q>(u, u);
        let mask = _mm256_movemask_ps(valid);
        if mask == 0 {
            return 0;
        }
        let (u, v) = (_mm256_and_ps(u, valid), _mm256_and_ps(v, valid));
        let x0 = _mm256_min_epi32(_mm256_cvttps_epi32(u), _mm256_set1_epi32(width as i32 - 2));
        let y0 = _mm256_min_epi32(_mm256_cvttps_epi32(v), _mm256_set1_epi32(height as i32 - 2));
        _mm256_storeu_ps(fxs.as_mut_ptr(), _mm256_sub_ps(u, _mm256_cvtepi32_ps(x0)));
        _mm256_storeu_ps(fys.as_mut_ptr(), _mm256_sub_ps(v, _mm256_cvtepi32_ps(y0)));
        let i = _mm256_add_epi32(_mm256_mullo_epi32(y0, _mm256_set1_epi32(width as i32)), x0);
        _mm256_storeu_si256(idx.as_mut_ptr() as *mut __m256i, i);
        mask
    }

    /// The bilinear sample of a 4-lane image at cell `i` with weights `(fx, fy)`: two 256-bit
    /// loads (`[p00 | p01]`, `[p10 | p11]`), the scalar sampler's operations lane by lane.
    #[target_feature(enable = "avx2")]
    #[inline]
    unsafe fn sample4(src: *const f32, i: usize, width: usize, fx: f32, fy: f32) -> __m128 {
        let p = src.add(i * 4);
        let top = _mm256_loadu_ps(p);
        let bottom = _mm256_loadu_ps(p.add(width * 4));
        let left = _mm256_permute2f128_ps::<0x20>(top, bottom);
        let right = _mm256_permute2f128_ps::<0x31>(top, bottom);
        let fx = _mm256_set1_ps(fx);
        let tb = _mm256_add_ps(left, _mm256_mul_ps(fx, _mm256_sub_ps(right, left)));
        let (t, b) = (_mm256_castps256_ps128(tb), _mm256_extractf128_ps::<1>(tb));
        _mm_add_ps(t, _mm_mul_ps(_mm_set1_ps(fy), _mm_sub_ps(b, t)))
    }

    /// # Safety
    /// AVX2 must be available; `source.len() ≥ width·height < 2³¹`, `width, height ≥ 2`, and
    /// `sum`, `observed` and every slice of `row` hold at least `width` elements.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn accumulate_rgb4_eq37(
        sum: &mut [f32],
        observed: &mut [u32],
        row: &DehazedRow<'_>,
        source: &[[f32; 4]],
        width: usize,
        height: usize,
        penalty: f32,
    ) -> usize {
        let sign = _mm_set1_ps(-0.0);
        let src = source.as_ptr() as *const f32;
        let mut x = 0usize;
        let (mut idx, mut fxs, mut fys) = ([0i32; 8], [0f32; 8], [0f32; 8]);
        while x + 8 <= width {
            let mask = cells(
                row.us, row.vs, x, width, height, &mut idx, &mut fxs, &mut fys,
            );
            for j in 0..8 {
                if mask & (1 << j) == 0 {
                    continue;
                }
                let xj = x + j;
                *observed.get_unchecked_mut(xj) += 1;
                if !*row.ref_ok.get_unchecked(xj) {
                    *sum.get_unchecked_mut(xj) += penalty;
                    continue;
                }
                let is = sample4(src, idx[j] as usize, width, fxs[j], fys[j]);
                // Eq. 3.6 with the source's own depth: J_s = I_s·(1/t_s) + A(1 − 1/t_s).
                let inv_t = *row.inv_t.get_unchecked(xj);
                let margin = row.src_margin * inv_t;
                let offset = row.airlight * (1.0 - inv_t);
                let js = _mm_add_ps(_mm_mul_ps(is, _mm_set1_ps(inv_t)), _mm_set1_ps(offset));
                let inside = _mm_and_ps(
                    _mm_cmp_ps::<_CMP_GE_OQ>(js, _mm_set1_ps(-margin)),
                    _mm_cmp_ps::<_CMP_LE_OQ>(js, _mm_set1_ps(1.0 + margin)),
                );
                // Lane 3 is padding.
                if _mm_movemask_ps(inside) & 0b111 != 0b111 {
                    *sum.get_unchecked_mut(xj) += penalty;
                    continue;
                }
                let jr = _mm_loadu_ps(row.jr4.as_ptr().add(xj) as *const f32);
                let a = _mm_andnot_ps(sign, _mm_sub_ps(jr, js));
                let c01 = _mm_add_ss(a, _mm_movehdup_ps(a));
                let cost = _mm_add_ss(c01, _mm_movehl_ps(a, a));
                *sum.get_unchecked_mut(xj) += _mm_cvtss_f32(cost).min(penalty);
            }
            x += 8;
        }
        x
    }
}
