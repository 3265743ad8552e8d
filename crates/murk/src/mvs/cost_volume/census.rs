//! The census term of the matching cost: a photometric comparison that survives what real
//! cameras do to the numbers they record.
//!
//! The L1 residuals of Eq. 3.1 and of the dehazing volume (Eq. 3.4–3.7) compare pixel values,
//! so any difference between the cameras' responses that the model does not name — vignetting,
//! a tone curve, a spatially varying gain — is an offset in every voxel. Haze makes it worse:
//! it scales the texture differences that separate the true plane from a wrong one by `t`
//! (Eq. 3.3, `I − A = t·(J − A)`), while a camera's gain scales the airlight too.
//!
//! The census transform (Zabih & Woodfill 1994) keeps only the signs of `I(q) − I(p)` for the
//! neighbours `q` of `p`. Within a window at one depth the haze model is an increasing affine
//! map of the radiance, `I = t·J + A(1 − t)` with `t > 0`, and so is any smooth camera gain;
//! tone curves are increasing too. The census code of the hazy observation is therefore the
//! census code of the scene radiance, in either camera, whatever `A`, `t` and the camera's
//! response — until sensor noise flips the signs of comparisons closer than the noise, where
//! transmission is low. The Hamming distance between the reference's code and the source's at
//! the plane's projection is the term's cost (SGBM-class matchers pair it with a pixel
//! difference the same way, e.g. AD-Census, Mei et al. 2011).
//!
//! murk adds `λ·H/B` to each voxel, `H` the Hamming distance over the `B` = 48 bits of a 7×7
//! window on the channels' mean, averaged over the sources that see the voxel (1 for a voxel no
//! source sees, as the photometric term gives it `γ`). The term is not scaled by the contrast
//! normalisation's weights (`depth::contrast`): it does not shrink with the transmission, so
//! the per-pixel weight `w_p` is divided out where it is applied.
//!
//! Source codes are read at the nearest pixel to the projection (the codes are bit strings,
//! not interpolable) and computed in the source's own image, not warped: a window of a slanted
//! plane is sheared between the views, as in any census stereo matcher.

use rayon::prelude::*;

use crate::camera::Intrinsics;
use crate::error::Result;
use crate::image::ImageF32;
use crate::monitor::Monitor;
use crate::mvs::plane_sweep::{PlaneSet, PlaneWarp};
use crate::mvs::pose::Pose;

/// Radius of the census window (7×7).
pub const CENSUS_RADIUS: usize = 3;

/// Bits per census code: every pixel of the window but the centre.
pub const CENSUS_BITS: u32 = ((2 * CENSUS_RADIUS + 1) * (2 * CENSUS_RADIUS + 1) - 1) as u32;

/// Census codes of an image, row-major, one `u64` per pixel.
#[derive(Clone, Debug, PartialEq)]
pub struct CensusImage {
    width: usize,
    height: usize,
    codes: Vec<u64>,
}

impl CensusImage {
    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }
    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }
    /// The codes, row-major.
    pub fn codes(&self) -> &[u64] {
        &self.codes
    }
}

/// The 7×7 census transform of `image`'s channel mean: bit `k` of pixel `p`'s code is set when
/// the `k`-th neighbour (row-major over the window, the centre skipped) is darker than `p`.
/// Neighbours beyond the border repeat the edge pixel, so a border pixel's outside bits compare
/// like with like (and are clear).
pub fn census_transform(image: &ImageF32) -> CensusImage {
    let (w, h, c) = (image.width(), image.height(), image.channels());
    let data = image.data();
    let gray: Vec<f32> = if c == 1 {
        data.to_vec()
    } else {
        data.chunks_exact(c)
            .map(|p| p.iter().sum::<f32>() / c as f32)
            .collect()
    };
    let r = CENSUS_RADIUS as isize;
    let mut codes = vec![0u64; w * h];
    codes
        .par_chunks_mut(w.max(1))
        .enumerate()
        .for_each(|(y, row)| {
            for (x, code) in row.iter_mut().enumerate() {
                let centre = gray[y * w + x];
                let mut bits = 0u64;
                let mut k = 0;
                for dy in -r..=r {
                    let yy = (y as isize + dy).clamp(0, h as isize - 1) as usize;
                    for dx in -r..=r {
                        if dx == 0 && dy == 0 {
                            continue;
                        }
                        let xx = (x as isize + dx).clamp(0, w as isize - 1) as usize;
                        bits |= u64::from(gray[yy * w + xx] < centre) << k;
                        k += 1;
                    }
                }
                *code = bits;
            }
        });
    CensusImage {
        width: w,
        height: h,
        codes,
    }
}

/// One source for [`add_census_costs`]: its codes, intrinsics and the reference→source pose.
#[derive(Clone, Copy, Debug)]
pub struct CensusSource<'a> {
    /// The source's census codes.
    pub census: &'a CensusImage,
    /// The source's intrinsics.
    pub intrinsics: Intrinsics,
    /// `(R, t)` from the reference's frame to the source's ([`Pose::relative`]).
    pub relative: Pose,
}

/// Adds `weight·H/B` (averaged over the sources that see the voxel, `weight` where none does)
/// to every voxel of `volume`, a `[plane][row][x]` cost volume over the reference rows `rows`
/// (as from [`super::build_cost_volume_rows`]). A voxel is seen by a source when the plane point
/// lies in front of it and projects into the hull of its pixel centres, the cost volume's own
/// rule. `pixel_weights` (row-major over `rows`, or empty) are the contrast weights that the
/// volume will be multiplied by; the term is divided by them so that it arrives unweighted.
#[allow(clippy::too_many_arguments)]
pub fn add_census_costs(
    volume: &mut [f32],
    reference: &CensusImage,
    k_ref: &Intrinsics,
    sources: &[CensusSource<'_>],
    planes: &PlaneSet,
    rows: std::ops::Range<usize>,
    weight: f32,
    pixel_weights: &[f32],
    monitor: &Monitor,
) -> Result<()> {
    let w = reference.width;
    let n_pix = w * rows.len();
    debug_assert_eq!(volume.len(), n_pix * planes.num_planes);
    debug_assert!(pixel_weights.is_empty() || pixel_weights.len() == n_pix);
    let census = CensusRows {
        reference,
        k_ref,
        sources,
        planes,
        rows,
        weight,
        pixel_weights,
    };
    volume.par_chunks_mut(n_pix).enumerate().try_for_each_init(
        CensusScratch::default,
        |scratch, (i, plane)| -> Result<()> {
            monitor.checkpoint()?;
            census.add_to_plane(i, plane, scratch);
            Ok(())
        },
    )
}

/// Per-worker buffers of [`CensusRows::add_to_plane`], reused from plane to plane.
#[derive(Default)]
pub struct CensusScratch {
    hamming: Vec<u32>,
    seen: Vec<u32>,
    warps: Vec<PlaneWarp>,
}

/// [`add_census_costs`] a plane at a time, for a caller that runs more per plane (the box window
/// of a group of planes while their rows are in L2).
pub struct CensusRows<'a> {
    /// The reference's codes.
    pub reference: &'a CensusImage,
    /// The reference's intrinsics.
    pub k_ref: &'a Intrinsics,
    /// The sources.
    pub sources: &'a [CensusSource<'a>],
    /// The planes.
    pub planes: &'a PlaneSet,
    /// The reference rows the planes' values cover.
    pub rows: std::ops::Range<usize>,
    /// The term's weight.
    pub weight: f32,
    /// Contrast weights, row-major over `rows`, or empty.
    pub pixel_weights: &'a [f32],
}

impl CensusRows<'_> {
    /// [`add_census_costs`] on plane `i`'s rows `plane` (`rows.len() · W` values).
    pub fn add_to_plane(&self, i: usize, plane: &mut [f32], scratch: &mut CensusScratch) {
        let w = self.reference.width;
        debug_assert_eq!(plane.len(), w * self.rows.len());
        let scale = self.weight / CENSUS_BITS as f32;
        let CensusScratch {
            hamming,
            seen,
            warps,
        } = scratch;
        hamming.resize(w, 0);
        seen.resize(w, 0);
        let z = self.planes.depth(i as f64);
        // Each source's homography once per plane; rows take their affine-in-x slice of it.
        warps.clear();
        warps.extend(
            self.sources
                .iter()
                .map(|s| PlaneWarp::new(self.k_ref, &s.intrinsics, &s.relative, z)),
        );
        for (k, out) in plane.chunks_exact_mut(w).enumerate() {
            let y = self.rows.start + k;
            let ref_codes = &self.reference.codes[y * w..(y + 1) * w];
            hamming.fill(0);
            seen.fill(0);
            for (s, plane_warp) in self.sources.iter().zip(warps.iter()) {
                let (sw, sh) = (s.census.width, s.census.height);
                let (max_u, max_v) = ((sw - 1) as f32, (sh - 1) as f32);
                let warp = plane_warp.row(y as f64).to_f32();
                for (x, (&rc, (hm, sn))) in ref_codes
                    .iter()
                    .zip(hamming.iter_mut().zip(seen.iter_mut()))
                    .enumerate()
                {
                    let (u, v, hw) = warp.project(x as f32);
                    if hw > 0.0 && u >= 0.0 && v >= 0.0 && u <= max_u && v <= max_v {
                        // Inside the hull, so rounding stays in the image. Through `i32`:
                        // f32 → i32 is one instruction, f32 → usize a two-range sequence.
                        let (xs, ys) = ((u + 0.5) as i32 as usize, (v + 0.5) as i32 as usize);
                        *hm += (rc ^ s.census.codes[ys * sw + xs]).count_ones();
                        *sn += 1;
                    }
                }
            }
            let weights_row =
                (!self.pixel_weights.is_empty()).then(|| &self.pixel_weights[k * w..][..w]);
            for (x, (o, (&hm, &sn))) in out
                .iter_mut()
                .zip(hamming.iter().zip(seen.iter()))
                .enumerate()
            {
                let term = if sn == 0 {
                    self.weight
                } else {
                    scale * hm as f32 / sn as f32
                };
                *o += match weights_row {
                    Some(wr) => term / wr[x],
                    None => term,
                };
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mvs::plane_sweep::PlaneSet;
    use proptest::prelude::*;

    /// An image of well-separated levels (`k/64`), so that rounding in a transform cannot
    /// reorder two of them.
    fn levels(w: usize, h: usize, c: usize, seed: &[u8]) -> ImageF32 {
        let data: Vec<f32> = (0..w * h * c)
            .map(|i| f32::from(seed[i % seed.len()] % 64) / 64.0)
            .collect();
        ImageF32::from_vec(w, h, c, data).unwrap()
    }

    proptest! {
        /// The haze model at one depth (`t·J + A(1 − t)`), a gain and a tone curve are
        /// increasing maps of the value: the codes do not change.
        #[test]
        fn codes_ignore_increasing_maps(
            seed in proptest::collection::vec(any::<u8>(), 37..200),
            t in 0.05f32..1.0,
            airlight in 0.0f32..1.0,
            gain in 0.5f32..2.0,
            gamma in 0.5f32..2.0,
        ) {
            let img = levels(11, 9, 1, &seed);
            let mut mapped = img.clone();
            for v in mapped.data_mut() {
                *v = gain * (t * *v + airlight * (1.0 - t)).powf(gamma);
            }
            prop_assert_eq!(census_transform(&img), census_transform(&mapped));
        }
    }

    /// Bit `k` is set exactly when the `k`-th neighbour is darker than the centre; edges repeat.
    #[test]
    fn codes_follow_the_definition() {
        let img = levels(9, 8, 3, &[7, 200, 13, 99, 41, 3, 250, 18, 77, 121, 5]);
        let codes = census_transform(&img);
        let gray = |x: isize, y: isize| {
            let (x, y) = (x.clamp(0, 8) as usize, y.clamp(0, 7) as usize);
            img.data()[(y * 9 + x) * 3..][..3].iter().sum::<f32>() / 3.0
        };
        for y in 0..8isize {
            for x in 0..9isize {
                let mut k = 0;
                for dy in -3..=3isize {
                    for dx in -3..=3isize {
                        if dx == 0 && dy == 0 {
                            continue;
                        }
                        let bit = codes.codes()[(y * 9 + x) as usize] >> k & 1 == 1;
                        assert_eq!(bit, gray(x + dx, y + dy) < gray(x, y), "({x},{y}) bit {k}");
                        k += 1;
                    }
                }
            }
        }
        assert_eq!(CENSUS_BITS, 48);
    }

    /// A source that is the reference shifted by 3 px (a rectified pair): the term is 0 on the
    /// plane of that disparity wherever the shifted window stays inside the image, the weight
    /// where no source sees the voxel, and divided by the contrast weights.
    #[test]
    fn the_true_plane_of_a_shifted_pair_costs_nothing() {
        let (w, h) = (40usize, 12usize);
        let seed: Vec<u8> = (0..255u8)
            .map(|i| i.wrapping_mul(97).wrapping_add(31))
            .collect();
        let reference = levels(w, h, 1, &seed);
        // Source pixel x shows reference pixel x + 3: a camera 1 unit to the right at depth f·1/3.
        let mut src = vec![0.0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                src[y * w + x] = reference.data()[y * w + (x + 3).min(w - 1)];
            }
        }
        let source = ImageF32::from_vec(w, h, 1, src).unwrap();
        let k = Intrinsics {
            fx: 30.0,
            fy: 30.0,
            cx: 20.0,
            cy: 6.0,
            skew: 0.0,
        };
        let relative = Pose::translation_only([-1.0, 0.0, 0.0]).unwrap();
        // Disparity f·b/z: planes at z = 30/d for d = 1..=5 (the set is uniform in 1/z).
        let planes = PlaneSet::new(6.0, 30.0, 5).unwrap();
        let true_plane = (0..5)
            .position(|i| (planes.depth(i as f64) - 10.0).abs() < 1e-6)
            .unwrap();
        let (rc, sc) = (census_transform(&reference), census_transform(&source));
        let sources = [CensusSource {
            census: &sc,
            intrinsics: k,
            relative,
        }];
        let mut volume = vec![0.0f32; w * h * 5];
        let weights = vec![2.0f32; w * h];
        add_census_costs(
            &mut volume,
            &rc,
            &k,
            &sources,
            &planes,
            0..h,
            1.5,
            &weights,
            &Monitor::noop(),
        )
        .unwrap();
        for y in 0..h {
            for x in 0..w {
                let v = |i: usize| volume[(i * h + y) * w + x];
                if (6..w - 6).contains(&x) && (3..h - 3).contains(&y) {
                    assert_eq!(v(true_plane), 0.0, "({x},{y})");
                }
                // x − 3 < 0: no source pixel on the true plane; the weight, halved.
                if x < 3 {
                    assert_eq!(v(true_plane), 0.75, "({x},{y})");
                }
                for i in 0..5 {
                    assert!((0.0..=0.75).contains(&v(i)));
                }
            }
        }
    }
}
