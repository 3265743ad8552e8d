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

# SIFT's difference-of-Gaussians peak threshold. COLMAP's default (0.02 / 3) finds few features in
# the low contrast of haze; on the simulator's hazy scenes that left a few hundred points and
# poses that were sometimes wrong by tens of degrees with a sub-pixel reprojection error.
PEAK_THRESHOLD = 0.02 / 3


def reconstruct(
    scene: Path, intrinsics: str, peak_threshold: float = PEAK_THRESHOLD, quiet: bool = False
) -> list[tuple[Path, int]]:
    """COLMAP models of `scene/images` in `scene/colmap/sparse/<i>`: (folder, number of points) each."""
    if quiet:
        pycolmap.logging.minloglevel = 2
    out = scene / "colmap"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir()
    db = out / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = intrinsics
    # One thread and fixed seeds everywhere: the same images give the same model on every run.
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.peak_threshold = peak_threshold
    extraction.num_threads = 1
    pycolmap.extract_features(
        db,
        scene / "images",
        camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=reader,
        extraction_options=extraction,
    )
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = 1
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = 0
    verification.ransac.num_threads = 1
    pycolmap.match_exhaustive(db, matching_options=matching, verification_options=verification)
    options = pycolmap.IncrementalPipelineOptions()
    options.ba_refine_focal_length = False
    options.ba_refine_principal_point = False
    options.num_threads = 1
    options.random_seed = 0
    models = pycolmap.incremental_mapping(db, scene / "images", out, options=options)
    written = []
    for i, model in models.items():
        folder = out / "sparse" / str(i)
        folder.mkdir(parents=True, exist_ok=True)
        model.write_text(str(folder))
        written.append((folder, model.num_points3D()))
        if not quiet:
            print(f"model {i}: {model.num_reg_images()} images, {model.num_points3D()} points -> {folder}")
    return written


def written_models(scene: Path) -> list[tuple[Path, int]]:
    """The models an earlier `reconstruct` of `scene` wrote, as it returned them: (folder, number of
    points) each."""
    out = []
    for folder in sorted((scene / "colmap" / "sparse").glob("*")):
        points = folder / "points3D.txt"
        if points.exists():
            lines = points.read_text().splitlines()
            out.append((folder, sum(1 for ln in lines if ln and not ln.startswith("#"))))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path, help="folder written by `murk simulate mvs`")
    ap.add_argument("--intrinsics", required=True, help="COLMAP PINHOLE fx,fy,cx,cy (pixels)")
    ap.add_argument("--peak-threshold", type=float, default=PEAK_THRESHOLD, help="SIFT peak threshold")
    a = ap.parse_args()
    reconstruct(a.scene, a.intrinsics, a.peak_threshold)


if __name__ == "__main__":
    main()
