"""A walled scene load starts no thread that outlives it: Landlock domains pass to the threads
a restricted thread starts, so a Dr.Jit pool worker born inside the first walled load would read
only that scene's folder for the rest of the process, and a later parallel (unwalled) load whose
texture task lands on that worker failed with 'Permission denied' (renderloop bench
--versus-mitsuba: fine_texture's newspaper.png after dof_desk's loop). Run in a fresh process:
the pool is process-wide, and this test process has long started it."""
from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

pytestmark = pytest.mark.requires("landlock")
REPO = Path(__file__).resolve().parents[2]
TEXTURES = 12  # many instantiation tasks, so the pool worker takes some of them

FIRST_SCENE = """<scene version="3.0.0">
  <integrator type="direct"/>
  <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="8"/>
    <integer name="height" value="8"/></film></sensor>
  <shape type="sphere"/>
</scene>"""


def textured_scene(folder: Path) -> Path:
    folder.mkdir()
    shapes = []
    for i in range(TEXTURES):
        Image.fromarray(np.full((4, 4, 3), 20 * i, dtype=np.uint8)).save(folder / f"tex{i}.png")
        shapes.append(f'<shape type="sphere"><point name="center" x="{3 * i}" y="0" z="0"/><bsdf type="diffuse">'
                      f'<texture name="reflectance" type="bitmap"><string name="filename" value="tex{i}.png"/>'
                      "</texture></bsdf></shape>")
    path = folder / "scene.xml"
    path.write_text('<scene version="3.0.0"><integrator type="direct"/>' + "".join(shapes) + "</scene>")
    return path


def test_a_walled_load_leaves_no_walled_pool_thread_behind(tmp_path):
    first = tmp_path / "first"
    first.mkdir()
    (first / "scene.xml").write_text(FIRST_SCENE)
    second = textured_scene(tmp_path / "second")
    script = textwrap.dedent(f"""
        import os
        from service.render.runtime import mitsuba
        from service.render.scenes import load_scene_info
        mi = mitsuba()
        threads = set(os.listdir("/proc/self/task"))
        load_scene_info({str(first / "scene.xml")!r})   # walled: reads only {first.name}/
        print("threads started by the walled load:", len(set(os.listdir("/proc/self/task")) - threads))
        for attempt in range(5):                        # parallel, unwalled: the pool opens files
            mi.load_file({str(second)!r})
        print("second scene loaded")
    """)
    result = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0 and "second scene loaded" in result.stdout, result.stderr[-2000:]
    started = int(result.stdout.split("threads started by the walled load:")[1].split()[0])
    # The walled thread itself may still be unwinding after its join; no pool worker is new.
    assert started <= 1, result.stdout
