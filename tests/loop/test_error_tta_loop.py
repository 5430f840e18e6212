"""The loop with its error map averaged over dihedral views (models/error_tta.py), end to end on
real renders (tiny non-square images, small untrained networks)."""
import numpy as np

from models.error_tta import ErrorTTA
from models.pretrained import Networks
from service.loop.loop import RenderLoop
from service.loop.spec import LoopSpec


def run(nets: Networks) -> list:
    spec = LoopSpec(scene="cornell-box", width=20, height=12, max_iterations=2, seed=3)
    return list(RenderLoop(spec, nets).run())


def test_the_loop_runs_with_eight_views_on_a_non_square_image(tiny_networks):
    plain = run(tiny_networks)
    viewed = run(Networks(tiny_networks.denoiser, ErrorTTA(tiny_networks.error_predictor, 8)))
    assert [r.spp_mean for r in viewed] == [16, 32]
    for record in viewed:
        assert record.error[0].shape == (12, 20) and np.isfinite(record.error[0]).all() and (record.error[0] >= 0).all()
    # the first iteration renders the same samples; its map is the views' average, not the plain network's
    assert not np.allclose(plain[0].error[0], viewed[0].error[0])
