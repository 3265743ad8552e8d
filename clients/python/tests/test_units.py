"""Conversions and policies that need no server."""

from __future__ import annotations

import struct
from pathlib import Path

import grpc
import numpy as np
import pytest

import murk_client as mc
from murk_client import images
from murk_client._proto.murk.v1 import common_pb2
from murk_client.retry import RetryPolicy


def test_raw_images_are_planar_on_the_wire() -> None:
    rgb = np.arange(2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3)  # (h, w, c)
    msg = images.to_proto(rgb, field="x")
    assert (msg.width, msg.height, msg.channels) == (3, 2, 3)
    wire = np.frombuffer(msg.raw_f32_le, dtype="<f4")
    # All of channel 0 first (row-major), then channel 1, ...
    np.testing.assert_array_equal(wire[:6], rgb[:, :, 0].ravel())
    np.testing.assert_array_equal(wire[6:12], rgb[:, :, 1].ravel())
    np.testing.assert_array_equal(images.from_proto(msg), rgb)
    grey = np.random.default_rng(1).random((5, 4)).astype(np.float64)
    back = images.from_proto(images.to_proto(grey, field="g"))
    assert back.shape == (5, 4) and back.dtype == np.float32
    np.testing.assert_allclose(back, grey, rtol=1e-7)


def test_raw_u8_planes_decode_to_unit_range() -> None:
    rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3) * 13  # (h, w, c)
    planar = np.ascontiguousarray(np.moveaxis(rgb, 2, 0)).tobytes()
    msg = common_pb2.Image(width=3, height=2, channels=3, raw_u8=planar)
    np.testing.assert_array_equal(images.from_proto(msg), rgb.astype(np.float32) / np.float32(255.0))
    msg.raw_u8 = planar[1:]
    with pytest.raises(mc.ClientInputError, match="raw_u8"):
        images.from_proto(msg)


def test_value_scale_zero_means_one() -> None:
    msg = images.to_proto(np.full((2, 2), 3.0), field="x")
    assert msg.value_scale == 0.0
    np.testing.assert_array_equal(images.from_proto(msg), np.full((2, 2), 3.0))
    msg.value_scale = 2.0
    msg.value_offset = 1.0
    np.testing.assert_array_equal(images.from_proto(msg), np.full((2, 2), 7.0))


def test_srgb_files_are_marked_and_arrays_decoded() -> None:
    e = images.to_proto(mc.EncodedImage(b"png", srgb=True), field="reference")
    assert e.transfer == common_pb2.TRANSFER_SRGB
    plain = images.to_proto(mc.EncodedImage(b"png"), field="reference")
    # Linear images go out unset (0), which every server version reads as linear.
    assert plain.transfer == common_pb2.TRANSFER_UNSPECIFIED
    lin = mc.srgb_to_linear(np.array([0.0, 0.5, 1.0]))
    assert lin.dtype == np.float32
    assert np.allclose(lin, [0.0, 0.21404, 1.0], atol=1e-4)


def test_bad_arrays_name_the_field() -> None:
    with pytest.raises(mc.ClientInputError) as e:
        images.to_proto(np.zeros((2, 2, 2, 2)), field="request.tof_depth.amplitude")
    assert e.value.field == "request.tof_depth.amplitude"
    with pytest.raises(mc.ClientInputError):
        images.to_proto(np.zeros((4, 4, 3)), field="m", channels=1)
    with pytest.raises(mc.ClientInputError):
        images.to_proto(np.array([["a"]]), field="s")


def test_image_files_decode_like_the_server(tmp_path: Path) -> None:
    from PIL import Image

    u16 = np.array([[0, 65535], [32768, 1]], dtype=np.uint16)
    Image.fromarray(u16).save(tmp_path / "a.png")
    np.testing.assert_allclose(mc.read_image(tmp_path / "a.png"), u16 / 65535.0, rtol=1e-6)
    u8 = np.array([[0, 255], [128, 1]], dtype=np.uint8)
    Image.fromarray(u8).save(tmp_path / "b.png")
    np.testing.assert_allclose(mc.read_image(tmp_path / "b.png"), u8 / 255.0, rtol=1e-6)
    f = np.random.default_rng(2).random((6, 5)).astype(np.float32)
    mc.write_exr(tmp_path / "c.exr", f)
    np.testing.assert_array_equal(mc.read_image(tmp_path / "c.exr"), f)
    n = np.random.default_rng(3).random((6, 5, 3)).astype(np.float32)
    mc.write_exr(tmp_path / "n.exr", n)
    np.testing.assert_array_equal(mc.read_image(tmp_path / "n.exr"), n)
    (tmp_path / "bad.exr").write_bytes(b"v/1\x01" + b"\0" * 10)
    with pytest.raises(mc.ClientInputError):
        mc.read_image(tmp_path / "bad.exr")


def test_retry_delay_honours_retry_info_with_jitter_and_cap() -> None:
    full = mc.ResourceExhausted("queue full", retry_after_s=2.0)
    p = RetryPolicy(jitter=0.5, max_backoff_s=2.5, random=lambda: 0.5)
    assert p.should_retry(full, 0)
    assert p.delay_s(full, 0) == pytest.approx(2.5)  # 2 * 1.25 = 2.5, at the cap
    assert RetryPolicy(jitter=0.5, random=lambda: 0.0).delay_s(full, 3) == pytest.approx(2.0)
    assert RetryPolicy(jitter=0.5, max_backoff_s=1.0, random=lambda: 0.9).delay_s(full, 0) == 1.0
    # Without a hint: exponential backoff.
    down = mc.Unavailable("connection refused")
    q = RetryPolicy(initial_backoff_s=0.1, multiplier=2.0, jitter=0.0, max_backoff_s=100)
    assert [q.delay_s(down, n) for n in range(4)] == pytest.approx([0.1, 0.2, 0.4, 0.8])
    # Jitter spreads a fleet's retries over [d, d * (1 + jitter)].
    rng = np.random.default_rng(4)
    r = RetryPolicy(jitter=0.5, max_backoff_s=100, random=lambda: float(rng.random()))
    spread = [r.delay_s(full, 0) for _ in range(200)]
    assert 2.0 <= min(spread) < 2.1 and 2.9 < max(spread) <= 3.0
    # Attempts are capped; a size limit (no RetryInfo) and bad input are never retried.
    assert not RetryPolicy(max_attempts=3).should_retry(full, 2)
    assert not p.should_retry(mc.ResourceExhausted("request too large"), 0)
    assert not p.should_retry(mc.InvalidArgument("bad"), 0)
    assert not RetryPolicy.never().should_retry(down, 0)


def test_job_errors_map_to_typed_exceptions() -> None:
    e = mc.errors.from_job_error(3, "non-finite sample", "request.tof_depth.phase", "abc")
    assert isinstance(e, mc.InvalidArgument) and e.field == "request.tof_depth.phase" and e.job_id == "abc"
    assert isinstance(mc.errors.from_job_error(13, "boom", "", "abc"), mc.Internal)
    assert isinstance(mc.errors.from_job_error(1, "stopped", "", "abc"), mc.JobCancelled)
    assert mc.errors.from_job_error(999, "?", "", "abc").code == grpc.StatusCode.UNKNOWN


def test_colmap_quaternion_and_principal_point() -> None:
    k = mc.Intrinsics.from_colmap(500, 500, 320, 240)
    assert (k.cx, k.cy) == (319.5, 239.5)
    angle = 0.3
    pose = mc.Pose.from_quaternion(np.cos(angle / 2), 0, np.sin(angle / 2), 0, [1, 2, 3])
    r = pose.rotation
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(r[0], [np.cos(angle), 0, np.sin(angle)], atol=1e-12)
    np.testing.assert_allclose(pose.camera_centre, -r.T @ np.array([1.0, 2.0, 3.0]))


def write_colmap_bin(d: Path) -> None:
    """A two-image, two-point model in COLMAP's binary format."""
    with open(d / "cameras.bin", "wb") as f:
        f.write(
            struct.pack("<Q", 1) + struct.pack("<iiQQ", 7, 1, 64, 48) + struct.pack("<4d", 50, 51, 32, 24)
        )
    with open(d / "images.bin", "wb") as f:
        f.write(struct.pack("<Q", 2))
        for iid, name, tx in ((1, b"a.png", 0.0), (2, b"b.png", 0.5)):
            f.write(struct.pack("<i7di", iid, 1, 0, 0, 0, tx, 0, 0, 7) + name + b"\0")
            f.write(struct.pack("<Q", 1) + struct.pack("<ddq", 3.0, 4.0, 1))
    with open(d / "points3D.bin", "wb") as f:
        f.write(struct.pack("<Q", 2))
        for pid, xyz in ((1, (0.1, 0.2, 3.0)), (2, (-0.1, 0.0, 4.0))):
            f.write(struct.pack("<Q3d3BdQ", pid, *xyz, 10, 20, 30, 0.5, 2) + struct.pack("<4i", 1, 0, 2, 0))


def test_colmap_binary_and_text_models(tmp_path: Path) -> None:
    write_colmap_bin(tmp_path)
    m = mc.load_colmap_model(tmp_path)
    assert m.cameras[7].model == "PINHOLE"
    k = m.cameras[7].intrinsics()
    assert (k.fx, k.fy, k.cx, k.cy) == (50, 51, 31.5, 23.5)
    assert m.image("b.png").pose.translation_scene_units.tolist() == [0.5, 0, 0]
    assert m.points_scene_units.shape == (2, 3) and m.point_tracks == [(1, 2), (1, 2)]
    assert m.nearest_sources("a.png", 4) == ["b.png"]
    txt = tmp_path / "txt"
    txt.mkdir()
    (txt / "cameras.txt").write_text("# c\n7 PINHOLE 64 48 50 51 32 24\n")
    (txt / "images.txt").write_text("# i\n1 1 0 0 0 0 0 0 7 a.png\n3 4 1\n2 1 0 0 0 0.5 0 0 7 b.png\n\n")
    (txt / "points3D.txt").write_text("1 0.1 0.2 3.0 10 20 30 0.5 1 0 2 0\n2 -0.1 0 4 1 2 3 0.5 1 0 2 0\n")
    t = mc.load_colmap_model(txt)
    np.testing.assert_allclose(t.points_scene_units, m.points_scene_units)
    assert [i.name for i in t.images.values()] == ["a.png", "b.png"]
    assert t.point_tracks == m.point_tracks
    # The keypoints behind the tracks, as observations in murk's pixels (COLMAP's minus 0.5).
    assert t.point_track_keypoints == m.point_track_keypoints == [(0, 0), (0, 0)]
    every = [[0, 0, 2.5, 3.5], [0, 1, 2.5, 3.5], [1, 0, 2.5, 3.5], [1, 1, 2.5, 3.5]]
    assert m.observations("a.png", ["b.png"]).tolist() == every
    # b.png lists no keypoints in the text model: only the reference's observations remain.
    assert t.observations("a.png", ["b.png"]).tolist() == [every[0], every[2]]
    assert m.observations("b.png", []).tolist() == [[0, 0, 2.5, 3.5], [1, 0, 2.5, 3.5]]
    with pytest.raises(mc.ClientInputError):
        mc.ColmapCamera(1, "OPENCV", 4, 4, (1, 1, 1, 1, 0, 0, 0, 0)).intrinsics()
    (tmp_path / "points3D.bin").write_bytes(struct.pack("<Q", 5))
    with pytest.raises(mc.ClientInputError):
        mc.load_colmap_model(tmp_path)


def test_seen_by_sources_become_track_masks() -> None:
    view = mc.View(np.zeros((4, 4)), mc.Intrinsics(4.0, 4.0, 2.0, 2.0), mc.Pose(np.eye(3), np.zeros(3)))
    pts = np.array([[0.0, 0.0, 1.0], [0.1, 0.0, 1.0]])
    req = mc.scattering_params_request(view, [view, view, view], pts, seen_by_sources=[[0, 2], []])
    assert list(req.scattering_params.sparse_point_sources) == [0b101, 0]
    assert list(mc.scattering_params_request(view, [view], pts).scattering_params.sparse_point_sources) == []
    with pytest.raises(mc.ClientInputError) as e:
        mc.scattering_params_request(view, [view], pts, seen_by_sources=[[0]])
    assert e.value.field == "request.scattering_params.sparse_point_sources"
    with pytest.raises(mc.ClientInputError) as e:
        mc.scattering_params_request(view, [view], pts, seen_by_sources=[[0], [1]])
    assert e.value.field == "request.scattering_params.sparse_point_sources[1]"


def test_observations_go_into_the_request_and_bad_ones_name_the_field() -> None:
    view = mc.View(np.zeros((4, 4)), mc.Intrinsics(4.0, 4.0, 2.0, 2.0), mc.Pose(np.eye(3), np.zeros(3)))
    pts = np.array([[0.0, 0.0, 1.0], [0.1, 0.0, 1.0]])
    obs = [[0, 0, 1.5, 2.0], [1, 2, 3.0, 0.5]]
    req = mc.scattering_params_request(view, [view, view], pts, observations=obs).scattering_params
    got = [(o.point, o.view, o.x, o.y) for o in req.sparse_point_observations]
    assert got == [(0, 0, 1.5, 2.0), (1, 2, 3.0, 0.5)]
    field = "request.scattering_params.sparse_point_observations"
    for bad, where in [
        ([[2, 0, 1.0, 1.0]], f"{field}[0].point"),
        ([[0, 0, 1.0, 1.0], [0, 3, 1.0, 1.0]], f"{field}[1].view"),
        ([[0, 1, float("nan"), 1.0]], f"{field}[0]"),
        ([[0, 1, 1.0]], field),
    ]:
        with pytest.raises(mc.ClientInputError) as e:
            mc.scattering_params_request(view, [view, view], pts, observations=bad)
        assert e.value.field == where
