"""The wavefront's lane → pixel map written out on the host with np.repeat: the reference the
device-built map (service/render/lane_map.py) and the splat are checked against."""
from __future__ import annotations

import numpy as np


def expand_counts(counts: np.ndarray) -> np.ndarray:
    """Flat pixel indices, each repeated by its count."""
    flat = np.asarray(counts, dtype=np.int64).ravel()
    return np.repeat(np.arange(flat.size, dtype=np.uint32), flat)
