"""Scene seeds per split: training and held-out scenes can never share a seed.

Each split owns a disjoint half-open range of scene seeds, so a held-out scene is never a
training scene whatever `--seed` and `--scenes` the two data sets were built with.
"""
from __future__ import annotations

import numpy as np

TRAIN_SEED_BASE = 0
HELDOUT_SEED_BASE = 1_000_000
SPLIT_SIZE = 1_000_000  # seeds per split: [base, base + SPLIT_SIZE)
SPLIT_BASES = {"train": TRAIN_SEED_BASE, "heldout": HELDOUT_SEED_BASE}
SPLITS = tuple(SPLIT_BASES)





def scene_seeds(split: str, n: int, seed: int) -> list[int]:
    """`n` distinct scene seeds of `split`, drawn reproducibly from the data-set seed.

    Drawn one at a time and de-duplicated, so the list is prefix-stable: asking for more
    scenes with the same seed extends an existing data set instead of replacing it.
    """
    if split not in SPLIT_BASES:
        raise ValueError(f"unknown split {split!r}; known splits: {', '.join(SPLITS)}")
    if not 0 <= n <= SPLIT_SIZE:
        raise ValueError(f"scene count must be in [0, {SPLIT_SIZE}], got {n}")
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    rng = np.random.default_rng([seed, SPLIT_BASES[split]])
    chosen: list[int] = []
    seen: set[int] = set()
    while len(chosen) < n:
        offset = int(rng.integers(SPLIT_SIZE))
        if offset not in seen:
            seen.add(offset)
            chosen.append(SPLIT_BASES[split] + offset)
    return chosen
