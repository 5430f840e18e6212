"""Scene loading: built-ins, XML files, resolution override, sampler, errors."""
from __future__ import annotations

import numpy as np
import pytest

from service.render.runtime import mitsuba
from service.render.scenes import (
    MAX_PIXELS,
    MAX_RESOLUTION,
    SceneError,
    builtin_scene_names,
    describe_builtin_scenes,
    load_scene,
    load_scene_info,
)

REQUIRED_BUILTINS = {"cornell-box", "cornell-box-orbit", "glossy-spheres", "fireflies", "veiled"}
SPHERE = '<shape type="sphere"><bsdf type="diffuse"/></shape>'


def camera_matrix(scene) -> np.ndarray:
    return np.asarray(scene.sensors()[0].world_transform().matrix).reshape(4, 4)


def ray_direction(scene, film_uv: tuple[float, float]) -> np.ndarray:
    mi = mitsuba()
    ray, _ = scene.sensors()[0].sample_ray(0.0, 0.0, mi.Point2f(*film_uv), mi.Point2f(0.5, 0.5))
    return np.asarray(ray.d).ravel()


def test_builtin_names_and_descriptions_line_up():
    names = builtin_scene_names()
    assert REQUIRED_BUILTINS <= set(names)
    described = describe_builtin_scenes()
    assert [name for name, _ in described] == names
    for _, line in described:
        assert line and "\n" not in line


@pytest.mark.parametrize("name", sorted(REQUIRED_BUILTINS))
def test_every_builtin_loads_at_a_custom_resolution_with_an_independent_sampler(name):
    scene = load_scene(name, width=24, height=16)
    sensor = scene.sensors()[0]
    assert list(sensor.film().size()) == [24, 16]
    assert list(sensor.film().crop_size()) == [24, 16]
    assert sensor.sampler().class_name() == "IndependentSampler"


def test_resized_film_gets_a_camera_projection_for_the_new_aspect():
    # Resizing after loading (mi.traverse 'film.size') keeps the old projection; ours must
    # match a scene declared at that size from the start.
    mi = mitsuba()
    declared = mi.cornell_box()
    declared["sensor"]["film"].update(width=32, height=16)
    reference = mi.load_dict(declared)
    resized = load_scene("cornell-box", width=32, height=16)
    for uv in [(0.0, 0.0), (1.0, 0.5), (0.5, 0.5)]:
        np.testing.assert_allclose(ray_direction(resized, uv), ray_direction(reference, uv), atol=1e-5)


def test_one_side_override_keeps_the_other_side():
    assert list(load_scene("cornell-box", width=20).sensors()[0].film().size()) == [20, 256]


def test_orbit_camera_moves_between_frames_and_starts_at_the_static_view():
    frame0 = camera_matrix(load_scene("cornell-box-orbit", width=8, height=8, frame=0))
    frame1 = camera_matrix(load_scene("cornell-box-orbit", width=8, height=8, frame=1))
    static = camera_matrix(load_scene("cornell-box", width=8, height=8, frame=1))
    assert not np.allclose(frame0, frame1)
    np.testing.assert_allclose(frame0, static, atol=1e-6)


def test_builtin_max_depth_is_reported():
    assert load_scene_info("cornell-box").max_depth == 8
    assert load_scene_info("glossy-spheres").max_depth > 8


def test_xml_with_relative_texture_loads_from_any_working_directory(tmp_path, write_scene_xml, monkeypatch):
    from PIL import Image

    path = write_scene_xml(
        '<shape type="sphere"><bsdf type="diffuse">'
        '<texture type="bitmap" name="reflectance"><string name="filename" value="textures/grey.png"/></texture>'
        "</bsdf></shape>",
        name="bundle/scene.xml",
    )
    (path.parent / "textures").mkdir()
    Image.fromarray(np.full((4, 4, 3), 200, np.uint8)).save(path.parent / "textures" / "grey.png")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    before = str(mitsuba().file_resolver())
    scene = load_scene(path, width=6, height=4)
    assert list(scene.sensors()[0].film().size()) == [6, 4]
    # The asset root is only borrowed for the load.
    assert str(mitsuba().file_resolver()) == before


def test_xml_stratified_sampler_is_kept_as_declared_with_its_count(write_scene_xml):
    sensor = """
      <sensor type="perspective">
        <sampler type="stratified"><integer name="sample_count" value="16"/><boolean name="jitter" value="false"/></sampler>
        <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>
      </sensor>"""
    sampler = load_scene(write_scene_xml(SPHERE, sensor=sensor)).sensors()[0].sampler()
    # the renderer reads its kind (stratified_sequence.is_stratifying), never draws from it
    assert sampler.class_name() == "StratifiedSampler"
    assert sampler.sample_count() == 16


def test_xml_frame_parameter_is_passed_only_when_declared(write_scene_xml, tmp_path):
    animated_sensor = """
      <sensor type="perspective">
        <transform name="to_world"><lookat origin="$frame, 0, 5" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>
      </sensor>"""
    animated = write_scene_xml(SPHERE, sensor=animated_sensor, defaults='<default name="frame" value="0"/>')
    assert not np.allclose(camera_matrix(load_scene(animated, frame=0)), camera_matrix(load_scene(animated, frame=2)))
    assert load_scene_info(animated).declares_frame
    static = write_scene_xml(SPHERE, name="static.xml")
    assert not load_scene_info(static, frame=5).declares_frame  # no "unused parameter" error


def test_xml_width_height_parameters_receive_the_override(write_scene_xml):
    sensor = """
      <sensor type="perspective">
        <film type="hdrfilm"><integer name="width" value="$width"/><integer name="height" value="$height"/></film>
      </sensor>"""
    defaults = '<default name="width" value="64"/><default name="height" value="48"/>'
    path = write_scene_xml(SPHERE, sensor=sensor, defaults=defaults)
    assert list(load_scene(path).sensors()[0].film().size()) == [64, 48]
    assert list(load_scene(path, width=10, height=6).sensors()[0].film().size()) == [10, 6]


def test_xml_sensor_without_film_gets_the_override(write_scene_xml):
    path = write_scene_xml(SPHERE, sensor='<sensor type="perspective"/>')
    assert list(load_scene(path, width=12, height=9).sensors()[0].film().size()) == [12, 9]


def test_xml_crop_window_is_dropped_when_resized(write_scene_xml):
    sensor = """
      <sensor type="perspective">
        <film type="hdrfilm">
          <integer name="width" value="64"/><integer name="height" value="64"/>
          <integer name="crop_width" value="16"/><integer name="crop_height" value="16"/>
        </film>
      </sensor>"""
    film = load_scene(write_scene_xml(SPHERE, sensor=sensor), width=20, height=10).sensors()[0].film()
    assert list(film.crop_size()) == [20, 10]


def test_xml_integrator_max_depth_is_kept(write_scene_xml):
    path = write_scene_xml(SPHERE + '<integrator type="path"><integer name="max_depth" value="3"/></integrator>')
    assert load_scene_info(path).max_depth == 3
    assert load_scene_info(write_scene_xml(SPHERE, name="plain.xml")).max_depth is None


def test_unknown_builtin_lists_the_known_ones():
    with pytest.raises(SceneError, match="unknown built-in scene 'cornel-box'.*cornell-box"):
        load_scene("cornel-box")


def test_missing_file(tmp_path):
    with pytest.raises(SceneError, match="not found"):
        load_scene(tmp_path / "nope.xml")
    with pytest.raises(SceneError, match="not found"):
        load_scene(str(tmp_path / "nope.xml"))
    with pytest.raises(SceneError, match="folder"):
        load_scene(tmp_path)


def test_malformed_xml_is_one_line_with_mitsubas_reason(tmp_path):
    path = tmp_path / "broken.xml"
    path.write_text('<scene version="3.0.0">\n  <shape type="sphere">\n</scene>\n')
    with pytest.raises(SceneError) as caught:
        load_scene(path)
    message = str(caught.value)
    assert "\n" not in message and "broken.xml" in message and "line" in message
    assert ".cpp:" not in message


def test_unknown_plugin_is_a_scene_error(write_scene_xml):
    with pytest.raises(SceneError, match="spherez"):
        load_scene(write_scene_xml('<shape type="spherez"/>'))


def test_scene_without_sensor_is_rejected(write_scene_xml):
    with pytest.raises(SceneError, match="no <sensor>"):
        load_scene(write_scene_xml(SPHERE, sensor=""))


@pytest.mark.parametrize(
    "size, reason",
    [
        ({"width": 0}, "between 1"),
        ({"height": -4}, "between 1"),
        ({"width": MAX_RESOLUTION + 1}, "between 1"),
        ({"width": MAX_RESOLUTION, "height": MAX_PIXELS // MAX_RESOLUTION + 1}, "cap"),
        ({"width": 2.5}, "integer"),
        ({"width": True}, "integer"),
    ],
)
def test_absurd_resolutions_are_rejected(size, reason):
    with pytest.raises(SceneError, match=reason):
        load_scene("cornell-box", **size)


def test_numpy_integer_resolution_is_accepted():
    assert list(load_scene("cornell-box", width=np.int64(8), height=np.int32(4)).sensors()[0].film().size()) == [8, 4]


def test_declared_film_above_the_cap_is_rejected(write_scene_xml):
    sensor = """
      <sensor type="perspective">
        <film type="hdrfilm"><integer name="width" value="100000"/><integer name="height" value="8"/></film>
      </sensor>"""
    with pytest.raises(SceneError, match="100000x8"):
        load_scene(write_scene_xml(SPHERE, sensor=sensor))


def test_negative_frame_is_rejected():
    with pytest.raises(SceneError, match="frame"):
        load_scene("cornell-box", frame=-1)


def test_tiny_render_of_every_builtin_is_finite():
    # Cheap smoke test: 8x8 at 2 spp with each scene's own integrator choice.
    from service.render.effects import inspect_scene, make_integrator

    mi = mitsuba()
    for name in sorted(REQUIRED_BUILTINS):
        scene = load_scene(name, width=8, height=8)
        image = np.asarray(mi.render(scene, integrator=make_integrator(inspect_scene(name, width=8, height=8)), spp=2))
        assert image.shape == (8, 8, 3) and np.isfinite(image).all() and image.mean() > 0, name
