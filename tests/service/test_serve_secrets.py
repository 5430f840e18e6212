"""Secrets stay out of `ps` and out of logs: `renderloop serve --token-file`, the warning on
`--token`, and uvicorn's access log with `token=`/`sig=` redacted (service/api/edge.py)."""
from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Iterator

import httpx
import pytest

from cli_server import CliServer
from service.cli import CliError, build_parser, serve_security
from service.api.signing import UrlSigner
from service_harness import renderloop_clis

TOKEN = "file-token-7c1e2b"


def token_file(folder: Path, mode: int = 0o600) -> Path:
    path = folder / "token"
    path.write_text(TOKEN + "\n")
    path.chmod(mode)
    return path


@pytest.fixture(scope="module")
def server(tmp_path_factory) -> Iterator[CliServer]:
    root = tmp_path_factory.mktemp("secrets")
    server = CliServer(root / "data", root / "server.log", ["--token-file", str(token_file(root))]).start()
    yield server
    server.stop()


def proc_text(pid: int, name: str) -> str:
    return Path(f"/proc/{pid}/{name}").read_bytes().replace(b"\0", b" ").decode(errors="replace")


def test_the_token_file_is_the_token_and_the_token_is_not_in_the_process_command_line(server):
    assert TOKEN not in proc_text(server.process.pid, "cmdline")
    assert TOKEN not in proc_text(server.process.pid, "environ")
    assert httpx.get(server.url + "/jobs", timeout=30).status_code == 401
    assert httpx.get(server.url + "/jobs", headers={"Authorization": f"Bearer {TOKEN}"}, timeout=30).status_code == 200


def test_the_access_log_never_shows_the_token_or_a_signature(server):
    expires, signature = UrlSigner.from_token(TOKEN).sign("no-such-job")
    with httpx.Client(base_url=server.url, timeout=30) as client:
        assert client.get("/jobs/no-such-job/preview", params={"token": TOKEN}).status_code == 401
        signed = client.get("/jobs/no-such-job/preview", params={"layer": "noisy", "exp": expires, "sig": signature})
        assert signed.status_code == 404  # past the guard: the signature was good
        client.get("/jobs", params={"limit": 5, "token": TOKEN})
    deadline = time.monotonic() + 30
    while server.log().count("token=***") < 2:
        assert time.monotonic() < deadline, f"the requests were not logged:\n{server.log()}"
        time.sleep(0.2)
    log = server.log()
    assert TOKEN not in log and signature not in log
    assert "sig=***" in log and "layer=noisy" in log  # redacted, not dropped


def test_token_on_the_command_line_warns_that_ps_shows_it(tmp_path):
    (tmp_path / "empty").write_text("\n")
    # --max-bundle-mb 0 stops the command right after the token is read, before it serves.
    result, shared, missing, empty = renderloop_clis(
        ["serve", "--token", TOKEN, "--max-bundle-mb", "0"],
        ["serve", "--token-file", str(token_file(tmp_path, 0o644)), "--max-bundle-mb", "0"],
        ["serve", "--token-file", str(tmp_path / "missing")],
        ["serve", "--token-file", str(tmp_path / "empty")])
    assert result.returncode == 2 and "--token is visible" in result.stderr and "--token-file" in result.stderr
    assert "readable by other users" in shared.stderr and TOKEN not in shared.stderr + shared.stdout
    assert missing.returncode == 2 and "token file" in missing.stderr and "Traceback" not in missing.stderr
    assert empty.returncode == 2 and "is empty" in empty.stderr


def test_the_token_file_can_come_from_the_environment(tmp_path, monkeypatch):
    """$RENDERLOOP_TOKEN_FILE gives `renderloop serve` its token as --token-file does: the serve
    command's security settings (serve_security, which the serve handler hands the server) carry
    the file's token. That a server enforces the token it is given is the module server's test
    above; a second server started only for this cost a `renderloop serve` start-up."""
    monkeypatch.delenv("RENDERLOOP_TOKEN", raising=False)
    monkeypatch.setenv("RENDERLOOP_TOKEN_FILE", str(token_file(tmp_path)))
    assert serve_security(build_parser().parse_args(["serve"])).token == TOKEN
    monkeypatch.setenv("RENDERLOOP_TOKEN_FILE", str(tmp_path / "missing"))
    with pytest.raises(CliError, match="token file"):
        serve_security(build_parser().parse_args(["serve"]))
