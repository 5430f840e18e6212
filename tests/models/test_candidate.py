"""An external denoiser's image (OIDN) as one more candidate of the joint softmax (models/candidate.py)."""
from __future__ import annotations

import dataclasses

import pytest
import torch
import torch.nn.functional as F

from models.candidate import N_STATS, box_mean, clamp_around, gate_statistics
from models.checkpoint import load_checkpoint, save_checkpoint
from models.denoiser import CANDIDATE_CHANNELS, NEUTRAL_SETTINGS, POST_TRAINING_SETTINGS, Denoiser, DenoiserConfig, lambda_code
from service.training.config import TrainConfig, TrainConfigError
from service.training.trainer import _denoiser_to_train, write_post_training_settings

from .conftest import TINY, make_frame

CANDIDATE = dataclasses.replace(TINY, oidn_candidate=True)
H, W = 13, 18   # not a multiple of the pyramid's alignment: padding is exercised too


def candidate_image(seed: int = 5) -> torch.Tensor:
    return torch.rand(1, 3, H, W, generator=torch.Generator().manual_seed(seed)) * 3


def saturate_gate(model: Denoiser, logit: float) -> None:
    """Force the candidate's logit g everywhere (the bias column of its λ module)."""
    with torch.no_grad():
        model.gate.hidden.weight.zero_()
        model.gate.specialise.base.zero_()
        model.gate.specialise.base[:, -1] = logit


@torch.no_grad()
def test_candidate_weight_is_a_share_in_0_1_at_every_level_and_every_lambda():
    model = Denoiser(CANDIDATE).eval()
    cache = model.prepare([make_frame(H, W)], 0, candidate_image())
    for lam in (1.0, 10.0, torch.rand(H, W) * 9 + 1):
        weights = model.candidate_weights(cache, lam)
        assert len(weights) == CANDIDATE.levels
        assert all(((w >= 0) & (w <= 1)).all() for w in weights)


@torch.no_grad()
def test_output_stays_between_a_constant_input_and_a_constant_candidate():
    """Every level is (1 − w)·kernel result + w·candidate and the kernels are convex: with a flat
    noisy image a and a flat candidate b the result must lie in [a, b] everywhere."""
    frame = make_frame(H, W)
    frame.color.fill_(0.5)
    frame.albedo.fill_(0.6)
    out = Denoiser(CANDIDATE).eval()([frame], 0, 3.0, torch.full((1, 3, H, W), 2.0))
    assert out.min() >= 0.5 - 1e-5 and out.max() <= 2.0 + 1e-5
    assert out.mean() > 0.5 + 0.1   # the fresh gate leans towards the candidate (σ(1) ≈ 0.73)


@pytest.mark.parametrize("lam", [1.0, 7.0, "map"])
@torch.no_grad()
def test_a_saturated_candidate_logit_returns_the_candidate_image_exactly(lam):
    model = Denoiser(CANDIDATE).eval()
    saturate_gate(model, 1e4)
    candidate = candidate_image()
    lam = torch.rand(H, W) * 9 + 1 if lam == "map" else lam
    out = model([make_frame(H, W), make_frame(H, W, seed=1)], 0, lam, candidate)
    # σ is bounded at σ(10) = 1 − 4.5e-5 (models.candidate.GATE_LOGIT_BOUND)
    torch.testing.assert_close(out, candidate, atol=2e-4, rtol=1e-4)


@torch.no_grad()
def test_a_suppressed_candidate_logit_returns_the_plain_kernel_network():
    model = Denoiser(CANDIDATE).eval()
    saturate_gate(model, -1e4)
    plain = Denoiser(TINY).eval()
    plain.load_state_dict({k: v for k, v in model.state_dict().items() if not k.startswith("gate.")})
    window = [make_frame(H, W), make_frame(H, W, seed=1)]
    torch.testing.assert_close(model(window, 0, 4.0, candidate_image()), plain(window, 0, 4.0), atol=2e-4, rtol=1e-4)


@torch.no_grad()
def test_a_lambda_edit_reruns_only_the_tail_with_the_candidate_cached(monkeypatch):
    model = Denoiser(CANDIDATE).eval()
    for delta in (model.specialise.delta, model.gate.specialise.delta):   # fresh λ modules ignore λ
        delta.add_(torch.randn_like(delta))
    cache = model.prepare([make_frame(H, W)], 0, candidate_image())
    assert all(level.candidate is not None and level.gate_hidden is not None for level in cache.levels)
    calls = []
    for name in ("encoder", "spatial", "kernel_head"):
        getattr(model, name).register_forward_hook(lambda *_, n=name: calls.append(n))
    monkeypatch.setattr("models.candidate.gate_statistics", lambda *_: pytest.fail("statistics recomputed"))
    a, b = model.apply(cache, 1.0), model.apply(cache, 10.0)
    assert calls == [] and not torch.equal(a, b)


@torch.no_grad()
def test_nan_and_inf_in_the_candidate_are_replaced_and_counted():
    candidate = candidate_image()
    candidate[0, 0, 2, 3], candidate[0, 1, 5, 5], candidate[0, 2, 7, 1] = float("nan"), float("inf"), -float("inf")
    model = Denoiser(CANDIDATE).eval()
    cache = model.prepare([make_frame(H, W)], 0, candidate)
    out = model.apply(cache, 2.0)
    assert torch.isfinite(out).all() and (out >= 0).all()
    assert cache.n_bad == 3


def test_the_candidate_must_be_given_exactly_when_the_config_asks_for_it():
    with pytest.raises(ValueError, match="needs"):
        Denoiser(CANDIDATE).prepare([make_frame(H, W)], 0)
    with pytest.raises(ValueError, match="takes no"):
        Denoiser(TINY).prepare([make_frame(H, W)], 0, candidate_image())


def test_gradients_reach_the_gate_and_the_kernels():
    model = Denoiser(CANDIDATE)
    out = model([make_frame(H, W)], 0, 1.0, candidate_image())
    out.mean().backward()
    assert model.gate.specialise.base.grad.abs().sum() > 0
    assert model.specialise.base.grad.abs().sum() > 0


def test_checkpoints_record_the_candidate_flag_and_reload_it(tmp_path):
    model = Denoiser(CANDIDATE).eval()
    loaded = load_checkpoint(save_checkpoint(tmp_path / "d.pt", model), expected_kind="denoiser")
    assert loaded.config.oidn_candidate
    window, candidate = [make_frame(H, W)], candidate_image()
    with torch.no_grad():
        torch.testing.assert_close(loaded(window, 0, 2.0, candidate), model(window, 0, 2.0, candidate))


def test_the_training_loss_keeps_the_kernels_learning_when_the_gate_trusts_the_candidate():
    from models.training import denoiser_loss

    model = Denoiser(CANDIDATE)
    saturate_gate(model, 1e4)
    frame = make_frame(16, 16)
    denoiser_loss(model, [frame], 0, frame.color * 0.9, torch.ones(1, 1, 16, 16), torch.rand(1, 3, 16, 16)).backward()
    assert model.specialise.base.grad.abs().sum() > 1e-4


@torch.no_grad()
def test_gate_offset_moves_every_levels_weight_towards_the_candidate():
    model = Denoiser(CANDIDATE).eval()
    cache = model.prepare([make_frame(H, W)], 0, candidate_image())
    before = model.candidate_weights(cache, 2.0)
    model.config = dataclasses.replace(CANDIDATE, gate_offset=2.0)
    after = model.candidate_weights(cache, 2.0)
    assert all((a > b).all() for a, b in zip(after, before))
    assert all((a < 1).all() for a in after)                     # a lean, not a switch


@torch.no_grad()
def test_coarse_gate_offset_moves_only_the_coarser_levels():
    model = Denoiser(dataclasses.replace(CANDIDATE, gate_offset=1.0)).eval()
    cache = model.prepare([make_frame(H, W)], 0, candidate_image())
    same = model.candidate_weights(cache, 2.0)
    model.config = dataclasses.replace(model.config, coarse_gate_offset=6.0)
    split = model.candidate_weights(cache, 2.0)
    torch.testing.assert_close(split[0], same[0], rtol=0, atol=0)
    assert all((s > w).all() for s, w in zip(split[1:], same[1:]))


@torch.no_grad()
def test_gate_offsets_act_fully_at_lambda_1_and_not_at_all_at_lambda_10():
    model = Denoiser(CANDIDATE).eval()
    cache = model.prepare([make_frame(H, W)], 0, candidate_image())
    plain = {lam: model.candidate_weights(cache, lam) for lam in (1.0, 10.0)}
    model.config = dataclasses.replace(CANDIDATE, gate_offset=2.0, coarse_gate_offset=10.0)
    leaning = {lam: model.candidate_weights(cache, lam) for lam in (1.0, 10.0)}
    assert all((a > b).all() for a, b in zip(leaning[1.0], plain[1.0]))
    for a, b in zip(leaning[10.0], plain[10.0]):
        torch.testing.assert_close(a, b)
    lam_map = torch.full((H, W), 10.0)
    lam_map[:, : W // 2] = 1.0        # a painted λ map: each pixel follows its own λ
    finest = model.candidate_weights(cache, lam_map)[0][0, 0]
    torch.testing.assert_close(finest[:, W // 2:], leaning[10.0][0][0, 0, :, W // 2:])
    assert (finest[:, : W // 2] > plain[10.0][0][0, 0, :, : W // 2]).all()


@pytest.mark.parametrize("shape", [(1, 1, 37, 29), (2, 1, 5, 3), (1, 1, 1, 1)])
@pytest.mark.parametrize("k", [3, 7])
def test_box_mean_equals_pooling_over_in_image_pixels(shape, k):
    x = torch.rand(shape, generator=torch.Generator().manual_seed(k)) * 100
    expected = F.avg_pool2d(x, k, stride=1, padding=k // 2, count_include_pad=False)
    torch.testing.assert_close(box_mean(x, k), expected)


GUIDED = dataclasses.replace(CANDIDATE, temporal=False)   # single frame with a candidate: the trunk reads it


def test_every_single_frame_network_with_a_candidate_reads_it_in_its_trunk_and_no_other_does():
    features = Denoiser(GUIDED).features.channels
    assert Denoiser(GUIDED).encoder.conv1.in_channels == features + CANDIDATE_CHANNELS
    for other in (CANDIDATE, dataclasses.replace(GUIDED, oidn_candidate=False)):   # temporal; no candidate
        assert not other.candidate_features and Denoiser(other).encoder.conv1.in_channels == features


@torch.no_grad()
def test_candidate_features_reach_the_kernels_through_the_trunk():
    model = Denoiser(GUIDED).eval()
    frame = make_frame(H, W, motion=False)
    saturate_gate(model, -40.0)             # the candidate's own share at its floor (4.5e-5): kernels alone
    plain = Denoiser(GUIDED).eval()         # the same network with the trunk's candidate channels cut
    plain.load_state_dict(model.state_dict())
    plain.encoder.conv1.weight[:, -CANDIDATE_CHANNELS:] = 0.0

    def change(net: Denoiser) -> float:   # how far the output moves when only the candidate changes
        first, second = (net.apply(net.prepare([frame], 0, candidate_image(seed)), 1.0) for seed in (1, 2))
        return float((first - second).abs().max())

    # without the features only the gate's floor lets the candidate through; with them the kernels read it
    # (at the networks' exposure, models.exposure, the random weights see this frame 3 stops darker: ~10×)
    assert change(model) > 5 * change(plain)


def test_kernel_clamp_keeps_the_kernels_within_its_band_at_lambda_1_and_lets_go_at_lambda_10():
    result = torch.tensor([0.1, 1.0, 5.0, 0.0]).view(1, 1, 1, 4)
    candidate = torch.tensor([1.0, 1.0, 1.0, 2.0]).view(1, 1, 1, 4)
    at_1 = clamp_around(result, candidate, 0.5, lambda_code(torch.tensor(1.0)).view(1, 1, 1, 1))
    torch.testing.assert_close(at_1.flatten(), torch.tensor([1 / 1.5, 1.0, 1.5, 2 / 1.5]))
    at_10 = clamp_around(result, candidate, 0.5, lambda_code(torch.tensor(10.0)).view(1, 1, 1, 1))
    torch.testing.assert_close(at_10, result)


@torch.no_grad()
def test_kernel_clamp_is_a_post_training_setting_that_moves_the_output_towards_the_candidate():
    model = Denoiser(CANDIDATE).eval()
    frame, candidate = make_frame(H, W), candidate_image()
    saturate_gate(model, -40.0)
    free = model([frame], 0, 1.0, candidate)
    model.config = dataclasses.replace(model.config, kernel_clamp=0.0)
    pinned = model([frame], 0, 1.0, candidate)
    assert (pinned - candidate).abs().mean() < 0.01 * (free - candidate).abs().mean()
    assert model.config.without_post_training_settings().kernel_clamp is None


def test_a_fine_tune_trains_without_the_post_training_settings_and_the_finished_file_carries_them(tmp_path):
    chosen = Denoiser(dataclasses.replace(TINY, temporal=False, oidn_candidate=True, **{
        name: getattr(DenoiserConfig(), name) for name in POST_TRAINING_SETTINGS}))
    save_checkpoint(tmp_path / "shipped.pt", chosen, {"recipe": "test"})
    config = TrainConfig(data=tmp_path, init=tmp_path / "shipped.pt", stage="lambda")
    config.validate()
    trained = _denoiser_to_train(config, "cpu", {})
    assert {name: getattr(trained.config, name) for name in POST_TRAINING_SETTINGS} == NEUTRAL_SETTINGS
    with torch.no_grad():
        trained.gate.hidden.weight.add_(0.25)   # the fine-tune moved the weights
    save_checkpoint(tmp_path / "denoiser.pt", trained, {"recipe": "test (fine-tune)"})
    write_post_training_settings(tmp_path / "denoiser.pt", DenoiserConfig())
    reloaded = load_checkpoint(tmp_path / "denoiser.pt", expected_kind="denoiser")
    assert all(getattr(reloaded.config, name) == getattr(DenoiserConfig(), name) for name in POST_TRAINING_SETTINGS)
    torch.testing.assert_close(reloaded.gate.hidden.weight, trained.gate.hidden.weight)   # the weights as trained
    assert reloaded.checkpoint_extra["recipe"] == "test (fine-tune)"


def test_gate_preparation_is_relu_of_its_layer_on_features_and_statistics_with_a_ones_channel():
    den = Denoiser(dataclasses.replace(TINY, oidn_candidate=True, temporal=False))
    gate, f = den.gate, make_frame()
    features = torch.rand(1, TINY.lambda_width, 12, 16)
    with torch.no_grad():
        hidden = gate.prepare(features, f.color, f.color * 0.8, f.variance)
        stats = gate_statistics(f.color, f.color * 0.8, f.variance)
        expected = F.relu(gate.hidden(torch.cat([features, stats], 1)))
    assert hidden.shape == (1, 1, TINY.gate_width + 1, 12, 16)
    assert torch.allclose(hidden[:, 0, :-1], expected, atol=1e-6)
    assert torch.equal(hidden[:, 0, -1], torch.ones(1, 12, 16))
