"""Test-time views of the error map (models/error_tta.py): each view's prediction comes back to
the image's place, one view is the network itself, screen-space motion turns with the image."""
import pytest
import torch
from torch import Tensor

from models.error_predictor import ErrorPredictor, ErrorPredictorConfig
from models.error_tta import D4, ErrorTTA, combine_views, view_frame
from models.frames import FrameTensors
from models.pretrained import load_networks
from tests.models.conftest import PLAIN_ERROR_NETWORK, make_frame


class PixelwiseMap:
    """An ErrorMap that is a function of each pixel's own inputs only, hence equivariant to every
    flip and transpose: a correct TTA returns exactly its plain map. It records what it was shown."""

    change_scale = None
    reads_disagreement = True

    def __init__(self) -> None:
        self.shapes: list[tuple[int, ...]] = []

    def __call__(self, frame: FrameTensors, denoised: Tensor, disagreement: Tensor | None = None) -> Tensor:
        self.shapes.append(tuple(denoised.shape))
        return frame.color[:, :1] + 2 * denoised[:, 1:2] + 3 * disagreement + frame.spp


def asymmetric_inputs(h: int = 5, w: int = 7) -> tuple[FrameTensors, Tensor, Tensor]:
    """Inputs whose planes are ramps in x and y: no flip or transpose maps them onto themselves."""
    y, x = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    ramp = (x + 10 * y).view(1, 1, h, w)
    frame = make_frame(h, w, spp=16.0)
    frame.color[:, :1] = ramp
    frame.spp = ramp.square()
    return frame, (ramp * 0.5).expand(1, 3, h, w).clone(), ramp / 100


@pytest.mark.parametrize("views", [2, 4, 8])
def test_each_views_map_comes_back_to_its_pixels(views):
    frame, denoised, disagreement = asymmetric_inputs()
    plain = PixelwiseMap()
    expected = plain(frame, denoised, disagreement)
    wrapped = ErrorTTA(PixelwiseMap(), views)
    assert torch.allclose(wrapped(frame, denoised, disagreement), expected, rtol=1e-6, atol=1e-6)


def test_eight_views_see_the_image_transposed_and_four_do_not():
    frame, denoised, disagreement = asymmetric_inputs(5, 7)
    four, eight = ErrorTTA(PixelwiseMap(), 4), ErrorTTA(PixelwiseMap(), 8)
    four(frame, denoised, disagreement), eight(frame, denoised, disagreement)
    assert set(four.network.shapes) == {(1, 3, 5, 7)}
    assert set(eight.network.shapes) == {(1, 3, 5, 7), (1, 3, 7, 5)}


def test_every_view_is_undone_by_its_inverse_and_the_eight_are_distinct():
    x = torch.arange(2 * 3 * 4 * 5, dtype=torch.float32).view(2, 3, 4, 5)
    seen = [view.forward(x) for view in D4]
    for view, y in zip(D4, seen):
        assert torch.equal(view.inverse(y), x)
    flat = {tuple(y.flatten().tolist()) + (tuple(y.shape),) for y in seen}
    assert len(flat) == 8


def _pixel_map(view, h: int, w: int):
    """The view as a map of pixel coordinates (x, y) of an h×w image to those of the viewed image."""
    def apply(x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
        if view.transpose:
            x, y = y, x
        vw, vh = (h, w) if view.transpose else (w, h)
        return (vw - 1 - x if view.flip_w else x), (vh - 1 - y if view.flip_h else y)
    return apply


@pytest.mark.parametrize("view", D4, ids=lambda v: f"t{int(v.transpose)}h{int(v.flip_h)}w{int(v.flip_w)}")
def test_motion_points_to_the_same_point_of_the_previous_frame_in_every_view(view):
    """Pixel p of frame t was at p + m in frame t − 1 (docs/design.md); in a view V the same point
    sits at V(p) and was at V(p + m), so the viewed motion at V(p) must be V(p + m) − V(p)."""
    h, w = 4, 6
    frame = make_frame(h, w, motion=True, seed=3)
    viewed = view_frame(frame, view).motion
    to_view = _pixel_map(view, h, w)
    y, x = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    mx, my = frame.motion[0, 0], frame.motion[0, 1]
    vx, vy = to_view(x, y)
    px, py = to_view(x + mx, y + my)
    at = (vy.long(), vx.long())
    assert torch.allclose(viewed[0, 0][at], px - vx, atol=1e-6)
    assert torch.allclose(viewed[0, 1][at], py - vy, atol=1e-6)


def test_one_view_is_the_plain_network_bit_for_bit():
    torch.manual_seed(0)
    network = ErrorPredictor(ErrorPredictorConfig(width=8, **PLAIN_ERROR_NETWORK)).eval()
    frame, denoised = make_frame(12, 16, spp=16.0), torch.rand(1, 3, 12, 16)
    with torch.no_grad():
        assert torch.equal(ErrorTTA(network, 1)(frame, denoised), network(frame, denoised))


def test_views_of_a_real_network_differ_and_their_mean_is_the_map():
    """The trained kernels are not symmetric (else the views would add nothing), and the map is the
    plain mean of the un-flipped views."""
    torch.manual_seed(0)
    network = ErrorPredictor(ErrorPredictorConfig(width=8, **PLAIN_ERROR_NETWORK)).eval()
    frame, denoised = make_frame(12, 12, spp=16.0), torch.rand(1, 3, 12, 12)
    with torch.no_grad():
        maps = [view.inverse(network(view_frame(frame, view), view.forward(denoised))) for view in D4]
        averaged = ErrorTTA(network, 8)(frame, denoised)
    assert not torch.allclose(maps[0], maps[1])
    assert torch.allclose(averaged, torch.stack(maps).mean(0), rtol=1e-5, atol=1e-7)


def test_the_geometric_mean_lies_below_the_mean_of_unequal_views():
    a, b = torch.full((1, 1, 2, 2), 1.0), torch.full((1, 1, 2, 2), 4.0)
    assert torch.allclose(combine_views([a, b], "geometric"), torch.full_like(a, 2.0))
    assert torch.allclose(combine_views([a, b], "mean"), torch.full_like(a, 2.5))


@pytest.mark.parametrize("views, combine", [(3, "mean"), (4, "median")])
def test_a_view_count_or_combine_rule_it_does_not_have_is_refused(views, combine):
    with pytest.raises(ValueError):
        ErrorTTA(PixelwiseMap(), views, combine)


def test_load_networks_wraps_the_shipped_error_network_with_its_surface():
    plain, wrapped = load_networks(error_views=1), load_networks(error_views=4)
    assert isinstance(plain.error_predictor, ErrorPredictor)
    assert isinstance(wrapped.error_predictor, ErrorTTA) and len(wrapped.error_predictor.views) == 4
    assert wrapped.error_predictor.change_scale == plain.error_predictor.change_scale
    assert wrapped.error_predictor.reads_disagreement == plain.error_predictor.reads_disagreement
