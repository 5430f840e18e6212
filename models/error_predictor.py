"""Error predictor (Vogels et al. 2018 §7): per-pixel SMAPE of the denoised image, estimated
without a reference, so the adaptive sampler can send samples where the error is.

    [encoder features of the noisy frame, log demodulated denoised, log2 samples per pixel
     (, √ the kernels/candidate disagreement)] → conv3x3 → 6 residual blocks → conv3x3
     → softplus (errors are ≥ 0)

The sample-count channel tells the network how far each pixel has converged under the loop's
non-uniform counts; relative variance is already among the encoder features. The disagreement
channel (`disagreement_input`) is where the denoiser's kernels' image and its OIDN candidate
differ (models/kernel_disagreement.py); a denoiser without a candidate (the temporal KPCN) has
none to give. The defaults below are the shipped network's configuration
(tests/models/test_shipped_config.py).

Trained with L1 against models.losses.smape_map(denoised, reference).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Protocol

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from models.exposure import Exposure
from models.features import (HDR_MAX, PATH_FEATURES, demodulate, log_transform, sample_count_feature, sanitize,
                             sanitize_frame)
from models.frames import FrameTensors
from models.kernel_disagreement import disagreement_feature
from models.layers import cat_channels_last, conv3x3, res_blocks, trunk_in_bfloat16

SAMPLE_COUNT_CHANNELS = 1   # log2(1 + spp) per pixel (models.features.sample_count_feature)


@dataclass
class ErrorPredictorConfig:
    width: int = 16               # narrow: it runs every sampling iteration, and only has to rank pixels
    blocks: int = 6               # paper: six residual blocks
    disagreement_input: bool = True   # + √D, D = the kernels' image against the candidate's (needs a candidate)
    # Calibration: the prediction times this. Procedural training scenes are easier for the
    # denoiser than hand-written ones, so the mean prediction runs low on them by a roughly
    # constant factor; fitted on the validation scenes (`renderloop bench --calibration --suite
    # val --fit-scale DIR`). Allocation ∝ error is unchanged by it; --target-error is not.
    output_scale: float = 0.9678349869049819
    # Calibration from the second iteration on (service.loop.change_calibration): the loop rescales
    # the map so its mean is √(the network's mean × change_scale × how much the denoised image
    # moved since the previous iteration). None: the network's mean alone. Fitted with
    # output_scale; the network never reads it.
    change_scale: float | None = 1.505622165667582


class ErrorPredictor(nn.Module):
    kind: ClassVar[str] = "error_predictor"

    def __init__(self, config: ErrorPredictorConfig | None = None):
        super().__init__()
        self.config = cfg = config or ErrorPredictorConfig()
        self.features = PATH_FEATURES
        self.head = conv3x3(self.input_channels, cfg.width)
        self.blocks = res_blocks(cfg.width, cfg.blocks)
        self.out = conv3x3(cfg.width, 1)

    @property
    def input_channels(self) -> int:
        cfg = self.config
        return self.features.channels + 3 + SAMPLE_COUNT_CHANNELS + int(cfg.disagreement_input)

    def forward(self, frame: FrameTensors, denoised: Tensor, disagreement: Tensor | None = None) -> Tensor:
        """frame: the noisy input, with its per-pixel sample counts (`spp`); denoised (N,3,H,W)
        → (N,1,H,W) predicted SMAPE ≥ 0.
        disagreement (N,1,H,W): models.kernel_disagreement's D, read only by a network with
        `disagreement_input` (and then required)."""
        # Both images in the noisy frame's exposure (models.exposure), like the denoiser's inputs:
        # SMAPE is relative, so the prediction does not change with the scene's units.
        exposure = Exposure.of(frame.color)
        f, _ = sanitize_frame(exposure.forward_frame(frame))
        d, _ = sanitize(exposure.forward(denoised.float()), 0.0, HDR_MAX)
        if f.spp is None:
            raise ValueError("the error network reads the per-pixel sample count: the frame has no spp map")
        inputs = [*self.features.planes(f), log_transform(demodulate(d, f.albedo)), sample_count_feature(f.spp)]
        if self.config.disagreement_input:
            if disagreement is None:
                raise ValueError("this error network reads the kernels/candidate disagreement: none was given")
            inputs.append(disagreement_feature(sanitize(disagreement.float(), 0.0, 1.0)[0]))
        x = cat_channels_last(inputs)
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=trunk_in_bfloat16(x)):
            raw = self.out(self.blocks(self.head.relu(x))).float()
        error = F.softplus(raw)
        return (error * self.config.output_scale).contiguous()

    @property
    def change_scale(self) -> float | None:
        """ErrorMap: the change calibration's factor (the config's)."""
        return self.config.change_scale

    @property
    def reads_disagreement(self) -> bool:
        """ErrorMap: the kernels/candidate disagreement is one of its inputs."""
        return self.config.disagreement_input


class ErrorMap(Protocol):
    """What the loop asks of an error map: ErrorPredictor, or anything with the same surface (a
    benchmark's allocator without a network, a test's planted map), which then says for itself
    what it reads and how it is calibrated."""

    @property
    def change_scale(self) -> float | None:
        """Calibration by the image's change from the second iteration on
        (service.loop.change_calibration); None: the map's own mean."""

    @property
    def reads_disagreement(self) -> bool:
        """Whether the loop must hand it the kernels/candidate disagreement."""

    def __call__(self, frame: FrameTensors, denoised: Tensor, disagreement: Tensor | None = None) -> Tensor:
        """(N,1,H,W) predicted SMAPE of `denoised` ≥ 0."""
