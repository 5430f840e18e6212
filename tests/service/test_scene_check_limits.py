"""Uploaded scenes are checked at submit in a child process with a memory and a time limit
(service/render/scene_probe.py), against a real `renderloop serve` process: a scene over either
limit is a 422 naming the limit and its setting, and the API process's memory stays flat."""
from __future__ import annotations

import struct
import time
import zlib

import httpx
import pytest

from service_harness import finished, wait_for, zip_bytes

# Small enough that a 4096² texture (~180 MB once loaded) is over it, large enough for a sphere.
SERVER_ENV = {"RENDERLOOP_SCENE_CHECK_MEMORY_MB": "100", "RENDERLOOP_SCENE_CHECK_SECONDS": "6"}
SPEC = '{"width": 8, "height": 8, "max_iterations": 1}'
SENSOR = """<sensor type="perspective"><transform name="to_world"><lookat origin="0,0,4" target="0,0,0" up="0,1,0"/></transform>
  <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film></sensor>
  <emitter type="constant"/>"""
API_GROWTH_BOUND = 64 * 2**20  # the API process's peak memory may move this much, not a scene's worth


@pytest.fixture(scope="module")
def server(module_server):
    return module_server


def scene(body: str) -> str:
    return f'<scene version="3.0.0">{SENSOR}{body}</scene>'


def grey_png(side: int) -> bytes:
    """A side×side RGB PNG, tens of KB on disk, side²×3 floats once Mitsuba loads it."""
    pixels = zlib.compress((b"\x00" + b"\x80" * (3 * side)) * side, 9)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", side, side, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", pixels) + chunk(b"IEND", b"")


def slow_scene(count: int) -> str:
    """Cheap in memory, slow to flatten: every `$dK` is looked for among `count` parameters."""
    defaults = "".join(f'<default name="d{i}" value="{i}"/>' for i in range(count))
    uses = "".join(f'<float name="f{i}" value="$d{i}"/>' for i in range(count))
    return f'<scene version="3.0.0">{defaults}{SENSOR}<shape type="sphere">{uses}</shape></scene>'


def peak_rss(pid: int) -> int:
    """VmHWM: the most resident memory the process has ever had."""
    with open(f"/proc/{pid}/status") as status:
        for line in status:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    raise AssertionError("no VmHWM")


def submit(client: httpx.Client, members: dict) -> httpx.Response:
    return client.post("/jobs", data={"spec": SPEC},
                       files={"bundle": ("scene.zip", zip_bytes(members), "application/zip")}, timeout=120)


def test_a_scene_over_the_check_memory_limit_is_422_and_the_api_memory_stays_flat(server, client):
    texture = ('<shape type="sphere"><bsdf type="diffuse"><texture type="bitmap" name="reflectance">'
               '<string name="filename" value="big.png"/></texture></bsdf></shape>')
    before = peak_rss(server.process.pid)
    response = submit(client, {"scene.xml": scene(texture), "big.png": grey_png(4096)})
    assert response.status_code == 422, response.text
    detail = response.json()["detail"]
    assert "needs more than 100 MiB" in detail and "--scene-check-memory-mb" in detail, detail
    assert peak_rss(server.process.pid) - before < API_GROWTH_BOUND  # in the API process: +180 MB


def test_a_scene_over_the_check_time_limit_is_422(server, client):
    started = time.monotonic()
    response = submit(client, {"scene.xml": slow_scene(16_000)})
    assert response.status_code == 422, response.text
    detail = response.json()["detail"]
    assert "took longer than 6 s" in detail and "--scene-check-seconds" in detail, detail
    assert time.monotonic() - started < 60  # about 40 s of flattening, cut at the limit


def test_a_small_scene_passes_the_check_and_renders(client):
    response = submit(client, {"scene.xml": scene('<shape type="sphere"/>')})
    assert response.status_code == 202, response.text
    assert wait_for(client, response.json()["id"], finished)["state"] == "completed"
