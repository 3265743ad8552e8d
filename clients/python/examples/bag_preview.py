"""Renders one frame of a `murk bag` output as a PNG: the input image (when the bag carries it,
e.g. with `murk bag --copy-inputs`), the depth colour-mapped (NaN, no measurement, black), and
the confidence or the mask. For a look at a result without Foxglove or RViz.

    pip install "./clients/python[bags]"   # numpy, Pillow, mcap, mcap-ros2-support
    python bag_preview.py OUT.mcap --frame 0 --out preview.png [--image-topic /stereo/left/image_rect]
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from PIL import Image


def image_array(msg: Any) -> np.ndarray:
    """A decoded sensor_msgs/Image as a float array in its own units (integers to [0, 1])."""
    enc = msg.encoding
    data = bytes(msg.data)
    if enc == "32FC1":
        a = np.frombuffer(data, dtype=">f4" if msg.is_bigendian else "<f4").reshape(msg.height, -1)
        return a[:, : msg.width].astype(np.float32)
    if enc in ("mono8", "8UC1"):
        return np.frombuffer(data, np.uint8).reshape(msg.height, msg.step)[:, : msg.width] / 255.0
    if enc in ("rgb8", "bgr8"):
        a = np.frombuffer(data, np.uint8).reshape(msg.height, msg.step)[:, : msg.width * 3]
        a = a.reshape(msg.height, msg.width, 3) / 255.0
        return a[..., ::-1] if enc == "bgr8" else a
    raise SystemExit(f"encoding {enc} is not drawn")


def turbo(v: np.ndarray) -> np.ndarray:
    """A compact colour map (blue near to red far) on [0, 1]."""
    r = np.clip(1.5 - np.abs(4 * v - 3), 0, 1)
    g = np.clip(1.5 - np.abs(4 * v - 2), 0, 1)
    b = np.clip(1.5 - np.abs(4 * v - 1), 0, 1)
    return np.stack([r, g, b], axis=-1)


def depth_rgb(depth: np.ndarray) -> np.ndarray:
    valid = np.isfinite(depth)
    if not valid.any():
        return np.zeros((*depth.shape, 3))
    lo, hi = np.percentile(depth[valid], [2, 98])
    v = np.clip((depth - lo) / max(hi - lo, 1e-9), 0, 1)
    out = turbo(np.where(valid, v, 0))
    out[~valid] = 0
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bag", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--frame", type=int, default=0, help="which result (0 = the first)")
    ap.add_argument("--prefix", default="/murk")
    ap.add_argument("--image-topic", help="an input image topic to draw beside the results")
    a = ap.parse_args()

    wanted = {f"{a.prefix}/depth", f"{a.prefix}/confidence", f"{a.prefix}/mask"}
    if a.image_topic:
        wanted.add(a.image_topic)
    by_topic: dict[str, list[Any]] = {}
    with open(a.bag, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _schema, channel, _message, msg in reader.iter_decoded_messages(topics=sorted(wanted)):
            by_topic.setdefault(channel.topic, []).append(msg)
    depths = by_topic.get(f"{a.prefix}/depth", [])
    if a.frame >= len(depths):
        raise SystemExit(f"{a.bag} has {len(depths)} results on {a.prefix}/depth")
    depth_msg = depths[a.frame]
    stamp = depth_msg.header.stamp
    panels = []
    if a.image_topic:
        # The input with the same stamp as the result.
        for m in by_topic.get(a.image_topic, []):
            if (m.header.stamp.sec, m.header.stamp.nanosec) == (stamp.sec, stamp.nanosec):
                img = image_array(m)
                panels.append(np.repeat(img[..., None], 3, axis=-1) if img.ndim == 2 else img)
                break
        else:
            raise SystemExit(f"no message on {a.image_topic} at {stamp.sec}.{stamp.nanosec:09d}")
    depth = image_array(depth_msg)
    panels.append(depth_rgb(depth))
    for name in ("confidence", "mask"):
        msgs = by_topic.get(f"{a.prefix}/{name}", [])
        if a.frame < len(msgs):
            c = np.nan_to_num(image_array(msgs[a.frame]))
            panels.append(np.repeat(np.clip(c, 0, 1)[..., None], 3, axis=-1))
    strip = np.concatenate(panels, axis=1)
    Image.fromarray(np.round(np.clip(strip, 0, 1) * 255).astype(np.uint8)).save(a.out)
    valid = np.isfinite(depth)
    print(
        f"frame {a.frame} at {stamp.sec}.{stamp.nanosec:09d} s: depth "
        f"{np.nanmin(depth):.2f}..{np.nanmax(depth):.2f} m, {valid.mean() * 100:.1f} % measured; "
        f"wrote {a.out}"
    )


if __name__ == "__main__":
    main()
