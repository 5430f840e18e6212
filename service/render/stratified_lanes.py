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

The film and lens uniforms keep coming from the pixel's own (0,2)-sequence that continues across
passes (stratified_sequence.py): the lanes of group b take the pass's sample numbers
((n_p >> (b+1)) << (b+1)) … + 2^b − 1 after the pixel's prior count — high bits first, so the
groups of one pixel tile prior … prior + n_p − 1 and each group's run is aligned to 2^b within
the pass.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import numpy as np

# Mitsuba's sampler per sequence length (lanes that one pixel's sequence spans, a power of 4).
# Every one keeps each dimension of a sample uniform; they differ in how independent two
# dimensions of one sample stay. Measured (8×8 histogram of dimension pairs, 2^16 lanes, χ²
# with 63 expected): `ldsampler` XORs every dimension of a sequence with the same scramble
# (χ² 65 600 at 4, ~110 at 16–256), `stratified` takes consecutive permutation seeds that tie
# neighbouring dimensions (32 900 at 4, 1 970 at 16, 168 at 64), `multijitter` 1 970 at 4, 290–460
# at 16, ≤ 64 from 64 on; `orthogonal` (a Bose orthogonal array, prime² counts only) 47–75 at 4.
# Multijitter's tie at 16 was kept: no bias seen (tests/fidelity scenes at 16 spp, mean within
# 0.4 % of mi.render and 1.7 standard errors), and it cut the lit plane's variance (the test
# scene in tests/render/test_stratified_sampling.py) at 16 spp to 0.04× independent's where four
# orthogonal sequences of 4 gave 0.15×.
SEQUENCE_SAMPLERS = {1: "independent", 4: "orthogonal"}
LONG_SEQUENCE_SAMPLER = "multijitter"


@dataclass(frozen=True)
class LaneGroupChunk:
    """One wavefront of a digit group: pixel-major lanes, `lanes_per_pixel` per pixel."""

    pixels: np.ndarray          # lane → flat pixel index (uint32, ascending, each repeated)
    sample_index: np.ndarray    # lane → the sample's number in its pixel over the job (uint32)
    lanes_per_pixel: int        # 2^b: the sampler's samples per wavefront


def digit_group_chunks(prior: np.ndarray, counts: np.ndarray, max_wavefront: int) -> Iterator[LaneGroupChunk]:
    """The pass's lanes grouped by the binary digits of each pixel's count, highest digit first,
    each group cut into chunks of whole pixels of at most `max_wavefront` lanes (at least one
    pixel). Over all chunks, pixel p gets exactly counts[p] lanes numbered prior[p] … + counts[p] − 1."""
    flat = np.asarray(counts, dtype=np.int64).ravel()
    if flat.size and flat.min() < 0:
        raise ValueError("sample counts must be >= 0")
    before = np.asarray(prior, dtype=np.int64).ravel()
    top = int(flat.max()).bit_length() if flat.size else 0
    for bit in reversed(range(top)):
        lanes_per_pixel = 1 << bit
        members = np.flatnonzero((flat >> bit) & 1)
        pixels_per_chunk = max(1, max_wavefront // lanes_per_pixel)
        for start in range(0, len(members), pixels_per_chunk):
            chunk = members[start:start + pixels_per_chunk]
            yield LaneGroupChunk(
                pixels=np.repeat(chunk, lanes_per_pixel).astype(np.uint32),
                sample_index=group_sample_indices(before[chunk], flat[chunk], bit),
                lanes_per_pixel=lanes_per_pixel)


def group_sample_indices(prior: np.ndarray, counts: np.ndarray, bit: int) -> np.ndarray:
    """Lane → sample number for the pixels (prior counts, this pass's counts) of digit group
    `bit`, pixel-major: each pixel's 2^bit numbers after the higher digits' runs."""
    lanes_per_pixel = 1 << bit
    first = np.asarray(prior, dtype=np.int64) + ((np.asarray(counts, dtype=np.int64) >> (bit + 1)) << (bit + 1))
    within = np.arange(lanes_per_pixel, dtype=np.int64)
    return (first[:, None] + within[None, :]).ravel().astype(np.uint32)


def sequence_length(lanes_per_pixel: int) -> int:
    """The lanes of one sequence in a group of `lanes_per_pixel` (2^b) lanes per pixel: 2^b when
    b is even; when b is odd, 2^(b−1), two sequences per pixel — the samplers stratify square
    counts, and a sequence's length must divide the sampler's count."""
    length = 1
    while length * 4 <= lanes_per_pixel:
        length *= 4
    return length


def sequence_sampler_kind(length: int) -> str:
    """Which of Mitsuba's samplers drives sequences of `length` lanes (SEQUENCE_SAMPLERS)."""
    return SEQUENCE_SAMPLERS.get(length, LONG_SEQUENCE_SAMPLER)


def group_sampler(mi, lanes_per_pixel: int, seed: int, lanes: int):
    """A Mitsuba sampler seeded for `lanes` pixel-major lanes, `lanes_per_pixel` per pixel, in
    sequences of sequence_length: what mi.render sets up for a uniform spp of that length."""
    length = sequence_length(lanes_per_pixel)
    sampler = mi.load_dict({"type": sequence_sampler_kind(length), "sample_count": length})
    sampler.set_samples_per_wavefront(length)
    sampler.seed(seed, lanes)
    return sampler
