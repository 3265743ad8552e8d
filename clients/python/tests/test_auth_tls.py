"""Bearer tokens and TLS (server-authenticated and mutual) as the server offers them."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

import murk_client as mc
from murk_client import Client, RetryPolicy

from .conftest import ServerFactory, optional_tool


def make_pki(d: Path) -> dict[str, Path]:
    """A throw-away CA, a server certificate for localhost and a client certificate (openssl)."""
    if optional_tool("openssl") is None:
        pytest.skip("SKIPPED: openssl not installed")

    def run(*args: str) -> None:
        subprocess.run(["openssl", *args], check=True, capture_output=True, cwd=d)

    run(
        "req",
        "-x509",
        "-newkey",
        "rsa:2048",
        "-nodes",
        "-keyout",
        "ca.key",
        "-out",
        "ca.pem",
        "-days",
        "2",
        "-subj",
        "/CN=murk test CA",
    )
    for name, subject, ext in (
        ("server", "/CN=localhost", "subjectAltName=DNS:localhost,IP:127.0.0.1"),
        ("client", "/CN=drone-17", "extendedKeyUsage=clientAuth"),
    ):
        run(
            "req",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-keyout",
            f"{name}.key",
            "-out",
            f"{name}.csr",
            "-subj",
            subject,
        )
        (d / f"{name}.ext").write_text(ext + "\n")
        run(
            "x509",
            "-req",
            "-in",
            f"{name}.csr",
            "-CA",
            "ca.pem",
            "-CAkey",
            "ca.key",
            "-CAcreateserial",
            "-out",
            f"{name}.pem",
            "-days",
            "2",
            "-extfile",
            f"{name}.ext",
        )
    return {n: d / n for n in ("ca.pem", "server.pem", "server.key", "client.pem", "client.key")}


def tokens_file(d: Path) -> Path:
    path = d / "tokens"
    path.write_text("alpha tok-alpha-0123456789abcdef\nbeta tok-beta-0123456789abcdef\n")
    return path


def small_request(tof_scene: Path) -> mc.pb.JobRequest:
    f = mc.load_tof_frame(tof_scene)
    return mc.tof_depth_request(
        f.amplitude, f.phase, modulation_frequency_hz=16e6, options={"fine_iterations": 3}
    )


def test_tokens_over_tls(start_server: ServerFactory, tmp_path: Path, tof_scene: Path) -> None:
    pki = make_pki(tmp_path)
    s = start_server(
        "--auth-tokens-file",
        str(tokens_file(tmp_path)),
        "--tls-cert",
        str(pki["server.pem"]),
        "--tls-key",
        str(pki["server.key"]),
    )
    port = s.addr.rsplit(":", 1)[1]
    ca = pki["ca.pem"].read_bytes()
    no_retry = RetryPolicy.never()
    with Client(
        f"https://localhost:{port}", root_certificates=ca, token="tok-alpha-0123456789abcdef"
    ) as alpha:
        job_id = alpha.submit(small_request(tof_scene))
        assert alpha.wait(job_id).state == mc.JobState.SUCCEEDED
        assert isinstance(alpha.result(job_id), mc.TofDepthResult)
    # Another tenant does not see alpha's job.
    with Client(
        f"localhost:{port}", root_certificates=ca, token="tok-beta-0123456789abcdef", retry=no_retry
    ) as beta:
        with pytest.raises(mc.NotFound):
            beta.job(job_id)
    with Client(f"https://localhost:{port}", root_certificates=ca, token="wrong", retry=no_retry) as bad:
        with pytest.raises(mc.Unauthenticated):
            bad.job(job_id)
    with Client(f"https://localhost:{port}", root_certificates=ca, retry=no_retry) as anonymous:
        with pytest.raises(mc.Unauthenticated):
            anonymous.submit(small_request(tof_scene))
    # Plaintext to a TLS port fails as unavailable (no silent downgrade).
    with Client(
        f"http://localhost:{port}", token="tok-alpha-0123456789abcdef", retry=no_retry, timeout_s=5
    ) as plain:
        with pytest.raises(mc.Unavailable):
            plain.job(job_id)


def test_mutual_tls(start_server: ServerFactory, tmp_path: Path, tof_scene: Path) -> None:
    pki = make_pki(tmp_path)
    s = start_server(
        "--tls-cert",
        str(pki["server.pem"]),
        "--tls-key",
        str(pki["server.key"]),
        "--tls-client-ca",
        str(pki["ca.pem"]),
    )
    port = s.addr.rsplit(":", 1)[1]
    ca = pki["ca.pem"].read_bytes()
    with Client(
        f"https://localhost:{port}",
        root_certificates=ca,
        private_key=pki["client.key"].read_bytes(),
        certificate_chain=pki["client.pem"].read_bytes(),
    ) as c:
        job_id = c.submit(small_request(tof_scene))
        assert c.wait(job_id).state == mc.JobState.SUCCEEDED
    with Client(
        f"https://localhost:{port}", root_certificates=ca, retry=RetryPolicy.never(), timeout_s=5
    ) as anonymous:
        with pytest.raises(mc.Unavailable):  # the handshake fails: no client certificate
            anonymous.job(job_id)
