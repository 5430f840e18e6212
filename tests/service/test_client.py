"""service.client.RenderloopClient against a real server: submit (built-in, folder, XML file),
wait, previews as numpy, λ three ways, download, typed errors, and a λ burst that must end on
the edit issued last."""
from __future__ import annotations

import shutil
from concurrent.futures import ThreadPoolExecutor

import httpx
import numpy as np
import pytest

from service.client import Conflict, InvalidRequest, NotFound, RenderloopClient, ServerUnreachable
from service.exr import read_exr
from service_harness import REPO, free_port

SMALL = {"width": 32, "height": 32, "max_iterations": 2}
TEXTURED_SCENE = REPO / "scenes" / "dev" / "fine_texture"  # an XML and the PNG it reads


@pytest.fixture(scope="module")
def server(module_server):
    return module_server


@pytest.fixture
def client(server):
    with RenderloopClient(server.url) as c:
        yield c


@pytest.fixture(scope="module")
def finished_job(module_server) -> str:
    """One completed 32² cornell-box job with the denoiser, shared by the read-only tests."""
    with RenderloopClient(module_server.url) as c:
        job_id = c.submit("cornell-box", **SMALL)
        assert c.wait(job_id, progress=False)["state"] == "completed"
        return job_id


def test_a_builtin_scene_is_submitted_followed_to_the_end_and_downloaded(client, tmp_path):
    job_id = client.submit("cornell-box", width=48, height=32, max_iterations=3, lam=2.0)
    final = client.wait(job_id)  # follows the server-sent events
    assert (final["state"], final["iteration"], final["spp"]) == ("completed", 3, 64.0)
    assert client.status(job_id)["lambda_value"] == 2.0
    path = client.download(job_id, tmp_path / "out" / "result.exr")
    frame = read_exr(path)
    assert frame.color.shape == (32, 48, 3) and np.isfinite(frame.color).all()
    assert np.all(frame.lam == 2.0) and frame.spp.mean() == pytest.approx(64)
    assert [p.name for p in path.parent.iterdir()] == ["result.exr"]  # no temporary left behind


def test_previews_come_back_as_numpy_arrays_of_the_right_shape(client, finished_job):
    denoised = client.preview(finished_job)
    assert denoised.shape == (32, 32, 3) and denoised.dtype == np.float32
    assert np.isfinite(denoised).all() and denoised.std() > 0
    noisy = client.preview(finished_job, "noisy")
    assert noisy.shape == (32, 32, 3) and not np.array_equal(noisy, denoised)
    assert client.preview(finished_job, "spp").mean() == pytest.approx(32)
    error = client.preview(finished_job, "error")
    assert error.shape == (32, 32) and np.isfinite(error).all() and error.max() > 0


def test_a_preview_before_the_first_iteration_is_none(client):
    blocker = client.submit("cornell-box", width=64, height=64, max_iterations=6, denoise=False, allocator="variance")
    waiting = client.submit("cornell-box", width=16, height=16, max_iterations=1)
    try:
        assert client.preview(waiting) is None
    finally:
        client.delete(waiting)
        client.delete(blocker)


def test_lambda_is_set_as_a_value_as_rects_and_as_a_numpy_map(client):
    job_id = client.submit("cornell-box", **SMALL)
    client.wait(job_id, progress=False)
    before = client.preview(job_id)
    applied = client.set_lambda(job_id, 3.0)
    assert applied["tail_passes"] >= 1 and applied["full_passes"] == 0
    assert np.all(client.preview(job_id, "lambda") == 3.0) and client.status(job_id)["lambda_value"] == 3.0
    assert not np.array_equal(client.preview(job_id), before)  # re-denoised with the new λ

    client.set_lambda(job_id, rects=[(0, 0, 8, 32, 6.0), {"x": 24, "y": 0, "w": 8, "h": 32, "value": 9.0}])
    lam = client.preview(job_id, "lambda")
    assert np.all(lam[:, :8] == 6.0) and np.all(lam[:, 8:24] == 3.0) and np.all(lam[:, 24:] == 9.0)

    painted = np.linspace(1.0, 10.0, 32 * 32, dtype=np.float32).reshape(32, 32)
    client.set_lambda(job_id, lambda_map=painted)
    assert np.array_equal(client.preview(job_id, "lambda"), painted)
    assert client.status(job_id)["lambda_value"] is None  # a per-pixel map now


def test_a_scene_folder_is_zipped_and_uploaded_and_waited_for_by_polling(server, tmp_path):
    folder = shutil.copytree(TEXTURED_SCENE, tmp_path / "my scene")
    (folder / ".git").mkdir()
    (folder / ".git" / "config").write_text("hidden files stay home")
    with RenderloopClient(server.url, follow_events=False) as client:
        job_id = client.submit(folder, width=32, height=24, max_iterations=2)
        final = client.wait(job_id, progress=False)
        assert final["state"] == "completed", final
        assert final["spec"]["scene"] == "scene.xml"
        image = client.preview(job_id)
        assert image.shape == (24, 32, 3) and np.isfinite(image).all() and image.std() > 0


def test_a_scene_xml_file_uploads_its_folder_and_names_itself(client, tmp_path):
    folder = shutil.copytree(TEXTURED_SCENE, tmp_path / "textured")
    shutil.copy(folder / "scene.xml", folder / "other.xml")  # two XMLs: the server cannot guess
    job_id = client.submit(str(folder / "other.xml"), width=16, height=16, max_iterations=1)
    final = client.wait(job_id, progress=False)
    assert final["state"] == "completed" and final["spec"]["scene"] == "other.xml"


def test_jobs_are_listed_canceled_and_deleted(client):
    job_id = client.submit("cornell-box", width=64, height=64, max_iterations=9, denoise=False,
                           allocator="variance")
    assert job_id in [job["id"] for job in client.jobs()]
    assert client.cancel(job_id)["id"] == job_id
    assert client.wait(job_id, progress=False)["state"] == "canceled"
    assert job_id in [job["id"] for job in client.jobs(state="canceled")]
    client.delete(job_id)
    with pytest.raises(NotFound):
        client.status(job_id)


def test_refusals_raise_typed_errors_carrying_the_servers_message(client, finished_job, tmp_path):
    with pytest.raises(NotFound) as missing:
        client.preview("no-such-job")
    assert missing.value.status == 404 and missing.value.message == "no job with id 'no-such-job'"
    with pytest.raises(InvalidRequest) as unknown:
        client.submit("no-such-scene")
    assert unknown.value.status == 422 and "unknown built-in scene 'no-such-scene'" in unknown.value.message
    with pytest.raises(InvalidRequest, match=r"λ must be finite and lie in \[1, 10\]"):
        client.set_lambda(finished_job, 11.0)
    with pytest.raises(InvalidRequest, match="λ map is 8×8, the job's image is 32×32"):
        client.set_lambda(finished_job, lambda_map=np.full((8, 8), 2.0))
    with pytest.raises(Conflict) as conflict:
        client.cancel(finished_job)
    assert conflict.value.status == 409 and "already completed" in conflict.value.message
    with pytest.raises(NotFound):
        client.download("no-such-job", tmp_path / "x.exr")
    assert not (tmp_path / "x.exr").exists()
    with pytest.raises(FileNotFoundError, match="no such scene"):
        client.submit(tmp_path / "missing" / "scene.xml")


def test_an_unreachable_server_is_a_clear_error():
    with RenderloopClient(f"http://127.0.0.1:{free_port()}") as client:
        with pytest.raises(ServerUnreachable, match="cannot reach http://127.0.0.1:"):
            client.jobs()


def lambda_layer(client: RenderloopClient, job_id: str) -> np.ndarray:
    return client.preview(job_id, "lambda")


def test_a_burst_of_lambda_edits_from_several_threads_ends_on_the_last_one_issued(client, tmp_path):
    job_id = client.submit("cornell-box", **SMALL)
    client.wait(job_id, progress=False)
    values = [1.0 + 0.45 * i for i in range(20)]  # 1.0 … 9.55, all different; the last is not the largest
    values[-1], values[-5] = values[-5], values[-1]
    sequences = [client._next_sequence() for _ in values]  # the order of issue
    answers: list[dict] = []
    with ThreadPoolExecutor(max_workers=4) as pool:  # in flight together, arriving in any order
        for value, sequence in zip(values, sequences):
            pool.submit(lambda v=value, s=sequence: answers.append(client.set_lambda(job_id, v, sequence=s)))
    assert len(answers) == len(values)
    last = values[-1]
    assert client.status(job_id)["lambda_value"] == last
    assert np.all(lambda_layer(client, job_id) == last)  # what the preview was denoised with
    assert np.all(read_exr(client.download(job_id, tmp_path / "r.exr")).lam == last)  # and the result
    assert max(a["version"] for a in answers) == client.status(job_id)["preview_version"]


def test_a_lambda_edit_that_arrives_after_a_newer_one_is_dropped(server, client):
    job_id = client.submit("cornell-box", **SMALL)
    client.wait(job_id, progress=False)
    with httpx.Client(base_url=server.url, timeout=60) as raw:
        newer = raw.put(f"/jobs/{job_id}/lambda", json={"value": 7.0, "sequence": 200}).json()
        late = raw.put(f"/jobs/{job_id}/lambda", json={"value": 2.0, "sequence": 100})  # issued earlier, came late
        assert late.status_code == 200 and late.json()["version"] == newer["version"]
        assert np.all(lambda_layer(client, job_id) == 7.0)
        bad = raw.put(f"/jobs/{job_id}/lambda", json={"value": 2.0, "sequence": -1})
        assert bad.status_code == 422 and "sequence" in bad.json()["detail"]
        bad = raw.put(f"/jobs/{job_id}/lambda", data={"sequence": "soon"}, files={"map": ("m.png", b"x", "image/png")})
        assert bad.status_code == 422 and "sequence" in bad.json()["detail"]
    client.set_lambda(job_id, lambda_map=np.full((32, 32), 3.0), sequence=150)  # a late map upload
    assert np.all(lambda_layer(client, job_id) == 7.0)
    with httpx.Client(base_url=server.url, timeout=60) as raw:
        # Edits without a sequence keep the arrival order.
        assert raw.put(f"/jobs/{job_id}/lambda", json={"value": 4.0}).status_code == 200
    assert np.all(lambda_layer(client, job_id) == 4.0)
