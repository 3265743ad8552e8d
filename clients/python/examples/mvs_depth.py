#!/usr/bin/env python3
"""MVS depth in haze from a COLMAP model: dehazing cost volume with known A and β.

    murk simulate mvs --out hazy
    python mvs_depth.py hazy/sparse hazy/images view_02.png --airlight 0.9 --beta 0.2 --out result

For a folder written by `murk simulate mvs`, A and β default to the ground truth in its
meta.json (scattering_params.py estimates them for real captures). The planes span the range of
the SfM points seen in front of the reference (scene units), not a fixed default.
"""

import argparse
import json
import os
from pathlib import Path

import numpy as np

import murk_client as mc


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", type=Path, help="COLMAP sparse model folder (text or binary)")
    ap.add_argument("images", type=Path, help="folder of the model's (undistorted) images")
    ap.add_argument("reference", help="image name of the reference view")
    ap.add_argument("--sources", type=int, default=4, help="nearest registered views to use")
    ap.add_argument("--airlight", type=float, help="A in (0, 1]")
    ap.add_argument("--beta", type=float, help="β per scene unit")
    ap.add_argument("--cost-volume", default="dehazing", choices=["dehazing", "eq37", "ordinary"])
    ap.add_argument("--planes", type=int, default=128)
    ap.add_argument("--out", type=Path, default=Path("mvs-result"))
    ap.add_argument("--server", default=os.environ.get("MURK_SERVER", "http://127.0.0.1:50051"))
    ap.add_argument("--token", default=os.environ.get("MURK_TOKEN"))
    a = ap.parse_args()

    meta_path = a.model.parent / "meta.json"
    if (a.airlight is None or a.beta is None) and meta_path.exists():
        meta = json.loads(meta_path.read_text())
        a.airlight = a.airlight if a.airlight is not None else meta["airlight"]
        a.beta = a.beta if a.beta is not None else meta["beta"]
        print(f"A = {a.airlight:.3f}, β = {a.beta:.4f}/scene unit from {meta_path} (ground truth)")
    model = mc.load_colmap_model(a.model)
    ref = model.image(a.reference)
    z = (model.points_scene_units @ ref.pose.rotation.T + ref.pose.translation_scene_units)[:, 2]
    z = z[z > 0]
    near, far = 0.75 * float(np.percentile(z, 1)), 1.5 * float(np.percentile(z, 99))
    names = model.nearest_sources(a.reference, a.sources)
    print(f"sources {names}; planes {near:.3g}…{far:.3g} scene units")
    with mc.Client(a.server, token=a.token) as murk:
        r = murk.mvs_depth(
            model.view(a.reference, a.images),
            [model.view(n, a.images) for n in names],
            cost_volume=a.cost_volume,
            airlight=a.airlight,
            beta_per_scene_unit=a.beta,
            near_scene_units=near,
            far_scene_units=far,
            num_planes=a.planes,
        )
    a.out.mkdir(parents=True, exist_ok=True)
    np.save(a.out / "z_depth.npy", r.z_depth)
    np.save(a.out / "confidence.npy", r.confidence)
    mc.write_exr(a.out / "z_depth.exr", r.z_depth)
    mc.write_png16(a.out / "inverse_depth.png", r.inverse_depth, 1.0 / r.far, 1.0 / r.near)
    print(
        f"job {r.job_id[:12]}: {r.cost_volume} volume, {r.num_planes} planes, "
        f"{r.compute_seconds:.2f} s; outputs in {a.out}"
    )
    gt = a.images.parent / "depth" / (Path(a.reference).stem + ".exr")
    if gt.exists():
        g = mc.read_image(gt)
        v = g > 0
        print(f"L1-rel against ground truth: {np.mean(np.abs(r.z_depth[v] - g[v]) / g[v]):.3f}")


if __name__ == "__main__":
    main()
