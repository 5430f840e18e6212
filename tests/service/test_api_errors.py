"""Bad input over real HTTP: 404, 422 with field messages, hostile bundles named. No rendering."""
from __future__ import annotations

import socket

import pytest

from service_harness import zip_bytes
from service.api.app import MAX_UPLOAD_BYTES

JOB = {"scene": "cornell-box", "width": 16, "height": 16, "max_iterations": 1}
SCENE = """<scene version="3.0.0">
  <texture type="bitmap" id="t"><string name="filename" value="{path}"/></texture>
</scene>"""
BOMB = """<?xml version="1.0"?>
<!DOCTYPE scene [<!ENTITY a "aaaaaaaaaa"><!ENTITY b "&a;&a;&a;&a;&a;&a;&a;&a;&a;&a;">]>
<scene version="3.0.0"><string name="x" value="&b;"/></scene>"""


@pytest.fixture(scope="module")
def server(module_server):
    return module_server



def upload(client, archive: bytes, spec: str = '{"width": 16, "height": 16, "max_iterations": 1}'):
    return client.post("/jobs", data={"spec": spec}, files={"bundle": ("scene.zip", archive, "application/zip")})


def test_unknown_job_is_404(client):
    for method, path in [("GET", "/jobs/nope"), ("GET", "/jobs/nope/preview"), ("POST", "/jobs/nope/cancel"),
                         ("GET", "/jobs/nope/result.exr"), ("GET", "/jobs/nope/events")]:
        response = client.request(method, path)
        assert response.status_code == 404, path
        assert "nope" in response.json()["detail"]
    response = client.put("/jobs/nope/lambda", json={"value": 2.0})
    assert response.status_code == 404


@pytest.mark.parametrize(
    "change, field",
    [
        ({"width": -4}, "width"),
        ({"height": 0}, "height"),
        ({"width": 5000, "height": 16}, "width"),
        ({"allocator": "magic"}, "allocator"),
        ({"lambda": 11}, "lambda"),
        ({"lambda": 0.5}, "lambda"),
        ({"frames": 17}, "frames"),
        ({"max_iterations": 13}, "max_iterations"),
        ({"time_limit": -1}, "time_limit"),
        ({"target_error": 0}, "target_error"),
        ({"scene": "../../etc/passwd"}, "scene"),
        ({"scene": "no-such-scene"}, "scene"),
        ({"colour": "red"}, "colour"),
        ({"max_iterations": None}, "stopping rule"),
        ({"max_iterations": None, "time_limit": 10}, "max_iterations or spp_budget"),
        ({"spp_budget": 8}, "below spp_first"),
        ({"width": "32"}, "width"),
        ({"denoise": "yes"}, "denoise"),
        ({"lambda": 11}, "[1, 10]"),
    ],
)
def test_bad_job_bodies_are_422(client, change, field):
    response = client.post("/jobs", json={**JOB, **change})
    assert response.status_code == 422, response.text
    assert field in response.json()["detail"]


def test_malformed_json_is_422(client):
    response = client.post("/jobs", content=b"{not json", headers={"content-type": "application/json"})
    assert response.status_code == 422 and "JSON" in response.json()["detail"]


@pytest.mark.parametrize(
    "members, symlinks, named",
    [
        ({"scene.xml": SCENE.format(path="/etc/passwd")}, {}, "/etc/passwd"),
        ({"scene.xml": SCENE.format(path="../../secret.png")}, {}, "../../secret.png"),
        ({"scene.xml": SCENE.format(path="tex.png"), "../evil.png": "x"}, {}, "../evil.png"),
        ({"scene.xml": SCENE.format(path="tex.png")}, {"tex.png": "/etc/passwd"}, "tex.png"),
        ({"scene.xml": '<scene version="3.0.0"><include filename="../up.xml"/></scene>'}, {}, "../up.xml"),
        ({"scene.xml": BOMB}, {}, "scene.xml"),
    ],
    ids=["absolute", "dotdot-reference", "dotdot-member", "zip-symlink", "include-outside", "entity-bomb"],
)
def test_hostile_bundles_are_422_naming_the_path(client, server, members, symlinks, named):
    jobs_before = set((server.data_dir / "jobs").iterdir())
    response = upload(client, zip_bytes(members, symlinks))
    assert response.status_code == 422, response.text
    assert named in response.json()["detail"]
    assert set((server.data_dir / "jobs").iterdir()) == jobs_before  # nothing was kept


def test_bundle_upload_needs_files(client):
    response = client.post("/jobs", data={"spec": "{}"}, files={"other": ("x", b"x")})
    assert response.status_code == 422 and "bundle" in response.json()["detail"]


def test_loose_file_upload_with_escape_is_422(client):
    files = [("files", ("scene.xml", SCENE.format(path="tex.png").encode())), ("files", ("../tex.png", b"x"))]
    response = client.post("/jobs", data={"spec": "{}"}, files=files)
    assert response.status_code == 422 and "../tex.png" in response.json()["detail"]


def test_oversized_upload_is_413(server):
    # A raw socket: httpx will not send a Content-Length it does not honour.
    request = (
        "POST /jobs HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: multipart/form-data; boundary=x\r\n"
        f"Content-Length: {MAX_UPLOAD_BYTES + 1}\r\nConnection: close\r\n\r\n"
    )
    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as sock:
        sock.sendall(request.encode())
        reply = b""
        while chunk := sock.recv(65536):
            reply += chunk
    assert reply.startswith(b"HTTP/1.1 413") and b"cap" in reply


def test_bad_query_and_lambda_bodies(client):
    job = client.post("/jobs", json={**JOB, "max_iterations": 1}).json()
    assert client.get(f"/jobs/{job['id']}/preview", params={"layer": "bogus"}).status_code == 422
    assert client.get(f"/jobs/{job['id']}/preview", params={"frame": 3}).status_code == 422
    for body in [{"value": 11}, {"value": 0}, {"rects": [{"x": 0, "y": 0, "w": -1, "h": 4, "value": 2}]},
                 {"value": 2, "rects": [{"x": 0, "y": 0, "w": 1, "h": 1, "value": 2}]}, {}]:
        response = client.put(f"/jobs/{job['id']}/lambda", json=body)
        assert response.status_code == 422, body
        assert response.json()["detail"]


def test_healthz(client):
    body = client.get("/healthz").json()
    assert body["status"] == "ok" and set(body["jobs"]) == {"queued", "running", "completed", "failed", "canceled"}


@pytest.mark.parametrize("body", [
    {"scene": "cornell-box", "max_iterations": None, "spp_budget": 1e30},
    {"scene": "cornell-box", "frames": 16, "spp_first": 1024, "max_iterations": 12},
])
def test_api_rejects_a_job_whose_scene_film_exceeds_the_sample_cap_without_width_height(client, body):
    # No width/height: the cap applies to the scene's own film (256² for the built-in box).
    response = client.post("/jobs", json=body)
    assert response.status_code == 422, response.text
    assert "over the cap" in response.json()["detail"] and "256x256" in response.json()["detail"]


@pytest.mark.parametrize("raw", ['{"scene": "cornell-box", "max_iterations": 1, "spp_budget": Infinity}',
                                 '{"scene": "cornell-box", "max_iterations": 1, "target_error": NaN}'])
def test_non_finite_numbers_are_422(client, raw):
    response = client.post("/jobs", content=raw, headers={"content-type": "application/json"})
    assert response.status_code == 422, response.text


def test_a_json_integer_of_thousands_of_digits_is_422_not_500(client):
    raw = '{"scene": "cornell-box", "seed": ' + "9" * 5000 + "}"
    response = client.post("/jobs", content=raw, headers={"content-type": "application/json"})
    assert response.status_code == 422, response.text


def test_job_list_offset_beyond_sqlite_integers_is_422_not_500(client):
    assert client.get("/jobs", params={"offset": 9223372036854775808}).status_code == 422


def test_openapi_describes_request_bodies_and_error_answers(client):
    document = client.get("/openapi.json").json()
    submit = document["paths"]["/jobs"]["post"]
    assert set(submit["requestBody"]["content"]) == {"application/json", "multipart/form-data"}
    assert {"400", "401", "413", "415", "422"} <= set(submit["responses"])
    lam = document["paths"]["/jobs/{job_id}/lambda"]["put"]
    assert set(lam["requestBody"]["content"]) == {"application/json", "multipart/form-data"}
    preview = document["paths"]["/jobs/{job_id}/preview"]["get"]["responses"]
    assert {"200", "204", "304", "404", "409", "422"} <= set(preview)
    assert {"JobCreate", "LambdaUpdate", "ErrorBody"} <= set(document["components"]["schemas"])


def test_a_job_whose_memory_estimate_is_over_the_server_cap_is_422(client):
    body = {"scene": "cornell-box", "width": 2048, "height": 2048, "frames": 16, "spp_first": 1, "max_iterations": 1}
    response = client.post("/jobs", json=body)
    assert response.status_code == 422 and "GiB" in response.json()["detail"]


def test_json_nested_a_hundred_thousand_deep_is_422_not_500(client):
    raw = '{"scene": ' + "[" * 100_000 + "]" * 100_000 + "}"
    response = client.post("/jobs", content=raw, headers={"content-type": "application/json"})
    assert response.status_code == 422, response.text


@pytest.mark.parametrize("body, message", [
    ('<scene version="3.0.0"><shape type="sphere"/></scene>', "no <sensor>"),
    ('<scene version="3.0.0"><sensor type="perspective"/><shape type="no_such_plugin"/></scene>', "no_such_plugin"),
    ('<scene version="3.0.0"><integrator type="path"><integer name="max_depth" value="abc"/></integrator>'
     '<sensor type="perspective"/></scene>', "abc"),
])
def test_scene_errors_are_422_at_submit_with_mitsubas_message(client, body, message):
    response = client.post("/jobs", data={"spec": '{"max_iterations": 1}'},
                           files={"bundle": ("s.zip", zip_bytes({"scene.xml": body}), "application/zip")})
    assert response.status_code == 422, response.text
    assert message in response.json()["detail"] and "/tmp" not in response.json()["detail"]


def test_scenes_lists_every_builtin_with_its_size_and_effects_report(client):
    scenes = {scene["name"]: scene for scene in client.get("/scenes").json()["scenes"]}
    assert {"cornell-box", "fireflies", "veiled"} <= set(scenes)
    assert scenes["veiled"]["effects"]["media"] is True and scenes["veiled"]["effects"]["integrator"] == "volpath"
    assert scenes["cornell-box"]["width"] > 0 and "integrator_reason" in scenes["cornell-box"]["effects"]


def test_a_file_name_as_json_scene_says_to_upload_a_bundle(client):
    response = client.post("/jobs", json={"scene": "cbox.xml", "max_iterations": 1})
    assert response.status_code == 422
    detail = response.json()["detail"]
    assert "cbox.xml" in detail and "bundle" in detail and "GET /scenes" in detail and "^[" not in detail


STATIC_SCENE = """<scene version="3.0.0">
  <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="8"/>
  <integer name="height" value="8"/></film></sensor>
  <shape type="sphere"/>
</scene>"""


def test_a_sequence_of_a_scene_without_frame_is_refused_at_submit(client):
    response = upload(client, zip_bytes({"scene.xml": STATIC_SCENE}), '{"frames": 3, "max_iterations": 1}')
    assert response.status_code == 422, response.text
    assert "$frame" in response.json()["detail"] and "3 frames" in response.json()["detail"]
    assert upload(client, zip_bytes({"scene.xml": STATIC_SCENE}), '{"frames": 1, "max_iterations": 1}').status_code == 202
