//! Plane-sweep cost volumes (reference §3.2.2): the ordinary volume of Eq. 3.1 and the dehazing
//! volume of Eq. 3.7.
//!
//! For every plane `z_i` of a [`PlaneSet`] and reference pixel `(u, v)`, each source view is
//! sampled bilinearly at `π_{r→s}(u, v; z_i)` and compared with the reference pixel by the L1
//! distance **summed** over channels (`Σ_c |·|`, as the reference code does; the maximum for
//! values in `[0, 1]` is therefore `C`, 3 for RGB):
//!
//! - **ordinary** (Eq. 3.1): `Σ_c |I_r − I_s|`;
//! - **dehazing** (Eq. 3.4–3.7): both samples are dehazed first, the reference with `z_i`
//!   (Eq. 3.5) and the source with `ζ`, the plane point's depth seen from the source camera
//!   (Eq. 3.6); the cost is `Σ_c |J_r − J_s|`, or the penalty `γ` when any channel of `J_r` or
//!   `J_s` leaves `[0, 1]` (Eq. 3.7). Transmission is floored at
//!   [`crate::atmosphere::MIN_TRANSMISSION`].
//!
//! `γ = C` (= 3 for RGB, the reference's value): the largest cost the ordinary volume can take.
//!
//! **Samples outside a source image** (outside the hull of its pixel centres, or with the plane
//! point behind the source camera) are unobserved: they are left out of the average over source
//! views, so a voxel is the mean over the `S' ≤ S` sources that see it. A voxel no source sees
//! gets the constant `γ`: an unverifiable depth hypothesis should never beat a verified one, and
//! a pixel that no source sees at any plane gets a flat curve that carries no preference.
//!
//! Layout: `f32`, `[plane][y][x]`, plane 0 the farthest (see [`PlaneSet`]). Computation: one pass
//! per plane (cancellation checkpoint between planes), rows in parallel with rayon; row buffers
//! are per worker and reused, so nothing is allocated per voxel or per row.

mod kernel;
pub mod sample;

use rayon::prelude::*;

use crate::atmosphere::{inverse_transmission, transmission, AtmosphereParams};
use crate::camera::Intrinsics;
use crate::error::{MurkError, Result};
use crate::image::ImageF32;
use crate::monitor::Monitor;
use crate::mvs::plane_sweep::{PlaneSet, PlaneWarp};
use crate::mvs::pose::Pose;

use kernel::{fill_row, Haze, RowScratch, SourcePlane};

/// Largest accepted volume, in voxels (`W·H·N`): 2²⁹ `f32`s are 2 GiB.
pub const MAX_VOXELS: usize = 1 << 29;

/// A calibrated view: image (1 or 3 channels, values nominally in `[0, 1]`), pinhole intrinsics
/// (murk pixel convention) and world-to-camera pose (scene units).
#[derive(Clone, Copy, Debug)]
pub struct View<'a> {
    /// The image.
    pub image: &'a ImageF32,
    /// Pinhole intrinsics, pixels.
    pub intrinsics: Intrinsics,
    /// World-to-camera pose.
    pub pose: Pose,
}

/// Which photometric cost to build.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum CostKind {
    /// Eq. 3.1 on the observed (hazy) images.
    Ordinary,
    /// Eq. 3.7: dehaze with the plane hypothesis and the given airlight and `β` (per scene unit).
    Dehazing(AtmosphereParams),
}

/// A plane-sweep cost volume, `f32`, `[plane][y][x]`.
#[derive(Clone, Debug, PartialEq)]
pub struct CostVolume {
    width: usize,
    height: usize,
    planes: PlaneSet,
    penalty: f32,
    data: Vec<f32>,
}

impl CostVolume {
    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }
    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }
    /// The planes swept.
    pub fn planes(&self) -> &PlaneSet {
        &self.planes
    }
    /// Number of planes.
    pub fn num_planes(&self) -> usize {
        self.planes.num_planes
    }
    /// `γ`: the dehazing penalty and the cost of unobserved voxels (= number of channels).
    pub fn penalty(&self) -> f32 {
        self.penalty
    }
    /// All costs, `[plane][y][x]`.
    pub fn data(&self) -> &[f32] {
        &self.data
    }
    /// Consumes the volume, returning its costs.
    pub fn into_vec(self) -> Vec<f32> {
        self.data
    }
    /// Costs of plane `i`, row-major `W·H`.
    pub fn plane(&self, i: usize) -> &[f32] {
        let n = self.width * self.height;
        &self.data[i * n..(i + 1) * n]
    }
    /// Cost of pixel `(x, y)` on plane `i`.
    #[inline]
    pub fn cost(&self, x: usize, y: usize, i: usize) -> f32 {
        self.data[(i * self.height + y) * self.width + x]
    }
    /// Per-pixel winner-take-all plane index without any aggregation (lowest index on ties),
    /// row-major `W·H`. A baseline and a test aid; regularised depth comes from aggregation.
    pub fn argmin_planes(&self) -> Vec<usize> {
        let n = self.width * self.height;
        let mut best = vec![0usize; n];
        let mut best_cost = self.plane(0).to_vec();
        for i in 1..self.num_planes() {
            for ((b, bc), &c) in best.iter_mut().zip(&mut best_cost).zip(self.plane(i)) {
                if c < *bc {
                    *bc = c;
                    *b = i;
                }
            }
        }
        best
    }
}

fn check_view(view: &View<'_>, channels: Option<(usize, usize, usize)>) -> Result<()> {
    let img = view.image;
    if let Some((w, h, c)) = channels {
        if img.dims() != (w, h) || img.channels() != c {
            return Err(MurkError::invalid(
                "image",
                format!(
                    "image is {}x{}x{} but the reference is {w}x{h}x{c}",
                    img.width(),
                    img.height(),
                    img.channels()
                ),
            ));
        }
    } else {
        if img.channels() != 1 && img.channels() != 3 {
            return Err(MurkError::invalid(
                "image",
                format!("need 1 or 3 channels, got {}", img.channels()),
            ));
        }
        if img.width() < 2 || img.height() < 2 {
            return Err(MurkError::invalid(
                "image",
                format!(
                    "need at least 2x2 pixels, got {}x{}",
                    img.width(),
                    img.height()
                ),
            ));
        }
    }
    img.ensure_finite().map_err(|e| e.within("image"))?;
    view.intrinsics
        .validate()
        .map_err(|e| e.within("intrinsics"))?;
    view.pose.validate().map_err(|e| e.within("pose"))
}

/// Builds the ordinary (Eq. 3.1) or dehazing (Eq. 3.7) cost volume of `reference` against
/// `sources` (at least one) over `planes`; see the module docs for the cost, the penalty and
/// the rule for unobserved samples.
///
/// Errors (`InvalidArgument`) name `reference.…`, `sources`, `sources[k].…`, `planes.…`,
/// `atmosphere.…`; cancellation through `monitor` returns `Cancelled`.
pub fn build_cost_volume(
    reference: &View<'_>,
    sources: &[View<'_>],
    planes: &PlaneSet,
    kind: CostKind,
    monitor: &Monitor,
) -> Result<CostVolume> {
    check_view(reference, None).map_err(|e| e.within("reference"))?;
    if sources.is_empty() {
        return Err(MurkError::invalid(
            "sources",
            "need at least one source view",
        ));
    }
    let (w, h, c) = (
        reference.image.width(),
        reference.image.height(),
        reference.image.channels(),
    );
    for (k, s) in sources.iter().enumerate() {
        check_view(s, Some((w, h, c))).map_err(|e| e.within(&format!("sources[{k}]")))?;
    }
    planes.validate().map_err(|e| e.within("planes"))?;
    if let CostKind::Dehazing(p) = kind {
        p.validate().map_err(|e| e.within("atmosphere"))?;
    }
    let n_pix = w * h;
    let n_planes = planes.num_planes;
    let voxels = n_pix
        .checked_mul(n_planes)
        .filter(|&v| v <= MAX_VOXELS)
        .ok_or_else(|| {
            MurkError::invalid(
                "planes.num_planes",
                format!(
                    "{w}x{h} pixels x {n_planes} planes exceeds the limit of {MAX_VOXELS} voxels"
                ),
            )
        })?;

    let relatives: Vec<Pose> = sources
        .iter()
        .map(|s| Pose::relative(&reference.pose, &s.pose))
        .collect();
    let penalty = c as f32;
    let mut data = vec![0.0f32; voxels];
    // Reused across planes so the loop allocates nothing per plane.
    let mut plane_sources: Vec<SourcePlane<'_>> = Vec::with_capacity(sources.len());
    for (i, out) in data.chunks_exact_mut(n_pix).enumerate() {
        monitor.checkpoint()?;
        let z = planes.depth(i as f64);
        plane_sources.clear();
        plane_sources.extend(sources.iter().zip(&relatives).map(|(s, rel)| SourcePlane {
            data: s.image.data(),
            warp: PlaneWarp::new(&reference.intrinsics, &s.intrinsics, rel, z),
        }));
        let haze = match kind {
            CostKind::Ordinary => Haze {
                airlight: 0.0,
                beta: 0.0,
                ref_inv_t: 1.0,
                ref_offset: 0.0,
            },
            CostKind::Dehazing(p) => {
                let inv_t = inverse_transmission(transmission(p.beta, z as f32));
                Haze {
                    airlight: p.airlight,
                    beta: p.beta,
                    ref_inv_t: inv_t,
                    ref_offset: p.airlight * (1.0 - inv_t),
                }
            }
        };
        let refd = reference.image.data();
        let srcs = &plane_sources[..];
        let dehaze = matches!(kind, CostKind::Dehazing(_));
        out.par_chunks_mut(w).enumerate().for_each_init(
            RowScratch::default,
            |scratch, (y, row)| match (c, dehaze) {
                (1, false) => {
                    fill_row::<1, false>(row, y, refd, w, h, srcs, haze, penalty, scratch)
                }
                (1, true) => fill_row::<1, true>(row, y, refd, w, h, srcs, haze, penalty, scratch),
                (_, false) => {
                    fill_row::<3, false>(row, y, refd, w, h, srcs, haze, penalty, scratch)
                }
                (_, true) => fill_row::<3, true>(row, y, refd, w, h, srcs, haze, penalty, scratch),
            },
        );
        monitor.progress("mvs.cost_volume", (i + 1) as f32 / n_planes as f32);
    }
    Ok(CostVolume {
        width: w,
        height: h,
        planes: *planes,
        penalty,
        data,
    })
}

#[cfg(test)]
mod tests;
