#!/usr/bin/env python3
"""How sampling a point's intensity at SfM keypoints biases β, with the geometry exact.

The scattering-parameter fits compare a point's intensity in the reference and in a source and
read the difference as haze. This experiment isolates how the point is *sampled*: it takes the
keypoints that COLMAP matched in the reference view of scenes made by `params_colmap_survey.py`,
places each exactly on the true surface (ground-truth depth, true poses), and fits β through
`ln((I_r − A)/(I_s − A)) = β (z_s − z_r)` at the true A (Tukey IRLS through the origin), so that
neither pose errors nor the airlight enter. The same number of random surface points is the
control. Three ways of sampling:

- `pixel`: one Gaussian blur of σ for every view, the reference read at the keypoint's pixel
  centre, the source bilinearly at the projection;
- `subpixel`: the same, the reference read at the keypoint's sub-pixel position;
- `footprint`: each view blurred so that both cover the same patch of surface (murk's
  `params::footprint`), read at the sub-pixel positions.

    python params_colmap_survey.py --murk ../../../target/release/murk --out /tmp/survey \\
        --seeds 700-719 --width 512 --height 384 --views 7
    python keypoint_sampling.py /tmp/survey/seed7* --sigmas 1,2,3

Prints β's relative error per scene, mode and point set, then the mean over the scenes.
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pycolmap

from murk_client import read_image

sys.path.insert(0, str(Path(__file__).resolve().parent))
from params_colmap_survey import read_exr_depth, read_poses  # noqa: E402

# The image's own blur, pixels (murk's PIXEL_PSF_SIGMA_PX).
PIXEL_PSF = 0.5
MODES = ("pixel", "subpixel", "footprint")


def blur(img: np.ndarray, sigma: float) -> np.ndarray:
    """Separable Gaussian blur, borders replicated."""
    if sigma <= 0:
        return img
    r = int(np.ceil(4 * sigma))
    x = np.arange(-r, r + 1)
    k = np.exp(-(x**2) / (2 * sigma * sigma))
    k /= k.sum()
    pad = np.pad(img, ((r, r), (r, r), (0, 0)), mode="edge")
    rows = sum(k[i] * pad[i : i + img.shape[0]] for i in range(2 * r + 1))
    return sum(k[i] * rows[:, i : i + img.shape[1]] for i in range(2 * r + 1))


def bilinear(img: np.ndarray, u: float, v: float) -> np.ndarray | None:
    """Bilinear sample at (u, v), pixel centres at integers; None outside."""
    h, w = img.shape[:2]
    if not (0 <= u < w - 1 and 0 <= v < h - 1):
        return None
    x0, y0 = int(u), int(v)
    fx, fy = u - x0, v - y0
    top = (1 - fx) * img[y0, x0] + fx * img[y0, x0 + 1]
    bottom = (1 - fx) * img[y0 + 1, x0] + fx * img[y0 + 1, x0 + 1]
    return (1 - fy) * top + fy * bottom


def local_blur(img: np.ndarray, u: float, v: float, sigma: float) -> np.ndarray | None:
    """The image blurred by `sigma` around (u, v), sampled there."""
    r = int(4 * sigma) + 4
    r0, c0 = int(v), int(u)
    h, w = img.shape[:2]
    if not (r <= r0 < h - r - 1 and r <= c0 < w - r - 1):
        return None
    patch = blur(img[r0 - r : r0 + r + 2, c0 - r : c0 + r + 2], sigma)
    return bilinear(patch, u - c0 + r, v - r0 + r)


def fit_beta(eqs: list[tuple[float, float]]) -> float:
    """β of y = β x through the origin, Tukey IRLS from least squares."""
    if len(eqs) < 20:
        return float("nan")
    x, y = np.array(eqs).T
    b = (x @ y) / (x @ x)
    for _ in range(30):
        r = y - b * x
        s = 1.4826 * np.median(np.abs(r)) + 1e-12
        t = np.clip(np.abs(r) / (4.685 * s), 0, 1)
        wgt = (1 - t * t) ** 2
        b = (wgt * x) @ y / ((wgt * x) @ x)
    return float(b)


def scene_errors(scene: Path, sigmas: list[float]) -> dict[tuple[float, str, str], float]:
    """β's relative error per (σ, point set, mode) on one scene."""
    meta = json.loads((scene / "meta.json").read_text())
    ref, f = meta["reference"], meta["config"]["focal_px"]
    w, h = meta["config"]["width"], meta["config"]["height"]
    cx, cy = w / 2 - 0.5, h / 2 - 0.5  # pixel centres at integers
    a, beta = meta["airlight"], meta["beta"]
    truth = read_poses(scene / "sparse" / "images.txt")
    centre = {n: -r.T @ t for n, (r, t) in truth.items()}
    sources = sorted((n for n in truth if n != ref), key=lambda n: np.linalg.norm(centre[n] - centre[ref]))[
        :4
    ]
    images = {n: np.asarray(read_image(scene / "images" / n), dtype=np.float64) for n in [ref, *sources]}
    depth = read_exr_depth(scene / "depth" / (Path(ref).stem + ".exr"))
    models = [pycolmap.Reconstruction(str(p)) for p in (scene / "colmap" / "sparse").iterdir()]
    rec = max(models, key=lambda m: m.num_points3D())
    ref_image = next(im for im in rec.images.values() if im.name == ref)
    # COLMAP puts pixel centres at +0.5.
    keypoints = [(p.xy[0] - 0.5, p.xy[1] - 0.5) for p in ref_image.points2D if p.has_point3D()]
    rng = np.random.default_rng(1)
    random_points = [(rng.uniform(5, w - 6), rng.uniform(5, h - 6)) for _ in keypoints]
    r_ref, t_ref = truth[ref]
    out = {}
    for sigma in sigmas:
        blurred = {n: blur(im, sigma) for n, im in images.items()}
        for label, points in (("keypoints", keypoints), ("random", random_points)):
            for mode in MODES:
                eqs = []
                for u, v in points:
                    if mode == "pixel":
                        u, v = round(u), round(v)
                    row, col = int(round(v)), int(round(u))
                    if not (0 <= row < h and 0 <= col < w):
                        continue
                    z = float(depth[row, col])
                    world = r_ref.T @ (np.array([(u - cx) / f * z, (v - cy) / f * z, z]) - t_ref)
                    i_ref = bilinear(blurred[ref], u, v)
                    if i_ref is None:
                        continue
                    for n in sources:
                        cam = truth[n][0] @ world + truth[n][1]
                        us, vs = f * cam[0] / cam[2] + cx, f * cam[1] / cam[2] + cy
                        if mode == "footprint":
                            # The same patch of surface: the source's σ scaled by z_r / z_s.
                            scaled = (sigma**2 + PIXEL_PSF**2) * (z / cam[2]) ** 2 - PIXEL_PSF**2
                            i_src = local_blur(images[n], us, vs, np.sqrt(max(scaled, 0.0)))
                        else:
                            i_src = bilinear(blurred[n], us, vs)
                        if i_src is None:
                            continue
                        for dr, ds in zip(i_ref - a, i_src - a, strict=True):
                            if dr * ds > 0 and abs(dr) > 0.05 and abs(ds) > 0.05:
                                eqs.append((cam[2] - z, np.log(dr / ds)))
                out[(sigma, label, mode)] = fit_beta(eqs) / beta - 1
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", type=Path, nargs="+", help="scene folders of params_colmap_survey.py")
    ap.add_argument("--sigmas", default="1,2,3", help="blur σ in pixels, comma-separated")
    a = ap.parse_args()
    sigmas = [float(s) for s in a.sigmas.split(",")]
    results = []
    for scene in a.scenes:
        if not (scene / "colmap" / "sparse").is_dir():
            continue
        try:
            errors = scene_errors(scene, sigmas)
        except StopIteration:
            continue  # the reference view did not register
        results.append(errors)
        cells = " ".join(f"{k[0]:g}/{k[1][:3]}/{k[2]}:{v:+.3f}" for k, v in errors.items())
        print(f"{scene.name} {cells}")
    print(f"\nβ's relative error, mean (median) over {len(results)} scenes:")
    for key in results[0] if results else []:
        vals = [r[key] for r in results]
        mean, median = np.nanmean(vals), np.nanmedian(vals)
        print(f"sigma {key[0]:g} px, {key[1]:9s} {key[2]:9s} {mean:+.3f} ({median:+.3f})")


if __name__ == "__main__":
    main()
