from dataclasses import replace

import pytest
import torch

from models.checkpoint import load_checkpoint, save_checkpoint
from models.denoiser import TRUNKS, Denoiser
from models.unet import UNetTrunk
from service.training.config import TRUNK_NAMES
from tests.models.conftest import TINY, make_frame
from tests.models.test_denoiser import hostile_cases

UNET = replace(TINY, trunk="unet")


def test_unet_trunk_gives_every_pyramid_level_width_channels_at_its_resolution():
    trunk = UNetTrunk(cin=7, width=8, levels=3)
    outputs = trunk(torch.rand(2, 7, 32, 48))
    assert [tuple(o.shape) for o in outputs] == [(2, 8, 32, 48), (2, 8, 16, 24), (2, 8, 8, 12)]


def test_unet_finest_features_see_farther_than_the_papers_trunk():
    """A change 24 px away reaches the finest level's features through the U-Net; the paper's
    per-level trunk (13 px across at the finest level) cannot see it."""
    far = make_frame(h=64, w=64, motion=False)
    changed = far.map(lambda _, t: t.clone())
    changed.color[..., 8:12, 8:12] += 50.0
    papers, unet = Denoiser(replace(TINY, temporal=False)), Denoiser(replace(UNET, temporal=False))
    with torch.no_grad():
        before, after = (papers.spatial(papers.encoder(papers._trunk_inputs([f]))) for f in (far, changed))
        assert torch.equal(before[..., 35:38, 35:38], after[..., 35:38, 35:38])
        before, after = (unet.unet(unet._trunk_inputs([f]))[0] for f in (far, changed))
        assert not torch.equal(before[..., 35:38, 35:38], after[..., 35:38, 35:38])   # any change: it reaches


@pytest.mark.parametrize("lam", [1.0, 10.0, "map"])
def test_unet_denoiser_prepare_then_apply_is_forward_on_odd_sizes(lam):
    den = Denoiser(UNET).eval()
    win = [make_frame(h=13, w=21, seed=i) for i in range(3)]
    if lam == "map":
        lam = torch.rand(1, 1, 13, 21) * 9 + 1
    with torch.no_grad():
        out = den(win, 1, lam)
        torch.testing.assert_close(den.apply(den.prepare(win, 1), lam), out)
    assert out.shape == (1, 3, 13, 21) and out.isfinite().all()


@pytest.mark.parametrize("case", list(hostile_cases()))
def test_unet_denoiser_stays_finite_forward_and_backward_on_hard_inputs(case):
    den = Denoiser(UNET)
    win = hostile_cases()[case]
    out = den(win, len(win) // 2, 1.0)
    assert out.isfinite().all()
    (out / (out.detach().abs() + 1)).sum().backward()
    grads = [p.grad for p in den.parameters() if p.grad is not None]
    assert grads and all(g.isfinite().all() for g in grads)


def test_unet_single_scale_output_lies_in_the_convex_hull_of_its_neighbourhood():
    den = Denoiser(replace(UNET, temporal=False, multiscale=False, kernel_size=3)).eval()
    f = make_frame()
    f.albedo.fill_(1.0)
    with torch.no_grad():
        out = den([f], 0, 5.0)
    padded = torch.nn.functional.pad(f.color, (1, 1, 1, 1), mode="replicate")
    win = padded.unfold(2, 3, 1).unfold(3, 3, 1)
    assert (out >= win.amin((-1, -2)) - 1e-4).all() and (out <= win.amax((-1, -2)) + 1e-4).all()


def test_unet_checkpoint_round_trips_and_a_checkpoint_without_a_trunk_loads_the_papers(tmp_path):
    den = Denoiser(UNET).eval()
    back = load_checkpoint(save_checkpoint(tmp_path / "u.pt", den), expected_kind="denoiser")
    assert back.config.trunk == "unet"
    win = [make_frame(seed=i) for i in range(3)]
    with torch.no_grad():
        torch.testing.assert_close(back(win, 1, 2.0), den(win, 1, 2.0))
    path = save_checkpoint(tmp_path / "old.pt", Denoiser(TINY))
    ckpt = torch.load(path, weights_only=True)
    del ckpt["config"]["trunk"]                     # written before the field existed
    torch.save(ckpt, path)
    assert load_checkpoint(path).config.trunk == "levels"


def test_unknown_trunk_fails_at_construction_and_the_cli_knows_every_trunk():
    with pytest.raises(ValueError, match="unknown trunk"):
        Denoiser(replace(TINY, trunk="transformer"))
    assert TRUNK_NAMES == TRUNKS
