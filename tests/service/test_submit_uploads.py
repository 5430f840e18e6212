"""`renderloop submit` uploads only what the scene references, asks which scene of a folder
before uploading, stores uploads once on the server, and names jobs. Real `renderloop`
subprocesses against a real server."""
from __future__ import annotations

import os
import shutil

import httpx
import pytest

from service.client import RenderloopClient
from service.jobs.blobs import BlobStore, file_digest, unique_bytes
from service.scene_upload import SceneUploadError, plan_upload
from service_harness import REPO, Server, free_port, renderloop_cli as renderloop
from required_components import require_component

TEXTURE = REPO / "scenes" / "dev" / "fine_texture" / "newspaper.png"
UNRELATED_BYTES = 40 * 2**20
CBOX = """<scene version="3.0.0">
    <default name="spp" value="8"/>
    <default name="wall" value="textures/wall.png"/>
    <include filename="parts/light.xml"/>
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0, 0, 3" target="0, 0, 0" up="0, 1, 0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
        <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="12"/></film>
    </sensor>
    <shape type="rectangle">
        <bsdf type="diffuse"><texture type="bitmap" name="reflectance"><string name="filename" value="$wall"/></texture></bsdf>
    </shape>
</scene>
"""
LIGHT = '<scene version="3.0.0"><emitter type="constant"/></scene>\n'
LEGO = """<scene version="3.0.0">
    <shape type="ply"><string name="filename" value="lego/lego.ply"/></shape>
</scene>
"""


@pytest.fixture(scope="module")
def server(module_server):
    return module_server


@pytest.fixture(scope="module")
def tutorials(tmp_path_factory):
    """The tutorials' folder: cbox.xml (an include, a texture named through a <default>) beside
    an unrelated 40 MB lego scene and an unused texture."""
    folder = tmp_path_factory.mktemp("tutorials")
    (folder / "parts").mkdir()
    (folder / "textures").mkdir()
    (folder / "lego").mkdir()
    (folder / "cbox.xml").write_text(CBOX)
    (folder / "parts" / "light.xml").write_text(LIGHT)
    shutil.copy(TEXTURE, folder / "textures" / "wall.png")
    shutil.copy(TEXTURE, folder / "textures" / "unused.png")
    (folder / "lego.xml").write_text(LEGO)
    (folder / "lego" / "lego.ply").write_bytes(os.urandom(UNRELATED_BYTES))
    return folder


def job(server, job_id: str) -> dict:
    return httpx.get(f"{server.url}/jobs/{job_id}", timeout=30).json()


def test_only_the_files_cbox_references_are_planned(tutorials):
    upload = plan_upload(tutorials / "cbox.xml")
    assert sorted(upload.files) == ["cbox.xml", "parts/light.xml", "textures/wall.png"]
    assert upload.entry == "cbox.xml" and upload.name == f"{tutorials.name}/cbox.xml"
    assert upload.size < 100_000
    other = plan_upload(tutorials / "cbox.xml", params={"wall": "textures/unused.png"})  # --param applied
    assert "textures/unused.png" in other.files and "textures/wall.png" not in other.files


def test_each_frame_s_files_are_planned_for_a_sequence(tmp_path):
    (tmp_path / "frames").mkdir()
    for frame in range(3):
        shutil.copy(TEXTURE, tmp_path / "frames" / f"wall_{frame}.png")
    (tmp_path / "anim.xml").write_text(CBOX.replace('value="textures/wall.png"', 'value="frames/wall_$frame.png"'))
    with pytest.raises(SceneUploadError, match=f"anim.xml:4: file not found: {tmp_path / 'parts' / 'light.xml'}$"):
        plan_upload(tmp_path / "anim.xml", frames=2)  # a missing file: its local path, before any upload
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "light.xml").write_text(LIGHT)
    upload = plan_upload(tmp_path / "anim.xml", frames=2)
    assert sorted(upload.files) == ["anim.xml", "frames/wall_0.png", "frames/wall_1.png", "parts/light.xml"]


def test_submitting_cbox_sends_only_its_files_and_the_job_renders_from_them(server, tutorials, tmp_path):
    out = tmp_path / "cbox.exr"
    result = renderloop("submit", str(tutorials / "cbox.xml"), "--server", server.url, "--spp", "4", "--png",
                        "-o", str(out))
    assert result.returncode == 0, result.stderr
    assert "uploading 3 file(s), 0.03 MiB" in result.stderr
    job_id = result.stdout.splitlines()[0]
    bundle = server.data_dir / "jobs" / job_id / "bundle"
    sent = sorted(p.relative_to(bundle).as_posix() for p in bundle.rglob("*") if p.is_file())
    assert sent == ["cbox.xml", "parts/light.xml", "textures/wall.png"]
    assert unique_bytes(bundle) < 5 * 2**20 < UNRELATED_BYTES  # the bound: under 5 MB
    assert (bundle / "textures" / "wall.png").stat().st_nlink >= 2  # a link to its blob
    assert out.stat().st_size > 0 and out.with_suffix(".png").stat().st_size > 0  # rendered behind the sandbox
    assert job(server, job_id)["name"] == f"{tutorials.name}/cbox.xml"


def test_a_folder_of_several_scenes_asks_for_one_before_uploading(tutorials):
    nowhere = f"http://127.0.0.1:{free_port()}"  # nothing listens: an attempted upload would say so
    result = renderloop("submit", str(tutorials), "--server", nowhere, "--spp", "4")
    assert result.returncode == 2
    assert result.stderr == (f"renderloop: error: {tutorials} holds several scenes (cbox.xml, lego.xml); "
                             "choose one with --scene NAME\n")


def test_scene_picks_the_folder_s_scene_and_name_names_the_job(server, tutorials):
    result = renderloop("submit", str(tutorials), "--scene", "cbox", "--server", server.url, "--spp", "4",
                        "--name", "cornell, take 2")
    assert result.returncode == 0, result.stderr
    job_id = result.stdout.strip()
    assert "uploading 3 file(s)" in result.stderr
    record = job(server, job_id)
    assert record["name"] == "cornell, take 2" and record["spec"]["name"] == "cornell, take 2"
    listed = httpx.get(f"{server.url}/jobs", timeout=30).json()["jobs"]
    assert next(j for j in listed if j["id"] == job_id)["name"] == "cornell, take 2"
    table = renderloop("jobs", "--server", server.url)
    assert any(line.startswith(job_id) and "cornell, take 2" in line for line in table.stdout.splitlines())


def test_a_builtin_job_is_named_after_its_scene(server):
    result = renderloop("submit", "cornell-box", "--server", server.url, "--width", "8", "--height", "8",
                        "--spp", "1")
    assert result.returncode == 0, result.stderr
    assert job(server, result.stdout.strip())["name"] == "cornell-box"


@pytest.mark.parametrize("name, message", [("", "at least 1 character"), ("two\nlines", "one printable line"),
                                           ("x" * 129, "at most 128 characters")])
def test_the_api_refuses_a_name_that_cannot_be_listed(server, name, message):
    body = {"scene": "cornell-box", "width": 8, "height": 8, "max_iterations": 1, "name": name}
    response = httpx.post(f"{server.url}/jobs", json=body, timeout=60)
    assert response.status_code == 422 and message in response.text


def test_submit_refuses_a_png_output_name_as_render_does(server):
    result = renderloop("submit", "cornell-box", "--server", server.url, "-o", "out.png")
    assert result.returncode == 2
    assert result.stderr == ("renderloop: error: output 'out.png' must end in .exr (add --png for a tonemapped PNG "
                             "beside it)\n")


def bundle_bytes(bundles: list) -> tuple[int, int]:
    """(bytes as `du` counts them: each inode once, bytes if every job had its own copy)."""
    files = [p for bundle in bundles for p in bundle.rglob("*") if p.is_file()]
    inodes = {(p.stat().st_dev, p.stat().st_ino): p.stat().st_size for p in files}
    return sum(inodes.values()), sum(p.stat().st_size for p in files)


@pytest.mark.slow  # ~90 s on 2 loaded cores (a scene check per submit); tests/service/test_blob_store.py is the fast twin
def test_twelve_jobs_of_one_upload_keep_one_copy_until_the_last_is_deleted(server, tutorials):
    blobs = BlobStore(server.data_dir)
    with RenderloopClient(server.url) as client:
        for earlier in client.jobs(limit=1000):  # this module's other jobs share the blobs: gone first
            client.wait(earlier["id"], progress=False)
            client.delete(earlier["id"])
        assert blobs.blobs() == []
        jobs = [client.submit(tutorials / "cbox.xml", spp_first=1, max_iterations=1) for _ in range(12)]
        assert all(client.wait(job_id, progress=False)["state"] == "completed" for job_id in jobs)
        texture = blobs.path_of(file_digest(tutorials / "textures" / "wall.png"))
        assert blobs.blobs() == [texture]  # the XMLs are under MIN_SHARED_BYTES: each job's own
        on_disk, copies = bundle_bytes([server.data_dir / "jobs" / job_id / "bundle" for job_id in jobs])
        xmls = (tutorials / "cbox.xml").stat().st_size + (tutorials / "parts" / "light.xml").stat().st_size
        assert on_disk == texture.stat().st_size + 12 * xmls  # one copy of the texture, not twelve
        assert copies == 12 * (texture.stat().st_size + xmls)
        assert texture.stat().st_nlink == 13
        for job_id in jobs[:-1]:
            client.delete(job_id)
        assert blobs.blobs() == [texture] and texture.stat().st_nlink == 2  # the last job still uses it
        client.delete(jobs[-1])
        assert blobs.blobs() == []


@pytest.mark.slow  # a local Ray runtime: ~10 s to start, a minute on a loaded machine
def test_a_ray_worker_renders_an_upload_from_its_links_behind_the_sandbox(tutorials, tmp_path):
    require_component("ray")
    server = Server(tmp_path / "data", tmp_path / "server.log", startup_seconds=300,
                    env={"RENDERLOOP_CONCURRENCY": "", "RENDERLOOP_WORKERS": "1"}).start()
    try:
        with RenderloopClient(server.url) as client:
            jobs = [client.submit(tutorials / "cbox.xml", spp_first=4, max_iterations=1) for _ in range(2)]
            assert [client.wait(job_id, progress=False)["state"] for job_id in jobs] == ["completed"] * 2
            assert client.preview(jobs[1]).shape == (12, 16, 3)
        texture = server.data_dir / "jobs" / jobs[1] / "bundle" / "textures" / "wall.png"
        assert texture.stat().st_nlink == 3  # its blob and both jobs
    finally:
        server.stop()
