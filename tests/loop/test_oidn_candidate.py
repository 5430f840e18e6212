"""The loop with a denoiser that mixes OIDN's image into its joint softmax (service/loop/oidn.py)."""
import numpy as np
import pytest
import torch

from models.denoiser import Denoiser, temporal_config
from models.error_predictor import ErrorPredictor, ErrorPredictorConfig
from models.pretrained import Networks
from tests.models.conftest import PLAIN_ERROR_NETWORK
from service.loop.loop import RenderLoop
from service.loop.spec import LoopSpec

SIZE = 16


@pytest.fixture
def candidate_networks() -> Networks:
    torch.manual_seed(0)
    denoiser = Denoiser(temporal_config(width=8, spatial_blocks=1, oidn_candidate=True)).eval()
    with torch.no_grad():   # fresh λ modules ignore λ; perturb them so an edit visibly matters
        for delta in (denoiser.specialise.delta, denoiser.gate.specialise.delta):
            delta.add_(torch.randn_like(delta) * 0.5)
    return Networks(denoiser, ErrorPredictor(ErrorPredictorConfig(width=8, **PLAIN_ERROR_NETWORK)).eval())


def test_oidn_runs_once_per_frame_per_iteration_and_not_on_a_lambda_edit(candidate_networks, monkeypatch):
    import service.loop.denoise_frame as denoise_frame_module

    calls = []
    real = denoise_frame_module._candidate
    monkeypatch.setattr(denoise_frame_module, "_candidate", lambda d, f: calls.append(1) or real(d, f))
    loop = RenderLoop(LoopSpec(scene="cornell-box", width=SIZE, height=SIZE, max_iterations=2), candidate_networks)
    list(loop.run())
    before = loop.denoised_only()[0].copy()  # the denoiser's image (the final one may fall back to the raw one)
    assert len(calls) == 2 and np.isfinite(before).all()
    lam = np.full((SIZE, SIZE), 10.0, np.float32)
    loop.set_lambda(lam)
    assert len(calls) == 2 and loop.session.tail_calls == 1
    assert not np.allclose(before, loop.denoised_only()[0])


def test_the_oidn_candidate_is_what_pyoidn_returns_on_the_frame(candidate_networks):
    from service.loop.denoise_frame import prepare_frame
    from service.loop.oidn import oidn_image
    from service.loop.tensors import frame_tensors, to_image

    loop = RenderLoop(LoopSpec(scene="cornell-box", width=SIZE, height=SIZE, max_iterations=1), candidate_networks)
    buffer = list(loop.run())[-1].buffers[0]
    candidate = prepare_frame(candidate_networks.denoiser, [frame_tensors(buffer)], 0).candidate
    np.testing.assert_allclose(to_image(candidate), oidn_image(buffer.mean, buffer.albedo, buffer.normal), atol=1e-6)


def test_an_error_network_reading_the_disagreement_runs_in_the_loop_and_the_exr_denoiser(candidate_networks, tmp_path):
    from service.exr import read_exr, result_frame, write_exr
    from service.exr_denoise import denoise_exr

    reader = ErrorPredictor(ErrorPredictorConfig(width=8, output_scale=1.0, change_scale=None)).eval()
    networks = Networks(candidate_networks.denoiser, reader)
    loop = RenderLoop(LoopSpec(scene="cornell-box", width=SIZE, height=SIZE, max_iterations=2), networks)
    last = list(loop.run())[-1]
    error = last.error[0]
    assert error.shape == (SIZE, SIZE) and np.isfinite(error).all() and (error >= 0).all()
    assert loop.session._frames[0].disagreement.shape == (1, 1, SIZE, SIZE)
    path = write_exr(tmp_path / "frame.exr", result_frame(last.buffers[0], last.buffers[0].mean, error=None, lam=None,
                                                          header={}))
    written = denoise_exr(path, tmp_path / "out.exr", networks)
    assert written.error is not None and np.isfinite(read_exr(tmp_path / "out.exr").error).all()
