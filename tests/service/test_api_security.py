"""Authentication and cross-site protection against a real server started with a token."""
from __future__ import annotations

import http.client
import os
import subprocess
import sys

import httpx
import pytest

from service_harness import REPO

TOKEN = "s3cret-token"
JOB = {"scene": "cornell-box", "width": 8, "height": 8, "max_iterations": 1}
SERVER_ENV = {"RENDERLOOP_TOKEN": TOKEN}


@pytest.fixture(scope="module")
def server(module_server):
    return module_server


def test_every_endpoint_but_healthz_needs_the_token(server):
    with httpx.Client(base_url=server.url, timeout=30) as anonymous:
        assert anonymous.get("/healthz").status_code == 200
        for method, path in [("GET", "/jobs"), ("GET", "/jobs/x"), ("POST", "/jobs/x/cancel"),
                             ("GET", "/jobs/x/preview"), ("GET", "/jobs/x/events"), ("GET", "/jobs/x/result.exr")]:
            response = anonymous.request(method, path)
            assert response.status_code == 401, (method, path)
            assert "token" in response.json()["detail"] and response.headers["www-authenticate"] == "Bearer"
        assert anonymous.post("/jobs", json=JOB).status_code == 401
        wrong = anonymous.get("/jobs", headers={"Authorization": "Bearer nope"})
        assert wrong.status_code == 401


def test_the_page_and_its_files_load_without_a_token_so_it_can_ask_for_one(server):
    with httpx.Client(base_url=server.url, timeout=30) as anonymous:
        page = anonymous.get("/")
        assert page.status_code == 200 and "text/html" in page.headers["content-type"]
        assert "frame-ancestors 'none'" in page.headers["content-security-policy"]
        for path in ("/page/main.js", "/page/api.js", "/page/page.css"):
            assert anonymous.get(path).status_code == 200, path
        assert anonymous.get("/page/missing.js").status_code == 404
        assert anonymous.get("/page/").status_code == 404  # the folder lists nothing
    # The open prefix opens the page's folder only, not the API behind a dotted path (sent
    # as written: http.client does not normalise `..` the way httpx does).
    for path in ("/page/../jobs", "/page/%2e%2e/jobs", "/page/../openapi.json", "/page/../page.py"):
        connection = http.client.HTTPConnection("127.0.0.1", server.port, timeout=30)
        connection.request("GET", path)
        response = connection.getresponse()
        assert response.status in (401, 404) and b'"jobs"' not in response.read(), path
        connection.close()
    response = httpx.get(server.url + "/", headers={"Host": "evil.example"})
    assert response.status_code == 400  # the Host allow-list still applies to the page


def test_the_right_token_is_accepted_and_a_job_is_created(server):
    with httpx.Client(base_url=server.url, timeout=30, headers={"Authorization": f"Bearer {TOKEN}"}) as client:
        assert client.get("/jobs").status_code == 200
        assert client.post("/jobs", json=JOB).status_code == 202


def test_event_streams_and_previews_take_the_token_from_the_query_for_browsers(server):
    with httpx.Client(base_url=server.url, timeout=30) as anonymous:
        assert anonymous.get("/jobs/nope/preview", params={"token": TOKEN}).status_code == 404  # past the guard
        assert anonymous.get("/jobs", params={"token": TOKEN}).status_code == 401  # only where headers are impossible


def test_a_foreign_host_header_is_refused_dns_rebinding(server):
    response = httpx.get(server.url + "/healthz", headers={"Host": "evil.example:8000"})
    assert response.status_code == 400 and "evil.example" in response.json()["detail"]


def test_json_sent_as_text_plain_is_415_so_no_page_can_submit_cross_site(server):
    response = httpx.post(server.url + "/jobs", content='{"scene": "cornell-box"}',
                          headers={"Content-Type": "text/plain", "Authorization": f"Bearer {TOKEN}"})
    assert response.status_code == 415 and "application/json" in response.json()["detail"]


def test_cors_is_closed_without_configured_origins(server):
    response = httpx.options(server.url + "/jobs", headers={"Origin": "https://evil.example",
                                                             "Access-Control-Request-Method": "POST"})
    assert "access-control-allow-origin" not in response.headers


def test_serve_refuses_a_public_bind_without_a_token():
    result = subprocess.run([sys.executable, "-m", "service.cli", "serve", "--host", "0.0.0.0", "--port", "1"],
                            cwd=REPO, capture_output=True, text=True, timeout=120,
                            env={k: v for k, v in os.environ.items() if k != "RENDERLOOP_TOKEN"})
    assert result.returncode == 2 and "--token" in result.stderr and "Traceback" not in result.stderr
