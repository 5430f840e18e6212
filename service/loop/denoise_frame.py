"""Denoise one frame's window and predict the result's error: the one path the loop, `renderloop
denoise` on an EXR, the dataset builder and the benchmarks all run, so what they measure is what
the service ships.

The denoiser's candidate image (models/candidate.py: OIDN on the centre frame, at the networks'
exposure, service/loop/oidn.py) is fetched here, when the denoiser's config asks for one: callers
hand over the window only. `models/` stays pure torch; the OIDN call lives in the service.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from models.denoiser import Denoiser, DenoiserCache
from models.error_predictor import ErrorMap
from models.frames import FrameTensors
from models.kernel_disagreement import apply_for_error_network
from models.pretrained import Networks
from service.loop.oidn import oidn_tensor


@dataclass(frozen=True)
class PreparedFrame:
    """The λ-independent half of a denoise (Denoiser.prepare) with the candidate it was given."""

    cache: DenoiserCache       # the pre-λ features: a λ edit re-runs only `denoiser.apply(cache, λ)`
    candidate: Tensor | None   # (1, 3, H, W) OIDN on the centre frame, None without `oidn_candidate`
    centre: FrameTensors       # the centre input the denoiser filtered (the error network's input)


@dataclass(frozen=True)
class DenoisedFrame:
    """A denoised frame, its predicted error and the features a λ edit re-runs from."""

    image: Tensor               # (1, 3, H, W) denoised radiance
    error: Tensor | None        # (1, 1, H, W) predicted SMAPE; None when not asked for
    cache: DenoiserCache
    centre: FrameTensors                 # the centre input the denoiser filtered (the error network's input)
    disagreement: Tensor | None = None   # kernels/candidate disagreement, for a network that reads it


def _candidate(denoiser: Denoiser, centre: FrameTensors) -> Tensor | None:
    """The candidate `denoiser.prepare` mixes into its joint softmax, or None if it takes none."""
    return oidn_tensor(centre) if denoiser.config.oidn_candidate else None


def prepare_frame(denoiser: Denoiser, window: list[FrameTensors], centre: int) -> PreparedFrame:
    """`denoiser.prepare` of an already filtered window (Denoiser.filtered_window), with the
    candidate fetched on its centre frame: once per frame and iteration, cached with the features."""
    candidate = _candidate(denoiser, window[centre])
    return PreparedFrame(denoiser.prepare(window, centre, candidate), candidate, window[centre])


@torch.no_grad()
def denoise_frame(denoiser: Denoiser, window: list[FrameTensors], centre: int,
                  lam: float | Tensor = 1.0) -> Tensor:
    """The denoised (1, 3, H, W) centre frame of a filtered window at λ, without error prediction."""
    return denoiser.apply(prepare_frame(denoiser, window, centre).cache, lam)


def apply_prepared(denoiser: Denoiser, prepared: PreparedFrame, lam: float | Tensor,
                   with_disagreement: bool) -> tuple[Tensor, Tensor | None]:
    """The λ tail of a prepared frame, and the kernels/candidate disagreement if asked for."""
    return apply_for_error_network(denoiser, prepared.cache, prepared.candidate, lam, with_disagreement)


def predict_error(error_network: ErrorMap, centre: FrameTensors, image: Tensor,
                  disagreement: Tensor | None) -> Tensor:
    """(1, 1, H, W) predicted SMAPE of `image`, read from the centre input the denoiser filtered."""
    if not error_network.reads_disagreement:
        return error_network(centre, image)
    return error_network(centre, image, disagreement)


@torch.no_grad()
def denoise_and_predict(networks: Networks, window: list[FrameTensors], centre: int,
                        lam: float | Tensor = 1.0, *, predict: bool = True) -> DenoisedFrame:
    """One prepare of the filtered window's centre frame, its λ tail and (`predict`) the error
    network's map of the result, handed the disagreement when it reads it."""
    prepared = prepare_frame(networks.denoiser, window, centre)
    image, disagreement = apply_prepared(networks.denoiser, prepared, lam, networks.error_predictor.reads_disagreement)
    error = predict_error(networks.error_predictor, prepared.centre, image, disagreement) if predict else None
    return DenoisedFrame(image, error, prepared.cache, prepared.centre, disagreement)
