"""The loop branch of the data set (`renderloop dataset --loop-branch`) and the error network
trained on it: what the loop feeds the error network, at every iteration's budget."""
from __future__ import annotations

import hashlib
import shutil
from dataclasses import replace
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from models.checkpoint import load_checkpoint
from models.pretrained import SHIPPED_WEIGHTS_DIR, load_networks
from service.dataset.build import LOOP_ITEMS, DatasetError, build_dataset, item_path, read_manifest
from service.dataset.loader import DenoiserDataset
from service.exr import read_exr
from service.loop.denoise_frame import denoise_frame

LOOP_LEVELS = ("spp16",) + LOOP_ITEMS


@pytest.fixture(scope="module")
def loop_dataset(tmp_path_factory, tiny) -> Path:
    root = tmp_path_factory.mktemp("loop")
    build_dataset(root, scenes=2, frames=1, split="train", loop_networks=load_networks(), **tiny)
    return root


def test_loop_branch_doubles_the_total_each_iteration_with_non_uniform_counts(loop_dataset):
    entry = read_manifest(loop_dataset)["splits"]["train"]
    assert entry["loop_branch"] and "--loop-branch" in entry["command"]
    uneven = False
    for seed in entry["scene_seeds"]:
        for item, mean in zip(LOOP_ITEMS, (32, 64, 128)):
            spp = read_exr(item_path(loop_dataset, "train", seed, 0, item)).spp
            assert spp.mean() == mean  # the loop's budget rule, exactly
            assert spp.min() >= 1
            uneven |= bool(spp.std() > 0)
    assert uneven  # allocated by the predicted error, not uniformly


def test_loader_serves_loop_levels_with_their_sample_counts(loop_dataset):
    data = DenoiserDataset(loop_dataset, split="train", levels=LOOP_LEVELS, crop=8, seed=0)
    assert {item.level for item in data.items} == set(LOOP_LEVELS)
    sample = data[0]
    assert sample.noisy.spp is not None and sample.noisy.spp.shape[-2:] == (8, 8)


def test_loop_levels_on_a_data_set_without_them_say_how_to_build_them(still_dataset):
    with pytest.raises(DatasetError, match="--loop-branch"):
        DenoiserDataset(still_dataset, split="heldout", levels=LOOP_LEVELS)


def test_loop_branch_refuses_sequences(tmp_path, tiny):
    with pytest.raises(DatasetError, match="--frames 1"):
        build_dataset(tmp_path, scenes=1, frames=2, loop_networks=load_networks(), **tiny)


def test_error_network_trains_on_loop_levels_reads_their_sample_counts_and_names_its_denoiser(loop_dataset, tmp_path):
    out = tmp_path / "weights"
    out.mkdir()
    shutil.copy(SHIPPED_WEIGHTS_DIR / "denoiser.pt", out / "denoiser.pt")
    result = subprocess.run(
        [sys.executable, "-m", "service.cli", "train", "--data", str(loop_dataset), "--stage", "error", "-o", str(out),
         "--steps", "4", "--val-every", "2", "--batch", "2", "--crop", "8", "--quiet",
         "--error-levels", ",".join(LOOP_LEVELS)],
        capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    model = load_checkpoint(out / "error_predictor.pt", expected_kind="error_predictor")
    assert model.config.disagreement_input
    denoiser_digest = hashlib.sha1((out / "denoiser.pt").read_bytes()).hexdigest()[:10]
    assert model.checkpoint_extra["denoiser"] == f"sha1:{denoiser_digest}"
    denoiser = load_checkpoint(out / "denoiser.pt", expected_kind="denoiser")
    sample = DenoiserDataset(loop_dataset, split="train", levels=("loop128",), crop=None)[0]
    with torch.no_grad():
        denoised = denoise_frame(denoiser, [sample.noisy], 0)
        disagreement = torch.zeros_like(denoised[:, :1])
        predicted = model(sample.noisy, denoised, disagreement)
        fewer = model(replace(sample.noisy, spp=sample.noisy.spp / 8), denoised, disagreement)
    assert torch.isfinite(predicted).all() and (predicted >= 0).all()
    assert not torch.equal(predicted, fewer)  # the sample-count channel reaches the output


def test_error_stage_from_init_starts_from_that_network_with_its_calibration_scale_reset(loop_dataset, tmp_path):
    shipped = load_checkpoint(SHIPPED_WEIGHTS_DIR / "error_predictor.pt", expected_kind="error_predictor")
    out = tmp_path / "weights"
    out.mkdir()
    shutil.copy(SHIPPED_WEIGHTS_DIR / "denoiser.pt", out / "denoiser.pt")
    result = subprocess.run(
        [sys.executable, "-m", "service.cli", "train", "--data", str(loop_dataset), "--stage", "error", "-o", str(out),
         "--init", str(SHIPPED_WEIGHTS_DIR / "error_predictor.pt"), "--steps", "2", "--val-every", "1",
         "--batch", "2", "--crop", "8", "--lr", "1e-12", "--quiet", "--error-levels", ",".join(LOOP_LEVELS)],
        capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    tuned = load_checkpoint(out / "error_predictor.pt", expected_kind="error_predictor")
    assert shipped.config.output_scale != 1.0 and tuned.config.output_scale == 1.0
    digest = hashlib.sha1((SHIPPED_WEIGHTS_DIR / "error_predictor.pt").read_bytes()).hexdigest()[:10]
    assert tuned.checkpoint_extra["init"] == f"sha1:{digest}"
    assert tuned.config.disagreement_input == shipped.config.disagreement_input
    for name, value in shipped.state_dict().items():
        torch.testing.assert_close(tuned.state_dict()[name], value, atol=1e-6, rtol=0)


@pytest.mark.parametrize("stage, trainable", [("gate", ("gate.",)), ("lambda", ("specialise.mix.", "specialise.delta"))])
def test_fine_tuning_stages_train_only_their_part_of_the_shipped_denoiser(loop_dataset, tmp_path, stage, trainable):
    out = tmp_path / stage
    result = subprocess.run(
        [sys.executable, "-m", "service.cli", "train", "--data", str(loop_dataset), "--stage", stage, "-o", str(out),
         "--init", str(SHIPPED_WEIGHTS_DIR / "denoiser.pt"),
         "--steps", "3", "--val-every", "3", "--batch", "2", "--crop", "16", "--lr", "0.05", "--quiet"],
        capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    before = load_checkpoint(SHIPPED_WEIGHTS_DIR / "denoiser.pt", expected_kind="denoiser").state_dict()
    written = out / ("denoiser.pt" if stage == "lambda" else f"stage_{stage}.pt")
    after = load_checkpoint(written, expected_kind="denoiser").state_dict()
    changed = {name for name in before if not torch.equal(before[name], after[name])}
    assert changed and all(name.startswith(trainable) for name in changed)
    config = load_checkpoint(written, expected_kind="denoiser").config
    # a stage file as trained (settings off); the finished denoiser with the shipped settings
    assert (config.gate_offset, config.energy_tolerance) == ((2.0, 0.03) if stage == "lambda" else (0.0, 0.0))
