#!/usr/bin/env python3
"""A and β through COLMAP models of hazy scenes: `murk params` on SfM it did not make.

For each seed: `murk simulate mvs` renders a hazy scene, pycolmap reconstructs it from the hazy
images alone (SIFT, exhaustive matching, intrinsics fixed as for a calibrated rig), and
`murk params` estimates A and β on that model. The model has its own unit, its own pose errors
and its own few points (SIFT finds little in the far haze), as a real capture's would.

β is per model unit. It is made comparable with the scene's β through the model's unit, which
this script measures itself, independently of murk, in two ways: the scale of the similarity
that maps the COLMAP camera centres onto the simulator's (Umeyama), and the median ratio of the
reference's ground-truth depth to the model points' depths at their pixels. On a sound model the
two agree. On a distorted one (a bas-relief ambiguity: translation directions tens of degrees
off) they do not, and only the depth ratio converts β·z, the optical depth that murk's
transmission and dehazing use, since β multiplies the model's depths. The same scene is also run
on the simulator's own model, so what the SfM costs is visible seed by seed.

    pip install pycolmap './clients/python'    # murk_client reads the EXR depth
    cargo build --release
    python params_colmap_survey.py --murk ../../../target/release/murk --out /tmp/colmap_survey \\
        --seeds 600-609 [--forward-motion 0.5]

Prints one row per seed and, over the seeds whose reference view registered, MAE_A and MAE_β
(per scene unit) and the coverage: on how many models the true A and β (through the depths'
unit) both lie within 2 of murk's reported standard errors, with the errors' mean and RMS in
reported standard errors (0 and 1 where they are calibrated). Reported separately for the models
murk calls identifiable, the target of docs/scattering-params.md. Each row ends with the SfM
points' relief about their plane and the plane's tilt, "flat" where murk calls the cloud
ambiguous. Writes `survey.json` in --out.

Rendering and COLMAP take most of a run. With `--reuse`, seeds whose folder in --out already
holds a scene and its COLMAP models run only `murk params` again (another build, other
`--murk-args`) on the same models.
"""

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pycolmap

from murk_client import read_image

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sfm_pycolmap import PEAK_THRESHOLD, reconstruct, written_models  # noqa: E402


def qvec_to_rotation(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def read_poses(images_txt: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """COLMAP images.txt → name: (world-to-camera R, t)."""
    lines = [ln for ln in images_txt.read_text().splitlines() if ln and not ln.startswith("#")]
    poses = {}
    for ln in lines[::2]:
        p = ln.split()
        rot = qvec_to_rotation(np.array([float(v) for v in p[1:5]]))
        poses[p[9]] = (rot, np.array([float(v) for v in p[5:8]]))
    return poses


def centre_scale(truth: Path, model: Path) -> float:
    """Scene units per model unit: the Umeyama similarity scale between the camera centres."""
    a, b = read_poses(truth), read_poses(model)
    names = sorted(set(a) & set(b))
    ca = np.array([-a[n][0].T @ a[n][1] for n in names])
    cb = np.array([-b[n][0].T @ b[n][1] for n in names])
    ca -= ca.mean(0)
    cb -= cb.mean(0)
    u, s, vt = np.linalg.svd(ca.T @ cb)
    s[-1] *= np.sign(np.linalg.det(u @ vt))  # no reflection, as Umeyama
    return float(s.sum() / (cb**2).sum())


def pose_errors(truth: Path, model: Path, reference: str) -> tuple[float, float]:
    """Largest rotation and translation-direction errors (degrees) of the views relative to the reference."""
    a, b = read_poses(truth), read_poses(model)
    (ra0, ta0), (rb0, tb0) = a[reference], b[reference]
    worst_rot, worst_dir = 0.0, 0.0
    for name in sorted(set(a) & set(b) - {reference}):
        (ra, ta), (rb, tb) = a[name], b[name]
        rel_a, rel_b = ra @ ra0.T, rb @ rb0.T
        da, db = ta - rel_a @ ta0, tb - rel_b @ tb0
        cos_rot = np.clip((np.trace(rel_a.T @ rel_b) - 1) / 2, -1, 1)
        cos_dir = np.clip(da @ db / (np.linalg.norm(da) * np.linalg.norm(db)), -1, 1)
        worst_rot = max(worst_rot, float(np.degrees(np.arccos(cos_rot))))
        worst_dir = max(worst_dir, float(np.degrees(np.arccos(cos_dir))))
    return worst_rot, worst_dir


def depth_scale(scene: Path, model_dir: Path, reference: str) -> float:
    """Scene units per model unit: median ratio of ground-truth depth to the points' model depths."""
    rec = pycolmap.Reconstruction(str(model_dir))
    img = next(im for im in rec.images.values() if im.name == reference)
    cam = rec.cameras[img.camera_id]
    gt = read_exr_depth(scene / "depth" / (Path(reference).stem + ".exr"))
    ratios = []
    world_to_cam = img.cam_from_world()
    for pid in rec.points3D:
        xyz = world_to_cam * rec.points3D[pid].xyz
        if xyz[2] <= 0:
            continue
        uv = cam.img_from_cam(xyz)
        col, row = int(uv[0]), int(uv[1])
        if 0 <= row < gt.shape[0] and 0 <= col < gt.shape[1]:
            ratios.append(gt[row, col] / xyz[2])
    return float(np.median(ratios)) if ratios else float("nan")


def read_exr_depth(path: Path) -> np.ndarray:
    d = np.asarray(read_image(path))
    return d[..., 0] if d.ndim == 3 else d


def murk_params(
    murk: str, model: Path, images: Path, reference: str, out: Path, extra: list[str]
) -> dict | str:
    """params.json of `murk params`, or murk's error message when it refuses the model."""
    shutil.rmtree(out, ignore_errors=True)
    cmd = [murk, "params", "--model", str(model), "--images", str(images)]
    cmd += ["--reference", reference, "--out", str(out), *extra]
    run = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "RUST_BACKTRACE": "0"})
    if run.returncode != 0:
        return run.stderr.strip().splitlines()[-1]
    return json.loads((out / "params.json").read_text())


def report(label: str, rows: list[dict], key: str) -> None:
    """MAE of A and of β (per scene unit) of the `key` estimates ("sfm" or "sim") over `rows`;
    for COLMAP models β is converted with the centres' unit and, after the slash, the depths'."""
    if not rows:
        return
    mae_a = np.mean([abs(r[key]["airlight"] - r["airlight"]) for r in rows])
    mae_b = np.mean([abs(r[key]["beta"] - r["beta"]) for r in rows])
    line = f"{label} ({len(rows)}): MAE_A {mae_a:.4f}, MAE_beta {mae_b:.4f}"
    if key == "sfm":
        mae_d = np.mean([abs(r[key]["beta_via_depths"] - r["beta"]) for r in rows])
        line += f" / {mae_d:.4f} (unit from centres / depths)"
        line += f"; truth within 2 SE (A and beta via depths): {sum(map(covered, rows))}/{len(rows)}"
        z = standard_scores(rows)
        if z:
            za, zb = np.array([a for a, _ in z]), np.array([b for _, b in z])
            line += (
                f"; errors in reported SE: A mean {za.mean():+.2f} RMS {np.sqrt((za**2).mean()):.2f},"
                f" beta mean {zb.mean():+.2f} RMS {np.sqrt((zb**2).mean()):.2f}"
            )
    print(line)


def standard_scores(rows: list[dict]) -> list[tuple[float, float]]:
    """(estimate − truth) / reported SE of A and of β (via the depths' unit) for the COLMAP models
    with both errors: about 0 on average and of RMS 1 where the errors are calibrated."""
    out = []
    for r in rows:
        s = r["sfm"]
        if s["airlight_std_error"] and s["beta_std_error_via_depths"]:
            out.append(
                (
                    (s["airlight"] - r["airlight"]) / s["airlight_std_error"],
                    (s["beta_via_depths"] - r["beta"]) / s["beta_std_error_via_depths"],
                )
            )
    return out


def fmt(v: float | None) -> str:
    return "-" if v is None else f"{v:.4f}"


def fmt_relief(r: dict | None) -> str:
    """The points' median distance to their plane over their depth and the plane's tilt from
    facing the reference, "flat" where murk calls the cloud ambiguous
    (docs/scattering-params.md#a-flat-point-cloud)."""
    if r is None:
        return "-"
    return f"{100 * r['relief']:.1f} %/{r['tilt_deg']:.0f} deg" + (" flat" if r["ambiguous"] else "")


def covered(row: dict) -> bool:
    """Whether the true A and β (converted with the depths' unit) both lie within 2 reported
    standard errors of the COLMAP model's estimates."""
    s = row["sfm"]
    if s["airlight_std_error"] is None or s["beta_std_error_via_depths"] is None:
        return False
    return (
        abs(s["airlight"] - row["airlight"]) <= 2 * s["airlight_std_error"]
        and abs(s["beta_via_depths"] - row["beta"]) <= 2 * s["beta_std_error_via_depths"]
    )


def coverage_label(row: dict) -> str:
    """Returns "covered" or "MISSED" (the truth beyond 2 SE), or "-" when murk reports no error."""
    if row["sfm"]["airlight_std_error"] is None or row["sfm"]["beta_std_error_via_depths"] is None:
        return "-"
    return "covered" if covered(row) else "MISSED"


def seeds_of(spec: str) -> list[int]:
    if "-" in spec:
        lo, hi = spec.split("-")
        return list(range(int(lo), int(hi) + 1))
    return [int(s) for s in spec.split(",")]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--murk", required=True, help="path to the murk binary")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--seeds", default="600-609", help="a range a-b or a comma list")
    ap.add_argument("--forward-motion", type=float, default=0.0)
    ap.add_argument("--width", type=int, default=512)
    ap.add_argument("--height", type=int, default=384)
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--murk-args", default="", help="extra `murk params` arguments (use --murk-args=...)")
    ap.add_argument(
        "--peak-threshold", type=float, default=PEAK_THRESHOLD, help="COLMAP's SIFT peak threshold"
    )
    ap.add_argument(
        "--reuse",
        action="store_true",
        help="keep a seed's rendered scene and COLMAP models where its folder in --out holds them,"
        " and run only murk again (the scene's settings are those it was rendered with)",
    )
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    rows = []
    print(
        "seed  A true  A sfm  A sim  | beta (per scene unit) true, sfm (centres/depths), sim"
        " | unit from centres/depths"
        " | pose err rot/dir deg | points | identifiability | SE | coverage | relief/tilt"
    )
    for seed in seeds_of(a.seeds):
        scene = a.out / f"seed{seed}"
        reused = a.reuse and (scene / "meta.json").exists() and (scene / "colmap" / "database.db").exists()
        if not reused:
            shutil.rmtree(scene, ignore_errors=True)
            sim = [a.murk, "simulate", "mvs", "--out", str(scene), "--seed", str(seed)]
            sim += ["--width", str(a.width), "--height", str(a.height), "--views", str(a.views)]
            sim += ["--forward-motion", str(a.forward_motion)]
            sim += ["--airlight-range", "0.5,1.0", "--median-transmission-range", "0.1,0.4"]
            subprocess.run(sim, check=True, capture_output=True)
        meta = json.loads((scene / "meta.json").read_text())
        reference = meta["reference"]
        focal = meta["config"]["focal_px"]
        intr = f"{focal},{focal},{a.width / 2},{a.height / 2}"
        models = written_models(scene) if reused else reconstruct(scene, intr, a.peak_threshold, quiet=True)
        model = max(models, key=lambda m: m[1], default=None) if models else None
        registered = model is not None and reference in read_poses(model[0] / "images.txt")
        extra = a.murk_args.split()
        sim_params = murk_params(
            a.murk, scene / "sparse", scene / "images", reference, scene / "p_sim", extra
        )
        assert isinstance(sim_params, dict), f"murk refused the simulator's own model: {sim_params}"
        row = {
            "seed": seed,
            "airlight": meta["airlight"],
            "beta": meta["beta"],
            "sim": {"airlight": sim_params["airlight"], "beta": sim_params["beta"]},
        }
        if registered:
            assert model is not None
            unit_c = centre_scale(scene / "sparse" / "images.txt", model[0] / "images.txt")
            unit_d = depth_scale(scene, model[0], reference)
            rot_err, dir_err = pose_errors(
                scene / "sparse" / "images.txt", model[0] / "images.txt", reference
            )
            p = murk_params(a.murk, model[0], scene / "images", reference, scene / "p_sfm", extra)
            if isinstance(p, str):
                print(f"{seed:4d}  murk refused the COLMAP model ({model[1]} points): {p}")
                row["refused"] = p
                rows.append(row)
                continue
            row["sfm"] = {
                "airlight": p["airlight"],
                "beta_per_model_unit": p["beta"],
                "beta": p["beta"] / unit_c,
                # β·z in the model's own depths: the optical depth murk's outputs use.
                "beta_via_depths": p["beta"] / unit_d,
                # None when β* is the sweep's guess (not identifiable).
                "beta_std_error": None if p["beta_std_error"] is None else p["beta_std_error"] / unit_c,
                "beta_std_error_via_depths": None
                if p["beta_std_error"] is None
                else p["beta_std_error"] / unit_d,
                "airlight_std_error": p["airlight_std_error"],
                "warnings": p["warnings"],
                "identifiable": p["identifiable"],
                "identifiability": p["identifiability"],
                "points": model[1],
                "unit_from_centres": unit_c,
                "unit_from_depths": unit_d,
                "worst_rotation_error_deg": rot_err,
                "worst_translation_direction_error_deg": dir_err,
                "relief": p.get("relief"),
            }
            s = row["sfm"]
            print(
                f"{seed:4d}  {meta['airlight']:.3f}  {s['airlight']:.3f}  {sim_params['airlight']:.3f}  |"
                f"  {meta['beta']:.4f}  {s['beta']:.4f}/{s['beta_via_depths']:.4f}  {sim_params['beta']:.4f}"
                f" | {unit_c:.4f}/{unit_d:.4f} | {rot_err:4.1f}/{dir_err:4.1f} | {model[1]:5d} |"
                f" {s['identifiability']} | SE A {fmt(s['airlight_std_error'])}"
                f" beta {fmt(s['beta_std_error_via_depths'])} | {coverage_label(row)}"
                f" | {fmt_relief(s['relief'])}"
            )
        else:
            print(f"{seed:4d}  the reference view did not register in COLMAP's largest model")
        rows.append(row)
    done = [r for r in rows if "sfm" in r]
    report("simulator's models, every seed", rows, "sim")
    if done:
        report("COLMAP models, every registered seed", done, "sfm")
        report("simulator's models of the same seeds", done, "sim")
        report("COLMAP models murk calls identifiable", [r for r in done if r["sfm"]["identifiable"]], "sfm")
        conflicts = [r for r in done if r["sfm"]["identifiability"] == "airlight_conflict"]
        report("COLMAP models with an airlight conflict", conflicts, "sfm")
        report("COLMAP models without one", [r for r in done if r not in conflicts], "sfm")
        # A similarity reconstruction has one unit: the centres' and the depths' scales agree. When
        # they do not, the model is distorted (small baselines leave SfM a bas-relief ambiguity),
        # and no β per model unit is a β per scene unit.
        sound = [
            r for r in done if abs(r["sfm"]["unit_from_depths"] / r["sfm"]["unit_from_centres"] - 1) < 0.05
        ]
        report("COLMAP models whose two unit estimates agree within 5 %", sound, "sfm")
        flagged = sum(not r["sfm"]["identifiable"] for r in done)
        flat = sum(bool(r["sfm"]["relief"] and r["sfm"]["relief"]["ambiguous"]) for r in done)
        print(
            f"registered {len(done)}/{len(rows)}; flagged not identifiable on the COLMAP model: {flagged};"
            f" flat point clouds: {flat}"
        )
    (a.out / "survey.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
