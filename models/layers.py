"""The few convolutional building blocks both networks are made of."""
from __future__ import annotations

import functools
import math

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor


def channels_last(x: Tensor) -> Tensor:
    """NHWC memory layout (same NCHW shape): oneDNN's 3×3 convs at these widths run ~2× faster
    on CPU in it (measured 137 vs 274 ms for 3×24→24 at 512², one thread)."""
    return x.contiguous(memory_format=torch.channels_last)


def cat_channels_last(tensors: list[Tensor]) -> Tensor:
    """Channel concatenation straight into NHWC: one pass, whatever the inputs' layouts
    (torch.cat of mixed layouts returns NCHW, and converting afterwards costs a second pass)."""
    return torch.cat([t.permute(0, 2, 3, 1) for t in tensors], dim=3).permute(0, 3, 1, 2)


def is_channels_last(x: Tensor) -> bool:
    return x.dim() == 4 and x.shape[1] > 1 and not x.is_contiguous() and x.is_contiguous(memory_format=torch.channels_last)


def conv3x3(cin: int, cout: int) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 3, padding=1)


class Pointwise(nn.Module):
    """1×1 convolution written as a matmul over (…, C, H·W).

    Why not nn.Conv2d(k=1): on CPU oneDNN's 1×1 path for these narrow widths measured ~5×
    slower than the plain matmul (17 ms vs 2 ms for 16→25 channels at 512²). It also accepts
    extra leading dims, so all frames of a window go through one call.
    """

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.weight = nn.Parameter(torch.empty(cout, cin))
        self.bias = nn.Parameter(torch.empty(cout))
        bound = 1 / math.sqrt(cin)            # nn.Conv2d's default init for a 1×1 kernel
        nn.init.uniform_(self.weight, -bound, bound)
        nn.init.uniform_(self.bias, -bound, bound)

    def forward(self, x: Tensor) -> Tensor:
        if is_channels_last(x):                       # pixels-major already: a plain linear layer
            return F.linear(x.permute(0, 2, 3, 1), self.weight, self.bias).permute(0, 3, 1, 2)
        *lead, c, h, w = x.shape
        flat = x.reshape(-1, c, h * w)
        # one batched GEMM with the bias fused; torch.matmul would fold the batch into one mm
        # and copy the result back to this layout (a full extra pass)
        y = torch.baddbmm(self.bias.view(1, -1, 1), self.weight.expand(flat.shape[0], -1, -1), flat)
        return y.view(*lead, -1, h, w)


class ConvPair(nn.Module):
    """relu(conv(relu(conv(x)))): two 3×3 convolutions (the source encoder; a U-Net stage)."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.conv1, self.conv2 = conv3x3(cin, cout), conv3x3(cout, cout)

    def forward(self, x: Tensor) -> Tensor:
        return F.relu_(self.conv2(F.relu_(self.conv1(x))))


class ResBlock(nn.Module):
    """relu(x + conv(relu(conv(x)))): the residual block of Vogels et al. 2018 (Fig. 3).
    ReLUs run in place: at 512² every avoided full-size allocation saves page faults."""

    def __init__(self, width: int):
        super().__init__()
        self.conv1 = conv3x3(width, width)
        self.conv2 = conv3x3(width, width)

    def forward(self, x: Tensor) -> Tensor:
        return self.conv2(F.relu_(self.conv1(x))).add_(x).relu_()


def res_blocks(width: int, n: int) -> nn.Sequential:
    return nn.Sequential(*[ResBlock(width) for _ in range(n)])


def trunk_in_bfloat16(x: Tensor) -> bool:
    """Whether a network's stack of 3×3 convs runs in bfloat16 (under torch.autocast): at
    inference on a CPU with native bf16 (AVX512-BF16/AMX), where oneDNN runs them faster (one
    512² frame through the shipped denoiser 564 → 508 ms incl. its OIDN call), at 0.5 % relative
    error in the features and no measurable change in the denoised image on the validation
    scenes (docs/models.md).
    Training (autograd) and CPUs without it keep float32: emulated bf16 would be slower."""
    return not torch.is_grad_enabled() and x.device.type == "cpu" and cpu_has_native_bfloat16()


@functools.cache
def cpu_has_native_bfloat16() -> bool:
    try:   # a private oneDNN probe: a torch build without it simply keeps float32
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False
