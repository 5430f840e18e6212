"""Issue 12's scene-bundle repros against a real `renderloop serve` subprocess.

Each hostile bundle must be refused at submit (4xx) with a message that names the offending
value and shows neither server paths nor file contents; legitimate bundles with includes and
textures in sub-folders must render to `completed`.
"""
from __future__ import annotations

import time

import httpx
import numpy as np
import pytest

from service_harness import REPO, finished, renderloop_cli, wait_for, zip_bytes
from service.render.runtime import mitsuba

SPEC = '{"width": 8, "height": 8, "max_iterations": 1}'
SENSOR = """<sensor type="perspective"><transform name="to_world"><lookat origin="0,0,4" target="0,0,0" up="0,1,0"/></transform>
  <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film></sensor>
  <emitter type="constant"/>"""


def scene(body: str, sensor: bool = True) -> str:
    return f'<scene version="3.0.0">\n{SENSOR if sensor else ""}\n{body}\n</scene>\n'


def textured_sphere(path: str, name: str = "filename") -> str:
    return (f'<shape type="sphere"><bsdf type="diffuse"><texture type="bitmap" name="reflectance">'
            f'<string name="{name}" value="{path}"/></texture></bsdf></shape>')


@pytest.fixture(scope="module")
def png(tmp_path_factory) -> bytes:
    mi = mitsuba()
    path = tmp_path_factory.mktemp("png") / "tex.png"
    image = mi.Bitmap(np.full((2, 2, 3), 0.5, dtype=np.float32))
    image.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, True).write(str(path))
    return path.read_bytes()


@pytest.fixture(scope="module")
def server(module_server):
    return module_server



def submit(client, members: dict, spec: str = SPEC) -> httpx.Response:
    archive = zip_bytes(members)
    return client.post("/jobs", data={"spec": spec}, files={"bundle": ("scene.zip", archive, "application/zip")})


def assert_refused(server, client, members: dict, named: str) -> str:
    jobs_before = set((server.data_dir / "jobs").iterdir()) if (server.data_dir / "jobs").exists() else set()
    response = submit(client, members)
    assert 400 <= response.status_code < 500, response.text
    detail = response.json()["detail"]
    assert named in detail
    for secret in (str(server.data_dir), str(REPO), "root:x:0", "/root"):
        assert secret not in detail
    jobs_after = set((server.data_dir / "jobs").iterdir()) if (server.data_dir / "jobs").exists() else set()
    assert jobs_after == jobs_before  # nothing kept, nothing queued
    return detail


def test_dollar_in_a_bitmap_property_name_cannot_read_an_outside_image(server, client, png):
    outside = server.data_dir.parent / "outside.png"
    outside.write_bytes(png)
    body = '<default name="n" value="filename"/>' + textured_sphere(str(outside), name="$n")
    assert_refused(server, client, {"scene.xml": scene(body)}, "absolute paths are not allowed")


def test_dollar_in_a_ply_property_name_cannot_read_etc_passwd(server, client):
    body = '<default name="n" value="filename"/><shape type="ply"><string name="$n" value="/etc/passwd"/></shape>'
    assert_refused(server, client, {"scene.xml": scene(body)}, "'/etc/passwd'")


def test_duplicate_defaults_first_one_absolute_is_refused(server, client, png):
    body = '<default name="p" value="/abs/red.png"/><default name="p" value="g.png"/>' + textured_sphere("$p")
    assert_refused(server, client, {"scene.xml": scene(body), "g.png": png}, "'/abs/red.png'")


def test_parents_default_overriding_the_childs_inside_an_include_is_refused(server, client, png):
    child = scene('<default name="p" value="g.png"/>' + textured_sphere("$p"), sensor=False)
    members = {"scene.xml": scene('<default name="p" value="/abs/red.png"/><include filename="sub/child.xml"/>'),
               "sub/child.xml": child, "g.png": png, "sub/g.png": png}
    detail = assert_refused(server, client, members, "'/abs/red.png'")
    assert detail.startswith("sub/child.xml:")


def test_relative_path_inside_an_include_does_not_fall_back_to_a_decoy_or_the_cwd(server, client, png):
    child = scene(textured_sphere("outside/red.png"), sensor=False)
    members = {"scene.xml": scene('<include filename="sub/child.xml"/>'), "sub/child.xml": child,
               "sub/outside/red.png": png}
    assert_refused(server, client, members, "'outside/red.png' is not in the bundle")


def test_bundle_with_includes_and_a_sub_folder_texture_completes(client, png):
    child = scene(textured_sphere("sub/tex.png"), sensor=False)
    members = {"scene.xml": scene('<default name="r" value="1"/><include filename="sub/child.xml"/>'),
               "sub/child.xml": child, "sub/tex.png": png}
    response = submit(client, members)
    assert response.status_code == 202, response.text
    job = wait_for(client, response.json()["id"], finished)
    assert job["state"] == "completed", job


def test_zipped_scene_folder_completes(client, png):
    members = {"myscene/scene.xml": scene('<include filename="parts/ball.xml"/>'),
               "myscene/parts/ball.xml": scene(textured_sphere("textures/tex.png"), sensor=False),
               "myscene/textures/tex.png": png}
    response = submit(client, members)
    assert response.status_code == 202, response.text
    assert wait_for(client, response.json()["id"], finished)["state"] == "completed"


def test_file_and_folder_of_one_name_and_long_names_are_4xx(server, client):
    assert_refused(server, client, {"scene.xml": scene(""), "a": "x", "a/b.txt": "y"}, "is both a file and a folder")
    assert_refused(server, client, {"scene.xml": scene(""), "x" * 300 + ".png": "x"}, "longer than 255 bytes")


def deep_scene(depth: int) -> str:
    return scene('<shape type="sphere">' * depth + "</shape>" * depth)


def test_xml_nested_thousands_deep_is_422_not_500(server, client):
    detail = assert_refused(server, client, {"scene.xml": deep_scene(5000)}, "nested deeper than")
    assert detail.startswith("scene.xml:")


def test_xml_nested_thousands_deep_is_one_cli_error_line(tmp_path):
    path = tmp_path / "deep.xml"
    path.write_text(deep_scene(5000))
    result = renderloop_cli("render", str(path), "-o", str(tmp_path / "out.exr"))
    assert result.returncode == 2, result.stderr
    assert result.stderr.startswith("renderloop: error: deep.xml:"), result.stderr
    assert "nested deeper than" in result.stderr and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr


def many_files(count: int) -> dict[str, str]:
    members = {"scene.xml": scene('<shape type="sphere"/>')}
    members.update({f"d{i % 64}/f{i}.txt": "x" for i in range(count - 1)})
    return members


def test_4096_loose_files_are_accepted_within_seconds(client):
    files = [("files", (name, data.encode(), "application/octet-stream")) for name, data in many_files(4096).items()]
    started = time.monotonic()
    response = client.post("/jobs", data={"spec": SPEC}, files=files, timeout=120)
    elapsed = time.monotonic() - started
    assert response.status_code == 202, response.text
    assert elapsed < 15, f"4096 file names took {elapsed:.1f} s"  # quadratic layout check: a minute


def test_4096_files_in_a_zip_are_accepted_within_seconds(client):
    started = time.monotonic()
    response = submit(client, many_files(4096))
    elapsed = time.monotonic() - started
    assert response.status_code == 202, response.text
    assert elapsed < 15, f"4096 zip entries took {elapsed:.1f} s"


def test_a_zip_claiming_more_entries_than_the_cap_is_refused_before_its_directory_is_read(server, client):
    archive = bytearray(zip_bytes({f"{i}.txt": "" for i in range(3 * 4096)}))
    # The directory itself is spoilt: only the end record's count can name the cap.
    archive[:] = archive.replace(b"PK\x01\x02", b"XX\x01\x02")
    response = client.post("/jobs", data={"spec": SPEC}, files={"bundle": ("s.zip", bytes(archive), "application/zip")})
    assert response.status_code == 422, response.text
    assert response.json()["detail"] == "bundle: 12288 entries, above the cap of 4096 files"
