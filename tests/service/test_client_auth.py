"""The client, the CLI verbs and /metrics against a real server started with a token."""
from __future__ import annotations

import httpx
import pytest

from service.client import AuthenticationRequired, RenderloopClient
from service_harness import renderloop_cli as renderloop

TOKEN = "client-test-token"
SERVER_ENV = {"RENDERLOOP_TOKEN": TOKEN}


@pytest.fixture(scope="module")
def server(module_server):
    return module_server


def test_without_the_token_the_client_raises_authentication_required(server, monkeypatch):
    monkeypatch.delenv("RENDERLOOP_TOKEN", raising=False)
    with RenderloopClient(server.url) as client:
        with pytest.raises(AuthenticationRequired) as refused:
            client.submit("cornell-box", width=8, height=8, max_iterations=1)
    assert refused.value.status == 401 and "needs a token" in refused.value.message
    with RenderloopClient(server.url, token="wrong") as client, pytest.raises(AuthenticationRequired):
        client.jobs()


def test_the_token_is_sent_given_or_from_the_environment(server, monkeypatch):
    with RenderloopClient(server.url, token=TOKEN) as client:
        job_id = client.submit("cornell-box", width=8, height=8, max_iterations=1)
        assert client.wait(job_id, progress=False)["state"] == "completed"  # the event stream too
        assert client.preview(job_id).shape == (8, 8, 3)
    monkeypatch.setenv("RENDERLOOP_TOKEN", TOKEN)
    with RenderloopClient(server.url) as client:
        assert job_id in [job["id"] for job in client.jobs()]
        assert "renderloop_jobs" in client.metrics()


def test_metrics_need_the_token_when_one_is_set(server):
    refused = httpx.get(server.url + "/metrics", timeout=30)
    assert refused.status_code == 401 and refused.headers["www-authenticate"] == "Bearer"
    allowed = httpx.get(server.url + "/metrics", headers={"Authorization": f"Bearer {TOKEN}"}, timeout=30)
    assert allowed.status_code == 200 and "renderloop_samples_rendered_total" in allowed.text


def test_the_cli_takes_the_token_from_the_flag_or_the_environment(server):
    assert renderloop("jobs", "--server", server.url, "--token", TOKEN).returncode == 0
    assert renderloop("jobs", "--server", server.url, env={"RENDERLOOP_TOKEN": TOKEN}).returncode == 0
    refused = renderloop("jobs", "--server", server.url)
    assert refused.returncode == 2 and refused.stderr.startswith("renderloop: error: this server needs a token")
    assert refused.stderr.count("\n") == 1
