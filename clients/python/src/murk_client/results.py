"""Results as numpy arrays, named as in the proto's result messages.

Every result keeps the message it came from in ``proto`` (for fields not surfaced here) and the
job's id in ``job_id``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from google.protobuf.message import Message

from ._proto.murk.v1 import jobs_pb2, mvs_pb2, params_pb2, ps_pb2, stereo_pb2, tof_pb2
from .errors import MurkError
from .images import FloatImage, from_proto


def _cost_volume_name(kind: int) -> str:
    """The client's name of a ``CostVolumeKind`` (UNSPECIFIED is the server's default, dehazing)."""
    names: dict[int, str] = {
        mvs_pb2.COST_VOLUME_KIND_ORDINARY: "ordinary",
        mvs_pb2.COST_VOLUME_KIND_DEHAZING_EQ37: "eq37",
    }
    return names.get(int(kind), "dehazing")


def _optional_image(result: Message, name: str, method: str) -> FloatImage | None:
    """The result image ``name``, decoded, or None where the request did not ask for it."""
    return from_proto(getattr(result, name), field=f"{method}.{name}") if result.HasField(name) else None


@dataclass(frozen=True)
class TofDepthResult:
    """ToF depth in fog; every array is ``(h, w)`` float32 of the input size.

    An image the request did not ask for (``outputs``) is ``None``; a sensor session returns only
    the z-depth (the range without intrinsics), the mask and ``range_std_m`` unless told otherwise.
    """

    #: Corrected range along the viewing ray, metres.
    range_m: FloatImage | None
    #: Corrected z-depth, metres (None without intrinsics).
    z_depth_m: FloatImage | None
    #: Range from the raw (foggy) phase, metres.
    raw_range_m: FloatImage | None
    #: z-depth from the raw phase, metres (None without intrinsics).
    raw_z_depth_m: FloatImage | None
    #: Standard deviation of range_m, metres.
    range_std_m: FloatImage | None
    #: Object mask: 1 = object, 0 = background, 127/255 (about 0.498) = uncertain (beside an
    #: object, too dim to call either way). ``mask > 0.5`` is the object, ``mask > 0`` the object
    #: or what may be part of it.
    mask: FloatImage | None
    #: Estimated scattering component: amplitude (sensor units) and phase (radians).
    scatter_amplitude: FloatImage | None
    scatter_phase: FloatImage | None
    #: Final IRLS weights in [0, 1].
    weight_amplitude: FloatImage | None
    weight_phase: FloatImage | None
    #: Direct component: amplitude and phase (radians).
    corrected_amplitude: FloatImage | None
    corrected_phase: FloatImage | None
    #: What the caller should know about the estimate, one sentence each (e.g. an IRLS that
    #: stopped at its iteration cap before converging).
    warnings: tuple[str, ...]
    job_id: str
    proto: tof_pb2.TofDepthResult
    #: With ``return_points``: the measured pixels in the camera frame (x right, y down, z
    #: forward, metres), ``(n, 3)`` float32, grey from the direct amplitude, ``(n, 3)`` uint8;
    #: else ``None``.
    points: npt.NDArray[np.float32] | None = None
    colors: npt.NDArray[np.uint8] | None = None

    @classmethod
    def from_proto(cls, r: tof_pb2.TofDepthResult, job_id: str = "") -> TofDepthResult:
        """From the result message."""
        points, colors = _points(r, "tof_depth", job_id)

        def image(name: str) -> FloatImage | None:
            return _optional_image(r, name, "tof_depth")

        return cls(
            range_m=image("range_m"),
            z_depth_m=image("z_depth_m"),
            raw_range_m=image("raw_range_m"),
            raw_z_depth_m=image("raw_z_depth_m"),
            range_std_m=image("range_std_m"),
            mask=image("mask"),
            scatter_amplitude=image("scatter_amplitude"),
            scatter_phase=image("scatter_phase"),
            weight_amplitude=image("weight_amplitude"),
            weight_phase=image("weight_phase"),
            corrected_amplitude=image("corrected_amplitude"),
            corrected_phase=image("corrected_phase"),
            warnings=tuple(r.warnings),
            job_id=job_id,
            proto=r,
            points=points,
            colors=colors,
        )


@dataclass(frozen=True)
class MvsDepthResult:
    """MVS depth of the reference view; arrays ``(h, w)`` float32 of the reference's size."""

    #: z-depth along the reference camera's optical axis, scene units.
    z_depth: FloatImage
    #: Inverse z-depth, per scene unit.
    inverse_depth: FloatImage
    #: Confidence in [0, 1] (0 = no preference among planes).
    confidence: FloatImage
    #: The plane set used: nearest and farthest z-depth (scene units) and count.
    near: float
    far: float
    num_planes: int
    #: ``"dehazing"``, ``"eq37"`` or ``"ordinary"``.
    cost_volume: str
    compute_seconds: float
    #: The gain each source's channels were divided by (brightness relative to the reference),
    #: source-major, one per image channel; exactly 1.0 within 0.5 % of 1 or with compensation off.
    source_gains: tuple[float, ...]
    #: The lens fall-off ``a`` divided out of every view (corners at ``1 + a`` of the centre's
    #: brightness); exactly 0.0 below 0.05 in magnitude, when it explains under 1.5 % of the
    #: matching cost, or with compensation off.
    vignetting_falloff: float
    #: What the caller should know about the estimate, one sentence each (e.g. a gain at the end
    #: of its searched range).
    warnings: tuple[str, ...]
    #: Each source's own lens fall-off relative to the reference's, ``delta`` of ``1 + delta r^2``
    #: divided out of that source; exactly 0.0 below 0.05 in magnitude or with compensation off.
    source_falloffs: tuple[float, ...]
    job_id: str
    proto: mvs_pb2.MvsDepthResult

    @classmethod
    def from_proto(cls, r: mvs_pb2.MvsDepthResult, job_id: str = "") -> MvsDepthResult:
        """From the result message."""
        return cls(
            z_depth=from_proto(r.z_depth, field="mvs_depth.z_depth"),
            inverse_depth=from_proto(r.inverse_depth, field="mvs_depth.inverse_depth"),
            confidence=from_proto(r.confidence, field="mvs_depth.confidence"),
            near=r.near,
            far=r.far,
            num_planes=r.num_planes,
            cost_volume=_cost_volume_name(r.cost_volume),
            compute_seconds=r.compute_seconds,
            source_gains=tuple(r.source_gains),
            vignetting_falloff=r.vignetting_falloff,
            warnings=tuple(r.warnings),
            source_falloffs=tuple(r.source_falloffs),
            job_id=job_id,
            proto=r,
        )


@dataclass(frozen=True)
class ResidualSample:
    """One evaluation of Algorithm 1's objective."""

    #: ``"beta"`` (Eq. 3.10, A = A0) or ``"joint"`` (the A x β grid of Eq. 3.8).
    stage: str
    airlight: float
    beta_per_scene_unit: float
    #: Mean Eq. 3.9 residual over the SfM pixels, scene units.
    residual: float


@dataclass(frozen=True)
class AirlightConflict:
    """The joint fit's A* against the airlight estimator's A0, when they disagree by more than 3
    of ``sqrt(airlight_initial_error**2 + fitted_airlight_std_error**2)``: the likeliest cause is
    a wrong SfM model (its translation directions off), else an estimator outside its range."""

    fitted_airlight: float
    fitted_airlight_std_error: float
    airlight_initial: float
    #: The estimator's typical error the test used (CNN 0.03, dark channel 0.11, a given A0 the
    #: request's prior scale).
    airlight_initial_error: float
    #: ``|A* - A0|`` over the combined error.
    sigmas: float


@dataclass(frozen=True)
class PoseError:
    """The SfM poses' share of the joint fit's standard errors, from the request's observations."""

    #: The poses' share of A's and β's (per scene unit) standard errors; None when it could not
    #: be computed (``undetermined`` says why).
    airlight_std_error: float | None
    beta_std_error_per_scene_unit: float | None
    #: Observations and points (seen by two or more views) behind the poses' covariance.
    observations: int
    points: int
    #: Reprojection error per degree of freedom, pixels.
    reprojection_rms_px: float
    #: The sources' largest 1-sigma rotation and baseline-direction turn, degrees.
    max_rotation_std_deg: float
    max_baseline_direction_std_deg: float
    #: Why the share could not be computed; empty when it was.
    undetermined: str

    @classmethod
    def from_proto(cls, p: params_pb2.PoseError) -> PoseError:
        """From the result's message."""
        return cls(
            airlight_std_error=p.airlight_std_error if p.HasField("airlight_std_error") else None,
            beta_std_error_per_scene_unit=p.beta_std_error if p.HasField("beta_std_error") else None,
            observations=p.observations,
            points=p.points,
            reprojection_rms_px=p.reprojection_rms_px,
            max_rotation_std_deg=p.max_rotation_std_deg,
            max_baseline_direction_std_deg=p.max_baseline_direction_std_deg,
            undetermined=p.undetermined,
        )


@dataclass(frozen=True)
class SamplingShare:
    """Where SfM put its points: their share of the joint fit's standard errors, from the same
    model refitted on the points sampled with twice the blur."""

    #: The blur of the fit's samples and the wider one, pixels.
    base_blur_px: float
    wide_blur_px: float
    #: A and β (per scene unit) refitted at the wider blur; None when that refit failed.
    refit_airlight: float | None
    refit_beta_per_scene_unit: float | None
    #: The share of A's and β's standard errors (how far they moved); None with the refit.
    airlight_std_error: float | None
    beta_std_error_per_scene_unit: float | None

    @classmethod
    def from_proto(cls, p: params_pb2.SamplingShare) -> SamplingShare:
        """From the result's message."""

        return cls(
            base_blur_px=p.base_blur_px,
            wide_blur_px=p.wide_blur_px,
            refit_airlight=p.refit_airlight if p.HasField("refit_airlight") else None,
            refit_beta_per_scene_unit=p.refit_beta if p.HasField("refit_beta") else None,
            airlight_std_error=p.airlight_std_error if p.HasField("airlight_std_error") else None,
            beta_std_error_per_scene_unit=p.beta_std_error if p.HasField("beta_std_error") else None,
        )


@dataclass(frozen=True)
class PointRelief:
    """How far the SfM points stand out of one plane in the reference camera."""

    #: Points behind the plane fit.
    points: int
    #: Median distance of the points to the least-squares plane over their median depth.
    relief: float
    #: Angle between the plane's normal and the optical axis, degrees (0 = facing the camera).
    tilt_deg: float
    #: A flat cloud facing the reference (relief below 0.04, tilt at most 45°): SfM's poses may
    #: be wrong by several degrees with small errors, and an identifiable estimate is "weak_sfm".
    ambiguous: bool

    @classmethod
    def from_proto(cls, p: params_pb2.PointRelief) -> PointRelief:
        """From the result's message."""
        return cls(points=p.points, relief=p.relief, tilt_deg=p.tilt_deg, ambiguous=p.ambiguous)


@dataclass(frozen=True)
class ScatteringParamsResult:
    """A*, β* of Algorithm 1 and the depth with them, with what the data say about them."""

    airlight: float
    #: β*, per scene unit.
    beta_per_scene_unit: float
    #: Standard errors of A* and β* (per scene unit); None when A* is the estimator's A0 or β*
    #: came from the sweep (no error model).
    airlight_std_error: float | None
    beta_std_error_per_scene_unit: float | None
    #: Whether the SfM points determine β*; when False β* is a guess, see ``identifiability``.
    identifiable: bool
    #: ``"identifiable"``, ``"no_depth_difference"`` (a rectified pair or sideways motion),
    #: ``"too_few_points"``, ``"flat_residual"``, ``"airlight_conflict"`` (the points' A
    #: disagrees with the image's airlight estimate: the SfM model is likely wrong; see
    #: ``airlight_conflict``), ``"airlight_at_bound"`` (the fit's A sits on the bound of its
    #: range, so the standard errors do not hold) or ``"weak_sfm"`` (the SfM input cannot pin
    #: β down: its poses are too uncertain, see ``pose_error``, or ambiguous, see ``relief``, or
    #: its points' intensities depend on how they are sampled, see ``sampling``). ``warnings``
    #: gives the numbers.
    identifiability: str
    #: ``"joint_fit"`` (A, β and source gains fitted to the points), ``"point_ratio"`` or
    #: ``"sweep"``.
    beta_source: str
    #: The β range used, per scene unit, and whether it came from the points' depths.
    beta_range_per_scene_unit: tuple[float, float]
    beta_range_from_points: bool
    #: ``None``, or ``"min"``/``"max"``: the end of the range β* was clamped to (the estimate
    #: before clamping is ``beta_unclamped_per_scene_unit``).
    beta_bound: str | None
    beta_unclamped_per_scene_unit: float
    #: Per source, its exposure gain relative to the reference from the joint fit.
    source_gains: list[float]
    #: The lens fall-off ``a`` from the joint fit (corners at ``1 + a`` of the centre's brightness).
    vignetting_falloff: float
    #: Per source, its lens fall-off relative to the reference's from the joint fit (0.0 unless
    #: the points determine one).
    source_falloffs: list[float]
    airlight_initial: float
    #: ``"cnn"``, ``"dark_channel"`` or ``"given"``.
    airlight_source: str
    beta_initial_per_scene_unit: float
    #: Mean Eq. 3.9 residual at (A*, β*), scene units.
    residual: float
    grid: list[ResidualSample]
    num_sparse_points: int
    depth: MvsDepthResult
    #: Set when the joint fit's A* and the estimator's A0 disagree beyond both their errors
    #: (``identifiability`` is then ``"airlight_conflict"`` unless the fit had another reason);
    #: None otherwise, and from servers before murk-algorithms-17.
    airlight_conflict: AirlightConflict | None
    #: What the caller should know about the estimate, one sentence each.
    warnings: tuple[str, ...]
    job_id: str
    proto: params_pb2.ScatteringParamsResult
    #: The SfM poses' share of the standard errors (included in them), when the request carried
    #: observations and the fit determined β with a finite error; None otherwise.
    pose_error: PoseError | None = None
    #: How far the SfM points stand out of one plane (None with fewer than 10 points).
    relief: PointRelief | None = None
    #: Where SfM put its points: their share of the standard errors (included in them), when
    #: the fit determined β with a finite error; None otherwise.
    sampling: SamplingShare | None = None

    @classmethod
    def from_proto(cls, r: params_pb2.ScatteringParamsResult, job_id: str = "") -> ScatteringParamsResult:
        """From the result message."""
        sources = {
            params_pb2.AIRLIGHT_SOURCE_CNN: "cnn",
            params_pb2.AIRLIGHT_SOURCE_DARK_CHANNEL: "dark_channel",
            params_pb2.AIRLIGHT_SOURCE_GIVEN: "given",
        }
        identifiability = {
            params_pb2.IDENTIFIABILITY_IDENTIFIABLE: "identifiable",
            params_pb2.IDENTIFIABILITY_NO_DEPTH_DIFFERENCE: "no_depth_difference",
            params_pb2.IDENTIFIABILITY_TOO_FEW_POINTS: "too_few_points",
            params_pb2.IDENTIFIABILITY_FLAT_RESIDUAL: "flat_residual",
            params_pb2.IDENTIFIABILITY_AIRLIGHT_CONFLICT: "airlight_conflict",
            params_pb2.IDENTIFIABILITY_AIRLIGHT_AT_BOUND: "airlight_at_bound",
            params_pb2.IDENTIFIABILITY_WEAK_SFM: "weak_sfm",
        }
        beta_sources = {
            params_pb2.BETA_SOURCE_JOINT_FIT: "joint_fit",
            params_pb2.BETA_SOURCE_POINT_RATIO: "point_ratio",
            params_pb2.BETA_SOURCE_SWEEP: "sweep",
        }
        bounds = {params_pb2.BETA_BOUND_MIN: "min", params_pb2.BETA_BOUND_MAX: "max"}
        return cls(
            airlight=r.airlight,
            beta_per_scene_unit=r.beta,
            airlight_std_error=r.airlight_std_error if r.HasField("airlight_std_error") else None,
            beta_std_error_per_scene_unit=r.beta_std_error if r.HasField("beta_std_error") else None,
            identifiable=r.identifiable,
            identifiability=identifiability.get(r.identifiability, "unspecified"),
            beta_source=beta_sources.get(r.beta_source, "unspecified"),
            beta_range_per_scene_unit=(r.beta_min, r.beta_max),
            beta_range_from_points=r.beta_range_from_points,
            beta_bound=bounds.get(r.beta_bound),
            beta_unclamped_per_scene_unit=r.beta_unclamped,
            source_gains=list(r.joint_fit.source_gains),
            vignetting_falloff=r.joint_fit.vignetting_falloff,
            source_falloffs=list(r.joint_fit.source_falloffs),
            airlight_initial=r.airlight_initial,
            airlight_source=sources.get(r.airlight_source, "unspecified"),
            beta_initial_per_scene_unit=r.beta_initial,
            residual=r.residual,
            grid=[
                ResidualSample(
                    "joint" if g.stage == params_pb2.SEARCH_STAGE_JOINT else "beta",
                    g.airlight,
                    g.beta,
                    g.residual,
                )
                for g in r.grid
            ],
            num_sparse_points=r.num_sparse_points,
            depth=MvsDepthResult.from_proto(r.depth, job_id),
            airlight_conflict=(
                AirlightConflict(
                    fitted_airlight=r.airlight_conflict.fitted_airlight,
                    fitted_airlight_std_error=r.airlight_conflict.fitted_airlight_std_error,
                    airlight_initial=r.airlight_conflict.airlight_initial,
                    airlight_initial_error=r.airlight_conflict.airlight_initial_error,
                    sigmas=r.airlight_conflict.sigmas,
                )
                if r.HasField("airlight_conflict")
                else None
            ),
            warnings=tuple(r.warnings),
            job_id=job_id,
            proto=r,
            pose_error=PoseError.from_proto(r.pose_error) if r.HasField("pose_error") else None,
            relief=PointRelief.from_proto(r.relief) if r.HasField("relief") else None,
            sampling=SamplingShare.from_proto(r.sampling) if r.HasField("sampling") else None,
        )


@dataclass(frozen=True)
class PhotometricStereoResult:
    """Shape of the object in turbid water; arrays of the images' size."""

    #: Unit normals ``(h, w, 3)``, camera frame, towards the camera; (0, 0, -1) off the object.
    normals: FloatImage
    #: Albedo ``(h, w)``; 0 off the object.
    albedo: FloatImage
    #: z-depth ``(h, w)``, millimetres; NaN off the object.
    depth_mm: FloatImage
    #: Normals after each iteration, when requested (``return_iteration_normals``).
    iteration_normals: list[FloatImage]
    #: Per-iteration diagnostics (``PsIteration`` messages; ``distance_fit`` says how each
    #: iteration's scale was fitted to the lights' fall-off).
    iterations: list[ps_pb2.PsIteration]
    #: The object's mean z-depth the result ends at, mm (fitted unless ``fix_distance``).
    mean_depth_mm: float
    total_seconds: float
    job_id: str
    proto: ps_pb2.PhotometricStereoResult

    @classmethod
    def from_proto(cls, r: ps_pb2.PhotometricStereoResult, job_id: str = "") -> PhotometricStereoResult:
        """From the result message."""
        return cls(
            normals=from_proto(r.normals, field="photometric_stereo.normals"),
            albedo=from_proto(r.albedo, field="photometric_stereo.albedo"),
            depth_mm=from_proto(r.depth_mm, field="photometric_stereo.depth_mm"),
            iteration_normals=[
                from_proto(n, field=f"photometric_stereo.iteration_normals[{i}]")
                for i, n in enumerate(r.iteration_normals)
            ],
            iterations=list(r.iterations),
            mean_depth_mm=r.iterations[-1].mean_depth_mm if r.iterations else float("nan"),
            total_seconds=r.total_seconds,
            job_id=job_id,
            proto=r,
        )


@dataclass(frozen=True)
class RectifiedStereoResult:
    """Depth of a rectified pair's left view; arrays ``(h, w)`` float32 of the left image's size.

    An image the request did not ask for (``outputs``) is ``None``; a sensor session returns only
    the z-depth and the confidence unless told otherwise.
    """

    #: z-depth along the left camera's optical axis, in the baseline's unit.
    z_depth: FloatImage | None
    #: Disparity ``u_left - u_right``, pixels (``fx * baseline / z - doffs``).
    disparity: FloatImage | None
    #: Confidence in [0, 1] (0 where the consistency check or the speckle filter rejected the
    #: pixel; its depth there is filled from its neighbours).
    confidence: FloatImage | None
    #: With ``return_points``: the confident pixels in the left camera's frame (x right, y down,
    #: z forward), ``(n, 3)`` float32, and their colours, ``(n, 3)`` uint8; else ``None``.
    points: npt.NDArray[np.float32] | None
    colors: npt.NDArray[np.uint8] | None
    #: The planes searched: nearest and farthest z-depth, count, and the disparity range.
    near: float
    far: float
    num_planes: int
    min_disparity_px: float
    max_disparity_px: float
    #: ``"dehazing"``, ``"eq37"`` or ``"ordinary"``.
    cost_volume: str
    compute_seconds: float
    #: The right image's gain per channel relative to the left's (divided out).
    right_gains: tuple[float, ...]
    vignetting_falloff: float
    right_falloff: float
    warnings: tuple[str, ...]
    job_id: str
    proto: stereo_pb2.RectifiedStereoResult

    @classmethod
    def from_proto(cls, r: stereo_pb2.RectifiedStereoResult, job_id: str = "") -> RectifiedStereoResult:
        """From the result message."""
        points, colors = _points(r, "rectified_stereo", job_id)

        def image(name: str) -> FloatImage | None:
            return _optional_image(r, name, "rectified_stereo")

        return cls(
            z_depth=image("z_depth"),
            disparity=image("disparity"),
            confidence=image("confidence"),
            points=points,
            colors=colors,
            near=r.near,
            far=r.far,
            num_planes=r.num_planes,
            min_disparity_px=r.min_disparity_px,
            max_disparity_px=r.max_disparity_px,
            cost_volume=_cost_volume_name(r.cost_volume),
            compute_seconds=r.compute_seconds,
            right_gains=tuple(r.right_gains),
            vignetting_falloff=r.vignetting_falloff,
            right_falloff=r.right_falloff,
            warnings=tuple(r.warnings),
            job_id=job_id,
            proto=r,
        )


Result = (
    TofDepthResult | MvsDepthResult | RectifiedStereoResult | ScatteringParamsResult | PhotometricStereoResult
)


def from_job_result(r: jobs_pb2.JobResult, job_id: str) -> Result:
    """The typed result of whichever method ``r`` holds."""
    which = r.WhichOneof("method")
    if which == "tof_depth":
        return TofDepthResult.from_proto(r.tof_depth, job_id)
    if which == "mvs_depth":
        return MvsDepthResult.from_proto(r.mvs_depth, job_id)
    if which == "rectified_stereo":
        return RectifiedStereoResult.from_proto(r.rectified_stereo, job_id)
    if which == "scattering_params":
        return ScatteringParamsResult.from_proto(r.scattering_params, job_id)
    if which == "photometric_stereo":
        return PhotometricStereoResult.from_proto(r.photometric_stereo, job_id)
    raise MurkError(f"job {job_id}: result of an unknown method (a newer server?)", job_id=job_id)


def _points(
    r: tof_pb2.TofDepthResult | stereo_pb2.RectifiedStereoResult, method: str, job_id: str
) -> tuple[npt.NDArray[np.float32] | None, npt.NDArray[np.uint8] | None]:
    """A result's ``points`` as ``(n, 3)`` positions and colours, or ``(None, None)``."""
    if not r.HasField("points"):
        return None, None
    n = r.points.count
    if len(r.points.xyz_f32_le) != 12 * n or len(r.points.rgb8) != 3 * n:
        raise MurkError(
            f"{method}.points: {n} points need {12 * n} position and {3 * n} "
            f"colour bytes, got {len(r.points.xyz_f32_le)} and {len(r.points.rgb8)}",
            job_id=job_id,
        )
    points = np.frombuffer(r.points.xyz_f32_le, dtype="<f4").reshape(n, 3).astype(np.float32)
    colors = np.frombuffer(r.points.rgb8, dtype=np.uint8).reshape(n, 3).copy()
    return points, colors
