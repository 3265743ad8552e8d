"""The Jobs API through the client: submit/watch/result/cancel/list, errors with their details,
RetryInfo under a full queue, and a result over gRPC's 4 MiB default through a default channel."""

from __future__ import annotations

from pathlib import Path

import grpc
import numpy as np
import pytest

import murk_client as mc
from murk_client import Client, RetryPolicy

from .conftest import MurkServer, ServerFactory


def slow_tof_request(frame: mc.TofFrame, variant: int) -> mc.pb.JobRequest:
    """A ToF job that runs for seconds (no early stop); ``variant`` makes its content hash unique."""
    return mc.tof_depth_request(
        frame.amplitude,
        frame.phase,
        modulation_frequency_hz=16e6,
        options={"fine_iterations": 2000 + variant, "convergence_tolerance": 0},
    )


def test_submit_watch_result_and_dedupe(client: Client, tof_scene: Path) -> None:
    frame = mc.load_tof_frame(tof_scene)
    req = mc.tof_depth_request(
        frame.amplitude, frame.phase, modulation_frequency_hz=16e6, options={"fine_iterations": 7}
    )
    job_id = client.submit(req)
    assert len(job_id) == 64
    updates = list(client.watch(job_id))
    assert updates[-1].state == mc.JobState.SUCCEEDED
    assert all(not u.state.terminal for u in updates[:-1])
    progress = [u.progress for u in updates]
    assert progress == sorted(progress) and progress[-1] == pytest.approx(1.0)
    result = client.result(job_id)
    assert isinstance(result, mc.TofDepthResult) and result.range_m.shape == frame.amplitude.shape
    # The same work again is the same job, answered from the cache.
    assert client.submit(req) == job_id
    status = client.job(job_id)
    assert status.state == mc.JobState.SUCCEEDED and status.result_size_bytes > 0
    assert status.end_time is not None and status.create_time is not None
    assert job_id in {j.id for j in client.list_jobs(page_size=2)}


def test_full_frame_result_over_4_mib_through_a_default_channel(client: Client, tof_scene_full: Path) -> None:
    frame = mc.load_tof_frame(tof_scene_full)
    assert frame.amplitude.shape == (424, 512)
    r = client.tof_depth(
        frame.amplitude,
        frame.phase,
        modulation_frequency_hz=frame.modulation_frequency_hz or 16e6,
        intrinsics=frame.intrinsics,
    )
    assert client.job(r.job_id).result_size_bytes > 4 * 1024 * 1024
    assert r.range_m.shape == (424, 512) and r.z_depth_m is not None
    assert r.warnings == (), r.warnings  # the IRLS converged within its cap
    gt = mc.read_image(tof_scene_full / "gt_range_m.exr")
    obj = (mc.read_image(tof_scene_full / "gt_object_mask.png") > 0.5) & (r.mask > 0.5)
    assert np.median(np.abs(r.range_m[obj] - gt[obj])) < np.median(np.abs(r.raw_range_m[obj] - gt[obj]))


def test_bad_request_names_the_field(client: Client, tof_scene: Path) -> None:
    frame = mc.load_tof_frame(tof_scene)
    phase = frame.phase.copy()
    phase[3, 5] = np.nan
    with pytest.raises(mc.InvalidArgument) as e:
        client.tof_depth(frame.amplitude, phase, modulation_frequency_hz=16e6)
    assert e.value.field == "request.tof_depth.phase"
    assert "NaN" in e.value.field_violations[0].description
    assert e.value.code == grpc.StatusCode.INVALID_ARGUMENT
    with pytest.raises(mc.InvalidArgument) as e:
        client.tof_depth(frame.amplitude, frame.phase[:10], modulation_frequency_hz=16e6)
    assert e.value.field == "request.tof_depth.phase" and "differs" in e.value.message
    # Unit mistakes caught before sending: MHz for Hz, degrees for radians.
    with pytest.raises(mc.ClientInputError) as e:
        client.tof_depth(frame.amplitude, frame.phase, modulation_frequency_hz=16)
    assert e.value.field == "request.tof_depth.modulation_frequency_hz"
    with pytest.raises(mc.ClientInputError) as e:
        client.tof_depth(frame.amplitude, np.degrees(frame.phase), modulation_frequency_hz=16e6)
    assert e.value.field == "request.tof_depth.phase"
    with pytest.raises(mc.NotFound):
        client.job("0" * 64)


def test_cancel_a_running_job(start_server: ServerFactory, tof_scene: Path) -> None:
    s = start_server("--concurrent-jobs", "1")
    frame = mc.load_tof_frame(tof_scene)
    with Client(s.url) as c:
        job_id = c.submit(slow_tof_request(frame, 0))
        for status in c.watch(job_id):
            if status.state == mc.JobState.RUNNING:
                assert c.cancel(job_id).id == job_id
                break
        assert c.wait(job_id).state == mc.JobState.CANCELLED
        with pytest.raises(mc.JobCancelled) as e:
            c.result(job_id)
        assert e.value.job_id == job_id


def test_full_queue_is_retried_as_retry_info_says(start_server: ServerFactory, tof_scene: Path) -> None:
    s: MurkServer = start_server("--concurrent-jobs", "1", "--queue-capacity", "1", "--retry-after-ms", "300")
    frame = mc.load_tof_frame(tof_scene)
    with Client(s.url, retry=RetryPolicy.never()) as c:
        running = c.submit(slow_tof_request(frame, 1))
        # Only once the first job left the queue for the worker is there room for the second
        # (on a loaded host the worker may take a moment to pick it up).
        for status in c.watch(running):
            if status.state == mc.JobState.RUNNING:
                break
        queued = c.submit(slow_tof_request(frame, 2))
        with pytest.raises(mc.ResourceExhausted) as e:
            c.submit(slow_tof_request(frame, 3))
        hint = e.value.retry_after_s
        assert hint is not None and hint >= 0.3

        # A retrying client waits the hinted time (plus jitter, under the cap); the queue frees
        # while it waits (the sleep hook cancels the two jobs), so the retry is accepted.
        delays: list[float] = []

        def sleep(seconds: float) -> None:
            delays.append(seconds)
            c.cancel(queued)
            c.cancel(running)
            c.wait(running)

        policy = RetryPolicy(jitter=0.5, max_backoff_s=30.0, sleep=sleep, random=lambda: 1.0)
        with Client(s.url, retry=policy) as retrying:
            job_id = retrying.submit(slow_tof_request(frame, 3))
            assert len(delays) == 1
            assert 1.5 * 0.3 <= delays[0] <= 30.0
            assert retrying.cancel(job_id).id == job_id


def test_watch_follows_a_job_across_a_server_crash(workdir: Path, tmp_path: Path, tof_scene: Path) -> None:
    """kill -9 mid-job, the server restarts on the same address with the same journal: the
    client's watch re-attaches (UNAVAILABLE is retried), the recovered job finishes and its result
    arrives, without the caller seeing the crash."""
    from .conftest import MurkServer

    cache = tmp_path / "cache"
    flags = ["--cache-dir", str(cache), "--concurrent-jobs", "1"]
    first = MurkServer(flags, workdir)
    servers = [first]
    frame = mc.load_tof_frame(tof_scene)
    try:
        policy = RetryPolicy(max_attempts=8, initial_backoff_s=0.05, max_backoff_s=1.0)
        with Client(first.url, retry=policy) as c:
            job_id = c.submit(slow_tof_request(frame, 4))
            states: list[str] = []

            def crash_once(status: mc.JobStatus) -> None:
                states.append(status.state.name)
                if status.state == mc.JobState.RUNNING and len(servers) == 1:
                    first.kill()
                    servers.append(MurkServer(flags, workdir, addr=first.addr))

            final = c.wait(job_id, progress=crash_once)
            assert len(servers) == 2, "the job never ran"
            assert final.state == mc.JobState.SUCCEEDED, states
            result = c.result(job_id)
            assert isinstance(result, mc.TofDepthResult) and result.job_id == job_id
    finally:
        for s in servers:
            s.stop()


def test_stream_resets_are_transient() -> None:
    class Reset(grpc.RpcError):
        def code(self) -> grpc.StatusCode:
            return grpc.StatusCode.INTERNAL

        def details(self) -> str:
            return "Stream removed (RST_STREAM (Received RST_STREAM with error code 2))"

    class Boom(Reset):
        def details(self) -> str:
            return "numerical breakdown in tof.phase.fine"

    assert isinstance(mc.errors.from_rpc_error(Reset()), mc.Unavailable)
    assert RetryPolicy().should_retry(mc.errors.from_rpc_error(Reset()), 0)
    assert isinstance(mc.errors.from_rpc_error(Boom()), mc.Internal)
