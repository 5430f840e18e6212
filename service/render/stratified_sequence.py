"""Per-pixel progressive stratification of the film and lens samples: the Sobol' (0,2)-sequence.

Mitsuba's stratifying samplers (stratified, multijitter, orthogonal, ldsampler) stratify a
pixel's samples for a sample count fixed before rendering. The loop hands a pixel its samples
over several passes with counts it only learns as it goes, so a pixel's k-th sample overall
(its count before the pass + its index within the pass) takes point k of one endless sequence
whose every aligned run of 2^m points is stratified: the first two dimensions of Sobol' (1967),
a (0,2)-sequence in base 2 — any 2^m consecutive points starting at a multiple of 2^m form a
(0,m,2)-net: each of the 2^m elementary intervals of area 2^-m holds exactly one point
(Niederreiter 1992, "Random Number Generation and Quasi-Monte Carlo Methods", ch. 4).

- Dimension 0 is the van der Corput radical inverse in base 2: the index's bits reversed
  (generator matrix = identity, read as bits after the binary point).
- Dimension 1 has the upper-triangular generator matrix C[i][j] = binom(j, i) mod 2 (Pascal's
  triangle mod 2: Sobol's primitive polynomial x + 1, m_1 = 1; its direction numbers, listed
  first in Joe & Kuo 2008, satisfy v_{j+1} = v_j ⊕ (v_j >> 1)).

Randomisation keeps every sample marginally uniform, so the estimator stays unbiased:
- each coordinate is Owen-scrambled per pixel (Owen 1995, "Randomly permuted (t,m,s)-nets and
  (t,s)-sequences"): its binary digit d flips by a function, random per (seed, pixel,
  dimension), of digits 1…d−1 (nested_scramble: a short chain of integer operations on the
  reversed bits instead of a hash per digit, as in Burley 2020). A scrambled net is still a net.
  A digital shift alone (one XOR per pixel) is not enough: it leaves each pixel's points a
  shifted regular grid per axis, which aliases with a fine texture — on a checkerboard of ~2
  checks per pixel it had 2.5× the per-pixel variance of independent samples;
- the lens pair reads the same sequence at a shuffled index: bit i of k flips by a random
  function of the bits of k above i. That permutation maps every aligned block of 2^m indices
  onto an aligned block, so the lens points stay a net for each prefix of 2^m samples, and,
  being non-linear, it does not tie the lens point to the film point (an XOR of the index
  would: a digital sequence is linear over GF(2), x(k ⊕ c) = x(k) ⊕ x(c)).

The functions take and return unsigned 32-bit arrays and work the same on Dr.Jit's UInt32
(inside the render kernel) and on numpy's uint32 (the tests).
"""
from __future__ import annotations

# Mitsuba's class names of the samplers that stratify a pixel's samples; `independent` (and
# anything unknown) keeps independent uniforms: the scene as written.
STRATIFYING_SAMPLERS = frozenset(
    {"StratifiedSampler", "MultijitterSampler", "OrthogonalSampler", "LowDiscrepancySampler"})
# Tags that make the hashes of the four shifted coordinates and of the shuffle differ.
FILM_X, FILM_Y, LENS_X, LENS_Y, LENS_SHUFFLE = 0x1F3D5B79, 0x2B7E1516, 0x3C6EF372, 0x5BE0CD19, 0x7F4A7C15
# 2^-24: the top 24 bits of a 32-bit coordinate make a float32 in [0, 1) exactly.
TO_UNIT = 1.0 / (1 << 24)


def is_stratifying(sampler) -> bool:
    """Whether the scene's sampler stratifies a pixel's samples (then the loop does too)."""
    return sampler is not None and sampler.class_name() in STRATIFYING_SAMPLERS


def mix32(x):
    """A 32-bit avalanche mix: xor-shift / multiply rounds as in MurmurHash3's finaliser
    (Appleby, public domain); every input bit affects every output bit."""
    x = x ^ (x >> 16)
    x = x * 0x85EBCA6B
    x = x ^ (x >> 13)
    x = x * 0xC2B2AE35
    return x ^ (x >> 16)


def pixel_hash(seed: int, pixel, tag: int):
    """A per-pixel 32-bit random value for (seed, pixel, tag): the digital shifts' source."""
    return mix32(mix32(pixel ^ ((seed * 0x9E3779B9 + tag) & 0xFFFFFFFF)) ^ tag)


def reverse_bits(x):
    """The 32 bits of x in reverse order (swap halves, bytes, nibbles, pairs, bits)."""
    x = (x >> 16) | (x << 16)
    x = ((x & 0xFF00FF00) >> 8) | ((x & 0x00FF00FF) << 8)
    x = ((x & 0xF0F0F0F0) >> 4) | ((x & 0x0F0F0F0F) << 4)
    x = ((x & 0xCCCCCCCC) >> 2) | ((x & 0x33333333) << 2)
    return ((x & 0xAAAAAAAA) >> 1) | ((x & 0x55555555) << 1)


def sobol_dim1(k):
    """Sobol's second dimension as 32 bits after the binary point: XOR of the direction
    numbers v_j = column j of the Pascal matrix mod 2 for each set bit j of k."""
    result = k ^ k  # zeros of k's type
    direction = 0x80000000
    for bit in range(32):
        result = result ^ (((k >> bit) & 1) * direction)
        direction ^= direction >> 1
    return result


def nested_scramble(x, key):
    """x with bit i flipped by a key-dependent function of its bits below i: a nested
    permutation of the bits' binary tree read from bit 0 up. Adding a number, multiplying by
    an odd one and XOR-ing with a multiple by an even one each keep bit i a function of the bits
    ≤ i that flips with bit i (Laine & Karras 2011, "Stratified sampling for stochastic
    transparency"; Burley 2020, "Practical hash-based Owen scrambling"), and so does any chain
    of them. Seven integer operations instead of a hash per digit."""
    x = x + key
    x = x ^ (x * 0x6A09E666)    # even multipliers: the fractional bits of √2, √3, √5, √7
    x = x * (key | 1)
    x = x ^ (x * 0xBB67AE84)
    x = x + mix32(key)
    x = x ^ (x * 0x3C6EF372)
    return x ^ (x * 0xA54FF53A)


def owen_scramble(fraction, key):
    """A 32-bit fraction Owen-scrambled: digit d (from the binary point) flipped by a
    key-dependent function of digits 1…d−1 — the nested scramble of its reversed bits."""
    return reverse_bits(nested_scramble(reverse_bits(fraction), key))


def shuffle_index(k, key):
    """k permuted so that bit i flips by a key-dependent function of the bits above it (the
    nested scramble of the reversed index): each aligned block of 2^m indices maps onto an
    aligned block, so every prefix of 2^m samples stays a net."""
    return reverse_bits(nested_scramble(reverse_bits(k), key))


def sequence_bits(k, seed: int, pixel, tag_x: int, tag_y: int):
    """Point k of the pixel's Owen-scrambled (0,2)-sequence, as two 32-bit fractions."""
    # Dimension 0 is reverse_bits(k), and owen_scramble reverses it back first.
    return (reverse_bits(nested_scramble(k, pixel_hash(seed, pixel, tag_x))),
            owen_scramble(sobol_dim1(k), pixel_hash(seed, pixel, tag_y)))


def film_bits(k, seed: int, pixel):
    """The film-position pair of a pixel's k-th sample (32-bit fractions)."""
    return sequence_bits(k, seed, pixel, FILM_X, FILM_Y)


def lens_bits(k, seed: int, pixel):
    """The aperture pair of a pixel's k-th sample: the sequence at a per-pixel shuffled index,
    with shifts of its own."""
    shuffled = shuffle_index(k, pixel_hash(seed, pixel, LENS_SHUFFLE))
    return sequence_bits(shuffled, seed, pixel, LENS_X, LENS_Y)


def unit_point(mi, bits):
    """A pair of 32-bit fractions (Dr.Jit UInt32) as a Point2f in [0, 1)²: their top 24 bits,
    exact in float32 (all 32 would round up to 1.0 near the top)."""
    x, y = bits
    return mi.Point2f(mi.Float(x >> 8), mi.Float(y >> 8)) * TO_UNIT
