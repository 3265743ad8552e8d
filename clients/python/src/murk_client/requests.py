"""Builders of the ``JobRequest`` each method takes, for :meth:`murk_client.Client.submit`.

The ``Client`` methods of the same names build these and wait for the result; call the builders
directly to submit now and collect later. Optional tuning (``options``, ``sgm``, ...) is given as
the proto message or as a mapping with the proto's field names, e.g.
``options={"fine_iterations": 20, "bilateral": {"disabled": True}}``; the proto files in
``proto/murk/v1`` document every field with its units and default.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt
from google.protobuf import json_format
from google.protobuf.message import Message

from ._proto.murk.v1 import common_pb2, jobs_pb2, mvs_pb2, params_pb2, ps_pb2, stereo_pb2, tof_pb2
from .errors import ClientInputError
from .images import ImageLike, to_proto
from .types import IntrinsicsLike, PsLight, View, intrinsics_proto, vector3_proto

M = TypeVar("M", bound=Message)
Tuning = Message | Mapping[str, Any]

_COST_VOLUMES = {
    "dehazing": mvs_pb2.COST_VOLUME_KIND_DEHAZING,
    "eq37": mvs_pb2.COST_VOLUME_KIND_DEHAZING_EQ37,
    "ordinary": mvs_pb2.COST_VOLUME_KIND_ORDINARY,
}
_AIRLIGHT_SOURCES = {
    "server": params_pb2.AIRLIGHT_SOURCE_UNSPECIFIED,
    "cnn": params_pb2.AIRLIGHT_SOURCE_CNN,
    "dark_channel": params_pb2.AIRLIGHT_SOURCE_DARK_CHANNEL,
    "given": params_pb2.AIRLIGHT_SOURCE_GIVEN,
}
#: The modulation frequencies the server accepts, Hz.
MIN_MODULATION_HZ = 1e5
MAX_MODULATION_HZ = 1e10
_ENCODINGS = {
    "f32": common_pb2.IMAGE_ENCODING_F32,
    "f16": common_pb2.IMAGE_ENCODING_F16,
    "png": common_pb2.IMAGE_ENCODING_PNG,
}
_PS_MODES = {"full": ps_pb2.PS_MODE_FULL, "backscatter_only": ps_pb2.PS_MODE_BACKSCATTER_ONLY}


def _outputs(
    outputs: Sequence[str] | None, encoding: str | None, field: str
) -> common_pb2.OutputOptions | None:
    """The ``outputs`` message of a request: which result images to return and their encoding
    (``"f32"`` exact, ``"f16"``, or ``"png"``: a lossless 16-bit PNG of metres in 1 mm steps
    and [0, 1] images in steps of 1/65535). ``None`` for both keeps the server's default."""
    if outputs is None and encoding is None:
        return None
    if isinstance(outputs, str):
        raise ClientInputError(f"{field}.fields", "expected a list of names, got one string")
    msg = common_pb2.OutputOptions(fields=list(outputs or ()))
    if encoding is not None:
        if encoding not in _ENCODINGS:
            raise ClientInputError(f"{field}.encoding", f"one of {sorted(_ENCODINGS)}, got {encoding!r}")
        msg.encoding = _ENCODINGS[encoding]
    return msg


def _tuning(value: Tuning | None, cls: type[M], field: str) -> M | None:
    if value is None:
        return None
    if isinstance(value, cls):
        return value
    if isinstance(value, Message):
        raise ClientInputError(
            field, f"expected {cls.DESCRIPTOR.full_name}, got {value.DESCRIPTOR.full_name}"
        )
    msg = cls()
    try:
        json_format.ParseDict(dict(value), msg)
    except json_format.ParseError as e:
        raise ClientInputError(field, str(e)) from e
    return msg


def _finite(value: float, field: str, *, positive: bool = False, non_negative: bool = False) -> float:
    v = float(value)
    if not math.isfinite(v):
        raise ClientInputError(field, f"must be finite, got {value}")
    if positive and v <= 0:
        raise ClientInputError(field, f"must be > 0, got {value}")
    if non_negative and v < 0:
        raise ClientInputError(field, f"must be >= 0, got {value}")
    return v


def _view(v: View, field: str) -> mvs_pb2.MvsView:
    return mvs_pb2.MvsView(
        image=to_proto(v.image, field=f"{field}.image"),
        intrinsics=intrinsics_proto(v.intrinsics, f"{field}.intrinsics"),
        pose=v.pose.to_proto(),
    )


def tof_depth_request(
    amplitude: ImageLike,
    phase: ImageLike,
    *,
    modulation_frequency_hz: float,
    intrinsics: IntrinsicsLike | None = None,
    light_position_m: Sequence[float] | None = None,
    options: Tuning | None = None,
    outputs: Sequence[str] | None = None,
    encoding: str | None = None,
    return_points: bool = False,
    max_point_range_std_m: float | None = None,
) -> jobs_pb2.JobRequest:
    """ToF depth in fog (Ch. 5).

    ``amplitude`` linear sensor units and ``phase`` in **radians** [0, 2π), one channel each, same
    size. ``modulation_frequency_hz`` in Hz (e.g. ``16e6``). ``intrinsics`` (pixels) enable the
    z-depth output; ``light_position_m`` (camera frame, metres) needs them. ``outputs`` names the
    result images to return (e.g. ``["z_depth_m", "mask"]``; default all) and ``encoding`` how
    (``"f32"``, default; ``"f16"``; ``"png"``); the others come back as ``None``.
    ``return_points`` (needs ``intrinsics``) also returns the pixels whose ``range_std_m`` is
    below ``max_point_range_std_m`` (metres; default 0.1) as points in the camera frame.
    """
    f = _finite(modulation_frequency_hz, "request.tof_depth.modulation_frequency_hz", positive=True)
    if not MIN_MODULATION_HZ <= f <= MAX_MODULATION_HZ:
        # The server's own range (src/tof/params.rs), checked before the images are uploaded:
        # 16 given for 16 MHz would put every range at 9e6 m.
        raise ClientInputError(
            "request.tof_depth.modulation_frequency_hz",
            f"must be in [1e5, 1e10] Hz (CW-ToF cameras modulate at 10-200 MHz, e.g. 16e6), got {f}",
        )
    if isinstance(phase, np.ndarray) and phase.dtype.kind == "f" and phase.size:
        hi = float(np.nanmax(phase))
        if hi > 2 * math.pi + 1e-3:
            raise ClientInputError(
                "request.tof_depth.phase", f"must be radians in [0, 2pi), max is {hi:.4g} (degrees?)"
            )
    if light_position_m is not None and intrinsics is None:
        raise ClientInputError("request.tof_depth.light_position_m", "needs intrinsics (each pixel's ray)")
    if return_points and intrinsics is None:
        raise ClientInputError("request.tof_depth.return_points", "needs intrinsics (each pixel's ray)")
    req = tof_pb2.TofDepthRequest(
        amplitude=to_proto(amplitude, field="request.tof_depth.amplitude", channels=1),
        phase=to_proto(phase, field="request.tof_depth.phase", channels=1),
        modulation_frequency_hz=f,
        return_points=return_points,
    )
    if max_point_range_std_m is not None:
        req.max_point_range_std_m = _finite(
            max_point_range_std_m, "request.tof_depth.max_point_range_std_m", positive=True
        )
    if intrinsics is not None:
        req.intrinsics.CopyFrom(intrinsics_proto(intrinsics, "request.tof_depth.intrinsics"))
    if light_position_m is not None:
        req.light_position_m.CopyFrom(vector3_proto(light_position_m, "request.tof_depth.light_position_m"))
    opts = _tuning(options, tof_pb2.TofOptions, "request.tof_depth.options")
    if opts is not None:
        req.options.CopyFrom(opts)
    out = _outputs(outputs, encoding, "request.tof_depth.outputs")
    if out is not None:
        req.outputs.CopyFrom(out)
    return jobs_pb2.JobRequest(tof_depth=req)


def mvs_depth_request(
    reference: View,
    sources: Sequence[View],
    *,
    cost_volume: str = "dehazing",
    airlight: float | None = None,
    beta_per_scene_unit: float | None = None,
    near_scene_units: float | None = None,
    far_scene_units: float | None = None,
    num_planes: int | None = None,
    sgm: Tuning | None = None,
) -> jobs_pb2.JobRequest:
    """MVS depth of ``reference`` in haze (Ch. 3.2) from 1 to 16 ``sources``.

    ``cost_volume``: ``"dehazing"`` (default; needs ``airlight`` in (0, 1] and
    ``beta_per_scene_unit`` >= 0), ``"eq37"`` (also needs them) or ``"ordinary"`` (Eq. 3.1).
    Planes span ``near_scene_units``…``far_scene_units`` z-depth (default 0.5…50: pass the range
    of your scene — for a COLMAP model, of its points).
    """
    if cost_volume not in _COST_VOLUMES:
        raise ClientInputError(
            "request.mvs_depth.cost_volume", f"one of {sorted(_COST_VOLUMES)}, got {cost_volume!r}"
        )
    if cost_volume != "ordinary" and (airlight is None or beta_per_scene_unit is None):
        raise ClientInputError(
            "request.mvs_depth.airlight",
            f"the {cost_volume} cost volume needs airlight and beta_per_scene_unit "
            "(Client.scattering_params estimates them)",
        )
    req = mvs_pb2.MvsDepthRequest(
        reference=_view(reference, "request.mvs_depth.reference"),
        sources=[_view(s, f"request.mvs_depth.sources[{i}]") for i, s in enumerate(sources)],
        cost_volume=_COST_VOLUMES[cost_volume],
        airlight=_finite(airlight or 0.0, "request.mvs_depth.airlight", non_negative=True),
        beta=_finite(beta_per_scene_unit or 0.0, "request.mvs_depth.beta", non_negative=True),
        near=_finite(near_scene_units or 0.0, "request.mvs_depth.near", non_negative=True),
        far=_finite(far_scene_units or 0.0, "request.mvs_depth.far", non_negative=True),
        num_planes=int(num_planes or 0),
    )
    s = _tuning(sgm, mvs_pb2.SgmOptions, "request.mvs_depth.sgm")
    if s is not None:
        req.sgm.CopyFrom(s)
    return jobs_pb2.JobRequest(mvs_depth=req)


def rectified_stereo_request(
    left: ImageLike,
    right: ImageLike,
    *,
    intrinsics: IntrinsicsLike,
    baseline: float,
    right_cx: float | None = None,
    disparity_range_px: tuple[float, float] | None = None,
    depth_range: tuple[float, float] | None = None,
    num_planes: int | None = None,
    cost_volume: str | None = None,
    airlight: float | None = None,
    beta: float | None = None,
    sgm: Tuning | None = None,
    return_points: bool = False,
    outputs: Sequence[str] | None = None,
    encoding: str | None = None,
) -> jobs_pb2.JobRequest:
    """Depth of the left view of a calibrated, rectified pair in haze (Ch. 3.2 with two views).

    ``intrinsics``: the left camera's rectified intrinsics (murk's pixel-centre convention, as
    ROS and OpenCV write them, skew 0); ``baseline``: the right camera's centre along the left
    camera's +x axis, in the unit depths come out in (``beta`` is per that unit);
    ``right_cx``: the right principal point's x when it differs (Middlebury's ``doffs`` is the
    difference). Search either ``disparity_range_px`` (min, max) or ``depth_range`` (near,
    far); neither searches 1 px to a quarter of the width. ``cost_volume`` defaults to
    ``"dehazing"`` with ``airlight`` and ``beta``, ``"ordinary"`` without. ``outputs``
    (``"z_depth"``, ``"disparity"``, ``"confidence"``) and ``encoding`` as for
    :func:`tof_depth_request`.
    """
    field = "request.rectified_stereo"
    kind = cost_volume or ("dehazing" if airlight is not None else "ordinary")
    if kind not in _COST_VOLUMES:
        raise ClientInputError(f"{field}.cost_volume", f"one of {sorted(_COST_VOLUMES)}, got {kind!r}")
    if kind != "ordinary" and (airlight is None or beta is None):
        raise ClientInputError(f"{field}.airlight", f"the {kind} cost volume needs airlight and beta")
    if disparity_range_px is not None and depth_range is not None:
        raise ClientInputError(f"{field}.near", "give disparity_range_px or depth_range, not both")
    req = stereo_pb2.RectifiedStereoRequest(
        left=to_proto(left, field=f"{field}.left"),
        right=to_proto(right, field=f"{field}.right"),
        intrinsics=intrinsics_proto(intrinsics, f"{field}.intrinsics"),
        baseline=_finite(baseline, f"{field}.baseline", positive=True),
        num_planes=int(num_planes or 0),
        cost_volume=_COST_VOLUMES[kind],
        airlight=_finite(airlight or 0.0, f"{field}.airlight", non_negative=True),
        beta=_finite(beta or 0.0, f"{field}.beta", non_negative=True),
        return_points=return_points,
    )
    if right_cx is not None:
        req.right_cx = _finite(right_cx, f"{field}.right_cx")
    if disparity_range_px is not None:
        lo, hi = disparity_range_px
        req.min_disparity_px = _finite(lo, f"{field}.min_disparity_px")
        req.max_disparity_px = _finite(hi, f"{field}.max_disparity_px")
    if depth_range is not None:
        near, far = depth_range
        req.near = _finite(near, f"{field}.near", positive=True)
        req.far = _finite(far, f"{field}.far", positive=True)
    s = _tuning(sgm, mvs_pb2.SgmOptions, f"{field}.sgm")
    if s is not None:
        req.sgm.CopyFrom(s)
    out = _outputs(outputs, encoding, f"{field}.outputs")
    if out is not None:
        req.outputs.CopyFrom(out)
    return jobs_pb2.JobRequest(rectified_stereo=req)


def scattering_params_request(
    reference: View,
    sources: Sequence[View],
    sparse_points_scene_units: npt.ArrayLike,
    *,
    airlight_source: str = "server",
    airlight: float | None = None,
    beta_min_per_scene_unit: float | None = None,
    beta_max_per_scene_unit: float | None = None,
    near_scene_units: float | None = None,
    far_scene_units: float | None = None,
    seen_by_sources: Sequence[Sequence[int]] | None = None,
    observations: npt.ArrayLike | None = None,
    options: Tuning | None = None,
) -> jobs_pb2.JobRequest:
    """Airlight A and scattering coefficient β by Algorithm 1 (Ch. 3.3), then the depth with them.

    ``sparse_points_scene_units``: an ``(n, 3)`` array of SfM points, world coordinates.
    ``seen_by_sources``: for each point, the indices into ``sources`` of the images whose SfM
    track includes it (COLMAP's observations); the fit then samples a point only where it was
    seen, not where a nearer surface hides it. Unset: every point is used in every source.
    ``observations``: an ``(m, 4)`` array of where SfM saw the points: point index, view (0 the
    reference, ``1 + i`` for ``sources[i]``) and the pixel ``x, y`` with the top-left pixel's
    centre at (0, 0) (COLMAP's keypoints minus 0.5). The standard errors then include the SfM
    poses' share (``ScatteringParamsResult.pose_error``). Unset: the poses are taken as exact.
    ``airlight_source``: ``"server"`` (its configured estimator), ``"cnn"``, ``"dark_channel"``
    or ``"given"`` (then ``airlight`` in (0, 1]); by default A is then fitted with β to the
    points, A0 as a prior. β bounds are per scene unit; unset ends come from the points' depths
    (any model unit works), and a bound that binds is reported in the result. ``options`` sets
    any other ``ScatteringParamsRequest`` field (``joint_fit``, ``beta_steps``, ``sgm``, ...).
    """
    if airlight_source not in _AIRLIGHT_SOURCES:
        raise ClientInputError(
            "request.scattering_params.airlight_source",
            f"one of {sorted(_AIRLIGHT_SOURCES)}, got {airlight_source!r}",
        )
    if (airlight is not None) != (airlight_source == "given"):
        raise ClientInputError(
            "request.scattering_params.airlight", "give airlight exactly when airlight_source='given'"
        )
    pts = np.asarray(sparse_points_scene_units, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ClientInputError(
            "request.scattering_params.sparse_points", f"expected shape (n, 3), got {pts.shape}"
        )
    req = _tuning(options, params_pb2.ScatteringParamsRequest, "request.scattering_params.options")
    req = req if req is not None else params_pb2.ScatteringParamsRequest()
    req.reference.CopyFrom(_view(reference, "request.scattering_params.reference"))
    del req.sources[:]
    req.sources.extend(_view(s, f"request.scattering_params.sources[{i}]") for i, s in enumerate(sources))
    del req.sparse_points[:]
    req.sparse_points.extend(
        vector3_proto(p, "request.scattering_params.sparse_points") for p in pts.tolist()
    )
    del req.sparse_point_sources[:]
    if seen_by_sources is not None:
        field = "request.scattering_params.sparse_point_sources"
        if len(seen_by_sources) != len(pts):
            raise ClientInputError(
                field, f"one entry per point: {len(seen_by_sources)} for {len(pts)} points"
            )
        for i, seen in enumerate(seen_by_sources):
            mask = 0
            for s in seen:
                if not 0 <= int(s) < len(sources):
                    raise ClientInputError(f"{field}[{i}]", f"source index {s} outside 0..{len(sources) - 1}")
                mask |= 1 << int(s)
            req.sparse_point_sources.append(mask)
    del req.sparse_point_observations[:]
    if observations is not None:
        field = "request.scattering_params.sparse_point_observations"
        obs = np.asarray(observations, dtype=np.float64)
        if obs.ndim != 2 or obs.shape[1] != 4:
            raise ClientInputError(field, f"expected shape (m, 4): point, view, x, y; got {obs.shape}")
        for i, (point, view, x, y) in enumerate(obs.tolist()):
            if not (point == int(point) and 0 <= point < len(pts)):
                raise ClientInputError(f"{field}[{i}].point", f"an index in 0..{len(pts) - 1}, got {point}")
            if not (view == int(view) and 0 <= view <= len(sources)):
                raise ClientInputError(f"{field}[{i}].view", f"0 (reference) to {len(sources)}, got {view}")
            if not (math.isfinite(x) and math.isfinite(y)):
                raise ClientInputError(f"{field}[{i}]", f"pixel must be finite, got ({x}, {y})")
            req.sparse_point_observations.add(point=int(point), view=int(view), x=x, y=y)
    req.airlight_source = _AIRLIGHT_SOURCES[airlight_source]
    if airlight is not None:
        req.airlight = _finite(airlight, "request.scattering_params.airlight", positive=True)
    if beta_min_per_scene_unit is not None:
        req.beta_min = _finite(
            beta_min_per_scene_unit, "request.scattering_params.beta_min", non_negative=True
        )
    if beta_max_per_scene_unit is not None:
        req.beta_max = _finite(beta_max_per_scene_unit, "request.scattering_params.beta_max", positive=True)
    if near_scene_units is not None:
        req.near = _finite(near_scene_units, "request.scattering_params.near", positive=True)
    if far_scene_units is not None:
        req.far = _finite(far_scene_units, "request.scattering_params.far", positive=True)
    return jobs_pb2.JobRequest(scattering_params=req)


def photometric_stereo_request(
    lights: Sequence[PsLight],
    mask: ImageLike,
    *,
    intrinsics: IntrinsicsLike,
    beta_per_mm: float,
    sigma_per_mm: float,
    initial_distance_mm: float | None = None,
    fix_distance: bool = False,
    mode: str = "full",
    options: Tuning | None = None,
) -> jobs_pb2.JobRequest:
    """Photometric stereo in turbid water (Ch. 4): normals, albedo and depth in mm.

    3 to 64 ``lights`` (positions in **mm**, camera frame), a single-channel ``mask`` (> 0.5 =
    object), ``beta_per_mm`` and ``sigma_per_mm`` (extinction, >= beta) **per millimetre**, and
    ``initial_distance_mm``: the object's mean z-depth as far as the rig knows it. The server
    fits the distance to the lights' 1/d² fall-off, so this is a starting guess (20 % off is
    fine); ``None`` lets the server search for it. ``fix_distance=True`` keeps the depth's mean
    at ``initial_distance_mm`` instead (the published method). ``mode``: ``"full"`` or
    ``"backscatter_only"`` (the baseline). ``options`` sets any other
    ``PhotometricStereoRequest`` field (``support_r``, ``max_iterations``, ...).
    """
    if mode not in _PS_MODES:
        raise ClientInputError("request.photometric_stereo.mode", f"one of {sorted(_PS_MODES)}, got {mode!r}")
    beta = _finite(beta_per_mm, "request.photometric_stereo.beta_per_mm", non_negative=True)
    sigma = _finite(sigma_per_mm, "request.photometric_stereo.sigma_per_mm", non_negative=True)
    if beta > 0.5 or sigma > 0.5:
        # Per-metre values given as per-mm would mean a medium opaque within 2 mm.
        raise ClientInputError(
            "request.photometric_stereo.beta_per_mm",
            f"{beta}/{sigma} per mm is implausibly turbid (per metre given?)",
        )
    req = _tuning(options, ps_pb2.PhotometricStereoRequest, "request.photometric_stereo.options")
    req = req if req is not None else ps_pb2.PhotometricStereoRequest()
    del req.lights[:]
    for i, light in enumerate(lights):
        field = f"request.photometric_stereo.lights[{i}]"
        req.lights.append(
            ps_pb2.PsLight(
                position_mm=vector3_proto(light.position_mm, f"{field}.position_mm"),
                intensity=_finite(light.intensity, f"{field}.intensity", positive=True),
                image=to_proto(light.image, field=f"{field}.image", channels=1),
                background=to_proto(light.background, field=f"{field}.background", channels=1),
            )
        )
    req.mask.CopyFrom(to_proto(mask, field="request.photometric_stereo.mask", channels=1))
    req.intrinsics.CopyFrom(intrinsics_proto(intrinsics, "request.photometric_stereo.intrinsics"))
    req.beta_per_mm = beta
    req.sigma_per_mm = sigma
    if initial_distance_mm is None:
        if fix_distance:
            raise ClientInputError(
                "request.photometric_stereo.initial_distance_mm", "fix_distance needs a distance"
            )
        req.initial_distance_mm = 0.0
    else:
        req.initial_distance_mm = _finite(
            initial_distance_mm, "request.photometric_stereo.initial_distance_mm", positive=True
        )
    req.fix_distance = fix_distance
    req.mode = _PS_MODES[mode]
    return jobs_pb2.JobRequest(photometric_stereo=req)
