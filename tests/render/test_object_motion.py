"""Motion vectors of moving shapes (service/render/object_motion.py): a point on a shape that moved
was elsewhere one frame earlier, whatever the camera did."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.loop.loop import RenderLoop
from service.loop.spec import LoopSpec
from service.render.effects import load_frames
from service.render.object_motion import pair_shapes, shape_motion
from service.render.runtime import mitsuba

SIZE = 32
# An orthographic camera 4 world units wide over 32 pixels (8 px per unit), looking down −z at a
# lit wall. The object moves 0.25 units (2 px) to the right per frame: Mitsuba XML has no
# arithmetic, so "scale 4, translate $frame, scale 0.25" adds 0.25 · frame to x.
SCENE = """<scene version="3.0.0">
  <default name="frame" value="0"/>
  <integrator type="path"><integer name="max_depth" value="2"/></integrator>
  <sensor type="orthographic">
    <transform name="to_world"><scale x="2" y="2"/><lookat origin="0, 0, 5" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="{size}"/><integer name="height" value="{size}"/>
      <rfilter type="box"/></film>
  </sensor>
  {shape}
  <shape type="rectangle"><transform name="to_world"><scale value="10"/><translate z="-2"/></transform>
    <bsdf type="diffuse"/></shape>
  <emitter type="constant"><rgb name="radiance" value="1"/></emitter>
</scene>"""
MOVES = '<scale value="4"/><translate x="$frame"/><scale value="0.25"/>'
SHAPES = {
    "analytic sphere": f'<shape type="sphere"><transform name="to_world"><scale value="0.8"/>{MOVES}</transform>'
                       '<bsdf type="diffuse"/></shape>',
    "mesh cube": f'<shape type="cube"><transform name="to_world"><scale value="0.7"/>{MOVES}</transform>'
                 '<bsdf type="diffuse"/></shape>',
}
PIXELS_PER_FRAME = 2.0


def write_scene(folder: Path, shape: str) -> Path:
    path = folder / "moving.xml"
    path.write_text(SCENE.format(size=SIZE, shape=shape))
    return path


@pytest.mark.parametrize("kind", sorted(SHAPES))
def test_a_moving_shape_carries_its_own_motion_and_the_still_wall_none(tmp_path: Path, kind: str):
    loop = RenderLoop(LoopSpec(scene=str(write_scene(tmp_path, SHAPES[kind])), frames=2, spp_first=4,
                               max_iterations=1, allocator="uniform", denoise=False), None)
    assert loop.effects.animated_shapes and not loop.effects.animated_camera
    buffer = next(iter(loop.run())).buffers[1]
    mx, my = buffer.motion[..., 0], buffer.motion[..., 1]
    centre = mx[SIZE // 2 - 2:SIZE // 2 + 2, SIZE // 2 - 1:SIZE // 2 + 3]   # always on the object
    # frame 1's pixel was 2 px further left in frame 0 (the object moves right)
    np.testing.assert_allclose(centre, -PIXELS_PER_FRAME, atol=1e-3)
    np.testing.assert_allclose(my[SIZE // 2 - 2:SIZE // 2 + 2], 0.0, atol=1e-3)
    assert np.abs(buffer.motion[:3, :3]).max() < 1e-3                          # the wall's corner


def test_shape_motion_is_none_for_a_still_sequence_and_pairs_only_like_shapes(tmp_path: Path):
    mi = mitsuba()
    still = write_scene(tmp_path, SHAPES["mesh cube"].replace("$frame", "0"))
    frames = load_frames(str(still), frames=2)
    assert shape_motion(mi, frames[1].scene, frames[0].scene) is None
    moving = load_frames(str(write_scene(tmp_path, SHAPES["analytic sphere"])), frames=2)
    motion = shape_motion(mi, moving[1].scene, moving[0].scene)
    assert motion is not None and motion.moving == 1
    # a frame whose shapes do not pair up (another shape list) gets no object motion
    assert shape_motion(mi, moving[1].scene, frames[0].scene) is None


def test_shapes_pair_by_kind_counts_and_nearest_box_whatever_their_order(tmp_path: Path):
    """Two 4-vertex rectangles listed in the opposite order in the previous frame still pair with
    themselves (Mitsuba promises no load order); a sphere pairs with no mesh."""
    mi = mitsuba()
    panel = ('<shape type="rectangle"><transform name="to_world"><scale value="0.3"/><translate x="1.5" y="1.5"/>'
             '</transform><bsdf type="diffuse"><rgb name="reflectance" value="0.2"/></bsdf></shape>')
    frames = load_frames(str(write_scene(tmp_path, SHAPES["analytic sphere"] + panel)), frames=2)
    now, before = list(frames[1].scene.shapes()), list(frames[0].scene.shapes())
    assert sum(s.is_mesh() for s in now) == 2                       # the wall and the panel: 4 vertices each
    pairs = pair_shapes(now, list(reversed(before)))
    assert len(pairs) == len(now)
    for shape, prev in pairs:
        assert shape.is_mesh() == prev.is_mesh()
        if shape.is_mesh():   # both still: each pairs with the very same box
            np.testing.assert_array_equal(np.asarray(shape.bbox().max), np.asarray(prev.bbox().max))
    assert shape_motion(mi, frames[1].scene, frames[0].scene).moving == 1
