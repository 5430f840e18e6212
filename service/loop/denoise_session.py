"""The denoised images of a render loop's latest iteration and the pre-λ features behind them,
so a λ edit re-runs only the network's λ tail (the loss-specialisation module, Vogels et al.
2018 §6) instead of the whole denoiser.

The lock is shared with the loop: a λ edit arrives on another thread (the server's λ
mailbox) while the loop renders.
"""
from __future__ import annotations

import threading

import numpy as np
import torch

from models.pretrained import Networks
from service.loop.oidn import candidate_for
from service.loop.tensors import frame_tensors, lam_tensor, temporal_window, to_image
from service.render.framebuffer import FrameBuffer


class DenoiseSession:
    def __init__(self, networks: Networks, frames: int, temporal_radius: int) -> None:
        self.networks = networks
        self.temporal_radius = temporal_radius  # 0: every frame alone (no temporal work)
        self.lock = threading.RLock()
        self._caches: list = [None] * frames  # models.Denoiser.prepare output per frame
        self.full_calls = 0  # full denoiser forward passes (prepare + apply)
        self.tail_calls = 0  # λ-only re-runs from cached features

    @property
    def has_features(self) -> bool:
        return all(cache is not None for cache in self._caches)

    @torch.no_grad()
    def denoise(self, buffers: list[FrameBuffer], lam_map: np.ndarray) -> list[torch.Tensor]:
        """Full passes over every frame's temporal window; keeps the pre-λ features.
        Returns the denoised images as (1, 3, H, W) tensors (the error network's input)."""
        tensors = [frame_tensors(b) for b in buffers]
        lam = lam_tensor(lam_map)
        caches, images = [], []
        for f in range(len(tensors)):
            indices, centre = temporal_window(f, len(tensors), self.temporal_radius)
            # the candidate image (OIDN) is computed once per iteration and cached with the features
            candidate = candidate_for(self.networks.denoiser, tensors[f])
            cache = self.networks.denoiser.prepare([tensors[i] for i in indices], centre, candidate)
            caches.append(cache)
            images.append(self.networks.denoiser.apply(cache, lam))
        with self.lock:
            self._caches = caches
            self.full_calls += len(caches)
        return images

    @torch.no_grad()
    def predict_error(self, buffers: list[FrameBuffer], images: list[torch.Tensor]) -> list[np.ndarray]:
        """Per-pixel predicted SMAPE of each denoised frame, (H, W) each."""
        return [to_image(self.networks.error_predictor(frame_tensors(b), image)) for b, image in zip(buffers, images)]

    @torch.no_grad()
    def relambda(self, lam_map: np.ndarray) -> list[np.ndarray]:
        """Every frame re-denoised with a new λ map from the cached features."""
        lam = lam_tensor(lam_map)
        with self.lock:
            images = [to_image(self.networks.denoiser.apply(cache, lam)) for cache in self._caches]
            self.tail_calls += len(images)
        return images
