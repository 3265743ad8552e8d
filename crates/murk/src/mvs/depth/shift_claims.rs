//! A rectified row's claims of the source's pixels, reduced per source column
//! ([`super::consistency`]): every voxel of a reference row lands on one source row at a
//! whole-pixel offset per plane, so the row's best `(level, plane)` per source column is a
//! minimum of packed `u32` keys, without atomics. Three equivalent loops: plain, one AVX-512
//! gather per 16 voxels for any offsets, and a sliding register for the offsets of planes at
//! most one pixel of disparity apart (a rectified pair's), which needs no gather.

/// The columns `x` of a `w`-pixel reference row whose voxel at `offset` lands inside a
/// `w_src`-pixel source row.
#[inline]
pub(super) fn inside_columns(offset: i32, w: usize, w_src: usize) -> std::ops::Range<usize> {
    let lo = (-(offset as i64)).max(0) as usize;
    let hi = (w_src as i64 - offset as i64).clamp(0, w as i64) as usize;
    lo.min(hi)..hi
}

/// A shift row's claim of plane `i` at `level` as one `u32`: smaller is better, and of equal
/// levels the higher plane (the nearer surface) wins, as in the 64-bit keys of
/// [`SourceClaims`](super::consistency::SourceClaims).
#[inline(always)]
pub(super) fn shift_key(level: u16, i: usize) -> u32 {
    (u32::from(level) << 16) | (0xFFFF - i as u32)
}

/// The level and the plane of a [`shift_key`].
#[inline]
pub(super) fn shift_key_parts(key: u32) -> (u16, usize) {
    ((key >> 16) as u16, (0xFFFF - (key & 0xFFFF)) as usize)
}

/// The per-source-column reduction of a shift row's `u16` claims
/// ([`SourceClaims::add_row`](super::consistency::SourceClaims::add_row)):
/// `local[x + offsets[i]] = min(local[x + offsets[i]], shift_key(levels[x·n + i], i))`
/// over the row's pixels `x` (`levels` is `[x][plane]`, `n` planes per pixel) whose target lies
/// in `local` (the source row). With `avx512` (the CPU has AVX-512 F, BW and VL), offsets that
/// step as a rectified pair's do ([`sliding_offsets`]) take [`reduce_shift_levels_sliding`],
/// any others [`reduce_shift_levels_gathered`]; without, the plain loop, plane by plane over
/// contiguous columns. All three give the same keys and minima.
pub(super) fn reduce_shift_levels(
    avx512: bool,
    levels: &[u16],
    n: usize,
    offsets: &[i32],
    local: &mut [u32],
) {
    let w = levels.len() / n.max(1);
    #[cfg(target_arch = "x86_64")]
    if avx512 && n > 0 && offsets.len() <= n {
        if sliding_offsets(offsets) {
            // SAFETY: the CPU has AVX-512 F, BW and VL (the caller's `avx512`); the offsets
            // step as the function requires (checked above).
            unsafe { reduce_shift_levels_sliding(levels, n, w, offsets, local) };
            return;
        }
        if std::mem::size_of_val(levels) < i32::MAX as usize {
            // SAFETY: the CPU has AVX-512 F, BW and VL (the caller's `avx512`), and `levels`
            // is addressable by `i32` byte offsets (checked above).
            unsafe { reduce_shift_levels_gathered(levels, n, w, offsets, local) };
            return;
        }
    }
    let _ = avx512;
    for (i, &o) in offsets.iter().enumerate() {
        let cols = inside_columns(o, w, local.len());
        if cols.is_empty() {
            // Every voxel of the plane lands outside (and `cols.start + o` may be negative).
            continue;
        }
        let dst = &mut local[(cols.start as i64 + o as i64) as usize..][..cols.len()];
        for (d, x) in dst.iter_mut().zip(cols) {
            *d = (*d).min(shift_key(levels[x * n + i], i));
        }
    }
}

/// Whether a row's whole-pixel offsets suit [`reduce_shift_levels_sliding`]: each plane's
/// offset is the previous plane's or one less, and no three planes share one. A rectified
/// pair's planes, uniform in disparity and at most one pixel apart (one per pixel of the range
/// by default: [`crate::mvs::rectified::RectifiedRig::planes`]), step so whenever they are
/// more than half a pixel apart, in any run of the plane set.
pub(super) fn sliding_offsets(offsets: &[i32]) -> bool {
    offsets
        .windows(2)
        .all(|p| matches!(i64::from(p[1]) - i64::from(p[0]), 0 | -1))
        && offsets.windows(3).all(|p| p[0] != p[2])
}

/// [`reduce_shift_levels`] of offsets that step as [`sliding_offsets`] requires, without a
/// gather. Plane `i`'s voxel at pixel `x` lands on column `x + offsets[i]`, so 16 planes that
/// start at `b` land, from pixel `x`, on the 16 columns left of `x + offsets[b]` at most
/// (two planes may share one). Each block of 16 planes keeps a register `r` whose lane `p`
/// holds the best key so far of column `x + offsets[b] − p`: at pixel `x` its 16 levels are one
/// contiguous load, their keys move to their columns' lanes (one permutation for the planes that
/// come first in their column, one for the second), and `r` takes the minimum. Lane 15's
/// column then has had every plane of the block (later pixels land further right), so `r`
/// shifts up by a lane for the next pixel, and the lane that leaves goes into a second register,
/// which after 16 pixels holds 16 finished columns in a row and takes one masked minimum into
/// `local`. The gathered path costs a 16-lane gather of `u32` words (a stride of `n`) per 16
/// voxels; this one a few register operations.
///
/// # Safety
/// The CPU has AVX-512 F, BW and VL; `levels` holds `w·n` values, `offsets.len() ≤ n`, and
/// [`sliding_offsets`]`(offsets)` holds.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512vl,avx2")]
unsafe fn reduce_shift_levels_sliding(
    levels: &[u16],
    n: usize,
    w: usize,
    offsets: &[i32],
    local: &mut [u32],
) {
    use std::arch::x86_64::*;
    assert!(
        levels.len() == w * n && offsets.len() <= n,
        "w·n levels, n offsets"
    );
    // The dispatch has just checked the steps. Memory safety does not rest on them (a lane
    // index out of its block fails the bounds check of `first`), only the keys' columns do.
    debug_assert!(sliding_offsets(offsets), "offsets that step by 0 or −1");
    let none = _mm512_set1_epi32(-1);
    let lane = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    for b in (0..offsets.len()).step_by(16) {
        let m = (offsets.len() - b).min(16);
        let base = i64::from(offsets[b]);
        // Lane `p` of the block's columns takes the keys of planes `first[p]` and `second[p]`
        // (the same plane where one lands there); `used` marks the lanes any plane lands on.
        let (mut first, mut second) = ([0i32; 16], [0i32; 16]);
        let mut used: __mmask16 = 0;
        let mut in_order = true;
        for k in 0..m {
            // 0 ≤ p ≤ k < 16: each step lowers the offset by at most one.
            let p = (base - i64::from(offsets[b + k])) as usize;
            if used & (1 << p) == 0 {
                first[p] = k as i32;
                used |= 1 << p;
            }
            second[p] = k as i32;
            in_order &= p == k;
        }
        // SAFETY: 16 `i32`s each.
        let (first, second) = unsafe {
            (
                _mm512_loadu_si512(first.as_ptr().cast()),
                _mm512_loadu_si512(second.as_ptr().cast()),
            )
        };
        // `shift_key`'s low half of plane `b + k` in lane `k`.
        let tags = _mm512_sub_epi32(_mm512_set1_epi32(shift_key(0, b) as i32), lane);
        let loaded: __mmask16 = if m == 16 { !0 } else { (1 << m) - 1 };
        let (mut r, mut done) = (none, none);
        let mut pending = 0usize;
        for x in 0..w {
            // SAFETY: lanes `k < m` read `levels[x·n + b + k]`, `b + k < offsets.len() ≤ n`;
            // the others are masked off.
            let level =
                unsafe { _mm256_maskz_loadu_epi16(loaded, levels.as_ptr().add(x * n + b).cast()) };
            let keys = _mm512_or_si512(_mm512_slli_epi32::<16>(_mm512_cvtepu16_epi32(level)), tags);
            let landed = if in_order {
                _mm512_mask_mov_epi32(none, used, keys)
            } else {
                _mm512_min_epu32(
                    _mm512_mask_permutexvar_epi32(none, used, first, keys),
                    _mm512_mask_permutexvar_epi32(none, used, second, keys),
                )
            };
            r = _mm512_min_epu32(r, landed);
            // Lane 15, column `x + base − 15`, is finished: it leaves `r` for `done`, whose lane
            // `j` is then column `x + base − 15 − j`.
            done = _mm512_alignr_epi32::<15>(done, r);
            r = _mm512_alignr_epi32::<15>(r, none);
            pending += 1;
            if pending == 16 {
                // SAFETY: as this function's.
                unsafe { min_into_descending(local, done, x as i64 + base - 15, 16) };
                (done, pending) = (none, 0);
            }
        }
        // After the last pixel, `done`'s pending lanes and every lane of `r`: lane `p` is
        // column `w + base − p` (lane 0 took no key).
        if w > 0 {
            // SAFETY: as this function's.
            unsafe {
                min_into_descending(local, done, w as i64 - 1 + base - 15, pending);
                min_into_descending(local, r, w as i64 + base, 16);
            }
        }
    }
}

/// `local[top − j] = min(local[top − j], keys[j])` for the lanes `j < count` whose column lies
/// in `local`, by one masked load and store.
///
/// # Safety
/// The CPU has AVX-512 F and VL.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl")]
#[inline]
unsafe fn min_into_descending(
    local: &mut [u32],
    keys: std::arch::x86_64::__m512i,
    top: i64,
    count: usize,
) {
    use std::arch::x86_64::*;
    // Reversed, lane `j` is column `top − 15 + j`.
    let reverse = _mm512_setr_epi32(15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0);
    let keys = _mm512_permutexvar_epi32(reverse, keys);
    let start = top - 15;
    // The lanes that hold one of the `count` keys and whose column is inside `local`.
    let lo = (16 - count.min(16) as i64).max(-start);
    let hi = (local.len() as i64 - start).min(16);
    if lo >= hi {
        return;
    }
    let mask = (((1u32 << (hi - lo)) - 1) << lo) as __mmask16;
    let dst = local
        .as_mut_ptr()
        .wrapping_offset(start as isize)
        .cast::<i32>();
    // SAFETY: the masked lanes `lo..hi` are columns `start + lo .. start + hi`, inside `local`;
    // a masked-off lane is neither read nor written.
    unsafe {
        let current = _mm512_maskz_loadu_epi32(mask, dst);
        _mm512_mask_storeu_epi32(dst, mask, _mm512_min_epu32(current, keys));
    }
}

/// [`reduce_shift_levels`] of any offsets with AVX-512: per plane, 16 pixels' levels by one
/// masked gather of the 32-bit words that hold them (the word starting at the level, or for the
/// last plane the word ending at it, so no gather reads outside `levels`), then 16 keys and one
/// masked minimum into `local`.
///
/// # Safety
/// The CPU has AVX-512 F, BW and VL; `levels` (`w·n` values) is under `i32::MAX` bytes.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512vl,avx2")]
unsafe fn reduce_shift_levels_gathered(
    levels: &[u16],
    n: usize,
    w: usize,
    offsets: &[i32],
    local: &mut [u32],
) {
    use std::arch::x86_64::*;
    assert!(
        levels.len() == w * n && offsets.len() <= n,
        "w·n levels, n offsets"
    );
    let base = levels.as_ptr().cast::<i32>();
    let stride = _mm512_set1_epi32((2 * n) as i32);
    let lane = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    let low = _mm512_set1_epi32(0xFFFF);
    for (i, &o) in offsets.iter().enumerate() {
        let cols = inside_columns(o, w, local.len());
        // `shift_key`'s low half, the same for every lane of the plane.
        let tag = _mm512_set1_epi32(shift_key(0, i) as i32);
        // The level of plane `i` is the low half of the word at it, or for the last of `n ≥ 2`
        // planes (whose word would reach into the next pixel, past the last one) the high half
        // of the word before it. With one plane the last pixel is left to the scalar below.
        let (first_byte, high) = if n == 1 || i + 1 < n {
            (2 * i as i32, false)
        } else {
            (2 * i as i32 - 2, true)
        };
        let mut x = cols.start;
        while x < cols.end {
            let count = (cols.end - x).min(16);
            let mut k: __mmask16 = if count == 16 { !0 } else { (1u16 << count) - 1 };
            if n == 1 && x + count == w {
                // One plane: the last pixel's word would end past `levels`; the scalar below.
                k &= !(1u16 << (count - 1));
            }
            let pixels = _mm512_add_epi32(_mm512_set1_epi32(x as i32), lane);
            let offs = _mm512_add_epi32(
                _mm512_mullo_epi32(pixels, stride),
                _mm512_set1_epi32(first_byte),
            );
            // SAFETY: lane `j < count` reads the 4 bytes at `2(x + j)n + first_byte`, inside
            // `levels` for every pixel but (with one plane) the last, which the mask excludes;
            // the masked `local` accesses stay in `x + o .. x + o + count ⊂ 0..local.len()`
            // ([`inside_columns`]).
            unsafe {
                let words = _mm512_mask_i32gather_epi32::<1>(_mm512_setzero_si512(), k, offs, base);
                let level = if high {
                    _mm512_srli_epi32::<16>(words)
                } else {
                    _mm512_and_si512(words, low)
                };
                let keys = _mm512_or_si512(_mm512_slli_epi32::<16>(level), tag);
                let dst = local.as_mut_ptr().add((x as i64 + o as i64) as usize);
                let cur = _mm512_maskz_loadu_epi32(k, dst.cast::<i32>());
                _mm512_mask_storeu_epi32(dst.cast::<i32>(), k, _mm512_min_epu32(cur, keys));
            }
            if k.count_ones() as usize != count {
                let last = x + count - 1;
                let q = (last as i64 + o as i64) as usize;
                local[q] = local[q].min(shift_key(levels[last * n + i], i));
            }
            x += count;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A seeded linear congruential generator.
    struct Lcg(u64);

    impl Lcg {
        /// The next value in `0..m`.
        fn next(&mut self, m: u64) -> u64 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (self.0 >> 33) % m
        }

        /// Reduces `levels` by the plain loop and by the AVX-512 dispatch into the same random
        /// `w_src`-column source row (a third of it unclaimed), and checks that the keys agree.
        fn check(&mut self, levels: &[u16], n: usize, offsets: &[i32], w_src: usize) {
            let start: Vec<u32> = (0..w_src)
                .map(|_| {
                    if self.next(3) == 0 {
                        u32::MAX
                    } else {
                        self.next(1 << 31) as u32
                    }
                })
                .collect();
            let (mut plain, mut fast) = (start.clone(), start);
            reduce_shift_levels(false, levels, n, offsets, &mut plain);
            reduce_shift_levels(true, levels, n, offsets, &mut fast);
            let w = levels.len() / n;
            assert_eq!(
                plain, fast,
                "n {n}, w {w}, source row {w_src}, offsets {offsets:?}"
            );
        }
    }

    /// The gathered AVX-512 reduction of a shift row's keys equals the plain loop's, for one
    /// plane and many, rows of one pixel and more, source rows shorter and longer than the
    /// reference's, and offsets that put some, all or none of a plane outside the source.
    #[test]
    fn shift_level_reduction_is_the_same_gathered() {
        if !crate::cpu::avx512bw_enabled() {
            eprintln!("skipped: this CPU has no AVX-512 BW");
            return;
        }
        let mut rng = Lcg(99);
        for n in [1usize, 2, 3, 17, 173] {
            for w in [1usize, 5, 16, 37] {
                for w_src in [w.saturating_sub(3).max(1), w, w + 7] {
                    let levels: Vec<u16> = (0..w * n).map(|_| rng.next(9000) as u16).collect();
                    let offsets: Vec<i32> = (0..n)
                        .map(|_| rng.next(2 * w as u64 + 9) as i32 - w as i32 - 4)
                        .collect();
                    rng.check(&levels, n, &offsets, w_src);
                }
            }
        }
    }

    /// The sliding reduction equals the plain loop for offsets that step by 0 or −1 (a plane in
    /// a column alone or with its neighbour, blocks of 16 planes full and partial), rows of one
    /// pixel and more, source rows shorter and longer than the reference's, and offsets that put
    /// some, all or none of the voxels outside the source.
    #[test]
    fn shift_level_reduction_is_the_same_sliding() {
        if !crate::cpu::avx512bw_enabled() {
            eprintln!("skipped: this CPU has no AVX-512 BW");
            return;
        }
        let mut rng = Lcg(7);
        let mut checked = 0;
        for n in [1usize, 2, 15, 16, 17, 33, 113] {
            for w in [1usize, 5, 16, 17, 40, 161] {
                for w_src in [w.saturating_sub(3).max(1), w, w + 7] {
                    for repeats in [0u64, 1, 2] {
                        let levels: Vec<u16> = (0..w * n).map(|_| rng.next(9000) as u16).collect();
                        let mut offsets =
                            vec![rng.next(2 * w as u64 + n as u64 + 9) as i32 - (w as i32) / 2];
                        for i in 1..n {
                            let last = offsets[i - 1];
                            let repeat = repeats > 0
                                && rng.next(3) < repeats
                                && (i < 2 || offsets[i - 2] != last);
                            offsets.push(if repeat { last } else { last - 1 });
                        }
                        assert!(sliding_offsets(&offsets));
                        rng.check(&levels, n, &offsets, w_src);
                        checked += 1;
                    }
                }
            }
        }
        assert!(checked > 300);
    }

    #[test]
    fn sliding_offsets_are_steps_of_zero_or_minus_one_at_most_two_alike() {
        assert!(sliding_offsets(&[]));
        assert!(sliding_offsets(&[5]));
        assert!(sliding_offsets(&[5, 4, 4, 3, 2, 2, 1]));
        assert!(!sliding_offsets(&[5, 6]), "a step up");
        assert!(!sliding_offsets(&[5, 3]), "a step of two");
        assert!(
            !sliding_offsets(&[5, 4, 4, 4]),
            "three planes on one column"
        );
        assert!(!sliding_offsets(&[i32::MIN, i32::MAX]));
    }
}
