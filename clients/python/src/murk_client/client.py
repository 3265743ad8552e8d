"""The murk client: one method per RPC, numpy in and out."""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any, TypeVar

import grpc
import numpy.typing as npt

from . import requests as build
from ._proto.murk.v1 import jobs_pb2, jobs_pb2_grpc, sessions_pb2
from .errors import (
    DeadlineExceeded,
    JobCancelled,
    MurkError,
    ResultIntegrityError,
    from_job_error,
    from_rpc_error,
)
from .images import ImageLike
from .requests import Tuning
from .results import (
    MvsDepthResult,
    PhotometricStereoResult,
    RectifiedStereoResult,
    Result,
    ScatteringParamsResult,
    TofDepthResult,
    from_job_result,
)
from .retry import RetryPolicy
from .sessions import FrameOutcome, run_session
from .types import IntrinsicsLike, JobState, JobStatus, PsLight, View

#: Called with every job update a watch receives (progress in [0, 1], stage, state).
ProgressCallback = Callable[[JobStatus], None]
T = TypeVar("T")
R = TypeVar(
    "R",
    TofDepthResult,
    MvsDepthResult,
    RectifiedStereoResult,
    ScatteringParamsResult,
    PhotometricStereoResult,
)


def _parse_target(target: str, tls: bool) -> tuple[str, bool]:
    for scheme, secure in (("https://", True), ("http://", False), ("grpcs://", True), ("grpc://", False)):
        if target.startswith(scheme):
            return target[len(scheme) :].rstrip("/"), secure
    return target, tls


class Client:
    """A connection to a murk server (or a load balancer in front of several).

    ``target`` is ``host:port``, ``http://host:port`` (plaintext) or ``https://host:port`` (TLS).
    ``token`` is sent as ``authorization: Bearer TOKEN`` on every call (servers started with
    ``--auth-tokens-file`` require it). ``root_certificates`` (PEM bytes) is the CA that signed
    the server's certificate and switches a bare ``host:port`` to TLS; without it ``https://``
    uses the system's roots. ``private_key``/``certificate_chain`` (PEM) are for mutual TLS.

    The channel is a default one: results of any size are fetched with ``Jobs.GetJobResult``
    in chunks of at most 1 MiB, never in one message over gRPC's default 4 MiB receive limit.

    ``retry`` governs every call: by default UNAVAILABLE and a full queue (RESOURCE_EXHAUSTED
    with RetryInfo) are retried with the server's hinted delay or exponential backoff, jittered
    and capped (:class:`RetryPolicy`). ``timeout_s`` is the deadline of each unary call; waits
    for a job take their own ``timeout_s``.
    """

    def __init__(
        self,
        target: str,
        *,
        token: str | None = None,
        root_certificates: bytes | None = None,
        private_key: bytes | None = None,
        certificate_chain: bytes | None = None,
        retry: RetryPolicy | None = None,
        timeout_s: float | None = 60.0,
        channel_options: Sequence[tuple[str, Any]] = (),
    ) -> None:
        address, secure = _parse_target(target, root_certificates is not None)
        options = list(channel_options)
        if secure:
            creds = grpc.ssl_channel_credentials(
                root_certificates=root_certificates,
                private_key=private_key,
                certificate_chain=certificate_chain,
            )
            self._channel = grpc.secure_channel(address, creds, options=options)
        else:
            self._channel = grpc.insecure_channel(address, options=options)
        self._jobs = jobs_pb2_grpc.JobsStub(self._channel)
        self._metadata: tuple[tuple[str, str], ...] = (("authorization", f"Bearer {token}"),) if token else ()
        self.retry = retry if retry is not None else RetryPolicy()
        self.timeout_s = timeout_s

    # -- lifecycle -----------------------------------------------------------------------------

    def close(self) -> None:
        """Closes the channel."""
        self._channel.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the Jobs API ----------------------------------------------------------------------------

    def submit(self, request: jobs_pb2.JobRequest) -> str:
        """Queues ``request`` (see :mod:`murk_client.requests`) and returns the job's id.

        Identical work returns the same id (the content hash of the request), so this is safe to
        repeat; a cached result makes the job SUCCEEDED at once.
        """
        job = self._unary(self._jobs.SubmitJob, jobs_pb2.SubmitJobRequest(request=request, omit_result=True))
        return job.id

    def job(self, job_id: str) -> JobStatus:
        """The job's current state and progress."""
        job = self._unary(
            self._jobs.GetJob, jobs_pb2.GetJobRequest(id=job_id, omit_result=True), job_id=job_id
        )
        return JobStatus.from_proto(job)

    def watch(self, job_id: str, *, timeout_s: float | None = None) -> Iterator[JobStatus]:
        """Yields the job on every change; the last item is terminal.

        A broken stream (a restarted server or replica, a load balancer reset) is re-attached
        under the retry policy; updates are not repeated. ``timeout_s`` bounds the whole watch
        (DeadlineExceeded; the job keeps running).
        """
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        attempt = 0
        while True:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            stream = self._jobs.WatchJob(
                jobs_pb2.WatchJobRequest(id=job_id, omit_result=True),
                metadata=self._metadata,
                timeout=remaining,
            )
            try:
                for job in stream:
                    attempt = 0
                    status = JobStatus.from_proto(job)
                    yield status
                    if status.state.terminal:
                        return
                # A stream that ends without a terminal update was cut: re-attach.
                err: MurkError = from_rpc_error(_Ended(), job_id=job_id)
            except grpc.RpcError as e:
                err = from_rpc_error(e, job_id=job_id)
            finally:
                # Ends the call on the server too when the caller stops iterating early.
                cancel: Any = getattr(stream, "cancel", None)
                if cancel is not None:
                    cancel()
            if not self.retry.should_retry(err, attempt):
                raise err from None
            self.retry.sleep(self.retry.delay_s(err, attempt))
            attempt += 1

    def wait(
        self, job_id: str, *, progress: ProgressCallback | None = None, timeout_s: float | None = None
    ) -> JobStatus:
        """Blocks until the job is terminal (calling ``progress`` on every update) and returns it."""
        last: JobStatus | None = None
        for status in self.watch(job_id, timeout_s=timeout_s):
            last = status
            if progress is not None:
                progress(status)
        assert last is not None  # watch() returns only after a terminal update
        return last

    def result(self, job_id: str) -> Result:
        """The result of a SUCCEEDED job, fetched in chunks (any size, default channel).

        Raises the job's own error when it failed (e.g. InvalidArgument with the field),
        JobCancelled when it was cancelled, FailedPrecondition while it is not finished.
        """
        data = self._with_retry(lambda: self._fetch_result(job_id), job_id)
        msg = jobs_pb2.JobResult()
        msg.ParseFromString(data)
        return from_job_result(msg, job_id)

    def cancel(self, job_id: str) -> JobStatus:
        """Requests cancellation; the state becomes CANCELLED once the worker has stopped."""
        job = self._unary(self._jobs.CancelJob, jobs_pb2.CancelJobRequest(id=job_id), job_id=job_id)
        return JobStatus.from_proto(job)

    def list_jobs(self, *, page_size: int = 100) -> Iterator[JobStatus]:
        """This tenant's jobs known to the server, newest first (pages fetched as needed)."""
        token = ""
        while True:
            page = self._unary(
                self._jobs.ListJobs, jobs_pb2.ListJobsRequest(page_size=page_size, page_token=token)
            )
            for job in page.jobs:
                yield JobStatus.from_proto(job)
            token = page.next_page_token
            if not token:
                return

    def run(
        self,
        request: jobs_pb2.JobRequest,
        *,
        progress: ProgressCallback | None = None,
        timeout_s: float | None = None,
    ) -> Result:
        """Submits ``request``, waits for it and returns its result (raising its error)."""
        job_id = self.submit(request)
        status = self.wait(job_id, progress=progress, timeout_s=timeout_s)
        if status.state == JobState.SUCCEEDED:
            return self.result(job_id)
        if status.error is not None:
            code, message, field = status.error
            raise from_job_error(code, message, field, job_id)
        if status.state == JobState.CANCELLED:
            raise JobCancelled(f"job {job_id} was cancelled", job_id=job_id)
        raise MurkError(f"job {job_id} ended {status.state.name}", job_id=job_id)

    # -- one method per reconstruction ---------------------------------------------------------

    def tof_depth(
        self,
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
        progress: ProgressCallback | None = None,
        timeout_s: float | None = None,
    ) -> TofDepthResult:
        """ToF depth in fog (Ch. 5); see :func:`murk_client.requests.tof_depth_request` for units."""
        req = build.tof_depth_request(
            amplitude,
            phase,
            modulation_frequency_hz=modulation_frequency_hz,
            intrinsics=intrinsics,
            light_position_m=light_position_m,
            options=options,
            outputs=outputs,
            encoding=encoding,
            return_points=return_points,
            max_point_range_std_m=max_point_range_std_m,
        )
        return _expect(self.run(req, progress=progress, timeout_s=timeout_s), TofDepthResult)

    def mvs_depth(
        self,
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
        progress: ProgressCallback | None = None,
        timeout_s: float | None = None,
    ) -> MvsDepthResult:
        """MVS depth in haze (Ch. 3.2); see :func:`murk_client.requests.mvs_depth_request`."""
        req = build.mvs_depth_request(
            reference,
            sources,
            cost_volume=cost_volume,
            airlight=airlight,
            beta_per_scene_unit=beta_per_scene_unit,
            near_scene_units=near_scene_units,
            far_scene_units=far_scene_units,
            num_planes=num_planes,
            sgm=sgm,
        )
        return _expect(self.run(req, progress=progress, timeout_s=timeout_s), MvsDepthResult)

    def rectified_stereo(
        self,
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
        progress: ProgressCallback | None = None,
        timeout_s: float | None = None,
    ) -> RectifiedStereoResult:
        """Rectified stereo depth in haze; see :func:`murk_client.requests.rectified_stereo_request`."""
        req = build.rectified_stereo_request(
            left,
            right,
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
        return _expect(self.run(req, progress=progress, timeout_s=timeout_s), RectifiedStereoResult)

    def scattering_params(
        self,
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
        progress: ProgressCallback | None = None,
        timeout_s: float | None = None,
    ) -> ScatteringParamsResult:
        """A and β by Algorithm 1 (Ch. 3.3); see :func:`murk_client.requests.scattering_params_request`."""
        req = build.scattering_params_request(
            reference,
            sources,
            sparse_points_scene_units,
            airlight_source=airlight_source,
            airlight=airlight,
            beta_min_per_scene_unit=beta_min_per_scene_unit,
            beta_max_per_scene_unit=beta_max_per_scene_unit,
            near_scene_units=near_scene_units,
            far_scene_units=far_scene_units,
            seen_by_sources=seen_by_sources,
            observations=observations,
            options=options,
        )
        return _expect(self.run(req, progress=progress, timeout_s=timeout_s), ScatteringParamsResult)

    def photometric_stereo(
        self,
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
        progress: ProgressCallback | None = None,
        timeout_s: float | None = None,
    ) -> PhotometricStereoResult:
        """Photometric stereo in turbid water (Ch. 4).

        See :func:`murk_client.requests.photometric_stereo_request` for units.
        """
        req = build.photometric_stereo_request(
            lights,
            mask,
            intrinsics=intrinsics,
            beta_per_mm=beta_per_mm,
            sigma_per_mm=sigma_per_mm,
            initial_distance_mm=initial_distance_mm,
            fix_distance=fix_distance,
            mode=mode,
            options=options,
        )
        return _expect(self.run(req, progress=progress, timeout_s=timeout_s), PhotometricStereoResult)

    # -- sensor sessions -----------------------------------------------------------------------

    def session(
        self, config: sessions_pb2.SessionConfig, frames: Iterable[sessions_pb2.SessionFrame]
    ) -> Iterator[FrameOutcome]:
        """Streams ``frames`` through a sensor session and yields each one's outcome, in order.

        ``config`` from :func:`murk_client.tof_session_config` or
        :func:`murk_client.stereo_session_config`; frames from :func:`murk_client.tof_frame` or
        :func:`murk_client.stereo_frame` (their ``sequence`` is numbered here). ``frames`` is
        read as the server takes them, so a generator over a live sensor works. On UNAVAILABLE
        the session is opened again (cold) and the unanswered frames are sent again, under the
        client's :class:`RetryPolicy`; a bad configuration raises :class:`InvalidArgument`.
        """
        return run_session(self._channel, self._metadata, config, frames, self.retry)

    # -- plumbing ------------------------------------------------------------------------------

    def _unary(self, method: Callable[..., T], request: Any, *, job_id: str | None = None) -> T:
        return self._with_retry(
            lambda: method(request, metadata=self._metadata, timeout=self.timeout_s), job_id
        )

    def _with_retry(self, call: Callable[[], T], job_id: str | None) -> T:
        attempt = 0
        while True:
            try:
                return call()
            except grpc.RpcError as e:
                err = from_rpc_error(e, job_id=job_id)
            except ResultIntegrityError as e:
                err = e
            if err.code == grpc.StatusCode.DEADLINE_EXCEEDED:
                raise DeadlineExceeded(err.message, job_id=job_id) from None
            if not self.retry.should_retry(err, attempt):
                raise err from None
            self.retry.sleep(self.retry.delay_s(err, attempt))
            attempt += 1

    def _fetch_result(self, job_id: str) -> bytes:
        parts = []
        total: int | None = None
        digest = ""
        offset = 0
        stream = self._jobs.GetJobResult(
            jobs_pb2.GetJobResultRequest(id=job_id), metadata=self._metadata, timeout=self.timeout_s
        )
        for chunk in stream:
            if total is None:
                total, digest = int(chunk.total_bytes), chunk.sha256
            if chunk.offset != offset:
                raise ResultIntegrityError(
                    f"job {job_id}: chunk at offset {chunk.offset}, expected {offset}", job_id=job_id
                )
            parts.append(chunk.data)
            offset += len(chunk.data)
        data = b"".join(parts)
        if total is not None and len(data) != total:
            raise ResultIntegrityError(f"job {job_id}: got {len(data)} of {total} bytes", job_id=job_id)
        if digest and hashlib.sha256(data).hexdigest() != digest:
            raise ResultIntegrityError(f"job {job_id}: result SHA-256 mismatch", job_id=job_id)
        return data


class _Ended(grpc.RpcError):
    """A watch stream that ended before the job was terminal (treated as UNAVAILABLE)."""

    def code(self) -> grpc.StatusCode:
        return grpc.StatusCode.UNAVAILABLE

    def details(self) -> str:
        return "watch stream ended before the job finished"


def _expect(result: Result, cls: type[R]) -> R:
    if not isinstance(result, cls):
        raise MurkError(f"expected a {cls.__name__}, got {type(result).__name__}")
    return result
