"""Ray's own processes are not a silent single point of failure: `kill -9` of the local
runtime's raylet under a running job ends the `renderloop serve` process with a non-zero status
(a supervisor restarts it) instead of a server answering /healthz 200 with jobs stuck; the job is
`queued` in the store, and the next server finishes it from its checkpoint."""
from __future__ import annotations

import os
import signal
import sqlite3
import subprocess

import httpx
import pytest

from iteration_hold import hold_value
from process_sockets import process_tree
from serve_process import BACKENDS, ServeProcess
from service_harness import finished, wait_for

pytestmark = pytest.mark.requires("ray")

RUNTIME_DIED_EXIT_CODE = 75  # service.jobs.ray_worker: EX_TEMPFAIL
EXIT_SECONDS = 30
JOB = {"scene": "cornell-box", "width": 32, "height": 32, "spp_first": 16, "max_iterations": 4}
# The first server's job holds inside its second iteration's render in its Ray worker
# (iteration_hold.py via serve_process.HOLD_SITE): running at the kill however fast the machine.
HELD_AFTER_ONE = hold_value(1)


def raylet_pid(server: ServeProcess) -> int:
    for pid in process_tree(server.process.pid):
        try:
            command = open(f"/proc/{pid}/cmdline", "rb").read().split(b"\0")[0]
        except OSError:
            continue
        if command.endswith(b"/raylet"):
            return pid
    raise AssertionError("no raylet under the server")


def test_a_killed_raylet_requeues_the_running_job_and_the_server_exits_non_zero(tmp_path):
    first = ServeProcess(tmp_path / "data", tmp_path / "serve0.log", BACKENDS["ray"], HELD_AFTER_ONE).start()
    second = None
    try:
        with httpx.Client(base_url=first.url, timeout=60) as client:
            job_id = client.post("/jobs", json=JOB).json()["id"]
            at_kill = wait_for(client, job_id, lambda job: job["iteration"] >= 1, timeout=300)
            os.kill(raylet_pid(first), signal.SIGKILL)
        try:
            first.process.wait(EXIT_SECONDS)
        except subprocess.TimeoutExpired:
            pytest.fail(f"the server kept running {EXIT_SECONDS} s without its raylet:\n{first.log()}")
        assert first.process.returncode == RUNTIME_DIED_EXIT_CODE, f"status {first.process.returncode}:\n{first.log()}"
        assert at_kill["state"] == "running" and at_kill["iteration"] < JOB["max_iterations"]
        with sqlite3.connect(first.data_dir / "jobs.sqlite") as db:
            assert db.execute("SELECT state FROM jobs WHERE id = ?", (job_id,)).fetchone()[0] == "queued"

        second = ServeProcess(first.data_dir, tmp_path / "serve1.log", BACKENDS["ray"]).start()
        with httpx.Client(base_url=second.url, timeout=60) as client:
            assert client.get("/healthz").json()["status"] == "ok"
            final = wait_for(client, job_id, finished, timeout=300)
        assert final["state"] == "completed" and final["iteration"] == JOB["max_iterations"], second.log()
    finally:
        first.close()
        if second is not None:
            second.close()
