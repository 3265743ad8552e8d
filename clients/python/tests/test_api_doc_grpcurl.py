"""The grpcurl sessions of docs/api.md, run with bash exactly as written against a real server.

grpcurl itself is used when it is installed; otherwise tests/tools/grpcurl, a stand-in with the
same flags and the same proto3 JSON mapping, takes its place (see its docstring)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from .conftest import REPO, MurkServer, murk_binary

TOOLS = Path(__file__).resolve().parent / "tools"
API_DOC = REPO / "docs" / "api.md"


def sessions() -> list[str]:
    text = API_DOC.read_text()
    return re.findall(r"<!-- grpcurl-session -->\n```sh\n(.*?)```", text, flags=re.S)


def test_api_doc_grpcurl_sessions_run(server: MurkServer, tmp_path: Path) -> None:
    blocks = sessions()
    assert len(blocks) == 4, f"one session per method expected in {API_DOC}"
    if shutil.which("jq") is None:
        pytest.skip("SKIPPED: jq not installed")
    script = "\n".join(blocks).replace("ADDR=127.0.0.1:50051", f"ADDR={server.addr}", 1)
    assert f"ADDR={server.addr}" in script
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "murk").symlink_to(murk_binary())
    if shutil.which("grpcurl") is None:
        shim = bin_dir / "grpcurl"
        shim.write_text(f'#!/bin/sh\nexec "{sys.executable}" "{TOOLS / "grpcurl"}" "$@"\n')
        shim.chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}"}
    done = subprocess.run(
        ["bash", "-euo", "pipefail", "-c", script],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, f"stdout:\n{done.stdout}\nstderr:\n{done.stderr}"
    out = done.stdout
    # Each watch ends SUCCEEDED; the estimates, the plane set and the chunk header are printed.
    assert out.count('"state":"JOB_STATE_SUCCEEDED"') >= 3, out
    assert '"costVolume":"COST_VOLUME_KIND_DEHAZING"' in out and '"numPlanes":64' in out
    assert '"identifiable":true' in out and '"betaSource":"BETA_SOURCE_JOINT_FIT"' in out
    assert '"totalBytes"' in out and "refused, as expected" in out
    assert "request.photometric_stereo.lights" in done.stderr, done.stderr
