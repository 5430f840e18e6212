"""`renderloop submit` and `renderloop jobs` as real subprocesses against a real server."""
from __future__ import annotations

import numpy as np
import pytest

from service.exr import read_exr
from service_harness import REPO, free_port, renderloop_cli as renderloop


@pytest.fixture(scope="module")
def server(module_server):
    return module_server


def test_submit_wait_writes_a_readable_exr_and_jobs_lists_it(server, tmp_path):
    out = tmp_path / "renders" / "out.exr"
    result = renderloop("submit", "cornell-box", "--server", server.url, "--width", "32", "--height", "24",
                        "--iterations", "2", "--lambda", "3", "--wait", "-o", str(out))
    assert result.returncode == 0, result.stderr
    job_id, summary, wrote = result.stdout.splitlines()
    assert len(job_id) == 32 and summary.startswith(f"{job_id} completed: 2 iterations, 32.0 spp mean")
    assert wrote == f"wrote {out}"
    frame = read_exr(out)
    assert frame.color.shape == (24, 32, 3) and np.isfinite(frame.color).all() and np.all(frame.lam == 3.0)
    assert "it/s" in result.stderr or "s/it" in result.stderr  # the progress bar went to stderr

    listed = renderloop("jobs", env={"RENDERLOOP_SERVER": server.url})  # the server from the environment
    assert listed.returncode == 0, listed.stderr
    header, *rows = listed.stdout.splitlines()
    assert header.split() == ["ID", "STATE", "ITER", "SPP", "ERROR", "NAME", "CREATED"]
    row = next(r.split() for r in rows if r.startswith(job_id))
    assert row[1:4] == ["completed", "2", "32.0"] and row[5] == "cornell-box"


def test_submit_without_wait_prints_only_the_job_id(server):
    result = renderloop("submit", "cornell-box", "--server", server.url, "--width", "8", "--height", "8",
                        "--iterations", "1")
    assert result.returncode == 0, result.stderr
    assert len(result.stdout.strip()) == 32 and result.stdout.count("\n") == 1


def test_a_scene_folder_is_uploaded_from_the_command_line(server, tmp_path):
    out = tmp_path / "t.exr"
    scene = REPO / "scenes" / "dev" / "fine_texture"
    result = renderloop("submit", str(scene), "--server", server.url, "--width", "16", "--height", "12",
                        "--iterations", "1", "-o", str(out))
    assert result.returncode == 0, result.stderr
    assert read_exr(out).color.shape == (12, 16, 3)


@pytest.mark.parametrize("args, message", [
    (["submit", "no-such-scene"], "unknown built-in scene 'no-such-scene'"),
    (["submit", "cornell-box", "--width", "16"], "give both width and height"),
    (["submit", "cornell-box", "--lambda", "20"], "λ must be finite and lie in [1, 10]"),
    (["submit", "missing/scene.xml"], "missing/scene.xml: no such scene file or folder"),
    (["jobs", "--limit", "0"], "limit"),
])
def test_bad_input_is_one_error_line_and_exit_2(server, args, message):
    result = renderloop(*args, "--server", server.url)
    assert result.returncode == 2, result
    assert result.stderr.startswith("renderloop: error: ") and message in result.stderr
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.stderr


def test_a_server_that_is_not_there_is_one_error_line():
    result = renderloop("jobs", "--server", f"http://127.0.0.1:{free_port()}")
    assert result.returncode == 2
    assert result.stderr.startswith("renderloop: error: cannot reach http://127.0.0.1:")
    assert "renderloop serve" in result.stderr and "Traceback" not in result.stderr
