import torch

from models.warp import flow_to_center, warp


def test_integer_shift_moves_features_exactly():
    feats = torch.rand(1, 4, 6, 7)
    motion = torch.zeros(1, 2, 6, 7)
    motion[:, 0], motion[:, 1] = 2, -1            # sample at (x+2, y-1)
    out, valid = warp(feats, motion)
    assert torch.equal(out[:, :, 1:, :5], feats[:, :, :-1, 2:])
    assert valid[:, :, 1:, :5].eq(1).all()
    assert valid[:, :, 0].eq(0).all() and valid[:, :, :, 5:].eq(0).all()
    assert out[:, :, 0].eq(0).all()


def test_zero_motion_is_identity_and_half_pixel_interpolates():
    feats = torch.rand(2, 3, 5, 5)
    out, valid = warp(feats, torch.zeros(2, 2, 5, 5))
    assert torch.equal(out, feats) and valid.eq(1).all()
    motion = torch.zeros(2, 2, 5, 5)
    motion[:, 0] = 0.5
    out, _ = warp(feats, motion)
    torch.testing.assert_close(out[..., :4], (feats[..., :4] + feats[..., 1:]) / 2)


def test_motion_off_screen_or_not_finite_is_invalid_and_zero():
    feats = torch.rand(1, 2, 4, 4)
    motion = torch.full((1, 2, 4, 4), 1e5)
    motion[0, 0, 0, 0] = float("nan")
    out, valid = warp(feats, motion)
    assert valid.eq(0).all() and out.eq(0).all()


def test_past_flow_chains_motion_vectors():
    motions = [torch.zeros(1, 2, 6, 6) for _ in range(3)]
    motions[2][:, 0], motions[1][:, 0] = 1, 2        # 2→1 moves by 1, 1→0 by 2
    flow, valid = flow_to_center(motions, center=2, j=0)
    assert torch.equal(flow[:, 0, :, :3], torch.full((1, 6, 3), 3.0))
    assert flow_to_center(motions, 2, 2) == (None, None)
    future, _ = flow_to_center(motions, center=1, j=2)
    assert torch.equal(future[:, 0], torch.full((1, 6, 6), -1.0))
