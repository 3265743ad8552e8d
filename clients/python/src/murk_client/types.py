"""Plain Python values of the API: cameras, poses, views, lights, job states.

Units are in the names: metres for ToF (``light_position_m``), millimetres for photometric
stereo (``position_mm``), *scene units* for MVS and the scattering parameters (the unit of the
poses: a COLMAP model's arbitrary SfM scale, metres only for a metric model).
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timezone

import numpy as np
import numpy.typing as npt

from ._proto.murk.v1 import common_pb2, jobs_pb2
from .errors import ClientInputError
from .images import ImageLike

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels: ``u = fx*x/z + skew*y/z + cx``, ``v = fy*y/z + cy``.

    Pixel (0, 0) is the **centre** of the top-left pixel. COLMAP (and OpenCV's calibration of
    images whose origin is the pixel corner) puts the principal point 0.5 px further: use
    :meth:`from_colmap` for COLMAP's ``PINHOLE`` parameters.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    skew: float = 0.0

    @classmethod
    def from_colmap(cls, fx: float, fy: float, cx: float, cy: float) -> Intrinsics:
        """From COLMAP ``PINHOLE`` parameters (principal point shifted by −0.5 px)."""
        return cls(fx, fy, cx - 0.5, cy - 0.5)

    def to_proto(self) -> common_pb2.CameraIntrinsics:
        """The ``CameraIntrinsics`` message."""
        return common_pb2.CameraIntrinsics(fx=self.fx, fy=self.fy, cx=self.cx, cy=self.cy, skew=self.skew)


IntrinsicsLike = Intrinsics | Sequence[float]


def intrinsics_proto(k: IntrinsicsLike, field: str) -> common_pb2.CameraIntrinsics:
    """``Intrinsics`` or a ``(fx, fy, cx, cy[, skew])`` sequence (murk's pixel-centre convention)."""
    if isinstance(k, Intrinsics):
        return k.to_proto()
    values = [float(v) for v in k]
    if len(values) not in (4, 5):
        raise ClientInputError(field, f"expected (fx, fy, cx, cy[, skew]), got {len(values)} values")
    return Intrinsics(*values).to_proto()


def vector3_proto(v: Sequence[float], field: str) -> common_pb2.Vector3:
    """A 3-vector from any length-3 sequence."""
    values = [float(x) for x in v]
    if len(values) != 3:
        raise ClientInputError(field, f"expected 3 values, got {len(values)}")
    return common_pb2.Vector3(x=values[0], y=values[1], z=values[2])


@dataclass(frozen=True)
class Pose:
    """World-to-camera rigid transform ``x_cam = R @ x_world + t`` (COLMAP's convention).

    ``rotation`` is 3x3, ``translation_scene_units`` 3 values in scene units.
    """

    rotation: npt.NDArray[np.float64]
    translation_scene_units: npt.NDArray[np.float64]

    @classmethod
    def from_quaternion(cls, qw: float, qx: float, qy: float, qz: float, t: Sequence[float]) -> Pose:
        """From COLMAP's ``QW QX QY QZ TX TY TZ`` (Hamilton quaternion, world-to-camera)."""
        q = np.array([qw, qx, qy, qz], dtype=np.float64)
        n = float(np.linalg.norm(q))
        if not np.isfinite(n) or n == 0.0:
            raise ClientInputError("pose.rotation", "quaternion must be finite and non-zero")
        w, x, y, z = q / n
        r = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
        return cls(r, np.asarray(t, dtype=np.float64).reshape(3))

    @property
    def camera_centre(self) -> npt.NDArray[np.float64]:
        """The camera centre in world coordinates, scene units (``-R^T t``)."""
        c: npt.NDArray[np.float64] = -self.rotation.T @ self.translation_scene_units
        return c

    def to_proto(self) -> common_pb2.Pose:
        """The ``Pose`` message."""
        r = np.asarray(self.rotation, dtype=np.float64)
        t = np.asarray(self.translation_scene_units, dtype=np.float64)
        if r.shape != (3, 3) or t.shape != (3,):
            raise ClientInputError(
                "pose", f"rotation must be 3x3 and translation 3, got {r.shape}, {t.shape}"
            )
        return common_pb2.Pose(rotation=r.reshape(9).tolist(), translation=t.tolist())


@dataclass(frozen=True)
class View:
    """One calibrated MVS view: image (grey or RGB, values nominally in [0, 1]), intrinsics, pose."""

    image: ImageLike
    intrinsics: IntrinsicsLike
    pose: Pose
    #: For messages only (e.g. the file name).
    name: str = ""


@dataclass(frozen=True)
class PsLight:
    """One light of a photometric-stereo capture.

    ``position_mm`` in the camera frame (+x right, +y down, +z forward), ``intensity`` the radiant
    intensity I0 (I0 / d² with d in mm is in image units), ``image`` with the object and
    ``background`` without it under the same light (backscatter only); single-channel, linear.
    """

    position_mm: Sequence[float]
    intensity: float
    image: ImageLike
    background: ImageLike


class JobState(enum.Enum):
    """Where a job is in its life."""

    UNSPECIFIED = 0
    QUEUED = 1
    RUNNING = 2
    SUCCEEDED = 3
    FAILED = 4
    CANCELLED = 5

    @property
    def terminal(self) -> bool:
        """True for SUCCEEDED, FAILED and CANCELLED (the job changes no more)."""
        return self in (JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED)


def _time(ts: object, present: bool) -> datetime | None:
    if not present:
        return None
    seconds = getattr(ts, "seconds", 0)
    nanos = getattr(ts, "nanos", 0)
    return datetime.fromtimestamp(seconds + nanos / 1e9, tz=timezone.utc)


@dataclass(frozen=True)
class JobStatus:
    """A job as the server reports it, without its result."""

    id: str
    state: JobState
    #: Overall progress in [0, 1].
    progress: float
    #: The algorithm stage running, e.g. ``"tof.phase.fine"``.
    stage: str
    #: ``"tof_depth"``, ``"mvs_depth"``, ``"rectified_stereo"``, ``"scattering_params"`` or
    #: ``"photometric_stereo"``.
    method: str
    #: Served from the result cache without recomputation.
    cached: bool
    #: Size of the encoded result, bytes, once SUCCEEDED.
    result_size_bytes: int
    create_time: datetime | None
    start_time: datetime | None
    end_time: datetime | None
    #: ``(google.rpc code, message, field)`` of a FAILED or CANCELLED job.
    error: tuple[int, str, str] | None

    @classmethod
    def from_proto(cls, job: jobs_pb2.Job) -> JobStatus:
        """From a ``Job`` message."""
        err = None
        if job.WhichOneof("outcome") == "error":
            err = (job.error.code, job.error.message, job.error.field)
        try:
            state = JobState(job.state)
        except ValueError:
            state = JobState.UNSPECIFIED
        return cls(
            id=job.id,
            state=state,
            progress=float(job.progress),
            stage=job.stage,
            method=job.method,
            cached=job.cached,
            result_size_bytes=int(job.result_size_bytes),
            create_time=_time(job.create_time, job.HasField("create_time")),
            start_time=_time(job.start_time, job.HasField("start_time")),
            end_time=_time(job.end_time, job.HasField("end_time")),
            error=err,
        )
