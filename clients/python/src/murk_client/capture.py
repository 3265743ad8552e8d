"""Readers of the folder layouts the murk CLI reads (and ``murk simulate`` writes).

- ToF frame: ``amplitude.exr``, ``phase.exr`` (radians) and optionally ``meta.json`` with
  ``modulation_frequency_hz``, ``intrinsics {fx, fy, cx, cy, skew}`` (pixels, centre of the
  top-left pixel = (0, 0)) and ``light_position_m [x, y, z]``.
- Photometric-stereo capture: ``meta.json`` (format ``murk.ps_capture``) naming per light an
  image with and without the object, ``mask.png``, intrinsics, medium (per mm), lights (mm).
- COLMAP sparse model (text or binary, undistorted ``PINHOLE``/``SIMPLE_PINHOLE`` cameras) with
  its images: COLMAP's principal point is converted to murk's convention (−0.5 px).
"""

from __future__ import annotations

import json
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import numpy.typing as npt

from .errors import ClientInputError
from .images import FloatImage, read_image
from .types import Intrinsics, Pose, PsLight, View

PathLike = str | Path


def _read_json(path: Path) -> dict[str, Any]:
    try:
        value = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise ClientInputError(str(path), f"not readable JSON: {e}") from e
    if not isinstance(value, dict):
        raise ClientInputError(str(path), "expected a JSON object")
    return value


def _inside(folder: Path, name: str, where: str) -> Path:
    """``folder / name`` for a relative path that stays inside the folder (as the server reads it)."""
    rel = Path(name)
    if not name or rel.is_absolute() or any(part == ".." for part in rel.parts):
        raise ClientInputError(where, f"{name!r} must be a path relative to the capture folder, without '..'")
    return folder / rel


def _intrinsics(value: Any, where: str) -> Intrinsics:
    if isinstance(value, dict):
        try:
            return Intrinsics(
                float(value["fx"]),
                float(value["fy"]),
                float(value["cx"]),
                float(value["cy"]),
                float(value.get("skew", 0.0)),
            )
        except (KeyError, TypeError, ValueError) as e:
            raise ClientInputError(where, f"expected {{fx, fy, cx, cy[, skew]}}: {e}") from e
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape == (3, 3):
        if not np.allclose(arr[1:, 0], 0) or arr[2, 1] != 0 or arr[2, 2] != 1:
            raise ClientInputError(
                where, "expected K = [[fx, skew, cx], [0, fy, cy], [0, 0, 1]] (transposed?)"
            )
        return Intrinsics(arr[0, 0], arr[1, 1], arr[0, 2], arr[1, 2], arr[0, 1])
    raise ClientInputError(where, "expected {fx, fy, cx, cy[, skew]} or a 3x3 K")


@dataclass(frozen=True)
class TofFrame:
    """One CW-ToF frame: amplitude (linear), phase (radians) and what ``meta.json`` says."""

    amplitude: FloatImage
    phase: FloatImage
    modulation_frequency_hz: float | None
    intrinsics: Intrinsics | None
    light_position_m: tuple[float, float, float] | None


def load_tof_frame(folder: PathLike) -> TofFrame:
    """Reads a ToF frame folder (the layout of ``murk simulate tof`` and ``murk tof --frame``)."""
    d = Path(folder)
    amplitude = read_image(d / "amplitude.exr")
    phase = read_image(d / "phase.exr")
    if amplitude.ndim != 2 or phase.shape != amplitude.shape:
        raise ClientInputError(
            str(d / "phase.exr"),
            f"amplitude {amplitude.shape} and phase {phase.shape} must be one-channel and equal",
        )
    meta = _read_json(d / "meta.json") if (d / "meta.json").exists() else {}
    k = _intrinsics(meta["intrinsics"], "meta.json.intrinsics") if meta.get("intrinsics") else None
    light = meta.get("light_position_m")
    f = meta.get("modulation_frequency_hz")
    return TofFrame(
        amplitude=amplitude,
        phase=phase,
        modulation_frequency_hz=float(f) if f is not None else None,
        intrinsics=k,
        light_position_m=(float(light[0]), float(light[1]), float(light[2])) if light else None,
    )


@dataclass(frozen=True)
class PsCapture:
    """A photometric-stereo capture: the arguments of ``Client.photometric_stereo``."""

    lights: list[PsLight]
    mask: FloatImage
    intrinsics: Intrinsics
    beta_per_mm: float
    sigma_per_mm: float
    #: The suggested initial plane's z-distance, mm (None when meta.json gives none).
    initial_distance_mm: float | None
    #: Ground truth of a simulated capture, when present: normals (h, w, 3), depth (h, w) mm.
    gt_normals: FloatImage | None = None
    gt_depth_mm: FloatImage | None = None


def load_ps_capture(folder: PathLike) -> PsCapture:
    """Reads a capture folder (``meta.json`` format ``murk.ps_capture``, images beside it)."""
    d = Path(folder)
    meta = _read_json(d / "meta.json")
    if meta.get("format", "murk.ps_capture") != "murk.ps_capture":
        raise ClientInputError("meta.json.format", f"expected 'murk.ps_capture', got {meta.get('format')!r}")
    try:
        medium = meta["medium"]
        specs = meta["lights"]
        images, backgrounds = meta["images"], meta["backgrounds"]
    except KeyError as e:
        raise ClientInputError(f"meta.json.{e.args[0]}", "missing") from e
    if not (len(specs) == len(images) == len(backgrounds)):
        raise ClientInputError("meta.json.lights", "lights, images and backgrounds must have one entry each")
    lights = [
        PsLight(
            position_mm=[float(v) for v in spec["position_mm"]],
            intensity=float(spec["intensity"]),
            image=read_image(_inside(d, img, f"meta.json.images[{i}]")),
            background=read_image(_inside(d, bg, f"meta.json.backgrounds[{i}]")),
        )
        for i, (spec, img, bg) in enumerate(zip(specs, images, backgrounds, strict=True))
    ]
    if "intrinsics" in meta and "K" in meta:
        raise ClientInputError("meta.json.K", "give either intrinsics or K, not both")
    k_key = "K" if "K" in meta else "intrinsics"
    if k_key not in meta:
        raise ClientInputError("meta.json.intrinsics", "missing: give intrinsics {fx, fy, cx, cy} or K (3x3)")
    gt_n = read_image(d / "gt_normals.exr") if (d / "gt_normals.exr").exists() else None
    gt_z = read_image(d / "gt_depth_mm.exr") if (d / "gt_depth_mm.exr").exists() else None
    dist = meta.get("initial_distance_mm")
    return PsCapture(
        lights=lights,
        mask=read_image(_inside(d, meta.get("mask", "mask.png"), "meta.json.mask")),
        intrinsics=_intrinsics(meta[k_key], f"meta.json.{k_key}"),
        beta_per_mm=float(medium["beta_per_mm"]),
        sigma_per_mm=float(medium["sigma_per_mm"]),
        initial_distance_mm=float(dist) if dist is not None else None,
        gt_normals=gt_n,
        gt_depth_mm=gt_z,
    )


# COLMAP camera model ids and parameter counts (colmap/src/colmap/sensor/models.h).
_MODELS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
}


@dataclass(frozen=True)
class ColmapCamera:
    """A COLMAP camera: model name, size and parameters as COLMAP stores them."""

    id: int
    model: str
    width: int
    height: int
    params: tuple[float, ...]

    def intrinsics(self) -> Intrinsics:
        """murk intrinsics (principal point −0.5 px); undistorted pinhole models only."""
        p = self.params
        if self.model == "SIMPLE_PINHOLE":
            return Intrinsics.from_colmap(p[0], p[0], p[1], p[2])
        if self.model == "PINHOLE":
            return Intrinsics.from_colmap(p[0], p[1], p[2], p[3])
        raise ClientInputError(
            f"cameras.{self.id}.model",
            f"{self.model} distorts; run `colmap image_undistorter` and use its undistorted model",
        )


@dataclass(frozen=True)
class ColmapImage:
    """A registered image: name, world-to-camera pose, camera id, and its 2D keypoints."""

    id: int
    name: str
    pose: Pose
    camera_id: int
    #: ``(k, 2)`` keypoint positions, COLMAP's pixels (the top-left pixel's centre at (0.5, 0.5)).
    keypoints: npt.NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))


@dataclass
class ColmapModel:
    """A COLMAP sparse model: cameras, registered images and the 3D points (scene units)."""

    cameras: dict[int, ColmapCamera]
    images: dict[int, ColmapImage]
    #: ``(n, 3)`` world coordinates, scene units.
    points_scene_units: npt.NDArray[np.float64]
    #: Per point, the ids of the images whose track includes it.
    point_tracks: list[tuple[int, ...]] = field(default_factory=list)
    #: Per point, its track's keypoint index in each of those images (same order).
    point_track_keypoints: list[tuple[int, ...]] = field(default_factory=list)

    def observations(self, reference: str, sources: Sequence[str]) -> npt.NDArray[np.float64]:
        """Where the model saw its points in ``reference`` and ``sources`` (image names): an
        ``(m, 4)`` array of point index (into ``points_scene_units``), view (0 the reference,
        ``1 + i`` for ``sources[i]``) and pixel in murk's convention (COLMAP's minus 0.5), the
        ``observations`` of :meth:`murk_client.Client.scattering_params`."""
        views = {self.image(reference).id: 0}
        for i, name in enumerate(sources):
            views[self.image(name).id] = i + 1
        rows = []
        for p, (ids, kps) in enumerate(zip(self.point_tracks, self.point_track_keypoints, strict=True)):
            for image_id, k in zip(ids, kps, strict=True):
                view = views.get(image_id)
                keypoints = self.images[image_id].keypoints if image_id in self.images else None
                if view is not None and keypoints is not None and k < len(keypoints):
                    rows.append([p, view, keypoints[k][0] - 0.5, keypoints[k][1] - 0.5])
        return np.asarray(rows, dtype=np.float64).reshape(-1, 4)

    def image(self, name: str) -> ColmapImage:
        """The registered image called ``name``."""
        for im in self.images.values():
            if im.name == name:
                return im
        raise ClientInputError("reference", f"no registered image named {name!r} in the model")

    def view(self, name: str, images_dir: PathLike) -> View:
        """The calibrated view of image ``name``, its pixels read from ``images_dir``."""
        im = self.image(name)
        return View(
            image=read_image(Path(images_dir) / name),
            intrinsics=self.cameras[im.camera_id].intrinsics(),
            pose=im.pose,
            name=name,
        )

    def nearest_sources(self, reference: str, n: int = 4) -> list[str]:
        """The ``n`` images whose camera centres are nearest the reference's (the CLI's choice),
        skipping those at the reference's own position (no baseline, no depth)."""
        c = self.image(reference).pose.camera_centre
        eps = 1e-9 * max(float(np.linalg.norm(c)), 1.0)
        others = sorted(
            (float(np.linalg.norm(im.pose.camera_centre - c)), im.name)
            for im in self.images.values()
            if im.name != reference
        )
        return [name for dist, name in others if dist > eps][:n]


def load_colmap_model(folder: PathLike) -> ColmapModel:
    """Reads ``cameras``/``images``/``points3D`` as ``.txt`` or ``.bin`` (detected)."""
    d = Path(folder)
    if all((d / f"{n}.bin").exists() for n in ("cameras", "images", "points3D")):
        with open(d / "cameras.bin", "rb") as f:
            cameras = _cameras_bin(f)
        with open(d / "images.bin", "rb") as f:
            images = _images_bin(f)
        with open(d / "points3D.bin", "rb") as f:
            points, tracks, keypoints = _points_bin(f)
    elif all((d / f"{n}.txt").exists() for n in ("cameras", "images", "points3D")):
        cameras, images = _cameras_txt(d / "cameras.txt"), _images_txt(d / "images.txt")
        points, tracks, keypoints = _points_txt(d / "points3D.txt")
    else:
        raise ClientInputError(str(d), "no COLMAP model (cameras/images/points3D .txt or .bin)")
    for im in images.values():
        if im.camera_id not in cameras:
            raise ClientInputError(f"images.{im.name}", f"unknown camera {im.camera_id}")
    return ColmapModel(cameras, images, points, tracks, keypoints)


def _lines(path: Path) -> list[str]:
    return [ln.strip() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]


def _cameras_txt(path: Path) -> dict[int, ColmapCamera]:
    out = {}
    for ln in _lines(path):
        t = ln.split()
        cid = int(t[0])
        out[cid] = ColmapCamera(cid, t[1], int(t[2]), int(t[3]), tuple(float(v) for v in t[4:]))
    return out


def _images_txt(path: Path) -> dict[int, ColmapImage]:
    out = {}
    # Two lines per image; the second (its 2D points) may be empty, so blank lines count here.
    lines = [ln for ln in path.read_text().splitlines() if not ln.startswith("#")]
    i = 0
    while i < len(lines):
        t = lines[i].split()
        if not t:
            i += 1
            continue
        iid = int(t[0])
        q = [float(v) for v in t[1:5]]
        tv = [float(v) for v in t[5:8]]
        xy = lines[i + 1].split() if i + 1 < len(lines) else []
        keypoints = np.asarray(
            [[float(xy[j]), float(xy[j + 1])] for j in range(0, len(xy) - 2, 3)], dtype=np.float64
        ).reshape(-1, 2)
        out[iid] = ColmapImage(
            iid, " ".join(t[9:]), Pose.from_quaternion(q[0], q[1], q[2], q[3], tv), int(t[8]), keypoints
        )
        i += 2
    return out


def _points_txt(
    path: Path,
) -> tuple[npt.NDArray[np.float64], list[tuple[int, ...]], list[tuple[int, ...]]]:
    xyz, tracks, keypoints = [], [], []
    for ln in _lines(path):
        t = ln.split()
        xyz.append([float(t[1]), float(t[2]), float(t[3])])
        tracks.append(tuple(int(v) for v in t[8::2]))
        keypoints.append(tuple(int(v) for v in t[9::2]))
    return np.asarray(xyz, dtype=np.float64).reshape(-1, 3), tracks, keypoints


def _read(f: BinaryIO, fmt: str) -> tuple[Any, ...]:
    size = struct.calcsize(fmt)
    data = f.read(size)
    if len(data) != size:
        raise ClientInputError(getattr(f, "name", "model"), "truncated COLMAP binary file")
    return struct.unpack(fmt, data)


def _cameras_bin(f: BinaryIO) -> dict[int, ColmapCamera]:
    out = {}
    for _ in range(_read(f, "<Q")[0]):
        cid, model_id, w, h = _read(f, "<iiQQ")
        name, n = _MODELS.get(model_id, (f"MODEL_{model_id}", 0))
        if n == 0:
            raise ClientInputError(f"cameras.{cid}.model", f"unknown COLMAP model id {model_id}")
        out[cid] = ColmapCamera(cid, name, w, h, tuple(float(v) for v in _read(f, f"<{n}d")))
    return out


def _images_bin(f: BinaryIO) -> dict[int, ColmapImage]:
    out = {}
    for _ in range(_read(f, "<Q")[0]):
        iid, qw, qx, qy, qz, tx, ty, tz, cid = _read(f, "<i7di")
        name = bytearray()
        while True:
            c = f.read(1)
            if not c:
                raise ClientInputError("images.bin", "truncated image name")
            if c == b"\0":
                break
            name += c
        n2d = _read(f, "<Q")[0]
        # x, y (f64) and the point's id (i64) per keypoint; only the positions are kept.
        raw = _read(f, "<" + "ddq" * n2d) if n2d else ()
        keypoints = np.asarray([raw[0::3], raw[1::3]], dtype=np.float64).T.reshape(-1, 2)
        pose = Pose.from_quaternion(qw, qx, qy, qz, [tx, ty, tz])
        out[iid] = ColmapImage(iid, name.decode(), pose, cid, keypoints)
    return out


def _points_bin(
    f: BinaryIO,
) -> tuple[npt.NDArray[np.float64], list[tuple[int, ...]], list[tuple[int, ...]]]:
    xyz, tracks, keypoints = [], [], []
    for _ in range(_read(f, "<Q")[0]):
        _pid, x, y, z, _r, _g, _b, _err, n = _read(f, "<Q3d3BdQ")
        track = _read(f, f"<{2 * n}i") if n else ()
        xyz.append([x, y, z])
        tracks.append(tuple(track[0::2]))
        keypoints.append(tuple(track[1::2]))
    return np.asarray(xyz, dtype=np.float64).reshape(-1, 3), tracks, keypoints
