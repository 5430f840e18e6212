"""A painted λ map's tail, folded rectangle by rectangle (models.lambda_regions), against the
whole per-pixel recomputation: the same image to float32 rounding, at the rectangles' edges too
and at the ends of λ's range (and beyond them, where λ is clamped)."""
import pytest
import torch

import models.denoiser
from models.denoiser import Denoiser, DenoiserConfig, LambdaModule
from models.lambda_range import LAMBDA_MAX, LAMBDA_MIN
from models.lambda_regions import constant_regions, region_tiles
from tests.models.conftest import PLAIN_DENOISER, make_frame

H, W = 36, 44


def lambda_sensitive(config: DenoiserConfig) -> Denoiser:
    """A network of that shape whose λ modules do something (a fresh one has ΔW = 0)."""
    den = Denoiser(config).eval()
    with torch.no_grad():
        for module in den.modules():
            if isinstance(module, LambdaModule):
                module.delta.normal_()
    return den


def painted(values: tuple[float, float, float]) -> torch.Tensor:
    """A background and two rectangles with odd edges (they fall inside the coarse levels' 2×2
    pixels, so the pyramid's λ codes get in-between values there), one touching the border."""
    background, first, second = values
    lam = torch.full((1, 1, H, W), background)
    lam[..., 5:18, 7:29] = first
    lam[..., 21:, 31:] = second
    return lam


def per_pixel_recomputation(den: Denoiser, cache, lam: torch.Tensor) -> torch.Tensor:
    """The whole tail as autograd runs it: every level at once, λ's MLP and the 1 + rank
    products at every pixel, clamp and blend as written (no folding, no bands, no regions)."""
    with torch.enable_grad():
        return den.apply(cache, lam).detach()


def relative_difference(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a - b).abs() / b.abs().clamp_min(1e-6)


@pytest.mark.parametrize("values", [(1.0, 6.0, 3.0), (LAMBDA_MIN, LAMBDA_MAX, 5.5), (LAMBDA_MAX, LAMBDA_MIN, LAMBDA_MAX),
                                    (0.2, 40.0, 1.0)])
@pytest.mark.parametrize("shape", ["shipped", "plain"])
def test_a_painted_map_folded_by_rectangles_is_the_per_pixel_image(values, shape, monkeypatch):
    config = DenoiserConfig() if shape == "shipped" else DenoiserConfig(**PLAIN_DENOISER)
    den = lambda_sensitive(config)
    lam = painted(values)
    with torch.no_grad():
        candidate = torch.rand(1, 3, H, W) * 2 if config.oidn_candidate else None
        cache = den.prepare([make_frame(H, W, motion=False)], 0, candidate)
        whole = per_pixel_recomputation(den, cache, lam)
        monkeypatch.setattr("models.denoiser.TILE_PIXELS", 40)   # several tiles per rectangle
        folded = den.apply(cache, lam)
        assert not torch.equal(folded, den.apply(cache, values[0]))   # λ matters here
    difference = relative_difference(folded, whole)
    edges = torch.zeros(H, W, dtype=torch.bool)
    for y0, y1, x0, x1 in ((5, 18, 7, 29), (21, H, 31, W)):
        edges[max(0, y0 - 2):y1 + 2, max(0, x0 - 2):x1 + 2] = True
        edges[y0 + 2:y1 - 2, x0 + 2:x1 - 2] = False
    assert float(difference[..., edges].max()) <= 1e-5   # the edges' pixels alone
    assert float(difference.max()) <= 1e-5


def test_every_kernel_head_of_a_painted_map_folds_to_one_lambda(monkeypatch):
    """The point of the rectangles: no λ module sees a per-pixel code map."""
    den = lambda_sensitive(DenoiserConfig())
    codes = []
    real = LambdaModule.forward
    monkeypatch.setattr(LambdaModule, "forward", lambda self, hidden, code: codes.append(code.shape[-2:]) or real(self, hidden, code))
    with torch.no_grad():
        cache = den.prepare([make_frame(H, W, motion=False)], 0, torch.rand(1, 3, H, W))
        den.apply(cache, painted((1.0, 6.0, 3.0)))
    assert codes and all(shape == (1, 1) for shape in codes)


def test_a_map_of_too_many_values_keeps_the_per_pixel_path_and_its_image():
    den = lambda_sensitive(DenoiserConfig())
    lam = torch.rand(1, 1, H, W) * 9 + 1
    with torch.no_grad():
        cache = den.prepare([make_frame(H, W, motion=False)], 0, torch.rand(1, 3, H, W))
        assert constant_regions(den._lambda_code(cache, lam)) is None
        banded = den.apply(cache, lam)
    assert float(relative_difference(banded, per_pixel_recomputation(den, cache, lam)).max()) <= 1e-5


def test_the_rectangles_cover_every_pixel_once_each_at_one_code():
    code = painted((1.0, 6.0, 3.0))
    regions = constant_regions(code)
    assert len(regions) == 1 + 3 + 1 + 2    # above, the first rectangle's rows, between, the second's
    covered = torch.zeros(H, W, dtype=torch.int64)
    for region in regions:
        covered[region.y0:region.y1, region.x0:region.x1] += 1
        assert bool((code[..., region.y0:region.y1, region.x0:region.x1] == region.code).all())
    assert bool((covered == 1).all())
    tiled = torch.zeros(H, W, dtype=torch.int64)
    for rows, cols, _ in region_tiles(regions, 50):
        assert (rows.stop - rows.start) * (cols.stop - cols.start) <= max(50, cols.stop - cols.start)
        tiled[rows, cols] += 1
    assert bool((tiled == 1).all())


def test_no_rectangles_for_a_map_past_the_limit_or_a_batch_of_different_maps():
    assert constant_regions(torch.rand(1, 1, 16, 16)) is None
    assert constant_regions(painted((1.0, 6.0, 3.0)), max_regions=6) is None
    batch = torch.ones(2, 1, 8, 8)
    batch[1, :, 2:4, 2:4] = 3.0
    assert constant_regions(batch) is None
    assert len(constant_regions(torch.ones(2, 1, 8, 8))) == 1
