"""frame_tensors: the networks' input planes are the buffer's per-pixel layers, whichever way
each plane is filled (straight from the sums, or copied from the buffer's per-pass cache)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from service.loop.tensors import frame_tensors, nchw
from service.render.framebuffer import SPLAT_CHANNELS, FrameBuffer


def sampled_buffer(splat: bool, motion: bool) -> FrameBuffer:
    rng = np.random.default_rng(7)
    height, width = 9, 13
    buffer = FrameBuffer.empty(height, width)
    buffer.spp[:] = rng.integers(0, 5, size=(height, width))
    n = buffer.spp[..., None]
    buffer.radiance_sum[:] = rng.gamma(2.0, 0.3, size=(height, width, 3)) * n
    buffer.radiance_sq_sum[:] = buffer.radiance_sum**2 / np.maximum(n, 1) * rng.uniform(1.0, 2.0, size=(height, width, 3))
    buffer.albedo_sum[:] = rng.random((height, width, 3)) * n
    buffer.normal_sum[:] = rng.normal(size=(height, width, 3)) * n
    buffer.depth_sum[:] = rng.random((height, width)) * buffer.spp
    if motion:
        buffer.motion_sum = rng.normal(size=(height, width, 2)) * n
    if splat:
        buffer.add_splat(rng.random((height, width, SPLAT_CHANNELS)))
    buffer.passes = 1
    return buffer


@pytest.mark.parametrize("splat", [False, True], ids=["box film", "splatting film"])
@pytest.mark.parametrize("motion", [False, True], ids=["static", "moving"])
def test_every_plane_is_the_buffers_layer(splat, motion):
    buffer = sampled_buffer(splat, motion)
    frame = frame_tensors(buffer)
    expected = {"color": buffer.mean, "variance": buffer.variance, "albedo": buffer.albedo,
                "normal": buffer.normal, "depth": buffer.depth, "spp": buffer.spp.astype(np.float32),
                "motion": buffer.motion}
    for name, layer in expected.items():
        tensor = getattr(frame, name)
        if layer is None:
            assert tensor is None
            continue
        assert tensor.dtype == torch.float32 and tensor.is_contiguous(), name
        assert torch.equal(tensor, nchw(layer)), name
    # the tensors are the networks' own: writing one leaves the buffer's cached mean as it was
    mean = buffer.mean.copy()
    frame.color.mul_(2.0)
    np.testing.assert_array_equal(buffer.mean, mean)
