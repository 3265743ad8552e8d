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
    for o in (outcomes[0], outcomes[1], outcomes[3]):
        assert isinstance(o.result, mc.TofDepthResult) and o.error is None and o.dropped is None
        np.testing.assert_array_equal(o.result.range_m, one_shot.range_m)
        assert o.compute_s > 0


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
