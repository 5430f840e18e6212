"""Mitsuba's own checks hold for our loads too: a property no plugin reads (a misspelt name) is
refused with one line naming the property and the user's file:line — as `mi.load_file` refuses
it — in the loader and end to end through the CLI (`render`, `render --explain`)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from service.render.scenes import SceneError, load_scene_info

REPO = Path(__file__).resolve().parents[2]
RENDERLOOP = Path(sys.executable).with_name("renderloop")
SENSOR = """    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0,0,4" target="0,0,0" up="0,1,0"/></transform>
        <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film>
    </sensor>"""
OBJECTS = """    <shape type="sphere"><bsdf type="diffuse"/></shape>
    <emitter type="constant"/>"""


def integrator_scene(depth_name: str) -> str:
    """A scene whose integrator's max depth sits on line 3 of the file under `depth_name`."""
    return (f'<scene version="3.0.0">\n    <integrator type="path">\n'
            f'        <integer name="{depth_name}" value="8"/>\n    </integrator>\n{SENSOR}\n{OBJECTS}\n</scene>\n')


def write(folder: Path, name: str, text: str) -> Path:
    path = folder / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(RENDERLOOP), *args], capture_output=True, text=True, timeout=300, cwd=REPO)


def test_misspelt_integrator_property_is_refused_at_its_own_line(tmp_path):
    path = write(tmp_path, "bad.xml", integrator_scene("max_dpeth"))
    with pytest.raises(SceneError) as error:
        load_scene_info(path)
    assert str(error.value).startswith('bad.xml:3: unreferenced property "max_dpeth"'), error.value
    assert 'integrator plugin of type "path"' in str(error.value)


def test_correctly_spelt_property_still_loads(tmp_path):
    loaded = load_scene_info(write(tmp_path, "good.xml", integrator_scene("max_depth")))
    assert loaded.max_depth == 8


def test_misspelt_property_in_an_included_file_names_that_file_and_line(tmp_path):
    sensor = SENSOR.replace('<film', '<float name="fov_axiz" value="40"/>\n        <film')
    write(tmp_path, "parts/camera.xml", f'<scene version="3.0.0">\n{sensor}\n</scene>\n')
    main = write(tmp_path, "main.xml", f'<scene version="3.0.0">\n    <include filename="parts/camera.xml"/>\n{OBJECTS}\n</scene>\n')
    with pytest.raises(SceneError, match=r'^parts/camera\.xml:4: unreferenced property "fov_axiz" in sensor plugin'):
        load_scene_info(main)


def test_several_misspelt_properties_are_each_named_with_their_line(tmp_path):
    text = integrator_scene("max_dpeth").replace('value="8"/>', 'value="8"/>\n        <integer name="rr_dpeth" value="5"/>')
    with pytest.raises(SceneError) as error:
        load_scene_info(write(tmp_path, "two.xml", text))
    assert '"max_dpeth" (two.xml:3)' in str(error.value) and '"rr_dpeth" (two.xml:4)' in str(error.value)


@pytest.mark.parametrize("explain", [False, True], ids=["render", "explain"])
def test_cli_refuses_a_misspelt_property_in_one_error_line(tmp_path, explain):
    path = write(tmp_path, "bad.xml", integrator_scene("max_dpeth"))
    extra = ["--explain"] if explain else ["--spp", "1", "--no-denoise", "-o", str(tmp_path / "out.exr")]
    result = cli("render", str(path), *extra)
    assert result.returncode == 2, result.stdout + result.stderr
    lines = result.stderr.strip().splitlines()
    assert lines == [f'renderloop: error: bad.xml:3: unreferenced property "max_dpeth" in integrator plugin of type '
                     f'"path", which reads no property of that name (misspelt?)'], result.stderr
    assert not (tmp_path / "out.exr").exists()
