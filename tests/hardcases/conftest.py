"""Hard cases end to end: tiny images, few iterations, the shipped networks (models/weights/*.pt):
the hard cases are about the networks users get."""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest
import torch

from models.pretrained import SHIPPED_WEIGHTS_DIR, load_networks

SIZE = 16  # film side of the XML hard-case scenes

# A camera looking down −Z at the origin; `extra` transforms follow the look-at (a frame move).
SENSOR = """
  <sensor type="perspective">
    <float name="fov" value="{fov}"/>
    <transform name="to_world"><lookat origin="0, 0, {distance}" target="0, 0, 0" up="0, 1, 0"/>{extra}</transform>
    <film type="hdrfilm"><integer name="width" value="{size}"/><integer name="height" value="{size}"/></film>
  </sensor>
"""
AREA_LIGHT = """
  <shape type="rectangle">
    <transform name="to_world"><scale value="0.5"/><rotate x="1" angle="90"/><translate y="2"/></transform>
    <emitter type="area"><rgb name="radiance" value="20"/></emitter>
  </shape>
"""
# name → (scene body, sensor overrides, <default> declarations)
SCENES: dict[str, tuple[str, dict, str]] = {
    # Emitters seen directly: a sphere light of radiance 5000 fills the middle of the frame.
    "direct-emitter": ("""
  <shape type="sphere"><float name="radius" value="0.6"/>
    <emitter type="area"><rgb name="radiance" value="5000, 4000, 3000"/></emitter></shape>
  <shape type="rectangle"><transform name="to_world"><scale value="3"/><translate z="-1"/></transform>
    <bsdf type="diffuse"/></shape>
""", {}, ""),
    # Pure black regions: a lit panel on the left, nothing at all (no environment) elsewhere.
    "black-regions": ("""
  <shape type="rectangle"><transform name="to_world"><scale x="0.8" y="3"/><translate x="-0.9"/></transform>
    <bsdf type="diffuse"/></shape>
  <emitter type="point"><point name="position" x="0" y="0" z="3"/><rgb name="intensity" value="10"/></emitter>
""", {}, ""),
    # Environment only: no shapes, every primary ray misses (no albedo, normal or depth anywhere).
    "environment-only": ("""
  <emitter type="constant"><rgb name="radiance" value="0.5, 0.7, 1.0"/></emitter>
""", {}, ""),
    # A zero-albedo sphere next to a glass (delta BSDF) sphere under a small area light.
    "black-and-glass": ("""
  <shape type="sphere"><point name="center" x="-0.6" y="0" z="0"/><float name="radius" value="0.5"/>
    <bsdf type="diffuse"><rgb name="reflectance" value="0"/></bsdf></shape>
  <shape type="sphere"><point name="center" x="0.6" y="0" z="0"/><float name="radius" value="0.5"/>
    <bsdf type="dielectric"/></shape>
  <shape type="rectangle"><transform name="to_world"><scale value="3"/><translate z="-1"/></transform>
    <bsdf type="diffuse"/></shape>
""" + AREA_LIGHT, {}, ""),
    # The camera jumps one unit sideways per frame while it sees only ~1.1 units of the wall:
    # each frame looks mostly at what the previous frame never saw.
    "camera-moves-off": ("""
  <shape type="sphere"><float name="radius" value="0.1"/><bsdf type="diffuse"/></shape>
  <shape type="rectangle"><transform name="to_world"><scale value="50"/><translate z="-0.5"/></transform>
    <bsdf type="diffuse"><texture type="checkerboard" name="reflectance"/></bsdf></shape>
  <emitter type="constant"/>
""", {"distance": 1.0, "extra": '<translate x="$frame"/>'}, '<default name="frame" value="0"/>'),
}


@pytest.fixture(scope="session")
def weights_dir() -> Path:
    return SHIPPED_WEIGHTS_DIR


@pytest.fixture(scope="session")
def nets() -> tuple[torch.nn.Module, torch.nn.Module]:
    """The shipped (trained) denoiser and error network: hard cases are about the real ones."""
    networks = load_networks()
    return networks.denoiser, networks.error_predictor


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Tiny tensors gain nothing from threads, and the test machine is shared."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def hard_scene(tmp_path: Path) -> Callable[[str], Path]:
    """hard_scene(name) → path of the XML file for SCENES[name]."""

    def write(name: str) -> Path:
        body, sensor, defaults = SCENES[name]
        options = {"fov": 40, "distance": 5.0, "extra": "", "size": SIZE, **sensor}
        path = tmp_path / f"{name}.xml"
        path.write_text(f'<scene version="3.0.0">\n{defaults}\n{SENSOR.format(**options)}\n{body}\n</scene>\n')
        return path

    return write
