"""How `renderloop train --stage error` builds the network it trains (fast: no data set)."""
import dataclasses

import pytest
import torch

from models.checkpoint import CheckpointError, save_checkpoint
from models.denoiser import Denoiser, temporal_config
from models.error_predictor import ErrorPredictor, ErrorPredictorConfig
from models.pretrained import load_networks
from service.training.config import TrainConfigError
from service.training.trainer import _error_network_to_train
from tests.models.conftest import make_frame


def test_an_init_network_starts_as_it_was_with_its_calibration_reset(tmp_path):
    torch.manual_seed(0)
    shipped = ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1, output_scale=1.25, change_scale=1.5))
    save_checkpoint(tmp_path / "error_predictor.pt", shipped)
    tuned = _error_network_to_train(tmp_path / "error_predictor.pt", "cpu", disagreement=True)
    # both calibrations are fitted to a trained network afterwards: a fine-tune starts without them
    assert tuned.config.output_scale == 1.0 and tuned.config.change_scale is None
    frame = dataclasses.replace(make_frame(8, 8), spp=torch.full((1, 1, 8, 8), 16.0))
    denoised, d = torch.rand(1, 3, 8, 8), torch.rand(1, 1, 8, 8)
    with torch.no_grad():
        torch.testing.assert_close(tuned(frame, denoised, d), shipped(frame, denoised, d) / 1.25)


def test_an_init_network_that_reads_another_input_than_its_denoiser_gives_is_refused(tmp_path):
    save_checkpoint(tmp_path / "error_predictor.pt", ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1)))
    with pytest.raises(TrainConfigError, match="disagreement"):
        _error_network_to_train(tmp_path / "error_predictor.pt", "cpu", disagreement=False)


@pytest.mark.parametrize("disagreement", [True, False])
def test_a_fresh_error_network_is_the_shipped_configuration_uncalibrated(disagreement):
    net = _error_network_to_train(None, "cpu", disagreement=disagreement)
    expected = dataclasses.replace(ErrorPredictorConfig(), output_scale=1.0, change_scale=None,
                                   disagreement_input=disagreement)
    assert net.config == expected


def test_weights_whose_error_network_reads_a_candidate_the_denoiser_lacks_are_refused_at_load(tmp_path):
    save_checkpoint(tmp_path / "denoiser.pt", Denoiser(temporal_config(width=8, spatial_blocks=1)))
    save_checkpoint(tmp_path / "error_predictor.pt",
                    ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1, disagreement_input=True)))
    with pytest.raises(CheckpointError, match="no candidate"):
        load_networks(tmp_path)
