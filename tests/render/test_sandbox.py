"""The kernel wall around scene loading (service/render/sandbox.py): a walled load reads its
own folder and the installed software, and nothing else — even when the flattener's check
has been raced."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from service.render import scenes
from service.render.runtime import mitsuba
from service.render.sandbox import run_walled

pytestmark = pytest.mark.requires("landlock")

TEXTURED_SQUARE = """
  <integrator type="direct"/>
  <emitter type="constant"/>
  <shape type="rectangle">
    <bsdf type="diffuse"><texture name="reflectance" type="bitmap"><string name="filename" value="tex.png"/></texture></bsdf>
  </shape>
"""


def write_png(path: Path, rgb: tuple[int, int, int]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.full((4, 4, 3), rgb, dtype=np.uint8)).save(path)
    return path


def read_text(path: Path | str) -> str:
    with open(path, encoding="utf-8", errors="replace") as handle:
        return handle.read()


def test_walled_thread_reads_its_folder_but_not_a_sibling(tmp_path):
    inside = tmp_path / "job"
    inside.mkdir()
    (inside / "ok.txt").write_text("inside")
    (tmp_path / "other-job.txt").write_text("secret")
    assert run_walled(lambda: read_text(inside / "ok.txt"), [inside]) == "inside"
    with pytest.raises(PermissionError):
        run_walled(lambda: read_text(tmp_path / "other-job.txt"), [inside])


def test_walled_thread_cannot_read_system_files_or_the_process_environment(tmp_path):
    for secret in ("/etc/passwd", "/proc/self/environ"):
        with pytest.raises(PermissionError):
            run_walled(lambda: read_text(secret), [tmp_path])


def test_wall_ends_with_its_thread(tmp_path):
    run_walled(lambda: None, [tmp_path])
    assert read_text("/etc/passwd")  # the caller's thread is never restricted


def test_walled_load_renders_a_texture_from_the_scene_folder(write_scene_xml, tmp_path):
    write_png(tmp_path / "tex.png", (255, 0, 0))
    loaded = scenes.load_scene_info(write_scene_xml(TEXTURED_SQUARE))
    image = np.asarray(mitsuba().render(loaded.scene, spp=4))
    centre = image[3:5, 3:5].reshape(-1, 3).mean(axis=0)
    assert centre[0] > 0.3 and centre[1] < 0.05  # red: the texture was read


def test_texture_swapped_for_an_outside_symlink_after_the_check_is_refused(write_scene_xml, tmp_path):
    """The race the second wall exists for: the flattener checked tex.png, then the file
    became a symlink to a file outside the scene folder before Mitsuba opened it."""
    bundle = tmp_path / "bundle"
    write_png(bundle / "tex.png", (255, 0, 0))
    outside = write_png(tmp_path / "outside" / "secret.png", (0, 255, 0))
    scene = bundle / "scene.xml"
    write_scene_xml(TEXTURED_SQUARE, name="bundle/scene.xml")
    mi = mitsuba()
    parsed = scenes._parse_scene(mi, scene, None, None, 0, None, bundle)
    (bundle / "tex.png").unlink()
    os.symlink(outside, bundle / "tex.png")
    with pytest.raises(scenes.SceneError) as refused:
        scenes._instantiate(mi, parsed)
    assert "Permission denied" in str(refused.value) or "permission" in str(refused.value).lower()
    assert str(tmp_path) not in str(refused.value)  # no server path in the message
