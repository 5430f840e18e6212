"""Authentication and cross-site protection against a real server started with a token."""
from __future__ import annotations

import http.client
import json
import os
import subprocess
import sys
import time

import httpx
import pytest

from service.api.signing import UrlSigner
from service_harness import REPO, wait_for

TOKEN = "s3cret-token"
JOB = {"scene": "cornell-box", "width": 8, "height": 8, "max_iterations": 1}
ALLOWED_ORIGIN = "https://app.example"
SERVER_ENV = {"RENDERLOOP_TOKEN": TOKEN, "RENDERLOOP_CORS_ORIGINS": ALLOWED_ORIGIN}
AUTH = {"Authorization": f"Bearer {TOKEN}"}


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


@pytest.fixture(scope="module")
def finished_job(server) -> str:
    with httpx.Client(base_url=server.url, timeout=30, headers=AUTH) as client:
        job_id = client.post("/jobs", json=JOB).json()["id"]
        wait_for(client, job_id, lambda job: job["state"] == "completed")
    return job_id


def test_a_signed_preview_and_event_stream_url_work_without_the_token(server, finished_job):
    links = httpx.get(f"{server.url}/jobs/{finished_job}/links", headers=AUTH, timeout=30).json()
    assert TOKEN not in json.dumps(links) and links["expires"] > time.time()
    with httpx.Client(base_url=server.url, timeout=30) as anonymous:
        preview = anonymous.get(links["preview"] + "&layer=noisy&format=png")
        assert preview.status_code == 200 and preview.headers["content-type"] == "image/png"
        events = anonymous.get(links["events"])
        assert events.status_code == 200 and "event: end" in events.text
        assert anonymous.get(f"/jobs/{finished_job}/links").status_code == 401  # issuing them needs the token


def _tampered(signature: str) -> str:
    """The signature with its first character changed: always a different string (overwriting
    the tail with a fixed "AA" left it unchanged for the 1 in 1024 signatures ending in "AA")."""
    return ("B" if signature[0] == "A" else "A") + signature[1:]


def test_an_expired_tampered_or_other_jobs_signature_is_401(server, finished_job):
    signer = UrlSigner.from_token(TOKEN)  # the server's own key: only the expiry makes it fail
    expires, signature = signer.sign(finished_job, now=time.time() - 2 * signer.seconds)
    links = httpx.get(f"{server.url}/jobs/{finished_job}/links", headers=AUTH, timeout=30).json()
    good_exp, good_sig = links["expires"], links["preview"].rsplit("sig=", 1)[1]
    other_job = httpx.post(server.url + "/jobs", json=JOB, headers=AUTH, timeout=30).json()["id"]
    with httpx.Client(base_url=server.url, timeout=30) as anonymous:
        for job_id, exp, sig in [(finished_job, expires, signature),           # expired
                                 (finished_job, good_exp, _tampered(good_sig)),   # tampered
                                 (finished_job, good_exp + 3600, good_sig),      # expiry pushed out
                                 (other_job, good_exp, good_sig)]:               # another job's
            for route in ("preview", "events"):
                response = anonymous.get(f"/jobs/{job_id}/{route}", params={"exp": exp, "sig": sig})
                assert response.status_code == 401, (job_id, exp, route)
                assert "/links" in response.json()["detail"]


def test_the_raw_token_in_a_url_is_refused_even_where_browsers_need_one(server, finished_job):
    with httpx.Client(base_url=server.url, timeout=30) as anonymous:
        for route in ("preview", "events"):
            response = anonymous.get(f"/jobs/{finished_job}/{route}", params={"token": TOKEN})
            assert response.status_code == 401 and "Authorization" in response.json()["detail"], route
        assert anonymous.get("/jobs", params={"token": TOKEN}).status_code == 401


def test_a_cross_site_browser_write_is_403_json_or_multipart(server):
    evil = {**AUTH, "Origin": "https://evil.example"}
    with httpx.Client(base_url=server.url, timeout=30) as client:
        response = client.post("/jobs", json=JOB, headers=evil)
        assert response.status_code == 403 and "https://evil.example" in response.json()["detail"]
        form = client.post("/jobs", headers=evil, data={"spec": json.dumps({"scene": "scene.xml"})},
                           files={"bundle": ("scene.zip", b"PK\x05\x06" + bytes(18), "application/zip")})
        assert form.status_code == 403
        assert client.request("DELETE", "/jobs/x", headers=evil).status_code == 403
        assert client.put("/jobs/x/lambda", json={"value": 2}, headers=evil).status_code == 403
        assert client.post("/jobs/x/cancel", headers={**AUTH, "Origin": "null"}).status_code == 403
        cross_site = client.post("/jobs", json=JOB, headers={**AUTH, "Sec-Fetch-Site": "cross-site"})
        assert cross_site.status_code == 403 and "Sec-Fetch-Site" in cross_site.json()["detail"]
        assert client.post("/jobs", json=JOB, headers={**AUTH, "Sec-Fetch-Site": "same-site"}).status_code == 403
        assert client.get("/jobs", headers=evil).status_code == 200  # reads: CORS keeps the answer from the page


def test_the_pages_own_origin_and_configured_origins_may_write(server):
    with httpx.Client(base_url=server.url, timeout=30, headers=AUTH) as client:
        own = client.post("/jobs", json=JOB, headers={"Origin": server.url, "Sec-Fetch-Site": "same-origin"})
        assert own.status_code == 202, own.text
        assert client.post("/jobs", json=JOB, headers={"Origin": server.url.replace("127.0.0.1", "localhost")},
                           ).status_code == 403  # another name is another origin
        allowed = client.post("/jobs", json=JOB, headers={"Origin": ALLOWED_ORIGIN, "Sec-Fetch-Site": "cross-site"})
        assert allowed.status_code == 202, allowed.text
        assert client.post("/jobs", json=JOB).status_code == 202  # no Origin: curl, service.client


def test_json_bodies_are_capped_at_1_mib_by_header_and_while_streaming(server):
    big = json.dumps({"value": 2, "rects": [{"x": 0, "y": 0, "w": 1, "h": 1, "value": 2}] * 40000}).encode()
    assert len(big) > 2**20
    with httpx.Client(base_url=server.url, timeout=30, headers=AUTH) as client:
        declared = client.put("/jobs/x/lambda", content=big, headers={"Content-Type": "application/json"})
        assert declared.status_code == 413 and "1 MiB" in declared.json()["detail"]
        streamed = client.post("/jobs", content=iter([big[:2**19], big[2**19:]]),
                               headers={"Content-Type": "application/json"})  # chunked: no length to check
        assert streamed.status_code == 413, streamed.text


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


def test_the_openapi_document_lists_the_links_route_and_the_edge_refusals(server):
    document = httpx.get(server.url + "/openapi.json", headers=AUTH, timeout=30).json()
    paths = document["paths"]
    assert "403" in paths["/jobs"]["post"]["responses"] and "403" in paths["/jobs/{job_id}"]["delete"]["responses"]
    assert {"429", "503"} <= set(paths["/jobs/{job_id}/events"]["get"]["responses"])
    assert "JobLinks" in json.dumps(paths["/jobs/{job_id}/links"]["get"]["responses"]["200"])
    assert "expires" in document["components"]["schemas"]["JobLinks"]["properties"]
