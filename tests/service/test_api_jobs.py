"""Jobs end to end over real HTTP: lifecycle, previews, result EXR, λ, cancel, polling.

Renders are tiny (cornell-box at 32² or 64², a few iterations): the machine is shared.
"""
from __future__ import annotations

import io
import json
import threading
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image

from service.api import imaging
from service.exr import read_exr
from service_harness import finished, wait_for, zip_bytes

NO_DENOISE = {"denoise": False, "allocator": "variance"}


@pytest.fixture(scope="module")
def server(module_server):
    """One server for the module (a start costs seconds): every test waits for its own jobs to end,
    so none leaves the single render thread busy for the next."""
    return module_server


def submit(client: httpx.Client, **overrides) -> str:
    body = {"scene": "cornell-box", "width": 64, "height": 64, "max_iterations": 3, **overrides}
    response = client.post("/jobs", json=body)
    assert response.status_code == 202, response.text
    assert response.json()["state"] == "queued"
    return response.json()["id"]


def exr_from(response: httpx.Response, tmp_path, name: str = "x.exr"):
    path = tmp_path / name
    path.write_bytes(response.content)
    return read_exr(path)


def watch(client: httpx.Client, job_id: str) -> list[dict]:
    """Every distinct status seen by polling until the job ends."""
    seen: list[dict] = []
    wait_for(client, job_id, lambda job: seen.append(job) or finished(job))
    return seen


def check_lifecycle(client: httpx.Client, job_id: str, tmp_path) -> dict:
    seen = watch(client, job_id)
    states = [s["state"] for s in seen]
    assert states[-1] == "completed", seen[-1]
    assert set(states) <= {"queued", "running", "completed"}
    order = {"queued": 0, "running": 1, "completed": 2}
    assert [order[s] for s in states] == sorted(order[s] for s in states)  # never goes back
    # Every snapshot: total spp doubles each iteration, 16 → 32 → 64 per pixel on average.
    for status in seen:
        if status["iteration"] > 0:
            assert status["spp"] == pytest.approx(16 * 2 ** (status["iteration"] - 1)), status
    final = seen[-1]
    assert (final["iteration"], final["spp"], final["stop_reason"]) == (3, 64.0, "max_iterations")
    assert final["preview_version"] >= 3
    assert final["started_at"] and final["finished_at"] and final["created_at"]
    assert final["timings"]["render"] > 0 and "io" in final["timings"]

    preview = client.get(f"/jobs/{job_id}/preview", params={"frame": 0, "layer": "denoised"})
    assert preview.status_code == 200 and preview.headers["content-type"] == "image/png"
    assert preview.headers["etag"]
    image = Image.open(io.BytesIO(preview.content))
    assert image.size == (64, 64) and image.mode == "RGB"
    assert np.asarray(image).std() > 0  # not a blank frame
    again = client.get(f"/jobs/{job_id}/preview", headers={"If-None-Match": preview.headers["etag"]})
    assert again.status_code == 304

    for layer in ("noisy", "spp", "lambda"):
        assert client.get(f"/jobs/{job_id}/preview", params={"layer": layer}).status_code == 200, layer
    spp = exr_from(client.get(f"/jobs/{job_id}/preview", params={"layer": "spp", "format": "exr"}), tmp_path)
    assert spp.spp.mean() == pytest.approx(64)

    result = client.get(f"/jobs/{job_id}/result.exr")
    assert result.status_code == 200
    frame = exr_from(result, tmp_path, "result.exr")
    for layer in ("color", "noisy", "variance", "albedo", "normal", "depth", "spp"):
        assert getattr(frame, layer) is not None, layer
    assert frame.color.shape == (64, 64, 3) and frame.spp.mean() == pytest.approx(64)
    return final


def test_lifecycle_without_denoiser(client, tmp_path):
    job_id = submit(client, **NO_DENOISE)
    check_lifecycle(client, job_id, tmp_path)
    assert client.get(f"/jobs/{job_id}/preview", params={"layer": "error"}).status_code == 409
    listed = [j["id"] for j in client.get("/jobs").json()["jobs"]]
    assert job_id in listed and len(listed) == len(set(listed))   # the module's server lists earlier jobs too


def test_lifecycle(client, tmp_path):
    job_id = submit(client)
    final = check_lifecycle(client, job_id, tmp_path)
    assert final["predicted_error"] is not None and final["predicted_error"] > 0
    error = client.get(f"/jobs/{job_id}/preview", params={"layer": "error"})
    assert error.status_code == 200
    frame = exr_from(client.get(f"/jobs/{job_id}/result.exr"), tmp_path)
    assert frame.error is not None and frame.lam is not None


def test_the_job_record_says_which_integrator_runs_and_why(client):
    final = wait_for(client, submit(client), finished)
    effects = final["effects"]
    assert effects["integrator"] == "path" and effects["integrator_declared"] is True
    assert "declared by the scene" in effects["integrator_reason"] and effects["media"] is False


def test_preview_is_204_before_the_first_iteration(client):
    blocker = submit(client, width=64, height=64, max_iterations=7, **NO_DENOISE)  # occupies the worker
    waiting = submit(client, width=16, height=16, max_iterations=1, **NO_DENOISE)
    response = client.get(f"/jobs/{waiting}/preview")
    assert response.status_code == 204 and response.content == b""
    assert client.get(f"/jobs/{waiting}/result.exr").status_code == 409
    assert client.put(f"/jobs/{waiting}/lambda", json={"value": 2}).status_code == 200  # kept for later
    # Canceling a queued job is immediate; the running one stops after its current iteration.
    assert client.post(f"/jobs/{waiting}/cancel").json()["state"] == "canceled"
    client.post(f"/jobs/{blocker}/cancel")
    final = wait_for(client, blocker, finished)
    assert final["state"] == "canceled" and final["stop_reason"] == "canceled"
    assert client.post(f"/jobs/{blocker}/cancel").status_code == 409
    assert client.put(f"/jobs/{blocker}/lambda", json={"value": 2}).status_code == 409


def test_cancel_mid_run(client):
    job_id = submit(client, max_iterations=9, **NO_DENOISE)
    wait_for(client, job_id, lambda job: job["iteration"] >= 1)
    response = client.post(f"/jobs/{job_id}/cancel")
    assert response.status_code == 200
    final = wait_for(client, job_id, finished)
    assert final["state"] == "canceled" and final["stop_reason"] == "canceled"
    assert 1 <= final["iteration"] < 9
    # What was rendered before the cancel is still there to look at.
    assert client.get(f"/jobs/{job_id}/preview").status_code == 200
    assert client.get(f"/jobs/{job_id}/result.exr").status_code == 200


def test_events_stream_until_the_job_ends(client):
    job_id = submit(client, width=32, height=32, **NO_DENOISE)
    events: list[tuple[str, dict]] = []
    with client.stream("GET", f"/jobs/{job_id}/events", timeout=120) as response:
        assert response.headers["content-type"].startswith("text/event-stream")
        kind = None
        for line in response.iter_lines():
            if line.startswith("event: "):
                kind = line[len("event: "):]
            elif line.startswith("data: "):
                events.append((kind, json.loads(line[len("data: "):])))
    kinds = [k for k, _ in events]
    assert kinds[-1] == "end" and events[-1][1]["state"] == "completed"
    statuses = [data for k, data in events if k == "status"]
    assert statuses[-1]["state"] == "completed" and statuses[-1]["iteration"] == 3
    iterations = [s["iteration"] for s in statuses]
    assert iterations == sorted(iterations)


def test_several_clients_poll_while_a_job_runs(server, client):
    job_id = submit(client, max_iterations=5, **NO_DENOISE)
    failures: list[str] = []
    counts = [0] * 4

    def poll(index: int) -> None:
        with httpx.Client(base_url=server.url, timeout=10) as own:
            while True:
                job = own.get(f"/jobs/{job_id}")
                preview = own.get(f"/jobs/{job_id}/preview", params={"layer": "noisy"})
                if job.status_code != 200 or preview.status_code not in (200, 204):
                    failures.append(f"{job.status_code} {preview.status_code}")
                    return
                counts[index] += 1
                if finished(job.json()):
                    return

    threads = [threading.Thread(target=poll, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(180)
    assert not failures
    assert all(c >= 3 for c in counts), counts  # polling stayed responsive while rendering
    assert client.get(f"/jobs/{job_id}").json()["state"] == "completed"


def test_lambda_map_kept_and_used_without_denoiser(client, tmp_path):
    job_id = submit(client, width=32, height=32, **NO_DENOISE)
    wait_for(client, job_id, finished)
    rects = {"rects": [{"x": 0, "y": 0, "w": 8, "h": 40, "value": 4.0}]}
    assert client.put(f"/jobs/{job_id}/lambda", json=rects).status_code == 200
    lam = exr_from(client.get(f"/jobs/{job_id}/preview", params={"layer": "lambda", "format": "exr"}), tmp_path).lam
    assert lam.shape == (32, 32) and np.all(lam[:, :8] == 4.0) and np.all(lam[:, 8:] == 1.0)
    job = client.get(f"/jobs/{job_id}").json()
    assert job["lambda_value"] is None  # a per-pixel map now


def png_bytes(values: np.ndarray, mode: str | None) -> bytes:
    buffer = io.BytesIO()
    image = Image.fromarray(values, mode=mode) if mode else Image.fromarray(values)  # uint16 → 16-bit grey
    image.save(buffer, format="PNG")
    return buffer.getvalue()


def test_lambda_map_upload_checks(client):
    job_id = submit(client, width=32, height=32, max_iterations=1, **NO_DENOISE)
    wait_for(client, job_id, finished)
    wrong_size = png_bytes(np.full((16, 16), 3, np.uint8), "L")
    response = client.put(f"/jobs/{job_id}/lambda", files={"map": ("lam.png", wrong_size, "image/png")})
    assert response.status_code == 422 and "16×16" in response.json()["detail"]
    out_of_range = imaging.exr_bytes("lambda", np.full((32, 32), 20.0, np.float32))  # EXR pixels are λ itself
    response = client.put(f"/jobs/{job_id}/lambda", files={"map": ("lam.exr", out_of_range, "image/x-exr")})
    assert response.status_code == 422 and "[1, 10]" in response.json()["detail"]
    rgb = png_bytes(np.full((32, 32, 3), 3, np.uint8), "RGB")
    response = client.put(f"/jobs/{job_id}/lambda", files={"map": ("lam.png", rgb, "image/png")})
    assert response.status_code == 422 and "single-channel" in response.json()["detail"]
    good = png_bytes(np.full((32, 32), 5, np.uint8), "L")
    response = client.put(f"/jobs/{job_id}/lambda", files={"map": ("lam.png", good, "image/png")})
    assert response.status_code == 200 and response.json()["version"] >= 2


@pytest.mark.parametrize("dtype, mode, full", [(np.uint8, "L", 255), (np.uint16, None, 65535)])
def test_grey_png_mask_maps_linearly_onto_the_lambda_range(client, tmp_path, dtype, mode, full):
    job_id = submit(client, width=32, height=32, max_iterations=1, **NO_DENOISE)
    wait_for(client, job_id, finished)
    mask = np.zeros((32, 32), dtype)
    mask[:, 16:] = full  # left half black, right half white
    mask[0, 0] = full // 3
    response = client.put(f"/jobs/{job_id}/lambda", files={"map": ("mask.png", png_bytes(mask, mode), "image/png")})
    assert response.status_code == 200, response.text
    lam = exr_from(client.get(f"/jobs/{job_id}/preview", params={"layer": "lambda", "format": "exr"}), tmp_path).lam
    assert np.all(lam[1:, :16] == 1.0) and np.all(lam[:, 16:] == 10.0)
    assert lam[0, 0] == pytest.approx(1.0 + 9.0 * (full // 3) / full)


def test_lambda_change_redenoises_from_cached_features(client):
    job_id = submit(client, width=32, height=32)
    wait_for(client, job_id, finished)
    before = client.get(f"/jobs/{job_id}/preview")
    response = client.put(f"/jobs/{job_id}/lambda", json={"value": 10.0})
    assert response.status_code == 200, response.text
    applied = response.json()
    assert applied["version"] > int(before.headers["x-preview-version"])
    assert applied["tail_passes"] >= 1 and applied["full_passes"] == 0  # cached path, no re-render
    after = client.get(f"/jobs/{job_id}/preview")
    assert after.headers["x-preview-version"] == str(applied["version"])
    assert after.content != before.content  # λ changed the denoised image
    assert client.get(f"/jobs/{job_id}").json()["lambda_value"] == 10.0


def test_lambda_burst_over_http_ends_on_the_value_sent_last(server, client, tmp_path):
    job_id = submit(client, width=32, height=32)
    wait_for(client, job_id, finished)
    values = [2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 2.5, 3.5]  # the last is neither the largest nor the first
    results: dict[float, dict] = {}

    def put(value: float, sequence: int) -> None:
        with httpx.Client(base_url=server.url, timeout=120) as own:
            results[value] = own.put(f"/jobs/{job_id}/lambda", json={"value": value, "sequence": sequence}).json()

    threads = []
    for sequence, value in enumerate(values):  # issued in this order, overlapping, arriving in any order
        threads.append(threading.Thread(target=put, args=(value, sequence)))
        threads[-1].start()
    for t in threads:
        t.join(120)
    assert client.get(f"/jobs/{job_id}").json()["lambda_value"] == values[-1]
    lam = exr_from(client.get(f"/jobs/{job_id}/preview", params={"layer": "lambda", "format": "exr"}), tmp_path).lam
    assert np.all(lam == values[-1])  # the preview was denoised with the λ sent last
    assert max(r["version"] for r in results.values()) == client.get(f"/jobs/{job_id}").json()["preview_version"]


def test_lambda_during_the_run_is_used_by_later_iterations(client, tmp_path):
    job_id = submit(client, width=32, height=32, max_iterations=5)
    wait_for(client, job_id, lambda job: job["iteration"] >= 1)
    assert client.put(f"/jobs/{job_id}/lambda", json={"value": 6.0}).status_code == 200
    final = wait_for(client, job_id, finished)
    assert final["state"] == "completed"
    frame = exr_from(client.get(f"/jobs/{job_id}/result.exr"), tmp_path)
    assert np.all(frame.lam == 6.0)


TINY_SCENE = ('<scene version="3.0.0"><sensor type="perspective"><film type="hdrfilm"><integer name="width" '
              'value="8"/><integer name="height" value="8"/></film></sensor><shape type="sphere"/>'
              '<emitter type="constant"/></scene>')


def test_result_header_names_a_bundle_scene_relative_to_the_bundle(client, tmp_path):
    archive = zip_bytes({"shots/a.xml": TINY_SCENE, "notes.txt": "two top-level entries: no folder is stripped"})
    response = client.post("/jobs", data={"spec": json.dumps({"scene": "shots/a.xml", "max_iterations": 1})},
                           files={"bundle": ("s.zip", archive, "application/zip")})
    assert response.status_code == 202, response.text
    job_id = response.json()["id"]
    assert wait_for(client, job_id, finished)["state"] == "completed"
    frame = exr_from(client.get(f"/jobs/{job_id}/result.exr"), tmp_path)
    assert frame.header["scene"] == "shots/a.xml"  # not the server's path to the job folder


def test_bundle_job_completes_when_the_data_dir_is_relative(start_server, tmp_path):
    """`make run` serves `--data-dir data`, relative to the working directory: an upload must not
    trip over comparing that relative folder with resolved paths (it was a 500)."""
    server = start_server(data_dir=Path("data"), cwd=tmp_path)
    archive = zip_bytes({"shot/scene.xml": TINY_SCENE})
    with httpx.Client(base_url=server.url, timeout=60) as client:
        response = client.post("/jobs", data={"spec": json.dumps({"scene": "scene.xml", "max_iterations": 1})},
                               files={"bundle": ("shot.zip", archive, "application/zip")})
        assert response.status_code == 202, response.text
        job_id = response.json()["id"]
        assert wait_for(client, job_id, finished)["state"] == "completed"
        assert client.get(f"/jobs/{job_id}/result.exr").status_code == 200
    assert (tmp_path / "data" / "jobs" / job_id).is_dir()
