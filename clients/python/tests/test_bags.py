"""`murk bag` on ROS 2 bags written by an independent library (mcap-ros2-support, the MCAP
project's own ROS 2 encoder), read back by the same library: every output message decodes, keeps
its input's stamp and frame_id, the depth matches the simulator's ground truth, and the point
clouds' layouts are consistent. The inputs come raw (rgb8, 32FC1, 16-bit with a scale) and as
CompressedImage (PNG and JPEG from Pillow's encoders). Bad bags (truncated, an unknown encoding,
no CameraInfo) end with a clear error, a nonzero exit and no output file."""

from __future__ import annotations

import io
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer
from PIL import Image

import murk_client as mc

from .conftest import murk_binary, read_meta, simulate

# The message definitions as rosbag2 records them (comments stripped), typed in from the ROS 2
# interface packages rather than taken from murk.
TIME = "int32 sec\nuint32 nanosec\n"
HEADER = "builtin_interfaces/Time stamp\nstring frame_id\n"
ROI = "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n"
SEP = "=" * 80 + "\n"
IMAGE = (
    "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\n"
    "uint32 step\nuint8[] data\n"
    f"{SEP}MSG: std_msgs/Header\n{HEADER}{SEP}MSG: builtin_interfaces/Time\n{TIME}"
)
CAMERA_INFO = (
    "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] d\n"
    "float64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\n"
    "sensor_msgs/RegionOfInterest roi\n"
    f"{SEP}MSG: std_msgs/Header\n{HEADER}{SEP}MSG: builtin_interfaces/Time\n{TIME}"
    f"{SEP}MSG: sensor_msgs/RegionOfInterest\n{ROI}"
)
COMPRESSED_IMAGE = (
    "std_msgs/Header header\nstring format\nuint8[] data\n"
    f"{SEP}MSG: std_msgs/Header\n{HEADER}{SEP}MSG: builtin_interfaces/Time\n{TIME}"
)

T0_NS = 1_700_000_000_000_000_000
PERIOD_NS = 100_000_000  # 10 Hz


def header(k: int, frame_id: str) -> dict[str, Any]:
    t = T0_NS + k * PERIOD_NS
    return {"stamp": {"sec": t // 1_000_000_000, "nanosec": t % 1_000_000_000}, "frame_id": frame_id}


def image_msg(k: int, frame_id: str, pixels: np.ndarray, encoding: str) -> dict[str, Any]:
    data = np.ascontiguousarray(pixels)
    h, w = data.shape[:2]
    return {
        "header": header(k, frame_id),
        "height": h,
        "width": w,
        "encoding": encoding,
        "is_bigendian": 0,
        "step": data.nbytes // h,
        "data": data.tobytes(),
    }


def compressed_msg(k: int, frame_id: str, rgb8: np.ndarray, form: str) -> dict[str, Any]:
    """An rgb8 image as image_transport's compressed plugin publishes it: the format string
    names the original encoding and the codec, the bytes are a PNG or a JPEG file."""
    buf = io.BytesIO()
    if form == "png":
        Image.fromarray(rgb8).save(buf, format="PNG")
    else:
        Image.fromarray(rgb8).save(buf, format="JPEG", quality=95)
    return {"header": header(k, frame_id), "format": f"rgb8; {form} compressed rgb8", "data": buf.getvalue()}


def camera_info_msg(
    k: int, frame_id: str, w: int, h: int, fx: float, fy: float, cx: float, cy: float, tx: float
) -> dict[str, Any]:
    return {
        "header": header(k, frame_id),
        "height": h,
        "width": w,
        "distortion_model": "plumb_bob",
        "d": [0.0] * 5,
        "k": [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
        "r": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        "p": [fx, 0.0, cx, tx, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
        "binning_x": 0,
        "binning_y": 0,
        "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
    }


@dataclass
class StereoBag:
    path: Path
    gt_depth: list[np.ndarray]
    airlight: float
    beta: float


@pytest.fixture(scope="module")
def stereo_sequence(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A rectified rig moving forward through a hazy room at 10 Hz for three frames, as
    `murk simulate stereo` renders it."""
    work = tmp_path_factory.mktemp("stereo_seq")
    return simulate("stereo", work / "seq", "--width", "96", "--height", "72", "--seed", "2", "--frames", "3")


def write_stereo_bag(path: Path, seq: Path, form: str) -> StereoBag:
    """The sequence as a bag: left and right CameraInfo on every frame (the right one's P
    carries Tx = -fx*B), the images as rgb8 `Image`s (`form` "raw") or as `CompressedImage`s
    ("png", "jpeg")."""
    frames = sorted(p for p in seq.iterdir() if p.is_dir())
    meta = read_meta(frames[0])
    k = meta["intrinsics"]
    baseline = float(meta["baseline"])
    with open(path, "wb") as f:
        w = Writer(f)
        if form == "raw":
            image_schema = w.register_msgdef("sensor_msgs/msg/Image", IMAGE)
        else:
            image_schema = w.register_msgdef("sensor_msgs/msg/CompressedImage", COMPRESSED_IMAGE)
        info_schema = w.register_msgdef("sensor_msgs/msg/CameraInfo", CAMERA_INFO)
        for i, frame in enumerate(frames):
            t = T0_NS + i * PERIOD_NS
            for side, tx in (("left", 0.0), ("right", -k["fx"] * baseline)):
                rgb8 = np.round(mc.read_image(frame / f"{side}.png") * 255).astype(np.uint8)
                h, wd = rgb8.shape[:2]
                info = camera_info_msg(i, f"stereo_{side}", wd, h, k["fx"], k["fy"], k["cx"], k["cy"], tx)
                w.write_message(f"/stereo/{side}/camera_info", info_schema, info, log_time=t)
                if form == "raw":
                    msg = image_msg(i, f"stereo_{side}", rgb8, "rgb8")
                    topic = f"/stereo/{side}/image_rect"
                else:
                    msg = compressed_msg(i, f"stereo_{side}", rgb8, form)
                    topic = f"/stereo/{side}/image_rect/compressed"
                w.write_message(topic, image_schema, msg, log_time=t)
        w.finish()
    return StereoBag(
        path=path,
        gt_depth=[mc.read_image(f / "depth.exr") for f in frames],
        airlight=float(meta["airlight"]),
        beta=float(meta["beta"]),
    )


@pytest.fixture(scope="module")
def stereo_bag(stereo_sequence: Path, tmp_path_factory: pytest.TempPathFactory) -> StereoBag:
    return write_stereo_bag(tmp_path_factory.mktemp("stereo_bag") / "stereo.mcap", stereo_sequence, "raw")


def run_bag(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(murk_binary()), "bag", *args], capture_output=True, text=True, timeout=600)


def read_back(path: Path) -> dict[str, list[Any]]:
    """Every message of the file, decoded, by topic, in the order the file holds them."""
    topics: dict[str, list[Any]] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _schema, channel, _message, ros_msg in reader.iter_decoded_messages():
            topics.setdefault(channel.topic, []).append(ros_msg)
    return topics


def cloud_xyz(cloud: Any) -> np.ndarray:
    """x, y, z of a PointCloud2 after checking its layout."""
    names = [f.name for f in cloud.fields]
    assert names[:3] == ["x", "y", "z"]
    assert all(f.datatype == 7 and f.count == 1 for f in cloud.fields)  # FLOAT32
    assert cloud.point_step >= 4 * len(cloud.fields)
    assert cloud.row_step == cloud.point_step * cloud.width
    assert len(cloud.data) == cloud.row_step * cloud.height
    raw = np.frombuffer(bytes(cloud.data), dtype="<f4").reshape(-1, cloud.point_step // 4)
    return raw[:, [names.index("x"), names.index("y"), names.index("z")]]


def float_image(msg: Any) -> np.ndarray:
    assert msg.encoding == "32FC1" and msg.step == 4 * msg.width
    return np.frombuffer(bytes(msg.data), dtype="<f4").reshape(msg.height, msg.width)


def run_stereo_bag(
    bag: StereoBag, out: Path, suffix: str = "", *extra: str
) -> subprocess.CompletedProcess[str]:
    return run_bag(
        str(bag.path),
        "--out",
        str(out),
        "--left",
        f"/stereo/left/image_rect{suffix}",
        "--right",
        f"/stereo/right/image_rect{suffix}",
        "--airlight",
        str(bag.airlight),
        "--beta",
        str(bag.beta),
        "--depth-range",
        "1.5,15",
        *extra,
    )


def check_stereo_output(bag: StereoBag, topics: dict[str, list[Any]], min_cp: float) -> list[float]:
    """Stamps, frame ids, the depth against the ground truth (the share of pixels within 10 %
    above `min_cp` on every frame), disparity against depth, the clouds' layouts; the frames'
    C.P."""
    n = len(bag.gt_depth)
    for t in ("depth", "confidence", "disparity", "points", "camera_info"):
        assert len(topics[f"/murk/{t}"]) == n, t
    cps = []
    for k, gt in enumerate(bag.gt_depth):
        want = header(k, "stereo_left")
        for t in ("depth", "confidence", "disparity", "points", "camera_info"):
            h = topics[f"/murk/{t}"][k].header
            assert (h.stamp.sec, h.stamp.nanosec) == (want["stamp"]["sec"], want["stamp"]["nanosec"])
            assert h.frame_id == "stereo_left"
        depth = float_image(topics["/murk/depth"][k])
        assert depth.shape == gt.shape
        valid = np.isfinite(depth) & (gt > 0)
        assert valid.mean() > 0.5
        cp = float(np.mean(np.abs(depth[valid] - gt[valid]) / gt[valid] < 0.1))
        assert cp > min_cp, (k, cp)
        cps.append(cp)
        disparity = topics["/murk/disparity"][k]
        d = float_image(disparity.image)
        np.testing.assert_allclose(d[valid], disparity.f * disparity.t / depth[valid], rtol=1e-3)
        xyz = cloud_xyz(topics["/murk/points"][k])
        assert len(xyz) > 0 and np.all(xyz[:, 2] > 0)
    return cps


def test_a_stereo_bag_from_another_writer(stereo_bag: StereoBag, tmp_path: Path) -> None:
    out = tmp_path / "out.mcap"
    r = run_stereo_bag(stereo_bag, out, "", "--copy-inputs")
    assert r.returncode == 0, r.stderr
    n = len(stereo_bag.gt_depth)
    assert f"{n} frames read, {n} processed, 0 failed" in r.stdout
    topics = read_back(out)
    # The inputs came through, byte for byte as decoded.
    assert len(topics["/stereo/left/image_rect"]) == n
    # the one-shot bar of the rectified-stereo test: > 50 % of pixels within 10 %
    check_stereo_output(stereo_bag, topics, 0.5)
    # The preview example draws a frame: the input, the depth, the confidence side by side.
    png = tmp_path / "preview.png"
    example = Path(__file__).resolve().parent.parent / "examples" / "bag_preview.py"
    done = subprocess.run(
        [sys.executable, str(example), str(out), "--frame", "1", "--out", str(png)]
        + ["--image-topic", "/stereo/left/image_rect"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert "% measured" in done.stdout
    h, w = stereo_bag.gt_depth[1].shape
    assert mc.read_image(png).shape == (h, 3 * w, 3)


@pytest.fixture(scope="module")
def raw_stereo_output(
    stereo_bag: StereoBag, tmp_path_factory: pytest.TempPathFactory
) -> dict[str, list[Any]]:
    """The raw bag's output, read back: what the compressed bags are compared with."""
    out = tmp_path_factory.mktemp("raw_stereo_out") / "raw.mcap"
    r = run_stereo_bag(stereo_bag, out)
    assert r.returncode == 0, r.stderr
    return read_back(out)


def test_no_points_leaves_the_clouds_out_and_the_rest_as_it_was(
    stereo_bag: StereoBag, raw_stereo_output: dict[str, list[Any]], tmp_path: Path
) -> None:
    out = tmp_path / "out.mcap"
    r = run_stereo_bag(stereo_bag, out, "", "--no-points")
    assert r.returncode == 0, r.stderr
    topics = read_back(out)
    assert "/murk/points" not in topics
    assert len(raw_stereo_output["/murk/points"]) == len(stereo_bag.gt_depth)
    for t in ("depth", "confidence", "disparity"):
        mine, theirs = topics[f"/murk/{t}"], raw_stereo_output[f"/murk/{t}"]
        assert len(mine) == len(theirs) == len(stereo_bag.gt_depth), t
    for mine, theirs in zip(topics["/murk/depth"], raw_stereo_output["/murk/depth"], strict=True):
        np.testing.assert_array_equal(float_image(mine), float_image(theirs))


@pytest.mark.parametrize("form", ["png", "jpeg"])
def test_a_compressed_stereo_bag(
    form: str,
    stereo_sequence: Path,
    stereo_bag: StereoBag,
    raw_stereo_output: dict[str, list[Any]],
    tmp_path: Path,
) -> None:
    """CompressedImage pairs (image_transport's `.../compressed` topics): PNG decodes to the raw
    bag's pixels, so its depth is the raw bag's to the bit; JPEG at quality 95 loses a little
    and must still meet the one-shot bar."""
    bag = write_stereo_bag(tmp_path / f"{form}.mcap", stereo_sequence, form)
    out = tmp_path / "out.mcap"
    r = run_stereo_bag(bag, out, "/compressed")
    assert r.returncode == 0, r.stderr
    topics = read_back(out)
    cps = check_stereo_output(bag, topics, 0.5)
    if form == "png":
        for mine, theirs in zip(topics["/murk/depth"], raw_stereo_output["/murk/depth"], strict=True):
            np.testing.assert_array_equal(float_image(mine), float_image(theirs))
    else:
        # JPEG's loss costs a few points of C.P. at most (3.4 on the worst frame with Pillow
        # 13's libjpeg-turbo); the bound leaves room for other encoders' quantisation
        raw_cps = check_stereo_output(stereo_bag, raw_stereo_output, 0.5)
        assert all(c >= raw_cp - 0.08 for c, raw_cp in zip(cps, raw_cps, strict=True)), (cps, raw_cps)


@pytest.fixture(scope="module")
def tof_sequence(tmp_path_factory: pytest.TempPathFactory) -> Path:
    work = tmp_path_factory.mktemp("tof_seq")
    return simulate("tof", work / "seq", "--width", "64", "--height", "53", "--seed", "3", "--frames", "3")


def write_tof_bag(
    path: Path,
    seq: Path,
    *,
    amplitude_encoding: str = "32FC1",
    with_info: bool = True,
    amplitude_scale: float | None = None,
) -> int:
    """The sequence as a bag of amplitude, phase and CameraInfo. With `amplitude_scale` both
    images are 16-bit as ToF drivers publish them: the amplitude as mono16 in units of
    amplitude_scale/65535, the phase as 16UC1 in units of 2π/65535."""
    frames = sorted(p for p in seq.iterdir() if p.is_dir())
    with open(path, "wb") as f:
        w = Writer(f)
        image_schema = w.register_msgdef("sensor_msgs/msg/Image", IMAGE)
        info_schema = w.register_msgdef("sensor_msgs/msg/CameraInfo", CAMERA_INFO)
        for i, frame_dir in enumerate(frames):
            frame = mc.load_tof_frame(frame_dir)
            k = frame.intrinsics
            assert k is not None
            h, wd = frame.amplitude.shape
            t = T0_NS + i * PERIOD_NS
            if with_info:
                w.write_message(
                    "/tof/camera_info",
                    info_schema,
                    camera_info_msg(i, "tof_optical", wd, h, k.fx, k.fy, k.cx, k.cy, 0.0),
                    log_time=t,
                )
            if amplitude_scale is None:
                amp = image_msg(i, "tof_optical", frame.amplitude.astype("<f4"), amplitude_encoding)
                phase = image_msg(i, "tof_optical", frame.phase.astype("<f4"), "32FC1")
            else:
                assert frame.amplitude.max() <= amplitude_scale
                assert 0.0 <= frame.phase.min() and frame.phase.max() < 2 * np.pi
                q_amp = np.round(frame.amplitude / amplitude_scale * 65535).astype("<u2")
                q_phase = np.round(frame.phase / (2 * np.pi) * 65535).astype("<u2")
                amp = image_msg(i, "tof_optical", q_amp, "mono16")
                phase = image_msg(i, "tof_optical", q_phase, "16UC1")
            w.write_message("/tof/amplitude", image_schema, amp, log_time=t)
            w.write_message("/tof/phase", image_schema, phase, log_time=t)
        w.finish()
    return len(frames)


def tof_args(bag: Path, out: Path, seq: Path) -> list[str]:
    meta = read_meta(next(p for p in sorted(seq.iterdir()) if p.is_dir()))
    light = ",".join(str(v) for v in meta["light_position_m"])
    return [
        str(bag),
        "--out",
        str(out),
        "--amplitude",
        "/tof/amplitude",
        "--phase",
        "/tof/phase",
        "--frequency-hz",
        str(meta["modulation_frequency_hz"]),
        "--light-position-m",
        light,
    ]


def check_tof_output(seq: Path, topics: dict[str, list[Any]]) -> list[np.ndarray]:
    """Stamps and frame ids, the mask's encoding, the depth against the ground truth, the
    clouds against the depth; each frame's depth."""
    frames = sorted(p for p in seq.iterdir() if p.is_dir())
    for t in ("depth", "mask", "range_std", "points", "camera_info"):
        assert len(topics[f"/murk/{t}"]) == len(frames), t
    depths = []
    for k, frame_dir in enumerate(frames):
        h = topics["/murk/depth"][k].header
        want = header(k, "tof_optical")
        assert (h.stamp.sec, h.stamp.nanosec, h.frame_id) == (
            want["stamp"]["sec"],
            want["stamp"]["nanosec"],
            "tof_optical",
        )
        depth = float_image(topics["/murk/depth"][k])
        gt = mc.read_image(frame_dir / "gt_z_depth_m.exr")
        mask = topics["/murk/mask"][k]
        assert mask.encoding == "mono8"
        objects = mc.read_image(frame_dir / "gt_object_mask.png") > 0.5
        measured = np.isfinite(depth)
        # the objects are measured; the fog-only background, whose spread is metres, is not
        assert measured[objects].mean() > 0.95 and measured[~objects].mean() < 0.05
        err = np.abs(depth[measured] - gt[measured])
        # the one-shot accuracy of the simulated scenes: millimetres, not the fog's decimetres
        assert float(np.median(err)) < 0.01 and float(np.percentile(err, 99)) < 0.1, err
        xyz = cloud_xyz(topics["/murk/points"][k])
        assert len(xyz) == int(measured.sum())
        np.testing.assert_allclose(np.sort(xyz[:, 2]), np.sort(depth[measured]), rtol=1e-6)
        depths.append(depth)
    return depths


def test_a_tof_bag_from_another_writer(tof_sequence: Path, tmp_path: Path) -> None:
    bag = tmp_path / "tof.mcap"
    write_tof_bag(bag, tof_sequence)
    out = tmp_path / "out.mcap"
    r = run_bag(*tof_args(bag, out, tof_sequence))
    assert r.returncode == 0, r.stderr
    check_tof_output(tof_sequence, read_back(out))


def test_a_sixteen_bit_tof_bag(tof_sequence: Path, tmp_path: Path) -> None:
    """mono16 amplitude and 16UC1 phase with their scales: the same objects at the same depth
    as from the float bag, to within the quantisation (2π/65535 rad of phase is 0.14 mm of
    range at 16 MHz)."""
    amax = max(float(mc.load_tof_frame(p).amplitude.max()) for p in tof_sequence.iterdir() if p.is_dir())
    scale = 1.01 * amax
    runs = []
    for amplitude_scale in (None, scale):
        name = "f32" if amplitude_scale is None else "u16"
        bag = tmp_path / f"{name}.mcap"
        write_tof_bag(bag, tof_sequence, amplitude_scale=amplitude_scale)
        out = tmp_path / f"{name}-out.mcap"
        extra = (
            []
            if amplitude_scale is None
            else ["--amplitude-scale", str(scale), "--phase-scale", str(2 * np.pi)]
        )
        r = run_bag(*tof_args(bag, out, tof_sequence), *extra)
        assert r.returncode == 0, r.stderr
        runs.append(check_tof_output(tof_sequence, read_back(out)))
    for f32, u16 in zip(*runs, strict=True):
        both = np.isfinite(f32) & np.isfinite(u16)
        # the masks agree but for a boundary pixel or two, and the depths to within the
        # quantisation
        assert np.mean(np.isfinite(f32) != np.isfinite(u16)) < 0.001
        assert float(np.median(np.abs(f32[both] - u16[both]))) < 3e-4


def assert_failed_cleanly(r: subprocess.CompletedProcess[str], out: Path, *needles: str) -> None:
    assert r.returncode != 0
    for n in needles:
        assert n in r.stderr, r.stderr
    assert not out.exists() and not out.with_name(out.name + ".partial").exists()


def test_a_truncated_bag_fails_cleanly(tof_sequence: Path, tmp_path: Path) -> None:
    bag = tmp_path / "tof.mcap"
    write_tof_bag(bag, tof_sequence)
    data = bag.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    out = tmp_path / "out.mcap"
    assert_failed_cleanly(run_bag(*tof_args(cut, out, tof_sequence)), out, "cut.mcap", "truncated")


def test_an_unknown_encoding_is_named_with_topic_and_stamp(tof_sequence: Path, tmp_path: Path) -> None:
    bag = tmp_path / "tof.mcap"
    # 4 bytes a pixel like 32FC1, under an encoding murk does not read
    write_tof_bag(bag, tof_sequence, amplitude_encoding="32SC1")
    out = tmp_path / "out.mcap"
    assert_failed_cleanly(
        run_bag(*tof_args(bag, out, tof_sequence)), out, "/tof/amplitude", "1700000000.000000000 s", "`32SC1`"
    )


def test_a_missing_camera_info_is_named(tof_sequence: Path, tmp_path: Path) -> None:
    bag = tmp_path / "tof.mcap"
    write_tof_bag(bag, tof_sequence, with_info=False)
    out = tmp_path / "out.mcap"
    assert_failed_cleanly(run_bag(*tof_args(bag, out, tof_sequence)), out, "/tof/camera_info", "CameraInfo")
