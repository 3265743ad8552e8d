//! The forward scatter from outside the kernel support: Eq. 4.49–4.50's constant term, and a
//! per-pixel version of it.
//!
//! Eq. 4.49 models every entry outside the support S(p) as one ε, and Eq. 4.50 then drops
//! Σ_{q∈S(p)} ε L_s(q): L'(p) ≈ Σ_{q∈S(p)} K_pq L_s(q) + C with C = ε Σ_q L_s(q). The
//! reference takes ε as the smallest in-support entry (Eq. 4.53) and notes that "the plausible
//! value of ε might be obtained if we compute all the elements of K; however, it requires a
//! large amount of computation". The truncated part is not constant over the object: a pixel
//! at the centre of a large object has more of it outside its window than one near the
//! silhouette, and K_pq is proportional to the facet area dA_q (Eq. 4.44), which grows towards
//! the silhouette. With an 81-px support on a 225-px sphere this is murk's largest error
//! (docs/ACCURACY.md).
//!
//! [`FarField::PerPixel`] keeps Eq. 4.52's structure — one extra unknown shared by all
//! pixels — but models the outside entries as K_pq ≈ κ_p·dA_q:
//!
//! Σ_{q∉S(p)} K_pq L_s(q) ≈ κ_p (T − Σ_{q∈S(p)} dA_q L_s(q)),  T = Σ_q dA_q L_s(q),
//!
//! with κ_p = Σ_{q∉S(p)} K_pq / Σ_{q∉S(p)} dA_q, the facet-area-weighted mean of K/dA outside
//! the support, computed once per kernel build on coarse cells ([`outside_support_kappa`]).
//! Unlike Eq. 4.50 nothing is dropped: the in-support part of the sum is subtracted from the
//! stored entries, so the model is exact when L_s is uniform outside S(p), and it vanishes
//! when the support covers the object.

use rayon::prelude::*;

use super::forward_kernel::{k_entry_fast, Physics, Pre};
use super::KernelLayout;
use crate::monitor::Monitor;

/// How the forward scatter from outside the support S(p) enters the system of Eq. 4.52.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum FarField {
    /// The reference: one constant C = ε Σ_q L_s(q) with ε from Eq. 4.53.
    ConstantEpsilon,
    /// κ_p (T − Σ_{q∈S(p)} dA_q L_s(q)) per pixel, with T = Σ_q dA_q L_s(q) (module docs).
    #[default]
    PerPixel,
}

/// Largest side of the coarse cells that sum the outside of the support, pixels.
const OUTER_CELL_PX: usize = 9;

/// The coarse cells are at most 1/`OUTER_CELLS_ACROSS` of the object's extent: K_pq depends on
/// q's tangent plane (Eq. 4.45), so a cell's mean geometry only stands in for its pixels while
/// the normal barely turns across it. On a 62×55-px sphere 9-px cells put κ 9 % off; at
/// 300×300 (a 225-px sphere) the bound is 9 px.
const OUTER_CELLS_ACROSS: usize = 24;

/// Side of the coarse outside cells in s-cells for an object whose mask spans `extent_px`.
fn outer_cell_multiple(extent_px: usize, s: usize) -> usize {
    let target = (extent_px / OUTER_CELLS_ACROSS).clamp(1, OUTER_CELL_PX);
    (target as f64 / s as f64).round().max(1.0) as usize
}

/// The larger side of the bounding box of `mask`, pixels (0 when empty).
fn mask_extent(mask: &[bool], w: usize) -> usize {
    let (mut x0, mut x1, mut y0, mut y1) = (usize::MAX, 0, usize::MAX, 0);
    for (i, _) in mask.iter().enumerate().filter(|(_, &m)| m) {
        let (x, y) = (i % w, i / w);
        (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
    }
    if x0 == usize::MAX {
        0
    } else {
        (x1 - x0 + 1).max(y1 - y0 + 1)
    }
}

/// Cells of `c`×`c` pixels with their masked pixels' mean geometry, as a [`Pre`] whose facet
/// area is the cell's *total* dA (K_pq is linear in dA_q, so one evaluation gives the cell's
/// Σ_q K_pq at the mean geometry). Cells without masked pixels are `None`.
fn aggregate(
    pre: &[Pre],
    mask: &[bool],
    (w, h): (usize, usize),
    c: usize,
    sigma: f64,
) -> Vec<Option<Pre>> {
    let (cw, ch) = (w.div_ceil(c), h.div_ceil(c));
    (0..cw * ch)
        .into_par_iter()
        .map(|i| {
            let (cx, cy) = (i % cw, i / cw);
            let (mut pt, mut nn, mut da, mut count) = ([0.0f64; 3], [0.0f64; 3], 0.0, 0usize);
            for y in cy * c..((cy + 1) * c).min(h) {
                for x in cx * c..((cx + 1) * c).min(w) {
                    let q = &pre[y * w + x];
                    if !mask[y * w + x] {
                        continue;
                    }
                    for k in 0..3 {
                        pt[k] += q.ray[k] * q.d;
                        nn[k] += q.n[k];
                    }
                    da += q.da;
                    count += 1;
                }
            }
            (count > 0).then(|| Pre::mean(pt, nn, count, da, sigma))
        })
        .collect()
}

/// κ_p of [`FarField::PerPixel`] for every pixel (0 at unmasked pixels and where nothing masked
/// lies outside the support), per mm² of facet area.
///
/// With `layout`'s cell size s and support radius K in cells, every pixel of the s×s cell (cx, cy) has the support {cells within Chebyshev distance
/// K}, so κ is computed once per cell, with p at the cell's mean geometry (K_pq
/// depends on p only through its ray and distance, which barely change across a cell seen from
/// outside the support). The outside is summed over coarse cells of about
/// [`OUTER_CELL_PX`] pixels or 1/[`OUTER_CELLS_ACROSS`] of the object, whichever is smaller
/// (a whole number of s-cells), at their mean geometry, like the far
/// window of [`super::KernelLayout`]; coarse cells that straddle the support's edge are split
/// into their s-cells. Cost: about (object area / 81 px²) + 4·(r/9 + 2)·(9/s)² evaluations
/// per s-cell.
pub(super) fn outside_support_kappa(
    ph: &Physics,
    pre: &[Pre],
    mask: &[bool],
    (w, h): (usize, usize),
    layout: &KernelLayout,
    monitor: &Monitor,
) -> Vec<f64> {
    let sigma = ph.sigma;
    let s = layout.cell().max(1);
    let half_cells = layout.far_cells();
    let m = outer_cell_multiple(mask_extent(mask, w), s);
    let fine = aggregate(pre, mask, (w, h), s, sigma);
    let outer = aggregate(pre, mask, (w, h), s * m, sigma);
    let (fw, fh) = (w.div_ceil(s), h.div_ceil(s));
    let (ow, oh) = (w.div_ceil(s * m), h.div_ceil(s * m));
    let hw = half_cells as isize;
    let occupied: Vec<usize> = (0..ow * oh).filter(|&i| outer[i].is_some()).collect();
    let kappa_cell: Vec<f64> = (0..fw * fh)
        .into_par_iter()
        .map(|c| {
            // A cancelled build discards κ; stop spending time on it.
            if monitor.is_cancelled() {
                return 0.0;
            }
            let Some(p) = fine[c] else { return 0.0 };
            let (pcx, pcy) = ((c % fw) as isize, (c / fw) as isize);
            let (x0, x1, y0, y1) = (pcx - hw, pcx + hw, pcy - hw, pcy + hw);
            let (mut num, mut den) = (0.0f64, 0.0f64);
            for &o in &occupied {
                let q = outer[o].as_ref().expect("occupied");
                let (ox0, oy0) = (((o % ow) * m) as isize, ((o / ow) * m) as isize);
                let (ox1, oy1) = (ox0 + m as isize - 1, oy0 + m as isize - 1);
                if ox1 < x0 || ox0 > x1 || oy1 < y0 || oy0 > y1 {
                    num += k_entry_fast(ph, &p, q);
                    den += q.da;
                    continue;
                }
                if ox0 >= x0 && ox1 <= x1 && oy0 >= y0 && oy1 <= y1 {
                    continue;
                }
                for fy in oy0..=oy1.min(fh as isize - 1) {
                    for fx in ox0..=ox1.min(fw as isize - 1) {
                        if (x0..=x1).contains(&fx) && (y0..=y1).contains(&fy) {
                            continue;
                        }
                        if let Some(q) = &fine[fy as usize * fw + fx as usize] {
                            num += k_entry_fast(ph, &p, q);
                            den += q.da;
                        }
                    }
                }
            }
            if den > 0.0 {
                num / den
            } else {
                0.0
            }
        })
        .collect();
    (0..w * h)
        .map(|i| {
            if mask[i] {
                kappa_cell[(i / w / s) * fw + (i % w) / s]
            } else {
                0.0
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::super::forward_kernel::tests::{medium, sphere};
    use super::super::{FTable, ForwardKernel, KernelLayout};
    use super::*;

    /// What a kernel predicts for L'(p) = Σ_q K_pq L_s(q): its rows applied to `ls` with the
    /// extra unknown at the value the last row implies, or at 0 (`far` false: a kernel whose
    /// support covers the object is the whole sum by itself).
    fn predict(kernel: &ForwardKernel, ls: &[f64], far: bool) -> Vec<f64> {
        let n = ls.len();
        let mut x = ls.to_vec();
        x.push(if far { kernel.constant_for(ls) } else { 0.0 });
        let mut y = vec![0.0; n + 1];
        kernel.apply(&x, &mut y);
        y.truncate(n);
        y
    }

    /// Mean relative error of the forward-scatter part (y − diagonal·x) against `truth`.
    fn scatter_error(kernel: &ForwardKernel, ls: &[f64], y: &[f64], truth: &[f64]) -> f64 {
        let (mut err, mut total) = (0.0, 0.0);
        for k in 0..ls.len() {
            let d = f64::from(kernel.diagonal()[k]) * ls[k];
            err += ((y[k] - d) - (truth[k] - d)).abs();
            total += truth[k] - d;
        }
        err / total
    }

    /// A support of 21 px on a sphere of ~70 px: against the whole-image kernel, the per-pixel
    /// far field predicts the forward scatter several times better than Eq. 4.52's constant ε,
    /// for uniform, shading-like and textured L_s, with the exact window and with far cells.
    #[test]
    fn per_pixel_far_field_predicts_the_truncated_scatter() {
        let ft = FTable::global();
        let m = medium();
        let (w, h) = (62, 55);
        let g = sphere(w, h, 70.0, 300.0, 110.0);
        let truth_kernel = ForwardKernel::build(ft, &m, &g, 125).unwrap();
        let n = truth_kernel.masked_count();
        for layout in [
            KernelLayout::exact(21).unwrap(),
            KernelLayout::coarse_far(21, 3, 5).unwrap(),
        ] {
            let eps =
                ForwardKernel::build_with(ft, &m, &g, &layout, FarField::ConstantEpsilon).unwrap();
            let per = ForwardKernel::build_with(ft, &m, &g, &layout, FarField::PerPixel).unwrap();
            for freq in [0.0, 0.05, 0.2] {
                let ls: Vec<f64> = (0..n)
                    .map(|k| {
                        let p = truth_kernel.pixel_index(k);
                        let (u, v) = ((p % w) as f64, (p / w) as f64);
                        1.0 + 0.3 * (u * freq).sin() * (v * 0.75 * freq).cos()
                    })
                    .collect();
                let truth = predict(&truth_kernel, &ls, false);
                let e_eps = scatter_error(&eps, &ls, &predict(&eps, &ls, true), &truth);
                let e_per = scatter_error(&per, &ls, &predict(&per, &ls, true), &truth);
                eprintln!(
                    "cell {} frequency {freq}: constant ε {e_eps:.3e}, per pixel {e_per:.3e}",
                    layout.cell()
                );
                assert!(e_per < 0.05, "per-pixel far field: {e_per}");
                assert!(
                    e_per < 0.25 * e_eps,
                    "per pixel {e_per} vs constant ε {e_eps}"
                );
            }
        }
    }

    /// When the support covers the object nothing lies outside it: κ = 0, the stored entries
    /// are the plain K̂ and the extra unknown is decoupled.
    #[test]
    fn far_field_vanishes_when_the_support_covers_the_object() {
        let ft = FTable::global();
        let m = medium();
        let g = sphere(30, 26, 35.0, 300.0, 110.0);
        let layout = KernelLayout::exact(61).unwrap();
        let eps =
            ForwardKernel::build_with(ft, &m, &g, &layout, FarField::ConstantEpsilon).unwrap();
        let per = ForwardKernel::build_with(ft, &m, &g, &layout, FarField::PerPixel).unwrap();
        let n = per.masked_count();
        for k in 0..n {
            assert_eq!(per.window(k), eps.window(k));
            assert_eq!(per.far_coefficient(k), 0.0);
        }
        let ls = vec![1.0; n];
        assert_eq!(per.constant_for(&ls), 0.0);
    }
}
