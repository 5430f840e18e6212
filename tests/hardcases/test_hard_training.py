"""A few training steps on HDR data (fireflies, exact zeros, radiance up to 1e6) keep the loss,
the gradients and the weights finite, for the denoiser and the error predictor."""
from __future__ import annotations

import math

import torch

from models.denoiser import Denoiser, temporal_config
from models.error_predictor import ErrorPredictor, ErrorPredictorConfig
from models.frames import FrameTensors
from models.training import denoiser_loss, error_predictor_loss, sample_lambda
from tests.models.conftest import PLAIN_ERROR_NETWORK

N, H, W = 2, 12, 16  # a size the 3-level pyramid must pad


def hdr_frame(gen: torch.Generator, motion: bool) -> FrameTensors:
    r = lambda c: torch.rand(N, c, H, W, generator=gen)
    color = r(3) * 4
    color[:, :, :3, :] = 0.0  # pure black rows
    color[:, :, 5, 5] = 1e6  # a firefly
    color[:, :, 8:10, 8:12] = 3e3  # an emitter seen directly
    variance = r(3) * color.square() / 16  # the variance of such a mean is huge too
    return FrameTensors(color=color, variance=variance, albedo=r(3) * (r(1) > 0.2), normal=r(3) * 2 - 1,
                        depth=r(1) * 10, motion=(r(2) - 0.5) * 8 if motion else None,
                        spp=torch.full((N, 1, H, W), 16.0))  # the error network reads sample counts


def finite_step(model: torch.nn.Module, optimiser: torch.optim.Optimizer, loss: torch.Tensor) -> None:
    assert torch.isfinite(loss), loss
    optimiser.zero_grad()
    loss.backward()
    assert math.isfinite(grad_norm(model)) and grad_norm(model) > 0
    optimiser.step()
    assert all(torch.isfinite(p).all() for p in model.parameters())



def grad_norm(model: torch.nn.Module) -> float:
    norms = [p.grad.detach().norm() for p in model.parameters() if p.grad is not None]
    return float(torch.stack(norms).norm()) if norms else 0.0


def test_denoiser_and_error_predictor_train_finitely_on_hdr_data():
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(1)
    denoiser = Denoiser(temporal_config(width=8, spatial_blocks=1, temporal_blocks=1, kernel_size=3,
                                       lambda_width=4, composite_width=4))
    predictor = ErrorPredictor(ErrorPredictorConfig(width=8, blocks=2, **PLAIN_ERROR_NETWORK))
    frames = [hdr_frame(gen, motion=i > 0) for i in range(3)]
    reference = frames[1].color.clamp(max=1e4) * 0.9
    reference[:, :, 5, 5] = 0.0  # the firefly is pure noise: the reference there is dark
    opt_d = torch.optim.Adam(denoiser.parameters(), lr=1e-3)
    opt_e = torch.optim.Adam(predictor.parameters(), lr=1e-3)
    for _ in range(3):
        lam = sample_lambda(N, H, W, gen)
        finite_step(denoiser, opt_d, denoiser_loss(denoiser, frames, 1, reference, lam))
        finite_step(denoiser, opt_d, denoiser_loss(denoiser, [frames[1]], 0, reference, lam))  # single frame
        finite_step(predictor, opt_e, error_predictor_loss(predictor, denoiser, frames[1], reference))
