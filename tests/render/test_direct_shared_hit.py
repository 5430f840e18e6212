"""The `direct` integrator traced with its primary hit shared by the features (direct_shared_hit.py).

Its radiance is pinned against mi.render by the fidelity suite (direct_*.xml); these tests pin
when the path is taken and that the features it yields are the ones the separate first-hit
intersection yields for every other integrator.
"""
from unittest import mock

import numpy as np
import pytest

import service.render.renderer as renderer
from service.render.direct_shared_hit import DirectSettings, direct_settings
from service.render.framebuffer import FrameBuffer
from service.render.runtime import mitsuba
from service.render.scenes import load_scene_info
from tests.fidelity.harness import SCENES


def test_direct_settings_read_the_strategy_counts_of_the_instance():
    mi = mitsuba()
    settings = direct_settings(mi, mi.load_dict({"type": "direct", "emitter_samples": 2, "bsdf_samples": 3}))
    assert settings == DirectSettings(emitter_samples=2, bsdf_samples=3)
    assert settings.frac_emitter == pytest.approx(0.4) and settings.frac_bsdf == pytest.approx(0.6)
    assert direct_settings(mi, mi.load_dict({"type": "direct", "shading_samples": 4})) == DirectSettings(4, 4)


def test_other_integrators_and_hidden_emitters_keep_their_own_sample_method():
    mi = mitsuba()
    assert direct_settings(mi, mi.load_dict({"type": "path"})) is None
    assert direct_settings(mi, mi.load_dict({"type": "direct", "hide_emitters": True})) is None


def render_features(scene, shared: bool) -> FrameBuffer:
    h, w = (int(v) for v in scene.sensors()[0].film().crop_size()[::-1])
    buffer = FrameBuffer.empty(h, w)
    if shared:
        renderer.render_samples(scene, np.full((h, w), 8), buffer, seed=7)
    else:
        with mock.patch.object(renderer, "direct_settings", lambda mi, integrator: None):
            renderer.render_samples(scene, np.full((h, w), 8), buffer, seed=7)
    return buffer


def test_shared_hit_features_equal_the_separate_first_hit_features():
    # Same seed → same camera rays (they are drawn before the integrator consumes samples), so
    # albedo, normal and depth must agree to rounding whichever intersection produced them.
    scene = load_scene_info(SCENES / "direct_mis_box.xml").scene
    shared, separate = render_features(scene, True), render_features(scene, False)
    for name in ("albedo_sum", "normal_sum", "depth_sum"):
        np.testing.assert_allclose(getattr(shared, name), getattr(separate, name), atol=1e-4, err_msg=name)
    # The radiance differs (different random numbers after the ray), so the two paths ran.
    assert not np.allclose(shared.radiance_sum, separate.radiance_sum)


def test_render_of_a_direct_scene_takes_the_shared_hit_path():
    scene = load_scene_info(SCENES / "direct_mis_box.xml").scene
    with mock.patch.object(renderer, "sample_lane", side_effect=AssertionError("integrator.sample() called")):
        render_features(scene, True)
