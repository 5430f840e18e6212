"""Any exposure: a real scene with its light scaled by 1e-6 … 1e12 (the same seed renders exactly
scaled samples) through the loop with the shipped networks gives the same relative result:
its SMAPE against its own reference, the output's energy, the error map and the allocation."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from models.losses import smape
from models.pretrained import Networks, load_networks
from service.loop.allocate import exposed_relative_variance
from service.loop.loop import RenderLoop
from service.loop.spec import LoopSpec

SCALES = (1e-6, 1e-3, 1.0, 1e4, 1e8, 1e12)
LIGHT = 10.0   # the area light's radiance at scale 1 (the scene's exposure statistic ≈ 0.05)

# 32², a diffuse floor, a rough gold and a rough plastic sphere under one small area light.
SCENE = """<scene version="3.0.0">
    <default name="light" value="10"/>
    <integrator type="path"><integer name="max_depth" value="6"/></integrator>
    <sensor type="perspective">
        <float name="fov" value="40"/>
        <transform name="to_world"><lookat origin="0, 1, 4" target="0, 0.3, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="32"/></film>
    </sensor>
    <shape type="rectangle">
        <transform name="to_world"><rotate x="1" angle="-90"/><scale value="3"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.6, 0.55, 0.5"/></bsdf>
    </shape>
    <shape type="sphere">
        <point name="center" x="-0.5" y="0.4" z="0"/><float name="radius" value="0.4"/>
        <bsdf type="roughconductor"><string name="material" value="Au"/><float name="alpha" value="0.15"/></bsdf>
    </shape>
    <shape type="sphere">
        <point name="center" x="0.5" y="0.4" z="0.2"/><float name="radius" value="0.4"/>
        <bsdf type="roughplastic"><float name="alpha" value="0.2"/>
            <rgb name="diffuse_reflectance" value="0.1, 0.25, 0.6"/></bsdf>
    </shape>
    <shape type="rectangle">
        <transform name="to_world"><rotate x="1" angle="90"/><scale value="0.5"/><translate y="2.5"/></transform>
        <emitter type="area"><rgb name="radiance" value="$light"/></emitter>
    </shape>
</scene>
"""


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("exposure") / "scene.xml"
    path.write_text(SCENE)
    return path


@pytest.fixture(scope="module")
def shipped() -> Networks:
    torch.set_num_threads(1)
    return load_networks()


def run(scene: Path, networks: Networks | None, k: float, **spec) -> list:
    """The loop's records for the scene with its light × k (a copy of each buffer as it was)."""
    loop = RenderLoop(LoopSpec(scene=str(scene), params={"light": repr(LIGHT * k)}, **spec), networks)
    return [(record, record.buffers[0].copy()) for record in loop.run()]


@pytest.fixture(scope="module")
def reference(scene) -> np.ndarray:
    record, buffer = run(scene, None, 1.0, spp_first=256, max_iterations=1, allocator="uniform", denoise=False,
                         seed=99)[-1]
    return buffer.mean


def relative_smape(image: np.ndarray, k: float, reference: np.ndarray) -> float:
    """SMAPE of the image in the scene's units at scale 1 against the reference."""
    return float(smape(torch.as_tensor(image / k, dtype=torch.float64), torch.as_tensor(reference, dtype=torch.float64)))


def test_a_scaled_light_renders_exactly_scaled_samples(scene):
    base = run(scene, None, 1.0, spp_first=4, max_iterations=1, allocator="uniform", denoise=False)[-1][1].mean
    for k in (1e-6, 1e12):
        samples = run(scene, None, k, spp_first=4, max_iterations=1, allocator="uniform", denoise=False)[-1][1].mean
        np.testing.assert_allclose(samples / k, base, rtol=1e-5, atol=1e-7 * float(base.max()))


def test_denoiser_error_map_and_variance_weights_are_the_same_at_any_scale(scene, shipped, reference):
    """One uniform 32-spp iteration per scale: the samples are the same up to the factor, so the
    denoised image, the error map and the variance allocator's weights must be too."""
    results = {}
    for k in SCALES:
        record, buffer = run(scene, shipped, k, spp_first=32, max_iterations=1, allocator="uniform")[-1]
        denoised = record.denoised[0]
        assert np.isfinite(denoised).all() and np.isfinite(record.error[0]).all()
        energy = float(denoised.mean() / buffer.mean.mean())
        assert energy == pytest.approx(1.0, abs=0.03), f"scale {k:g}: the output keeps {energy:.4f} of the energy"
        rv = exposed_relative_variance(buffer.mean, buffer.variance)
        results[k] = (relative_smape(denoised, k, reference), float(record.error[0].mean()), rv)
    base_smape, base_error, base_rv = results[1.0]
    assert base_smape < relative_smape(run(scene, None, 1.0, spp_first=32, max_iterations=1, allocator="uniform",
                                           denoise=False)[-1][1].mean, 1.0, reference)   # it denoises at all
    for k, (s, e, rv) in results.items():
        assert s == pytest.approx(base_smape, rel=0.02), f"scale {k:g}: SMAPE {s:.5f} vs {base_smape:.5f} at 1"
        assert e == pytest.approx(base_error, rel=0.02), f"scale {k:g}: predicted error {e:.5f} vs {base_error:.5f}"
        np.testing.assert_allclose(rv, base_rv, rtol=1e-3, atol=1e-9)


@pytest.mark.slow
def test_the_adaptive_loop_keeps_its_smape_at_any_scale(scene, shipped, reference):
    """16 → 32 → 64 spp with the error allocator, four seeds per scale (one changed sample count
    reshuffles every later sample, so single runs differ by their noise): the mean SMAPE of each
    scale within 2 % of scale 1's."""
    means = {}
    for k in SCALES:
        smapes = []
        for seed in range(4):
            record, buffer = run(scene, shipped, k, spp_first=16, max_iterations=3, seed=seed)[-1]
            assert np.isfinite(record.denoised[0]).all()
            assert float(record.denoised[0].mean() / buffer.mean.mean()) == pytest.approx(1.0, abs=0.03)
            smapes.append(relative_smape(record.denoised[0], k, reference))
        means[k] = float(np.mean(smapes))
    for k, m in means.items():
        assert m == pytest.approx(means[1.0], rel=0.02), f"loop SMAPE per scale: {means}"
