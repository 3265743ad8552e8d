//! The per-row inner loop shared by the ordinary (Eq. 3.1) and dehazing (Eq. 3.7) cost volumes.
//! One generic body keeps the two volumes' arithmetic identical, so with `β = 0` (where
//! dehazing is the identity) they agree bit for bit.

use super::sample::bilinear;
use crate::atmosphere::{inverse_transmission, transmission};
use crate::mvs::plane_sweep::PlaneWarp;

/// One source view for one plane: its samples and the plane's reference→source warp.
pub(super) struct SourcePlane<'a> {
    pub data: &'a [f32],
    pub warp: PlaneWarp,
}

/// Per-plane constants of the dehazing volume: the reference is dehazed with the plane's own
/// depth `z_i` (Eq. 3.5), so `J_r = I_r·inv_t + offset` with both constant over the plane.
#[derive(Clone, Copy)]
pub(super) struct Haze {
    pub airlight: f32,
    pub beta: f32,
    pub ref_inv_t: f32,
    pub ref_offset: f32,
}

/// Per-worker row buffers, reused across rows so the sweep allocates nothing per voxel or row.
#[derive(Default)]
pub(super) struct RowScratch {
    /// Dehazed (or plain) reference row, interleaved.
    jr: Vec<f32>,
    /// Whether every channel of the reference pixel is in `[0, 1]` (Eq. 3.7).
    ref_ok: Vec<bool>,
    /// Sum of per-source costs.
    sum: Vec<f32>,
    /// Number of sources that observe the voxel.
    observed: Vec<u32>,
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
    scratch.jr.clear();
    scratch.ref_ok.clear();
    for ir in row.chunks_exact(C) {
        let mut ok = true;
        for &v in ir {
            let j = if DEHAZE {
                v * haze.ref_inv_t + haze.ref_offset
            } else {
                v
            };
            ok &= (0.0..=1.0).contains(&j);
            scratch.jr.push(j);
        }
        scratch.ref_ok.push(ok);
    }
    scratch.sum.clear();
    scratch.sum.resize(width, 0.0);
    scratch.observed.clear();
    scratch.observed.resize(width, 0);

    for s in sources {
        let warp = s.warp.row(y as f64);
        let pixels = scratch
            .sum
            .iter_mut()
            .zip(scratch.observed.iter_mut())
            .zip(scratch.jr.chunks_exact(C).zip(&scratch.ref_ok));
        for (x, ((sum, observed), (jr, &ref_ok))) in pixels.enumerate() {
            let (us, vs, zeta) = warp.map(x as f64);
            // ζ ≤ 0 (or NaN): the plane point is behind the source camera.
            if zeta.is_nan() || zeta <= 0.0 {
                continue;
            }
            let Some(is) = bilinear::<C>(s.data, width, height, us, vs) else {
                continue;
            };
            *observed += 1;
            if DEHAZE && !ref_ok {
                *sum += penalty;
                continue;
            }
            let (inv_t, offset) = if DEHAZE {
                // Eq. 3.6: the source sample is dehazed with the plane point's depth ζ as seen
                // from the source camera, not with z_i.
                let inv_t = inverse_transmission(transmission(haze.beta, zeta as f32));
                (inv_t, haze.airlight * (1.0 - inv_t))
            } else {
                (1.0, 0.0)
            };
            let mut cost = 0.0f32;
            let mut src_ok = true;
            for c in 0..C {
                let js = if DEHAZE {
                    is[c] * inv_t + offset
                } else {
                    is[c]
                };
                src_ok &= (0.0..=1.0).contains(&js);
                cost += (jr[c] - js).abs();
            }
            *sum += if DEHAZE && !src_ok { penalty } else { cost };
        }
    }

    for ((o, &sum), &n) in out.iter_mut().zip(&scratch.sum).zip(&scratch.observed) {
        *o = if n == 0 { penalty } else { sum / n as f32 };
    }
}
