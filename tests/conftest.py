"""Shared fixtures. Add fixtures here; never remove one another test relies on."""
from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import pytest

# The suite runs on shared 2-core machines, where torch's one-thread-per-core default makes
# small denoises 30× slower (docs/benchmarks.md); servers started by tests inherit this.
os.environ.setdefault("RENDERLOOP_TORCH_THREADS", "1")

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
