"""Hard scenes through the whole loop (render → denoise → predict error → allocate), error
allocator, three doubling iterations: nothing non-finite or negative, budgets exact."""
from __future__ import annotations

import numpy as np
import pytest

from hardcase_checks import doubling_totals, run_checked
from models.pretrained import Networks
from service.loop.loop import RenderLoop
from service.loop.spec import LoopSpec

ITERATIONS = 3


def loop_for(source: str, nets, size: int = 16, **spec) -> RenderLoop:
    spec = {"max_iterations": ITERATIONS, "allocator": "error", **spec}
    return RenderLoop(LoopSpec(scene=str(source), width=size, height=size, **spec),
                      Networks(nets[0], nets[1]))


def test_tiny_very_bright_light(nets):
    """The fireflies scene: a 1 cm bulb of radiance 2000 lights the room through the ceiling."""
    records = run_checked(loop_for("fireflies", nets), doubling_totals(16 * 16, 16, ITERATIONS))
    assert records[-1].stop_reason == "max_iterations"


def test_emitters_seen_directly(nets, hard_scene):
    records = run_checked(loop_for(hard_scene("direct-emitter"), nets), doubling_totals(16 * 16, 16, ITERATIONS))
    assert records[-1].buffers[0].mean.max() >= 1e3  # the light itself is in the frame


def test_pure_black_regions(nets, hard_scene):
    records = run_checked(loop_for(hard_scene("black-regions"), nets), doubling_totals(16 * 16, 16, ITERATIONS))
    noisy = records[-1].buffers[0].mean
    assert (noisy.max(axis=2) == 0).mean() > 0.3 and noisy.max() > 0  # large exact-zero areas beside lit ones


def test_environment_only_scene(nets, hard_scene):
    records = run_checked(loop_for(hard_scene("environment-only"), nets), doubling_totals(16 * 16, 16, ITERATIONS))
    buffer = records[-1].buffers[0]
    assert (buffer.depth == 0).all() and (buffer.albedo == 0).all()  # every primary ray missed
    # hdrfilm's default gaussian filter is importance-sampled from a table: each lane's weight
    # f/pdf is ≈ 1, not exactly 1, so a constant sky comes back within a fraction of a percent.
    np.testing.assert_allclose(buffer.mean, np.broadcast_to([0.5, 0.7, 1.0], buffer.mean.shape), rtol=5e-3)


def test_black_and_glass_materials(nets, hard_scene):
    run_checked(loop_for(hard_scene("black-and-glass"), nets), doubling_totals(16 * 16, 16, ITERATIONS))


def test_sequence_whose_camera_moves_off_the_previous_frame(nets, hard_scene):
    loop = loop_for(hard_scene("camera-moves-off"), nets, frames=3, max_iterations=2)
    assert loop.effects.temporal and loop.effects.motion_vectors
    records = run_checked(loop, doubling_totals(16 * 16, 16, 2))
    motion = records[-1].buffers[1].motion
    # Points of frame 1 that frame 0 saw moved by most of the frame; the rest were never seen.
    assert motion is not None and np.isfinite(motion).all() and np.abs(motion).max() > 8


@pytest.mark.parametrize("width, height", [(1, 1), (7, 13), (1024, 16)])
def test_odd_image_sizes(nets, width, height):
    loop = RenderLoop(LoopSpec(scene="cornell-box", width=width, height=height, max_iterations=2, allocator="error"),
                      Networks(nets[0], nets[1]))
    records = run_checked(loop, doubling_totals(width * height, 16, 2))
    assert records[-1].denoised[0].shape == (height, width, 3)
    assert records[-1].error[0].shape == (height, width)
