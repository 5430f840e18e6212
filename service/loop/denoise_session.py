"""The denoised images of a render loop's latest iteration and the pre-λ features behind them,
so a λ edit re-runs only the network's λ tail (the loss-specialisation module, Vogels et al.
2018 §6) instead of the whole denoiser.

The lock is shared with the loop: a λ edit arrives on another thread (the server's λ
mailbox) while the loop renders.
"""
from __future__ import annotations

import threading
import time

import numpy as np
import torch

from models.frames import FrameTensors
from models.pretrained import Networks
from service.loop.denoise_frame import DenoisedFrame, denoise_and_predict, predict_error
from service.loop.tensors import frame_tensors, lam_tensor, temporal_window, to_image
from service.render.framebuffer import FrameBuffer


class DenoiseSession:
    def __init__(self, networks: Networks, frames: int, temporal_radius: int, owned: range | None = None) -> None:
        """`owned`: the frames this session denoises (default all); their temporal windows may
        reach frames owned elsewhere, whose buffers the caller keeps current."""
        self.networks = networks
        self.temporal_radius = temporal_radius  # 0: every frame alone (no temporal work)
        self.owned = owned if owned is not None else range(frames)
        self.lock = threading.RLock()
        # per owned frame, the last full pass: its pre-λ features (models.Denoiser.prepare), the
        # center input it filtered and the kernels/candidate disagreement an error network may read
        self._frames: dict[int, DenoisedFrame] = {}
        self.full_calls = 0  # full denoiser forward passes (prepare + apply)
        self.tail_calls = 0  # λ-only re-runs from cached features
        self.tail_seconds = 0.0  # their wall time, images out included (a λ edit's Server-Timing)
        # Frames go where the networks are: CPU, or CUDA on a GPU worker (service.jobs.ray_actor).
        self.device = next(networks.denoiser.parameters()).device

    def _tensors(self, buffer: FrameBuffer) -> FrameTensors:
        return frame_tensors(buffer, self.device)  # one host → device copy of the whole block

    @property
    def inputs(self) -> dict[int, FrameTensors]:
        """Per owned frame, the center input the last `denoise` filtered (Denoiser.filtered_window)."""
        return {f: frame.centre for f, frame in self._frames.items()}

    @property
    def has_features(self) -> bool:
        return all(f in self._frames for f in self.owned)

    @torch.no_grad()
    def denoise(self, buffers: list[FrameBuffer], lam_map: np.ndarray) -> dict[int, torch.Tensor]:
        """Full passes over every owned frame's temporal window; keeps the pre-λ features.
        Returns the denoised images as (1, 3, H, W) tensors (the error network's input)."""
        needed = sorted({i for f in self.owned for i in temporal_window(f, len(buffers), self.temporal_radius)[0]})
        tensors = {i: self._tensors(buffers[i]) for i in needed}
        lam = lam_tensor(lam_map)
        frames: dict[int, DenoisedFrame] = {}
        denoiser = self.networks.denoiser
        for f in self.owned:
            indices, centre = temporal_window(f, len(buffers), self.temporal_radius)
            # what the network filters (a single-frame one: the window's samples pooled); the
            # candidate image (OIDN) is computed on its center once per iteration, cached with the features
            window, centre = denoiser.filtered_window([tensors[i] for i in indices], centre)
            frames[f] = denoise_and_predict(self.networks, window, centre, lam, predict=False)
        with self.lock:
            self._frames = frames
            self.full_calls += len(frames)
        images = {f: frame.image for f, frame in frames.items()}
        return images

    @torch.no_grad()
    def predict_error(self, images: dict[int, torch.Tensor]) -> dict[int, np.ndarray]:
        """Per-pixel predicted SMAPE of each denoised (owned) frame, (H, W) each, read from the
        inputs the denoiser filtered (those of the last `denoise`, which made `images`)."""
        network = self.networks.error_predictor
        return {f: to_image(predict_error(network, self._frames[f].centre, image, self._frames[f].disagreement))
                for f, image in images.items()}

    @torch.no_grad()
    def relambda(self, lam_map: np.ndarray) -> dict[int, np.ndarray]:
        """Every owned frame re-denoised with a new λ map from the cached features."""
        lam = lam_tensor(lam_map)
        with self.lock:
            started = time.perf_counter()
            images = {f: to_image(self.networks.denoiser.apply(frame.cache, lam)) for f, frame in self._frames.items()}
            self.tail_calls += len(images)
            self.tail_seconds += time.perf_counter() - started
        return images
