"""numpy arrays <-> the API's ``Image`` message, and image files on disk.

The wire format is easy to get wrong by hand, so it lives here once:

- ``raw_f32_le`` is **planar**: all of channel 0 row-major, then channel 1, ... An ``(h, w, c)``
  array must be transposed to ``(c, h, w)`` before its bytes are sent, and back on receipt.
- ``value_scale = 0`` means 1 (proto3 cannot tell an unset float from 0), so a decoded value is
  ``value_offset + (value_scale or 1) * v``.
- Integer images (8/16-bit PNG, integer TIFF) decode to [0, 1]; EXR and float TIFF as stored.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from ._proto.murk.v1 import common_pb2
from .errors import ClientInputError

#: A float32 image: ``(h, w)`` for one channel, ``(h, w, c)`` for several (interleaved, the numpy
#: convention; the wire's planar layout is handled here).
FloatImage = npt.NDArray[np.float32]


@dataclass(frozen=True)
class EncodedImage:
    """An image file sent byte for byte (PNG 8/16-bit, TIFF or OpenEXR); the server decodes it.

    ``value_scale``/``value_offset`` map the decoded samples (``offset + scale * v``), e.g.
    ``value_scale=2*pi`` for a 16-bit PNG that stores phase 0..2π as 0..65535. ``srgb=True``
    says the file is sRGB-encoded, as most cameras write 8-bit PNG and JPEG: the server decodes
    it to linear light, which the scattering models need (``Image.transfer``).
    """

    data: bytes
    value_scale: float = 1.0
    value_offset: float = 0.0
    srgb: bool = False

    @classmethod
    def from_file(
        cls, path: str | Path, *, value_scale: float = 1.0, value_offset: float = 0.0, srgb: bool = False
    ) -> EncodedImage:
        """Reads ``path`` without decoding it."""
        return cls(Path(path).read_bytes(), value_scale, value_offset, srgb)


#: What every image argument accepts.
ImageLike = npt.ArrayLike | EncodedImage


def to_proto(image: ImageLike, *, field: str, channels: int | None = None) -> common_pb2.Image:
    """Converts an array (``(h, w)`` or ``(h, w, c)``, any real dtype) or an :class:`EncodedImage`.

    ``field`` names the argument in errors; ``channels``, when given, is the channel count the
    server requires there. Non-finite samples are left to the server, whose INVALID_ARGUMENT names
    the field, so that both paths report alike.
    """
    if isinstance(image, EncodedImage):
        return common_pb2.Image(
            encoded=image.data,
            value_scale=0.0 if image.value_scale == 1.0 else image.value_scale,
            value_offset=image.value_offset,
            transfer=common_pb2.TRANSFER_SRGB if image.srgb else common_pb2.TRANSFER_UNSPECIFIED,
        )
    arr = np.asarray(image)
    if arr.dtype.kind not in "fiub":
        raise ClientInputError(field, f"expected a numeric array, got dtype {arr.dtype}")
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim != 3:
        raise ClientInputError(field, f"expected shape (h, w) or (h, w, c), got {arr.shape}")
    h, w, c = arr.shape
    if h == 0 or w == 0 or c == 0:
        raise ClientInputError(field, f"empty image of shape {arr.shape}")
    if channels is not None and c != channels:
        raise ClientInputError(field, f"expected {channels} channel(s), got {c}")
    planar = np.ascontiguousarray(np.moveaxis(arr, 2, 0), dtype="<f4")
    return common_pb2.Image(width=w, height=h, channels=c, raw_f32_le=planar.tobytes())


def srgb_to_linear(image: npt.ArrayLike) -> FloatImage:
    """Decodes sRGB-encoded values in [0, 1] to linear light (IEC 61966-2-1), for arrays sent
    to murk: the scattering models are linear in radiance."""
    v = np.asarray(image, dtype=np.float32)
    out: FloatImage = np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4).astype(np.float32)
    return out


def from_proto(image: common_pb2.Image, *, field: str = "image") -> FloatImage:
    """Decodes a result image: ``(h, w)`` for one channel, ``(h, w, c)`` otherwise.

    Raw f32, f16 and 8-bit samples (``v / 255``) are unpacked; an encoded image (the 16-bit PNG
    of a compact result) is decoded with the same rules as the files :func:`read_image` reads,
    then mapped by ``value_scale``/``value_offset``.
    """
    which = image.WhichOneof("data")
    if which in ("raw_f32_le", "raw_f16_le"):
        data: bytes = getattr(image, which)
        size, dtype = (4, "<f4") if which == "raw_f32_le" else (2, "<f2")
        h, w, c = image.height, image.width, max(image.channels, 1)
        expected = h * w * c * size
        if len(data) != expected:
            raise ClientInputError(
                field,
                f"{w}x{h}x{c} {which} needs {expected} bytes, got {len(data)}",
            )
        planar = np.frombuffer(data, dtype=dtype).reshape(c, h, w)
        arr: FloatImage = np.ascontiguousarray(np.moveaxis(planar, 0, 2), dtype=np.float32)
    elif which == "raw_u8":
        h, w, c = image.height, image.width, max(image.channels, 1)
        if len(image.raw_u8) != h * w * c:
            got = len(image.raw_u8)
            raise ClientInputError(field, f"{w}x{h}x{c} raw_u8 needs {h * w * c} bytes, got {got}")
        planar8 = np.frombuffer(image.raw_u8, dtype=np.uint8).reshape(c, h, w)
        arr = np.ascontiguousarray(np.moveaxis(planar8, 0, 2), dtype=np.float32) / np.float32(255.0)
    elif which == "encoded":
        arr = _decode_bytes(image.encoded, field)
        if arr.ndim == 2:
            arr = arr[:, :, None]
    else:
        raise ClientInputError(field, "image carries no pixels")
    scale = image.value_scale if image.value_scale != 0.0 else 1.0
    if scale != 1.0 or image.value_offset != 0.0:
        arr = (arr * np.float32(scale) + np.float32(image.value_offset)).astype(np.float32)
    return arr[:, :, 0] if arr.shape[2] == 1 else arr


def read_image(path: str | Path) -> FloatImage:
    """Reads an image file as the server would decode it: float32, integer formats in [0, 1].

    OpenEXR (every channel, as stored; ``Y`` or ``R,G,B``), PNG 8/16-bit and TIFF.
    """
    p = Path(path)
    return _decode_bytes(p.read_bytes(), str(p))


def _decode_bytes(data: bytes, label: str) -> FloatImage:
    if data[:4] == b"\x76\x2f\x31\x01":
        return _decode_exr(data, label)
    import io

    from PIL import Image as PilImage

    try:
        with PilImage.open(io.BytesIO(data)) as im:
            im.load()
            mode = im.mode
            arr = np.asarray(im)
    except Exception as e:  # Pillow raises many types for corrupt files
        raise ClientInputError(label, f"not a readable PNG/TIFF/EXR image: {e}") from e
    if mode in ("I;16", "I;16B", "I;16L", "I") and arr.dtype != np.float32:
        # Pillow opens 16-bit greyscale PNG as I;16 (or widened to I, int32).
        out = arr.astype(np.float32) / np.float32(65535.0)
    elif arr.dtype == np.uint16:
        out = arr.astype(np.float32) / np.float32(65535.0)
    elif arr.dtype == np.uint8 or arr.dtype == np.bool_:
        out = arr.astype(np.float32) / np.float32(255.0 if arr.dtype == np.uint8 else 1.0)
    elif arr.dtype.kind == "f":
        out = arr.astype(np.float32)
    else:
        raise ClientInputError(label, f"unsupported sample type {arr.dtype} (mode {mode})")
    if out.ndim == 3 and out.shape[2] == 4:
        out = out[:, :, :3]
    result: FloatImage = np.ascontiguousarray(out, dtype=np.float32)
    return result


def _decode_exr(data: bytes, label: str) -> FloatImage:
    import os
    import tempfile

    import OpenEXR

    # The binding reads from a path; a temporary file keeps this function's bytes-in contract.
    fd, tmp = tempfile.mkstemp(suffix=".exr")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        try:
            with OpenEXR.File(tmp, separate_channels=True) as exr:
                channels = {k: np.asarray(v.pixels) for k, v in exr.channels().items()}
        except Exception as e:
            raise ClientInputError(label, f"not a readable OpenEXR file: {e}") from e
    finally:
        os.unlink(tmp)
    if set(channels) >= {"R", "G", "B"}:
        names = ["R", "G", "B"]
    elif "Y" in channels:
        names = ["Y"]
    elif len(channels) == 1:
        names = list(channels)
    else:
        raise ClientInputError(label, f"expected channels Y or R,G,B, got {sorted(channels)}")
    planes = [channels[n].astype(np.float32) for n in names]
    out: FloatImage = planes[0] if len(planes) == 1 else np.stack(planes, axis=2)
    return np.ascontiguousarray(out, dtype=np.float32)


def write_exr(path: str | Path, image: npt.ArrayLike) -> None:
    """Writes a float32 OpenEXR file: channel ``Y`` for ``(h, w)``, ``R,G,B`` for ``(h, w, 3)``."""
    import OpenEXR

    arr = np.ascontiguousarray(np.asarray(image, dtype=np.float32))
    if arr.ndim == 2:
        channels = {"Y": arr}
    elif arr.ndim == 3 and arr.shape[2] == 3:
        channels = {n: np.ascontiguousarray(arr[:, :, i]) for i, n in enumerate("RGB")}
    else:
        raise ClientInputError(str(path), f"cannot write shape {arr.shape} as EXR")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, channels) as exr:
        exr.write(str(path))


def write_png16(path: str | Path, image: npt.ArrayLike, lo: float, hi: float) -> None:
    """Writes ``(h, w)`` values mapped from [lo, hi] to a 16-bit greyscale PNG (NaN -> 0)."""
    from PIL import Image as PilImage

    arr = np.asarray(image, dtype=np.float64)
    if arr.ndim != 2:
        raise ClientInputError(str(path), f"expected a (h, w) array, got {arr.shape}")
    span = hi - lo if hi > lo else 1.0
    scaled = np.nan_to_num((arr - lo) / span, nan=0.0, posinf=1.0, neginf=0.0)
    u16 = np.round(np.clip(scaled, 0.0, 1.0) * 65535.0).astype(np.uint16)
    PilImage.fromarray(u16).save(str(path))
