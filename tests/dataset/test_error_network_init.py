"""How `renderloop train --stage error` builds the network it trains (fast: no data set)."""
import pytest
import torch

from models.checkpoint import CheckpointError, save_checkpoint
from models.denoiser import Denoiser, DenoiserConfig
from models.error_predictor import ErrorPredictor, ErrorPredictorConfig
from models.pretrained import load_networks
from service.training.config import TrainConfig, TrainConfigError
from service.training.trainer import _error_network_to_train
from tests.models.conftest import make_frame


def test_an_init_network_widened_for_the_disagreement_predicts_what_it_did_with_its_scale_reset(tmp_path):
    torch.manual_seed(0)
    shipped = ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1, output_scale=1.25, change_scale=1.5))
    save_checkpoint(tmp_path / "error_predictor.pt", shipped)
    widened = _error_network_to_train(tmp_path / "error_predictor.pt", "cpu", disagreement=True)
    # both calibrations are fitted to a trained network afterwards: a fine-tune starts without them
    assert widened.config.disagreement_input and widened.config.output_scale == 1.0
    assert widened.config.change_scale is None
    frame, denoised = make_frame(8, 8), torch.rand(1, 3, 8, 8)
    with torch.no_grad():
        before = shipped(frame, denoised) / 1.25
        for d in (torch.zeros(1, 1, 8, 8), torch.rand(1, 1, 8, 8)):
            torch.testing.assert_close(widened(frame, denoised, d), before)   # zero weights on the new channel


@pytest.mark.parametrize("had,added", [({}, {"residual": True}), ({}, {"disagreement": True, "residual": True}),
                                       ({"residual_input": True}, {"disagreement": True}),
                                       ({"disagreement_input": True}, {"residual": True})])
def test_an_init_network_given_more_inputs_predicts_what_it_did(tmp_path, had, added):
    torch.manual_seed(0)
    shipped = ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1, **had))
    save_checkpoint(tmp_path / "error_predictor.pt", shipped)
    widened = _error_network_to_train(tmp_path / "error_predictor.pt", "cpu", **added)
    assert widened.config.residual_input == (added.get("residual", False) or had.get("residual_input", False))
    frame, denoised, d = make_frame(8, 8), torch.rand(1, 3, 8, 8), torch.rand(1, 1, 8, 8)
    with torch.no_grad():
        before = shipped(frame, denoised, d if shipped.config.disagreement_input else None)
        torch.testing.assert_close(widened(frame, denoised, d if widened.config.disagreement_input else None), before)


def test_a_fresh_error_network_gets_the_inputs_asked_for():
    net = _error_network_to_train(None, "cpu", disagreement=True, residual=True)
    assert net.config.sample_count_input and net.config.disagreement_input and net.config.residual_input


def test_a_fresh_error_network_takes_the_width_asked_for():
    assert _error_network_to_train(None, "cpu", width=24).config.width == 24
    assert _error_network_to_train(None, "cpu").config.width == ErrorPredictorConfig().width


@pytest.mark.parametrize("stage,init", [("multiscale", "d.pt"), ("error", "e.pt")])
def test_error_width_is_refused_where_no_fresh_error_network_is_built(tmp_path, stage, init):
    config = TrainConfig(data=tmp_path, stage=stage, init=tmp_path / init, error_width=32)
    with pytest.raises(TrainConfigError, match="error-width"):
        config.validate()


def test_error_residual_is_refused_for_a_denoiser_stage(tmp_path):
    with pytest.raises(TrainConfigError, match="error-residual"):
        TrainConfig(data=tmp_path, stage="multiscale", init=tmp_path / "d.pt", error_residual=True).validate()


def test_error_width_is_accepted_for_a_fresh_error_network_and_beside_a_denoiser_init(tmp_path):
    TrainConfig(data=tmp_path, stage="error", error_width=32).validate()
    TrainConfig(data=tmp_path, stage="all", init=tmp_path / "d.pt", error_width=32).validate()


@pytest.mark.parametrize("stage", ["multiscale", "lambda", "gate"])
def test_error_disagreement_is_refused_for_a_denoiser_stage(tmp_path, stage):
    config = TrainConfig(data=tmp_path, stage=stage, init=tmp_path / "d.pt", oidn_candidate=True,
                         error_disagreement=True)
    with pytest.raises(TrainConfigError, match="error-disagreement"):
        config.validate()


def test_weights_whose_error_network_reads_a_candidate_the_denoiser_lacks_are_refused_at_load(tmp_path):
    save_checkpoint(tmp_path / "denoiser.pt", Denoiser(DenoiserConfig(width=8, spatial_blocks=1)))
    save_checkpoint(tmp_path / "error_predictor.pt",
                    ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1, disagreement_input=True)))
    with pytest.raises(CheckpointError, match="no candidate"):
        load_networks(tmp_path)
