"""Lanes for a scene with a stratifying sampler: every dimension of a path stratified per pixel,
under per-pixel counts that vary.

Mitsuba's samplers stratify the samples of one *sequence* — `samples_per_wavefront` consecutive
lanes — and take a lane's sample number as `lane % samples_per_wavefront` (Mitsuba 3,
src/render/sampler.cpp: current_sample_index, compute_per_sequence_seed). `mi.render` gives each
pixel one sequence of spp lanes, so every pixel needs the same count. The loop's counts differ
per pixel, so each pass's count map is split by binary digits: the pixels whose count n_p has
bit b set get 2^b lanes in a group whose count is 2^b everywhere, traced with one of Mitsuba's
stratifying samplers in sequences of 2^b lanes (2^(b−1) when b is odd: two per pixel), chosen by
sequence length so that each sample's dimensions stay independent of one another
(SEQUENCE_SAMPLERS). A pixel's sequences are independent stratified estimates; together they
are exactly its n_p samples. Each group (and each chunk of a group, cut at whole pixels) is
seeded on its own.

Digits 2k and 2k+1 share one sequence length (4^k: one sequence of it for digit 2k, two for
digit 2k+1) and so one sampler, and are traced as one group: a pixel gets ((n_p >> 2k) & 3)
whole sequences of 4^k lanes, consecutive. Each sequence is still a complete sequence of its
sampler, seeded by (chunk seed, its first lane), so the samples have the distribution the two
separate groups gave; what changes is half as many traces and launches per pass — each one is
~30 ms of Python tracing and ~10 ms of kernel assembly on the LLVM backend whatever its size, what
made an uneven pass at 128² cost ~3× an independent one (docs/sampler.md, "Uneven stratified
passes").

The film and lens uniforms keep coming from the pixel's own (0,2)-sequence that continues across
passes (stratified_sequence.py): the lanes of group b take the pass's sample numbers
((n_p >> (b+1)) << (b+1)) … + 2^b − 1 after the pixel's prior count — high bits first, so the
groups of one pixel tile prior … prior + n_p − 1 and each group's run is aligned to 2^b within
the pass.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import drjit as dr
import numpy as np

from service.render.lane_map import ChunkRows, lane_rows, lane_within_row, row_pixels, upload

# Mitsuba's sampler per sequence length (lanes that one pixel's sequence spans, a power of 4).
# Every one keeps each dimension of a sample uniform; they differ in how independent two
# dimensions of one sample stay. Measured (8×8 histogram of dimension pairs, 2^16 lanes, χ²
# with 63 expected): `ldsampler` XORs every dimension of a sequence with the same scramble
# (χ² 65 600 at 4, ~110 at 16–256), `stratified` takes consecutive permutation seeds that tie
# neighbouring dimensions (32 900 at 4, 1 970 at 16, 168 at 64), `multijitter` 1 970 at 4, 290–460
# at 16, ≤ 64 from 64 on; `orthogonal` (a Bose orthogonal array, prime² counts only) 47–75 at 4.
# Multijitter's tie at 16 was kept: no bias seen (tests/fidelity scenes at 16 spp, mean within
# 0.4 % of mi.render and 1.7 standard errors; living_room at 256², 24 seeds: image mean −0.02 %
# against independent's +0.01 %, where `stratified` reads −0.23 %), and it cut the lit plane's
# variance (the test scene in tests/render/test_stratified_sampling.py) at 16 spp to 0.04×
# independent's where four orthogonal sequences of 4 gave 0.15×. `stratified` for the long
# sequences read 1.07× multijitter's denoised SMAPE on the 12 stratifying suite scenes at 16 spp
# (docs/decisions.md).
SEQUENCE_SAMPLERS = {1: "independent", 4: "orthogonal"}
LONG_SEQUENCE_SAMPLER = "multijitter"


@dataclass(frozen=True)
class LaneGroupChunk:
    """One wavefront of a sequence-length group: pixel-major lanes, each pixel's lanes consecutive
    and a whole number of sequences of `sequence_length` lanes. The lanes themselves are expanded
    on the device (lane_map.py): a pixel's lane j takes sample number first_sample[row] + j."""

    rows: ChunkRows             # the chunk's pixels (ascending) and lanes per pixel
    first_sample: np.ndarray    # row → its first lane's sample number in the pixel over the job (uint32)
    sequence_length: int        # 4^k: the sampler's samples per wavefront

    @property
    def pixels(self) -> np.ndarray:
        """The chunk's distinct flat pixels, ascending (int64)."""
        if self.rows.pixels is not None:
            return self.rows.pixels
        return self.rows.first_pixel + np.arange(self.rows.size // self.rows.uniform)


def digit_group_chunks(prior: np.ndarray, counts: np.ndarray, max_wavefront: int) -> Iterator[LaneGroupChunk]:
    """The pass's lanes grouped by sequence length (digits 2k and 2k+1 of each pixel's count),
    longest first, each group cut into chunks of whole pixels of at most `max_wavefront` lanes
    (at least one pixel). Over all chunks, pixel p gets exactly counts[p] lanes numbered
    prior[p] … + counts[p] − 1, each digit's run aligned to its 2^b within the pass. Host work
    is per pixel, never per lane."""
    flat = np.asarray(counts, dtype=np.int64).ravel()
    if flat.size and flat.min() < 0:
        raise ValueError("sample counts must be >= 0")
    before = np.asarray(prior, dtype=np.int64).ravel()
    top = int(flat.max()).bit_length() if flat.size else 0
    for low_bit in reversed(range(0, top, 2)):
        length = 1 << low_bit
        sequences = (flat >> low_bit) & 3          # 2 for digit 2k+1, 1 for digit 2k
        members = np.flatnonzero(sequences)
        lanes = sequences[members] * length
        first_samples = group_first_samples(before[members], flat[members], low_bit)
        for chunk in _cut_at_pixels(lanes, max_wavefront):
            yield LaneGroupChunk(rows=_chunk_rows(members[chunk], lanes[chunk]),
                                 first_sample=first_samples[chunk], sequence_length=length)


def _chunk_rows(pixels: np.ndarray, lanes: np.ndarray) -> ChunkRows:
    """Rows of whole pixels; the arithmetic (upload-free) form when they are consecutive pixels
    with one count, as under a uniform count map."""
    size = int(lanes.sum())
    if int(lanes.min()) == int(lanes.max()) and int(pixels[-1] - pixels[0]) == len(pixels) - 1:
        return ChunkRows(size=size, uniform=int(lanes[0]), first_pixel=int(pixels[0]))
    return ChunkRows(size=size, pixels=pixels, lanes=lanes)


def group_lanes(mi, chunk: LaneGroupChunk):
    """The chunk's lanes expanded on the device (lane_map.py): (flat pixel, sample number in
    the pixel) per lane, device UInt32."""
    row = lane_rows(mi, chunk.rows)
    first_sample = dr.gather(mi.UInt32, upload(mi, chunk.first_sample), row)
    return row_pixels(mi, chunk.rows, row), first_sample + lane_within_row(mi, chunk.rows, row)


def _cut_at_pixels(lanes: np.ndarray, max_wavefront: int) -> Iterator[slice]:
    """Consecutive runs of pixels (lanes[i] each) of at most max_wavefront lanes, at least one
    pixel per run."""
    ends = np.cumsum(lanes)
    start = 0
    while start < len(lanes):
        offset = ends[start - 1] if start else 0
        stop = max(int(np.searchsorted(ends, offset + max_wavefront, side="right")), start + 1)
        yield slice(start, stop)
        start = stop


def group_first_samples(prior: np.ndarray, counts: np.ndarray, low_bit: int) -> np.ndarray:
    """Each pixel's first sample number (prior counts, this pass's counts) in the group of digits
    low_bit and low_bit + 1: its ((n >> low_bit) & 3) · 2^low_bit numbers come after the higher
    digits' runs — digit low_bit + 1's run, then digit low_bit's."""
    counts = np.asarray(counts, dtype=np.int64)
    first = np.asarray(prior, dtype=np.int64) + ((counts >> (low_bit + 2)) << (low_bit + 2))
    return first.astype(np.uint32)


def sequence_sampler_kind(length: int) -> str:
    """Which of Mitsuba's samplers drives sequences of `length` lanes (SEQUENCE_SAMPLERS)."""
    return SEQUENCE_SAMPLERS.get(length, LONG_SEQUENCE_SAMPLER)


def sequence_sampler(mi, length: int, seed: int, lanes: int):
    """A Mitsuba sampler seeded for `lanes` lanes in sequences of `length` (a power of 4), each
    sequence `length` consecutive lanes starting at a multiple of `length`."""
    sampler = mi.load_dict({"type": sequence_sampler_kind(length), "sample_count": length})
    sampler.set_samples_per_wavefront(length)
    sampler.seed(seed, lanes)
    return sampler
