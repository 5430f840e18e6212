"""The scene exactly as written, through the API: an uploaded scene with a misspelt property is
refused at submit (422, the CLI's message), and a bundle job with no stopping rule renders the
scene's own sampler sample_count, which the job record names as its budget."""
from __future__ import annotations

import json

import httpx
import pytest

from service_harness import finished, wait_for, zip_bytes

SCENE = """<scene version="3.0.0">
    <default name="spp" value="4"/>
    <integrator type="path">
        <integer name="{depth}" value="3"/>
    </integrator>
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0,0,4" target="0,0,0" up="0,1,0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
        <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film>
    </sensor>
    <shape type="sphere"><bsdf type="diffuse"/></shape>
    <emitter type="constant"/>
</scene>
"""


@pytest.fixture(scope="module")
def server(module_server):
    return module_server


def submit(client: httpx.Client, depth_name: str, spec: dict) -> httpx.Response:
    archive = zip_bytes({"scene.xml": SCENE.format(depth=depth_name)})
    return client.post("/jobs", data={"spec": json.dumps(spec)}, files={"bundle": ("scene.zip", archive, "application/zip")})


def test_bundle_with_a_misspelt_property_is_422_naming_it_and_its_line(server, client):
    response = submit(client, "max_dpeth", {"max_iterations": 1, "denoise": False})
    assert response.status_code == 422, response.text
    assert response.json()["detail"] == ("spec: "  # the location, as every 422 of a bundle spec
                                         'scene.xml:4: unreferenced property "max_dpeth" in integrator plugin of type '
                                         '"path", which reads no property of that name (misspelt?)')


def test_bundle_job_without_a_stopping_rule_ends_at_the_scenes_sample_count(server, client):
    response = submit(client, "max_depth", {"params": {"spp": "32"}, "denoise": False})
    assert response.status_code == 202, response.text
    job = wait_for(client, response.json()["id"], finished)
    assert job["state"] == "completed", job
    assert job["spp"] == pytest.approx(32.0)
    assert job["stop_reason"] == "spp_budget"
    assert (job["spec"]["spp_budget"], job["spec"]["budget_source"], job["spec"]["max_iterations"]) == (32.0, "scene", None)


def test_bundle_job_with_a_stopping_rule_keeps_it(server, client):
    response = submit(client, "max_depth", {"params": {"spp": "32"}, "denoise": False, "max_iterations": 1})
    assert response.status_code == 202, response.text
    job = wait_for(client, response.json()["id"], finished)
    assert job["state"] == "completed" and job["spp"] == pytest.approx(16.0), job
    assert job["spec"]["budget_source"] is None


def test_budget_source_is_the_servers_to_set_not_the_clients(server, client):
    response = submit(client, "max_depth", {"budget_source": "scene"})
    assert response.status_code == 422, response.text
