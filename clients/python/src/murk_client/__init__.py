"""Python client of murk: 3D shape and depth through fog, haze and turbid water over gRPC.

>>> from murk_client import Client, load_tof_frame
>>> frame = load_tof_frame("scene")                      # murk simulate tof --out scene
>>> with Client("http://127.0.0.1:50051") as murk:
...     r = murk.tof_depth(frame.amplitude, frame.phase,
...                        modulation_frequency_hz=frame.modulation_frequency_hz,
...                        intrinsics=frame.intrinsics)
>>> r.range_m.shape, r.mask.mean()

Units are in the argument names: metres for ToF, millimetres for photometric stereo, scene units
(the poses' unit) for MVS and scattering parameters.
"""

from ._proto.murk.v1 import jobs_pb2 as pb
from .capture import (
    ColmapCamera,
    ColmapImage,
    ColmapModel,
    PsCapture,
    TofFrame,
    load_colmap_model,
    load_ps_capture,
    load_tof_frame,
)
from .client import Client, ProgressCallback
from .errors import (
    ClientInputError,
    DeadlineExceeded,
    FailedPrecondition,
    FieldViolation,
    Internal,
    InvalidArgument,
    JobCancelled,
    MurkError,
    NotFound,
    PermissionDenied,
    ResourceExhausted,
    ResultIntegrityError,
    Unauthenticated,
    Unavailable,
)
from .images import EncodedImage, read_image, srgb_to_linear, write_exr, write_png16
from .requests import (
    mvs_depth_request,
    photometric_stereo_request,
    rectified_stereo_request,
    scattering_params_request,
    tof_depth_request,
)
from .results import (
    AirlightConflict,
    MvsDepthResult,
    PhotometricStereoResult,
    PointRelief,
    PoseError,
    RectifiedStereoResult,
    ResidualSample,
    Result,
    SamplingShare,
    ScatteringParamsResult,
    TofDepthResult,
)
from .retry import RetryPolicy
from .sessions import FrameOutcome, stereo_frame, stereo_session_config, tof_frame, tof_session_config
from .types import Intrinsics, JobState, JobStatus, Pose, PsLight, View

__version__ = "0.1.0"

__all__ = [
    "AirlightConflict",
    "Client",
    "ClientInputError",
    "ColmapCamera",
    "ColmapImage",
    "ColmapModel",
    "DeadlineExceeded",
    "EncodedImage",
    "FailedPrecondition",
    "FieldViolation",
    "FrameOutcome",
    "Internal",
    "Intrinsics",
    "InvalidArgument",
    "JobCancelled",
    "JobState",
    "JobStatus",
    "MurkError",
    "MvsDepthResult",
    "NotFound",
    "PermissionDenied",
    "PhotometricStereoResult",
    "PointRelief",
    "PoseError",
    "SamplingShare",
    "Pose",
    "ProgressCallback",
    "RectifiedStereoResult",
    "PsCapture",
    "PsLight",
    "ResidualSample",
    "ResourceExhausted",
    "Result",
    "ResultIntegrityError",
    "RetryPolicy",
    "ScatteringParamsResult",
    "TofDepthResult",
    "TofFrame",
    "Unauthenticated",
    "Unavailable",
    "View",
    "load_colmap_model",
    "load_ps_capture",
    "load_tof_frame",
    "mvs_depth_request",
    "pb",
    "photometric_stereo_request",
    "read_image",
    "rectified_stereo_request",
    "scattering_params_request",
    "srgb_to_linear",
    "stereo_frame",
    "stereo_session_config",
    "tof_depth_request",
    "tof_frame",
    "tof_session_config",
    "write_exr",
    "write_png16",
]
