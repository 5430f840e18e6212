"""`renderloop status|cancel|download|delete ID` as real subprocesses against a real server that
needs a token: the happy path of each, and one `renderloop: error:` line with exit 2 for an
unknown id, a refused token and a server that is not there."""
from __future__ import annotations

import json
import time

import httpx
import numpy as np
import pytest

from service.exr import read_exr
from service_harness import free_port, renderloop_cli as renderloop

TOKEN = "verbs-test-token"
SERVER_ENV = {"RENDERLOOP_TOKEN": TOKEN}


@pytest.fixture(scope="module")
def server(module_server):
    return module_server


@pytest.fixture(scope="module")
def token_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("secrets") / "token"
    path.write_text(TOKEN + "\n")
    path.chmod(0o600)
    return path


def cli(server, token_file, *args: str):
    return renderloop(*args, "--server", server.url, "--token-file", str(token_file))


def test_status_download_and_delete_a_finished_job(server, token_file, tmp_path):
    submitted = cli(server, token_file, "submit", "cornell-box", "--width", "16", "--height", "12", "--spp", "4",
                    "--name", "box", "--wait")
    assert submitted.returncode == 0, submitted.stderr
    job_id = submitted.stdout.splitlines()[0]

    status = cli(server, token_file, "status", job_id)
    assert status.returncode == 0, status.stderr
    record = json.loads(status.stdout)
    assert (record["id"], record["state"], record["name"], record["spp"]) == (job_id, "completed", "box", 4.0)

    out = tmp_path / "dl" / "box.exr"
    downloaded = cli(server, token_file, "download", job_id, "-o", str(out), "--png")
    assert downloaded.returncode == 0, downloaded.stderr
    assert downloaded.stdout.splitlines() == [f"wrote {out}", f"wrote {out.with_suffix('.png')}"]
    assert read_exr(out).color.shape == (12, 16, 3) and np.isfinite(read_exr(out).color).all()
    assert out.with_suffix(".png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    deleted = cli(server, token_file, "delete", job_id)
    assert (deleted.returncode, deleted.stdout) == (0, f"{job_id} deleted\n")
    gone = cli(server, token_file, "status", job_id)
    assert gone.returncode == 2 and gone.stderr.startswith("renderloop: error: ") and job_id in gone.stderr


def test_cancel_stops_a_running_job(server, token_file):
    submitted = cli(server, token_file, "submit", "cornell-box", "--width", "96", "--height", "96",
                    "--iterations", "12", "--spp-first", "64")
    assert submitted.returncode == 0, submitted.stderr
    job_id = submitted.stdout.strip()
    canceled = cli(server, token_file, "cancel", job_id)
    assert canceled.returncode == 0, canceled.stderr
    assert canceled.stdout.split()[0] == job_id
    headers = {"Authorization": f"Bearer {TOKEN}"}
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        record = httpx.get(f"{server.url}/jobs/{job_id}", headers=headers, timeout=30).json()
        if record["state"] != "running":
            break
        time.sleep(0.2)
    assert record["state"] == "canceled" and record["iteration"] < 12


@pytest.mark.parametrize("verb", ["status", "cancel", "download", "delete"])
def test_an_unknown_id_is_one_error_line(server, token_file, verb, tmp_path):
    extra = ["-o", str(tmp_path / "x.exr")] if verb == "download" else []
    result = cli(server, token_file, verb, "0" * 32, *extra)
    assert result.returncode == 2 and result.stderr.startswith("renderloop: error: ")
    assert "0" * 32 in result.stderr and "(HTTP 404)" in result.stderr
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.stderr


def test_a_refused_token_and_an_absent_server_are_one_error_line(server):
    refused = renderloop("status", "0" * 32, "--server", server.url, "--token", "wrong")
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1
    assert refused.stderr.startswith("renderloop: error: ") and "(HTTP 401)" in refused.stderr
    absent = renderloop("cancel", "0" * 32, "--server", f"http://127.0.0.1:{free_port()}", "--token", TOKEN)
    assert absent.returncode == 2 and absent.stderr.startswith("renderloop: error: cannot reach http://127.0.0.1:")
    assert absent.stderr.count("\n") == 1
