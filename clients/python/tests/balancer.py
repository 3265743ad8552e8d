"""A throw-away nginx in front of test replicas, running the project's own ``deploy/nginx.conf``
with only the deployment-specific parts rewritten: the listen address (a free loopback port),
the upstream servers (the replicas' addresses instead of Docker's ``murk`` name) and the file
paths (a temporary directory, so no root is needed). The Rust service tests do the same
(``crates/murk-server/tests/service/common/nginx.rs``)."""

from __future__ import annotations

import shutil
import socket
import subprocess
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[3]


def free_port() -> int:
    """A loopback port nothing listens on (at the time of asking)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _rewrite(text: str, replaced: list[tuple[str, str]]) -> str:
    for old, new in replaced:
        # A deploy file that no longer has a line this rewrites would silently test another
        # configuration than the shipped one.
        assert old in text, f"deploy/nginx.conf no longer contains `{old}`: update tests/balancer.py"
        text = text.replace(old, new, 1)
    return text


class Nginx:
    """nginx (one foreground process) balancing over ``upstreams`` (``host:port``)."""

    def __init__(self, upstreams: list[str], tmp: Path) -> None:
        binary = shutil.which("nginx") or next(
            (p for p in ("/usr/sbin/nginx", "/usr/local/sbin/nginx") if Path(p).is_file()), None
        )
        if binary is None:
            pytest.skip("SKIPPED: nginx is not installed (apt-get install nginx); .ci/run installs it")
        self.port = free_port()
        servers = "".join(f"server {u};\n        " for u in upstreams)
        temp_paths = "".join(
            f"\n    {kind}_temp_path {tmp}/{kind};"
            for kind in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi")
        )
        conf = _rewrite(
            (REPO / "deploy" / "nginx.conf").read_text(),
            [
                ("pid /tmp/nginx.pid;", f"pid {tmp}/nginx.pid;"),
                ("server murk:50051;", servers),
                ("listen 50051 http2;", f"listen 127.0.0.1:{self.port} http2;"),
                ("include /etc/murk/tls/*.conf;", f"include {tmp}/tls/*.conf;"),
                ("http {", "http {" + temp_paths),
            ],
        )
        path = tmp / "nginx.conf"
        path.write_text(conf)
        # -e: the compiled-in error log (/var/log/nginx) may not be writable; one foreground
        # process as the invoking user, with no privilege drop to a user that could not write tmp.
        self.proc = subprocess.Popen(
            [
                binary,
                "-e",
                "stderr",
                "-p",
                str(tmp),
                "-c",
                str(path),
                "-g",
                "daemon off; master_process off;",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        deadline = time.monotonic() + 10
        while True:
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=1).close()
                break
            except OSError:
                if self.proc.poll() is not None:
                    assert self.proc.stderr is not None
                    raise RuntimeError("nginx exited at start:\n" + self.proc.stderr.read()) from None
                if time.monotonic() > deadline:
                    raise RuntimeError("nginx did not come up") from None
                time.sleep(0.02)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def stop(self) -> None:
        self.proc.kill()
        self.proc.wait()
