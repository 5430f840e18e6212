"""The loop's final image: the denoised image falling back per region towards the raw (splatted)
image where the samples alone are expected to be closer (service/loop/final_image.py)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from models.exposure import Exposure
from models.losses import SMAPE_EPS
from models.pretrained import load_networks
from service.loop.final_image import WINDOW, box_mean, compose_final, raw_expected_error
from service.loop.loop import RenderLoop
from service.loop.spec import LoopSpec
from service.loop.tensors import nchw
from service.render.runtime import mitsuba

H, W = 24, 32


def halves(left: float, right: float) -> np.ndarray:
    out = np.full((H, W), right)
    out[:, : W // 2] = left
    return out


def test_each_region_takes_the_image_with_the_lower_expected_error() -> None:
    denoised, raw = np.full((H, W, 3), 1.0, np.float32), np.full((H, W, 3), 2.0, np.float32)
    # left: the raw image's spread is tiny, the denoised predicted poor; right: the reverse
    variance = np.repeat(halves(1e-8, 1.0)[..., None], 3, axis=-1)
    predicted = halves(0.1, 1e-3)
    out = compose_final(denoised, raw, variance, predicted, exposure=1.0)
    margin = WINDOW  # the decision reads a neighbourhood: the seam's pixels mix
    np.testing.assert_allclose(out[:, : W // 2 - margin], 2.0, atol=1e-4)
    np.testing.assert_allclose(out[:, W // 2 + margin:], 1.0, atol=1e-4)


def test_a_pixel_without_raw_variance_keeps_the_denoised_image() -> None:
    # zero spread among the samples is no evidence of zero error (a rare path can miss them all)
    denoised, raw = np.full((H, W, 3), 1.0, np.float32), np.zeros((H, W, 3), np.float32)
    out = compose_final(denoised, raw, np.zeros((H, W, 3)), np.full((H, W), 0.5), exposure=1.0)
    np.testing.assert_array_equal(out, denoised)


def test_a_negative_raw_pixel_never_makes_the_final_image_negative() -> None:
    # a Mitchell film's negative lobes can make a splatted pixel negative; the product stays ≥ 0
    denoised, raw = np.full((H, W, 3), 0.01, np.float32), np.full((H, W, 3), -0.02, np.float32)
    out = compose_final(denoised, raw, np.full((H, W, 3), 1e-10), np.full((H, W), 0.5), exposure=1.0)
    assert out.min() >= 0 and np.isfinite(out).all()


def test_the_raw_error_is_smapes_expected_value_for_normal_noise_at_the_networks_exposure() -> None:
    rng = np.random.default_rng(0)
    truth, sigma, exposure = 0.3, 0.02, 4.0
    noisy = truth + sigma * rng.standard_normal(200_000)
    measured = np.mean(np.abs(noisy - truth) * exposure / ((np.abs(noisy) + truth) * exposure + SMAPE_EPS))
    predicted = raw_expected_error(np.full((1, 1, 3), truth), np.full((1, 1, 3), sigma**2), exposure)
    assert predicted[0, 0] == pytest.approx(measured, rel=0.02)


def test_box_mean_is_the_window_mean_with_the_edge_pixels_standing_in_beyond_the_film() -> None:
    values = np.random.default_rng(1).random((11, 7))
    r = WINDOW // 2
    padded = np.pad(values, r, mode="edge")
    brute = np.array([[padded[y:y + WINDOW, x:x + WINDOW].mean() for x in range(7)] for y in range(11)])
    np.testing.assert_allclose(box_mean(values), brute, rtol=1e-12)


# A low-noise, finely detailed scene under Mitsuba's default Gaussian film (the tutorials' lego in
# miniature): direct light from a constant sky onto a fine checkerboard.
DETAIL_SCENE = """<scene version="3.0.0">
  <integrator type="direct"/>
  <sensor type="perspective">
    <float name="fov" value="30"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="32"/></film>
  </sensor>
  <emitter type="constant"><rgb name="radiance" value="1.0"/></emitter>
  <shape type="rectangle">
    <bsdf type="diffuse"><texture type="checkerboard" name="reflectance">
      <rgb name="color0" value="0.1"/><rgb name="color1" value="0.8"/>
      <transform name="to_uv"><scale x="9" y="9"/></transform></texture></bsdf>
  </shape>
</scene>
"""


def smape(image: np.ndarray, reference: np.ndarray) -> float:
    return float(np.mean(np.abs(image - reference) / (np.abs(image) + np.abs(reference) + SMAPE_EPS)))


@pytest.fixture(scope="module")
def detail_run(tmp_path_factory) -> tuple[RenderLoop, np.ndarray, np.ndarray]:
    """(loop after 16 → 128 spp with the shipped networks, its final image, a 2048-spp mi.render reference)."""
    path = Path(tmp_path_factory.mktemp("detail")) / "scene.xml"
    path.write_text(DETAIL_SCENE)
    mi = mitsuba()
    reference = np.asarray(mi.render(mi.load_file(str(path)), spp=2048, seed=99))[..., :3]
    loop = RenderLoop(LoopSpec(scene=str(path), width=32, height=32, max_iterations=4, seed=3), load_networks())
    last = list(loop.run())[-1]
    return loop, last.denoised[0], reference


def test_a_denoised_job_splats_its_samples_and_its_final_image_is_composed_from_both(detail_run) -> None:
    loop, final, _ = detail_run
    buffer = loop.state.buffers[0]
    assert buffer.splat_weight is not None and not np.array_equal(buffer.raw, buffer.mean)
    exposure = float(Exposure.of(nchw(buffer.mean)).scale.flatten()[0])
    expected = compose_final(loop.denoised_only()[0], buffer.raw, buffer.raw_variance, loop.state.error_maps[0], exposure)
    np.testing.assert_array_equal(final, expected)


def test_on_low_noise_detail_the_final_image_falls_back_towards_the_better_raw_image(detail_run) -> None:
    # Here the denoiser loses detail (its input, the per-pixel FIS estimate, has ~3x the splat's
    # variance under the Gaussian film): the final image must leave most of that loss behind.
    loop, final, reference = detail_run
    denoised, raw = loop.denoised_only()[0], loop.state.buffers[0].raw
    assert smape(raw, reference) < smape(denoised, reference)  # the case under test
    assert smape(final, reference) < smape(denoised, reference)
    assert smape(final, reference) < 1.25 * smape(raw, reference)


def test_a_lambda_edit_reuses_the_raw_share_and_blends_the_new_denoised_image(detail_run, monkeypatch) -> None:
    # The raw image's share depends on the samples and the error map, not on λ: a λ edit at 2 MP
    # must not pay the share's window means again (≈ 0.8 s), only the blend.
    import service.loop.loop as loop_module

    loop, _, _ = detail_run
    buffer = loop.state.buffers[0]
    loop.denoised()  # the share is computed here, with the current λ
    calls = []
    monkeypatch.setattr(loop_module, "raw_share", lambda *a, **k: calls.append(a) or pytest.fail("share recomputed"))
    original = loop.state.lam_map.copy()
    try:
        final = loop.set_lambda(np.full_like(original, 4.0))[0]
        exposure = float(Exposure.of(nchw(buffer.mean)).scale.flatten()[0])
        expected = compose_final(loop.denoised_only()[0], buffer.raw, buffer.raw_variance, loop.state.error_maps[0],
                                 exposure)
        np.testing.assert_allclose(final, expected, rtol=1e-6, atol=1e-7)
        assert not calls
    finally:
        monkeypatch.undo()
        loop.set_lambda(original)
