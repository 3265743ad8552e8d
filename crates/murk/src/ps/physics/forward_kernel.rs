//! Surface-camera forward scatter (Eq. 4.41–4.46) and its truncated kernel with a constant
//! global term (Eq. 4.48–4.53): the kernel's layout, build and application. Each entry K_pq
//! is computed by [`mod@super::kernel_entry`], where the model's choices are documented.

use nalgebra::Vector3;
use rayon::prelude::*;

use super::f_table::FTable;
use super::facet_emission::FacetEmission;
use super::far_field::{outside_support_kappa, FarField, OutsideBlocks};
use super::kernel_batch::{k_entries_fast, PreLanes};
use super::kernel_entry::{k_entry, pixel_solid_angle, Physics, Pre};
use super::kernel_layout::KernelLayout;
use super::Medium;
use crate::camera::Intrinsics;
use crate::error::{MurkError, Result};
use crate::monitor::Monitor;

/// Chebyshev radius (pixels) within which [`dense_forward_scatter`] is always exact.
pub const DENSE_NEAR_RADIUS: usize = 32;

/// Per-pixel surface samples in the camera frame, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct SurfaceGeometry {
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
    /// Camera intrinsics (for the pixel solid angles).
    pub intrinsics: Intrinsics,
    /// Surface point seen by each pixel, mm, camera frame.
    pub points_mm: Vec<[f32; 3]>,
    /// Unit surface normal at each pixel, pointing towards the camera.
    pub normals: Vec<[f32; 3]>,
    /// Pixels on the object; only these take part in the kernel.
    pub mask: Vec<bool>,
    /// How each facet radiates toward the medium ([`FacetEmission`]).
    pub emission: FacetEmission,
}

impl SurfaceGeometry {
    /// Fails unless the sizes agree, the intrinsics are valid and every masked point is finite
    /// and in front of the camera with a finite normal.
    pub fn validate(&self) -> Result<()> {
        self.intrinsics
            .validate()
            .map_err(|e| e.within("intrinsics"))?;
        let n = self.width * self.height;
        if self.width == 0 || self.height == 0 {
            return Err(MurkError::invalid("width", "image must not be empty"));
        }
        for (name, len) in [
            ("points_mm", self.points_mm.len()),
            ("normals", self.normals.len()),
            ("mask", self.mask.len()),
        ] {
            if len != n {
                return Err(MurkError::invalid(
                    name,
                    format!("expected width·height = {n} entries, got {len}"),
                ));
            }
        }
        for (i, &m) in self.mask.iter().enumerate() {
            if !m {
                continue;
            }
            let p = self.points_mm[i];
            if !(p.iter().all(|v| v.is_finite()) && p[2] > 0.0) {
                return Err(MurkError::invalid(
                    "points_mm",
                    format!("masked pixel {i} has point {p:?} (must be finite with z > 0)"),
                ));
            }
            if !self.normals[i].iter().all(|v| v.is_finite()) {
                return Err(MurkError::invalid(
                    "normals",
                    format!("masked pixel {i} has a non-finite normal"),
                ));
            }
        }
        Ok(())
    }
}

fn f3(v: [f32; 3]) -> Vector3<f64> {
    Vector3::new(v[0] as f64, v[1] as f64, v[2] as f64)
}

/// Per-pixel precomputation for every pixel (unmasked ones are left at default and never read).
fn precompute(geom: &SurfaceGeometry) -> Vec<Pre> {
    let w = geom.width;
    (0..w * geom.height)
        .into_par_iter()
        .map(|i| {
            if !geom.mask[i] {
                return Pre::default();
            }
            let omega = pixel_solid_angle(&geom.intrinsics, (i % w) as f64, (i / w) as f64);
            Pre::new(f3(geom.points_mm[i]), f3(geom.normals[i]), omega)
        })
        .collect()
}

/// Truncated forward-scatter kernel K̂ (Eq. 4.51) with the constant term of Eq. 4.52/4.53.
///
/// Storage, per masked pixel p (row-major order), as f32 with implicit neighbour offsets (see
/// [`KernelLayout`]): the near block of K_pq row by row, then the far window of per-pixel cell
/// values row by row. Entries whose q (or cell) is unmasked, outside the image, or (for the far
/// window) inside the near block are stored as 0, which keeps every row contiguous and the
/// apply loop branch-free. The near block holds the diagonal e^{−σ d_vp}, which is also kept
/// separately in [`ForwardKernel::diagonal`].
#[derive(Clone, Debug)]
pub struct ForwardKernel {
    width: usize,
    height: usize,
    layout: KernelLayout,
    /// Cell grid size (⌈w/s⌉, ⌈h/s⌉).
    cells_w: usize,
    cells_h: usize,
    masked: Vec<u32>,
    index_of: Vec<u32>,
    diag: Vec<f32>,
    /// dA_q over its cell's mean dA, per masked pixel (empty without a far window): the far
    /// window multiplies K at the cell's mean geometry with Σ_q (dA_q/dA̅)·x_q, so the facet
    /// area, which varies fastest near the silhouette (Eq. 4.44), is kept per pixel.
    cell_weight: Vec<f32>,
    entries: Vec<f32>,
    epsilon: f64,
    far_field: FarField,
    /// Per masked pixel p, the coefficient of the extra unknown x_C in row p (empty without
    /// one): 1 for Eq. 4.52, κ_p/κ̄ for [`FarField::PerPixel`].
    far_coeff: Vec<f64>,
    /// Per masked pixel q, its weight in the last row (x_C = Σ_q weight_q L_s(q); empty
    /// without one): ε for Eq. 4.52, κ̄·dA_q for [`FarField::PerPixel`].
    total_weight: Vec<f64>,
    /// [`FarField::Blocks`]: the outside of the support summed on coarse blocks, and the facet
    /// area dA_q (mm²) of every pixel, which weights L_s in the blocks' sums.
    blocks: Option<(OutsideBlocks, Vec<f64>)>,
}

/// Marks unmasked pixels in [`ForwardKernel::masked_index`]'s table.
const NOT_MASKED: u32 = u32::MAX;

/// Lights processed together per pass over the kernel in [`ForwardKernel::apply_block`].
const BLOCK: usize = 8;

/// Cells viewed more obliquely than this (smallest v·n of their pixels) are summed pixel by
/// pixel: near the silhouette K_pq changes too fast across a cell (the facet area of Eq. 4.44
/// and the tangent-plane crossing of Eq. 4.43 both diverge at grazing view) for the mean
/// geometry to stand for it; the mean over-estimated such cells by 12–14 % in
/// `far_cells_approximate_the_exact_kernel`.
const CELL_MIN_COS_VIEW: f64 = 0.3;

/// Mean geometry of the masked pixels of every s×s cell, as a [`Pre`] whose facet area is the
/// cells' mean (K_pq is proportional to dA_q, and the operator multiplies by the cell's *sum*
/// of L_s), and whether the cell must be summed per pixel instead (partly masked, or more
/// oblique than [`CELL_MIN_COS_VIEW`]). Cells without masked pixels keep d = 0 and are never
/// read.
fn cell_geometry(
    pre: &[Pre],
    mask: &[bool],
    w: usize,
    h: usize,
    s: usize,
    sigma: f64,
) -> (usize, usize, Vec<(Pre, bool)>) {
    let (cw, ch) = (w.div_ceil(s), h.div_ceil(s));
    let cells = (0..cw * ch)
        .into_par_iter()
        .map(|c| {
            let (cx, cy) = (c % cw, c / cw);
            let (mut pt, mut nn, mut da, mut count) =
                (Vector3::zeros(), Vector3::zeros(), 0.0, 0usize);
            let (mut inside, mut min_vn) = (0usize, f64::INFINITY);
            for y in cy * s..((cy + 1) * s).min(h) {
                for x in cx * s..((cx + 1) * s).min(w) {
                    let i = y * w + x;
                    inside += 1;
                    if !mask[i] {
                        continue;
                    }
                    let q = &pre[i];
                    pt += q.ray * q.d;
                    nn += q.n;
                    min_vn = min_vn.min(-q.ray.dot(&q.n));
                    da += q.da;
                    count += 1;
                }
            }
            if count == 0 {
                return (Pre::default(), false);
            }
            let per_pixel = count < inside || min_vn < CELL_MIN_COS_VIEW;
            let cell = Pre::mean(pt, nn, count, da / count as f64, sigma);
            (cell, per_pixel)
        })
        .collect();
    (cw, ch, cells)
}

impl ForwardKernel {
    /// Builds K̂ over the masked pixels of `geom` with the reference's exact r×r support
    /// (`support_r` odd, ≥ 3); see [`ForwardKernel::build_with`].
    pub fn build(
        ft: &FTable,
        medium: &Medium,
        geom: &SurfaceGeometry,
        support_r: usize,
    ) -> Result<ForwardKernel> {
        ForwardKernel::build_with(
            ft,
            medium,
            geom,
            &KernelLayout::exact(support_r)?,
            FarField::ConstantEpsilon,
        )
    }

    /// Builds K̂ over the masked pixels of `geom` in `layout`, in parallel over pixels, and ε
    /// (Eq. 4.53) as the smallest stored off-diagonal per-pixel entry whose q is masked (0 when
    /// there is none). `far_field` picks the model of the scatter from outside the support
    /// ([`FarField`]); with [`FarField::PerPixel`] the stored entries are K_pq − κ_p·dA_q.
    pub fn build_with(
        ft: &FTable,
        medium: &Medium,
        geom: &SurfaceGeometry,
        layout: &KernelLayout,
        far_field: FarField,
    ) -> Result<ForwardKernel> {
        Self::build_monitored(ft, medium, geom, layout, far_field, &Monitor::noop())
    }

    /// [`ForwardKernel::build_with`] that stops with [`MurkError::Cancelled`] soon after
    /// `monitor` is cancelled: the build is seconds of one parallel loop at r = 81, so every
    /// pixel's row (a few µs to ms of work) first checks the flag, and a cancelled build skips
    /// the rest instead of finishing it.
    pub fn build_monitored(
        ft: &FTable,
        medium: &Medium,
        geom: &SurfaceGeometry,
        layout: &KernelLayout,
        far_field: FarField,
        monitor: &Monitor,
    ) -> Result<ForwardKernel> {
        medium.validate()?;
        geom.validate()?;
        let (w, h) = (geom.width, geom.height);
        if w * h >= NOT_MASKED as usize {
            return Err(MurkError::invalid("width", "image too large"));
        }
        let sigma = medium.sigma_per_mm;
        let ph = Physics::new(ft, medium, geom.emission);
        let mut pre = precompute(geom);
        for p in &mut pre {
            p.att = (-sigma * p.d).exp();
        }
        let s = layout.cell();
        let (cells_w, cells_h, cells) = if layout.far_width() > 0 {
            cell_geometry(&pre, &geom.mask, w, h, s, sigma)
        } else {
            (w, h, Vec::new())
        };
        let mut index_of = vec![NOT_MASKED; w * h];
        let mut masked = Vec::new();
        for (i, &m) in geom.mask.iter().enumerate() {
            if m {
                index_of[i] = masked.len() as u32;
                masked.push(i as u32);
            }
        }
        let diag: Vec<f32> = masked
            .iter()
            .map(|&p| (-sigma * pre[p as usize].d).exp() as f32)
            .collect();
        let cell_weight: Vec<f32> = if cells.is_empty() {
            Vec::new()
        } else {
            masked
                .iter()
                .map(|&p| {
                    let p = p as usize;
                    let c = (p / w / s) * cells_w + (p % w) / s;
                    (pre[p].da / cells[c].0.da) as f32
                })
                .collect()
        };
        // κ_p = far_coeff_p·κ̄, scaled so that x_C is of the order of Eq. 4.52's C. The
        // constant-ε model has κ̄ = 0 here (nothing subtracted in the support) and its last-row
        // weights ε once ε is known; the blocks need neither.
        let blocks = if far_field == FarField::Blocks {
            let b = OutsideBlocks::build(&ph, &pre, &geom.mask, (w, h), layout, monitor);
            monitor.checkpoint()?;
            Some((b, pre.iter().map(|p| p.da).collect::<Vec<f64>>()))
        } else {
            None
        };
        let (far_coeff, kappa_mean) = match far_field {
            FarField::ConstantEpsilon => (vec![1.0; masked.len()], 0.0),
            FarField::Blocks => (Vec::new(), 0.0),
            FarField::PerPixel => {
                let kappa = outside_support_kappa(&ph, &pre, &geom.mask, (w, h), layout, monitor);
                monitor.checkpoint()?;
                let kappa: Vec<f64> = masked.iter().map(|&p| kappa[p as usize]).collect();
                let mean = kappa.iter().sum::<f64>() / kappa.len().max(1) as f64;
                if mean > 0.0 {
                    (kappa.iter().map(|k| k / mean).collect(), mean)
                } else {
                    (vec![0.0; masked.len()], 0.0)
                }
            }
        };
        let (nb, fw) = (layout.near_width(), layout.far_width());
        let (mc, kc) = (layout.near_cells() as isize, layout.far_cells() as isize);
        let si = s as isize;
        let per = layout.entries_per_pixel();
        let lanes = PreLanes::new(&pre);
        let cell_lanes = PreLanes::new(&cells.iter().map(|c| c.0).collect::<Vec<_>>());
        // The masked pixels of each cell summed pixel by pixel, consecutive (row-major within
        // the cell), so that a cell's entries are one batch: cell c's pixels are
        // cell_pixel_start[c]..cell_pixel_start[c + 1].
        let mut cell_pixel_start = Vec::with_capacity(cells.len() + 1);
        let mut cell_pixels = Vec::new();
        for (c, (_, per_pixel)) in cells.iter().enumerate() {
            cell_pixel_start.push(cell_pixels.len() as u32);
            if *per_pixel {
                let (cx, cy) = ((c % cells_w) * s, (c / cells_w) * s);
                for qy in cy..(cy + s).min(h) {
                    let run = qy * w + cx..qy * w + (cx + s).min(w);
                    for (q, &m) in pre[run.clone()].iter().zip(&geom.mask[run]) {
                        if m {
                            cell_pixels.push(*q);
                        }
                    }
                }
            }
        }
        cell_pixel_start.push(cell_pixels.len() as u32);
        let cell_pixel_lanes = PreLanes::new(&cell_pixels);
        let mut entries = vec![0f32; masked.len() * per];
        // What the per-pixel far field takes out of entry pq, per unit dA_q: κ_p (far_field.rs;
        // 0 for the other models).
        let kappa_of = |k: usize| far_coeff.get(k).map_or(0.0, |c| c * kappa_mean);
        let epsilon = entries
            .par_chunks_mut(per)
            .zip(masked.par_iter())
            .enumerate()
            // One row of entries at a time comes back from the batch evaluation.
            .map_init(
                || (vec![0.0f64; nb.max(fw)], vec![0.0f64; s * s]),
                |(row_buf, pixel_buf), (k, (win, &pi))| {
                    if monitor.is_cancelled() {
                        return f64::INFINITY;
                    }
                    let pi = pi as usize;
                    let (px, py) = ((pi % w) as isize, (pi / w) as isize);
                    let (pcx, pcy) = (px / si, py / si);
                    let (ox, oy) = ((pcx - mc) * si, (pcy - mc) * si);
                    let pp = &pre[pi];
                    let kappa = kappa_of(k);
                    let mut min = f64::INFINITY;
                    let (near, far) = win.split_at_mut(nb * nb);
                    for (wy, wrow) in near.chunks_exact_mut(nb).enumerate() {
                        let qy = oy + wy as isize;
                        if qy < 0 || qy >= h as isize {
                            continue;
                        }
                        let x0 = ox.max(0);
                        let x1 = (ox + nb as isize - 1).min(w as isize - 1);
                        if x1 < x0 {
                            continue;
                        }
                        let row = qy as usize * w;
                        let ks = &mut row_buf[..(x1 - x0 + 1) as usize];
                        k_entries_fast(&ph, pp, &lanes, row + x0 as usize, ks);
                        for (qx, &k) in (x0..=x1).zip(ks.iter()) {
                            let qi = row + qx as usize;
                            if !geom.mask[qi] {
                                continue;
                            }
                            let slot = &mut wrow[(qx - ox) as usize];
                            let q = &pre[qi];
                            if qi == pi {
                                *slot = ((-sigma * pp.d).exp() - kappa * q.da) as f32;
                                continue;
                            }
                            min = min.min(f64::from(k as f32));
                            *slot = (k - kappa * q.da) as f32;
                        }
                    }
                    if fw > 0 {
                        for (fy, frow) in far.chunks_exact_mut(fw).enumerate() {
                            let cy = pcy - kc + fy as isize;
                            if cy < 0 || cy >= cells_h as isize {
                                continue;
                            }
                            // The row's cells at their mean geometry, in one batch; the near
                            // block's cells, if the row crosses it, are left out.
                            let lo = (pcx - kc).max(0);
                            let hi = (pcx + kc).min(cells_w as isize - 1);
                            let crosses = (cy - pcy).abs() <= mc;
                            let row = cy as usize * cells_w;
                            let ks = &mut row_buf[..(hi - lo + 1).max(0) as usize];
                            // Runs of cells left and right of the near block, or the whole
                            // row and an empty run ((1, 0): b < a).
                            let runs = if crosses {
                                [(lo, (pcx - mc - 1).min(hi)), ((pcx + mc + 1).max(lo), hi)]
                            } else {
                                [(lo, hi), (1, 0)]
                            };
                            for (a, b) in runs {
                                if b >= a {
                                    let run = &mut ks[(a - lo) as usize..=(b - lo) as usize];
                                    k_entries_fast(&ph, pp, &cell_lanes, row + a as usize, run);
                                }
                            }
                            for (fx, slot) in frow.iter_mut().enumerate() {
                                let cx = pcx - kc + fx as isize;
                                if cx < 0 || cx >= cells_w as isize {
                                    continue;
                                }
                                if (cx - pcx).abs() <= mc && crosses {
                                    continue;
                                }
                                let (cell, per_pixel) = &cells[cy as usize * cells_w + cx as usize];
                                if cell.d == 0.0 {
                                    continue;
                                }
                                let k = if *per_pixel {
                                    // Σ_q K_pq x_q = k·Σ_q w_q x_q holds exactly for uniform x with
                                    // k = Σ_q K_pq / Σ_q w_q, and Σ_q w_q is the masked count.
                                    let c = cy as usize * cells_w + cx as usize;
                                    let (a, b) = (
                                        cell_pixel_start[c] as usize,
                                        cell_pixel_start[c + 1] as usize,
                                    );
                                    let pks = &mut pixel_buf[..b - a];
                                    k_entries_fast(&ph, pp, &cell_pixel_lanes, a, pks);
                                    let mut sum = 0.0;
                                    for &k in pks.iter() {
                                        // Eq. 4.53's minimum over the pixels themselves.
                                        min = min.min(f64::from(k as f32));
                                        sum += k;
                                    }
                                    (sum / (b - a) as f64) as f32
                                } else {
                                    ks[(cx - lo) as usize] as f32
                                };
                                min = min.min(f64::from(k));
                                *slot = (f64::from(k) - kappa * cell.da) as f32;
                            }
                        }
                    }
                    min
                },
            )
            .reduce(|| f64::INFINITY, f64::min);
        monitor.checkpoint()?;
        let epsilon = if epsilon.is_finite() { epsilon } else { 0.0 };
        let total_weight = match far_field {
            FarField::ConstantEpsilon => vec![epsilon; masked.len()],
            FarField::Blocks => Vec::new(),
            FarField::PerPixel => masked
                .iter()
                .map(|&q| kappa_mean * pre[q as usize].da)
                .collect(),
        };
        Ok(ForwardKernel {
            width: w,
            height: h,
            layout: *layout,
            cells_w,
            cells_h,
            masked,
            index_of,
            diag,
            cell_weight,
            entries,
            epsilon,
            far_field,
            far_coeff,
            total_weight,
            blocks,
        })
    }

    /// Number n of masked pixels (the operator acts on vectors of length
    /// [`ForwardKernel::dim`]).
    pub fn masked_count(&self) -> usize {
        self.masked.len()
    }

    /// Number of extra far-field unknowns after the n pixels ([`FarField::unknowns`]: Eq. 4.52's
    /// C, or none).
    pub fn extra_unknowns(&self) -> usize {
        self.far_field.unknowns()
    }

    /// Number of stored [`FarField::Blocks`] entries (0 for the other models, or when the
    /// support covers the object).
    pub fn far_block_entries(&self) -> usize {
        self.blocks.as_ref().map_or(0, |(b, _)| b.len())
    }

    /// Length of the augmented operator's vectors: n, plus 1 when there is a C.
    pub fn dim(&self) -> usize {
        self.masked.len() + self.extra_unknowns()
    }

    /// ε of Eq. 4.53.
    pub fn epsilon(&self) -> f64 {
        self.epsilon
    }

    /// The far-field model the kernel was built with.
    pub fn far_field(&self) -> FarField {
        self.far_field
    }

    /// The value of the extra unknown x_C that is consistent with `ls` (L_s per masked pixel):
    /// Eq. 4.52's last row, ε Σ_q L_s(q) (or κ̄ Σ_q dA_q L_s(q) for [`FarField::PerPixel`]);
    /// `None` for [`FarField::Blocks`], which has no such unknown. A good start for the solver.
    ///
    /// # Panics
    /// If `ls` does not have one value per masked pixel.
    pub fn constant_for(&self, ls: &[f64]) -> Option<f64> {
        assert_eq!(ls.len(), self.masked.len(), "one value per masked pixel");
        (self.extra_unknowns() == 1)
            .then(|| ls.iter().zip(&self.total_weight).map(|(x, w)| w * x).sum())
    }

    /// The far field the constant x_C adds to masked pixel `k`: x_C·far_coeff_k, with
    /// far_coeff ≡ 1 for Eq. 4.52 and κ_k/κ̄ for [`FarField::PerPixel`]; 0 for
    /// [`FarField::Blocks`], which has no x_C.
    pub fn far_coefficient(&self, k: usize) -> f64 {
        self.far_coeff.get(k).copied().unwrap_or(0.0)
    }

    /// The requested support r.
    pub fn support(&self) -> usize {
        self.layout.support_r()
    }

    /// How the support is stored.
    pub fn layout(&self) -> &KernelLayout {
        &self.layout
    }

    /// Memory held by the kernel, bytes.
    pub fn bytes(&self) -> usize {
        self.entries.len() * 4
            + self.diag.len() * 4
            + self.cell_weight.len() * 4
            + self.masked.len() * 4
            + self.index_of.len() * 4
            + (self.far_coeff.len() + self.total_weight.len()) * 8
            + self
                .blocks
                .as_ref()
                .map_or(0, |(b, da)| b.bytes() + da.len() * 8)
    }

    /// Image width and height the kernel was built for.
    pub fn image_size(&self) -> (usize, usize) {
        (self.width, self.height)
    }

    /// K_pp = e^{−σ d_vp} per masked pixel.
    pub fn diagonal(&self) -> &[f32] {
        &self.diag
    }

    /// Row-major pixel index of masked pixel `k`.
    pub fn pixel_index(&self, k: usize) -> usize {
        self.masked[k] as usize
    }

    /// Masked index of row-major pixel `pixel`; `None` if it is not masked or out of range.
    pub fn masked_index(&self, pixel: usize) -> Option<usize> {
        match self.index_of.get(pixel) {
            Some(&k) if k != NOT_MASKED => Some(k as usize),
            _ => None,
        }
    }

    /// Everything stored for masked pixel `k`: the near block, then the far window (see the
    /// type's documentation). For the exact layout this is the r×r window, row-major.
    pub fn window(&self, k: usize) -> &[f32] {
        let per = self.layout.entries_per_pixel();
        &self.entries[k * per..(k + 1) * per]
    }

    /// y = M·x for the augmented operator of Eq. 4.52: for masked p,
    /// y_p = Σ_{q∈S(p)} K̂_pq x_q + c_p x_C, and y_C = Σ_q w_q x_q − x_C (Eq. 4.52: c ≡ 1,
    /// w ≡ ε), with x and y of length [`ForwardKernel::dim`] (masked pixels in row-major order,
    /// then C). [`FarField::Blocks`] has no C: y_p = Σ_{q∈S(p)} K̂_pq x_q plus the blocks' sum.
    ///
    /// # Panics
    /// If `x` or `y` does not have length [`ForwardKernel::dim`].
    pub fn apply(&self, x: &[f64], y: &mut [f64]) {
        self.apply_block(x, y, 1);
    }

    /// [`ForwardKernel::apply`] on `k` vectors stored one after another in `xs` (each
    /// [`ForwardKernel::dim`] long), results likewise in `ys`; up to eight vectors share one pass
    /// over the kernel.
    ///
    /// # Panics
    /// If `xs` or `ys` does not have length k·dim.
    pub fn apply_block(&self, xs: &[f64], ys: &mut [f64], k: usize) {
        let m = self.dim();
        assert_eq!(xs.len(), k * m, "xs must hold k·dim values");
        assert_eq!(ys.len(), k * m, "ys must hold k·dim values");
        for j0 in (0..k).step_by(BLOCK) {
            let kb = BLOCK.min(k - j0);
            self.apply_group(
                &xs[j0 * m..(j0 + kb) * m],
                &mut ys[j0 * m..(j0 + kb) * m],
                kb,
            );
        }
    }

    fn apply_group(&self, xs: &[f64], ys: &mut [f64], kb: usize) {
        let n = self.masked.len();
        let m = self.dim();
        let (w, h) = (self.width, self.height);
        let s = self.layout.cell();
        let (nb, fw) = (self.layout.near_width(), self.layout.far_width());
        let (mc, kc) = (
            self.layout.near_cells() as isize,
            self.layout.far_cells() as isize,
        );
        let si = s as isize;
        // Interleave into image layout, BLOCK values per pixel, so every window row is one
        // contiguous run of both kernel entries and inputs; the far window reads per-cell sums.
        let mut img = vec![0.0f64; w * h * BLOCK];
        for (p, &pi) in self.masked.iter().enumerate() {
            for j in 0..kb {
                img[pi as usize * BLOCK + j] = xs[j * m + p];
            }
        }
        let (cw, ch) = (self.cells_w, self.cells_h);
        let mut cells = Vec::new();
        if fw > 0 {
            cells = vec![0.0f64; cw * ch * BLOCK];
            for (&pi, &wt) in self.masked.iter().zip(&self.cell_weight) {
                let pi = pi as usize;
                let c = (pi / w / s) * cw + (pi % w) / s;
                let wt = f64::from(wt);
                for j in 0..BLOCK {
                    cells[c * BLOCK + j] += wt * img[pi * BLOCK + j];
                }
            }
        }
        let mut out = vec![0.0f64; n * BLOCK];
        out.par_chunks_mut(BLOCK).enumerate().for_each(|(p, o)| {
            let pi = self.masked[p] as usize;
            let (px, py) = ((pi % w) as isize, (pi / w) as isize);
            let (pcx, pcy) = (px / si, py / si);
            let (ox, oy) = ((pcx - mc) * si, (pcy - mc) * si);
            let (near, far) = self.window(p).split_at(nb * nb);
            let mut acc = [0.0f64; BLOCK];
            let x0 = ox.max(0);
            let x1 = (ox + nb as isize - 1).min(w as isize - 1);
            let (k0, k1) = ((x0 - ox) as usize, (x1 - ox) as usize);
            for wy in 0..nb {
                let qy = oy + wy as isize;
                if qy < 0 || qy >= h as isize {
                    continue;
                }
                let ks = &near[wy * nb + k0..=wy * nb + k1];
                let base = (qy as usize * w + x0 as usize) * BLOCK;
                dot_row(ks, &img[base..base + ks.len() * BLOCK], &mut acc);
            }
            if fw > 0 {
                let c0 = (pcx - kc).max(0);
                let c1 = (pcx + kc).min(cw as isize - 1);
                let (k0, k1) = ((c0 - pcx + kc) as usize, (c1 - pcx + kc) as usize);
                for fy in 0..fw {
                    let cy = pcy - kc + fy as isize;
                    if cy < 0 || cy >= ch as isize {
                        continue;
                    }
                    let ks = &far[fy * fw + k0..=fy * fw + k1];
                    let base = (cy as usize * cw + c0 as usize) * BLOCK;
                    dot_row(ks, &cells[base..base + ks.len() * BLOCK], &mut acc);
                }
            }
            o.copy_from_slice(&acc);
        });
        if let Some((blocks, da)) = &self.blocks {
            blocks.add_to(&self.masked, da, w, &img, BLOCK, &mut out);
        }
        for j in 0..kb {
            let x = &xs[j * m..(j + 1) * m];
            let y = &mut ys[j * m..(j + 1) * m];
            match self.constant_for(&x[..n]) {
                Some(total) => {
                    let xc = x[n];
                    for p in 0..n {
                        y[p] = out[p * BLOCK + j] + self.far_coeff[p] * xc;
                    }
                    y[n] = total - xc;
                }
                None => {
                    for p in 0..n {
                        y[p] = out[p * BLOCK + j];
                    }
                }
            }
        }
    }
}

/// `acc[j] += Σ_i ks[i]·xs[i·BLOCK + j]`: one row of kernel entries against BLOCK interleaved
/// inputs.
#[inline(always)]
fn dot_row(ks: &[f32], xs: &[f64], acc: &mut [f64; BLOCK]) {
    for (kv, xb) in ks.iter().zip(xs.chunks_exact(BLOCK)) {
        let kv = *kv as f64;
        for j in 0..BLOCK {
            acc[j] += kv * xb[j];
        }
    }
}

/// The untruncated surface-camera forward scatter L_f(p) = Σ_{q≠p, q masked} K_pq L_s(q)
/// (Eq. 4.42) for every masked pixel and every light (`ls[j]` = L_s of light j over the full
/// image, row-major), 0 at unmasked pixels. q within [`DENSE_NEAR_RADIUS`] pixels (Chebyshev)
/// of p are summed exactly; farther q are taken on the image-aligned grid
/// {x ≡ 0, y ≡ 0 mod `far_stride`} with weight far_stride² (`far_stride` ≤ 1 is exact).
/// All lights share one pass over q; parallel over p.
/// The far sampling is a quadrature of a smooth, slowly decaying kernel: with a near radius of
/// only 8 px and stride 2 the worst per-pixel relative error measured on a small sphere is 6 %;
/// with the production radius of 32 px the sampled q carry a much smaller share of the sum.
///
/// # Panics
/// If the geometry is invalid or a light's image does not have width·height values.
pub fn dense_forward_scatter(
    ft: &FTable,
    medium: &Medium,
    geom: &SurfaceGeometry,
    ls: &[&[f32]],
    far_stride: usize,
) -> Vec<Vec<f32>> {
    dense_forward_scatter_radius(ft, medium, geom, ls, far_stride, DENSE_NEAR_RADIUS)
}

pub(crate) fn dense_forward_scatter_radius(
    ft: &FTable,
    medium: &Medium,
    geom: &SurfaceGeometry,
    ls: &[&[f32]],
    far_stride: usize,
    near: usize,
) -> Vec<Vec<f32>> {
    if let Err(e) = geom.validate() {
        panic!("dense_forward_scatter: {e}");
    }
    let (w, h) = (geom.width, geom.height);
    let npx = w * h;
    let k = ls.len();
    for l in ls {
        assert_eq!(l.len(), npx, "every light needs width·height values of L_s");
    }
    let s = far_stride.max(1);
    let weight = (s * s) as f64;
    let pre = precompute(geom);
    // L_s interleaved per pixel so the q loop reads all lights at once.
    let mut lsv = vec![0.0f64; npx * k];
    for (j, l) in ls.iter().enumerate() {
        for i in 0..npx {
            lsv[i * k + j] = l[i] as f64;
        }
    }
    let far: Vec<u32> = (0..npx)
        .filter(|&i| geom.mask[i] && (i % w).is_multiple_of(s) && (i / w).is_multiple_of(s))
        .map(|i| i as u32)
        .collect();
    let ph = Physics::new(ft, medium, geom.emission);
    let near = near as isize;
    let mut out = vec![0.0f64; npx * k];
    out.par_chunks_mut(k.max(1))
        .enumerate()
        .for_each(|(pi, acc)| {
            if k == 0 || !geom.mask[pi] {
                return;
            }
            let pp = &pre[pi];
            let (px, py) = ((pi % w) as isize, (pi / w) as isize);
            let mut add = |qi: usize, wgt: f64| {
                let kv = wgt * k_entry(&ph, pp, &pre[qi]);
                for (a, l) in acc.iter_mut().zip(&lsv[qi * k..qi * k + k]) {
                    *a += kv * l;
                }
            };
            let (y0, y1) = ((py - near).max(0), (py + near).min(h as isize - 1));
            let (x0, x1) = ((px - near).max(0), (px + near).min(w as isize - 1));
            for qy in y0..=y1 {
                for qx in x0..=x1 {
                    let qi = qy as usize * w + qx as usize;
                    if qi != pi && geom.mask[qi] {
                        add(qi, 1.0);
                    }
                }
            }
            for &qi in &far {
                let qi = qi as usize;
                let (qx, qy) = ((qi % w) as isize, (qi / w) as isize);
                if (qx - px).abs() > near || (qy - py).abs() > near {
                    add(qi, weight);
                }
            }
        });
    (0..k)
        .map(|j| (0..npx).map(|i| out[i * k + j] as f32).collect())
        .collect()
}

#[cfg(test)]
pub(super) mod tests {
    use super::super::kernel_entry::{k_entry_fast, kernel_entry, MIN_COS_VIEW};
    use super::*;
    use crate::error::field_of;
    use crate::ps::physics::facet_emission::lambertian_quadrature;
    use crate::ps::physics::h::scatter_quadrature_cs;

    pub(in crate::ps::physics) fn medium() -> Medium {
        Medium {
            beta_per_mm: 0.004,
            sigma_per_mm: 0.005,
        }
    }

    /// A sphere of radius `rad` centred on the optical axis at depth `z0` (mm), as seen by a
    /// w×h camera with focal length `f` px; the mask is where the rays hit it.
    pub(in crate::ps::physics) fn sphere(
        w: usize,
        h: usize,
        f: f64,
        z0: f64,
        rad: f64,
    ) -> SurfaceGeometry {
        let k = Intrinsics::new(
            f,
            f,
            (w as f64 - 1.0) / 2.0 + 0.3,
            (h as f64 - 1.0) / 2.0 - 0.2,
        );
        let mut g = SurfaceGeometry {
            width: w,
            height: h,
            intrinsics: k,
            points_mm: vec![[0.0; 3]; w * h],
            normals: vec![[0.0, 0.0, -1.0]; w * h],
            mask: vec![false; w * h],
            emission: FacetEmission::default(),
        };
        for v in 0..h {
            for u in 0..w {
                let r = k.ray(u as f64, v as f64);
                // |t r − c|² = rad², c = (0, 0, z0).
                let b = r[2] * z0;
                let disc = b * b - (z0 * z0 - rad * rad);
                if disc <= 0.0 {
                    continue;
                }
                let t = b - disc.sqrt();
                let p = [t * r[0], t * r[1], t * r[2]];
                let n = [p[0] / rad, p[1] / rad, (p[2] - z0) / rad];
                let i = v * w + u;
                g.points_mm[i] = [p[0] as f32, p[1] as f32, p[2] as f32];
                g.normals[i] = [n[0] as f32, n[1] as f32, n[2] as f32];
                g.mask[i] = true;
            }
        }
        g
    }

    /// Fronto-parallel plane at depth `z0` filling the image.
    fn plane(w: usize, h: usize, f: f64, z0: f64) -> SurfaceGeometry {
        let k = Intrinsics::new(f, f, (w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
        let mut pts = Vec::with_capacity(w * h);
        for v in 0..h {
            for u in 0..w {
                let r = k.ray(u as f64, v as f64);
                let t = z0 / r[2];
                pts.push([(t * r[0]) as f32, (t * r[1]) as f32, z0 as f32]);
            }
        }
        SurfaceGeometry {
            width: w,
            height: h,
            intrinsics: k,
            points_mm: pts,
            normals: vec![[0.0, 0.0, -1.0]; w * h],
            mask: vec![true; w * h],
            emission: FacetEmission::default(),
        }
    }

    fn point(g: &SurfaceGeometry, i: usize) -> (Vector3<f64>, f64, Vector3<f64>) {
        let p = f3(g.points_mm[i]);
        let d = p.norm();
        (p, d, p / d)
    }

    fn omega(g: &SurfaceGeometry, i: usize) -> f64 {
        pixel_solid_angle(&g.intrinsics, (i % g.width) as f64, (i / g.width) as f64)
    }

    /// Eq. 4.41 (with the Lambertian cosine when `g` asks for it) by brute-force quadrature,
    /// with the facet area and d_vp′ spelled out again.
    fn k_brute(m: &Medium, g: &SurfaceGeometry, pi: usize, qi: usize) -> f64 {
        let (_, dp, rp) = point(g, pi);
        let (q, dq, rq) = point(g, qi);
        let n = f3(g.normals[qi]);
        let vn = (-rq.dot(&n)).max(MIN_COS_VIEW);
        let da = omega(g, qi) * dq * dq / vn;
        // First crossing of p's ray with q's tangent plane, if ahead of the camera.
        let t = n.dot(&q) / n.dot(&rp);
        let len = if t > 0.0 && t < dp { t } else { dp };
        match g.emission {
            FacetEmission::Isotropic => {
                scatter_quadrature_cs(m, da, dq, rp.dot(&rq), rp.cross(&rq).norm(), len)
            }
            FacetEmission::Lambertian => lambertian_quadrature(m, da, rp, q, n, len),
        }
    }

    #[test]
    fn kernel_entry_matches_quadrature_of_eq_4_41() {
        for emission in [FacetEmission::Isotropic, FacetEmission::Lambertian] {
            kernel_entry_matches_quadrature(emission);
        }
    }

    fn kernel_entry_matches_quadrature(emission: FacetEmission) {
        let ft = FTable::global();
        let m = medium();
        let g = SurfaceGeometry {
            emission,
            ..sphere(40, 36, 60.0, 400.0, 150.0)
        };
        let c = 18 * 40 + 20;
        let mut truncated = 0;
        for (pi, qi) in [
            (c, c + 1),
            (c, c + 41),
            (c + 5, c - 3),
            (c, c + 7 * 40 + 9),
            (c - 12, c + 12),
            (c + 12 * 40, c - 9 * 40),
        ] {
            assert!(g.mask[pi] && g.mask[qi]);
            let (_, dp, rp) = point(&g, pi);
            let (q, _, _) = point(&g, qi);
            let got = kernel_entry(
                ft,
                &m,
                g.emission,
                rp,
                dp,
                q,
                f3(g.normals[qi]),
                omega(&g, qi),
            );
            let want = k_brute(&m, &g, pi, qi);
            assert!(
                (got - want).abs() < 1e-3 * want,
                "({pi},{qi}): {got} vs {want}"
            );
            let n = f3(g.normals[qi]);
            let t = n.dot(&q) / n.dot(&rp);
            if t > 0.0 && t < dp {
                truncated += 1;
            }
        }
        // On a convex surface p lies behind q's tangent plane: the d_vp′ truncation is exercised.
        assert!(truncated >= 4, "{truncated}");
    }

    /// Over many pairs of a sphere — every neighbour within 5 px of several pixels, including
    /// silhouette ones, and random far pairs — the Lambertian entries read from the tables
    /// stay within 1e-3 of quadrature: the cosine weight makes near entries small, but the
    /// tables' error is far below their worst-case bound away from the (u → 0, v → π/2) corner.
    #[test]
    fn lambertian_entries_match_quadrature_over_a_sphere() {
        let ft = FTable::global();
        let m = medium();
        let g = sphere(48, 44, 70.0, 400.0, 100.0);
        let w = g.width;
        let masked: Vec<usize> = (0..w * g.height).filter(|&i| g.mask[i]).collect();
        let mut pairs = Vec::new();
        let mut seed = 11u64;
        for _ in 0..6 {
            let pi = masked[(lcg(&mut seed) * masked.len() as f64) as usize];
            for dy in -5isize..=5 {
                for dx in -5isize..=5 {
                    let (x, y) = ((pi % w) as isize + dx, (pi / w) as isize + dy);
                    if x < 0 || y < 0 || x >= w as isize || y >= g.height as isize {
                        continue;
                    }
                    let qi = y as usize * w + x as usize;
                    if qi != pi && g.mask[qi] {
                        pairs.push((pi, qi));
                    }
                }
            }
        }
        // Silhouette pixels: masked with an unmasked 4-neighbour.
        let edge: Vec<usize> = masked
            .iter()
            .copied()
            .filter(|&i| [i - 1, i + 1, i - w, i + w].iter().any(|&j| !g.mask[j]))
            .collect();
        for k in 0..200 {
            let pi = if k % 2 == 0 {
                edge[(lcg(&mut seed) * edge.len() as f64) as usize]
            } else {
                masked[(lcg(&mut seed) * masked.len() as f64) as usize]
            };
            let qi = masked[(lcg(&mut seed) * masked.len() as f64) as usize];
            if qi != pi {
                pairs.push((pi, qi));
            }
        }
        let mut worst = 0.0f64;
        for (pi, qi) in pairs {
            let (_, dp, rp) = point(&g, pi);
            let (q, _, _) = point(&g, qi);
            let got = kernel_entry(
                ft,
                &m,
                g.emission,
                rp,
                dp,
                q,
                f3(g.normals[qi]),
                omega(&g, qi),
            );
            let want = k_brute(&m, &g, pi, qi);
            if want == 0.0 {
                assert!(got.abs() < 1e-15, "{got}");
                continue;
            }
            worst = worst.max((got - want).abs() / want);
        }
        eprintln!("Lambertian entries over a sphere: worst relative error {worst:.2e}");
        assert!(worst < 1e-3, "{worst}");
    }

    fn lcg(seed: &mut u64) -> f64 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*seed >> 11) as f64) / (1u64 << 53) as f64
    }

    #[test]
    fn apply_equals_dense_augmented_matrix() {
        let ft = FTable::global();
        let m = medium();
        let g = sphere(24, 20, 25.0, 300.0, 110.0);
        let r = 5;
        let kern = ForwardKernel::build(ft, &m, &g, r).unwrap();
        let n = kern.masked_count();
        assert!(n > 100 && n < 24 * 20, "{n}");
        // Naive augmented matrix of Eq. 4.52.
        let mut mat = vec![0.0f64; (n + 1) * (n + 1)];
        let mut eps = f64::INFINITY;
        for a in 0..n {
            let pi = kern.pixel_index(a);
            assert_eq!(kern.masked_index(pi), Some(a));
            let (_, dp, rp) = point(&g, pi);
            for b in 0..n {
                let qi = kern.pixel_index(b);
                let (dx, dy) = (
                    (qi % 24) as isize - (pi % 24) as isize,
                    (qi / 24) as isize - (pi / 24) as isize,
                );
                if dx.abs() > 2 || dy.abs() > 2 {
                    continue;
                }
                let v = if a == b {
                    (-m.sigma_per_mm * dp).exp()
                } else {
                    let (q, _, _) = point(&g, qi);
                    let k = kernel_entry(
                        ft,
                        &m,
                        g.emission,
                        rp,
                        dp,
                        q,
                        f3(g.normals[qi]),
                        omega(&g, qi),
                    ) as f32 as f64;
                    eps = eps.min(k);
                    k
                };
                mat[a * (n + 1) + b] = v;
            }
            mat[a * (n + 1) + n] = 1.0;
        }
        for b in 0..n {
            mat[n * (n + 1) + b] = eps;
        }
        mat[n * (n + 1) + n] = -1.0;
        // The build evaluates short brackets by a 3-point rule and the rest from the table
        // (h::bracket_fast), `kernel_entry` with the accurate bracket: they agree to ~1e-3, to
        // ~3e-3 for the smallest entry of a Lambertian facet, whose cosine weight is small at a
        // grazing silhouette facet, so the table's absolute error is a larger share of it.
        assert!(
            (kern.epsilon() - eps).abs() <= 5e-3 * eps,
            "ε is the smallest stored off-diagonal entry: {} vs {eps}",
            kern.epsilon()
        );
        assert!(eps > 0.0);

        let mut seed = 7u64;
        let k = 9;
        let xs: Vec<f64> = (0..k * (n + 1)).map(|_| lcg(&mut seed) - 0.3).collect();
        let mut ys = vec![0.0; k * (n + 1)];
        kern.apply_block(&xs, &mut ys, k);
        for j in 0..k {
            let x = &xs[j * (n + 1)..(j + 1) * (n + 1)];
            let mut y1 = vec![0.0; n + 1];
            kern.apply(x, &mut y1);
            for a in 0..=n {
                let want: f64 = (0..=n).map(|b| mat[a * (n + 1) + b] * x[b]).sum();
                let off: f64 = (0..n)
                    .filter(|&b| b != a)
                    .map(|b| (mat[a * (n + 1) + b] * x[b]).abs())
                    .sum();
                let tol = 1e-6 * (1.0 + want.abs()) + 2e-3 * off;
                assert!(
                    (y1[a] - want).abs() < tol,
                    "light {j} row {a}: {} vs {want}",
                    y1[a]
                );
                assert!((ys[j * (n + 1) + a] - y1[a]).abs() < 1e-12 * (1.0 + want.abs()));
            }
        }
        assert!(kern.bytes() >= n * r * r * 4);
        assert_eq!(kern.support(), r);
        assert_eq!(kern.diagonal().len(), n);
        assert_eq!(kern.window(0).len(), r * r);
    }

    /// The far-cell layout against the exact kernel, both with supports covering the whole
    /// image so only the cell quadrature differs: the off-diagonal sum Σ_{q≠p} K_pq x_q of a
    /// smooth or textured x agrees to a stated tolerance, the diagonal is the exact one and ε is within 5 %.
    /// The build's batched rows (`kernel_batch`) store, slot for slot and bit for bit, what a
    /// plain loop over the layout stores entry by entry with [`k_entry_fast`]: near block, far
    /// cells at their mean geometry, and far cells summed pixel by pixel, with the image edge
    /// and partial cells in the window.
    #[test]
    fn batched_build_matches_an_entry_by_entry_loop() {
        let ft = FTable::global();
        let m = medium();
        let (w, h) = (47, 41);
        let mut g = sphere(w, h, 60.0, 300.0, 110.0);
        // A few holes, so that cells are partly masked away from the silhouette too.
        for i in (0..w * h).step_by(53) {
            g.mask[i] = false;
        }
        let layout = KernelLayout::coarse_far(35, 3, 4).unwrap();
        let kern =
            ForwardKernel::build_with(ft, &m, &g, &layout, FarField::ConstantEpsilon).unwrap();
        let ph = Physics::new(ft, &m, g.emission);
        let sigma = m.sigma_per_mm;
        let mut pre = precompute(&g);
        for p in &mut pre {
            p.att = (-sigma * p.d).exp();
        }
        let s = layout.cell();
        let (cells_w, cells_h, cells) = cell_geometry(&pre, &g.mask, w, h, s, sigma);
        let (nb, fw) = (layout.near_width(), layout.far_width());
        let (mc, kc) = (layout.near_cells() as isize, layout.far_cells() as isize);
        let si = s as isize;
        let (mut per_pixel_cells, mut mean_cells) = (0, 0);
        for k in 0..kern.masked_count() {
            let pi = kern.pixel_index(k);
            let pp = &pre[pi];
            let (px, py) = ((pi % w) as isize, (pi / w) as isize);
            let (pcx, pcy) = (px / si, py / si);
            let (ox, oy) = ((pcx - mc) * si, (pcy - mc) * si);
            let mut want = vec![0f32; layout.entries_per_pixel()];
            for wy in 0..nb {
                for wx in 0..nb {
                    let (qx, qy) = (ox + wx as isize, oy + wy as isize);
                    if qx < 0 || qy < 0 || qx >= w as isize || qy >= h as isize {
                        continue;
                    }
                    let qi = qy as usize * w + qx as usize;
                    if !g.mask[qi] {
                        continue;
                    }
                    want[wy * nb + wx] = if qi == pi {
                        (-sigma * pp.d).exp() as f32
                    } else {
                        k_entry_fast(&ph, pp, &pre[qi]) as f32
                    };
                }
            }
            for fy in 0..fw {
                for fx in 0..fw {
                    let (cx, cy) = (pcx - kc + fx as isize, pcy - kc + fy as isize);
                    if cx < 0 || cy < 0 || cx >= cells_w as isize || cy >= cells_h as isize {
                        continue;
                    }
                    if (cx - pcx).abs() <= mc && (cy - pcy).abs() <= mc {
                        continue;
                    }
                    let (cell, per_pixel) = &cells[cy as usize * cells_w + cx as usize];
                    if cell.d == 0.0 {
                        continue;
                    }
                    want[nb * nb + fy * fw + fx] = if *per_pixel {
                        per_pixel_cells += 1;
                        let (mut sum, mut count) = (0.0, 0usize);
                        for qy in cy as usize * s..((cy as usize + 1) * s).min(h) {
                            for qx in cx as usize * s..((cx as usize + 1) * s).min(w) {
                                if g.mask[qy * w + qx] {
                                    sum += k_entry_fast(&ph, pp, &pre[qy * w + qx]);
                                    count += 1;
                                }
                            }
                        }
                        (sum / count as f64) as f32
                    } else {
                        mean_cells += 1;
                        k_entry_fast(&ph, pp, cell) as f32
                    };
                }
            }
            let got = kern.window(k);
            for (slot, (a, b)) in got.iter().zip(&want).enumerate() {
                assert_eq!(
                    a.to_bits(),
                    b.to_bits(),
                    "pixel {pi} slot {slot}: {a} vs {b}"
                );
            }
        }
        assert!(
            per_pixel_cells > 1000 && mean_cells > 1000,
            "{per_pixel_cells} {mean_cells}"
        );
    }

    #[test]
    fn far_cells_approximate_the_exact_kernel() {
        let ft = FTable::global();
        let m = medium();
        // 62×55: neither side a multiple of 3, so border cells are partial.
        let (w, h) = (62, 55);
        let g = sphere(w, h, 70.0, 300.0, 110.0);
        let exact = ForwardKernel::build(ft, &m, &g, 125).unwrap();
        let layout = KernelLayout::coarse_far(125, 3, 9).unwrap();
        assert!(layout.far_width() > 0);
        let coarse =
            ForwardKernel::build_with(ft, &m, &g, &layout, FarField::ConstantEpsilon).unwrap();
        let n = exact.masked_count();
        assert_eq!(coarse.masked_count(), n);
        assert_eq!(coarse.diagonal(), exact.diagonal());
        assert!(
            coarse.bytes() < exact.bytes() / 4,
            "{} vs {}",
            coarse.bytes(),
            exact.bytes()
        );
        // Uniform, shading-like (periods of ~100 px) and textured (periods of ~30 px) L_s.
        for freq in [0.0, 0.05, 0.2] {
            let x: Vec<f64> = (0..n)
                .map(|k| {
                    let p = exact.pixel_index(k);
                    let (u, v) = ((p % w) as f64, (p / w) as f64);
                    1.0 + 0.3 * (u * freq).sin() * (v * 0.75 * freq).cos()
                })
                .chain([0.0])
                .collect();
            let (mut ye, mut yc) = (vec![0.0; n + 1], vec![0.0; n + 1]);
            exact.apply(&x, &mut ye);
            coarse.apply(&x, &mut yc);
            let (mut worst, mut sum_err, mut sum_ref) = (0.0f64, 0.0, 0.0);
            for k in 0..n {
                let diag = f64::from(exact.diagonal()[k]) * x[k];
                let (fe, fc) = (ye[k] - diag, yc[k] - diag);
                assert!(fe > 0.0);
                worst = worst.max((fc - fe).abs() / fe);
                sum_err += (fc - fe).abs();
                sum_ref += fe;
            }
            let mean = sum_err / sum_ref;
            eprintln!("far cells, frequency {freq}: worst {worst:.2e}, mean {mean:.2e}");
            // Measured: mean ≤ 1.3·10⁻³, worst ≤ 2·10⁻³ at every frequency.
            assert!(mean < 3e-3, "frequency {freq}: mean relative error {mean}");
            assert!(
                worst < 5e-3,
                "frequency {freq}: worst relative error {worst}"
            );
        }
        // ε: the smallest per-pixel entry, from a cell centroid instead of a pixel.
        assert!(
            (coarse.epsilon() - exact.epsilon()).abs() < 0.05 * exact.epsilon(),
            "{} vs {}",
            coarse.epsilon(),
            exact.epsilon()
        );
    }

    #[test]
    fn bad_support_and_geometry_are_rejected() {
        let ft = FTable::global();
        let g = sphere(8, 8, 10.0, 300.0, 110.0);
        for r in [0, 1, 2, 4, 80] {
            let e = ForwardKernel::build(ft, &medium(), &g, r).unwrap_err();
            assert_eq!(field_of(e), "support_r");
        }
        let mut bad = g.clone();
        bad.mask.pop();
        assert_eq!(
            field_of(ForwardKernel::build(ft, &medium(), &bad, 3).unwrap_err()),
            "mask"
        );
        let bad_m = Medium {
            beta_per_mm: 0.01,
            sigma_per_mm: 0.001,
        };
        assert_eq!(
            field_of(ForwardKernel::build(ft, &bad_m, &g, 3).unwrap_err()),
            "sigma_per_mm"
        );
    }

    #[test]
    fn dense_forward_scatter_matches_naive_sum() {
        let ft = FTable::global();
        let m = medium();
        let (w, h) = (30, 26);
        let g = sphere(w, h, 30.0, 300.0, 120.0);
        let mut seed = 3u64;
        let l0: Vec<f32> = (0..w * h).map(|_| lcg(&mut seed) as f32).collect();
        let l1: Vec<f32> = (0..w * h).map(|i| 0.5 + 0.01 * (i % w) as f32).collect();
        let exact = dense_forward_scatter(ft, &m, &g, &[&l0, &l1], 1);
        // Every q is within 32 px here, so this is also the all-near path; a near radius of 8
        // exercises the far path with stride 1 (exact) and stride 2 (sampled).
        let far1 = dense_forward_scatter_radius(ft, &m, &g, &[&l0, &l1], 1, 8);
        let far2 = dense_forward_scatter_radius(ft, &m, &g, &[&l0, &l1], 2, 8);
        let mut worst2 = 0.0f64;
        for pi in 0..w * h {
            if !g.mask[pi] {
                assert_eq!(exact[0][pi], 0.0);
                continue;
            }
            let (_, dp, rp) = point(&g, pi);
            let mut want = [0.0f64; 2];
            for qi in 0..w * h {
                if qi == pi || !g.mask[qi] {
                    continue;
                }
                let (q, _, _) = point(&g, qi);
                let k = kernel_entry(
                    ft,
                    &m,
                    g.emission,
                    rp,
                    dp,
                    q,
                    f3(g.normals[qi]),
                    omega(&g, qi),
                );
                want[0] += k * l0[qi] as f64;
                want[1] += k * l1[qi] as f64;
            }
            for j in 0..2 {
                assert!((exact[j][pi] as f64 - want[j]).abs() < 1e-5 * want[j]);
                assert!((far1[j][pi] as f64 - want[j]).abs() < 1e-5 * want[j]);
                worst2 = worst2.max((far2[j][pi] as f64 - want[j]).abs() / want[j]);
            }
        }
        eprintln!(
            "dense forward scatter, far stride 2 beyond 8 px: worst relative error {worst2:.3}"
        );
        assert!(worst2 < 0.08, "{worst2}");
    }

    /// Θ(r) = Σ_{q∈S_r(p), q≠p} K_pq at the centre of a fronto-parallel plane (Fig. 4.9).
    fn theta(g: &SurfaceGeometry, m: &Medium, r: usize) -> f64 {
        let ft = FTable::global();
        let (w, h) = (g.width, g.height);
        let pi = (h / 2) * w + w / 2;
        let (_, dp, rp) = point(g, pi);
        let half = (r / 2) as isize;
        let mut s = 0.0;
        for dy in -half..=half {
            for dx in -half..=half {
                let qi = ((h / 2) as isize + dy) as usize * w + ((w / 2) as isize + dx) as usize;
                if qi != pi {
                    let (q, _, _) = point(g, qi);
                    s += kernel_entry(
                        ft,
                        m,
                        g.emission,
                        rp,
                        dp,
                        q,
                        f3(g.normals[qi]),
                        omega(g, qi),
                    );
                }
            }
        }
        s
    }

    #[test]
    fn plane_kernel_decays_slowly_fig_4_9() {
        let m = Medium {
            beta_per_mm: 0.002,
            sigma_per_mm: 0.0025,
        };
        let g = plane(121, 121, 300.0, 500.0);
        let ratio = theta(&g, &m, 51) / theta(&g, &m, 101);
        eprintln!("plane facing the camera: Θ(51)/Θ(101) = {ratio:.3}");
        assert!(ratio < 0.9 && ratio > 0.2, "{ratio}");
    }
}
