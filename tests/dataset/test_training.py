"""Training on a tiny generated data set (slow: run with `-m slow`)."""
import subprocess
import sys

import pytest
import torch

from models.checkpoint import load_checkpoint, save_checkpoint
from models.denoiser import Denoiser, DenoiserConfig
from models.training import denoiser_loss, sample_lambda
from service.dataset.loader import DenoiserDataset, collate_samples

pytestmark = pytest.mark.slow


def test_a_tiny_denoiser_loss_falls_and_stays_finite_on_hdr_data(sequence_dataset):
    torch.manual_seed(0)
    data = DenoiserDataset(sequence_dataset, split="train", radius=1, crop=16, seed=0)
    batch = collate_samples([data[i] for i in range(min(4, len(data)))])
    # HDR: scale one scene up so radiance spans 1e-3 … 1e4 like a bright emitter seen directly.
    for frame in batch.frames:
        frame.color[0] *= 1e3
        frame.variance[0] *= 1e6
    for ref in batch.references:
        ref[0] *= 1e3
    model = Denoiser(DenoiserConfig(width=8, spatial_blocks=1))
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    gen = torch.Generator().manual_seed(0)
    losses = []
    for _ in range(40):
        lam = sample_lambda(batch.frames[0].color.shape[0], 16, 16, gen)
        loss = denoiser_loss(model, batch.frames, batch.centre, batch.references[batch.centre], lam)
        opt.zero_grad()
        loss.backward()
        assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)
        opt.step()
        losses.append(loss.item())
    assert all(torch.isfinite(torch.tensor(losses)))
    assert sum(losses[-5:]) / 5 < 0.9 * sum(losses[:5]) / 5


@pytest.mark.parametrize("stage", ["all", "staged"])
def test_train_command_writes_loadable_checkpoints_with_their_command(sequence_dataset, tmp_path, stage):
    out = tmp_path / "weights"
    result = subprocess.run(
        [sys.executable, "-m", "service.cli", "train", "--data", str(sequence_dataset), "--stage", stage,
         "-o", str(out), "--steps", "4", "--val-every", "2", "--batch", "2", "--crop", "16", "--width", "8",
         "--spatial-blocks", "2", "--quiet"],
        capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr
    denoiser = load_checkpoint(out / "denoiser.pt", expected_kind="denoiser")
    assert denoiser.config.width == 8 and denoiser.config.spatial_blocks == 2
    assert "renderloop train" in denoiser.checkpoint_extra["command"]
    assert denoiser.config.temporal and denoiser.config.multiscale  # the shipped one is the full network
    if stage == "staged":
        single = load_checkpoint(out / "stage_single.pt", expected_kind="denoiser")
        assert not single.config.temporal and not single.config.multiscale
        assert denoiser.checkpoint_extra["stage"] == "lambda"
    load_checkpoint(out / "error_predictor.pt", expected_kind="error_predictor")


def test_train_command_trains_on_noisy_targets_and_validates_on_clean_references(sequence_dataset, tmp_path):
    out = tmp_path / "n2n"
    result = subprocess.run(
        [sys.executable, "-m", "service.cli", "train", "--data", str(sequence_dataset), "--noisy-targets",
         "--val-data", str(sequence_dataset), "--stage", "denoiser", "-o", str(out), "--steps", "4", "--val-every", "2",
         "--batch", "2", "--crop", "16", "--width", "8", "--trunk", "unet", "--quiet"],
        capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr
    denoiser = load_checkpoint(out / "denoiser.pt", expected_kind="denoiser")
    assert denoiser.config.trunk == "unet" and "--noisy-targets" in denoiser.checkpoint_extra["command"]
    assert "best validation SMAPE" in result.stdout


def test_a_fine_tune_with_keep_settings_writes_the_init_settings_into_its_checkpoint(sequence_dataset, tmp_path):
    settings = {"energy_tolerance": 0.03, "gate_offset": 2.0, "coarse_gate_offset": 10.0, "candidate_cap": True,
                "kernel_clamp": 0.5}
    init = tmp_path / "shipped.pt"
    save_checkpoint(init, Denoiser(DenoiserConfig(width=8, spatial_blocks=1, temporal=False, oidn_candidate=True,
                                                  **settings)))
    out = tmp_path / "fine-tuned"
    result = subprocess.run(
        [sys.executable, "-m", "service.cli", "train", "--data", str(sequence_dataset), "--stage", "multiscale",
         "--init", str(init), "--oidn-candidate", "--single-frame", "--keep-settings", "-o", str(out),
         "--steps", "2", "--val-every", "1", "--batch", "2", "--crop", "16", "--quiet"],
        capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr
    tuned = load_checkpoint(out / "stage_multiscale.pt", expected_kind="denoiser")
    assert {name: getattr(tuned.config, name) for name in settings} == settings
    assert tuned.checkpoint_extra["settings_from"] == str(init) and "--keep-settings" in tuned.checkpoint_extra["command"]


def test_an_error_network_trained_with_error_disagreement_reads_it_and_loads_for_the_loop(sequence_dataset, tmp_path):
    out = tmp_path / "with-d"
    out.mkdir()
    save_checkpoint(out / "denoiser.pt", Denoiser(DenoiserConfig(width=8, spatial_blocks=1, temporal=False,
                                                                 oidn_candidate=True)))
    result = subprocess.run(
        [sys.executable, "-m", "service.cli", "train", "--data", str(sequence_dataset), "--stage", "error",
         "--error-disagreement", "-o", str(out), "--steps", "2", "--val-every", "1", "--batch", "2", "--crop", "16",
         "--quiet"],
        capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr
    network = load_checkpoint(out / "error_predictor.pt", expected_kind="error_predictor")
    assert network.config.disagreement_input and "--error-disagreement" in network.checkpoint_extra["command"]
