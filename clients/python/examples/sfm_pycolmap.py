#!/usr/bin/env python3
"""Reconstruct a `murk simulate mvs` scene with COLMAP (pycolmap) for testing murk on an SfM model.

Such a model has its own unit and pose errors, like a real capture's:

    murk simulate mvs --out scene --width 512 --height 384 --views 8 --forward-motion 0.5
    pip install pycolmap
    python sfm_pycolmap.py scene --intrinsics 400,400,256,192     # COLMAP PINHOLE fx,fy,cx,cy
    murk params --model scene/colmap/sparse/0 --images scene/images --reference view_04.png --out params

The intrinsics are fixed (given, not refined), as for a calibrated rig. `murk params` and
`murk mvs` compare with the scene's ground truth in one unit. They measure the model's scale
from its points against the ground-truth depth.
"""

import argparse
import shutil
from pathlib import Path

import pycolmap


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path, help="folder written by `murk simulate mvs`")
    ap.add_argument("--intrinsics", required=True, help="COLMAP PINHOLE fx,fy,cx,cy (pixels)")
    a = ap.parse_args()
    out = a.scene / "colmap"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir()
    db = out / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = a.intrinsics
    pycolmap.extract_features(
        db, a.scene / "images", camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader
    )
    pycolmap.match_exhaustive(db)
    options = pycolmap.IncrementalPipelineOptions()
    options.ba_refine_focal_length = False
    options.ba_refine_principal_point = False
    models = pycolmap.incremental_mapping(db, a.scene / "images", out, options=options)
    for i, model in models.items():
        folder = out / "sparse" / str(i)
        folder.mkdir(parents=True, exist_ok=True)
        model.write_text(str(folder))
        print(f"model {i}: {model.num_reg_images()} images, {model.num_points3D()} points -> {folder}")


if __name__ == "__main__":
    main()
