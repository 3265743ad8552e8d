#!/usr/bin/env python3
"""Photometric stereo in turbid water: a capture folder in, normals, albedo and depth (mm) out.

    murk simulate ps --out sphere --width 96 --height 96
    python photometric_stereo.py sphere --out result

Writes normals.npy (h, w, 3), depth_mm.npy, albedo.npy, EXR copies and a PNG of the normals;
prints the mean angular error when the capture has ground-truth normals.
"""

import argparse
import os
from pathlib import Path

import numpy as np
from PIL import Image

import murk_client as mc


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture", type=Path, help="folder with meta.json (murk.ps_capture), images, mask.png")
    ap.add_argument(
        "--initial-distance-mm",
        type=float,
        help="mean z-depth of the object, mm, a starting guess (default: meta.json, else searched for)",
    )
    ap.add_argument("--out", type=Path, default=Path("ps-result"))
    ap.add_argument("--server", default=os.environ.get("MURK_SERVER", "http://127.0.0.1:50051"))
    ap.add_argument("--token", default=os.environ.get("MURK_TOKEN"))
    a = ap.parse_args()

    cap = mc.load_ps_capture(a.capture)
    distance = a.initial_distance_mm or cap.initial_distance_mm
    with mc.Client(a.server, token=a.token) as murk:
        r = murk.photometric_stereo(
            cap.lights,
            cap.mask,
            intrinsics=cap.intrinsics,
            beta_per_mm=cap.beta_per_mm,
            sigma_per_mm=cap.sigma_per_mm,
            initial_distance_mm=distance,
            options={"auto_support": True},
        )
    a.out.mkdir(parents=True, exist_ok=True)
    for name in ("normals", "depth_mm", "albedo"):
        np.save(a.out / f"{name}.npy", getattr(r, name))
        mc.write_exr(a.out / f"{name}.exr", getattr(r, name))
    rgb = np.clip((r.normals * np.array([1, -1, -1]) + 1) * 127.5, 0, 255).astype(np.uint8)
    Image.fromarray(rgb).save(a.out / "normals.png")
    print(
        f"job {r.job_id[:12]}: {len(r.iterations)} iterations, {r.total_seconds:.2f} s, "
        f"mean z {r.mean_depth_mm:.1f} mm; outputs in {a.out}"
    )
    if cap.gt_normals is not None:
        obj = cap.mask > 0.5
        cos = np.clip(np.sum(r.normals[obj] * cap.gt_normals[obj], axis=1), -1, 1)
        print(f"mean angular error: {np.degrees(np.arccos(cos)).mean():.2f}°")


if __name__ == "__main__":
    main()
