#!/usr/bin/env python3
"""A simulated hazy stereo stream: murk's sensor session against one-shot murk and OpenCV's SGBM
on the same moving frames, each scored against the ground truth.

`murk simulate stereo` renders a rectified rig moving through a hazy room (16-bit linear PNGs
and the left view's true z-depth per pair). Then, on the same pairs:

- `murk stereo --sequence` streams them through one sensor session: each pair after the first
  searches the band around the previous pair's disparities, with the previous corrections;
- `murk stereo` computes each pair on its own, over the whole window (one-shot);
- OpenCV's StereoSGBM (MODE_SGBM_3WAY, the settings of hazy_stereo_sgbm.py, on every core as
  murk) computes each pair from 8-bit sRGB encodings of the same images, as a camera would give
  them, timed in this process on its second run in a row.

The disparity window of SGBM and murk is the truth's range over the whole sequence with a
margin (×0.8 below, ×1.2 above, SGBM's count a multiple of 16), as a stereo user sets it from
the rig. One-shot murk and SGBM alternate pair by pair, so a host whose speed drifts slows both
alike; the stream runs once, before them. Each depth is scored with hazy_stereo_sgbm.py's
`scores`: C.P. (relative depth error < 10 %, §3.4.3) dense, where a missing pixel counts as
wrong, and the disparity bad-pixel rates.

    apt-get install python3-opencv    # cv2 (Debian's python3)
    cargo build --release
    /usr/bin/python3 stereo_stream_sgbm.py --murk ../../../target/release/murk --out /tmp/simstream
"""

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from hazy_stereo_sgbm import cv2, make_sgbm, np, scores  # noqa: E402  (cv2 with the EXR switch set)


def read_exr(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SystemExit(f"cannot read {path}")
    return img.astype(np.float64)


def srgb8(path: Path) -> np.ndarray:
    """A 16-bit linear PNG as the 8-bit sRGB image a camera would write (BGR, as cv2 reads it)."""
    lin = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64) / 65535.0
    enc = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * np.power(lin, 1 / 2.4) - 0.055)
    return np.clip(np.round(enc * 255.0), 0, 255).astype(np.uint8)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--murk", required=True, help="the murk binary")
    ap.add_argument("--out", type=Path, required=True, help="working folder (created)")
    ap.add_argument("--frames", type=int, default=30, help="pairs in the stream")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--fps", type=float, default=10.0, help="the rig's frame rate")
    ap.add_argument("--forward-per-s", type=float, default=0.5, help="speed along the optical axis")
    ap.add_argument("--sideways-per-s", type=float, default=0.0, help="speed to the right")
    ap.add_argument("--seed", type=int, default=0, help="the simulated room and haze")
    ap.add_argument(
        "--sgbm-threads",
        type=int,
        default=os.cpu_count() or 1,
        help="OpenCV's threads for SGBM (default: every core, as murk uses them)",
    )
    a = ap.parse_args()

    out: Path = a.out
    seq = out / "sequence"
    if not (seq / "frame_0000" / "meta.json").exists():
        subprocess.run(
            [
                a.murk,
                "simulate",
                "stereo",
                "--out",
                str(seq),
                "--seed",
                str(a.seed),
                "--width",
                str(a.width),
                "--height",
                str(a.height),
                "--frames",
                str(a.frames),
                "--fps",
                str(a.fps),
                "--forward-per-s",
                str(a.forward_per_s),
                "--sideways-per-s",
                str(a.sideways_per_s),
            ],
            check=True,
            capture_output=True,
        )
    frames = sorted(p for p in seq.iterdir() if (p / "meta.json").exists())[: a.frames]
    meta = json.loads((frames[0] / "meta.json").read_text())
    k = meta["intrinsics"]
    fb = k["fx"] * meta["baseline"]
    truth = [read_exr(f / "depth.exr") for f in frames]
    ok = [np.isfinite(z) & (z > 0) for z in truth]
    d_lo = min(float((fb / z[m]).min()) for z, m in zip(truth, ok, strict=True))
    d_hi = max(float((fb / z[m]).max()) for z, m in zip(truth, ok, strict=True))
    min_disp = int(np.floor(d_lo * 0.8))
    num_disp = int(np.ceil((d_hi * 1.2 - min_disp) / 16.0) * 16)

    rig = [
        "--intrinsics",
        f"{k['fx']},{k['fy']},{k['cx']},{k['cy']}",
        "--baseline",
        str(meta["baseline"]),
        "--airlight",
        str(meta["airlight"]),
        "--beta",
        str(meta["beta"]),
        "--disparity-range",
        f"{min_disp},{min_disp + num_disp}",
    ]
    run = subprocess.run(
        [
            a.murk,
            "stereo",
            "--sequence",
            str(seq),
            "--out",
            str(out / "stream"),
            "--queue-policy",
            "fifo",
            *rig,
        ],
        check=True,
        capture_output=True,
        text=True,
    )
    summary = run.stdout.strip().splitlines()[-1]
    fps = re.search(r"([0-9.]+) frames/s", summary)
    stream_compute = re.search(r"compute mean ([0-9.]+) ms", summary)

    sgbm = make_sgbm(min_disp, num_disp)
    cv2.setNumThreads(max(a.sgbm_threads, 1))

    rows = []
    for f, z, m in zip(frames, truth, ok, strict=True):
        left, right = srgb8(f / "left.png"), srgb8(f / "right.png")
        sgbm.compute(left, right)
        t0 = time.perf_counter()
        raw = sgbm.compute(left, right)
        sgbm_s = time.perf_counter() - t0
        d = raw.astype(np.float64) / 16.0
        sgbm_valid = d >= min_disp
        sgbm_depth = np.where(sgbm_valid, fb / np.maximum(d, 1e-6), 0.0)

        one = subprocess.run(
            [
                a.murk,
                "stereo",
                "--left",
                str(f / "left.png"),
                "--right",
                str(f / "right.png"),
                "--out",
                str(out / "oneshot" / f.name),
                *rig,
            ],
            check=True,
            capture_output=True,
            text=True,
        )
        compute = re.search(r", ([0-9.]+) s;", one.stdout)

        def murk_scores(
            folder: Path, z: np.ndarray = z, m: np.ndarray = m, on: np.ndarray = sgbm_valid
        ) -> dict[str, float]:
            depth = read_exr(folder / "depth.exr")
            valid = np.isfinite(depth) & (depth > 0)
            return scores(depth, valid, z, m, fb, 0.0, on)

        rows.append(
            {
                "frame": f.name,
                "stream": murk_scores(out / "stream" / f.name),
                "oneshot": murk_scores(out / "oneshot" / f.name),
                "sgbm": scores(sgbm_depth, sgbm_valid, z, m, fb, 0.0, sgbm_valid),
                "oneshot_compute_s": float(compute.group(1)) if compute else None,
                "sgbm_s": sgbm_s,
            }
        )

    def mean(method: str, key: str) -> float:
        return float(np.mean([r[method][key] for r in rows]))

    cp_gain = [r["stream"]["cp_dense"] - r["oneshot"]["cp_dense"] for r in rows]
    oneshot_s = [r["oneshot_compute_s"] for r in rows if r["oneshot_compute_s"] is not None]
    sgbm_ms = 1e3 * float(np.mean([r["sgbm_s"] for r in rows]))
    report = {
        "frames": len(rows),
        "size": f"{a.width}x{a.height}",
        "window_px": [min_disp, min_disp + num_disp],
        "truth_disparity_px": [d_lo, d_hi],
        "sgbm_threads": cv2.getNumThreads(),
        "stream": {
            "frames_per_second": float(fps.group(1)) if fps else None,
            "compute_ms_mean": float(stream_compute.group(1)) if stream_compute else None,
            "summary": summary,
        },
        "oneshot_compute_ms_mean": 1e3 * float(np.mean(oneshot_s)) if oneshot_s else None,
        "sgbm_ms_mean": sgbm_ms,
        "stream_over_sgbm": (float(stream_compute.group(1)) / sgbm_ms) if stream_compute else None,
        "cp_dense_mean": {m: mean(m, "cp_dense") for m in ("stream", "oneshot", "sgbm")},
        "bad2_dense_mean": {m: mean(m, "bad2_dense") for m in ("stream", "oneshot", "sgbm")},
        "stream_minus_oneshot_cp": {
            "mean": float(np.mean(cp_gain)),
            "worst": float(np.min(cp_gain)),
            "frames_below": int(sum(g < 0 for g in cp_gain)),
        },
        "per_frame": rows,
    }
    (out / "report.json").write_text(json.dumps(report, indent=2))
    brief = {key: v for key, v in report.items() if key != "per_frame"}
    print(json.dumps(brief, indent=2))


if __name__ == "__main__":
    main()
