"""Sensor sessions: a stream of frames answered frame by frame (``murk.v1.Sessions/Stream``).

>>> frames = (mc.tof_frame(a, p, frame_id=name) for name, a, p in camera)
>>> config = mc.tof_session_config(width=512, height=424, modulation_frequency_hz=16e6)
>>> for out in murk.session(config, frames):
...     if out.result is not None:
...         use(out.frame_id, out.result.range_m)  # compact by default: range, mask, std

Results come in frame order. A frame the server drops (``queue_policy="latest"`` when the robot
falls behind, or past ``frame_deadline_s``) comes back with ``dropped`` set; a bad frame with
``error`` set; neither ends the session. When the server becomes UNAVAILABLE (the replica behind a
balancer went away, or shut down) the client opens a new session, which starts cold, and sends
again the frames that were not answered.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import grpc
import numpy as np
from google.protobuf.timestamp_pb2 import Timestamp

from ._proto.murk.v1 import jobs_pb2, sessions_pb2, sessions_pb2_grpc
from .errors import ClientInputError, FieldViolation, InvalidArgument, MurkError, from_rpc_error
from .images import ImageLike, to_proto
from .requests import Tuning, rectified_stereo_request, tof_depth_request
from .results import RectifiedStereoResult, TofDepthResult
from .retry import RetryPolicy
from .types import IntrinsicsLike

_POLICIES = {"latest": sessions_pb2.QUEUE_POLICY_LATEST, "fifo": sessions_pb2.QUEUE_POLICY_FIFO}


def _config(
    request: jobs_pb2.JobRequest,
    width: int,
    height: int,
    queue_policy: str,
    max_queued_frames: int,
    frame_deadline_s: float,
) -> sessions_pb2.SessionConfig:
    if queue_policy not in _POLICIES:
        raise ClientInputError("config.queue_policy", f"one of {sorted(_POLICIES)}, got {queue_policy!r}")
    config = sessions_pb2.SessionConfig(
        width=int(width),
        height=int(height),
        queue_policy=_POLICIES[queue_policy],
        max_queued_frames=int(max_queued_frames),
        frame_deadline_seconds=float(frame_deadline_s),
    )
    which = request.WhichOneof("method")
    if which == "tof_depth":
        config.tof.CopyFrom(request.tof_depth)
        config.tof.ClearField("amplitude")
        config.tof.ClearField("phase")
    else:
        config.stereo.CopyFrom(request.rectified_stereo)
        config.stereo.ClearField("left")
        config.stereo.ClearField("right")
    return config


@contextmanager
def _as_config(request_prefix: str, config_prefix: str) -> Iterator[None]:
    """Renames a request builder's field paths to the session configuration's."""
    try:
        yield
    except ClientInputError as e:
        field = (e.field or "").replace(request_prefix, config_prefix, 1)
        raise ClientInputError(field, e.field_violations[0].description) from None


def tof_session_config(
    *,
    width: int,
    height: int,
    modulation_frequency_hz: float,
    intrinsics: IntrinsicsLike | None = None,
    light_position_m: Sequence[float] | None = None,
    options: Tuning | None = None,
    outputs: Sequence[str] | None = None,
    encoding: str | None = None,
    return_points: bool = False,
    max_point_range_std_m: float | None = None,
    queue_policy: str = "fifo",
    max_queued_frames: int = 0,
    frame_deadline_s: float = 0.0,
    scatter_grid: int = 0,
) -> sessions_pb2.SessionConfig:
    """A ToF session of ``width × height`` frames; arguments as for ``tof_depth_request``.

    A session's results are compact unless ``outputs``/``encoding`` say otherwise: the z-depth
    (the range without intrinsics), the mask and ``range_std_m``, as lossless 16-bit PNGs
    (metres in 1 mm steps); the client decodes them to float32 arrays like any other result.

    ``queue_policy``: ``"fifo"`` (every frame computed; the server pushes back) or ``"latest"``
    (a full queue drops its oldest frame). ``max_queued_frames`` 0 = the server's default.

    ``scatter_grid``: a frame computed from the previous frame's answer solves for the scatter
    on the means of blocks this many pixels a side (1–4; 1 = every frame at full size; 0 = the
    server's default, 2), and a frame computed from scratch its coarse level; the mask and the
    depths are still decided at full size.
    """
    if not 0 <= int(scatter_grid) <= 4:
        raise ClientInputError("config.tof_scatter_grid", f"0 to 4 (0: the default), got {scatter_grid}")
    # The images come with each frame: the request is built on placeholders and sent without.
    blank = np.zeros((2, 2), np.float32)
    with _as_config("request.tof_depth", "config.tof"):
        req = tof_depth_request(
            blank,
            blank,
            modulation_frequency_hz=modulation_frequency_hz,
            intrinsics=intrinsics,
            light_position_m=light_position_m,
            options=options,
            outputs=outputs,
            encoding=encoding,
            return_points=return_points,
            max_point_range_std_m=max_point_range_std_m,
        )
    config = _config(req, width, height, queue_policy, max_queued_frames, frame_deadline_s)
    config.tof_scatter_grid = int(scatter_grid)
    return config


def stereo_session_config(
    *,
    width: int,
    height: int,
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
    queue_policy: str = "fifo",
    max_queued_frames: int = 0,
    frame_deadline_s: float = 0.0,
) -> sessions_pb2.SessionConfig:
    """A rectified-stereo session of ``width × height`` pairs; arguments as for
    ``rectified_stereo_request``, queue as for :func:`tof_session_config`. The default results
    are compact: the z-depth and the confidence as 16-bit PNGs."""
    blank = np.zeros((2, 2), np.float32)
    with _as_config("request.rectified_stereo", "config.stereo"):
        req = rectified_stereo_request(
            blank,
            blank,
            intrinsics=intrinsics,
            baseline=baseline,
            right_cx=right_cx,
            disparity_range_px=disparity_range_px,
            depth_range=depth_range,
            num_planes=num_planes,
            cost_volume=cost_volume,
            airlight=airlight,
            beta=beta,
            sgm=sgm,
            return_points=return_points,
            outputs=outputs,
            encoding=encoding,
        )
    return _config(req, width, height, queue_policy, max_queued_frames, frame_deadline_s)


def _stamp(stamp_s: float | None) -> Timestamp | None:
    if stamp_s is None:
        return None
    t = Timestamp()
    t.FromNanoseconds(int(round(stamp_s * 1e9)))
    return t


def tof_frame(
    amplitude: ImageLike, phase: ImageLike, *, frame_id: str = "", stamp_s: float | None = None
) -> sessions_pb2.SessionFrame:
    """A ToF frame (phase in radians); ``stamp_s`` the capture time, seconds since the epoch."""
    return sessions_pb2.SessionFrame(
        frame_id=frame_id,
        stamp=_stamp(stamp_s),
        amplitude=to_proto(amplitude, field="frame.amplitude"),
        phase=to_proto(phase, field="frame.phase"),
    )


def stereo_frame(
    left: ImageLike, right: ImageLike, *, frame_id: str = "", stamp_s: float | None = None
) -> sessions_pb2.SessionFrame:
    """A rectified pair; ``stamp_s`` the capture time, seconds since the epoch."""
    return sessions_pb2.SessionFrame(
        frame_id=frame_id,
        stamp=_stamp(stamp_s),
        left=to_proto(left, field="frame.left"),
        right=to_proto(right, field="frame.right"),
    )


@dataclass(frozen=True)
class FrameOutcome:
    """What became of one frame: exactly one of ``result``, ``dropped`` and ``error`` is set."""

    sequence: int
    frame_id: str
    #: The frame's stamp, seconds since the epoch (None when it had none).
    stamp_s: float | None
    result: TofDepthResult | RectifiedStereoResult | None
    #: ``"superseded"`` or ``"deadline"`` when the server dropped the frame.
    dropped: str | None
    #: The frame's error (e.g. :class:`InvalidArgument` naming ``frame.phase``).
    error: MurkError | None
    queue_s: float = 0.0
    compute_s: float = 0.0
    #: What to know about this frame (e.g. a stereo frame searched over the whole range again).
    warnings: tuple[str, ...] = ()


def run_session(
    channel: grpc.Channel,
    metadata: Sequence[tuple[str, str]],
    config: sessions_pb2.SessionConfig,
    frames: Iterable[sessions_pb2.SessionFrame],
    retry: RetryPolicy,
) -> Iterator[FrameOutcome]:
    """See :meth:`murk_client.Client.session`."""
    stub = sessions_pb2_grpc.SessionsStub(channel)
    source = iter(frames)
    lock = threading.Lock()
    pending: dict[int, sessions_pb2.SessionFrame] = {}
    next_sequence = [1]
    exhausted = [False]

    def requests(resend: list[sessions_pb2.SessionFrame]) -> Iterator[sessions_pb2.SessionRequest]:
        yield sessions_pb2.SessionRequest(config=config)
        for frame in resend:
            yield sessions_pb2.SessionRequest(frame=frame)
        while True:
            try:
                frame = next(source)
            except StopIteration:
                exhausted[0] = True
                return
            f = sessions_pb2.SessionFrame()
            f.CopyFrom(frame)
            with lock:
                f.sequence = next_sequence[0]
                next_sequence[0] += 1
                pending[f.sequence] = f
            yield sessions_pb2.SessionRequest(frame=f)

    attempt = 0
    while True:
        with lock:
            resend = [pending[k] for k in sorted(pending)]
        events = stub.Stream(requests(resend), metadata=tuple(metadata))
        try:
            for event in events:
                which = event.WhichOneof("event")
                if which == "result":
                    attempt = 0
                    yield _outcome_of_result(event.result, pending, lock)
                elif which == "dropped":
                    d = event.dropped
                    with lock:
                        pending.pop(d.sequence, None)
                    reason = "deadline" if d.reason == sessions_pb2.DROP_REASON_DEADLINE else "superseded"
                    yield FrameOutcome(
                        sequence=d.sequence,
                        frame_id=d.frame_id,
                        stamp_s=d.stamp.ToNanoseconds() / 1e9 if d.HasField("stamp") else None,
                        result=None,
                        dropped=reason,
                        error=None,
                    )
            return
        except grpc.RpcError as e:
            err = from_rpc_error(e)
            if err.code != grpc.StatusCode.UNAVAILABLE or not retry.should_retry(err, attempt):
                raise err from None
            retry.sleep(retry.delay_s(err, attempt))
            attempt += 1
            with lock:
                if exhausted[0] and not pending:
                    return


def _outcome_of_result(
    r: sessions_pb2.FrameResult, pending: dict[int, sessions_pb2.SessionFrame], lock: threading.Lock
) -> FrameOutcome:
    with lock:
        pending.pop(r.sequence, None)
    which = r.WhichOneof("outcome")
    result: TofDepthResult | RectifiedStereoResult | None = None
    error: MurkError | None = None
    if which == "tof":
        result = TofDepthResult.from_proto(r.tof)
    elif which == "stereo":
        result = RectifiedStereoResult.from_proto(r.stereo)
    else:
        e = r.error
        if e.code == grpc.StatusCode.INVALID_ARGUMENT.value[0]:
            error = InvalidArgument(e.message, field_violations=[FieldViolation(e.field, e.message)])
        else:
            error = MurkError(e.message)
    return FrameOutcome(
        sequence=r.sequence,
        frame_id=r.frame_id,
        stamp_s=r.stamp.ToNanoseconds() / 1e9 if r.HasField("stamp") else None,
        result=result,
        dropped=None,
        error=error,
        queue_s=r.queue_seconds,
        compute_s=r.compute_seconds,
        warnings=tuple(r.warnings),
    )
