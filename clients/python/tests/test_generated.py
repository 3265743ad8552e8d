"""The checked-in protobuf/gRPC modules match a fresh generation from ../../proto."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent.parent


def test_generated_code_matches_the_protos() -> None:
    for module in ("grpc_tools", "mypy_protobuf"):
        if importlib.util.find_spec(module) is None:
            pytest.skip(f"SKIPPED: {module} not installed (pip install './clients/python[dev]')")
    sys.path.insert(0, str(HERE))
    try:
        import generate_protos
    finally:
        sys.path.remove(str(HERE))
    drift = generate_protos.check()
    assert not drift, (
        "src/murk_client/_proto is stale; run `python clients/python/generate_protos.py`:\n"
        + "\n".join(drift)
    )
