"""Typed exceptions for every way a call or a job can fail.

The server attaches ``google.rpc`` details to its errors (``grpc-status-details-bin``):
``BadRequest`` names the request field at fault (``tof_depth.phase``), ``RetryInfo`` says when a
full queue or a draining replica is worth retrying, ``PreconditionFailure`` says why a result
cannot be returned on a unary call. They are decoded here into attributes, so callers never
touch the wire format.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import grpc


@dataclass(frozen=True)
class FieldViolation:
    """One bad field of a request: its dotted path (``tof_depth.phase``) and what is wrong."""

    field: str
    description: str


class MurkError(Exception):
    """Base of every error this package raises.

    ``code`` is the gRPC status code, ``message`` the server's text.
    """

    code: grpc.StatusCode = grpc.StatusCode.UNKNOWN

    def __init__(
        self,
        message: str,
        *,
        code: grpc.StatusCode | None = None,
        job_id: str | None = None,
        field_violations: Sequence[FieldViolation] = (),
        retry_after_s: float | None = None,
        precondition_types: Sequence[str] = (),
    ) -> None:
        super().__init__(message)
        self.message = message
        if code is not None:
            self.code = code
        #: The job the error belongs to, when known (a failed job, or ``x-murk-job-id``).
        self.job_id = job_id
        #: ``google.rpc.BadRequest`` violations (empty for other errors).
        self.field_violations = tuple(field_violations)
        #: ``google.rpc.RetryInfo``: seconds the server asks the client to wait before retrying.
        self.retry_after_s = retry_after_s
        #: ``google.rpc.PreconditionFailure`` violation types, e.g. ``RESULT_TOO_LARGE``.
        self.precondition_types = tuple(precondition_types)

    @property
    def field(self) -> str | None:
        """The dotted path of the first bad field, e.g. ``"tof_depth.phase"``, or None."""
        return self.field_violations[0].field if self.field_violations else None

    def __str__(self) -> str:
        where = f" [{self.field}]" if self.field else ""
        return f"{self.code.name}{where}: {self.message}"


class InvalidArgument(MurkError):
    """The request is malformed; :attr:`field` names the part (never worth retrying)."""

    code = grpc.StatusCode.INVALID_ARGUMENT


class ClientInputError(InvalidArgument, ValueError):
    """An argument this package rejected before sending anything (same fields as the server's)."""

    def __init__(self, field: str, description: str) -> None:
        super().__init__(f"{field}: {description}", field_violations=[FieldViolation(field, description)])


class NotFound(MurkError):
    """No such job for this tenant (or it was forgotten)."""

    code = grpc.StatusCode.NOT_FOUND


class FailedPrecondition(MurkError):
    """The job is not finished, or a unary result would exceed the size limit."""

    code = grpc.StatusCode.FAILED_PRECONDITION


class ResourceExhausted(MurkError):
    """The queue is full (or a size limit was hit); :attr:`retry_after_s` says when to retry."""

    code = grpc.StatusCode.RESOURCE_EXHAUSTED


class Unauthenticated(MurkError):
    """No token, or a token the server does not know."""

    code = grpc.StatusCode.UNAUTHENTICATED


class PermissionDenied(MurkError):
    """The token is valid but may not do this."""

    code = grpc.StatusCode.PERMISSION_DENIED


class Unavailable(MurkError):
    """The server cannot be reached or is shutting down (transient)."""

    code = grpc.StatusCode.UNAVAILABLE


class DeadlineExceeded(MurkError):
    """The call's deadline passed."""

    code = grpc.StatusCode.DEADLINE_EXCEEDED


class JobCancelled(MurkError):
    """The job was cancelled (by a CancelJob call, or because every caller went away)."""

    code = grpc.StatusCode.CANCELLED


class Internal(MurkError):
    """A failure inside the server or the algorithm (e.g. a numerical breakdown)."""

    code = grpc.StatusCode.INTERNAL


class ResultIntegrityError(MurkError):
    """A chunked result did not reassemble to the size and SHA-256 the server announced."""

    code = grpc.StatusCode.DATA_LOSS


_BY_CODE: dict[grpc.StatusCode, type[MurkError]] = {
    cls.code: cls
    for cls in (
        InvalidArgument,
        NotFound,
        FailedPrecondition,
        ResourceExhausted,
        Unauthenticated,
        PermissionDenied,
        Unavailable,
        DeadlineExceeded,
        JobCancelled,
        Internal,
        ResultIntegrityError,
    )
}
_BY_NUMBER: dict[int, grpc.StatusCode] = {c.value[0]: c for c in grpc.StatusCode}


def error_for(
    code: grpc.StatusCode,
    message: str,
    *,
    job_id: str | None = None,
    field_violations: Sequence[FieldViolation] = (),
    retry_after_s: float | None = None,
    precondition_types: Sequence[str] = (),
) -> MurkError:
    """The typed exception for ``code`` (``MurkError`` itself for codes without a subclass)."""
    cls = _BY_CODE.get(code, MurkError)
    return cls(
        message,
        code=code,
        job_id=job_id,
        field_violations=field_violations,
        retry_after_s=retry_after_s,
        precondition_types=precondition_types,
    )


def from_job_error(code: int, message: str, field: str, job_id: str) -> MurkError:
    """The exception for a job that ended FAILED (``Job.error``: a google.rpc code number)."""
    status = _BY_NUMBER.get(code, grpc.StatusCode.UNKNOWN)
    violations = [FieldViolation(field, message)] if field else []
    return error_for(status, message, job_id=job_id, field_violations=violations)


# How gRPC core reports an HTTP/2 stream the other side reset (RST_STREAM), which it maps to
# INTERNAL although nothing ran on the server.
_TRANSPORT_RESETS = ("RST_STREAM", "Stream removed")


def from_rpc_error(err: grpc.RpcError, *, job_id: str | None = None) -> MurkError:
    """Decodes a failed call, its ``google.rpc`` details included."""
    from google.rpc import error_details_pb2
    from grpc_status import rpc_status

    call: Any = err
    code: grpc.StatusCode = call.code() if hasattr(call, "code") else grpc.StatusCode.UNKNOWN
    message: str = (call.details() if hasattr(call, "details") else None) or str(err)
    if code == grpc.StatusCode.INTERNAL and any(m in message for m in _TRANSPORT_RESETS):
        # A stream reset by the peer or a proxy, e.g. nginx when the replica behind a watch dies:
        # the transport failed, not the server's work, so it is as retryable as UNAVAILABLE.
        code = grpc.StatusCode.UNAVAILABLE
    violations: list[FieldViolation] = []
    retry_after: float | None = None
    preconditions: list[str] = []
    try:
        status = rpc_status.from_call(call)
    except Exception:
        # A status whose details do not match code/message (a proxy rewrote it): keep the code.
        status = None
    if status is not None:
        for detail in status.details:
            if detail.Is(error_details_pb2.BadRequest.DESCRIPTOR):
                br = error_details_pb2.BadRequest()
                detail.Unpack(br)
                violations += [FieldViolation(v.field, v.description) for v in br.field_violations]
            elif detail.Is(error_details_pb2.RetryInfo.DESCRIPTOR):
                ri = error_details_pb2.RetryInfo()
                detail.Unpack(ri)
                retry_after = ri.retry_delay.seconds + ri.retry_delay.nanos / 1e9
            elif detail.Is(error_details_pb2.PreconditionFailure.DESCRIPTOR):
                pf = error_details_pb2.PreconditionFailure()
                detail.Unpack(pf)
                preconditions += [v.type for v in pf.violations]
    if job_id is None and hasattr(call, "trailing_metadata"):
        for key, value in call.trailing_metadata() or ():
            if key == "x-murk-job-id" and isinstance(value, str):
                job_id = value
    return error_for(
        code,
        message,
        job_id=job_id,
        field_violations=violations,
        retry_after_s=retry_after,
        precondition_types=preconditions,
    )
