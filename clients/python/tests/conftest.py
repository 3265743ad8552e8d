"""Fixtures: a real ``murk serve`` from the release binary, and simulated scenes to send it.

The binary is ``$MURK_BIN`` or ``target/release/murk`` of this repository (``cargo build
--release`` or ``cargo test --release`` builds it). Without it the server tests skip with the
reason, unless ``MURK_BIN`` is set (CI sets it), in which case a missing binary is an error.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from murk_client import Client, RetryPolicy

REPO = Path(__file__).resolve().parents[3]


def murk_binary() -> Path:
    env = os.environ.get("MURK_BIN")
    path = Path(env) if env else REPO / "target" / "release" / "murk"
    if not path.is_file():
        if env:
            raise FileNotFoundError(f"MURK_BIN={env} does not exist")
        pytest.skip(f"SKIPPED: no murk binary at {path} (cargo build --release, or set MURK_BIN)")
    return path


def _message(line: str) -> str | None:
    try:
        return str(json.loads(line).get("fields", {}).get("message"))
    except ValueError:
        return None


class MurkServer:
    """``murk serve`` on an ephemeral loopback port; stderr (JSON logs) kept for diagnostics."""

    def __init__(self, args: list[str], cwd: Path, addr: str = "127.0.0.1:0") -> None:
        self.args = args
        self.log: list[str] = []
        self._logged = threading.Condition()
        cmd = [str(murk_binary()), "serve", "--addr", addr, "--log-format", "json", *args]
        self.proc = subprocess.Popen(
            cmd, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
        )
        self.addr = self._wait_for_address()
        # Keep draining stderr so that a chatty server never blocks on a full pipe.
        self._drain = threading.Thread(target=self._pump, daemon=True)
        self._drain.start()

    def _wait_for_address(self) -> str:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.log.append(line)
            try:
                entry = json.loads(line)
            except ValueError:
                continue
            fields = entry.get("fields", {})
            if fields.get("message") == "murk serving":
                return str(fields["addr"])
        raise RuntimeError("murk serve exited before serving:\n" + "".join(self.log[-20:]))

    def _pump(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            with self._logged:
                self.log.append(line)
                self._logged.notify_all()

    def wait_for_log(self, message: str, timeout_s: float) -> dict | None:  # type: ignore[type-arg]
        """The fields of the first line logged with ``message``, waiting up to ``timeout_s`` for
        it (woken by each new line, not polling); None when none came."""

        def first() -> dict | None:  # type: ignore[type-arg]
            for line in self.log:
                if _message(line) == message:
                    return dict(json.loads(line)["fields"])
            return None

        with self._logged:
            return self._logged.wait_for(first, timeout=timeout_s)

    @property
    def url(self) -> str:
        return f"http://{self.addr}"

    def kill(self) -> None:
        """SIGKILL: no drain, no goodbye to clients (a crashed or OOM-killed replica)."""
        self.proc.kill()
        self.proc.wait()

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


@pytest.fixture(scope="session")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("murk")


@pytest.fixture(scope="session")
def server(workdir: Path) -> Iterator[MurkServer]:
    """One plain server for the tests that need no special configuration."""
    s = MurkServer([], workdir)
    yield s
    s.stop()


@pytest.fixture()
def start_server(workdir: Path) -> Iterator[ServerFactory]:
    """Starts servers with given flags; stops them after the test."""
    started: list[MurkServer] = []

    def start(*args: str) -> MurkServer:
        s = MurkServer(list(args), workdir)
        started.append(s)
        return s

    yield start
    for s in started:
        s.stop()


class ServerFactory:  # typing aid for the fixture above
    def __call__(self, *args: str) -> MurkServer: ...


@pytest.fixture()
def client(server: MurkServer) -> Iterator[Client]:
    with Client(server.url, retry=RetryPolicy(max_attempts=3, initial_backoff_s=0.05)) as c:
        yield c


def simulate(kind: str, out: Path, *args: str) -> Path:
    if not out.exists():
        subprocess.run(
            [str(murk_binary()), "simulate", kind, "--out", str(out), *args],
            check=True,
            capture_output=True,
        )
    return out


@pytest.fixture(scope="session")
def tof_scene(workdir: Path) -> Path:
    return simulate("tof", workdir / "tof", "--width", "64", "--height", "53", "--seed", "3")


@pytest.fixture(scope="session")
def tof_scene_full(workdir: Path) -> Path:
    """The reference's full 512x424 frame: its result (~8.7 MB) exceeds gRPC's 4 MiB default."""
    return simulate("tof", workdir / "tof_full", "--seed", "5")


@pytest.fixture(scope="session")
def mvs_scene(workdir: Path) -> Path:
    return simulate("mvs", workdir / "mvs", "--width", "96", "--height", "72", "--seed", "2")


@pytest.fixture(scope="session")
def mvs_scene_rectified(workdir: Path) -> Path:
    """A rectified pair: every point at the same depth in both views, so β cannot be known."""
    return simulate(
        "mvs", workdir / "mvs_rectified", "--width", "96", "--height", "72", "--seed", "2", "--rectified-pair"
    )


@pytest.fixture(scope="session")
def mvs_scene_forward(workdir: Path) -> Path:
    """Views spread along the optical axis too: the points' depths differ between views, which
    is what determines β."""
    return simulate(
        "mvs",
        workdir / "mvs_forward",
        "--width",
        "96",
        "--height",
        "72",
        "--seed",
        "2",
        "--forward-motion",
        "0.5",
    )


@pytest.fixture(scope="session")
def ps_scene(workdir: Path) -> Path:
    return simulate("ps", workdir / "ps", "--width", "48", "--height", "48")


def read_meta(folder: Path) -> dict:  # type: ignore[type-arg]
    return json.loads((folder / "meta.json").read_text())


def optional_tool(name: str) -> str | None:
    from shutil import which

    return which(name)
