"""A file the scene names that does not exist: a local render (`renderloop render FILE.xml`)
says "file not found" with the path where it looked, not "not in the bundle" (it has none);
an uploaded bundle keeps the bundle's wording."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from service.render.scenes import SceneError, film_size

RENDERLOOP = Path(sys.executable).with_name("renderloop")
SCENE = """<scene version="3.0.0">
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0,0,4" target="0,0,0" up="0,1,0"/></transform>
        <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>
    </sensor>
    <shape type="obj"><string name="filename" value="meshes/box.obj"/></shape>
    <emitter type="constant"/>
</scene>
"""


@pytest.fixture
def scene(tmp_path) -> Path:
    path = tmp_path / "scene.xml"
    path.write_text(SCENE)
    return path


def test_a_local_render_of_a_scene_with_a_missing_mesh_says_file_not_found_with_its_path(scene):
    result = subprocess.run([str(RENDERLOOP), "render", str(scene), "--spp", "1", "--no-denoise",
                             "-o", str(scene.parent / "out.exr")], capture_output=True, text=True, timeout=300)
    assert result.returncode != 0
    missing = scene.parent / "meshes" / "box.obj"
    assert f"file not found: {missing}" in result.stderr, result.stderr
    assert "bundle" not in result.stderr


def test_a_bundle_missing_a_mesh_is_still_told_it_is_not_in_the_bundle(scene):
    with pytest.raises(SceneError, match="'meshes/box.obj' is not in the bundle"):
        film_size(scene, root=scene.parent)
