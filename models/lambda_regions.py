"""A painted λ map as rectangles of one λ each, so the λ tail folds its kernel head everywhere.

The λ module's kernel head is W(λ) = W₀ + Σᵣ sᵣ(λ)·ΔWᵣ (models.denoiser.LambdaModule): over a
set of pixels that share one λ it folds into ONE matrix product, where a per-pixel map costs
1 + rank products plus the λ MLP at every pixel (and the candidate gate's the same again).
What users paint (the page's rectangles, a global value, a brush of a few values) is piecewise
constant, so a level's code map splits into a few rectangles of one value each: consecutive
rows that are identical form a row group, and each row group splits where its row changes value.
Every rectangle then takes the folded path, tiled into pieces of about `tile_pixels` pixels so a
tile's F·k² weight planes stay in cache (models.denoiser.TILE_PIXELS). A map with more
rectangles than `max_regions` (an uploaded photograph-like map) returns None: the caller keeps
the per-pixel path, where the per-pixel products are cheaper than hundreds of tiny ones.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import torch
from torch import Tensor

# Above this many rectangles per level the per-pixel path is cheaper than the folded tiles'
# fixed costs (each tile runs ~60 small ops: the k² taps, the λ MLP on one value, the gate).
MAX_REGIONS = 64


@dataclass(frozen=True)
class Region:
    """Rows y0…y1−1 and columns x0…x1−1 of a level, all at one λ code (shape (N,1,1,1))."""

    y0: int
    y1: int
    x0: int
    x1: int
    code: Tensor


def _row_group_starts(plane: Tensor) -> list[int]:
    """First row of each run of identical rows of a (h, w) plane."""
    same_as_above = (plane[1:] == plane[:-1]).all(dim=1)
    return [0] + (torch.nonzero(~same_as_above).flatten() + 1).tolist()


def _column_run_starts(row: Tensor) -> list[int]:
    """First column of each run of one value along a (w,) row."""
    return [0] + (torch.nonzero(row[1:] != row[:-1]).flatten() + 1).tolist()


def constant_regions(code: Tensor, max_regions: int = MAX_REGIONS) -> list[Region] | None:
    """A (N,1,h,w) λ code map as rectangles of one code each, covering every pixel once (row
    groups top to bottom, columns left to right); None when the map needs more than
    `max_regions`, or when the batch's maps differ (each image would need its own rectangles)."""
    n, _, h, w = code.shape
    if n > 1 and not bool((code == code[:1]).all()):
        return None
    plane = code[0, 0]
    row_starts = _row_group_starts(plane)
    if len(row_starts) > max_regions:
        return None
    regions: list[Region] = []
    for y0, y1 in zip(row_starts, row_starts[1:] + [h]):
        column_starts = _column_run_starts(plane[y0])
        if len(regions) + len(column_starts) > max_regions:
            return None
        for x0, x1 in zip(column_starts, column_starts[1:] + [w]):
            regions.append(Region(y0, y1, x0, x1, code[:, :, y0:y0 + 1, x0:x0 + 1]))
    return regions


def region_tiles(regions: list[Region], tile_pixels: int) -> Iterator[tuple[slice, slice, Tensor]]:
    """(rows, columns, code) of bands of about `tile_pixels` pixels within each region: a narrow
    region gets taller bands, so the number of tiles follows the pixel count, not the regions'."""
    for region in regions:
        rows = max(1, tile_pixels // (region.x1 - region.x0))
        for y0 in range(region.y0, region.y1, rows):
            yield slice(y0, min(region.y1, y0 + rows)), slice(region.x0, region.x1), region.code
