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
//!   [`crate::atmosphere::MIN_TRANSMISSION`]. That is [`CostKind::Dehazing`] (=
//!   [`DehazingOptions::EQ37`]).
//! - **noise-robust dehazing** ([`CostKind::DehazingWith`], [`DehazingOptions`]): Eq. 3.5
//!   multiplies sensor noise by `1/t`, so with noise the Eq. 3.7 residual of the correct depth
//!   grows with distance and the volume favours near planes. The same constraint `J_r = J_s`
//!   can be measured in observation space, `t_r·(J_r − J_s) = (I_r − A) − (t_r/t_s)(I_s − A)`
//!   (the reference against the source re-hazed to the reference's depth; noise `σ·sqrt(1 +
//!   (t_r/t_s)²)`, independent of distance) — [`DehazingResidual::ObservationSpace`], or its
//!   noise-whitened form. The `[0, 1]` check can be hard (Eq. 3.7), widened by `k` noise stds
//!   of the dehazed value (`k·σ/t`, `σ` estimated robustly from the reference,
//!   [`estimate_noise_sigma`]), reference-only, soft (excursion added to the residual), or off;
//!   every dehazing voxel is capped at `γ`. `DehazingOptions::default()` — observation space,
//!   no range check — is the measured best (`examples/mvs_survey.rs`, docs/accuracy.md). With
//!   `β = 0` every mode equals the ordinary volume bit for bit.
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
//! per plane (cancellation checkpoint between planes), planes in parallel with rayon; row
//! buffers are per worker and reused, so nothing is allocated per voxel or per row. The row
//! kernels are in `kernel.rs` (scalar, the reference) and `simd.rs` (AVX2, chosen at run time,
//! tested equal to the scalar rows); the volume's memory comes from
//! [`crate::large_buffer::zeroed`] (transparent huge pages on Linux).

pub mod census;
mod kernel;
mod row;
pub mod sample;
mod shift;

/// The consistency check's claims treat a row as a shift by the sweep's own rule.
pub(crate) use shift::SHIFT_TOLERANCE_PX;
mod simd;

use rayon::prelude::*;

use crate::atmosphere::{inverse_transmission, transmission, AtmosphereParams};
use crate::camera::Intrinsics;
use crate::error::{MurkError, Result};
use crate::image::ImageF32;
use crate::monitor::Monitor;
use crate::mvs::plane_sweep::{PlaneSet, PlaneWarp};
use crate::mvs::pose::Pose;

use kernel::{fill_row, fill_row_observation, ReferenceImages, RowScratch, SourcePlane};
use row::Haze;

/// `γ` for images of `channels` channels: the cost of a voxel no source sees, and the cap of every
/// dehazing voxel (the module docs). No voxel of a volume over images in `[0, 1]` exceeds it,
/// which lets depth estimation scale a strip's levels before any cost is computed.
pub fn penalty_for(channels: usize) -> f32 {
    channels as f32
}

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

/// The views with their images replaced by `images` (the reference's, then the sources' in
/// order), or as they are when `None`: intrinsics and poses stay.
pub(crate) fn views_over<'a>(
    reference: &View<'a>,
    sources: &[View<'a>],
    images: &'a Option<(ImageF32, Vec<ImageF32>)>,
) -> (View<'a>, Vec<View<'a>>) {
    match images {
        Some((r, s)) => (
            View {
                image: r,
                ..*reference
            },
            sources
                .iter()
                .zip(s)
                .map(|(v, image)| View { image, ..*v })
                .collect(),
        ),
        None => (*reference, sources.to_vec()),
    }
}

/// Which photometric cost to build.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum CostKind {
    /// Eq. 3.1 on the observed (hazy) images.
    Ordinary,
    /// Eq. 3.7 exactly as in the reference: dehaze with the plane hypothesis and the given
    /// airlight and `β` (per scene unit); same as `DehazingWith(p, DehazingOptions::EQ37)`.
    Dehazing(AtmosphereParams),
    /// The dehazing volume with a choice of residual space and range penalty
    /// ([`DehazingOptions`]; its `Default` is the measured, noise-robust choice).
    DehazingWith(AtmosphereParams, DehazingOptions),
}

impl CostKind {
    /// Atmosphere and options of a dehazing kind, `None` for [`CostKind::Ordinary`].
    pub fn dehazing(&self) -> Option<(AtmosphereParams, DehazingOptions)> {
        match *self {
            CostKind::Ordinary => None,
            CostKind::Dehazing(p) => Some((p, DehazingOptions::EQ37)),
            CostKind::DehazingWith(p, o) => Some((p, o)),
        }
    }
}

/// Where the dehazing volume measures the residual of the constraint `J_r = J_s`.
///
/// Sensor noise `σ` in `I` becomes `σ/t` in the dehazed `J` (Eq. 3.5), so in Eq. 3.7 the
/// residual of a correct-depth voxel grows like `σ·sqrt(1/t_r² + 1/t_s²)`, and far, dim voxels
/// (small `t`) look worse than near ones for no geometric reason.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DehazingResidual {
    /// Eq. 3.7: `Σ_c |J_r − J_s|`, in dehazed space.
    Eq37,
    /// `t_r·Σ_c |J_r − J_s| = Σ_c |(I_r − A) − (t_r/t_s)(I_s − A)|`: the same constraint in
    /// observation space, the reference compared with the source re-hazed to the reference's
    /// depth. The noise of a correct-depth voxel is `σ·sqrt(1 + (t_r/t_s)²)`, no longer `∝ 1/t`.
    ObservationSpace,
    /// The observation-space residual divided by its noise std relative to `t_r = t_s`:
    /// `t_r·sqrt(2/(1 + (t_r/t_s)²))·Σ_c |J_r − J_s|` (whitened, then scaled so equal
    /// transmissions give the observation-space value).
    NoiseWhitened,
}

/// When a dehazed value outside `[0, 1]` earns the penalty `γ`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum RangePenalty {
    /// Eq. 3.7: `γ` whenever any channel of `J_r` or `J_s` leaves `[0, 1]`.
    Hard,
    /// `γ` only when a channel leaves `[0, 1]` by more than `k·σ/t`, i.e. by more than `k`
    /// noise standard deviations of the dehazed value (`σ` from [`DehazingOptions::noise_sigma`]
    /// or estimated from the reference image, [`estimate_noise_sigma`]).
    NoiseAware {
        /// Margin in noise standard deviations, finite and `≥ 0`.
        k: f32,
    },
    /// Soft: each channel's excursion beyond the noise-widened range `[−k·σ/t, 1 + k·σ/t]`
    /// (dehazed units) is added to the L1 residual before it is scaled to the residual space,
    /// the voxel capped at `γ`. In observation space this is the L1 distance of the observation
    /// from the set of values the haze model allows at the hypothesised depth,
    /// `A(1 − t) + t·[0, 1]`, less the noise margin: a residual in the same units as the
    /// photometric one instead of a cliff.
    Soft {
        /// Margin in noise standard deviations, finite and `≥ 0`.
        k: f32,
    },
    /// As [`RangePenalty::NoiseAware`] but for the reference only: `J_r` depends only on the
    /// reference pixel and the hypothesis, so its range bound holds whatever the sources see,
    /// while an out-of-range source sample may be an occlusion (the source sees a nearer
    /// surface, dehazed with the plane's larger ζ) rather than a wrong depth.
    ReferenceAware {
        /// Margin in noise standard deviations, finite and `≥ 0`.
        k: f32,
    },
    /// No range check (ablation).
    Off,
}

/// Options of the dehazing volume. [`DehazingOptions::EQ37`] is the reference's Eq. 3.7;
/// `Default` is the choice measured best with sensor noise (`examples/mvs_survey.rs`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DehazingOptions {
    /// Residual space.
    pub residual: DehazingResidual,
    /// Range penalty.
    pub range: RangePenalty,
    /// Sensor-noise std (pixel-value units) for [`RangePenalty::NoiseAware`]; `None` estimates
    /// it from the reference image.
    pub noise_sigma: Option<f32>,
}

impl DehazingOptions {
    /// The reference's Eq. 3.7: dehazed-space residual, hard `[0, 1]` penalty.
    pub const EQ37: DehazingOptions = DehazingOptions {
        residual: DehazingResidual::Eq37,
        range: RangePenalty::Hard,
        noise_sigma: None,
    };

    fn validate(&self) -> Result<()> {
        if let RangePenalty::NoiseAware { k }
        | RangePenalty::Soft { k }
        | RangePenalty::ReferenceAware { k } = self.range
        {
            if !k.is_finite() || k < 0.0 {
                return Err(MurkError::invalid(
                    "range.k",
                    format!("must be finite and >= 0, got {k}"),
                ));
            }
        }
        if let Some(s) = self.noise_sigma {
            if !s.is_finite() || s < 0.0 {
                return Err(MurkError::invalid(
                    "noise_sigma",
                    format!("must be finite and >= 0, got {s}"),
                ));
            }
        }
        Ok(())
    }
}

impl Default for DehazingOptions {
    fn default() -> Self {
        DehazingOptions {
            residual: DehazingResidual::ObservationSpace,
            range: RangePenalty::Off,
            noise_sigma: None,
        }
    }
}

/// Robust estimate of additive white sensor noise std of `image` (pixel-value units): the median
/// absolute response of the 3×3 Laplacian-difference kernel `[1 −2 1; −2 4 −2; 1 −2 1]`
/// (Immerkær 1996; it cancels locally planar intensity) over all channels, divided by
/// `0.6745·6` (the kernel's noise gain is `sqrt(36) = 6`; the median of `|N(0, s²)|` is
/// `0.6745·s`). Texture biases it upwards; the median keeps edges from dominating.
/// Returns 0 for images smaller than 3×3.
pub fn estimate_noise_sigma(image: &ImageF32) -> f32 {
    let (w, h, c) = (image.width(), image.height(), image.channels());
    if w < 3 || h < 3 {
        return 0.0;
    }
    let d = image.data();
    let at = |x: usize, y: usize, ch: usize| d[(y * w + x) * c + ch];
    // Row by row on rayon: the median below depends only on the values, not their order.
    let row_len = (w - 2) * c;
    let mut r = vec![0.0f32; (h - 2) * row_len];
    r.par_chunks_mut(row_len).enumerate().for_each(|(k, out)| {
        let y = k + 1;
        for (o, (x, ch)) in out
            .iter_mut()
            .zip((1..w - 1).flat_map(|x| (0..c).map(move |ch| (x, ch))))
        {
            let v = at(x - 1, y - 1, ch) - 2.0 * at(x, y - 1, ch) + at(x + 1, y - 1, ch)
                - 2.0 * at(x - 1, y, ch)
                + 4.0 * at(x, y, ch)
                - 2.0 * at(x + 1, y, ch)
                + at(x - 1, y + 1, ch)
                - 2.0 * at(x, y + 1, ch)
                + at(x + 1, y + 1, ch);
            *o = v.abs();
        }
    });
    let mid = r.len() / 2;
    let (_, m, _) = r.select_nth_unstable_by(mid, f32::total_cmp);
    *m / (0.6745 * 6.0)
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

impl View<'_> {
    /// Checks the view as [`build_cost_volume`] does: with `like = None` (a reference) the image
    /// must have 1 or 3 channels and at least 2×2 pixels; with `like = Some((w, h, c))` (a
    /// source) exactly that shape. Pixels must be finite, intrinsics and pose valid. Errors name
    /// `image`, `intrinsics.…` or `pose.…`.
    pub fn validate(&self, like: Option<(usize, usize, usize)>) -> Result<()> {
        check_view(self, like)
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
    build_cost_volume_rows(
        reference,
        sources,
        planes,
        kind,
        0..reference.image.height(),
        monitor,
    )
}

/// The checks of [`build_cost_volume`] without building anything (errors as there).
pub fn validate_inputs(
    reference: &View<'_>,
    sources: &[View<'_>],
    planes: &PlaneSet,
    kind: CostKind,
) -> Result<()> {
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
    if let Some((p, o)) = kind.dehazing() {
        p.validate().map_err(|e| e.within("atmosphere"))?;
        o.validate().map_err(|e| e.within("options"))?;
    }
    Ok(())
}

/// [`build_cost_volume`] for the reference rows `rows` only: a volume `rows.len()` pixels high
/// whose row `k` is reference row `rows.start + k`, equal to those rows of the whole volume.
/// Depth estimation in horizontal strips uses it to bound memory. Fails naming `rows` for an
/// empty range or one beyond the reference image.
pub fn build_cost_volume_rows(
    reference: &View<'_>,
    sources: &[View<'_>],
    planes: &PlaneSet,
    kind: CostKind,
    rows: std::ops::Range<usize>,
    monitor: &Monitor,
) -> Result<CostVolume> {
    let images = SweepImages::new(reference, sources, planes, kind)?;
    build_cost_volume_rows_in(
        Vec::new(),
        reference,
        sources,
        planes,
        kind,
        rows,
        &images,
        monitor,
    )
}

/// Whether `kind` takes the closed-form direct rows ([`kernel::fill_row_observation`]) with
/// dehazing: the default dehazing volume. `β = 0` keeps the generic row, so that "β = 0 ⇒
/// dehazing = ordinary" stays exact.
fn observation_kernel(kind: CostKind) -> bool {
    matches!(
        kind.dehazing(),
        Some((p, o)) if p.beta > 0.0
            && o.residual == DehazingResidual::ObservationSpace
            && o.range == RangePenalty::Off
    )
}

/// The copies of the images that the row loops read, made once per volume and shared by the
/// strips of [`build_cost_volume_rows_in`] (per strip they were a few megabytes of fresh pages
/// each): 4-lane RGB pixels ([`sample::pad_rgb4`]) and, for sources whose rows are horizontal
/// shifts of the reference's, channel planes ([`shift::planar`]).
///
/// A shifting source's rows read its planes, not its 4-lane copy, so that copy (and the
/// reference's, when every source shifts) is made only when a plane has a row that does not
/// shift after all ([`Rgb4Copy`]): on a rectified pair, 10 MB of copies at 640×480 that no
/// row reads.
pub struct SweepImages {
    ref4: Rgb4Copy,
    sources4: Vec<Rgb4Copy>,
    ref_planar: Vec<f32>,
    shift_planar: Vec<Vec<f32>>,
    /// The reference's noise σ ([`estimate_noise_sigma`], a median over the whole image) where
    /// the cost's range check needs it and its options do not give it, else 0: estimated once,
    /// not once per band of rows.
    noise_sigma: f32,
}

/// A view's [`sample::pad_rgb4`] copy, made now or when first needed.
struct Rgb4Copy {
    copy: std::sync::OnceLock<Vec<[f32; 4]>>,
    /// Whether the cost's loops read this copy at all (else it stays empty).
    wanted: bool,
    /// Subtracted from every value ([`sample::pad_rgb4`]'s offset).
    offset: f32,
}

impl Rgb4Copy {
    /// The copy of `image`, made now, if `now` and the loops want it.
    fn new(image: &ImageF32, wanted: bool, offset: f32, now: bool) -> Self {
        let copy = std::sync::OnceLock::new();
        if wanted && now {
            let _ = copy.set(sample::pad_rgb4(image.data(), offset));
        }
        Self {
            copy,
            wanted,
            offset,
        }
    }

    /// The copy of `image` (the view it was made for), made on the first call where it was
    /// not made up front; empty where the loops do not want it.
    fn get(&self, image: &ImageF32) -> &[[f32; 4]] {
        if !self.wanted {
            return &[];
        }
        self.copy
            .get_or_init(|| sample::pad_rgb4(image.data(), self.offset))
    }

    /// Values in the copy made so far (0 before it is made).
    fn len(&self) -> usize {
        self.copy.get().map_or(0, Vec::len)
    }
}

impl SweepImages {
    /// The copies for these views, planes and cost (validated first, with the errors of
    /// [`build_cost_volume`]).
    pub fn new(
        reference: &View<'_>,
        sources: &[View<'_>],
        planes: &PlaneSet,
        kind: CostKind,
    ) -> Result<Self> {
        validate_inputs(reference, sources, planes, kind)?;
        let (w, h, c) = (
            reference.image.width(),
            reference.image.height(),
            reference.image.channels(),
        );
        let n_planes = planes.num_planes;
        let refd = reference.image.data();
        let dehaze = kind.dehazing().is_some();
        let observation = observation_kernel(kind);
        let relatives: Vec<Pose> = sources
            .iter()
            .map(|s| Pose::relative(&reference.pose, &s.pose))
            .collect();
        // The RGB direct rows' vector loop reads one 4-lane register per pixel, minus the airlight
        // for the dehazing volume; the copies are two passes over the images against W·H·N samples.
        let rgb4_offset = match kind.dehazing() {
            Some((p, _)) if observation => p.airlight,
            _ => 0.0,
        };
        // Eq. 3.7 with a hard or noise-widened range check (not the soft penalty) has a vector
        // loop too, on the plain images.
        let eq37_vector = matches!(
            kind.dehazing(),
            Some((_, o)) if o.residual == DehazingResidual::Eq37
                && !matches!(o.range, RangePenalty::Soft { .. })
        );
        let wanted = c == 3 && (observation || !dehaze || eq37_vector);
        // Channel planes for the direct rows of sources whose rows are horizontal shifts of the
        // reference's (a rectified pair), judged on the middle row and plane; a row that is not a
        // shift after all takes the general loop.
        let shift_copies = || {
            let shifting: Vec<bool> = sources
                .iter()
                .zip(&relatives)
                .map(|(s, rel)| {
                    let direct = observation || !dehaze;
                    let z = planes.depth(n_planes as f64 / 2.0);
                    let mid = PlaneWarp::new(&reference.intrinsics, &s.intrinsics, rel, z)
                        .row((h / 2) as f64);
                    direct && w >= 2 && h >= 2 && mid.shift(w, shift::SHIFT_TOLERANCE_PX).is_some()
                })
                .collect();
            // The sources' planes and the reference's are independent copies: made together.
            rayon::join(
                || {
                    sources
                        .par_iter()
                        .zip(&shifting)
                        .map(|(s, &shifts)| {
                            if shifts {
                                shift::planar(s.image.data(), c, rgb4_offset)
                            } else {
                                Vec::new()
                            }
                        })
                        .collect::<Vec<_>>()
                },
                || {
                    if shifting.iter().any(|&s| s) {
                        shift::planar(refd, c, rgb4_offset)
                    } else {
                        Vec::new()
                    }
                },
            )
        };
        let noise = || match kind.dehazing() {
            Some((_, o))
                if o.noise_sigma.is_none()
                    && matches!(
                        o.range,
                        RangePenalty::NoiseAware { .. }
                            | RangePenalty::ReferenceAware { .. }
                            | RangePenalty::Soft { .. }
                    ) =>
            {
                estimate_noise_sigma(reference.image)
            }
            _ => 0.0,
        };
        // The copies and the noise estimate are independent passes over the images: run together.
        // A source with shift planes gets its 4-lane copy only if a row needs it.
        let ((shift_planar, ref_planar), noise_sigma) = rayon::join(shift_copies, noise);
        let all_shift = shift_planar.iter().all(|p| !p.is_empty());
        let (ref4, sources4) = rayon::join(
            || Rgb4Copy::new(reference.image, wanted, rgb4_offset, !all_shift),
            || {
                sources
                    .par_iter()
                    .zip(&shift_planar)
                    .map(|(s, planar)| {
                        Rgb4Copy::new(s.image, wanted, rgb4_offset, planar.is_empty())
                    })
                    .collect::<Vec<_>>()
            },
        );
        Ok(Self {
            ref4,
            sources4,
            ref_planar,
            shift_planar,
            noise_sigma,
        })
    }

    /// Whether every copy is empty or the size of its view's image (the loops index them by
    /// the views' sizes).
    fn fits(&self, reference: &View<'_>, sources: &[View<'_>]) -> bool {
        let sized = |len: usize, img: &ImageF32, per_pixel: usize| {
            len == 0 || len == img.width() * img.height() * per_pixel
        };
        let c = reference.image.channels();
        self.sources4.len() == sources.len()
            && self.shift_planar.len() == sources.len()
            && sized(self.ref4.len(), reference.image, 1)
            && sized(self.ref_planar.len(), reference.image, c)
            && sources.iter().enumerate().all(|(k, s)| {
                sized(self.sources4[k].len(), s.image, 1)
                    && sized(self.shift_planar[k].len(), s.image, c)
            })
    }
}

/// [`build_cost_volume_rows`] into `buffer`'s memory when its capacity holds the volume (its
/// contents do not matter), so that depth estimated strip by strip reuses the previous strip's
/// volumes instead of faulting in fresh pages for each, with the image copies `images` made
/// once for all strips ([`SweepImages::new`] of the same views, planes and cost).
#[allow(clippy::too_many_arguments)]
pub fn build_cost_volume_rows_in(
    buffer: Vec<f32>,
    reference: &View<'_>,
    sources: &[View<'_>],
    planes: &PlaneSet,
    kind: CostKind,
    rows: std::ops::Range<usize>,
    images: &SweepImages,
    monitor: &Monitor,
) -> Result<CostVolume> {
    validate_inputs(reference, sources, planes, kind)?;
    let voxels = volume_voxels(reference.image.width(), rows.len(), planes.num_planes)?;
    let mut data = crate::large_buffer::reuse(buffer, voxels);
    let layout = RowsLayout {
        plane_stride: reference.image.width() * rows.len(),
        first_row: 0,
    };
    fill_cost_rows(
        &mut data,
        layout,
        reference,
        sources,
        planes,
        kind,
        rows.clone(),
        images,
        monitor,
    )?;
    Ok(CostVolume {
        width: reference.image.width(),
        height: rows.len(),
        planes: *planes,
        penalty: penalty_for(reference.image.channels()),
        data,
    })
}

/// `w × rows × planes` voxels, or an error naming `planes.num_planes` beyond [`MAX_VOXELS`].
fn volume_voxels(w: usize, rows: usize, n_planes: usize) -> Result<usize> {
    w.checked_mul(rows)
        .and_then(|p| p.checked_mul(n_planes))
        .filter(|&v| v <= MAX_VOXELS)
        .ok_or_else(|| {
            MurkError::invalid(
                "planes.num_planes",
                format!("{w}x{rows} pixels x {n_planes} planes exceeds the limit of {MAX_VOXELS} voxels"),
            )
        })
}

/// Where [`fill_cost_rows`] writes in its buffer: plane `i`'s rows start at
/// `i · plane_stride + first_row · W`, so a caller can keep rows it already has in front of them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RowsLayout {
    /// Values from one plane's rows to the next plane's.
    pub plane_stride: usize,
    /// Rows of each plane's part before the written ones.
    pub first_row: usize,
}

/// The cost volume's rows `rows` ([`build_cost_volume_rows_in`]'s values) written into `out` as
/// `layout` says (`planes.num_planes · plane_stride` values; the values outside the written rows
/// are left as they are), for a caller that builds a strip a band of rows at a time, each band
/// windowed while in cache. The views are not validated again: `images` must come from
/// [`SweepImages::new`] of the same views, planes and cost, which validates them (only their
/// sizes are checked here, naming `images`; rows outside the reference are refused naming
/// `rows`, a buffer or layout that does not hold them naming `out`).
#[allow(clippy::too_many_arguments)]
pub fn fill_cost_rows(
    out: &mut [f32],
    layout: RowsLayout,
    reference: &View<'_>,
    sources: &[View<'_>],
    planes: &PlaneSet,
    kind: CostKind,
    rows: std::ops::Range<usize>,
    images: &SweepImages,
    monitor: &Monitor,
) -> Result<()> {
    let cost_rows = CostRows::new(reference, sources, planes, kind, rows.clone(), images)?;
    let w = reference.image.width();
    let n_planes = planes.num_planes;
    let RowsLayout {
        plane_stride,
        first_row,
    } = layout;
    if plane_stride < (first_row + rows.len()) * w || out.len() != plane_stride * n_planes {
        return Err(MurkError::invalid(
            "out",
            format!(
                "{} values with {plane_stride} per plane cannot hold rows {first_row}.. of \
                 {w}x{} pixels x {n_planes} planes",
                out.len(),
                rows.len()
            ),
        ));
    }
    let n_pix = w * rows.len();
    let done = std::sync::atomic::AtomicUsize::new(0);
    // One rayon task per plane: a plane is ~50k voxels of independent work, and parallelising
    // over planes instead of over each plane's rows saves a fork-join (and the workers' sleep
    // and wake-up) per plane. Each worker reuses its row scratch and source list across planes.
    out.par_chunks_mut(plane_stride)
        .enumerate()
        .try_for_each_init(CostScratch::default, |scratch, (i, plane)| -> Result<()> {
            monitor.checkpoint()?;
            cost_rows.fill_plane(i, &mut plane[first_row * w..][..n_pix], scratch);
            let k = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            monitor.progress("mvs.cost_volume", k as f32 / n_planes as f32);
            Ok(())
        })
}

/// Per-worker buffers of [`CostRows::fill_plane`], reused from plane to plane: the row scratch
/// and the plane's list of sources.
#[derive(Default)]
pub struct CostScratch<'a> {
    rows: RowScratch,
    sources: Vec<SourcePlane<'a>>,
}

/// The cost volume's rows `rows` of the views, ready to be written a plane at a time
/// ([`CostRows::fill_plane`]): a caller that runs more per plane than the costs (the box window
/// of a group of planes while their rows are in L2) calls it from its own tasks.
pub struct CostRows<'a> {
    reference: &'a View<'a>,
    sources: &'a [View<'a>],
    planes: &'a PlaneSet,
    kind: CostKind,
    rows: std::ops::Range<usize>,
    images: &'a SweepImages,
    relatives: Vec<Pose>,
    /// Noise margins (observation units) of the hard range check on the reference and on the
    /// sources (0 for Eq. 3.7, ∞ for none), and of the soft one.
    margin: f32,
    src_margin: f32,
    soft_margin: Option<f32>,
}

impl<'a> CostRows<'a> {
    /// The rows `rows` of the views' costs. The views are not validated again: `images` must
    /// come from [`SweepImages::new`] of the same views, planes and cost, which validates them
    /// (only their sizes are checked here, naming `images`; rows outside the reference are
    /// refused naming `rows`).
    pub fn new(
        reference: &'a View<'a>,
        sources: &'a [View<'a>],
        planes: &'a PlaneSet,
        kind: CostKind,
        rows: std::ops::Range<usize>,
        images: &'a SweepImages,
    ) -> Result<Self> {
        if !images.fits(reference, sources) {
            return Err(MurkError::invalid(
                "images",
                "the image copies were made from other views (SweepImages::new of these views)",
            ));
        }
        if rows.is_empty() || rows.end > reference.image.height() {
            return Err(MurkError::invalid(
                "rows",
                format!(
                    "rows {}..{} are empty or outside the reference's {} rows",
                    rows.start,
                    rows.end,
                    reference.image.height()
                ),
            ));
        }
        let sigma = |o: &DehazingOptions| o.noise_sigma.unwrap_or(images.noise_sigma);
        let (margin, src_margin, soft_margin) = match kind.dehazing() {
            None => (0.0, 0.0, None),
            Some((_, o)) => match o.range {
                RangePenalty::Hard => (0.0, 0.0, None),
                RangePenalty::Off => (f32::INFINITY, f32::INFINITY, None),
                RangePenalty::NoiseAware { k } => (k * sigma(&o), k * sigma(&o), None),
                RangePenalty::ReferenceAware { k } => (k * sigma(&o), f32::INFINITY, None),
                RangePenalty::Soft { k } => (f32::INFINITY, f32::INFINITY, Some(k * sigma(&o))),
            },
        };
        let relatives = sources
            .iter()
            .map(|s| Pose::relative(&reference.pose, &s.pose))
            .collect();
        Ok(Self {
            reference,
            sources,
            planes,
            kind,
            rows,
            images,
            relatives,
            margin,
            src_margin,
            soft_margin,
        })
    }

    /// Plane `i`'s costs of the rows into `out` (`rows.len() · W` values, row after row). Every
    /// value is assigned (`mean_or_penalty` ends each row), so `out` may hold anything.
    pub fn fill_plane(&self, i: usize, out: &mut [f32], scratch: &mut CostScratch<'a>) {
        let (w, h, c) = (
            self.reference.image.width(),
            self.reference.image.height(),
            self.reference.image.channels(),
        );
        assert_eq!(out.len(), w * self.rows.len(), "a plane's rows");
        let SweepImages {
            ref4,
            sources4,
            ref_planar,
            shift_planar,
            ..
        } = self.images;
        let z = self.planes.depth(i as f64);
        let reference = self.reference;
        let plane_sources = &mut scratch.sources;
        plane_sources.clear();
        // Whether every row of this plane reads the source's shift planes (the row loops'
        // own test), so that its 4-lane copy is not needed.
        let shifts = |planar: &[f32], warp: &PlaneWarp| {
            self.rows
                .clone()
                .all(|y| shift::row_shift(planar, ref_planar, &warp.row(y as f64), w).is_some())
        };
        let mut every_source_shifts = true;
        plane_sources.extend(
            self.sources
                .iter()
                .zip(&self.relatives)
                .zip(sources4)
                .zip(shift_planar)
                .map(|(((s, rel), copy), planar)| {
                    let warp = PlaneWarp::new(&reference.intrinsics, &s.intrinsics, rel, z);
                    let padded = if shifts(planar, &warp) {
                        &[]
                    } else {
                        every_source_shifts = false;
                        copy.get(s.image)
                    };
                    SourcePlane {
                        data: s.image.data(),
                        padded,
                        planar,
                        warp,
                    }
                }),
        );
        let ref4 = if every_source_shifts {
            &[]
        } else {
            ref4.get(reference.image)
        };
        let haze = match self.kind.dehazing() {
            None => Haze::CLEAR,
            Some((p, o)) => {
                let t = transmission(p.beta, z as f32);
                let inv_t = inverse_transmission(t);
                Haze {
                    airlight: p.airlight,
                    beta: p.beta,
                    ref_inv_t: inv_t,
                    ref_offset: p.airlight * (1.0 - inv_t),
                    ref_t: t.max(crate::atmosphere::MIN_TRANSMISSION),
                    residual: o.residual,
                    ref_lo: -self.margin * inv_t,
                    ref_hi: 1.0 + self.margin * inv_t,
                    src_margin: self.src_margin,
                    soft_margin: self.soft_margin,
                }
            }
        };
        let penalty = penalty_for(c);
        let refd = reference.image.data();
        let dehaze = self.kind.dehazing().is_some();
        let observation = observation_kernel(self.kind);
        let srcs = &plane_sources[..];
        let images = ReferenceImages {
            data: refd,
            rgb4: ref4,
            planar: ref_planar,
        };
        let scratch = &mut scratch.rows;
        for (k, row) in out.chunks_exact_mut(w).enumerate() {
            let y = self.rows.start + k;
            match (c, dehaze) {
                (1, true) if observation => fill_row_observation::<1, true>(
                    row, y, images, w, h, srcs, haze, penalty, scratch,
                ),
                (_, true) if observation => fill_row_observation::<3, true>(
                    row, y, images, w, h, srcs, haze, penalty, scratch,
                ),
                // The ordinary volume's direct row (bit-identical to the generic one).
                (1, false) => fill_row_observation::<1, false>(
                    row, y, images, w, h, srcs, haze, penalty, scratch,
                ),
                (_, false) => fill_row_observation::<3, false>(
                    row, y, images, w, h, srcs, haze, penalty, scratch,
                ),
                (1, true) => fill_row::<1, true>(row, y, refd, w, h, srcs, haze, penalty, scratch),
                (_, true) => fill_row::<3, true>(row, y, refd, w, h, srcs, haze, penalty, scratch),
            }
        }
    }
}

#[cfg(test)]
mod tests;
