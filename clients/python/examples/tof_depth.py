#!/usr/bin/env python3
"""ToF depth in fog: a frame folder in, corrected range/z-depth and mask out.

    murk simulate tof --out scene --preset medium
    python tof_depth.py scene --out result --server http://127.0.0.1:50051

Writes range_m.npy / z_depth_m.npy / mask.npy, EXR copies and 16-bit PNG previews of the raw and
corrected range on one scale; prints the error against the ground truth when the folder has it.
"""

import argparse
import os
from pathlib import Path

import numpy as np

import murk_client as mc


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("frame", type=Path, help="folder with amplitude.exr, phase.exr, meta.json")
    ap.add_argument("--out", type=Path, default=Path("tof-result"))
    ap.add_argument("--server", default=os.environ.get("MURK_SERVER", "http://127.0.0.1:50051"))
    ap.add_argument("--token", default=os.environ.get("MURK_TOKEN"))
    ap.add_argument(
        "--ca", type=Path, default=os.environ.get("MURK_TLS_CA"), help="CA certificate (PEM) for https"
    )
    a = ap.parse_args()

    frame = mc.load_tof_frame(a.frame)
    if frame.modulation_frequency_hz is None:
        raise SystemExit("meta.json gives no modulation_frequency_hz")
    ca = a.ca.read_bytes() if a.ca else None
    with mc.Client(a.server, token=a.token, root_certificates=ca) as murk:
        r = murk.tof_depth(
            frame.amplitude,
            frame.phase,
            modulation_frequency_hz=frame.modulation_frequency_hz,  # Hz
            intrinsics=frame.intrinsics,
            light_position_m=frame.light_position_m if frame.intrinsics else None,
            progress=lambda job: print(
                f"\r{job.state.name:9} {job.progress:4.0%} {job.stage:24}", end="", flush=True
            ),
        )
    print()
    a.out.mkdir(parents=True, exist_ok=True)
    outputs = {"range_m": r.range_m, "raw_range_m": r.raw_range_m, "mask": r.mask}
    if r.z_depth_m is not None:
        outputs["z_depth_m"] = r.z_depth_m
    for name, arr in outputs.items():
        np.save(a.out / f"{name}.npy", arr)
        mc.write_exr(a.out / f"{name}.exr", arr)
    obj = r.mask > 0.5
    lo, hi = np.percentile(r.range_m[obj], [1, 99]) if obj.any() else (0.0, 1.0)
    mc.write_png16(a.out / "range_m.png", r.range_m, float(lo), float(hi))
    mc.write_png16(a.out / "raw_range_m.png", r.raw_range_m, float(lo), float(hi))
    print(f"job {r.job_id[:12]}: {obj.mean():.1%} of pixels are object; outputs in {a.out}")
    gt_path = a.frame / "gt_range_m.exr"
    if gt_path.exists():
        gt = mc.read_image(gt_path)
        sel = obj & (mc.read_image(a.frame / "gt_object_mask.png") > 0.5)
        raw = np.median(np.abs(r.raw_range_m[sel] - gt[sel])) * 1e3
        cor = np.median(np.abs(r.range_m[sel] - gt[sel])) * 1e3
        print(f"median range error on the object: raw {raw:.1f} mm, corrected {cor:.1f} mm")


if __name__ == "__main__":
    main()
