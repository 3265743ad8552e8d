#!/usr/bin/env python3
"""`murk params` with exact geometry at COLMAP's keypoints: what the SfM points' *places* cost.

`params_colmap_survey.py` runs murk on COLMAP models of hazy scenes, where the poses, the point
positions and the choice of points all differ from the truth. This experiment keeps only the
choice of points. For every scene of a survey folder whose reference view registered, it writes
a COLMAP text model in the simulator's frame with the true poses and, as points:

- `--points keypoints`: each keypoint COLMAP matched in the reference, placed on the true
  surface (ground-truth depth at its pixel), its track the images COLMAP matched it in, its
  observations the exact projections;
- `--points random`: as many random pixels of the reference, each seen by the views where the
  ground-truth depth shows it.

Then `murk params` (with `--no-pose-error`: the poses are exact) estimates A and β, compared with
the truth per scene unit. With exact geometry, a bias left at the keypoints and not at random
points comes from where SfM puts its points (blobs and corners), not from its poses.

    python params_colmap_survey.py --murk ../../../target/release/murk --out /tmp/survey \\
        --seeds 700-719 --width 512 --height 384 --views 7 --forward-motion 0.5
    python params_keypoint_geometry.py --murk ../../../target/release/murk /tmp/survey/seed7*
    python params_keypoint_geometry.py --murk ../../../target/release/murk --points random \\
        /tmp/survey/seed7*

Prints one row per scene, then over the scenes murk calls identifiable: how many have the true A
and β within 2 reported standard errors, MAE_A, MAE_β and β's mean relative error.
"""

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pycolmap

sys.path.insert(0, str(Path(__file__).resolve().parent))
from params_colmap_survey import read_exr_depth, read_poses  # noqa: E402


def qvecs(images_txt: Path) -> dict[str, list[str]]:
    """COLMAP images.txt → name: the QW … TZ fields as written."""
    lines = [ln for ln in images_txt.read_text().splitlines() if ln and not ln.startswith("#")]
    return {ln.split()[9]: ln.split()[1:8] for ln in lines[::2]}


def write_model(
    scene: Path, out: Path, points: list[tuple[np.ndarray, tuple[float, float], list[str]]]
) -> None:
    """A COLMAP text model in the simulator's frame: its camera, the true poses, `points` as
    (world point, reference keypoint in COLMAP pixels, track), observations the exact projections."""
    truth = read_poses(scene / "sparse" / "images.txt")
    meta = json.loads((scene / "meta.json").read_text())
    ref, focal = meta["reference"], meta["config"]["focal_px"]
    cx, cy = meta["config"]["width"] / 2, meta["config"]["height"] / 2
    out.mkdir(parents=True, exist_ok=True)
    shutil.copy(scene / "sparse" / "cameras.txt", out / "cameras.txt")
    order = sorted(truth)
    ids = {n: i + 1 for i, n in enumerate(order)}
    seen: dict[str, list[tuple[float, float, int]]] = {n: [] for n in order}
    tracks = []
    for k, (x, keypoint, track) in enumerate(points):
        elements = []
        for n in track:
            rot, t = truth[n]
            c = rot @ x + t
            uv = keypoint if n == ref else (focal * c[0] / c[2] + cx, focal * c[1] / c[2] + cy)
            elements.append((ids[n], len(seen[n])))
            seen[n].append((uv[0], uv[1], k + 1))
        tracks.append(elements)
    q = qvecs(scene / "sparse" / "images.txt")
    lines = []
    for n in order:
        lines.append(" ".join([str(ids[n]), *q[n], "1", n]))
        lines.append(" ".join(f"{u} {v} {pid}" for u, v, pid in seen[n]))
    (out / "images.txt").write_text("\n".join(lines) + "\n")
    (out / "points3D.txt").write_text(
        "\n".join(
            f"{k + 1} {x[0]} {x[1]} {x[2]} 128 128 128 0.1 " + " ".join(f"{i} {j}" for i, j in tr)
            for k, ((x, _, _), tr) in enumerate(zip(points, tracks, strict=True))
        )
        + "\n"
    )


def scene_points(
    scene: Path, mode: str, seed: int
) -> list[tuple[np.ndarray, tuple[float, float], list[str]]]:
    """The points of the module docs for one scene (empty when the reference did not register)."""
    meta = json.loads((scene / "meta.json").read_text())
    ref, focal = meta["reference"], meta["config"]["focal_px"]
    w, h = meta["config"]["width"], meta["config"]["height"]
    # murk's pixel convention: the top-left pixel's centre at (0, 0); COLMAP's at (0.5, 0.5).
    cx, cy = w / 2 - 0.5, h / 2 - 0.5
    truth = read_poses(scene / "sparse" / "images.txt")
    depths = {n: read_exr_depth(scene / "depth" / (Path(n).stem + ".exr")) for n in truth}
    rot0, t0 = truth[ref]

    def on_surface(u: float, v: float) -> np.ndarray:
        z = depths[ref][int(round(v)), int(round(u))]
        return rot0.T @ (np.array([(u - cx) / focal * z, (v - cy) / focal * z, z]) - t0)

    def visible_in(x: np.ndarray) -> list[str]:
        views = []
        for n, (rot, t) in truth.items():
            c = rot @ x + t
            col, row = int(round(focal * c[0] / c[2] + cx)), int(round(focal * c[1] / c[2] + cy))
            if 0 <= col < w and 0 <= row < h and abs(depths[n][row, col] / c[2] - 1) < 0.02:
                views.append(n)
        return views

    model_dir = scene / "colmap" / "0"
    if not (model_dir / "images.bin").exists():
        return []
    rec = pycolmap.Reconstruction(str(model_dir))
    image = next((im for im in rec.images.values() if im.name == ref), None)
    if image is None:
        return []
    keypoints = [p for p in image.points2D if p.has_point3D()]
    points = []
    if mode == "keypoints":
        for p in keypoints:
            u, v = p.xy[0] - 0.5, p.xy[1] - 0.5
            if not (0 <= round(u) < w and 0 <= round(v) < h):
                continue
            track = [rec.images[e.image_id].name for e in rec.points3D[p.point3D_id].track.elements]
            points.append(
                (on_surface(u, v), (float(p.xy[0]), float(p.xy[1])), [n for n in track if n in truth])
            )
    else:
        rng = np.random.default_rng(seed)
        while len(points) < len(keypoints):
            u, v = rng.uniform(8, w - 9), rng.uniform(8, h - 9)
            x = on_surface(u, v)
            track = visible_in(x)
            if ref in track and len(track) >= 2:
                points.append((x, (u + 0.5, v + 0.5), track))
    return points


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--murk", required=True, help="path to the murk binary")
    ap.add_argument("--points", choices=["keypoints", "random"], default="keypoints")
    ap.add_argument("--seed", type=int, default=1, help="seed of the random points")
    ap.add_argument("scenes", nargs="+", type=Path, help="scene folders of params_colmap_survey.py")
    a = ap.parse_args()
    rows = []
    for scene in a.scenes:
        points = scene_points(scene, a.points, a.seed)
        if not points:
            print(f"{scene.name}: the reference view did not register")
            continue
        meta = json.loads((scene / "meta.json").read_text())
        model = scene / f"exact_{a.points}"
        shutil.rmtree(model, ignore_errors=True)
        write_model(scene, model, points)
        out = scene / f"p_exact_{a.points}"
        shutil.rmtree(out, ignore_errors=True)
        cmd = [a.murk, "params", "--model", str(model), "--images", str(scene / "images")]
        cmd += ["--reference", meta["reference"], "--out", str(out), "--no-pose-error"]
        run = subprocess.run(cmd, capture_output=True, text=True)
        if run.returncode != 0:
            print(f"{scene.name}: murk refused the model: {run.stderr.strip().splitlines()[-1]}")
            continue
        p = json.loads((out / "params.json").read_text())
        row = {
            "a": meta["airlight"],
            "b": meta["beta"],
            "a_est": p["airlight"],
            "b_est": p["beta"],
            "a_se": p["airlight_std_error"],
            "b_se": p["beta_std_error"],
            "verdict": p["identifiability"],
        }
        rows.append(row)
        se = "" if row["a_se"] is None else f" ± {row['a_se']:.3f}"
        se_b = "" if row["b_se"] is None else f" ± {row['b_se']:.4f}"
        print(
            f"{scene.name}: {len(points)} points | A {row['a']:.3f} est {row['a_est']:.3f}{se}"
            f" | beta {row['b']:.4f} est {row['b_est']:.4f}{se_b} | {row['verdict']}"
        )
    ident = [r for r in rows if r["verdict"] == "identifiable"]
    if not ident:
        return
    covered = sum(
        abs(r["a_est"] - r["a"]) <= 2 * r["a_se"] and abs(r["b_est"] - r["b"]) <= 2 * r["b_se"] for r in ident
    )
    mae_a = np.mean([abs(r["a_est"] - r["a"]) for r in ident])
    mae_b = np.mean([abs(r["b_est"] - r["b"]) for r in ident])
    rel = np.mean([(r["b_est"] - r["b"]) / r["b"] for r in ident])
    print(
        f"{a.points}, identifiable {len(ident)}/{len(rows)}: truth within 2 SE {covered}/{len(ident)},"
        f" MAE_A {mae_a:.4f}, MAE_beta {mae_b:.4f}, beta's mean relative error {rel:+.3f}"
    )


if __name__ == "__main__":
    main()
