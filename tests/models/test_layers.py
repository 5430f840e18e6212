"""The building blocks' fast inference paths compute what their plain definitions say."""
from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from models.layers import (ConvPair, Conv3x3, Pointwise, ResBlock, cat_channels_last, channels_last,
                           cpu_has_native_bfloat16, fused_conv_available)


def _image(c: int = 6, h: int = 9, w: int = 11, seed: int = 0) -> torch.Tensor:
    return channels_last(torch.randn(2, c, h, w, generator=torch.Generator().manual_seed(seed)))


@pytest.mark.skipif(not fused_conv_available(), reason="this torch build has no oneDNN fused convolution")
def test_fused_conv_relu_and_conv_add_relu_equal_the_eager_layers_in_float32():
    conv, x, residual = Conv3x3(6, 6), _image(), _image(seed=1)
    with torch.inference_mode():
        assert torch.allclose(conv.relu(x), F.relu(conv(x)), atol=1e-5)
        assert torch.allclose(conv.add_relu(x, residual), F.relu(conv(x) + residual), atol=1e-5)


@pytest.mark.skipif(not (fused_conv_available() and cpu_has_native_bfloat16()),
                    reason="no fused bfloat16 convolution here (torch build or CPU): both sides would be eager")
def test_fused_conv_under_autocast_runs_in_bfloat16_like_the_eager_conv():
    conv, x = Conv3x3(6, 6), _image()
    with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16):
        fused, eager = conv.relu(x), F.relu(conv(x))
    assert fused.dtype == eager.dtype == torch.bfloat16
    assert torch.allclose(fused.float(), eager.float(), atol=0.05, rtol=0.02)


def test_fused_conv_weights_follow_a_load_state_dict():
    conv, x = Conv3x3(6, 6), _image()
    with torch.inference_mode():
        before = conv.relu(x)
    other = Conv3x3(6, 6)
    conv.load_state_dict(other.state_dict())
    with torch.inference_mode():
        after = conv.relu(x)
        assert not torch.allclose(before, after)
        assert torch.allclose(after, F.relu(other(x)), atol=1e-5)


def test_blocks_train_through_the_eager_path_with_gradients():
    block, pair, x = ResBlock(6), ConvPair(6, 6), _image().requires_grad_()
    pair(block(x)).sum().backward()
    assert x.grad is not None and block.conv1.weight.grad is not None and pair.conv1.weight.grad is not None


@pytest.mark.parametrize("layout", ["channels_last", "nchw"])
@pytest.mark.parametrize("grad", [False, True])
def test_pointwise_relu_into_writes_relu_of_the_layer_into_the_planes(layout, grad):
    layer, x = Pointwise(6, 4), _image()
    if layout == "nchw":
        x = x.contiguous()
    planes = torch.empty(2, 3, 5, 9, 11)                   # (N, F, C + 1, H, W) like the λ tail's
    with torch.set_grad_enabled(grad):
        layer.relu_into(x, planes[:, 1, :4])
        expected = F.relu(layer(x))
    assert torch.allclose(planes[:, 1, :4], expected, atol=1e-6)


def test_cat_channels_last_converts_dtype_in_the_same_pass():
    parts = [torch.rand(1, 3, 5, 7), channels_last(torch.rand(1, 2, 5, 7)), torch.rand(1, 1, 5, 7)]
    plain = cat_channels_last(parts)
    in_bf16 = cat_channels_last(parts, torch.bfloat16)
    assert plain.is_contiguous(memory_format=torch.channels_last) and in_bf16.is_contiguous(memory_format=torch.channels_last)
    assert in_bf16.dtype == torch.bfloat16
    assert torch.equal(in_bf16, torch.cat(parts, 1).to(torch.bfloat16))
    assert torch.equal(plain, torch.cat(parts, 1))


def test_a_conv_built_under_inference_mode_runs_and_equals_the_eager_layer():
    """Parameters created under inference_mode are inference tensors without a version counter
    (a network built inside a timed or served inference block)."""
    with torch.inference_mode():
        conv, x, residual = Conv3x3(6, 6), _image(), _image(seed=1)
        assert torch.allclose(conv.relu(x), F.relu(conv(x)), atol=1e-5)
        assert torch.allclose(conv.add_relu(x, residual), F.relu(conv(x) + residual), atol=1e-5)
