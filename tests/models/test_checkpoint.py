
import pytest
import torch

from models import pretrained
from models.checkpoint import CheckpointError, load_checkpoint, save_checkpoint, stored_config
from models.denoiser import Denoiser
from models.error_predictor import ErrorPredictor, ErrorPredictorConfig
from tests.models.conftest import TINY, make_frame


def test_checkpoint_round_trip_restores_config_weights_and_extra(tmp_path):
    den = Denoiser(TINY).eval()
    path = save_checkpoint(tmp_path / "d.pt", den, extra={"epoch": 3})
    back = load_checkpoint(path, expected_kind="denoiser")
    assert back.config == den.config and back.checkpoint_extra == {"epoch": 3}
    win = [make_frame(seed=i) for i in range(3)]
    with torch.no_grad():
        torch.testing.assert_close(back(win, 1, 2.0), den(win, 1, 2.0))
    ep = ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1))
    assert isinstance(load_checkpoint(save_checkpoint(tmp_path / "e.pt", ep)), ErrorPredictor)


def test_missing_file_raises_checkpoint_error(tmp_path):
    with pytest.raises(CheckpointError, match="not found"):
        load_checkpoint(tmp_path / "nope.pt")


def test_wrong_kind_raises_checkpoint_error(tmp_path):
    path = save_checkpoint(tmp_path / "e.pt", ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1)))
    with pytest.raises(CheckpointError, match="expected 'denoiser'"):
        load_checkpoint(path, expected_kind="denoiser")


def test_version_mismatch_raises_checkpoint_error(tmp_path):
    path = save_checkpoint(tmp_path / "d.pt", Denoiser(TINY))
    ckpt = torch.load(path, weights_only=True)
    ckpt["format_version"] = 99
    torch.save(ckpt, path)
    with pytest.raises(CheckpointError, match="format 99"):
        load_checkpoint(path)


def test_shape_mismatch_raises_checkpoint_error_naming_the_tensor(tmp_path):
    path = save_checkpoint(tmp_path / "d.pt", Denoiser(TINY))
    ckpt = torch.load(path, weights_only=True)
    ckpt["config"] = {**ckpt["config"], "width": 12}       # config no longer matches the weights
    torch.save(ckpt, path)
    with pytest.raises(CheckpointError, match="encoder.conv1.weight"):
        load_checkpoint(path)


def test_missing_weights_say_how_to_produce_them(tmp_path):
    with pytest.raises(CheckpointError, match="renderloop train"):
        pretrained.load_denoiser(tmp_path)
    with pytest.raises(CheckpointError, match="renderloop train"):
        pretrained.load_error_predictor(tmp_path)


def test_weights_dir_follows_the_environment_unless_named(tmp_path, monkeypatch):
    monkeypatch.delenv(pretrained.WEIGHTS_DIR_ENV, raising=False)
    assert pretrained.weights_dir() == pretrained.SHIPPED_WEIGHTS_DIR
    monkeypatch.setenv(pretrained.WEIGHTS_DIR_ENV, str(tmp_path))
    assert pretrained.weights_dir() == tmp_path
    assert pretrained.weights_dir(tmp_path / "other") == tmp_path / "other"



def test_a_format_1_checkpoint_is_refused_by_name(tmp_path):
    """Format 1 (no s(1) anchor in the λ module) is no longer read: no shipped file has it."""
    path = save_checkpoint(tmp_path / "d.pt", Denoiser(TINY))
    ckpt = torch.load(path, weights_only=True)
    ckpt["format_version"] = 1
    torch.save(ckpt, path)
    with pytest.raises(CheckpointError, match="format 1"):
        load_checkpoint(path, expected_kind="denoiser")


def _with_stored_field(path, name, value) -> None:
    ckpt = torch.load(path, weights_only=True)
    ckpt["config"] = {**ckpt["config"], name: value}
    torch.save(ckpt, path)


def test_a_checkpoint_storing_a_retired_field_at_the_value_the_code_builds_loads_as_before(tmp_path):
    """Files written before an option was removed (the shipped error network stores
    sample_count_input=True) load to the same network: the field is checked, then dropped."""
    ep = ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1)).eval()
    path = save_checkpoint(tmp_path / "e.pt", ep)
    _with_stored_field(path, "sample_count_input", True)
    back = load_checkpoint(path, expected_kind="error_predictor")
    assert back.config == ep.config
    assert stored_config(torch.load(path, weights_only=True), path) == ep.config


def test_a_checkpoint_trained_for_a_removed_option_is_refused_by_name(tmp_path):
    path = save_checkpoint(tmp_path / "e.pt", ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1)))
    _with_stored_field(path, "sample_count_input", False)
    with pytest.raises(CheckpointError, match="sample_count_input=False"):
        load_checkpoint(path)
