"""The scene's own sampler: a stratifying one (stratified, multijitter, orthogonal, ldsampler)
gets per-pixel progressive (0,2)-sequence film and lens samples (stratified_sequence.py);
`independent` keeps independent uniforms."""
from __future__ import annotations

import drjit as dr
import numpy as np
import pytest

import service.render.renderer as renderer
from service.render.framebuffer import FrameBuffer
from service.render.renderer import render_samples
from service.render.stratified_lanes import digit_group_chunks, group_lanes, sequence_sampler
from service.render.runtime import mitsuba
from service.render.stratified_sequence import film_bits, lens_bits, reverse_bits, sobol_dim1
from tests.fidelity.harness import compare_file

SIZE = 16
SEEDS = 8

# A plane that emits a checkerboard (checks of ~1.4 pixels): its image is the texture filtered
# over each pixel, so all the noise is film-position (and lens) noise. Measured at 16 spp in two
# passes, 8 seeds: stratified ÷ independent per-pixel variance 0.09 (box), 0.35 (gaussian), 0.37
# (thin lens); with only a digital shift (no Owen scrambling) 2.5× worse than independent at
# 4× finer checks, a regular grid aliasing with the texture.
TEXTURED_PLANE = """<scene version="3.0.0">
    <sensor type="{sensor}">
        <float name="fov" value="40"/>{lens}
        <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
        <sampler type="{sampler}"><integer name="sample_count" value="16"/></sampler>
        <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/>
            <rfilter type="{rfilter}"/></film>
    </sensor>
    <integrator type="path"><integer name="max_depth" value="2"/></integrator>
    <shape type="rectangle">
        <emitter type="area"><texture name="radiance" type="checkerboard">
            <rgb name="color0" value="0.05"/><rgb name="color1" value="1.0"/>
            <transform name="to_uv"><scale x="4" y="4"/></transform></texture></emitter>
    </shape>
</scene>"""
# A diffuse plane filling the frame, lit by a square area light out of view: nearly all of its
# noise is in the integrator's own dimensions (the light sample, the BSDF sample), which film and
# lens samples alone cannot stratify. Measured at 4 + uneven 6…19 spp, 8 seeds: per-pixel
# relative variance ÷ independent's 1.02 with only film and lens stratified (28410ed, before the
# digit groups), 0.22 with every dimension stratified (stratified_lanes.SEQUENCE_SAMPLERS).
LIT_PLANE = """<scene version="3.0.0">
    <sensor type="perspective">
        <float name="fov" value="40"/>
        <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
        <sampler type="{sampler}"><integer name="sample_count" value="16"/></sampler>
        <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/>
            <rfilter type="box"/></film>
    </sensor>
    <integrator type="path"><integer name="max_depth" value="3"/></integrator>
    <shape type="rectangle">
        <transform name="to_world"><scale value="3"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf>
    </shape>
    <shape type="rectangle">
        <transform name="to_world"><scale value="0.6"/><rotate x="1" angle="180"/>
            <translate x="2" y="0.5" z="1.2"/></transform>
        <emitter type="area"><rgb name="radiance" value="6"/></emitter>
    </shape>
</scene>"""
PINHOLE = dict(sensor="perspective", lens="")
# Focused at 3 while the plane is at 4: a blur of a few pixels, so aperture noise dominates.
THIN_LENS = dict(sensor="thinlens",
                 lens='<float name="aperture_radius" value="0.1"/><float name="focus_distance" value="3"/>')


def load(sampler: str, rfilter: str = "box", camera: dict = PINHOLE):
    mi = mitsuba()
    return mi.load_string(TEXTURED_PLANE.format(sampler=sampler, rfilter=rfilter, **camera))


def estimates_over_seeds(scene, passes: list[np.ndarray]) -> np.ndarray:
    """(SEEDS, H, W, 3): the per-pixel estimates after rendering the count maps `passes`."""
    images = []
    for seed in range(SEEDS):
        buffer = FrameBuffer.empty(SIZE, SIZE)
        for counts in passes:
            render_samples(scene, counts, buffer, seed=seed)
        images.append(buffer.radiance_sum / buffer.spp[..., None])
    return np.array(images)


def per_pixel_variance_over_seeds(scene, passes: list[int]) -> float:
    """Mean over pixels of the variance, across SEEDS seeds, of the per-pixel estimate after
    rendering `passes` uniform passes (spp each)."""
    images = estimates_over_seeds(scene, [np.full((SIZE, SIZE), spp) for spp in passes])
    return float(np.var(images, axis=0, ddof=1).mean())


def test_first_points_of_the_sequence_form_a_0_m_2_net_for_every_m():
    k = np.arange(1 << 10, dtype=np.uint32)
    pixel = np.full(k.shape, 77, dtype=np.uint32)
    for points in (film_bits(k, 5, pixel), lens_bits(k, 5, pixel)):
        x, y = (p.astype(np.uint64) for p in points)
        for m in range(1, 11):
            n = 1 << m
            for x_bits in range(m + 1):   # elementary intervals 2^-x_bits × 2^-(m - x_bits)
                cell = (x[:n] >> (32 - x_bits)) << (m - x_bits) | (y[:n] >> (32 - (m - x_bits)))
                assert len(np.unique(cell)) == n, (m, x_bits)


def test_generator_matrices_are_van_der_corput_and_pascal_mod_2():
    # Dimension 0: bit j of k goes to bit 31 − j; dimension 1: column j is binom(j, i) mod 2.
    for j in range(32):
        k = np.array([1 << j], dtype=np.uint32)
        assert int(reverse_bits(k)[0]) == 1 << (31 - j)
        column = sum(1 << (31 - i) for i in range(j + 1) if (j & i) == i)   # Lucas: binom odd
        assert int(sobol_dim1(k)[0]) == column, j


def device_lanes(chunk) -> tuple[np.ndarray, np.ndarray]:
    """A digit group chunk's lanes as the renderer traces them: (flat pixel, sample number)."""
    pixels, sample_index = group_lanes(mitsuba(), chunk)
    return np.asarray(pixels), np.asarray(sample_index)


def test_digit_groups_give_each_pixel_exactly_its_counts_sample_numbers_across_passes():
    prior = np.array([[3, 0], [1, 5]])
    counts = np.array([[2, 1], [0, 11]])
    numbers: dict[int, list[int]] = {p: [] for p in range(4)}
    for max_wavefront in (1, 3, 1 << 20):   # chunks cut at whole pixels, whatever the size
        numbers = {p: [] for p in range(4)}
        for chunk in digit_group_chunks(prior, counts, max_wavefront):
            # pixel-major, each pixel's lanes consecutive, whole sequences of 4^k lanes each
            pixels, sample_index = device_lanes(chunk)
            assert (np.diff(pixels.astype(np.int64)) >= 0).all()
            np.testing.assert_array_equal(np.unique(pixels), chunk.pixels)
            lanes = np.unique(pixels, return_counts=True)[1]
            assert (lanes % chunk.sequence_length == 0).all() and lanes.max() <= 3 * chunk.sequence_length
            assert len(pixels) <= max(max_wavefront, lanes.max())
            for pixel, number in zip(pixels.tolist(), sample_index.tolist()):
                numbers[pixel].append(number)
        assert {p: sorted(n) for p, n in numbers.items()} == {
            0: [3, 4], 1: [0], 2: [], 3: list(range(5, 16))}
    # high digits first: pixel 3's 11 = 8 + 2 + 1 takes 5…12, then 13…14, then 15
    assert numbers[3] == list(range(5, 16))


def test_digits_sharing_a_sequence_length_are_traced_as_one_group():
    # counts with every digit 0…5 set somewhere: sequence lengths 16 (digits 4, 5), 4 (2, 3) and
    # 1 (0, 1) — three groups, not six; each digit's run keeps its alignment to 2^b in the pass.
    counts = np.array([63, 1, 2, 3, 12, 48, 0, 5])
    prior = np.array([7, 0, 3, 1, 2, 9, 4, 0])
    chunks = list(digit_group_chunks(prior, counts, 1 << 20))
    assert [c.sequence_length for c in chunks] == [16, 4, 1]
    lanes = [device_lanes(c) for c in chunks]
    for pixel, n in enumerate(counts.tolist()):
        numbers = np.concatenate([numbers[pixels == pixel] for pixels, numbers in lanes]).astype(int) - prior[pixel]
        assert sorted(numbers.tolist()) == list(range(n))
        for bit in range(6):   # digit b of n: numbers (n >> (b+1)) << (b+1) … + 2^b − 1, together
            if n >> bit & 1:
                first = (n >> (bit + 1)) << (bit + 1)
                assert set(range(first, first + (1 << bit))) <= set(numbers.tolist())


# 256 spp: one digit group of 256 lanes per pixel; 255: eight groups (128 + 64 + … + 1).
@pytest.mark.parametrize("name, edit, spp", [("thinlens_tent.xml", "stratified", 256),
                                             ("path_gaussian.xml", "multijitter", 255)])
def test_stratified_scene_matches_mi_render_within_its_noise(name, edit, spp):
    c = compare_file(name, spp, ours_edit=lambda xml: xml.replace('type="independent"', f'type="{edit}"'))
    assert not c.failures(), c.failures()


@pytest.mark.parametrize("rfilter, camera", [("box", PINHOLE), ("gaussian", PINHOLE), ("box", THIN_LENS)])
def test_stratified_samples_cut_the_per_pixel_variance_at_equal_samples(rfilter, camera):
    # Two passes (4 + 12): the second continues each pixel's sequence where the first stopped.
    independent = per_pixel_variance_over_seeds(load("independent", rfilter, camera), [4, 12])
    stratified = per_pixel_variance_over_seeds(load("multijitter", rfilter, camera), [4, 12])
    assert stratified < 0.6 * independent, (stratified, independent)


def test_the_integrators_own_dimensions_are_stratified_under_uneven_counts():
    mi = mitsuba()
    # A uniform first pass, then one whose counts differ per pixel (every digit group 1…16).
    passes = [np.full((SIZE, SIZE), 4), np.random.default_rng(1).integers(6, 20, (SIZE, SIZE))]
    independent = estimates_over_seeds(mi.load_string(LIT_PLANE.format(sampler="independent")), passes)
    stratified = estimates_over_seeds(mi.load_string(LIT_PLANE.format(sampler="ldsampler")), passes)

    def relative_variance(images: np.ndarray) -> float:
        return float((np.var(images, axis=0, ddof=1) / images.mean(axis=0) ** 2).mean())

    assert relative_variance(stratified) < 0.5 * relative_variance(independent), (
        relative_variance(stratified), relative_variance(independent))
    # Still unbiased: the image means agree within 4 standard errors of their seeds' spread.
    means = [images.mean(axis=(1, 2, 3)) for images in (independent, stratified)]
    error = np.sqrt(sum(m.var(ddof=1) / len(m) for m in means))
    assert abs(means[1].mean() - means[0].mean()) < 4 * error, (means, error)


@pytest.mark.parametrize("sampler", ["stratified", "ldsampler"])
def test_a_stratified_pass_traces_exactly_each_pixels_count(sampler):
    # Each lane of a white sky adds exactly 1.0 to its pixel: a pixel given too few or too many
    # lanes (a digit group lost or doubled, a chunk cut mid-pixel) fails here.
    mi = mitsuba()
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "path"},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
        "sensor": {"type": "perspective", "sampler": {"type": sampler, "sample_count": 16},
                   "film": {"type": "hdrfilm", "width": 12, "height": 8, "rfilter": {"type": "box"}}}})
    buffer = FrameBuffer.empty(8, 12)
    for counts in np.random.default_rng(5).integers(0, 37, size=(2, 8, 12)):
        before = buffer.radiance_sum[..., 0].copy()
        render_samples(scene, counts, buffer, seed=5, max_wavefront=97)
        np.testing.assert_allclose(buffer.radiance_sum[..., 0] - before, counts, rtol=0, atol=1e-4)
    np.testing.assert_array_equal(buffer.spp, buffer.radiance_sum[..., 0].round())


def pair_chi2(a: np.ndarray, b: np.ndarray) -> float:
    """χ² of an 8×8 histogram of (a, b) against uniform: ~63 when a and b are independent."""
    histogram, _, _ = np.histogram2d(a, b, bins=8, range=[[0, 1], [0, 1]])
    return float(((histogram - histogram.mean()) ** 2 / histogram.mean()).sum())


@pytest.mark.parametrize("lanes_per_pixel", [1, 2, 4, 8, 64, 128])
def test_the_dimensions_of_one_sample_are_independent_of_each_other(lanes_per_pixel):
    # Each dimension is stratified over a pixel's sequence, but two dimensions of one lane must
    # not be tied: Mitsuba's ldsampler XORs every dimension of a sequence with the same
    # scramble (χ² 65 600 at 4 lanes: u1 − u2 a multiple of 1/4), its stratified sampler's
    # consecutive permutation seeds tie neighbouring dimensions (32 900 at 4) — joint
    # distributions on a few lines, biased for any non-separable integrand. Sequences of 16
    # (16 and 32 lanes per pixel) are left out: multijitter's χ² there is 290–480, kept for its
    # variance (stratified_lanes.py says why).
    mi = mitsuba()
    # a digit group's sequences: 2^b lanes for even b, two sequences of 2^(b-1) for odd b
    length = 4 ** ((lanes_per_pixel.bit_length() - 1) // 2)
    sampler = sequence_sampler(mi, length, seed=11, lanes=1 << 14)
    u1, u2, u3 = (np.asarray(sampler.next_1d()) for _ in range(3))
    v1, v2 = np.asarray(sampler.next_2d()), np.asarray(sampler.next_2d())
    for a, b in ((u1, u2), (u2, u3), (v1[0], v2[0]), (v1[1], v2[1]), (u1, v1[0])):
        assert pair_chi2(a, b) < 150, pair_chi2(a, b)   # 99.99th percentile of χ²(63): ~120
    # and each dimension alone is stratified over a pixel's sequence (one lane per stratum)
    strata = np.floor(u1 * length).astype(int).reshape(-1, length)
    assert all(len(set(row)) == length for row in strata[:64].tolist())


def test_an_independent_scene_never_reads_the_sequence_and_repeats_with_its_seed(monkeypatch):
    def refuse(*_args):
        raise AssertionError("the sequence was used for an independent scene")

    monkeypatch.setattr(renderer, "film_bits", refuse)
    monkeypatch.setattr(renderer, "lens_bits", refuse)
    scene = load("independent", "gaussian", THIN_LENS)
    images = []
    for _ in range(2):
        buffer = FrameBuffer.empty(SIZE, SIZE)
        render_samples(scene, np.full((SIZE, SIZE), 8), buffer, seed=3)
        images.append(buffer.radiance_sum.copy())
    assert np.array_equal(images[0], images[1])


def test_a_stratified_scene_repeats_with_its_seed_and_differs_with_another():
    scene = load("stratified", "box", THIN_LENS)

    def image(seed: int) -> np.ndarray:
        buffer = FrameBuffer.empty(SIZE, SIZE)
        render_samples(scene, np.full((SIZE, SIZE), 8), buffer, seed=seed)
        return buffer.radiance_sum

    first = image(3)
    assert np.array_equal(first, image(3))
    assert not np.array_equal(first, image(4))


def test_uneven_stratified_passes_build_one_kernel_per_digit_and_reuse_it():
    """Each group's sequence length is a literal of its kernel (Mitsuba's samples_per_wavefront),
    so counts 1…7 trace two kernels (sequences of 1 for digits 0 and 1, of 4 for digit 2).
    Further count maps must reuse them: a kernel keyed by where malloc put a lane array (align 64
    vs 1) was rebuilt in about one pass of three."""
    mi = mitsuba()
    scene = mi.load_string(LIT_PLANE.format(sampler="multijitter"))
    rng = np.random.default_rng(3)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()   # drop what ran before
        for _ in range(4):
            render_samples(scene, rng.integers(1, 8, (SIZE, SIZE)), FrameBuffer.empty(SIZE, SIZE), max_wavefront=200)
        launched = [entry for entry in dr.kernel_history() if entry["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    # The trace kernels (thousands of operations); the lane map's scatter of run starts
    # (lane_map.py, a handful) is one more kernel, shared by every chunk.
    traced = [entry for entry in launched if entry["operation_count"] > 100]
    assert len(traced) >= 8   # 4 maps × 2 groups actually traced
    assert len({str(entry["hash"]) for entry in traced}) <= 2
    assert len({str(entry["hash"]) for entry in launched}) <= 3
