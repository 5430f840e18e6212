"""The scene's own sampler: a stratifying one (stratified, multijitter, orthogonal, ldsampler)
gets per-pixel progressive (0,2)-sequence film and lens samples (stratified_sequence.py);
`independent` keeps independent uniforms."""
from __future__ import annotations

import numpy as np
import pytest

import service.render.renderer as renderer
from service.render.framebuffer import FrameBuffer
from service.render.renderer import expand_counts, render_samples, sample_indices
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
PINHOLE = dict(sensor="perspective", lens="")
# Focused at 3 while the plane is at 4: a blur of a few pixels, so aperture noise dominates.
THIN_LENS = dict(sensor="thinlens",
                 lens='<float name="aperture_radius" value="0.1"/><float name="focus_distance" value="3"/>')


def load(sampler: str, rfilter: str = "box", camera: dict = PINHOLE):
    mi = mitsuba()
    return mi.load_string(TEXTURED_PLANE.format(sampler=sampler, rfilter=rfilter, **camera))


def per_pixel_variance_over_seeds(scene, passes: list[int]) -> float:
    """Mean over pixels of the variance, across SEEDS seeds, of the per-pixel estimate after
    rendering `passes` uniform passes (spp each)."""
    images = []
    for seed in range(SEEDS):
        buffer = FrameBuffer.empty(SIZE, SIZE)
        for spp in passes:
            render_samples(scene, np.full((SIZE, SIZE), spp), buffer, seed=seed)
        images.append(buffer.radiance_sum / buffer.spp[..., None])
    return float(np.var(np.array(images), axis=0, ddof=1).mean())


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


def test_sample_indices_continue_a_pixels_count_across_passes():
    prior = np.array([[3, 0], [1, 5]])
    counts = np.array([[2, 1], [0, 3]])
    lanes = expand_counts(counts)
    assert sample_indices(prior, counts, lanes, 0).tolist() == [3, 4, 0, 5, 6, 7]
    # a chunk that starts mid-pass sees the same numbers
    assert sample_indices(prior, counts, lanes[4:], 4).tolist() == [6, 7]


@pytest.mark.parametrize("name, edit", [("thinlens_tent.xml", "stratified"), ("path_gaussian.xml", "multijitter")])
def test_stratified_scene_matches_mi_render_within_its_noise(name, edit):
    c = compare_file(name, 256, ours_edit=lambda xml: xml.replace('type="independent"', f'type="{edit}"'))
    assert not c.failures(), c.failures()


@pytest.mark.parametrize("rfilter, camera", [("box", PINHOLE), ("gaussian", PINHOLE), ("box", THIN_LENS)])
def test_stratified_samples_cut_the_per_pixel_variance_at_equal_samples(rfilter, camera):
    # Two passes (4 + 12): the second continues each pixel's sequence where the first stopped.
    independent = per_pixel_variance_over_seeds(load("independent", rfilter, camera), [4, 12])
    stratified = per_pixel_variance_over_seeds(load("multijitter", rfilter, camera), [4, 12])
    assert stratified < 0.6 * independent, (stratified, independent)


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
