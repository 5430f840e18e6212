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


def cat_channels_last(tensors: list[Tensor], dtype: torch.dtype | None = None) -> Tensor:
    """Channel concatenation straight into NHWC: one pass, whatever the inputs' layouts
    (torch.cat of mixed layouts returns NCHW, and converting afterwards costs a second pass).
    dtype: the result's, converted in the same pass (a bfloat16 trunk's input)."""
    if dtype is None or all(t.dtype == dtype for t in tensors):
        return torch.cat([t.permute(0, 2, 3, 1) for t in tensors], dim=3).permute(0, 3, 1, 2)
    n, _, h, w = tensors[0].shape
    out = tensors[0].new_empty(n, h, w, sum(t.shape[1] for t in tensors), dtype=dtype)
    start = 0
    for t in tensors:
        out[..., start:start + t.shape[1]].copy_(t.permute(0, 2, 3, 1))
        start += t.shape[1]
    return out.permute(0, 3, 1, 2)


def is_channels_last(x: Tensor) -> bool:
    return x.dim() == 4 and x.shape[1] > 1 and not x.is_contiguous() and x.is_contiguous(memory_format=torch.channels_last)


class Conv3x3(nn.Conv2d):
    """A 3×3 convolution (padding 1) that, at inference on the CPU, runs its ReLU — and a
    residual block's skip addition — inside oneDNN's convolution (the post-ops `torch.compile`
    uses, `mkldnn._convolution_pointwise`) instead of as separate passes over the output. At
    512², 16 channels, one thread (scratch timings, median of 30): float32 on an AVX2-only EPYC,
    conv + ReLU 14.7 ms against 15.7 eagerly, conv + add + ReLU 13.9 against 16.3; bfloat16 on an
    AVX512-BF16 Xeon, 2.1 against 3.5 and 2.3 against 5.0. Training, other devices and a torch
    build without the op take the eager path; the parameters and state-dict keys are nn.Conv2d's."""

    def __init__(self, cin: int, cout: int):
        super().__init__(cin, cout, 3, padding=1)

    def relu(self, x: Tensor) -> Tensor:
        """relu(conv(x))."""
        dtype = _fused_dtype(x)
        if dtype is None:
            return F.relu_(self(x))
        weight, bias = self._weights_in(dtype)
        return torch.ops.mkldnn._convolution_pointwise(
            x.to(dtype), weight, bias, [1, 1], [1, 1], [1, 1], 1, "relu", [], "")

    def add_relu(self, x: Tensor, residual: Tensor) -> Tensor:
        """relu(conv(x) + residual)."""
        dtype = _fused_dtype(x)
        if dtype is None or residual.dtype != dtype or not is_channels_last(residual):
            return self(x).add_(residual).relu_()
        weight, bias = self._weights_in(dtype)
        return torch.ops.mkldnn._convolution_pointwise(
            x.to(dtype), residual, weight, bias, [1, 1], [1, 1], [1, 1], 1, "add", 1.0, "relu", [], "")

    def _weights_in(self, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
        """The parameters as the fused op takes them, cast afresh on every call: a few
        microseconds for 16×16×3×3 weights, and nothing to go stale (a cache keyed on the
        parameters' versions broke on inference tensors, which have none)."""
        weight = self.weight.detach().to(dtype).contiguous(memory_format=torch.channels_last)
        return weight, self.bias.detach().to(dtype)


def _fused_dtype(x: Tensor) -> torch.dtype | None:
    """The dtype a fused convolution of `x` runs in (autocast's, as an nn.Conv2d would), or
    None where the eager path must run: autograd on, not a channels-last CPU image, no op."""
    if torch.is_grad_enabled() or x.device.type != "cpu" or not is_channels_last(x) or not fused_conv_available():
        return None
    dtype = torch.get_autocast_dtype("cpu") if torch.is_autocast_enabled("cpu") else x.dtype
    # oneDNN refuses a bfloat16 convolution on a CPU without native bf16 (no AVX512-BF16 or
    # AVX-NE-CONVERT): the eager layer emulates it there
    return None if dtype == torch.bfloat16 and not cpu_has_native_bfloat16() else dtype


@functools.cache
def fused_conv_available() -> bool:
    """Whether this torch build has oneDNN's fused convolution (the op behind Conv3x3's fast path)."""
    try:
        return torch.backends.mkldnn.is_available() and hasattr(torch.ops.mkldnn, "_convolution_pointwise")
    except (AttributeError, RuntimeError):
        return False


def conv3x3(cin: int, cout: int) -> Conv3x3:
    return Conv3x3(cin, cout)


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

    def relu_into(self, x: Tensor, out: Tensor) -> None:
        """out[...] = relu(self(x)) for x (N,C,H,W), out an (N,cout,H,W) view with contiguous
        planes. Without autograd a channels-last x is read transposed by the GEMM, which writes
        straight into `out`: no NHWC result to transpose into the planes afterwards."""
        n, c, h, w = x.shape
        if torch.is_grad_enabled() or not is_channels_last(x):
            out.copy_(F.relu_(self(x)))
            return
        planes = out.view(n, -1, h * w)
        pixels = x.permute(0, 2, 3, 1).reshape(n, h * w, c).transpose(1, 2)
        for i in range(n):   # a 2-D GEMM takes the transposed operand as it is; a batched one copied it
            torch.addmm(self.bias.view(-1, 1), self.weight, pixels[i], out=planes[i])
        planes.relu_()


class ConvPair(nn.Module):
    """relu(conv(relu(conv(x)))): two 3×3 convolutions (the source encoder)."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.conv1, self.conv2 = conv3x3(cin, cout), conv3x3(cout, cout)

    def forward(self, x: Tensor) -> Tensor:
        return self.conv2.relu(self.conv1.relu(x))


class ResBlock(nn.Module):
    """relu(x + conv(relu(conv(x)))): the residual block of Vogels et al. 2018 (Fig. 3).
    ReLUs run in place: at 512² every avoided full-size allocation saves page faults."""

    def __init__(self, width: int):
        super().__init__()
        self.conv1 = conv3x3(width, width)
        self.conv2 = conv3x3(width, width)

    def forward(self, x: Tensor) -> Tensor:
        return self.conv2.add_relu(self.conv1.relu(x), x)


def res_blocks(width: int, n: int) -> nn.Sequential:
    return nn.Sequential(*[ResBlock(width) for _ in range(n)])


def trunk_in_bfloat16(x: Tensor) -> bool:
    """Whether a network's stack of 3×3 convs runs in bfloat16 (under torch.autocast): at
    inference on a CPU with native bf16 (AVX512-BF16/AMX), where oneDNN runs them faster (one
    512² frame through the shipped denoiser 564 → 508 ms incl. its OIDN call), at 0.5 % relative
    error in the features and no measurable change in the denoised image on the validation
    scenes (docs/decisions.md, "Speed on the CPU").
    Training (autograd) and CPUs without it keep float32: emulated bf16 would be slower."""
    return not torch.is_grad_enabled() and x.device.type == "cpu" and cpu_has_native_bfloat16()


@functools.cache
def cpu_has_native_bfloat16() -> bool:
    try:   # a private oneDNN probe: a torch build without it simply keeps float32
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False
