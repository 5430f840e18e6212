"""GET /metrics: Prometheus text from a real server after a real job, and one registry per app."""
from __future__ import annotations

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families

from service.api.metrics import STAGES, ServiceMetrics
from service.client import RenderloopClient
from service.jobs.store import JobStore


@pytest.fixture(scope="module")
def server(module_server):
    return module_server


def scrape(url: str) -> dict[tuple[str, tuple], float]:
    """{(sample name, sorted labels): value} of one scrape."""
    response = httpx.get(url + "/metrics", timeout=30)
    assert response.status_code == 200 and response.headers["content-type"].startswith("text/plain")
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for family in text_string_to_metric_families(response.text) for s in family.samples}


def test_metrics_after_a_finished_job_count_its_stages_samples_and_lambda_edits(server):
    with RenderloopClient(server.url) as client:
        job_id = client.submit("cornell-box", width=32, height=32, max_iterations=2)
        assert client.wait(job_id, progress=False)["state"] == "completed"
        client.set_lambda(job_id, 4.0)
    metrics = scrape(server.url)
    assert metrics[("renderloop_jobs", (("state", "completed"),))] == 1
    assert metrics[("renderloop_jobs", (("state", "running"),))] == 0
    for stage in STAGES:
        assert metrics[("renderloop_iteration_stage_seconds_count", (("stage", stage),))] == 2, stage
        assert metrics[("renderloop_iteration_stage_seconds_sum", (("stage", stage),))] > 0, stage
    assert metrics[("renderloop_iterations_total", ())] == 2
    assert metrics[("renderloop_samples_rendered_total", ())] == 32 * 32 * 32  # 16 spp, then doubled to 32
    assert metrics[("renderloop_lambda_edit_seconds_count", ())] == 1
    assert metrics[("renderloop_lambda_edit_seconds_sum", ())] > 0


def test_metrics_are_documented_as_text_in_the_openapi(server):
    operation = httpx.get(server.url + "/openapi.json", timeout=30).json()["paths"]["/metrics"]["get"]
    assert list(operation["responses"]["200"]["content"]) == ["text/plain"]
    assert "401" in operation["responses"]


def test_each_app_counts_in_its_own_registry(tmp_path):
    first, second = ServiceMetrics(JobStore(tmp_path / "a")), ServiceMetrics(JobStore(tmp_path / "b"))
    first.iteration_finished({"render": 0.5, "denoise": 0.1}, samples=1000)
    first.lambda_applied(0.02)
    assert b"renderloop_samples_rendered_total 1000.0" in first.exposition()
    assert b"renderloop_samples_rendered_total 0.0" in second.exposition()
    assert b'renderloop_lambda_edit_seconds_count 0.0' in second.exposition()
