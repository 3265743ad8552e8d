"""Sensor sessions through the client against a real server: outcomes in frame order with their
metadata, a bad frame that leaves the session going, the same depth as one-shot requests, drops
under the ``latest`` policy, and a bad configuration named by its field."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

import murk_client as mc
from murk_client import Client
from murk_client._proto.murk.v1 import sessions_pb2

from .balancer import Nginx
from .conftest import MurkServer, simulate


def test_a_tof_session_answers_every_frame_in_order(client: Client, tof_scene: Path) -> None:
    frame = mc.load_tof_frame(tof_scene)
    h, w = frame.amplitude.shape
    config = mc.tof_session_config(
        width=w,
        height=h,
        modulation_frequency_hz=frame.modulation_frequency_hz,
        intrinsics=frame.intrinsics,
        light_position_m=frame.light_position_m,
    )
    bad_phase = frame.phase.copy()
    bad_phase[0, 0] = np.nan

    def frames() -> Iterator[sessions_pb2.SessionFrame]:
        for k in range(4):
            phase = bad_phase if k == 2 else frame.phase
            yield mc.tof_frame(frame.amplitude, phase, frame_id=f"f{k}", stamp_s=1.7e9 + k / 10)

    outcomes = list(client.session(config, frames()))
    assert [o.sequence for o in outcomes] == [1, 2, 3, 4]
    assert [o.frame_id for o in outcomes] == ["f0", "f1", "f2", "f3"]
    assert outcomes[3].stamp_s == pytest.approx(1.7e9 + 0.3)
    bad = outcomes[2]
    assert bad.result is None and isinstance(bad.error, mc.InvalidArgument)
    assert bad.error.field == "frame.phase"
    one_shot = client.tof_depth(
        frame.amplitude,
        frame.phase,
        modulation_frequency_hz=frame.modulation_frequency_hz,
        intrinsics=frame.intrinsics,
        light_position_m=frame.light_position_m,
    )
    assert one_shot.z_depth_m is not None and one_shot.range_std_m is not None
    # No measurement where the reported spread is at its cap (the direct return below the noise).
    measured = one_shot.range_std_m < one_shot.range_std_m.max()
    for o in (outcomes[0], outcomes[1], outcomes[3]):
        assert isinstance(o.result, mc.TofDepthResult) and o.error is None and o.dropped is None
        # A session's default result is compact: the z-depth in whole millimetres (0 where
        # nothing was measured), the mask and the spread; nothing else.
        r = o.result
        assert r.z_depth_m is not None and r.mask is not None and r.range_std_m is not None
        assert r.range_m is None and r.raw_range_m is None and r.weight_phase is None
        np.testing.assert_allclose(r.z_depth_m[measured], one_shot.z_depth_m[measured], atol=5.1e-4)
        assert np.all(r.z_depth_m[~measured] == 0)
        np.testing.assert_array_equal(r.mask, one_shot.mask)
        assert o.compute_s > 0


def test_a_session_returns_the_images_and_encoding_it_asks_for(client: Client, tof_scene: Path) -> None:
    frame = mc.load_tof_frame(tof_scene)
    h, w = frame.amplitude.shape
    kwargs = {
        "modulation_frequency_hz": frame.modulation_frequency_hz,
        "intrinsics": frame.intrinsics,
        "light_position_m": frame.light_position_m,
    }
    exact = client.tof_depth(frame.amplitude, frame.phase, **kwargs, outputs=["range_m", "corrected_phase"])
    assert exact.z_depth_m is None and exact.mask is None
    assert exact.range_m is not None and exact.corrected_phase is not None
    config = mc.tof_session_config(
        width=w, height=h, **kwargs, outputs=["range_m", "corrected_phase"], encoding="f16"
    )
    (o,) = client.session(config, [mc.tof_frame(frame.amplitude, frame.phase)])
    assert isinstance(o.result, mc.TofDepthResult)
    assert o.result.range_m is not None and o.result.corrected_phase is not None
    assert o.result.mask is None and o.result.z_depth_m is None
    assert o.result.proto.range_m.WhichOneof("data") == "raw_f16_le"
    # Half-precision floats: 11 significant bits.
    np.testing.assert_allclose(o.result.range_m, exact.range_m, rtol=2.0**-11)
    np.testing.assert_allclose(o.result.corrected_phase, exact.corrected_phase, rtol=2.0**-11)
    with pytest.raises(mc.ClientInputError) as e:
        mc.tof_session_config(width=w, height=h, **kwargs, encoding="jpeg")
    assert e.value.field == "config.tof.outputs.encoding"


def test_a_tof_sessions_grid_answers_as_the_full_size_frames(client: Client, tmp_path: Path) -> None:
    # 128 x 106 frames: the default 2 x 2 grid divides them, so the warm frames solve for the
    # scatter on the 64 x 53 block means and decide the mask and depth at full size, and the
    # first frame solves its coarse level there.
    size = ("--width", "128", "--height", "106")
    seq = simulate("tof", tmp_path / "seq", *size, "--seed", "4", "--frames", "3")
    frames = [mc.load_tof_frame(d) for d in sorted(p for p in seq.iterdir() if p.is_dir())]
    h, w = frames[0].amplitude.shape
    kwargs = {
        "modulation_frequency_hz": frames[0].modulation_frequency_hz,
        "intrinsics": frames[0].intrinsics,
        "light_position_m": frames[0].light_position_m,
        "outputs": ["range_m", "mask"],
        "encoding": "f32",
    }
    answers = {}
    for grid in (0, 1):
        config = mc.tof_session_config(width=w, height=h, **kwargs, scatter_grid=grid)
        answers[grid] = list(client.session(config, [mc.tof_frame(f.amplitude, f.phase) for f in frames]))
    for on_grid, full in zip(answers[0], answers[1], strict=True):
        assert on_grid.result is not None and full.result is not None
        assert on_grid.result.mask.shape == (h, w)
        object_pixels = (full.result.mask == 1.0) & (on_grid.result.mask == 1.0)
        assert np.mean(on_grid.result.mask != full.result.mask) <= 0.01
        assert object_pixels.sum() > 1000
        diff = np.abs(on_grid.result.range_m - full.result.range_m)[object_pixels]
        assert np.median(diff) < 1e-3
    with pytest.raises(mc.ClientInputError) as e:
        mc.tof_session_config(width=w, height=h, **kwargs, scatter_grid=5)
    assert e.value.field == "config.tof_scatter_grid"


def test_latest_drops_frames_it_cannot_keep_up_with(client: Client, tof_scene: Path) -> None:
    frame = mc.load_tof_frame(tof_scene)
    h, w = frame.amplitude.shape
    config = mc.tof_session_config(
        width=w,
        height=h,
        modulation_frequency_hz=frame.modulation_frequency_hz,
        options={"fine_iterations": 400, "convergence_tolerance": 0.0},
        queue_policy="latest",
        max_queued_frames=1,
    )
    frames = [mc.tof_frame(frame.amplitude, frame.phase, frame_id=f"f{k}") for k in range(10)]
    outcomes = list(client.session(config, frames))
    assert sorted(o.sequence for o in outcomes) == list(range(1, 11))
    dropped = [o for o in outcomes if o.dropped is not None]
    assert dropped and all(o.dropped == "superseded" for o in dropped)
    answered = [o.sequence for o in outcomes if o.result is not None]
    assert answered == sorted(answered) and answered[-1] == 10


def test_a_bad_configuration_names_its_field(client: Client) -> None:
    # Checked here before anything is sent...
    with pytest.raises(mc.ClientInputError) as local:
        mc.tof_session_config(width=64, height=53, modulation_frequency_hz=16.0)
    assert local.value.field == "config.tof.modulation_frequency_hz"
    # ...or by the server, which ends the session.
    config = mc.tof_session_config(width=1, height=53, modulation_frequency_hz=16e6)
    with pytest.raises(mc.InvalidArgument) as remote:
        list(client.session(config, []))
    assert remote.value.field == "config.width"


def test_a_session_survives_its_replica_dying_behind_nginx(
    workdir: Path, tmp_path: Path, tof_scene: Path
) -> None:
    """Two replicas behind the shipped ``deploy/nginx.conf``: the replica serving a stream is
    killed (SIGKILL, no drain) mid-stream; the client opens a new session through the balancer,
    which reaches the other replica, sends the unanswered frames again, and every frame is
    answered once, in order."""
    replicas = [MurkServer([], workdir), MurkServer([], workdir)]
    balancer = Nginx([r.addr for r in replicas], tmp_path)
    try:
        frame = mc.load_tof_frame(tof_scene)
        h, w = frame.amplitude.shape
        config = mc.tof_session_config(
            width=w,
            height=h,
            modulation_frequency_hz=frame.modulation_frequency_hz,
            intrinsics=frame.intrinsics,
            # Frames slow enough that some are still unanswered when the replica dies.
            options={"fine_iterations": 200, "convergence_tolerance": 0.0},
        )
        frames = (mc.tof_frame(frame.amplitude, frame.phase, frame_id=f"f{k}") for k in range(10))
        policy = mc.RetryPolicy(max_attempts=5, initial_backoff_s=0.05, max_backoff_s=0.5)
        outcomes = []
        killed: list[MurkServer] = []
        with Client(balancer.url, retry=policy) as c:
            for o in c.session(config, frames):
                outcomes.append(o)
                if len(outcomes) == 3:
                    serving = _serving_replica(replicas)
                    serving.kill()
                    killed.append(serving)
        assert [o.frame_id for o in outcomes] == [f"f{k}" for k in range(10)]
        assert all(isinstance(o.result, mc.TofDepthResult) and o.error is None for o in outcomes)
        (survivor,) = [r for r in replicas if r is not killed[0]]
        # The survivor computed the frames the dead replica left unanswered.
        ended = survivor.wait_for_log("session ended", timeout_s=10)
        assert ended is not None, "the new session did not reach the other replica"
        assert 1 <= int(ended["computed"]) <= 7, ended
    finally:
        balancer.stop()
        for r in replicas:
            r.stop()


def _serving_replica(replicas: list[MurkServer]) -> MurkServer:
    """The replica that logged the session's start (its log line may still be in the pipe)."""
    for _ in range(100):
        for r in replicas:
            if r.wait_for_log("session started", timeout_s=0.05) is not None:
                return r
    raise AssertionError("no replica logged the session")
