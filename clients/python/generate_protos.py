#!/usr/bin/env python3
"""Generates murk_client's protobuf/gRPC modules (and their type stubs) from ../../proto.

The generated code is checked in so that ``pip install ./clients/python`` needs no proto
compiler; ``tests/test_generated.py`` regenerates it into a temporary folder and fails when the
checked-in copy has drifted from the protos. Run after changing a .proto file::

    python clients/python/generate_protos.py          # rewrite src/murk_client/_proto
    python clients/python/generate_protos.py --check  # exit 1 when it would change anything

Needs the ``dev`` extra (grpcio-tools for protoc and its gRPC plugin, mypy-protobuf for the
``.pyi`` stubs). protoc writes ``from murk.v1 import ...``; the imports are rewritten into the
package (``from murk_client._proto.murk.v1 import ...``) so that murk_client does not claim a
top-level ``murk`` package.
"""

from __future__ import annotations

import argparse
import filecmp
import re
import shutil
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
PROTO_ROOT = HERE.parent.parent / "proto"
TARGET = HERE / "src" / "murk_client" / "_proto"
PACKAGE = "murk_client._proto"


def _rewrite_imports(text: str) -> str:
    text = re.sub(r"^from murk\.v1 import", f"from {PACKAGE}.murk.v1 import", text, flags=re.M)
    text = re.sub(r"^import murk\.v1\.", f"import {PACKAGE}.murk.v1.", text, flags=re.M)
    return re.sub(r"(?<![\w.])murk\.v1\.(\w+_pb2)\b", rf"{PACKAGE}.murk.v1.\1", text)


def generate(out: Path) -> None:
    """Writes the generated package tree under ``out`` (which must be empty or absent)."""
    import grpc_tools
    from grpc_tools import protoc  # type: ignore[import-untyped]

    protos = sorted(str(p.relative_to(PROTO_ROOT)) for p in PROTO_ROOT.rglob("*.proto"))
    if not protos:
        raise SystemExit(f"no .proto files under {PROTO_ROOT}")
    well_known = Path(grpc_tools.__file__).parent / "_proto"
    out.mkdir(parents=True, exist_ok=True)
    # mypy-protobuf's plugins sit beside the interpreter (a venv's bin/), which need not be on
    # PATH when the script runs as `venv/bin/python generate_protos.py`.
    bindir = Path(sys.executable).parent
    plugins = []
    for name in ("protoc-gen-mypy", "protoc-gen-mypy_grpc"):
        exe = shutil.which(name) or shutil.which(name, path=str(bindir))
        if exe is None:
            raise SystemExit(f"{name} not found: pip install 'murk-client[dev]' (mypy-protobuf)")
        plugins.append(f"--plugin={name}={exe}")
    args = [
        "protoc",
        *plugins,
        f"-I{PROTO_ROOT}",
        f"-I{well_known}",
        f"--python_out={out}",
        f"--grpc_python_out={out}",
        f"--mypy_out={out}",
        f"--mypy_grpc_out={out}",
        *protos,
    ]
    if protoc.main(args) != 0:
        raise SystemExit("protoc failed")
    for path in out.rglob("*.py*"):
        path.write_text(_rewrite_imports(path.read_text()))
    for pkg in [out, *(d for d in out.rglob("*") if d.is_dir())]:
        (pkg / "__init__.py").write_text('"""Generated from proto/ by generate_protos.py; do not edit."""\n')


def _differences(a: Path, b: Path) -> list[str]:
    files_a = {p.relative_to(a) for p in a.rglob("*") if p.is_file() and "__pycache__" not in p.parts}
    files_b = {p.relative_to(b) for p in b.rglob("*") if p.is_file() and "__pycache__" not in p.parts}
    diff = [f"only in checked-in copy: {p}" for p in sorted(files_a - files_b)]
    diff += [f"missing from checked-in copy: {p}" for p in sorted(files_b - files_a)]
    diff += [
        f"differs: {p}" for p in sorted(files_a & files_b) if not filecmp.cmp(a / p, b / p, shallow=False)
    ]
    return diff


def check() -> list[str]:
    """What differs between the checked-in modules and a fresh generation (empty = in sync)."""
    with tempfile.TemporaryDirectory() as tmp:
        fresh = Path(tmp) / "_proto"
        generate(fresh)
        return _differences(TARGET, fresh)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="only report drift")
    if parser.parse_args().check:
        diff = check()
        for line in diff:
            print(line)
        return 1 if diff else 0
    with tempfile.TemporaryDirectory() as tmp:
        fresh = Path(tmp) / "_proto"
        generate(fresh)
        shutil.rmtree(TARGET, ignore_errors=True)
        shutil.copytree(fresh, TARGET)
    print(f"wrote {TARGET}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
