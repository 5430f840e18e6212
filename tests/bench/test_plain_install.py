"""`renderloop bench` from a plain install: no dev-only package (scipy) at import or in its
rankings, bench/ not in the wheel, and a wheel's `renderloop bench` says where to get it."""
from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import uniform_filter
from scipy.stats import spearmanr
from setuptools import find_packages

from bench.quality_measures import average_ranks, spearman
from service.bench_command import BenchNotInstalled, load_bench_main
from service.cli import main as renderloop
from service.exr_denoise import box_mean_edge

REPO = Path(__file__).resolve().parents[2]

# A child interpreter in which `import scipy` fails, as on an install without the dev extra.
WITHOUT_SCIPY = """
import importlib.abc, sys
class NoScipy(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "scipy" or name.startswith("scipy."):
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
sys.meta_path.insert(0, NoScipy())
"""


def test_bench_cli_and_renderloop_denoise_import_and_rank_without_scipy():
    script = WITHOUT_SCIPY + """
import numpy as np
import bench.cli, bench.calibration_report, bench.quality_eval, service.exr_denoise
from bench.quality_measures import spearman
assert "scipy" not in sys.modules
print(spearman(np.array([1.0, 2.0, 2.0, 5.0]), np.array([0.1, 0.3, 0.2, 0.9])))
print(service.exr_denoise.estimate_variance(np.ones((9, 9, 3), np.float32)).max())
"""
    run = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    rho, variance = (float(v) for v in run.stdout.split())
    assert rho == pytest.approx(spearmanr([1, 2, 2, 5], [0.1, 0.3, 0.2, 0.9])[0])
    assert variance == 0.0                                  # a flat image: no residual noise


def test_spearman_ranks_ties_as_scipy_does_and_has_no_ranking_for_a_constant_or_nan_input():
    rng = np.random.default_rng(0)
    a = rng.integers(0, 6, (24, 24)).astype(np.float32)    # many ties
    b = a + rng.normal(0, 2, a.shape)
    assert spearman(a, b) == pytest.approx(spearmanr(a.ravel(), b.ravel())[0], abs=1e-12)
    np.testing.assert_array_equal(average_ranks(np.array([3.0, 1.0, 3.0, 2.0])), [3.5, 1.0, 3.5, 2.0])
    assert np.isnan(spearman(np.ones(9), np.arange(9.0)))
    assert np.isnan(spearman(np.array([1.0, np.nan, 3.0]), np.arange(3.0)))


def test_the_variance_estimates_box_filter_is_scipys_nearest_mode_uniform_filter():
    x = np.random.default_rng(1).random((13, 5, 3))        # narrower than the window: edges repeat
    np.testing.assert_allclose(box_mean_edge(x, 7), uniform_filter(x, size=(7, 7, 1), mode="nearest"), atol=1e-12)


def test_the_wheel_ships_the_product_and_not_the_measurement_wing():
    config = tomllib.loads((REPO / "pyproject.toml").read_text())
    find = config["tool"]["setuptools"]["packages"]["find"]
    packages = find_packages(where=str(REPO), include=find["include"])
    assert {"service", "service.loop", "models"} <= set(packages)
    assert not [p for p in packages if p.split(".")[0] in ("bench", "tests")]
    assert "scipy" not in " ".join(config["project"]["dependencies"])


def test_renderloop_bench_without_bench_says_to_run_it_from_a_checkout(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "bench", None)         # as in a wheel: no bench package
    monkeypatch.setitem(sys.modules, "bench.cli", None)
    with pytest.raises(BenchNotInstalled, match="source checkout"):
        load_bench_main(tmp_path)                           # a site-packages: no bench/ beside service/
    monkeypatch.setattr("service.bench_command.checkout_root", lambda: tmp_path)
    assert renderloop(["bench", "--help"]) != 0
    assert "clone the renderloop repository" in capsys.readouterr().err
