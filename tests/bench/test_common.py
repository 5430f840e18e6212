"""The measurement wing's shared pieces: metric names and values, the reference cache, thread pinning."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from bench.common import (METRIC_NAMES, REFERENCE_SEED, cached_reference, fill, git_commit, image_metrics, load_bench_networks,
                          pinned_torch_threads, provenance)
from models.checkpoint import read_checkpoint
from models.pretrained import SHIPPED_WEIGHTS_DIR


def test_identical_images_score_perfectly_under_every_metric_name():
    image = np.random.default_rng(0).random((16, 16, 3), dtype=np.float32)
    metrics = image_metrics(image, image)
    assert tuple(metrics) == METRIC_NAMES
    assert metrics["smape"] == pytest.approx(0.0, abs=1e-7)
    assert metrics["relmse"] == pytest.approx(0.0, abs=1e-7)
    assert metrics["dssim"] == pytest.approx(0.0, abs=1e-4)


def test_metrics_sanitise_non_finite_pixels_instead_of_propagating_them():
    reference = np.ones((8, 8, 3), dtype=np.float32)
    image = reference.copy()
    image[0, 0] = np.nan
    image[1, 1] = np.inf
    metrics = image_metrics(image, reference)
    assert all(np.isfinite(value) for value in metrics.values())
    assert metrics["smape"] > 0  # the two bad pixels count as black, not as matches


def test_reference_is_rendered_once_with_the_reference_seed_then_read_from_the_cache(tmp_path: Path):
    seeds = []

    def render(seed: int):
        seeds.append(seed)
        return np.full((4, 4, 3), 0.5, np.float32), np.full((4, 4, 3), 0.01, np.float32)

    path = tmp_path / "ref.npz"
    first = cached_reference(path, render)
    second = cached_reference(path, render)
    assert seeds == [REFERENCE_SEED]
    np.testing.assert_array_equal(first.mean, second.mean)
    assert second.relative_error == pytest.approx(0.1 / 0.51, rel=1e-5)


def test_pinned_threads_are_restored_even_when_the_body_raises():
    before = torch.get_num_threads()
    with pytest.raises(RuntimeError):
        with pinned_torch_threads(1):
            assert torch.get_num_threads() == 1
            raise RuntimeError("boom")
    assert torch.get_num_threads() == before


def test_provenance_names_command_variant_and_commit():
    text = provenance("renderloop bench --sampler", "llvm_ad_rgb")
    assert "Command: `renderloop bench --sampler`" in text and "`llvm_ad_rgb`" in text and "Date:" in text and "commit" in text


def test_every_template_field_is_filled_or_the_fill_fails():
    with pytest.raises(KeyError):
        fill("memory.md", provenance="p")


def test_bench_networks_describe_each_checkpoint_by_its_recipe_and_data_hash():
    description = load_bench_networks(None).description
    for name in ("denoiser.pt", "error_predictor.pt"):
        extra = read_checkpoint(SHIPPED_WEIGHTS_DIR / name)["extra"]
        assert f"recipe={extra['recipe']}" in description and f"data={extra['data']}" in description
        if "calibration" in extra:
            assert f"calibration={extra['calibration']}" in description


def test_bench_networks_name_the_shipped_folder_relative_to_the_repository(monkeypatch):
    """A report's "Weights:" line must not carry this machine's path (it is committed)."""
    monkeypatch.chdir(SHIPPED_WEIGHTS_DIR.parents[1])
    description = load_bench_networks(None).description
    assert description.startswith("models/weights: ")
    assert str(SHIPPED_WEIGHTS_DIR.parents[1]) not in description


def test_a_copied_tree_names_the_commit_it_was_told(monkeypatch) -> None:
    # a device machine gets the files without (or with a stale) .git: the run passes the commit
    monkeypatch.setenv("RENDERLOOP_COMMIT", "0badc0de")
    assert git_commit() == "0badc0de"
    monkeypatch.delenv("RENDERLOOP_COMMIT")
    assert git_commit() not in ("", "0badc0de")
