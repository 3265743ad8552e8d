"""Each script in examples/ runs against the server on `murk simulate` output and writes its files."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from .conftest import MurkServer

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def run_example(script: str, server: MurkServer, *args: str) -> str:
    done = subprocess.run(
        [sys.executable, str(EXAMPLES / script), *args, "--server", server.url],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_tof_example(server: MurkServer, tof_scene: Path, tmp_path: Path) -> None:
    out = run_example("tof_depth.py", server, str(tof_scene), "--out", str(tmp_path))
    assert "median range error" in out
    assert np.load(tmp_path / "range_m.npy").shape == (53, 64)
    assert (tmp_path / "z_depth_m.exr").exists() and (tmp_path / "range_m.png").exists()


def test_mvs_example(server: MurkServer, mvs_scene: Path, tmp_path: Path) -> None:
    out = run_example(
        "mvs_depth.py",
        server,
        str(mvs_scene / "sparse"),
        str(mvs_scene / "images"),
        "view_02.png",
        "--planes",
        "48",
        "--out",
        str(tmp_path),
    )
    l1_rel = float(out.rsplit("L1-rel against ground truth:", 1)[1])
    assert l1_rel < 0.2, out
    assert np.load(tmp_path / "z_depth.npy").shape == (72, 96)


def test_params_example(server: MurkServer, mvs_scene: Path, tmp_path: Path) -> None:
    run_example(
        "scattering_params.py",
        server,
        str(mvs_scene / "sparse"),
        str(mvs_scene / "images"),
        "view_02.png",
        "--airlight-source",
        "dark_channel",
        "--out",
        str(tmp_path),
    )
    params = json.loads((tmp_path / "params.json").read_text())
    assert 0 < params["airlight"] <= 1 and params["beta_per_scene_unit"] > 0 and params["search"]
    # The model's observations went with the request: the poses' share is reported with them.
    pose = params["pose_error"]
    assert pose is None or pose["observations"] > 0, pose


@pytest.mark.parametrize("script", ["photometric_stereo.py"])
def test_ps_example(server: MurkServer, ps_scene: Path, tmp_path: Path, script: str) -> None:
    out = run_example(script, server, str(ps_scene), "--out", str(tmp_path))
    err = float(out.rsplit("mean angular error:", 1)[1].strip().rstrip("°"))
    assert err < 10.0, out
    assert np.load(tmp_path / "normals.npy").shape == (48, 48, 3)
