//! The forward scatter from outside the kernel support: Eq. 4.49–4.50's constant term, a
//! per-pixel version of it, and the outside summed on coarse blocks.
//!
//! Eq. 4.49 models every entry outside the support S(p) as one ε, and Eq. 4.50 then drops
//! Σ_{q∈S(p)} ε L_s(q): L'(p) ≈ Σ_{q∈S(p)} K_pq L_s(q) + C with C = ε Σ_q L_s(q). The
//! reference takes ε as the smallest in-support entry (Eq. 4.53) and notes that "the plausible
//! value of ε might be obtained if we compute all the elements of K; however, it requires a
//! large amount of computation". The truncated part is not constant over the object: a pixel
//! at the centre of a large object has more of it outside its window than one near the
//! silhouette, and K_pq is proportional to the facet area dA_q (Eq. 4.44), which grows towards
//! the silhouette. With an 81-px support on a 225-px sphere it is the constant-ε model's largest
//! error (docs/accuracy.md).
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
//!
//! But L_s is not uniform: near lights shade the object strongly, and the error of assuming
//! so, 0.9 % of L_s on the vase at r = 81, is what the distance fit reads as a 3 % longer
//! distance. [`FarField::Blocks`], the default, therefore makes no assumption on L_s. The
//! coarse cells that κ_p is averaged over are kept, one K per unit facet area from each s-cell
//! of p to each of them ([`OutsideBlocks`]), and the operator sums them against each cell's
//! Σ_q dA_q L_s(q) (Eq. 4.42 with Eq. 4.44's dA_q factored out). That is the layout's far
//! window carried over the whole object at a coarser step, and it needs no extra unknown.

use nalgebra::Vector3;
use rayon::prelude::*;

use super::kernel_entry::{k_entry_fast, Physics, Pre};
use super::KernelLayout;
use crate::monitor::Monitor;

/// How the forward scatter from outside the support S(p) enters the system of Eq. 4.52.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum FarField {
    /// The reference: one constant C = ε Σ_q L_s(q) with ε from Eq. 4.53.
    ConstantEpsilon,
    /// κ_p (T − Σ_{q∈S(p)} dA_q L_s(q)) per pixel, with T = Σ_q dA_q L_s(q) (module docs):
    /// exact when L_s is uniform outside the support.
    PerPixel,
    /// No model: the outside of S(p) is summed inside the operator on coarse blocks
    /// ([`OutsideBlocks`]), K at each block's mean geometry times the block's Σ_q dA_q L_s(q),
    /// so the far field follows L_s whatever it is. No extra unknown. The default.
    #[default]
    Blocks,
}

impl FarField {
    /// Number of extra unknowns the model adds to the augmented system of Eq. 4.52.
    pub fn unknowns(self) -> usize {
        match self {
            FarField::ConstantEpsilon | FarField::PerPixel => 1,
            FarField::Blocks => 0,
        }
    }
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
            let (mut pt, mut nn, mut da, mut count) =
                (Vector3::zeros(), Vector3::zeros(), 0.0, 0usize);
            for y in cy * c..((cy + 1) * c).min(h) {
                for x in cx * c..((cx + 1) * c).min(w) {
                    let q = &pre[y * w + x];
                    if !mask[y * w + x] {
                        continue;
                    }
                    pt += q.ray * q.d;
                    nn += q.n;
                    da += q.da;
                    count += 1;
                }
            }
            (count > 0).then(|| Pre::mean(pt, nn, count, da, sigma))
        })
        .collect()
}

/// κ_p of [`FarField::PerPixel`] for every pixel (0 at unmasked pixels and where nothing masked
/// lies outside the support), per mm² of facet area: Σ K / Σ dA over the pieces of the outside
/// of p's support ([`OutsideGrid`]), with p at its s-cell's mean geometry (K_pq depends on p
/// only through its ray and distance, which barely change across a cell seen from outside the
/// support). Cost: about (object area / 81 px²) + 4·(r/9 + 2)·(9/s)² evaluations per s-cell.
pub(super) fn outside_support_kappa(
    ph: &Physics,
    pre: &[Pre],
    mask: &[bool],
    (w, h): (usize, usize),
    layout: &KernelLayout,
    monitor: &Monitor,
) -> Vec<f64> {
    let grid = OutsideGrid::new(pre, mask, (w, h), layout, ph.sigma);
    let kappa_cell: Vec<f64> = (0..grid.fw * grid.fh)
        .into_par_iter()
        .map(|c| {
            // A cancelled build discards κ; stop spending time on it.
            if monitor.is_cancelled() {
                return 0.0;
            }
            let Some(p) = grid.fine[c] else { return 0.0 };
            let (mut num, mut den) = (0.0f64, 0.0f64);
            grid.for_each_outside(c, |q, _| {
                num += k_entry_fast(ph, &p, q);
                den += q.da;
            });
            if den > 0.0 {
                num / den
            } else {
                0.0
            }
        })
        .collect();
    let (s, fw) = (grid.s, grid.fw);
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

/// The two grids that partition the outside of every support: the s-cells of `layout` (p's
/// grid, and the pieces of straddling outer cells) and the outer cells of m×m s-cells.
struct OutsideGrid {
    s: usize,
    m: usize,
    fw: usize,
    fh: usize,
    ow: usize,
    half_cells: isize,
    fine: Vec<Option<Pre>>,
    outer: Vec<Option<Pre>>,
    occupied: Vec<usize>,
}

impl OutsideGrid {
    fn new(
        pre: &[Pre],
        mask: &[bool],
        (w, h): (usize, usize),
        layout: &KernelLayout,
        sigma: f64,
    ) -> OutsideGrid {
        let s = layout.cell().max(1);
        let m = outer_cell_multiple(mask_extent(mask, w), s);
        let fine = aggregate(pre, mask, (w, h), s, sigma);
        let outer = aggregate(pre, mask, (w, h), s * m, sigma);
        let (ow, oh) = (w.div_ceil(s * m), h.div_ceil(s * m));
        let occupied = (0..ow * oh).filter(|&i| outer[i].is_some()).collect();
        OutsideGrid {
            s,
            m,
            fw: w.div_ceil(s),
            fh: h.div_ceil(s),
            ow,
            half_cells: layout.far_cells() as isize,
            fine,
            outer,
            occupied,
        }
    }

    /// Calls `f` with the mean geometry and the source index of every occupied piece outside
    /// the support of s-cell `c`: every pixel of the s×s cell (cx, cy) has the support
    /// {s-cells within Chebyshev distance K}; outer cells wholly outside it come whole (source
    /// index o), those that straddle its edge as their occupied s-cells outside it (source
    /// index outer cells + s-cell index).
    fn for_each_outside(&self, c: usize, mut f: impl FnMut(&Pre, usize)) {
        let (m, hw) = (self.m as isize, self.half_cells);
        let (pcx, pcy) = ((c % self.fw) as isize, (c / self.fw) as isize);
        let (x0, x1, y0, y1) = (pcx - hw, pcx + hw, pcy - hw, pcy + hw);
        for &o in &self.occupied {
            let (ox0, oy0) = ((o % self.ow) as isize * m, (o / self.ow) as isize * m);
            let (ox1, oy1) = (ox0 + m - 1, oy0 + m - 1);
            if ox1 < x0 || ox0 > x1 || oy1 < y0 || oy0 > y1 {
                f(self.outer[o].as_ref().expect("occupied"), o);
                continue;
            }
            if ox0 >= x0 && ox1 <= x1 && oy0 >= y0 && oy1 <= y1 {
                continue;
            }
            for fy in oy0..=oy1.min(self.fh as isize - 1) {
                for fx in ox0..=ox1.min(self.fw as isize - 1) {
                    if (x0..=x1).contains(&fx) && (y0..=y1).contains(&fy) {
                        continue;
                    }
                    let i = fy as usize * self.fw + fx as usize;
                    if let Some(q) = &self.fine[i] {
                        f(q, self.outer.len() + i);
                    }
                }
            }
        }
    }
}

/// [`FarField::Blocks`]: for every s-cell of p, K per unit facet area from the cell's mean
/// geometry to every piece of the outside of its support ([`OutsideGrid`]: outer cells of
/// about [`OUTER_CELL_PX`] pixels, split into s-cells along the support's edge), so that
/// Σ_{q∉S(p)} K_pq L_s(q) ≈ Σ_B k_pB Σ_{q∈B} dA_q L_s(q) (K_pq is proportional to dA_q, Eq.
/// 4.44). This is the far window of [`super::KernelLayout`] carried over the whole object at a
/// coarser step: the quadrature the per-pixel models fit their coefficients on, kept instead of
/// reduced, so no assumption on L_s is made. About (object area / 81 px²) entries per s-cell
/// of p, a few per cent of the near kernel's.
#[derive(Clone, Debug)]
pub(super) struct OutsideBlocks {
    /// Side of the s-cells and of the outer cells, pixels.
    s: usize,
    outer_px: usize,
    /// Width of the s-cell and outer grids, and the outer grid's cell count.
    fw: usize,
    ow: usize,
    n_outer: usize,
    /// Entries of s-cell c are `start[c]..start[c + 1]`.
    start: Vec<u32>,
    /// Source of each entry: an outer cell o < n_outer, or n_outer + an s-cell index.
    source: Vec<u32>,
    /// K per mm² of the source's facet area.
    value: Vec<f32>,
}

impl OutsideBlocks {
    /// Builds the entries. Once `monitor` is cancelled the remaining cells are left empty: the
    /// caller checks the monitor and discards the result.
    pub(super) fn build(
        ph: &Physics,
        pre: &[Pre],
        mask: &[bool],
        (w, h): (usize, usize),
        layout: &KernelLayout,
        monitor: &Monitor,
    ) -> OutsideBlocks {
        let grid = OutsideGrid::new(pre, mask, (w, h), layout, ph.sigma);
        let rows: Vec<Vec<(u32, f32)>> = (0..grid.fw * grid.fh)
            .into_par_iter()
            .map(|c| {
                let mut row = Vec::new();
                if monitor.is_cancelled() {
                    return row;
                }
                let Some(p) = grid.fine[c] else {
                    return row;
                };
                grid.for_each_outside(c, |q, source| {
                    row.push((source as u32, (k_entry_fast(ph, &p, q) / q.da) as f32));
                });
                row
            })
            .collect();
        let mut start = Vec::with_capacity(rows.len() + 1);
        let total: usize = rows.iter().map(Vec::len).sum();
        let (mut source, mut value) = (Vec::with_capacity(total), Vec::with_capacity(total));
        for row in rows {
            start.push(source.len() as u32);
            for (i, v) in row {
                source.push(i);
                value.push(v);
            }
        }
        start.push(source.len() as u32);
        OutsideBlocks {
            s: grid.s,
            outer_px: grid.s * grid.m,
            fw: grid.fw,
            ow: grid.ow,
            n_outer: grid.outer.len(),
            start,
            source,
            value,
        }
    }

    /// Memory held, bytes.
    pub(super) fn bytes(&self) -> usize {
        self.start.len() * 4 + self.source.len() * 4 + self.value.len() * 4
    }

    /// Number of stored entries.
    pub(super) fn len(&self) -> usize {
        self.value.len()
    }

    /// Adds Σ_B k_pB Σ_{q∈B} dA_q x_q to `out[p·lanes + j]` for every masked pixel p (row-major
    /// index `masked[p]`) and each of `lanes` interleaved inputs `xs` in image layout (x at
    /// row-major pixel q is `xs[q·lanes + j]`), with `da[q]` the facet area of pixel q.
    pub(super) fn add_to(
        &self,
        masked: &[u32],
        da: &[f64],
        w: usize,
        xs: &[f64],
        lanes: usize,
        out: &mut [f64],
    ) {
        let n_outer = self.n_outer;
        let mut sums = vec![0.0f64; (n_outer + self.start.len() - 1) * lanes];
        for &qi in masked {
            let qi = qi as usize;
            let (x, y) = (qi % w, qi / w);
            let o = (y / self.outer_px) * self.ow + x / self.outer_px;
            let f = n_outer + (y / self.s) * self.fw + x / self.s;
            for j in 0..lanes {
                let v = da[qi] * xs[qi * lanes + j];
                sums[o * lanes + j] += v;
                sums[f * lanes + j] += v;
            }
        }
        let cells = self.start.len() - 1;
        let mut per_cell = vec![0.0f64; cells * lanes];
        per_cell
            .par_chunks_mut(lanes)
            .enumerate()
            .for_each(|(c, acc)| {
                let (a, b) = (self.start[c] as usize, self.start[c + 1] as usize);
                for (&src, &v) in self.source[a..b].iter().zip(&self.value[a..b]) {
                    let src = &sums[src as usize * lanes..(src as usize + 1) * lanes];
                    let v = f64::from(v);
                    for (a, x) in acc.iter_mut().zip(src) {
                        *a += v * x;
                    }
                }
            });
        for (p, &pi) in masked.iter().enumerate() {
            let pi = pi as usize;
            let c = (pi / w / self.s) * self.fw + (pi % w) / self.s;
            for j in 0..lanes {
                out[p * lanes + j] += per_cell[c * lanes + j];
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::forward_kernel::tests::{medium, sphere};
    use super::super::{FTable, ForwardKernel, KernelLayout, SurfaceGeometry};
    use super::*;

    /// What a kernel predicts for L'(p) = Σ_q K_pq L_s(q): its rows applied to `ls` with the
    /// extra unknown at the value the last row implies, or at 0 (`far` false: a kernel whose
    /// support covers the object is the whole sum by itself).
    fn predict(kernel: &ForwardKernel, ls: &[f64], far: bool) -> Vec<f64> {
        let n = ls.len();
        let mut x = ls.to_vec();
        if let Some(c) = kernel.constant_for(ls) {
            x.push(if far { c } else { 0.0 });
        }
        let mut y = vec![0.0; kernel.dim()];
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

    /// A sphere of ~70 px in a 62×55 image, and its whole-image kernel (r = 125 covers it).
    fn small_sphere() -> (SurfaceGeometry, ForwardKernel) {
        let g = sphere(62, 55, 70.0, 300.0, 110.0);
        let truth = ForwardKernel::build(FTable::global(), &medium(), &g, 125).unwrap();
        (g, truth)
    }

    /// A 21-px support, as the exact window and with 3×3 far cells.
    fn support_21_layouts() -> [KernelLayout; 2] {
        [
            KernelLayout::exact(21).unwrap(),
            KernelLayout::coarse_far(21, 3, 5).unwrap(),
        ]
    }

    /// A support of 21 px on a sphere of ~70 px: against the whole-image kernel, the per-pixel
    /// far field predicts the forward scatter several times better than Eq. 4.52's constant ε,
    /// for uniform, shading-like and textured L_s, with the exact window and with far cells;
    /// the blocks are never worse than the per-pixel model, which is exact for uniform L_s
    /// where the blocks are a quadrature.
    #[test]
    fn per_pixel_far_field_predicts_the_truncated_scatter() {
        let (ft, m) = (FTable::global(), medium());
        let (g, truth_kernel) = small_sphere();
        let (w, n) = (g.width, truth_kernel.masked_count());
        for layout in support_21_layouts() {
            let eps =
                ForwardKernel::build_with(ft, &m, &g, &layout, FarField::ConstantEpsilon).unwrap();
            let per = ForwardKernel::build_with(ft, &m, &g, &layout, FarField::PerPixel).unwrap();
            let blocks = ForwardKernel::build_with(ft, &m, &g, &layout, FarField::Blocks).unwrap();
            assert!(blocks.far_block_entries() > 0);
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
                let e_blocks = scatter_error(&blocks, &ls, &predict(&blocks, &ls, true), &truth);
                eprintln!(
                    "cell {} frequency {freq}: constant ε {e_eps:.3e}, per pixel {e_per:.3e}, \
                     blocks {e_blocks:.3e}",
                    layout.cell()
                );
                assert!(e_per < 0.05, "per-pixel far field: {e_per}");
                assert!(
                    e_per < 0.25 * e_eps,
                    "per pixel {e_per} vs constant ε {e_eps}"
                );
                assert!(
                    e_blocks <= 1.01 * e_per,
                    "blocks {e_blocks} vs per pixel {e_per}"
                );
            }
        }
    }

    /// What the blocks are for: L_s that varies strongly across the object, as near lights
    /// shade it (bright on one side, falling off, a shadowed band). The per-pixel model assumes
    /// the outside of each support is uniformly lit and is off by several per cent; the blocks
    /// sum the actual L_s and stay at their quadrature error.
    #[test]
    fn blocks_follow_an_unevenly_lit_object() {
        let (ft, m) = (FTable::global(), medium());
        let (g, truth_kernel) = small_sphere();
        let (w, h, n) = (g.width, g.height, truth_kernel.masked_count());
        let ls: Vec<f64> = (0..n)
            .map(|k| {
                let p = truth_kernel.pixel_index(k);
                let (u, v) = ((p % w) as f64 / w as f64, (p / w) as f64 / h as f64);
                let shade = 1.6 - 1.2 * u + 0.4 * u * u + 0.5 * v - 0.3 * u * v;
                if u > 0.8 {
                    0.1 * shade
                } else {
                    shade
                }
            })
            .collect();
        let truth = predict(&truth_kernel, &ls, false);
        for layout in support_21_layouts() {
            let per = ForwardKernel::build_with(ft, &m, &g, &layout, FarField::PerPixel).unwrap();
            let blocks = ForwardKernel::build_with(ft, &m, &g, &layout, FarField::Blocks).unwrap();
            assert_eq!((per.dim(), blocks.dim()), (n + 1, n));
            let e_per = scatter_error(&per, &ls, &predict(&per, &ls, true), &truth);
            let e_blocks = scatter_error(&blocks, &ls, &predict(&blocks, &ls, true), &truth);
            eprintln!(
                "cell {}: uneven L_s: per pixel {e_per:.3e}, blocks {e_blocks:.3e}",
                layout.cell()
            );
            assert!(e_blocks < 0.01, "blocks: {e_blocks}");
            assert!(
                e_blocks < 0.5 * e_per,
                "blocks {e_blocks} vs per pixel {e_per}"
            );
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
        for model in [FarField::PerPixel, FarField::Blocks] {
            let per = ForwardKernel::build_with(ft, &m, &g, &layout, model).unwrap();
            assert_eq!(per.far_block_entries(), 0);
            let n = per.masked_count();
            for k in 0..n {
                assert_eq!(per.window(k), eps.window(k));
                assert_eq!(per.far_coefficient(k), 0.0);
            }
            let ls = vec![1.0; n];
            assert_eq!(per.constant_for(&ls).unwrap_or(0.0), 0.0);
        }
    }
}
