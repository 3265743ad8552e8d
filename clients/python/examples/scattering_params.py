#!/usr/bin/env python3
"""Airlight A and scattering coefficient β of a hazy scene by Algorithm 1, and its depth.

    murk simulate mvs --out hazy
    python scattering_params.py hazy/sparse hazy/images view_02.png --out params

Writes params.json (A, β per scene unit, the search's samples) and the depth with them.
"""

import argparse
import json
import os
from pathlib import Path

import numpy as np

import murk_client as mc


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", type=Path)
    ap.add_argument("images", type=Path)
    ap.add_argument("reference")
    ap.add_argument("--sources", type=int, default=4)
    ap.add_argument("--airlight-source", default="server", choices=["server", "cnn", "dark_channel"])
    ap.add_argument("--out", type=Path, default=Path("params-result"))
    ap.add_argument("--server", default=os.environ.get("MURK_SERVER", "http://127.0.0.1:50051"))
    ap.add_argument("--token", default=os.environ.get("MURK_TOKEN"))
    a = ap.parse_args()

    model = mc.load_colmap_model(a.model)
    sources = model.nearest_sources(a.reference, a.sources)
    with mc.Client(a.server, token=a.token) as murk:
        r = murk.scattering_params(
            model.view(a.reference, a.images),
            [model.view(n, a.images) for n in sources],
            model.points_scene_units,
            airlight_source=a.airlight_source,
            # Where SfM saw the points: the standard errors then include the poses' share.
            observations=model.observations(a.reference, sources),
        )
    a.out.mkdir(parents=True, exist_ok=True)
    summary = {
        "airlight": r.airlight,
        "beta_per_scene_unit": r.beta_per_scene_unit,
        "airlight_std_error": r.airlight_std_error,
        "beta_std_error_per_scene_unit": r.beta_std_error_per_scene_unit,
        "identifiability": r.identifiability,
        "pose_error": None if r.pose_error is None else r.pose_error.__dict__,
        "airlight_initial": r.airlight_initial,
        "airlight_source": r.airlight_source,
        "beta_initial_per_scene_unit": r.beta_initial_per_scene_unit,
        "residual_scene_units": r.residual,
        "sparse_pixels": r.num_sparse_points,
        "search": [s.__dict__ for s in r.grid],
        "job_id": r.job_id,
    }
    (a.out / "params.json").write_text(json.dumps(summary, indent=2))
    np.save(a.out / "z_depth.npy", r.depth.z_depth)
    mc.write_exr(a.out / "z_depth.exr", r.depth.z_depth)
    print(
        f"A = {r.airlight:.3f} ({r.airlight_source} gave {r.airlight_initial:.3f}), "
        f"β = {r.beta_per_scene_unit:.4f} per scene unit"
    )
    meta = a.model.parent / "meta.json"
    if meta.exists():
        m = json.loads(meta.read_text())
        print(f"ground truth: A = {m['airlight']:.3f}, β = {m['beta']:.4f}")


if __name__ == "__main__":
    main()
