"""One "denoise a window and predict its error" path (service/loop/denoise_frame.py), which fetches
the denoiser's OIDN candidate itself: the loop, the EXR denoiser, the dataset builder and the
benchmarks all run it, so nobody else decides whether a denoiser gets its candidate (issue 46)."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch

from models.denoiser import Denoiser, DenoiserConfig
from models.error_predictor import ErrorPredictor, ErrorPredictorConfig
from models.frames import FrameTensors
from models.kernel_disagreement import apply_with_kernels_image, kernel_disagreement
from models.pretrained import Networks, load_networks
from service.loop.denoise_frame import denoise_and_predict, denoise_frame, prepare_frame
from service.loop.denoise_session import DenoiseSession
from service.loop.loop import RenderLoop
from service.loop.oidn import oidn_image
from service.loop.spec import LoopSpec
from service.loop.tensors import frame_tensors, nchw, to_image

REPO = Path(__file__).resolve().parents[1]
# The candidate's only fetcher, the OIDN module itself, and the timing benches that time OIDN alone
# (not as a denoiser's input): OIDN on a frame, `oidn_tensor`, is named nowhere else.
OIDN_TENSOR_USERS = {"service/loop/denoise_frame.py", "service/loop/oidn.py", "bench/models_report.py",
                     "bench/versus_mitsuba_costs.py"}
# Runs its worker in an older tree under test, which may predate the one path.
OLD_TREE_FALLBACK = {"bench/lambda_edit_ab.py"}


def random_frame(size: int, seed: int = 0) -> FrameTensors:
    g = torch.Generator().manual_seed(seed)
    rand = lambda c: torch.rand(1, c, size, size, generator=g)   # noqa: E731
    return FrameTensors(color=rand(3) * 2, variance=rand(3) * 0.1, albedo=rand(3) * 0.8 + 0.1,
                        normal=rand(3) * 2 - 1, depth=rand(1) + 1, motion=None, spp=torch.full((1, 1, size, size), 16.0))


def pyoidn_candidate(frame: FrameTensors) -> torch.Tensor:
    return nchw(oidn_image(to_image(frame.color), to_image(frame.albedo), to_image(frame.normal)))


@torch.no_grad()
def test_denoise_and_predict_fetches_the_candidate_and_hands_the_error_network_the_disagreement():
    denoiser = Denoiser(DenoiserConfig(width=8, spatial_blocks=1, temporal=False, oidn_candidate=True)).eval()
    reader = ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1, disagreement_input=True)).eval()
    plain = ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1, disagreement_input=False)).eval()
    frame = random_frame(16)
    candidate = pyoidn_candidate(frame)
    output, kernels = apply_with_kernels_image(denoiser, denoiser.prepare([frame], 0, candidate))
    result = denoise_and_predict(Networks(denoiser, reader), [frame], 0)
    torch.testing.assert_close(result.image, output)
    torch.testing.assert_close(denoiser.apply(result.cache, 1.0), output)   # the cache serves further λ tails
    torch.testing.assert_close(result.error, reader(frame, output, kernel_disagreement(kernels, candidate)))
    torch.testing.assert_close(denoise_and_predict(Networks(denoiser, plain), [frame], 0).error, plain(frame, output))
    assert denoise_and_predict(Networks(denoiser, plain), [frame], 0, predict=False).error is None
    torch.testing.assert_close(denoise_frame(denoiser, [frame], 0, 4.0), denoiser.apply(result.cache, 4.0))


@torch.no_grad()
def test_a_denoiser_without_oidn_candidate_gets_no_candidate():
    denoiser = Denoiser(DenoiserConfig(width=8, spatial_blocks=1, temporal=False, oidn_candidate=False)).eval()
    frame = random_frame(16)
    prepared = prepare_frame(denoiser, [frame], 0)
    assert prepared.candidate is None
    torch.testing.assert_close(denoiser.apply(prepared.cache), denoiser([frame], 0, 1.0, None))


@pytest.fixture(scope="module")
def shipped() -> Networks:
    return load_networks()


@torch.no_grad()
def test_the_loop_session_denoises_and_predicts_what_denoise_and_predict_gives_on_a_real_render(shipped):
    size = 24
    loop = RenderLoop(LoopSpec(scene="cornell-box", width=size, height=size, max_iterations=1), shipped)
    buffers = list(loop.run())[-1].buffers
    session = DenoiseSession(shipped, frames=1, temporal_radius=0)
    images = session.denoise(buffers, np.ones((size, size), np.float32))
    errors = session.predict_error(images)
    window, centre = shipped.denoiser.filtered_window([frame_tensors(buffers[0])], 0)
    alone = denoise_and_predict(shipped, window, centre)
    assert shipped.denoiser.config.oidn_candidate and shipped.error_predictor.reads_disagreement
    assert torch.equal(images[0], alone.image)
    np.testing.assert_array_equal(errors[0], to_image(alone.error))


def python_files() -> list[Path]:
    return sorted(p for top in ("service", "bench", "models", "scripts", "tests") for p in (REPO / top).rglob("*.py"))


def test_no_module_outside_the_one_denoise_path_fetches_the_candidate():
    this = Path(__file__).resolve()
    offenders = []
    for path in python_files():
        if path == this:
            continue
        name, text = path.relative_to(REPO).as_posix(), path.read_text(encoding="utf-8")
        if re.search(r"\bcandidate_for\b", text) and name not in OLD_TREE_FALLBACK:
            offenders.append(f"{name}: candidate_for")
        if re.search(r"\boidn_tensor\b", text) and name not in OIDN_TENSOR_USERS:
            offenders.append(f"{name}: oidn_tensor")
    assert offenders == []
