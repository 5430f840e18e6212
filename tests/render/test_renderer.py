"""The per-pixel-count renderer: exact counts, unbiased accumulation, bounded chunks."""
import drjit as dr
import numpy as np
import pytest

from service.loop.allocate import exposed_relative_variance
from service.render.framebuffer import FrameBuffer
from service.render.renderer import pass_seed, render_samples
from service.render.runtime import mitsuba
from tests.render.cornell import cornell_box

SIZE = 24


@pytest.fixture(scope="module")
def cornell():
    return cornell_box(SIZE, "box")


@pytest.fixture(scope="module")
def reference(cornell):
    """A high-spp mean image from the same renderer (the unbiasedness yardstick)."""
    buffer = FrameBuffer.empty(SIZE, SIZE)
    render_samples(cornell, np.full((SIZE, SIZE), 512), buffer, seed=999)
    return buffer


def uniform(spp: int) -> np.ndarray:
    return np.full((SIZE, SIZE), spp, dtype=np.int64)


def test_a_negative_sample_count_is_refused(cornell):
    counts = uniform(1)
    counts[3, 5] = -1
    with pytest.raises(ValueError, match="sample counts must be >= 0"):
        render_samples(cornell, counts, FrameBuffer.empty(SIZE, SIZE))


def test_pass_seeds_differ_between_passes_and_chunks():
    seeds = {pass_seed(0, p, c) for p in range(20) for c in range(5)}
    assert len(seeds) == 100 and all(0 <= s < 2**32 for s in seeds)


def test_counts_are_honoured_exactly(cornell):
    rng = np.random.default_rng(0)
    counts = rng.integers(0, 9, size=(SIZE, SIZE))
    buffer = FrameBuffer.empty(SIZE, SIZE)
    result = render_samples(cornell, counts, buffer, seed=1)
    assert result.samples == counts.sum()
    np.testing.assert_array_equal(buffer.spp, counts)


def test_uniform_map_matches_mi_render(cornell):
    mi = mitsuba()
    buffer = FrameBuffer.empty(SIZE, SIZE)
    render_samples(cornell, uniform(128), buffer, seed=2)
    ours = buffer.mean
    theirs = np.array(mi.render(cornell, spp=128, seed=5))
    assert abs(ours.mean() / theirs.mean() - 1) < 0.01
    # Per pixel within noise: both are 128-spp estimates, so their difference has ~twice our variance.
    z = (ours - theirs) / np.sqrt(2 * buffer.variance + 1e-6)
    assert np.abs(z).mean() < 1.5


def test_non_uniform_map_stays_unbiased(cornell, reference):
    rng = np.random.default_rng(3)
    counts = rng.integers(1, 64, size=(SIZE, SIZE))
    buffer = FrameBuffer.empty(SIZE, SIZE)
    render_samples(cornell, counts, buffer, seed=3)
    # Standard error of the global mean from the per-pixel variances of the mean.
    diff = buffer.mean.mean() - reference.mean.mean()
    stderr = np.sqrt(buffer.variance.sum() + reference.variance.sum()) / buffer.mean[..., 0].size
    assert abs(diff) < 4 * stderr + 1e-4


def test_two_passes_equal_one_pass_with_summed_counts_in_distribution(cornell):
    a, b = uniform(8), np.random.default_rng(4).integers(0, 16, size=(SIZE, SIZE))
    twice = FrameBuffer.empty(SIZE, SIZE)
    render_samples(cornell, a, twice, seed=4)
    render_samples(cornell, b, twice, seed=4)
    once = FrameBuffer.empty(SIZE, SIZE)
    render_samples(cornell, a + b, once, seed=5)
    np.testing.assert_array_equal(twice.spp, once.spp)
    assert twice.passes == 2
    diff = twice.mean.mean() - once.mean.mean()
    stderr = np.sqrt(twice.variance.sum() + once.variance.sum()) / twice.spp.size
    assert abs(diff) < 4 * stderr + 1e-4
    # Same seed argument, different pass index: the second pass must not repeat the first.
    assert not np.allclose(twice.radiance_sum, 2 * once.radiance_sum)


def test_zero_count_pixels_stay_empty_and_finite(cornell):
    counts = uniform(4)
    counts[:, : SIZE // 2] = 0
    buffer = FrameBuffer.empty(SIZE, SIZE)
    render_samples(cornell, counts, buffer, seed=6)
    assert (buffer.spp[:, : SIZE // 2] == 0).all()
    for layer in (buffer.mean, buffer.variance, buffer.albedo, buffer.normal, buffer.depth,
                  exposed_relative_variance(buffer.mean, buffer.variance)):
        assert np.isfinite(layer).all()
    assert (buffer.mean[:, : SIZE // 2] == 0).all()


def test_all_zero_counts_render_nothing(cornell):
    buffer = FrameBuffer.empty(SIZE, SIZE)
    result = render_samples(cornell, uniform(0), buffer, seed=7)
    assert result.samples == 0 and result.chunks == 0
    assert buffer.spp.sum() == 0


def test_chunked_equals_unchunked_in_distribution(cornell):
    chunked = FrameBuffer.empty(SIZE, SIZE)
    result = render_samples(cornell, uniform(16), chunked, seed=8, max_wavefront=1000)
    assert result.chunks == -(-SIZE * SIZE * 16 // 1000)
    whole = FrameBuffer.empty(SIZE, SIZE)
    render_samples(cornell, uniform(16), whole, seed=9)
    np.testing.assert_array_equal(chunked.spp, whole.spp)
    diff = chunked.mean.mean() - whole.mean.mean()
    stderr = np.sqrt(chunked.variance.sum() + whole.variance.sum()) / whole.spp.size
    assert abs(diff) < 4 * stderr + 1e-4


def test_first_hit_aovs_describe_the_visible_surface(cornell, reference):
    # The Cornell box walls are diffuse with albedo < 1 and sit 3-6 units from the camera.
    assert 0 < reference.albedo.max() <= 1
    norms = np.linalg.norm(reference.normal, axis=-1)
    # Pixel-averaged unit normals: 1 inside a wall, shorter only where walls meet.
    assert np.median(norms) > 0.99 and norms.max() <= 1 + 1e-4
    centre = reference.depth[SIZE // 2, SIZE // 2]
    assert 3.0 < centre < 6.0


def test_motion_is_zero_for_a_static_camera_and_aligns_frames_when_it_moves():
    mi = mitsuba()

    def shifted(dx):
        d = mi.cornell_box()
        d["sensor"]["film"].update(width=SIZE, height=SIZE)
        d["sensor"]["to_world"] = mi.ScalarTransform4f().translate([dx, 0, 0]) @ d["sensor"]["to_world"]
        return mi.load_dict(d)

    s0, s1 = shifted(0.0), shifted(0.15)
    static = FrameBuffer.empty(SIZE, SIZE)
    render_samples(s0, uniform(2), static, seed=10, prev_sensor=s0.sensors()[0])
    assert np.abs(static.motion).max() < 1e-3

    moving = FrameBuffer.empty(SIZE, SIZE)
    render_samples(s1, uniform(64), moving, seed=11, prev_sensor=s0.sensors()[0])
    previous = FrameBuffer.empty(SIZE, SIZE)
    render_samples(s0, uniform(64), previous, seed=12)
    m = moving.motion
    assert np.abs(m[..., 0]).mean() > 0.3  # the camera moved sideways
    grid = np.arange(SIZE)
    xs = np.clip(np.round(grid[None, :] + m[..., 0]).astype(int), 0, SIZE - 1)
    ys = np.clip(np.round(grid[:, None] + m[..., 1]).astype(int), 0, SIZE - 1)
    warped = previous.mean[ys, xs]
    assert np.abs(warped - moving.mean).mean() < 0.6 * np.abs(previous.mean - moving.mean).mean()


def test_albedo_is_one_on_conductors_and_glass_and_the_reflectance_on_diffuse_walls():
    """eval_diffuse_reflectance of a glossy lobe returns its peak at one direction (~55 on Cr at
    roughness 0.05), and 0 on glass: neither is a texture the denoiser can divide out."""
    mi = mitsuba()
    scene = mi.cornell_box()
    scene["sensor"]["film"].update(width=SIZE, height=SIZE, rfilter={"type": "box"})
    scene["small-box"]["bsdf"] = {"type": "roughconductor", "material": "Cr", "alpha": 0.05}
    scene["large-box"]["bsdf"] = {"type": "dielectric"}
    buffer = FrameBuffer.empty(SIZE, SIZE)
    render_samples(mi.load_dict(scene), uniform(4), buffer, seed=3)
    white = np.all(buffer.albedo == 1.0, axis=-1)
    assert buffer.albedo.max() == 1.0 and white.mean() > 0.05          # both boxes cover part of the view
    walls = buffer.albedo[~white & (buffer.albedo.sum(-1) > 0)]
    assert 0 < np.median(walls.max(-1)) < 0.9                           # diffuse walls keep their colour


def unit_sky_scene(film: dict, integrator: str = "path"):
    """Nothing but a constant emitter of radiance 1: every traced lane returns exactly 1.0."""
    mi = mitsuba()
    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": integrator, "hide_emitters": False},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
        "sensor": {"type": "perspective", "film": {"type": "hdrfilm", **film}},
    })


@pytest.mark.parametrize("integrator", ["path", "direct"])  # direct: its own shared-hit trace
def test_radiance_sum_counts_the_lanes_actually_traced_per_pixel(integrator):
    # Independent of the spp bookkeeping: each traced lane adds exactly 1.0 to its pixel, so a
    # renderer that traced half the lanes (or put them in the wrong pixel) fails here.
    scene = unit_sky_scene({"width": 12, "height": 8, "rfilter": {"type": "box"}}, integrator)
    counts = np.random.default_rng(5).integers(0, 7, size=(8, 12))
    buffer = FrameBuffer.empty(8, 12)
    render_samples(scene, counts, buffer, seed=5, max_wavefront=97)
    np.testing.assert_allclose(buffer.radiance_sum[..., 0], counts, rtol=0, atol=1e-4)
    np.testing.assert_allclose(buffer.radiance_sq_sum[..., 1], counts, rtol=0, atol=1e-4)


def test_unit_sky_matches_mi_render_exactly_with_a_box_filter():
    mi = mitsuba()
    scene = unit_sky_scene({"width": 8, "height": 6, "rfilter": {"type": "box"}})
    buffer = FrameBuffer.empty(6, 8)
    render_samples(scene, np.full((6, 8), 3), buffer, seed=1)
    np.testing.assert_allclose(buffer.mean, np.asarray(mi.render(scene, spp=3))[..., :3], atol=1e-5)


def test_filter_weights_average_to_one_per_pixel_even_at_the_film_border():
    # With a filter the lanes carry weights f/(p ∫f); on a constant image their mean must be 1
    # in every pixel, border pixels (truncated footprint) included — as hdrfilm's normalisation.
    scene = unit_sky_scene({"width": 10, "height": 7, "rfilter": {"type": "mitchell"}})
    buffer = FrameBuffer.empty(7, 10)
    render_samples(scene, np.full((7, 10), 4000), buffer, seed=2)
    # Signed weights (negative lobes) have a spread; judge each pixel by its own standard error.
    z = (buffer.mean[..., 0] - 1.0) / np.sqrt(buffer.variance[..., 0])
    assert np.abs(z).max() < 4.5 and abs(z.mean()) < 4.5 / np.sqrt(z.size)


def test_adaptive_passes_reuse_the_compiled_kernels(cornell):
    """Every new count map moves the chunks' first pixels and spans; keyed by them, each chunk of
    each adaptive pass used to build its own kernel (~0.34 s apiece on the LLVM backend). Three
    different maps in 8 chunks each must launch at most three distinct kernels (24 before)."""
    rng = np.random.default_rng(3)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()   # drop what ran before
        for _ in range(3):
            counts = rng.choice([1, 3], (SIZE, SIZE))
            render_samples(cornell, counts, FrameBuffer.empty(SIZE, SIZE), max_wavefront=int(counts.sum()) // 8 + 1)
        launched = [entry for entry in dr.kernel_history() if entry["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert len(launched) >= 24   # 3 maps × 8 chunks actually traced
    assert len({str(entry["hash"]) for entry in launched}) <= 3
