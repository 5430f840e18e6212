import pytest
import torch

from models.denoiser import NEUTRAL_SETTINGS, temporal_config
from models.frames import FrameTensors

# Test networks whose inputs are the frame alone (no OIDN candidate, no trunk guide, no
# post-training setting; the error network without the disagreement and uncalibrated, reading the
# frame, the denoised image and the sample counts). **PLAIN_DENOISER with temporal=… and a width
# gives such a network.
PLAIN_DENOISER = {"oidn_candidate": False, **NEUTRAL_SETTINGS}
PLAIN_ERROR_NETWORK = {"disagreement_input": False, "output_scale": 1.0, "change_scale": None}
# A tiny temporal KPCN (the named design); tests of the shipped shape replace its switches.
TINY = temporal_config(width=8, spatial_blocks=1, temporal_blocks=1, kernel_size=3, lambda_width=4, composite_width=4)


def make_frame(h: int = 12, w: int = 16, n: int = 1, motion: bool = True, seed: int = 0,
               spp: float | None = None) -> FrameTensors:
    """Random buffers; `spp`: a uniform per-pixel sample count (the error network reads one)."""
    g = torch.Generator().manual_seed(seed)
    r = lambda c: torch.rand(n, c, h, w, generator=g)
    return FrameTensors(color=r(3) * 2, variance=r(3) * 0.1, albedo=r(3) * 0.8 + 0.1,
                        normal=r(3) * 2 - 1, depth=r(1) + 1, motion=(r(2) - 0.5) * 2 if motion else None,
                        spp=None if spp is None else torch.full((n, 1, h, w), float(spp)))


@pytest.fixture(autouse=True)
def _seed_and_threads():
    torch.manual_seed(0)
    torch.set_num_threads(1)   # the machine is shared; tiny tensors gain nothing from threads
