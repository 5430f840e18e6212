"""`renderloop denoise` takes the EXRs Mitsuba writes itself: an `aov` integrator's output
(R,G,B with albedo.*, nn.* or sh_normal.*, depth as dd.T or missing, no variance, no spp),
made here with `mi.render`, denoised through the real CLI as a subprocess."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from service.exr import ExrError, read_exr
from service.exr_denoise import NO_VARIANCE_NOTE, estimate_variance
from service.render.runtime import mitsuba

REPO = Path(__file__).resolve().parents[1]
RENDERLOOP = Path(sys.executable).with_name("renderloop")
SIZE, SPP = 24, 8
ALL_AOVS = "albedo:albedo,nn:sh_normal,dd:depth"


def smape(image: np.ndarray, reference: np.ndarray, eps: float = 1e-2) -> float:
    """Vogels et al. 2018, eq. 2."""
    return float(np.mean(np.abs(image - reference) / (np.abs(image) + np.abs(reference) + eps)))


def mitsuba_scene(integrator: dict, spp: int) -> object:
    """A diffuse sphere on a plane under a constant sky, rendered through a box filter."""
    mi = mitsuba()
    return mi.load_dict({
        "type": "scene",
        "integrator": integrator,
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 1, 4], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": SIZE, "height": SIZE, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "ball": {"type": "sphere", "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8, 0.3, 0.2]}}},
        "floor": {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, -1, 0]).rotate([1, 0, 0], -90)
                  .scale(4), "bsdf": {"type": "diffuse"}},
        "sky": {"type": "constant"},
    })


def write_aov_exr(path: Path, aovs: str, spp: int = SPP, seed: int = 0) -> Path:
    """What a user gets from mi.render with an aov integrator and `film.bitmap().write(...)`."""
    mi = mitsuba()
    scene = mitsuba_scene({"type": "aov", "aovs": aovs, "img": {"type": "path"}}, spp)
    mi.render(scene, seed=seed)
    scene.sensors()[0].film().bitmap().write(str(path))
    return path


def denoise(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(RENDERLOOP), "denoise", *args], capture_output=True, text=True, timeout=300, cwd=REPO)


@pytest.fixture(scope="module")
def reference() -> np.ndarray:
    mi = mitsuba()
    return np.asarray(mi.render(mitsuba_scene({"type": "path"}, 1024), seed=7), dtype=np.float32)[..., :3]


def test_mitsuba_names_are_read_into_the_layers(tmp_path):
    frame = read_exr(write_aov_exr(tmp_path / "aov.exr", ALL_AOVS))
    assert frame.color.shape == (SIZE, SIZE, 3) and frame.noisy is None and frame.variance is None
    assert frame.albedo is not None and frame.normal is not None and frame.depth is not None
    hit = frame.depth > 0
    # AOVs are pixel means over the samples (a miss adds 0), so only edge pixels are shorter than 1.
    assert hit.any() and np.median(np.linalg.norm(frame.normal[hit], axis=-1)) == pytest.approx(1.0, abs=1e-3)


def test_an_aov_render_is_denoised_with_one_line_on_the_estimated_variance(tmp_path, reference):
    source = write_aov_exr(tmp_path / "aov.exr", ALL_AOVS)
    result = denoise(str(source), "--spp", str(SPP), "-o", str(tmp_path / "out.exr"))
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines()[0] == f"note: {NO_VARIANCE_NOTE}"
    assert sum(line.startswith("note:") for line in result.stdout.splitlines()) == 1
    out, noisy = read_exr(tmp_path / "out.exr"), read_exr(source).color
    np.testing.assert_array_equal(out.noisy, noisy)  # Mitsuba's radiance kept as the noisy layer
    assert np.isfinite(out.color).all() and np.all(out.spp == SPP)
    assert out.error is None and "no error estimate: no variance layer" in result.stdout  # none on an estimate
    # The denoiser did its job on Mitsuba's own input: much closer to a 1024-spp reference.
    assert smape(out.color, reference) < 0.7 * smape(noisy, reference)


def test_an_aov_render_without_depth_is_denoised(tmp_path):
    source = write_aov_exr(tmp_path / "aov.exr", "albedo:albedo,sh_normal:sh_normal")
    assert read_exr(source).depth is None
    result = denoise(str(source), "-o", str(tmp_path / "out.exr"))
    assert result.returncode == 0, result.stderr
    assert np.isfinite(read_exr(tmp_path / "out.exr").color).all()


def test_a_render_without_albedo_is_one_error_line_with_the_recipe(tmp_path):
    source = write_aov_exr(tmp_path / "aov.exr", "nn:sh_normal")
    result = denoise(str(source), "-o", str(tmp_path / "out.exr"))
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("renderloop: error:"), result.stderr
    assert "missing layers albedo.R/G/B" in lines[0] and 'value="albedo:albedo,nn:sh_normal,dd:depth"' in lines[0]


def test_estimated_variance_tracks_the_true_noise_of_a_flat_image():
    rng = np.random.default_rng(0)
    sigma = 0.1
    image = 0.5 + sigma * rng.standard_normal((64, 64, 3))
    assert estimate_variance(image).mean() == pytest.approx(sigma**2, rel=0.1)
