"""The shipped observability files against a real Prometheus scraping a real murk: the scrape
configuration, the alert rules (loaded and evaluated without error, and their unit tests), and
every query of the Grafana dashboard, which must return data after a few jobs and a session.

Uses the ``prometheus`` and ``promtool`` binaries (Debian's ``prometheus`` package; .ci/run
installs it) and ``redis-server`` for the Redis panel; skips with the reason when they are
missing. Grafana itself is not run here: its provisioning files are plain YAML and JSON, and what
matters in them, the queries, are evaluated by Prometheus."""

from __future__ import annotations

import json
import re
import shutil
import socket
import subprocess
import time
import urllib.parse
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml

import murk_client as mc
from murk_client import Client, RetryPolicy

from .balancer import free_port
from .conftest import REPO, MurkServer

OBSERVABILITY = REPO / "deploy" / "observability"


def _tool(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        pytest.skip(f"SKIPPED: {name} is not installed (apt-get install prometheus); .ci/run installs it")
    return path


def test_the_alert_rules_pass_their_unit_tests() -> None:
    promtool = _tool("promtool")
    for args in (["check", "rules", "alerts.yml"], ["test", "rules", "alerts.test.yml"]):
        run = subprocess.run([promtool, *args], cwd=OBSERVABILITY, capture_output=True, text=True)
        assert run.returncode == 0, run.stdout + run.stderr


def test_the_dashboard_has_a_panel_for_each_figure_an_operator_needs() -> None:
    dashboard = json.loads((OBSERVABILITY / "grafana" / "dashboards" / "murk.json").read_text())
    exprs = " ".join(t["expr"] for p in dashboard["panels"] for t in p["targets"])
    for metric in (
        "murk_queue_depth",
        "murk_jobs_total",
        "murk_job_duration_seconds_bucket",
        "murk_queue_wait_seconds_bucket",
        "murk_cache_hits_total",
        "murk_tenant_requests_total",
        "murk_redis_up",
        "murk_sessions_open",
        "murk_session_frames_total",
        "murk_session_frame_latency_seconds_bucket",
    ):
        assert metric in exprs, metric
    datasource = (OBSERVABILITY / "grafana" / "provisioning" / "datasources" / "prometheus.yml").read_text()
    assert all(p["datasource"]["uid"] == "prometheus" for p in dashboard["panels"])
    assert "uid: prometheus" in datasource


class _Prometheus:
    """``prometheus`` on a free port with the shipped configuration, its Docker DNS discovery
    replaced by the test replica's address and the intervals shortened."""

    def __init__(self, tmp: Path, metrics_addr: str) -> None:
        binary = _tool("prometheus")
        config = (OBSERVABILITY / "prometheus.yml").read_text()
        replaced = [
            ("scrape_interval: 15s", "scrape_interval: 1s"),
            ("evaluation_interval: 15s", "evaluation_interval: 1s"),
            ("/etc/prometheus/alerts.yml", str(OBSERVABILITY / "alerts.yml")),
        ]
        for old, new in replaced:
            assert old in config, f"deploy/observability/prometheus.yml no longer has `{old}`"
            config = config.replace(old, new, 1)
        dns = re.search(r"    dns_sd_configs:\n(      .*\n)+", config)
        assert dns, "deploy/observability/prometheus.yml no longer discovers the replicas by DNS"
        config = config.replace(dns.group(0), f"    static_configs:\n      - targets: ['{metrics_addr}']\n")
        (tmp / "prometheus.yml").write_text(config)
        self.port = free_port()
        self.proc = subprocess.Popen(
            [
                binary,
                f"--config.file={tmp / 'prometheus.yml'}",
                f"--storage.tsdb.path={tmp / 'data'}",
                f"--web.listen-address=127.0.0.1:{self.port}",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )

    def get(self, path: str, **params: str) -> dict:  # type: ignore[type-arg]
        url = f"http://127.0.0.1:{self.port}{path}"
        if params:
            url += "?" + urllib.parse.urlencode(params)
        with urllib.request.urlopen(url, timeout=5) as r:
            body: dict = json.loads(r.read())  # type: ignore[type-arg]
        assert body["status"] == "success", body
        return body["data"]  # type: ignore[no-any-return]

    def wait_until(self, what: str, ready: Callable[[], bool], timeout_s: float = 60.0) -> None:
        """Polls ``ready`` (Prometheus scrapes on its own clock, so this waits for its next
        scrape or evaluation), bounded by ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                if ready():
                    return
            except OSError:
                pass  # not listening yet
            if self.proc.poll() is not None:
                assert self.proc.stderr is not None
                raise AssertionError("prometheus exited:\n" + self.proc.stderr.read()[-3000:])
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out waiting for {what}")
            time.sleep(0.25)

    def stop(self) -> None:
        self.proc.kill()
        self.proc.wait()


@pytest.fixture()
def redis_url(tmp_path: Path) -> Iterator[str]:
    binary = shutil.which("redis-server")
    if binary is None:
        pytest.skip(
            "SKIPPED: redis-server is not installed (apt-get install redis-server); .ci/run installs it"
        )
    port = free_port()
    proc = subprocess.Popen(
        [binary, "--bind", "127.0.0.1", "--port", str(port), "--save", "", "--dir", str(tmp_path)],
        stdout=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 10
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            break
        except OSError:
            assert time.monotonic() < deadline, "redis-server did not come up"
            time.sleep(0.02)
    yield f"redis://127.0.0.1:{port}/0"
    proc.kill()
    proc.wait()


def test_every_dashboard_query_returns_data_from_a_real_prometheus(
    workdir: Path, tmp_path: Path, tof_scene: Path, redis_url: str
) -> None:
    metrics_addr = f"127.0.0.1:{free_port()}"
    token = "obs-token-0123456789abcdef"
    tokens = tmp_path / "tokens"
    tokens.write_text(f"fleet-a {token}\n")
    server = MurkServer(
        ["--metrics-addr", metrics_addr, "--auth-tokens-file", str(tokens), "--redis-url", redis_url], workdir
    )
    prometheus = _Prometheus(tmp_path, metrics_addr)
    try:

        def murk_target_up() -> bool:
            targets = prometheus.get("/api/v1/targets")["activeTargets"]
            return any(t["labels"]["job"] == "murk" and t["health"] == "up" for t in targets)

        # Scraping before the work, so that the rates see it happen.
        prometheus.wait_until("the murk target to be up", murk_target_up)

        frame = mc.load_tof_frame(tof_scene)
        kwargs = {
            "modulation_frequency_hz": frame.modulation_frequency_hz,
            "intrinsics": frame.intrinsics,
            "light_position_m": frame.light_position_m,
        }
        with Client(server.url, token=token, retry=RetryPolicy(max_attempts=1)) as c:
            # A job, the same job again (a cache hit), a refused request, and a session.
            c.tof_depth(frame.amplitude, frame.phase, **kwargs)
            c.tof_depth(frame.amplitude, frame.phase, **kwargs)
            bad_phase = frame.phase.copy()
            bad_phase[0, 0] = np.nan
            with pytest.raises(mc.InvalidArgument):
                c.tof_depth(frame.amplitude, bad_phase, **kwargs)
            h, w = frame.amplitude.shape
            config = mc.tof_session_config(width=w, height=h, **kwargs)
            outcomes = list(c.session(config, [mc.tof_frame(frame.amplitude, frame.phase) for _ in range(2)]))
            assert all(o.result is not None for o in outcomes)

        dashboard = json.loads((OBSERVABILITY / "grafana" / "dashboards" / "murk.json").read_text())
        queries = {
            f"{p['title']} / {t['legendFormat']}": t["expr"].replace("$__rate_interval", "1m")
            for p in dashboard["panels"]
            for t in p["targets"]
        }
        empty: dict[str, str] = {}

        def every_query_has_data() -> bool:
            empty.clear()
            for name, expr in queries.items():
                if not prometheus.get("/api/v1/query", query=expr)["result"]:
                    empty[name] = expr
            return not empty

        try:
            prometheus.wait_until("every dashboard query to return data", every_query_has_data)
        except AssertionError as e:
            raise AssertionError(f"{e}; still empty: {json.dumps(empty, indent=1)}") from None

        def rules_evaluated() -> bool:
            rules = [r for g in prometheus.get("/api/v1/rules")["groups"] for r in g["rules"]]
            shipped = yaml.safe_load((OBSERVABILITY / "alerts.yml").read_text())["groups"][0]["rules"]
            return len(rules) == len(shipped) and all(r["health"] == "ok" for r in rules)

        prometheus.wait_until("the alert rules to be evaluated without error", rules_evaluated)
        firing = [a["labels"]["alertname"] for a in prometheus.get("/api/v1/alerts")["alerts"]]
        assert not firing, f"a healthy replica fires {firing}"
    finally:
        prometheus.stop()
        server.stop()
