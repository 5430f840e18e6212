"""A hard case through the HTTP service: a real uvicorn server, the fireflies scene at 7×13,
a λ map with a sharp 1 | 10 edge; the job must end `completed` with a finite result."""
from __future__ import annotations

from pathlib import Path

import httpx

from hardcase_checks import assert_finite_frame
from service.exr import read_exr
from bench.server import running_server, wait_for_job


def test_fireflies_job_at_7x13_completes_with_finite_layers(tmp_path: Path, weights_dir: Path):
    with running_server(tmp_path / "data", weights_dir) as url, httpx.Client(base_url=url, timeout=120) as client:
        created = client.post("/jobs", json={"scene": "fireflies", "width": 7, "height": 13, "max_iterations": 3,
                                             "allocator": "error"})
        assert created.status_code == 202, created.text
        job_id = created.json()["id"]
        job = wait_for_job(client, job_id, timeout=300)
        assert job["state"] == "completed", job
        assert job["iteration"] == 3 and job["spp"] == 64 and job["stop_reason"] == "max_iterations"
        edge = client.put(f"/jobs/{job_id}/lambda", json={"rects": [
            {"x": 0, "y": 0, "w": 3, "h": 13, "value": 10.0}, {"x": 3, "y": 0, "w": 4, "h": 13, "value": 1.0}]})
        assert edge.status_code == 200, edge.text
        for layer in ("denoised", "noisy", "error", "spp", "lambda"):
            preview = client.get(f"/jobs/{job_id}/preview", params={"layer": layer, "format": "exr"})
            assert preview.status_code == 200, (layer, preview.text)
        result = client.get(f"/jobs/{job_id}/result.exr")
        assert result.status_code == 200, result.text
    path = tmp_path / "result.exr"
    path.write_bytes(result.content)
    frame = read_exr(path)
    assert_finite_frame(frame)
    assert frame.color.shape == (13, 7, 3) and int(frame.spp.sum()) == 64 * 7 * 13
