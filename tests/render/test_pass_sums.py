"""Every column of a pass's per-pixel sums lands in its own FrameBuffer array and its own pixel
(service/render/pass_sums.py, lane_map.py): on a scene where each sample's value is exact and
different per pixel and per channel — an orthographic camera looking straight at an emitting,
textured square, one texel per pixel, nearest lookup, box filter — each pixel's sums must be
its count times its known values. A lane sent to a neighbour, a pixel straddling two chunks
counted once, or two columns swapped, fails here."""
from __future__ import annotations

import numpy as np
import pytest

from service.render.framebuffer import FrameBuffer
from service.render.renderer import render_samples
from service.render.runtime import mitsuba

SIZE = 12
DISTANCE = 2.0   # camera to square
NEAR_CLIP = 0.5  # rays start here, so every first hit's depth is DISTANCE − NEAR_CLIP


def texel_values() -> np.ndarray:
    """(SIZE, SIZE, 3) distinct values in (0, 1): pixel and channel each change them."""
    y, x = np.mgrid[0:SIZE, 0:SIZE].astype(np.float32)
    channels = [(x + SIZE * y + 1) / (SIZE * SIZE + 1), (x + 1) / (SIZE + 1), (y + 1) / (SIZE + 1)]
    return np.stack(channels, axis=-1).astype(np.float32)


def camera(mi, x_shift: float = 0.0, sampler: str = "independent") -> dict:
    return {"type": "orthographic", "near_clip": NEAR_CLIP,
            "to_world": mi.ScalarTransform4f().look_at(origin=[x_shift, 0, DISTANCE], target=[x_shift, 0, 0], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": SIZE, "height": SIZE, "rfilter": {"type": "box"}},
            "sampler": {"type": sampler}}


def textured_square(mi, sampler: str, integrator: dict):
    """The square's emission is `texel_values`, its diffuse reflectance half of it."""
    def texture(scale: float) -> dict:
        return {"type": "bitmap", "bitmap": mi.Bitmap(texel_values() * np.float32(scale)),
                "filter_type": "nearest", "raw": True}

    return mi.load_dict({
        "type": "scene", "integrator": integrator, "sensor": camera(mi, sampler=sampler),
        "square": {"type": "rectangle", "emitter": {"type": "area", "radiance": texture(1.0)},
                   "bsdf": {"type": "diffuse", "reflectance": texture(0.5)}},
    })


def reference_image(mi, scene) -> np.ndarray:
    """The square as mi.render sees it at one sample per pixel (orientation of the texture
    on the film, without assuming it)."""
    return np.asarray(mi.render(scene, spp=1))[..., :3].astype(np.float64)


COUNT_MAPS = {
    "uniform": lambda rng: np.full((SIZE, SIZE), 5),
    "uneven with zeros": lambda rng: rng.integers(0, 12, size=(SIZE, SIZE)),
}


@pytest.mark.parametrize("sampler", ["independent", "multijitter"])   # lane runs; digit groups
@pytest.mark.parametrize("count_map", sorted(COUNT_MAPS))
def test_each_column_of_the_pass_sums_lands_in_its_own_pixel(sampler, count_map):
    mi = mitsuba()
    scene = textured_square(mi, sampler, {"type": "path"})
    counts = COUNT_MAPS[count_map](np.random.default_rng(7))
    buffer = FrameBuffer.empty(SIZE, SIZE)
    # 53 lanes a chunk: pixels straddle chunk cuts (independent) or groups split (stratified)
    render_samples(scene, counts, buffer, seed=3, max_wavefront=53, prev_sensor=mi.load_dict(camera(mi, 2.0 / SIZE)))
    n = counts[..., None].astype(np.float64)
    emitted = reference_image(mi, scene)
    np.testing.assert_allclose(buffer.radiance_sum, n * emitted, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(buffer.radiance_sq_sum, n * emitted**2, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(buffer.albedo_sum, n * emitted / 2, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(buffer.normal_sum, n * np.array([0.0, 0.0, 1.0]), atol=1e-5)
    np.testing.assert_allclose(buffer.depth_sum, counts * (DISTANCE - NEAR_CLIP), rtol=1e-5)
    # the previous camera stood one pixel to the right: every point was one pixel further left
    np.testing.assert_allclose(buffer.motion_sum, n * np.array([-1.0, 0.0]), atol=1e-3)
    np.testing.assert_array_equal(buffer.spp, counts)


def test_the_integrators_own_aovs_land_in_their_columns():
    mi = mitsuba()
    integrator = {"type": "aov", "aovs": "dd:depth,nn:sh_normal", "integrator": {"type": "path"}}
    scene = textured_square(mi, "independent", integrator)
    counts = np.random.default_rng(8).integers(0, 9, size=(SIZE, SIZE))
    buffer = FrameBuffer.empty(SIZE, SIZE)
    render_samples(scene, counts, buffer, seed=4, max_wavefront=41)
    layers = {name: buffer.aov_sum[..., i] for i, name in enumerate(buffer.aov_names)}
    depth = next(v for name, v in layers.items() if name.startswith("dd"))
    np.testing.assert_allclose(depth, counts * (DISTANCE - NEAR_CLIP), rtol=1e-5)
    normal_z = next(v for name, v in layers.items() if name.startswith("nn") and name.endswith("Z"))
    np.testing.assert_allclose(normal_z, counts.astype(np.float64), rtol=1e-5)
    np.testing.assert_allclose(buffer.radiance_sum, counts[..., None] * reference_image(mi, scene), rtol=1e-5, atol=1e-6)


def test_non_finite_samples_are_dropped_and_counted_once_per_pass():
    mi = mitsuba()
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "path"},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": float("inf")}},
        "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 9, "height": 5, "rfilter": {"type": "box"}}},
    })
    counts = np.random.default_rng(9).integers(0, 6, size=(5, 9))
    buffer = FrameBuffer.empty(5, 9)
    for _ in range(2):   # the count adds up across passes; chunks of 17 lanes within each
        render_samples(scene, counts, buffer, seed=1, max_wavefront=17)
    assert buffer.meta["nonfinite_samples"] == 2 * counts.sum()
    assert not buffer.radiance_sum.any() and np.isfinite(buffer.radiance_sq_sum).all()


class Stop(Exception):
    pass


def test_progress_hears_of_every_chunk_and_a_raise_stops_the_pass_without_touching_the_buffer():
    mi = mitsuba()
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "path"},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
        "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 9, "height": 5, "rfilter": {"type": "box"}}},
    })
    counts = np.random.default_rng(10).integers(0, 6, size=(5, 9))
    heard: list[int] = []
    buffer = FrameBuffer.empty(5, 9)
    result = render_samples(scene, counts, buffer, seed=1, max_wavefront=23, progress=heard.append)
    assert sum(heard) == counts.sum() and len(heard) == result.chunks > 1

    def stop(_lanes: int) -> None:
        raise Stop

    with pytest.raises(Stop):
        render_samples(scene, counts, buffer, seed=2, max_wavefront=23, progress=stop)
    np.testing.assert_array_equal(buffer.spp, counts)   # the stopped pass added nothing
    render_samples(scene, counts, buffer, seed=3, max_wavefront=23)   # and leaves nothing behind
    np.testing.assert_allclose(buffer.radiance_sum[..., 0], 2 * counts, atol=1e-4)
