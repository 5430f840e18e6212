"""The effects report pins what the renderer simulates for a scene, decision by decision."""
from __future__ import annotations

import numpy as np
import pytest

from service.render.effects import DEFAULT_MAX_DEPTH, SceneEffects, inspect_scene, make_integrator
from service.render.scenes import SceneError

LIGHT = '<emitter type="constant"/>'
DIFFUSE_SPHERE = '<shape type="sphere"><bsdf type="diffuse"/></shape>'
FOG_CUBE = """
  <shape type="cube">
    <bsdf type="null"/>
    <medium type="homogeneous" name="interior"><float name="sigma_t" value="1"/></medium>
  </shape>"""
FRAME_DEFAULT = '<default name="frame" value="0"/>'


def sphere_with(bsdf: str) -> str:
    return f'<shape type="sphere">{bsdf}</shape>' + LIGHT


def test_no_media_means_path(write_scene_xml):
    effects = inspect_scene(write_scene_xml(DIFFUSE_SPHERE + LIGHT))
    assert not effects.media and effects.integrator == "path"
    assert make_integrator(effects).class_name() == "PathIntegrator"


def test_media_means_volpath(write_scene_xml):
    effects = inspect_scene(write_scene_xml(FOG_CUBE + LIGHT))
    assert effects.media and effects.integrator == "volpath"
    # class_name() says VolumetricPathIntegrator while str() says VolumetricSimplePathIntegrator.
    assert make_integrator(effects).class_name().startswith("Volumetric")
    # The null boundary of a medium is no specular surface.
    assert not effects.delta_bsdf


def test_medium_on_the_camera_counts(write_scene_xml):
    sensor = """
      <sensor type="perspective">
        <medium type="homogeneous"><float name="sigma_t" value="0.1"/></medium>
        <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>
      </sensor>"""
    assert inspect_scene(write_scene_xml(DIFFUSE_SPHERE + LIGHT, sensor=sensor)).integrator == "volpath"


def test_builtin_integrator_choices():
    assert inspect_scene("veiled", width=8, height=8).integrator == "volpath"
    assert inspect_scene("cornell-box", width=8, height=8).integrator == "path"


def test_a_declared_integrator_runs_as_written_with_all_its_parameters(write_scene_xml):
    from service.render.scenes import load_scene

    declared = write_scene_xml(DIFFUSE_SPHERE + LIGHT + """<integrator type="path">
        <integer name="max_depth" value="3"/><integer name="rr_depth" value="2"/>
        <boolean name="hide_emitters" value="true"/></integrator>""")
    effects = inspect_scene(declared)
    assert effects.integrator_declared and effects.integrator == "path" and effects.max_depth == 3
    assert "declared" in effects.integrator_reason
    # None: the renderer uses each frame's own scene.integrator(), parameters and all.
    assert make_integrator(effects) is None
    own = str(load_scene(declared).integrator())
    assert "max_depth = 3" in own and "rr_depth = 2" in own  # hide_emitters: pinned by tests/fidelity


def test_only_an_undeclared_integrator_is_chosen_with_mitsubas_defaults(write_scene_xml):
    effects = inspect_scene(write_scene_xml(DIFFUSE_SPHERE + LIGHT, name="plain.xml"))
    assert not effects.integrator_declared and "chose 'path'" in effects.integrator_reason
    assert effects.max_depth == DEFAULT_MAX_DEPTH == -1
    assert "max_depth = 4294967295" in str(make_integrator(effects))  # -1 as unsigned: unbounded


def test_a_declared_direct_integrator_is_not_replaced_by_path(write_scene_xml):
    effects = inspect_scene(write_scene_xml(DIFFUSE_SPHERE + LIGHT + '<integrator type="direct"/>'))
    assert effects.integrator == "direct" and effects.integrator_declared


@pytest.mark.parametrize("body, words", [
    ('<integrator type="ptracer"/>', ["ptracer", "use 'path'"]),
    ('<integrator type="stokes"><integrator type="path"/></integrator>', ["stokes", "polarized"]),
])
def test_integrators_that_cannot_be_driven_per_pixel_are_refused_in_one_line(write_scene_xml, body, words):
    with pytest.raises(SceneError) as err:
        inspect_scene(write_scene_xml(DIFFUSE_SPHERE + LIGHT + body))
    message = str(err.value)
    assert "\n" not in message and all(w in message for w in words)


@pytest.mark.parametrize("sensor_type", ["radiancemeter", "irradiancemeter"])
def test_sensors_that_do_not_map_pixels_to_rays_are_refused(write_scene_xml, sensor_type):
    sensor = f'<sensor type="{sensor_type}"><film type="hdrfilm"><integer name="width" value="1"/><integer name="height" value="1"/></film></sensor>'
    with pytest.raises(SceneError, match=f"sensor '{sensor_type}' is not supported"):
        inspect_scene(write_scene_xml(DIFFUSE_SPHERE + LIGHT, sensor=sensor))


def test_make_integrator_rejects_other_integrators(write_scene_xml):
    effects = inspect_scene(write_scene_xml(DIFFUSE_SPHERE + LIGHT))
    with pytest.raises(ValueError, match="integrator"):
        make_integrator(SceneEffects(**{**effects.__dict__, "integrator": "bdpt"}))


def test_thin_lens_with_aperture_is_depth_of_field(write_scene_xml):
    thin_lens = """
      <sensor type="thinlens">
        <float name="aperture_radius" value="0.1"/><float name="focus_distance" value="5"/>
        <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>
      </sensor>"""
    assert inspect_scene(write_scene_xml(DIFFUSE_SPHERE + LIGHT, sensor=thin_lens)).depth_of_field
    assert not inspect_scene(write_scene_xml(DIFFUSE_SPHERE + LIGHT, name="pinhole.xml")).depth_of_field


def test_emitter_kinds(write_scene_xml, tmp_path):
    from PIL import Image

    Image.fromarray(np.full((4, 8, 3), 128, np.uint8)).save(tmp_path / "sky.png")
    lights = """
      <shape type="rectangle"><emitter type="area"/></shape>
      <emitter type="point"><point name="position" x="0" y="3" z="0"/></emitter>
      <emitter type="spot"/>
      <emitter type="directional"><vector name="direction" x="0" y="-1" z="0"/></emitter>
    """
    assert inspect_scene(write_scene_xml(lights)).emitters == ("area", "point", "spot", "directional")
    # Mitsuba allows one infinite (environment-like) emitter per scene: check those one by one.
    assert inspect_scene(write_scene_xml(LIGHT, name="constant.xml")).emitters == ("constant",)
    envmap = '<emitter type="envmap"><string name="filename" value="sky.png"/></emitter>'
    assert inspect_scene(write_scene_xml(envmap, name="env.xml")).emitters == ("environment",)


@pytest.mark.parametrize(
    "bsdf, glossy, delta",
    [
        ('<bsdf type="diffuse"/>', False, False),
        ('<bsdf type="roughconductor"><float name="alpha" value="0.2"/></bsdf>', True, False),
        ('<bsdf type="roughplastic"/>', True, False),
        ('<bsdf type="dielectric"/>', False, True),
        ('<bsdf type="conductor"/>', False, True),
        ('<bsdf type="twosided"><bsdf type="roughconductor"/></bsdf>', True, False),
    ],
)
def test_glossy_and_delta_detection(write_scene_xml, bsdf, glossy, delta):
    effects = inspect_scene(write_scene_xml(sphere_with(bsdf)))
    assert (effects.glossy, effects.delta_bsdf) == (glossy, delta)


def test_glossy_spheres_builtin_has_both():
    effects = inspect_scene("glossy-spheres", width=8, height=8)
    assert effects.glossy and effects.delta_bsdf


def test_single_frame_is_neither_temporal_nor_moving():
    effects = inspect_scene("cornell-box-orbit", width=8, height=8, frames=1)
    assert effects.frames == 1 and not effects.temporal and not effects.motion_vectors
    assert not effects.animated_camera


def test_animated_camera_needs_motion_vectors(write_scene_xml):
    sensor = """
      <sensor type="perspective">
        <transform name="to_world"><lookat origin="$frame, 0, 5" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>
      </sensor>"""
    effects = inspect_scene(write_scene_xml(DIFFUSE_SPHERE + LIGHT, sensor=sensor, defaults=FRAME_DEFAULT), frames=3)
    assert effects.animated_camera and not effects.animated_shapes
    assert effects.temporal and effects.motion_vectors


def test_animated_shape_needs_motion_vectors(write_scene_xml):
    moving = '<shape type="sphere"><point name="center" x="$frame" y="0" z="0"/></shape>' + LIGHT
    effects = inspect_scene(write_scene_xml(moving, defaults=FRAME_DEFAULT), frames=3)
    assert effects.animated_shapes and not effects.animated_camera and effects.motion_vectors


def test_static_xml_over_frames_is_temporal_without_motion(write_scene_xml):
    effects = inspect_scene(write_scene_xml(DIFFUSE_SPHERE + LIGHT), frames=3)
    assert effects.temporal and not effects.motion_vectors


def test_frame_parameter_that_moves_nothing_gives_no_motion(write_scene_xml):
    effects = inspect_scene(write_scene_xml(DIFFUSE_SPHERE + LIGHT, defaults=FRAME_DEFAULT), frames=4)
    assert effects.temporal and not effects.motion_vectors


def test_builtin_orbit_moves_and_cornell_box_does_not():
    assert inspect_scene("cornell-box-orbit", width=8, height=8, frames=3).motion_vectors
    static = inspect_scene("cornell-box", width=8, height=8, frames=3)
    assert static.temporal and not static.motion_vectors


def test_bad_frame_count_is_rejected():
    with pytest.raises(SceneError, match="frames"):
        inspect_scene("cornell-box", frames=0)
