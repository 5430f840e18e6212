"""The bundle caps are the server's to set (`serve --max-bundle-files/--max-bundle-mb`, or their
environment variables for the uvicorn factory): a bundle over them is refused with the cap named."""
from __future__ import annotations

import httpx
import pytest

from service_harness import zip_bytes

SCENE = '<scene version="3.0.0"><shape type="sphere"/></scene>'
SERVER_ENV = {"RENDERLOOP_MAX_BUNDLE_FILES": "2", "RENDERLOOP_MAX_BUNDLE_MB": "1"}


@pytest.fixture(scope="module")
def server(module_server):
    return module_server


def test_a_bundle_with_more_files_than_the_configured_cap_is_refused(server):
    archive = zip_bytes({"scene.xml": SCENE, "a.txt": "a", "b.txt": "b"})
    response = httpx.post(server.url + "/jobs", data={"spec": '{"max_iterations": 1}'},
                          files={"bundle": ("s.zip", archive, "application/zip")}, timeout=60)
    assert response.status_code in (413, 422), response.text
    assert "2" in response.json()["detail"]


def test_a_body_over_the_configured_size_is_413(server):
    archive = zip_bytes({"scene.xml": SCENE, "big.bin": b"x" * (2 * 2**20)})
    response = httpx.post(server.url + "/jobs", data={"spec": '{"max_iterations": 1}'},
                          files={"bundle": ("s.zip", archive, "application/zip")}, timeout=60)
    assert response.status_code == 413, response.text
