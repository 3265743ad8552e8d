"""When and how long to wait before retrying a call.

Every murk call the client makes is safe to repeat: a job's id is the content hash of its
request, so a repeated SubmitJob returns the same job (or its cached result) instead of queueing
the work twice, and Get/Watch/Cancel/GetJobResult only read or are idempotent.
"""

from __future__ import annotations

import random
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import grpc

from .errors import MurkError


def _default_codes() -> frozenset[grpc.StatusCode]:
    # DATA_LOSS is what a chunked result that did not reassemble raises (ResultIntegrityError):
    # fetching it again is the remedy.
    return frozenset(
        {grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.RESOURCE_EXHAUSTED, grpc.StatusCode.DATA_LOSS}
    )


@dataclass(frozen=True)
class RetryPolicy:
    """Retries transient failures: UNAVAILABLE and RESOURCE_EXHAUSTED (a full queue) by default.

    The delay before retry ``n`` (0-based) is the server's ``RetryInfo`` hint when it sent one,
    else ``initial_backoff_s * multiplier**n``; either is multiplied by a random factor in
    ``[1, 1 + jitter]`` (so that a fleet refused at once does not come back at once) and capped
    at ``max_backoff_s``. A RESOURCE_EXHAUSTED without RetryInfo is a size limit, not a full
    queue, and is not retried.
    """

    #: Total attempts, the first included (1 = never retry).
    max_attempts: int = 6
    initial_backoff_s: float = 0.25
    multiplier: float = 2.0
    #: Upper bound of every single delay, seconds, the server's hint included.
    max_backoff_s: float = 10.0
    #: Relative random extra delay, >= 0.
    jitter: float = 0.5
    retryable: frozenset[grpc.StatusCode] = field(default_factory=_default_codes)
    #: Waits ``seconds``; replaceable in tests.
    sleep: Callable[[float], None] = time.sleep
    #: Uniform random numbers in [0, 1); replaceable for reproducible delays.
    random: Callable[[], float] = random.random

    def __post_init__(self) -> None:
        if self.max_attempts < 1:
            raise ValueError("max_attempts must be >= 1")
        if not (self.initial_backoff_s >= 0 and self.max_backoff_s >= 0 and self.jitter >= 0):
            raise ValueError("backoffs and jitter must be >= 0")
        if self.multiplier < 1:
            raise ValueError("multiplier must be >= 1")

    @classmethod
    def never(cls) -> RetryPolicy:
        """No retries: every error is raised at once."""
        return cls(max_attempts=1)

    def should_retry(self, error: MurkError, attempt: int) -> bool:
        """Whether to retry after ``error`` on 0-based ``attempt``."""
        if attempt + 1 >= self.max_attempts or error.code not in self.retryable:
            return False
        if error.code == grpc.StatusCode.RESOURCE_EXHAUSTED:
            return error.retry_after_s is not None
        return True

    def delay_s(self, error: MurkError, attempt: int) -> float:
        """Seconds to wait before retrying after ``error`` on 0-based ``attempt``."""
        base: float | None = error.retry_after_s
        if base is None:
            base = self.initial_backoff_s * self.multiplier**attempt
        return min(self.max_backoff_s, base * (1.0 + self.jitter * self.random()))
