"""The thread backend bounds no job's memory (docs/security.md, "Scene checks at submit"), so
`renderloop serve` refuses it on a non-loopback address unless told that every submitter is
trusted (`--trust-uploads`)."""
from __future__ import annotations

import httpx

from cli_server import CliServer
from service_harness import renderloop_cli


def test_serve_refuses_the_thread_backend_on_a_public_address_without_trust_uploads(tmp_path):
    result = renderloop_cli("serve", "--host", "0.0.0.0", "--port", "1", "--concurrency", "1", "--insecure-no-auth",
                            "--data-dir", str(tmp_path / "data"))
    assert result.returncode == 2, result.stderr
    assert result.stderr.startswith("renderloop: error: --concurrency") and "--trust-uploads" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr


def test_serve_with_trust_uploads_runs_the_thread_backend_on_a_public_address(tmp_path):
    server = CliServer(tmp_path / "data", tmp_path / "serve.log", ["--host", "0.0.0.0", "--trust-uploads",
                                                                   "--insecure-no-auth"]).start()
    try:
        assert httpx.get(server.url + "/healthz", timeout=30).status_code == 200
    finally:
        server.stop()
