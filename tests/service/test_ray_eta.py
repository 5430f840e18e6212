"""The Ray backend's driver records the ETA and the stop message as the thread backend does
(service/jobs/ray_worker.py `_iterate`, `_end`), on a real `renderloop serve` with Ray workers.
Slow: a local Ray runtime takes seconds to a minute to start on a loaded 2-core machine."""
from __future__ import annotations

import pytest

from job_events import status_events
from service_harness import wait_for

pytestmark = pytest.mark.slow
SERVER_ENV = {"RENDERLOOP_CONCURRENCY": "", "RENDERLOOP_WORKERS": "1"}


@pytest.fixture(scope="module")
def server(module_server):
    return module_server


def test_a_ray_job_streams_its_eta_and_ends_with_its_stop_message(client):
    assert client.get("/info").json()["backend"] == "ray"
    job = client.post("/jobs", json={"scene": "cornell-box", "width": 32, "height": 32, "max_iterations": 3,
                                     "time_limit": 600}, timeout=120).json()
    statuses = status_events(client, job["id"], timeout=600)
    running = [s for s in statuses if s["state"] == "running" and 1 <= s["iteration"] < 3]
    assert running and all(s["eta_seconds"] is not None for s in running), statuses
    final = wait_for(client, job["id"], lambda j: j["state"] in ("completed", "failed"))
    assert final["state"] == "completed", final
    assert final["stop_message"].startswith("stopped after 3 iterations (max_iterations 3)"), final
