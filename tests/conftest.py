"""Shared fixtures. Add fixtures here; never remove one another test relies on."""
from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import pytest
import torch

from models.denoiser import Denoiser, temporal_config
from models.error_predictor import ErrorPredictor, ErrorPredictorConfig
from models.pretrained import Networks
from required_components import require_component
from tests.models.conftest import PLAIN_ERROR_NETWORK

# The suite runs on shared 2-core machines, where torch's one-thread-per-core default makes
# small denoises 30× slower (docs/benchmarks.md); servers started by tests inherit this.
os.environ.setdefault("RENDERLOOP_TORCH_THREADS", "1")
# Servers started by tests keep the in-process thread backend unless a test asks for Ray
# (RENDERLOOP_CONCURRENCY="" plus RENDERLOOP_WORKERS): a local Ray runtime costs ~8 s to start
# and the suite starts dozens of servers on 2 cores. tests/service/test_ray_workers.py covers Ray.
os.environ.setdefault("RENDERLOOP_CONCURRENCY", "1")

# A camera that sees the unit sphere at the origin; tiny film so loads and renders stay cheap.
TINY_SENSOR_XML = """
  <sensor type="perspective">
    <float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0, 0, 5" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>
  </sensor>
"""


@pytest.fixture
def write_scene_xml(tmp_path: Path) -> Callable[..., Path]:
    """`write_scene_xml(body, *, sensor=TINY_SENSOR_XML, defaults="", name="scene.xml")` → path.

    Writes a Mitsuba 3 scene into tmp_path: `defaults` (e.g. `<default name="frame" value="0"/>`)
    first, then the sensor (pass sensor="" to leave it out), then `body`.
    """

    def write(body: str, *, sensor: str = TINY_SENSOR_XML, defaults: str = "", name: str = "scene.xml") -> Path:
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(f'<scene version="3.0.0">\n{defaults}\n{sensor}\n{body}\n</scene>\n')
        return path

    return write


@pytest.fixture(scope="session")
def tiny_networks() -> Networks:
    """Small untrained networks, seeded: the loop's plumbing (features cache, λ tail, error
    maps) runs through real networks at a fraction of the shipped ones' cost."""
    torch.manual_seed(0)
    denoiser = Denoiser(temporal_config(width=8, spatial_blocks=1)).eval()
    # The λ module starts as "no specialisation"; perturb it so λ visibly matters.
    with torch.no_grad():
        for parameter in denoiser.specialise.parameters():
            parameter.add_(torch.randn_like(parameter) * 0.5)
    return Networks(denoiser, ErrorPredictor(ErrorPredictorConfig(width=8, **PLAIN_ERROR_NETWORK)).eval())


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "requires(*names): the test drives these components for real; a missing one "
                                       "fails it, or skips it under ALLOW_SKIP=1 (tests/required_components.py)")


def pytest_runtest_setup(item: pytest.Item) -> None:
    for mark in item.iter_markers("requires"):
        for name in mark.args:
            require_component(name)
