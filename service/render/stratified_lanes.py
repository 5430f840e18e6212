"""Lanes for a scene with a stratifying sampler: every dimension of a path stratified per pixel,
under per-pixel counts that vary.

Mitsuba's samplers stratify the samples of one *sequence* — `samples_per_wavefront` consecutive
lanes — and take a lane's sample number as `lane % samples_per_wavefront` (Mitsuba 3,
src/render/sampler.cpp: current_sample_index, compute_per_sequence_seed). `mi.render` gives each
pixel one sequence of spp lanes, so every pixel needs the same count. The loop's counts differ
per pixel, so each pass's count map is split by binary digits: the pixels whose count n_p has
bit b set get 2^b lanes in a group whose count is 2^b everywhere, traced with Mitsuba's
`ldsampler` (a randomly permuted, XOR-scrambled (0,2)-sequence per pair of dimensions) in
sequences of 2^b lanes. A pixel's groups are independent stratified estimates; together they are
exactly its n_p samples. Each group (and each chunk of a group, cut at whole pixels) is seeded
on its own.

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

# The Mitsuba sampler that drives a group's integrator dimensions: its sample count may be any
# power of two that is a square (it rounds 2^b up to 4^⌈b/2⌉, at least 4, and a sequence of 2^b
# lanes then reads a random 2^b of those points: still without repetition, so still no worse
# than independent), and samples_per_wavefront = 2^b divides it.
GROUP_SAMPLER = "ldsampler"


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


def group_sample_count(lanes_per_pixel: int) -> int:
    """The count GROUP_SAMPLER takes for sequences of `lanes_per_pixel` lanes: the smallest
    square power of two ≥ it (at least 4), which it would round to anyway (quietly, this way)."""
    side = 2
    while side * side < lanes_per_pixel:
        side *= 2
    return side * side


def group_sampler(mi, lanes_per_pixel: int, seed: int, lanes: int):
    """Mitsuba's GROUP_SAMPLER seeded for `lanes` pixel-major lanes in sequences of
    `lanes_per_pixel` (one per pixel): what mi.render sets up for a uniform spp."""
    sampler = mi.load_dict({"type": GROUP_SAMPLER, "sample_count": group_sample_count(lanes_per_pixel)})
    sampler.set_samples_per_wavefront(lanes_per_pixel)
    sampler.seed(seed, lanes)
    return sampler
