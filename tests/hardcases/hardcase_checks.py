"""Assertions every hard case shares: finite, non-negative outputs and exact sample budgets."""
from __future__ import annotations

import numpy as np

from service.exr import ExrFrame
from service.loop.spec import IterationRecord

LAYERS = ("color", "noisy", "variance", "albedo", "normal", "depth", "motion", "spp", "error", "lam")


def assert_finite_frame(frame: ExrFrame) -> None:
    """Every layer of an output frame is finite; radiance layers and the error are ≥ 0."""
    for name in LAYERS:
        layer = getattr(frame, name)
        if layer is not None:
            assert np.isfinite(layer).all(), f"layer {name} has NaN/Inf"
    for name in ("color", "noisy", "variance", "error"):
        layer = getattr(frame, name)
        if layer is not None:
            assert layer.min() >= 0, f"layer {name} is negative ({layer.min()})"


def assert_finite_record(record: IterationRecord) -> None:
    for image in record.denoised:
        assert np.isfinite(image).all() and image.min() >= 0
    for error in record.error:
        if error is not None:
            assert np.isfinite(error).all() and error.min() >= 0
    for buffer in record.buffers:
        assert np.isfinite(buffer.mean).all() and buffer.mean.min() >= 0
        assert np.isfinite(buffer.variance).all() and buffer.variance.min() >= 0


def doubling_totals(pixels: int, spp_first: int, iterations: int) -> list[int]:
    """Total samples per frame after each iteration: spp_first·pixels, then doubling."""
    return [spp_first * pixels * 2 ** i for i in range(iterations)]


def run_checked(loop, totals: list[int]) -> list[IterationRecord]:
    """Run the loop to its end, checking every iteration's outputs and exact sample totals."""
    records = []
    for record in loop.run():
        assert_finite_record(record)
        expected = totals[len(records)]
        assert [int(b.spp.sum()) for b in record.buffers] == [expected] * len(record.buffers)
        records.append(record)
    assert len(records) == len(totals), "the loop stopped early"
    for frame in loop.result_frames():
        assert_finite_frame(frame)
    return records
