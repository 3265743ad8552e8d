#!/usr/bin/env python3
"""Hazy real stereo pair: murk against OpenCV's SGBM on the same pair, accuracy, time and memory.

A real rectified pair with ground-truth disparity (Middlebury Aloe, shipped by Debian's
`opencv-doc` package) gets haze synthesised from its ground-truth depth, `I = J·t + A(1 − t)`,
`t = exp(−β z)` (Eq. 3.3), plus sensor noise, and is saved as 8-bit PNGs with a COLMAP text
model (two PINHOLE cameras, metres). Then:

- OpenCV's StereoSGBM runs on the hazy pair (timed in this process, on as many threads as murk
  has cores: `--sgbm-threads`);
- `murk mvs` runs on the same files with the true A and β (timed, and its peak memory measured
  by GNU time: the CLI starts its server in-process, so the process's peak RSS is murk's), or
  with `--method stereo`, `murk stereo` with the rig's calibration (focal length, principal
  points, baseline) and SGBM's disparity window, as a stereo user configures it;
- both are scored against the ground truth: C.P. (relative depth error < 10 %, §3.4.3) dense,
  where a missing pixel counts as wrong, and on SGBM's valid pixels; L1-rel; and the Middlebury
  bad-pixel rates (|disparity error| > 1 and > 2 px), which are far stricter than C.P. here
  (the Aloe depth range is 1.2–1.9 m, so 10 % of depth is 15–25 px of disparity at half size).

    apt-get install opencv-doc python3-opencv time    # the pair, cv2 (Debian's python3), GNU time
    cargo build --release
    /usr/bin/python3 hazy_stereo_sgbm.py --murk ../../../target/release/murk --out /tmp/aloe

Calibration of the full-size pair (Middlebury 2006): f = 3740 px, baseline 160 mm, doffs = 270 px
(the right principal point lies doffs to the right of the left one), z = f·B/(d + doffs).
"""

import argparse
import json
import os
import re
import resource
import subprocess
import time
from pathlib import Path

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
import cv2  # noqa: E402  (the EXR switch must be set before the import)
import numpy as np  # noqa: E402

DATA = Path("/usr/share/doc/opencv-doc/examples/data")
FOCAL_FULL_PX = 3740.0
BASELINE_M = 0.160
DOFFS_FULL_PX = 270.0


def fill_occlusions(disp: np.ndarray) -> np.ndarray:
    """Unknown (0) disparities take the smaller of their row neighbours': occlusions are background."""
    out = disp.copy()
    for row in out:
        known = np.flatnonzero(row > 0)
        if known.size == 0:
            continue
        idx = np.arange(row.size)
        left = np.interp(idx, known, row[known], left=row[known[0]], right=row[known[-1]])
        prev_k = np.maximum.accumulate(np.where(row > 0, idx, -1))
        next_k = np.minimum.accumulate(np.where(row > 0, idx, row.size)[::-1])[::-1]
        lo = np.where(prev_k >= 0, row[np.clip(prev_k, 0, row.size - 1)], np.inf)
        hi = np.where(next_k < row.size, row[np.clip(next_k, 0, row.size - 1)], np.inf)
        fill = np.minimum(lo, hi)
        fill = np.where(np.isfinite(fill), fill, left)
        row[row <= 0] = fill[row <= 0]
    return out


def right_view_disparity(disp_left: np.ndarray) -> np.ndarray:
    """Forward-warps the left disparity to the right view (x_R = x_L − d), the nearest surface wins."""
    h, w = disp_left.shape
    out = np.zeros_like(disp_left)
    ys, xs = np.nonzero(disp_left > 0)
    d = disp_left[ys, xs]
    xr = np.round(xs - d).astype(int)
    ok = (xr >= 0) & (xr < w)
    order = np.argsort(d[ok])  # larger disparity (nearer) written last
    out[ys[ok][order], xr[ok][order]] = d[ok][order]
    return fill_occlusions(out)


def make_sgbm(min_disp: int, num_disp: int) -> "cv2.StereoSGBM":
    """OpenCV's SGBM as the comparisons run it: MODE_SGBM_3WAY, a 5×5 block, OpenCV's suggested
    P1/P2 for 3 channels, its usual uniqueness and speckle filters."""
    bs = 5
    return cv2.StereoSGBM_create(
        minDisparity=min_disp,
        numDisparities=num_disp,
        blockSize=bs,
        P1=8 * 3 * bs * bs,
        P2=32 * 3 * bs * bs,
        disp12MaxDiff=1,
        uniquenessRatio=10,
        speckleWindowSize=100,
        speckleRange=2,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )


def write_colmap(
    out: Path,
    w: int,
    h: int,
    f: float,
    cx_l: float,
    cx_r: float,
    cy: float,
    disp: np.ndarray,
    depth: np.ndarray,
    left_img: np.ndarray,
    rng: np.random.Generator,
) -> None:
    """A two-camera COLMAP text model in metres with a sparse set of ground-truth points."""
    sparse = out / "sparse"
    sparse.mkdir(parents=True, exist_ok=True)
    (sparse / "cameras.txt").write_text(
        f"1 PINHOLE {w} {h} {f} {f} {cx_l} {cy}\n2 PINHOLE {w} {h} {f} {f} {cx_r} {cy}\n"
    )
    ys, xs = np.nonzero(disp > 0)
    pick = rng.choice(ys.size, size=min(2000, ys.size), replace=False)
    pts, obs_l, obs_r = [], [], []
    for k, i in enumerate(pick, start=1):
        x, y = float(xs[i]), float(ys[i])
        z = float(depth[ys[i], xs[i]])
        xw, yw = (x - cx_l) * z / f, (y - cy) * z / f
        xr = f * (xw - BASELINE_M) / z + cx_r
        if not 0 <= xr < w:
            continue
        c = left_img[ys[i], xs[i]]
        pts.append(f"{k} {xw} {yw} {z} {c[2]} {c[1]} {c[0]} 0.5 1 {len(obs_l)} 2 {len(obs_r)}")
        obs_l.append(f"{x} {y} {k}")
        obs_r.append(f"{xr} {y} {k}")
    (sparse / "images.txt").write_text(
        "1 1 0 0 0 0 0 0 1 left.png\n" + " ".join(obs_l) + "\n"
        f"2 1 0 0 0 {-BASELINE_M} 0 0 2 right.png\n" + " ".join(obs_r) + "\n"
    )
    (sparse / "points3D.txt").write_text("\n".join(pts) + "\n")


def scores(
    depth: np.ndarray,
    valid: np.ndarray,
    gt: np.ndarray,
    gt_ok: np.ndarray,
    fb: float,
    doffs: float,
    on: np.ndarray,
) -> dict[str, float]:
    """C.P. dense (missing = wrong) and on `on`, L1-rel and disparity bad-pixel rates on valid GT."""
    ev = gt_ok
    rel = np.where(valid, np.abs(depth - gt) / gt, np.inf)
    d_est = np.where(valid, fb / np.where(valid, depth, 1.0) - doffs, np.inf)
    d_gt = fb / gt - doffs
    derr = np.abs(d_est - d_gt)
    return {
        "cp_dense": float(np.mean(rel[ev] < 0.1) * 100),
        "cp_on_sgbm_valid": float(np.mean(rel[ev & on] < 0.1) * 100),
        "l1_rel_valid": float(np.mean(rel[ev & valid])),
        "bad1_dense": float(np.mean(derr[ev] > 1.0) * 100),
        "bad2_dense": float(np.mean(derr[ev] > 2.0) * 100),
        "bad2_on_sgbm_valid": float(np.mean(derr[ev & on] > 2.0) * 100),
        "valid_fraction": float(np.mean(valid[ev]) * 100),
    }


def stream(
    a: argparse.Namespace,
    out: Path,
    stereo_cmd: list[str],
    gt_depth: np.ndarray,
    gt_ok: np.ndarray,
    fb: float,
    doffs: float,
    sgbm_valid: np.ndarray,
) -> dict[str, object]:
    """The pair `a.stream_frames` times through one sensor session: a static rig, so every frame
    after the first searches the band around the previous frame's disparities."""
    seq = out / "sequence"
    for k in range(a.stream_frames):
        d = seq / f"frame_{k:03d}"
        d.mkdir(parents=True, exist_ok=True)
        for side in ("left", "right"):
            link = d / f"{side}.png"
            if not link.exists():
                link.symlink_to((out / "images" / f"{side}.png").resolve())
    # The one-shot command's rig flags, with the sequence in place of the pair.
    cmd = list(stereo_cmd)
    i = cmd.index("--left")
    del cmd[i : i + 4]
    cmd[cmd.index("--out") + 1] = str(out / "stream")
    cmd += ["--sequence", str(seq), "--queue-policy", "fifo"]
    run = subprocess.run(cmd, check=True, capture_output=True, text=True)
    line = run.stdout.strip().splitlines()[-1]
    fps = re.search(r"([0-9.]+) frames/s", line)
    compute = re.search(r"compute mean ([0-9.]+) ms", line)
    p50 = re.search(r"p50 ([0-9.]+) ms", line)

    def score(name: str) -> dict[str, float]:
        depth = cv2.imread(str(out / "stream" / name / "depth.exr"), cv2.IMREAD_UNCHANGED).astype(np.float64)
        valid = np.isfinite(depth) & (depth > 0)
        return scores(depth, valid, gt_depth, gt_ok, fb, doffs, sgbm_valid)

    last = f"frame_{a.stream_frames - 1:03d}"
    return {
        "frames": a.stream_frames,
        "frames_per_second": float(fps.group(1)) if fps else None,
        "compute_ms_mean": float(compute.group(1)) if compute else None,
        "latency_ms_p50": float(p50.group(1)) if p50 else None,
        "first_frame": score("frame_000"),
        "last_frame": score(last),
        "summary": line,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA, help="folder with aloeL.jpg, aloeR.jpg, aloeGT.png")
    ap.add_argument("--murk", default="murk", help="the murk binary")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--scale", type=float, default=0.5, help="downscale of the full-size pair")
    ap.add_argument("--crop", default="640x480", help="centre crop WxH after scaling ('' = none)")
    ap.add_argument("--airlight", type=float, default=0.85)
    ap.add_argument("--median-transmission", type=float, default=0.3)
    ap.add_argument("--noise", type=float, default=0.01, help="Gaussian sensor noise std, [0, 1] units")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--right-gain",
        type=float,
        default=1.0,
        help="exposure gain of the right camera relative to the left (1.05 = 5 %% brighter)",
    )
    ap.add_argument(
        "--right-tint",
        default="1,1,1",
        help="white balance of the right camera relative to the left: R,G,B gains on top of --right-gain",
    )
    ap.add_argument(
        "--vignetting",
        type=float,
        default=0.0,
        help="radial fall-off of both cameras (same lens model): gain 1 - V*(r/r_corner)^2",
    )
    ap.add_argument(
        "--right-vignetting",
        type=float,
        default=0.0,
        help="radial fall-off of the right camera instead of --vignetting (0.2 = 20 %% darker corners)",
    )
    ap.add_argument(
        "--right-gamma",
        type=float,
        default=1.0,
        help="tone curve of the right camera relative to the left: recorded value = value^G",
    )
    ap.add_argument(
        "--right-shift-y",
        type=float,
        default=0.0,
        help="rectification error: the right image moved down by this many pixels (sub-pixel allowed)",
    )
    ap.add_argument(
        "--method",
        choices=["mvs", "stereo"],
        default="mvs",
        help="murk's input: the COLMAP model (`murk mvs`) or the rectified rig (`murk stereo`)",
    )
    ap.add_argument(
        "--stream-frames",
        type=int,
        default=0,
        help="also stream the pair this many times through a sensor session (`murk stereo --sequence`, "
        "the rig's flags): frames/s, per-frame compute and the first and last frames' scores",
    )
    ap.add_argument("--repeats", type=int, default=3, help="timed runs of each method (best is reported)")
    ap.add_argument(
        "--sgbm-threads",
        type=int,
        default=os.cpu_count() or 1,
        help="OpenCV's threads for SGBM (default: every core, as murk uses them; MODE_SGBM_3WAY "
        "runs its rows in parallel)",
    )
    ap.add_argument("--murk-args", default="", help="extra `murk mvs` flags")
    ap.add_argument(
        "--srgb",
        action="store_true",
        help="cameras that write sRGB: haze the decoded (linear) radiance, encode the images, and run "
        "`murk mvs --srgb` (--airlight stays in linear units)",
    )
    ap.add_argument(
        "--same-window",
        action="store_true",
        help="give murk SGBM's disparity window and one plane per disparity",
    )
    a = ap.parse_args()
    rng = np.random.default_rng(a.seed)

    left = cv2.imread(str(a.data / "aloeL.jpg"))
    right = cv2.imread(str(a.data / "aloeR.jpg"))
    gt_full = cv2.imread(str(a.data / "aloeGT.png"), cv2.IMREAD_UNCHANGED).astype(np.float64)
    h0, w0 = gt_full.shape
    w, h = int(round(w0 * a.scale)), int(round(h0 * a.scale))
    left = cv2.resize(left, (w, h), interpolation=cv2.INTER_AREA)
    right = cv2.resize(right, (w, h), interpolation=cv2.INTER_AREA)
    # Nearest sampling keeps unknown (0) disparities unknown instead of blending them in.
    yi = np.minimum((np.arange(h) / a.scale).astype(int), h0 - 1)
    xi = np.minimum((np.arange(w) / a.scale).astype(int), w0 - 1)
    disp = gt_full[np.ix_(yi, xi)] * a.scale
    f, doffs = FOCAL_FULL_PX * a.scale, DOFFS_FULL_PX * a.scale
    cx_l, cy = (w0 / 2.0) * a.scale, (h0 / 2.0) * a.scale
    if a.crop:
        cw, ch = (int(v) for v in a.crop.split("x"))
        x0, y0 = (w - cw) // 2, (h - ch) // 2
        left, right, disp = (m[y0 : y0 + ch, x0 : x0 + cw] for m in (left, right, disp))
        cx_l, cy, w, h = cx_l - x0, cy - y0, cw, ch
    cx_r = cx_l + doffs
    fb = f * BASELINE_M
    gt_ok = disp > 0
    filled_l = fill_occlusions(disp)
    depth_l = fb / (filled_l + doffs)
    depth_r = fb / (right_view_disparity(filled_l) + doffs)
    beta = -np.log(a.median_transmission) / float(np.median(depth_l))

    def haze(
        img: np.ndarray,
        depth: np.ndarray,
        gain: float | np.ndarray = 1.0,
        vignetting: float = 0.0,
        gamma: float = 1.0,
    ) -> np.ndarray:
        # A camera's gain, vignetting and tone curve act on everything it records, airlight
        # included; noise is added to the linear signal, before the tone curve.
        t = np.exp(-beta * depth)[..., None]
        j = img.astype(np.float64) / 255.0
        if a.srgb:
            # The Aloe photographs are sRGB-encoded: the radiance that haze attenuates is linear.
            j = np.where(j <= 0.04045, j / 12.92, ((j + 0.055) / 1.055) ** 2.4)
        i = gain * (j * t + a.airlight * (1.0 - t))
        if vignetting:
            yy, xx = np.mgrid[0:h, 0:w]
            cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
            r2 = ((xx - cx) ** 2 + (yy - cy) ** 2) / (cx**2 + cy**2)
            i *= (1.0 - vignetting * r2)[..., None]
        i += rng.normal(0.0, a.noise, i.shape)
        if gamma != 1.0:
            i = np.clip(i, 0.0, 1.0) ** gamma
        if a.srgb:
            i = np.clip(i, 0.0, 1.0)
            i = np.where(i <= 0.0031308, 12.92 * i, 1.055 * i ** (1 / 2.4) - 0.055)
        return np.clip(np.round(i * 255.0), 0, 255).astype(np.uint8)

    out = a.out
    (out / "images").mkdir(parents=True, exist_ok=True)
    # cv2 images are BGR.
    tint_bgr = np.array([float(v) for v in a.right_tint.split(",")][::-1])
    hl = haze(left, depth_l, 1.0, a.vignetting)
    hr = haze(right, depth_r, a.right_gain * tint_bgr, a.right_vignetting or a.vignetting, a.right_gamma)
    if a.right_shift_y:
        # What an imperfect rectification leaves: the model says the rows agree, the images do not.
        shift = np.float32([[1, 0, 0], [0, 1, a.right_shift_y]])
        hr = cv2.warpAffine(hr, shift, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    cv2.imwrite(str(out / "images" / "left.png"), hl)
    cv2.imwrite(str(out / "images" / "right.png"), hr)
    write_colmap(out, w, h, f, cx_l, cx_r, cy, disp, fb / np.where(gt_ok, disp + doffs, 1.0), left, rng)
    gt_depth = np.where(gt_ok, fb / (disp + doffs), 0.0)
    # Disparity search window of the images as given (d = x_L − x_R): the ground truth's range
    # with a margin, as a user of SGBM would set it from the rig.
    d_lo, d_hi = float(disp[gt_ok].min()), float(disp[gt_ok].max())
    min_disp = int(np.floor(d_lo * 0.8))
    num_disp = int(np.ceil((d_hi * 1.2 - min_disp) / 16.0) * 16)

    sgbm = make_sgbm(min_disp, num_disp)
    # The same cores as murk. (OpenCV's 0 would run SGBM on one thread.)
    cv2.setNumThreads(max(a.sgbm_threads, 1))

    def run_sgbm() -> tuple[np.ndarray, float]:
        t0 = time.perf_counter()
        raw = sgbm.compute(hl, hr)
        return raw, time.perf_counter() - t0

    # One untimed run first, as murk's runs each start a fresh process but SGBM's reuse this one.
    raw, _ = run_sgbm()
    d_sgbm = raw.astype(np.float64) / 16.0
    sgbm_valid = d_sgbm >= min_disp
    depth_sgbm = np.where(sgbm_valid, fb / np.maximum(d_sgbm + doffs, 1e-6), 0.0)

    # murk: by default the COLMAP model's points give the plane range and the displacement the
    # plane count, as for any capture; --same-window gives it SGBM's disparity window instead.
    z_near, z_far = fb / (min_disp + num_disp + doffs), fb / (max(min_disp, 0) + doffs)
    mvs_cmd = [
        "/usr/bin/time",
        "-f",
        "maxrss_kib=%M",
        a.murk,
        "mvs",
        "--model",
        str(out / "sparse"),
        "--images",
        str(out / "images"),
        "--reference",
        "left.png",
        "--sources",
        "right.png",
        "--airlight",
        str(a.airlight),
        "--beta",
        str(beta),
        "--out",
        str(out / "murk"),
        *(["--near", str(z_near), "--far", str(z_far), "--planes", str(num_disp)] if a.same_window else []),
        *(["--srgb"] if a.srgb else []),
        *a.murk_args.split(),
    ]
    # The rig as a stereo user has it: murk's pixel-centre principal points are COLMAP's minus
    # 0.5, and the search window is SGBM's, one plane per pixel of disparity.
    stereo_cmd = [
        "/usr/bin/time",
        "-f",
        "maxrss_kib=%M",
        a.murk,
        "stereo",
        "--left",
        str(out / "images" / "left.png"),
        "--right",
        str(out / "images" / "right.png"),
        "--intrinsics",
        f"{f},{f},{cx_l - 0.5},{cy - 0.5}",
        "--right-cx",
        str(cx_r - 0.5),
        "--baseline",
        str(BASELINE_M),
        "--disparity-range",
        f"{min_disp},{min_disp + num_disp}",
        "--airlight",
        str(a.airlight),
        "--beta",
        str(beta),
        "--out",
        str(out / "murk"),
        *(["--srgb"] if a.srgb else []),
        *a.murk_args.split(),
    ]
    cmd = stereo_cmd if a.method == "stereo" else mvs_cmd
    best_murk, peak_murk_mib = np.inf, 0.0
    sgbm_times: list[float] = []
    compute_times: list[float] = []
    planes_line = None
    # SGBM and murk alternate, so that a host whose speed drifts (shared VMs swing by 2x within
    # an hour) slows both alike; each pair's ratio is reported as well as the best times. SGBM's
    # time is its second run in a row: its first after murk's process is slower (caches, 0.12 s
    # against 0.09 s on the 2-core VM), and the warm one is the harder bar.
    for _ in range(a.repeats):
        run_sgbm()
        sgbm_times.append(run_sgbm()[1])
        t0 = time.perf_counter()
        run = subprocess.run(cmd, check=True, capture_output=True, text=True)
        best_murk = min(best_murk, time.perf_counter() - t0)
        # The CLI's summary line: "job ID: ..., N planes over z ..., S s; ..." (server-side time).
        compute = re.search(r"planes over z [^,]*, ([0-9.]+) s;", run.stdout)
        if compute:
            compute_times.append(float(compute.group(1)))
        rss = re.search(r"maxrss_kib=(\d+)", run.stderr)
        if rss:
            peak_murk_mib = max(peak_murk_mib, int(rss.group(1)) / 1024.0)
        planes_line = re.search(r"(\d+) planes over z", run.stdout)
    peak_self_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    depth_murk = cv2.imread(str(out / "murk" / "depth.exr"), cv2.IMREAD_UNCHANGED).astype(np.float64)
    conf_murk = cv2.imread(str(out / "murk" / "confidence.exr"), cv2.IMREAD_UNCHANGED).astype(np.float64)
    murk_valid = np.isfinite(depth_murk) & (depth_murk > 0)
    murk_confident = murk_valid & (conf_murk > 0)

    pair_ratios = [m / g for m, g in zip(compute_times, sgbm_times, strict=False)]
    report = {
        "pair": f"{w}x{h}",
        "method": a.method,
        "right_gain": a.right_gain,
        "right_tint_rgb": a.right_tint,
        "vignetting": a.vignetting,
        "right_vignetting": a.right_vignetting,
        "right_gamma": a.right_gamma,
        "right_shift_y": a.right_shift_y,
        "srgb": a.srgb,
        "airlight": a.airlight,
        "beta_per_m": beta,
        "median_transmission": a.median_transmission,
        "disparity_range_px": [d_lo, d_hi],
        "sgbm_window_px": [min_disp, min_disp + num_disp],
        "sgbm": {
            **scores(depth_sgbm, sgbm_valid, gt_depth, gt_ok, fb, doffs, sgbm_valid),
            "seconds": min(sgbm_times),
            "threads": cv2.getNumThreads(),
            "peak_rss_mib_python_process": peak_self_mib,
        },
        "murk": {
            **scores(depth_murk, murk_valid, gt_depth, gt_ok, fb, doffs, sgbm_valid),
            "seconds_process": best_murk,
            "seconds_compute": min(compute_times) if compute_times else None,
            "seconds_compute_per_run": compute_times,
            "peak_rss_mib": peak_murk_mib,
            "planes": int(planes_line.group(1)) if planes_line else None,
        },
        "murk_confident": scores(depth_murk, murk_confident, gt_depth, gt_ok, fb, doffs, sgbm_valid),
        # murk's server-side compute over SGBM's compute: best over best, and each alternating
        # pair's ratio (its median is the figure least moved by the host's speed drifting).
        "time_ratio": {
            "best_over_best": min(compute_times) / min(sgbm_times) if compute_times else None,
            "per_pair": pair_ratios,
            "median_of_pairs": float(np.median(pair_ratios)) if pair_ratios else None,
            "sgbm_seconds_per_run": sgbm_times,
        },
        "murk_cmd": " ".join(cmd),
    }
    if a.stream_frames > 0:
        report["stream"] = stream(a, out, stereo_cmd, gt_depth, gt_ok, fb, doffs, sgbm_valid)
    (out / "report.json").write_text(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))
    cv2.imwrite(str(out / "sgbm_disparity.png"), np.clip(d_sgbm * 2, 0, 255).astype(np.uint8))


if __name__ == "__main__":
    main()
