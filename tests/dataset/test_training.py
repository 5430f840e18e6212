"""Training on a tiny generated data set (slow: run with `-m slow`)."""
import subprocess
import sys

import pytest
import torch

from models.checkpoint import DATA_KEY, RECIPE_KEY, load_checkpoint
from models.denoiser import NEUTRAL_SETTINGS, POST_TRAINING_SETTINGS, DenoiserConfig, Denoiser, temporal_config
from models.training import denoiser_loss, sample_lambda
from service.dataset.loader import DenoiserDataset, collate_samples
from service.training.provenance import data_hash

pytestmark = pytest.mark.slow
TINY_RUN = ["--steps", "2", "--val-every", "1", "--batch", "2", "--crop", "16", "--quiet"]


def train(*argv: str) -> subprocess.CompletedProcess:
    result = subprocess.run([sys.executable, "-m", "service.cli", "train", *argv, *TINY_RUN],
                            capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr
    return result


def settings_of(model) -> dict:
    return {name: getattr(model.config, name) for name in POST_TRAINING_SETTINGS}


def test_a_tiny_temporal_denoiser_loss_falls_and_stays_finite_on_hdr_data(sequence_dataset):
    torch.manual_seed(0)
    data = DenoiserDataset(sequence_dataset, split="train", radius=1, crop=16, seed=0)
    batch = collate_samples([data[i] for i in range(min(4, len(data)))])
    # HDR: scale one scene up so radiance spans 1e-3 … 1e4 like a bright emitter seen directly.
    for frame in batch.frames:
        frame.color[0] *= 1e3
        frame.variance[0] *= 1e6
    for ref in batch.references:
        ref[0] *= 1e3
    model = Denoiser(temporal_config(width=8, spatial_blocks=1))
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


def test_the_recipes_stages_chain_into_the_shipped_configuration_with_recipe_and_data_recorded(sequence_dataset,
                                                                                                tmp_path):
    """single → multiscale → gate → lambda → error, each from the previous file (scripts/train-weights.sh)."""
    data = ["--data", str(sequence_dataset), "--recipe", "tiny"]
    train(*data, "--stage", "single", "-o", str(tmp_path / "single"))
    train(*data, "--stage", "multiscale", "--init", str(tmp_path / "single/stage_single.pt"), "-o", str(tmp_path / "ms"))
    train(*data, "--stage", "gate", "--init", str(tmp_path / "ms/stage_multiscale.pt"), "-o", str(tmp_path / "gate"))
    result = train(*data, "--stage", "lambda", "--init", str(tmp_path / "gate/stage_gate.pt"),
                   "-o", str(tmp_path / "final"))
    assert "stage lambda: best validation" in result.stdout
    single = load_checkpoint(tmp_path / "single/stage_single.pt", expected_kind="denoiser")
    assert not single.config.multiscale and settings_of(single) == NEUTRAL_SETTINGS   # trained without them
    denoiser = load_checkpoint(tmp_path / "final/denoiser.pt", expected_kind="denoiser")
    assert denoiser.config == DenoiserConfig()     # the shipped configuration, post-training settings included
    assert denoiser.checkpoint_extra[RECIPE_KEY] == "tiny"
    assert denoiser.checkpoint_extra[DATA_KEY] == data_hash([sequence_dataset])
    assert denoiser.checkpoint_extra["init"].startswith("sha1:") and str(tmp_path) not in str(denoiser.checkpoint_extra)
    train(*data, "--stage", "error", "-o", str(tmp_path / "final"))
    error_net = load_checkpoint(tmp_path / "final/error_predictor.pt", expected_kind="error_predictor")
    assert error_net.config.disagreement_input
    assert error_net.config.output_scale == 1.0 and error_net.config.change_scale is None   # fitted afterwards
    assert error_net.checkpoint_extra["denoiser"].startswith("sha1:")


def test_the_temporal_kpcn_trains_its_own_stage_from_the_multiscale_one(sequence_dataset, tmp_path):
    data = ["--data", str(sequence_dataset), "--temporal"]
    train(*data, "--stage", "multiscale", "-o", str(tmp_path / "ms"))
    train(*data, "--stage", "temporal", "--init", str(tmp_path / "ms/stage_multiscale.pt"), "-o", str(tmp_path / "t"))
    temporal = load_checkpoint(tmp_path / "t/stage_temporal.pt", expected_kind="denoiser")
    assert temporal.config == temporal_config() and temporal.temporal is not None
