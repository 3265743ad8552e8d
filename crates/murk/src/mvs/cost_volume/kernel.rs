//! The per-row inner loop shared by the ordinary (Eq. 3.1) and dehazing (Eq. 3.7) cost volumes.
//! One generic body keeps the two volumes' arithmetic identical, so with `β = 0` (where
//! dehazing is the identity) they agree bit for bit.

use super::row::Haze;
use super::sample::bilinear_inside;
use super::shift::{self, ShiftRow};
use super::simd::{self, RowInputs};
use crate::mvs::plane_sweep::{PlaneWarp, RowWarp};

use super::DehazingResidual;

/// One source view for one plane: its samples and the plane's reference→source warp.
pub(super) struct SourcePlane<'a> {
    pub data: &'a [f32],
    /// The same image as [`super::sample::pad_rgb4`] pixels for the RGB direct rows' AVX2 loop;
    /// empty otherwise.
    pub padded: &'a [[f32; 4]],
    /// The same image as channel planes ([`super::shift::planar`], same offset as `padded`) for
    /// the direct rows whose warp is a horizontal shift; empty where the source has none.
    pub planar: &'a [f32],
    pub warp: PlaneWarp,
}

/// The reference image in the forms the direct rows ([`fill_row_observation`]) read.
#[derive(Clone, Copy)]
pub(super) struct ReferenceImages<'a> {
    /// Interleaved, `width × height × C`.
    pub data: &'a [f32],
    /// [`super::sample::pad_rgb4`] pixels for the RGB AVX2 loop; empty otherwise.
    pub rgb4: &'a [[f32; 4]],
    /// Channel planes ([`super::shift::planar`]); empty where no source has shift rows.
    pub planar: &'a [f32],
}

/// `max(0, dist(j, [0, 1]) − margin)`: how far a dehazed value lies outside its noise-widened
/// range.
#[inline]
fn excursion(j: f32, margin: f32) -> f32 {
    ((-j).max(j - 1.0) - margin).max(0.0)
}

/// Per-worker row buffers, reused across rows so the sweep allocates nothing per voxel or row.
#[derive(Default)]
pub(super) struct RowScratch {
    /// Dehazed (or plain) reference row, interleaved.
    jr: Vec<f32>,
    /// Whether every channel of the reference pixel is in `[0, 1]` (Eq. 3.7).
    ref_ok: Vec<bool>,
    /// Soft-penalty excursion of the reference pixel, summed over channels.
    ref_exc: Vec<f32>,
    /// Sum of per-source costs.
    sum: Vec<f32>,
    /// Number of sources that observe the voxel.
    observed: Vec<u32>,
    /// Source sample coordinates of the row (NaN = unobserved).
    us: Vec<f32>,
    vs: Vec<f32>,
    /// `1/t_s` of the row's samples (or `t_r/t_s` in the observation-space kernel).
    inv_t: Vec<f32>,
    /// The dehazed reference row in the 4-lane layout (Eq. 3.7's AVX2 loop).
    jr4: Vec<[f32; 4]>,
    /// One source's costs along a shift row ([`super::shift`]).
    shift_cost: Vec<f32>,
}

/// Fills one row of one plane. `penalty` is γ (Eq. 3.7) and also the cost of a voxel that no
/// source observes. Sources are the outer loop so each inner loop walks one source image along
/// one epipolar-ish path, with the row's warp reduced to affine-in-`u` terms.
#[allow(clippy::too_many_arguments)]
#[inline]
pub(super) fn fill_row<const C: usize, const DEHAZE: bool>(
    out: &mut [f32],
    y: usize,
    reference: &[f32],
    width: usize,
    height: usize,
    sources: &[SourcePlane<'_>],
    haze: Haze,
    penalty: f32,
    scratch: &mut RowScratch,
) {
    let row = &reference[y * width * C..(y + 1) * width * C];
    // Eq. 3.7 with a hard (or noise-widened) range check on RGB has an AVX2 loop; it reads the
    // sources' 4-lane copies, which the caller provides exactly in that case.
    let vector_eq37 = DEHAZE
        && C == 3
        && haze.residual == DehazingResidual::Eq37
        && haze.soft_margin.is_none()
        && sources.iter().all(|s| !s.padded.is_empty());
    // The ordinary volume compares the reference row as it is; only the dehazing volume needs
    // the dehazed row and its range flags.
    if vector_eq37 {
        // The dehazed row straight into the 4-lane layout, pixel by pixel (no soft penalty
        // here, so no excursions).
        scratch.jr4.resize(width, [0.0; 4]);
        scratch.ref_ok.resize(width, true);
        scratch.ref_exc.clear();
        scratch.ref_exc.resize(width, 0.0);
        simd::dehaze_reference_rgb4(row, haze, &mut scratch.jr4, &mut scratch.ref_ok);
    } else if DEHAZE {
        scratch.jr.clear();
        scratch.ref_ok.clear();
        scratch.ref_exc.clear();
        let ref_soft = haze.soft_margin.map(|m| m * haze.ref_inv_t);
        for ir in row.chunks_exact(C) {
            let mut ok = true;
            let mut exc = 0.0f32;
            for &v in ir {
                let j = v * haze.ref_inv_t + haze.ref_offset;
                ok &= (haze.ref_lo..=haze.ref_hi).contains(&j);
                if let Some(m) = ref_soft {
                    exc += excursion(j, m);
                }
                scratch.jr.push(j);
            }
            scratch.ref_ok.push(ok);
            scratch.ref_exc.push(exc);
        }
    } else {
        scratch.ref_ok.clear();
        scratch.ref_ok.resize(width, true);
        scratch.ref_exc.clear();
        scratch.ref_exc.resize(width, 0.0);
    }
    scratch.sum.clear();
    scratch.sum.resize(width, 0.0);
    scratch.observed.clear();
    scratch.observed.resize(width, 0);
    scratch.us.resize(width, 0.0);
    scratch.vs.resize(width, 0.0);

    let sum = &mut scratch.sum[..width];
    let observed = &mut scratch.observed[..width];
    // Pixel x's reference values are jr_row[x·stride..x·stride + C].
    let (jr_row, stride) = if vector_eq37 {
        (scratch.jr4[..width].as_flattened(), 4)
    } else if DEHAZE {
        (&scratch.jr[..width * C], C)
    } else {
        (row, C)
    };
    let (us_row, vs_row) = (&mut scratch.us[..width], &mut scratch.vs[..width]);
    scratch.inv_t.resize(width, 0.0);
    let inv_t_row = &mut scratch.inv_t[..width];
    let ref_ok = &scratch.ref_ok[..width];
    let ref_exc = &scratch.ref_exc[..width];
    let jr4 = &scratch.jr4[..];
    for s in sources {
        let warp = s.warp.row(y as f64);
        simd::source_coords(&warp, width, height, us_row, vs_row);
        if DEHAZE {
            simd::inverse_transmission_row(&warp, haze.beta, inv_t_row);
        }
        let start = if vector_eq37 {
            let row = simd::DehazedRow {
                us: us_row,
                vs: vs_row,
                inv_t: inv_t_row,
                airlight: haze.airlight,
                src_margin: haze.src_margin,
                ref_ok,
                jr4,
            };
            simd::accumulate_rgb4_eq37(sum, observed, &row, s.padded, width, height, penalty)
        } else {
            0
        };
        for x in start..width {
            let inv_t_here = if DEHAZE { inv_t_row[x] } else { 1.0 };
            let (us, vs) = (us_row[x], vs_row[x]);
            if us.is_nan() {
                continue;
            }
            let is = bilinear_inside::<C>(s.data, width, us, vs, height);
            observed[x] += 1;
            if DEHAZE && !ref_ok[x] {
                sum[x] += penalty;
                continue;
            }
            let jr = &jr_row[x * stride..x * stride + C];
            let (inv_t, offset, lo, hi, scale) = if DEHAZE {
                // Eq. 3.6: the source sample is dehazed with the plane point's depth ζ as seen
                // from the source camera, not with z_i.
                let inv_t = inv_t_here;
                let margin = haze.src_margin * inv_t;
                let scale = match haze.residual {
                    DehazingResidual::Eq37 => 1.0,
                    DehazingResidual::ObservationSpace => haze.ref_t,
                    DehazingResidual::NoiseWhitened => {
                        // t_r·sqrt(2 / (1 + (t_r/t_s)²)): exactly 1 when t_r = t_s = 1.
                        let r = haze.ref_t * inv_t;
                        haze.ref_t * (2.0 / (1.0 + r * r)).sqrt()
                    }
                };
                (
                    inv_t,
                    haze.airlight * (1.0 - inv_t),
                    -margin,
                    1.0 + margin,
                    scale,
                )
            } else {
                (1.0, 0.0, 0.0, 1.0, 1.0)
            };
            let mut cost = 0.0f32;
            let mut src_ok = true;
            for c in 0..C {
                let js = if DEHAZE {
                    is[c] * inv_t + offset
                } else {
                    is[c]
                };
                src_ok &= (lo..=hi).contains(&js);
                cost += (jr[c] - js).abs();
            }
            sum[x] += if DEHAZE && !src_ok {
                penalty
            } else if DEHAZE {
                // Capped at γ so the volume stays in [0, γ] without the hard check too (a no-op
                // for Eq. 3.7, whose in-range residual is at most C = γ).
                let exc = match haze.soft_margin {
                    None => 0.0,
                    Some(m) => {
                        let m = m * inv_t;
                        let e: f32 = is.iter().map(|&v| excursion(v * inv_t + offset, m)).sum();
                        ref_exc[x] + e
                    }
                };
                ((cost + exc) * scale).min(penalty)
            } else {
                cost
            };
        }
    }

    simd::mean_or_penalty(out, &scratch.sum, &scratch.observed, penalty);
}

/// The default dehazing volume's row ([`DehazingResidual::ObservationSpace`], no range check,
/// `β > 0`) in closed form: `min(γ, Σ_c |(I_r − A) − (t_r/t_s)(I_s − A)|)`, which is
/// `t_r·Σ_c |J_r − J_s|` (Eq. 3.5–3.6) without dehazing either sample. Equal to [`fill_row`]
/// in that mode up to `f32` rounding (tested); skips its per-voxel mode switches.
///
/// With `HAZE = false` it is the ordinary volume's row (Eq. 3.1), `Σ_c |I_r − I_s|` uncapped,
/// bit for bit what [`fill_row`] computes without dehazing (tested).
///
/// Where the CPU has AVX2 the row runs through [`simd`]'s loops, eight pixels at a time (RGB
/// reads the reference's `rgb4` and the sources' `padded` images, [`super::sample::pad_rgb4`]); the
/// scalar loop below does the rest of the row, or all of it.
#[allow(clippy::too_many_arguments)]
#[inline]
pub(super) fn fill_row_observation<'a, const C: usize, const HAZE: bool>(
    out: &mut [f32],
    y: usize,
    reference: ReferenceImages<'a>,
    width: usize,
    height: usize,
    sources: &[SourcePlane<'a>],
    haze: Haze,
    penalty: f32,
    scratch: &mut RowScratch,
) {
    let t_r = haze.ref_t;
    // k = t_r/t_s per pixel of the row.
    let ratio_of = |warp: &RowWarp, ratio_row: &mut [f32]| {
        simd::inverse_transmission_row(warp, haze.beta, ratio_row);
        for r in ratio_row.iter_mut() {
            *r *= t_r;
        }
    };
    let shift_row = |s: &SourcePlane<'a>, warp: &RowWarp| {
        ShiftRow::of(s.planar, reference.planar, y, warp, width)
    };
    scratch.inv_t.resize(width, 0.0);
    if let [s] = sources {
        let warp = s.warp.row(y as f64);
        if let Some(row) = shift_row(s, &warp) {
            // One source whose row shifts (a rectified pair): the mean of its sums is its
            // cost, written without them.
            let ratio_row = &mut scratch.inv_t[..width];
            if HAZE {
                ratio_of(&warp, ratio_row);
            }
            let target = shift::Target::Only(out);
            shift::accumulate::<C, HAZE>(target, row, ratio_row, width, height, penalty);
            return;
        }
    }
    let row = &reference.data[y * width * C..(y + 1) * width * C];
    let a = haze.airlight;
    scratch.sum.clear();
    scratch.sum.resize(width, 0.0);
    scratch.observed.clear();
    scratch.observed.resize(width, 0);
    scratch.us.resize(width, 0.0);
    scratch.vs.resize(width, 0.0);
    let sum = &mut scratch.sum[..width];
    let observed = &mut scratch.observed[..width];
    let (us_row, vs_row) = (&mut scratch.us[..width], &mut scratch.vs[..width]);
    let ratio_row = &mut scratch.inv_t[..width];
    scratch.shift_cost.resize(width, 0.0);
    for s in sources {
        let warp = s.warp.row(y as f64);
        if HAZE {
            ratio_of(&warp, ratio_row);
        }
        if let Some(row) = shift_row(s, &warp) {
            shift::accumulate::<C, HAZE>(
                shift::Target::Sums {
                    sum,
                    observed,
                    cost: &mut scratch.shift_cost,
                },
                row,
                ratio_row,
                width,
                height,
                penalty,
            );
            continue;
        }
        simd::source_coords(&warp, width, height, us_row, vs_row);
        let inputs = RowInputs {
            us: us_row,
            vs: vs_row,
            ratio: ratio_row,
            airlight: a,
        };
        let start = if C == 3 {
            simd::accumulate_rgb4::<HAZE>(
                sum,
                observed,
                &inputs,
                &reference.rgb4[y * width..(y + 1) * width],
                s.padded,
                width,
                height,
                penalty,
            )
        } else {
            simd::accumulate::<C, HAZE>(sum, observed, &inputs, row, s.data, width, height, penalty)
        };
        for x in start..width {
            let us = us_row[x];
            if us.is_nan() {
                continue;
            }
            let is = bilinear_inside::<C>(s.data, width, us, vs_row[x], height);
            let ir = &row[x * C..x * C + C];
            let mut cost = 0.0f32;
            if HAZE {
                // The airlight terms folded into one offset:
                // (I_r − A) − k(I_s − A) = I_r − k·I_s + A(k − 1).
                let k = ratio_row[x];
                let b = a * (k - 1.0);
                for c in 0..C {
                    cost += (ir[c] - k * is[c] + b).abs();
                }
                cost = cost.min(penalty);
            } else {
                for c in 0..C {
                    cost += (ir[c] - is[c]).abs();
                }
            }
            sum[x] += cost;
            observed[x] += 1;
        }
    }
    simd::mean_or_penalty(out, sum, observed, penalty);
}

#[cfg(test)]
mod tests {
    use super::super::row::mean_or_penalty;
    use super::*;
    use crate::atmosphere::inverse_transmission;
    use crate::camera::Intrinsics;
    use crate::mvs::cost_volume::sample::pad_rgb4;
    use crate::mvs::pose::Pose;

    /// An RGB test image, `w × h`, pseudo-random values `(hash mod 1000)/scale − shift`.
    fn test_image(w: usize, h: usize, seed: usize, scale: f32, shift: f32) -> Vec<f32> {
        (0..w * h * 3)
            .map(|i| (((i + seed) * 2654435761) % 1000) as f32 / scale - shift)
            .collect()
    }

    /// Intrinsics and a reference → source pose with a sideways and forward baseline.
    fn test_geometry() -> (Intrinsics, Pose) {
        let k = Intrinsics::new(30.0, 30.0, 20.0, 6.0);
        let rel = Pose::translation_only([-0.3, 0.05, 0.1]).unwrap();
        (k, rel)
    }

    /// The plane constants at depth `z` with airlight `a`: range margin `margin` (observation
    /// units) on both the reference and the source check (`∞` = no check), no soft penalty.
    fn haze_at(a: f32, beta: f32, z: f64, residual: DehazingResidual, margin: f32) -> Haze {
        let t = (-beta * z as f32).exp();
        let inv_t = inverse_transmission(t);
        Haze {
            airlight: a,
            beta,
            ref_inv_t: inv_t,
            ref_offset: a * (1.0 - inv_t),
            ref_t: t,
            residual,
            ref_lo: -margin * inv_t,
            ref_hi: 1.0 + margin * inv_t,
            src_margin: margin,
            soft_margin: None,
        }
    }

    /// The direct ordinary row (AVX2 loops and scalar loop, RGB and grey) equals the generic row
    /// without dehazing, bit for bit.
    #[test]
    fn direct_ordinary_row_matches_generic_row() {
        // Not a multiple of 8: the AVX2 loop and the scalar remainder both run.
        let (w, h) = (43usize, 12usize);
        let (refd, src) = (
            test_image(w, h, 0, 700.0, 0.2),
            test_image(w, h, 7, 700.0, 0.2),
        );
        let (ref4, src4) = (pad_rgb4(&refd, 0.0), pad_rgb4(&src, 0.0));
        let images = ReferenceImages {
            data: &refd,
            rgb4: &ref4,
            planar: &[],
        };
        let (k, rel) = test_geometry();
        let haze = Haze::CLEAR;
        for z in [1.0f64, 2.5, 6.0] {
            let sources = [
                SourcePlane {
                    data: &src,
                    padded: &src4,
                    planar: &[],
                    warp: PlaneWarp::new(&k, &k, &rel, z),
                },
                SourcePlane {
                    data: &refd,
                    padded: &ref4,
                    planar: &[],
                    warp: PlaneWarp::new(&k, &k, &Pose::identity(), z),
                },
            ];
            for y in 0..h {
                let (mut g, mut f) = (vec![0.0; w], vec![0.0; w]);
                let mut s = RowScratch::default();
                fill_row::<3, false>(&mut g, y, &refd, w, h, &sources, haze, 3.0, &mut s);
                for scalar in [false, true] {
                    crate::cpu::force_scalar(scalar);
                    fill_row_observation::<3, false>(
                        &mut f, y, images, w, h, &sources, haze, 3.0, &mut s,
                    );
                    assert_eq!(g, f, "z {z}, row {y}, scalar {scalar}");
                }
                crate::cpu::force_scalar(false);
            }
            // One channel: the gather loop.
            let (gray_ref, gray_src) = (&refd[..w * h], &src[..w * h]);
            let gray = [SourcePlane {
                data: gray_src,
                padded: &[],
                planar: &[],
                warp: PlaneWarp::new(&k, &k, &rel, z),
            }];
            for y in 0..h {
                let (mut g, mut f) = (vec![0.0; w], vec![0.0; w]);
                let mut s = RowScratch::default();
                fill_row::<1, false>(&mut g, y, gray_ref, w, h, &gray, haze, 1.0, &mut s);
                let gray_images = ReferenceImages {
                    data: gray_ref,
                    rgb4: &[],
                    planar: &[],
                };
                fill_row_observation::<1, false>(
                    &mut f,
                    y,
                    gray_images,
                    w,
                    h,
                    &gray,
                    haze,
                    1.0,
                    &mut s,
                );
                assert_eq!(g, f, "gray: z {z}, row {y}");
            }
        }
    }

    /// The closed-form observation-space row (AVX2 and scalar) equals the generic row in that
    /// mode.
    #[test]
    fn observation_row_matches_generic_row() {
        // Not a multiple of 8: the AVX2 loop and the scalar remainder both run.
        let (w, h) = (43usize, 12usize);
        let (refd, src) = (
            test_image(w, h, 0, 1000.0, 0.0),
            test_image(w, h, 7, 1000.0, 0.0),
        );
        let (a, beta) = (0.8f32, 0.3f32);
        let (ref4, src4) = (pad_rgb4(&refd, a), pad_rgb4(&src, a));
        let images = ReferenceImages {
            data: &refd,
            rgb4: &ref4,
            planar: &[],
        };
        let (k, rel) = test_geometry();
        for z in [1.0f64, 2.5, 6.0] {
            let sources = [SourcePlane {
                data: &src,
                padded: &src4,
                planar: &[],
                warp: PlaneWarp::new(&k, &k, &rel, z),
            }];
            let haze = haze_at(
                a,
                beta,
                z,
                DehazingResidual::ObservationSpace,
                f32::INFINITY,
            );
            for y in 0..h {
                let (mut g, mut f) = (vec![0.0; w], vec![0.0; w]);
                let mut s = RowScratch::default();
                fill_row::<3, true>(&mut g, y, &refd, w, h, &sources, haze, 3.0, &mut s);
                for scalar in [false, true] {
                    crate::cpu::force_scalar(scalar);
                    fill_row_observation::<3, true>(
                        &mut f, y, images, w, h, &sources, haze, 3.0, &mut s,
                    );
                    for (x, (g, f)) in g.iter().zip(&f).enumerate() {
                        assert!(
                            (g - f).abs() <= 1e-5 * g.max(1.0),
                            "z {z} ({x}, {y}), scalar {scalar}: {g} vs {f}"
                        );
                    }
                }
                crate::cpu::force_scalar(false);
            }
        }
    }

    /// Rows whose warp is a horizontal shift (a rectified pair; a vertical baseline) take the
    /// shift path when the channel planes are given, and agree with the general path, RGB and
    /// grey, ordinary and observation-space: bit for bit for an integer shift, up to the rounding
    /// of the general path's coordinates otherwise, with the same pixels observed (columns that
    /// leave the source get the penalty in both).
    #[test]
    fn shift_rows_match_the_general_rows() {
        let (w, h) = (43usize, 12usize);
        let (refd, src) = (
            test_image(w, h, 0, 1000.0, 0.0),
            test_image(w, h, 7, 1000.0, 0.0),
        );
        let k = Intrinsics::new(30.0, 30.0, 20.0, 6.0);
        let (a, beta) = (0.8f32, 0.3f32);
        for (t, z, integer) in [
            ([-0.3, 0.0, 0.0], 1.0, true),  // du = −9 exactly
            ([-0.3, 0.0, 0.0], 2.5, false), // du = −3.6
            ([0.5, 0.0, 0.0], 0.7, false),  // du ≈ +21.4: half the row leaves the source
            ([0.0, 0.11, 0.0], 1.3, false), // v = y + 2.54…, fy ≠ 0, the last rows leave it
            ([-0.2, 0.0, 0.0], 1e9, false), // du = −6e−9: fx rounds to 1 in the cell to the left
        ] {
            let rel = Pose::translation_only(t).unwrap();
            let warp = PlaneWarp::new(&k, &k, &rel, z);
            assert!(warp.row(3.0).shift(w, shift::SHIFT_TOLERANCE_PX).is_some());
            for (c, haze_on) in [(3usize, false), (3, true), (1, false), (1, true)] {
                let offset = if haze_on { a } else { 0.0 };
                let (rd, sd) = (&refd[..w * h * c], &src[..w * h * c]);
                let (ref4, src4) = if c == 3 {
                    (pad_rgb4(rd, offset), pad_rgb4(sd, offset))
                } else {
                    (Vec::new(), Vec::new())
                };
                let (ref_planar, src_planar) =
                    (shift::planar(rd, c, offset), shift::planar(sd, c, offset));
                let haze = if haze_on {
                    haze_at(
                        a,
                        beta,
                        z,
                        DehazingResidual::ObservationSpace,
                        f32::INFINITY,
                    )
                } else {
                    haze_at(0.0, 0.0, z, DehazingResidual::Eq37, 0.0)
                };
                let penalty = c as f32;
                let general = [SourcePlane {
                    data: sd,
                    padded: &src4,
                    planar: &[],
                    warp,
                }];
                let shifted = [SourcePlane {
                    planar: &src_planar,
                    ..general[0]
                }];
                for y in 0..h {
                    let (mut g, mut f) = (vec![0.0; w], vec![0.0; w]);
                    let mut s = RowScratch::default();
                    macro_rules! row {
                        ($c:literal, $haze:literal, $out:expr, $planar:expr, $srcs:expr) => {
                            fill_row_observation::<$c, $haze>(
                                $out,
                                y,
                                ReferenceImages {
                                    data: rd,
                                    rgb4: &ref4,
                                    planar: $planar,
                                },
                                w,
                                h,
                                $srcs,
                                haze,
                                penalty,
                                &mut s,
                            )
                        };
                    }
                    match (c, haze_on) {
                        (3, false) => {
                            row!(3, false, &mut g, &[], &general);
                            row!(3, false, &mut f, &ref_planar, &shifted);
                        }
                        (3, true) => {
                            row!(3, true, &mut g, &[], &general);
                            row!(3, true, &mut f, &ref_planar, &shifted);
                        }
                        (1, false) => {
                            row!(1, false, &mut g, &[], &general);
                            row!(1, false, &mut f, &ref_planar, &shifted);
                        }
                        _ => {
                            row!(1, true, &mut g, &[], &general);
                            row!(1, true, &mut f, &ref_planar, &shifted);
                        }
                    }
                    for (x, (g, f)) in g.iter().zip(&f).enumerate() {
                        let at = format!("t {t:?} z {z} c {c} haze {haze_on} ({x}, {y})");
                        // Unobserved on one side only would be the penalty against a cost.
                        assert_eq!(*g == penalty, *f == penalty, "{at}: {g} vs {f}");
                        if integer && !haze_on && c == 3 {
                            assert_eq!(g, f, "{at}");
                        } else {
                            assert!((g - f).abs() <= 1e-4 * g.max(1.0), "{at}: {g} vs {f}");
                        }
                    }
                }
            }
        }
    }

    /// The only source's shift costs, written straight to the row ([`shift::Target::Only`]),
    /// are bit for bit the mean that [`mean_or_penalty`] takes of the same source's sums
    /// ([`shift::Target::Sums`]), with the penalty where the sample leaves the source: RGB and
    /// grey, ordinary and observation-space, whole and fractional shifts, rows that leave the
    /// source at either end or entirely, on top of a row that held other values.
    #[test]
    fn only_source_costs_are_the_mean_of_its_sums() {
        let (w, h) = (43usize, 12usize);
        let (refd, src) = (
            test_image(w, h, 0, 1000.0, 0.0),
            test_image(w, h, 7, 1000.0, 0.0),
        );
        let ratio: Vec<f32> = (0..w).map(|x| 0.8 + 0.01 * x as f32).collect();
        for (du, v) in [
            (-9.0, 3.0),
            (-3.6, 3.0),
            (21.4, 5.0),
            (2.5, 4.54),
            (-6e-9, 0.0),
            (0.0, 11.0),
            (50.0, 2.0),
            (-3.0, 11.5),
        ] {
            for c in [3usize, 1] {
                let (rd, sd) = (&refd[..w * h * c], &src[..w * h * c]);
                let (ref_planar, src_planar) =
                    (shift::planar(rd, c, 0.2), shift::planar(sd, c, 0.2));
                for y in [0, 5, h - 1] {
                    let row = ShiftRow {
                        reference: &ref_planar,
                        source: &src_planar,
                        y,
                        du,
                        v,
                    };
                    let penalty = 0.6 * c as f32;
                    let only_and_mean = |haze: bool| {
                        let mut only = vec![-7.0f32; w];
                        let (mut sum, mut observed, mut cost) =
                            (vec![0.0f32; w], vec![0u32; w], vec![-7.0f32; w]);
                        macro_rules! both {
                            ($c:literal, $haze:literal) => {{
                                shift::accumulate::<$c, $haze>(
                                    shift::Target::Only(&mut only),
                                    row,
                                    &ratio,
                                    w,
                                    h,
                                    penalty,
                                );
                                shift::accumulate::<$c, $haze>(
                                    shift::Target::Sums {
                                        sum: &mut sum,
                                        observed: &mut observed,
                                        cost: &mut cost,
                                    },
                                    row,
                                    &ratio,
                                    w,
                                    h,
                                    penalty,
                                );
                            }};
                        }
                        match (c, haze) {
                            (3, false) => both!(3, false),
                            (3, true) => both!(3, true),
                            (1, false) => both!(1, false),
                            _ => both!(1, true),
                        }
                        let mut mean = vec![0.0f32; w];
                        mean_or_penalty(&mut mean, &sum, &observed, penalty);
                        (only, mean)
                    };
                    for haze in [false, true] {
                        let (only, mean) = only_and_mean(haze);
                        for (x, (o, m)) in only.iter().zip(&mean).enumerate() {
                            assert_eq!(
                                o.to_bits(),
                                m.to_bits(),
                                "du {du} v {v} c {c} haze {haze} ({x}, {y}): {o} vs {m}"
                            );
                        }
                    }
                }
            }
        }
    }

    /// Eq. 3.7's AVX2 loop (hard and noise-widened range checks), and the scalar loop on the
    /// 4-lane reference, equal the generic scalar row bit for bit, on values that put some
    /// dehazed samples outside `[0, 1]`.
    #[test]
    fn eq37_vector_row_matches_scalar_row() {
        let (w, h) = (43usize, 12usize);
        let (refd, src) = (
            test_image(w, h, 0, 1000.0, 0.0),
            test_image(w, h, 7, 1000.0, 0.0),
        );
        let src4 = pad_rgb4(&src, 0.0);
        let (k, rel) = test_geometry();
        let (a, beta) = (0.8f32, 0.3f32);
        let mut penalised = 0usize;
        for (z, margin) in [(1.0f64, 0.0f32), (2.5, 0.0), (6.0, 0.0), (2.5, 0.02)] {
            let sources = [SourcePlane {
                data: &src,
                padded: &src4,
                planar: &[],
                warp: PlaneWarp::new(&k, &k, &rel, z),
            }];
            let haze = haze_at(a, beta, z, DehazingResidual::Eq37, margin);
            // Without the 4-lane copies the row takes the generic scalar path throughout.
            let plain = [SourcePlane {
                data: &src,
                padded: &[],
                planar: &[],
                warp: PlaneWarp::new(&k, &k, &rel, z),
            }];
            for y in 0..h {
                let (mut v, mut f, mut g) = (vec![0.0; w], vec![0.0; w], vec![0.0; w]);
                let mut s = RowScratch::default();
                fill_row::<3, true>(&mut g, y, &refd, w, h, &plain, haze, 3.0, &mut s);
                fill_row::<3, true>(&mut v, y, &refd, w, h, &sources, haze, 3.0, &mut s);
                crate::cpu::force_scalar(true);
                fill_row::<3, true>(&mut f, y, &refd, w, h, &sources, haze, 3.0, &mut s);
                crate::cpu::force_scalar(false);
                assert_eq!(v, g, "vector: z {z}, margin {margin}, row {y}");
                assert_eq!(f, g, "4-lane scalar: z {z}, margin {margin}, row {y}");
                penalised += g.iter().filter(|&&c| c == 3.0).count();
            }
        }
        assert!(penalised > 0, "the range check never fired");
    }
}
