import pytest
import torch

from models.losses import asymmetric_loss, l1, smape, smape_map
from models.metrics import psnr, relmse, ssim


def test_smape_matches_hand_computed_value():
    d, r = torch.tensor([1.0, 0.0, 2.0]), torch.tensor([3.0, 0.0, 2.0])
    # |1-3|/(1+3+0.01), 0/(0.01), 0
    assert smape(d, r).item() == pytest.approx((2 / 4.01) / 3)


def test_smape_map_is_per_pixel_channel_mean():
    d = torch.zeros(1, 3, 1, 2)
    r = torch.ones(1, 3, 1, 2)
    r[0, 0, 0, 1] = 0
    m = smape_map(d, r)
    assert m.shape == (1, 1, 1, 2)
    torch.testing.assert_close(m[0, 0, 0], torch.tensor([1 / 1.01, (2 / 1.01) / 3]))


def test_asymmetric_loss_matches_hand_computed_value():
    c = torch.tensor([0.0, 0.0])   # noisy input
    r = torch.tensor([1.0, 1.0])   # reference
    d = torch.tensor([0.5, 1.5])   # first between c and r (residual noise), second overshoots away from c
    l0, l1_ = 0.5 / 1.51, 0.5 / 2.51
    assert asymmetric_loss(d, r, c, 4.0).item() == pytest.approx((l0 + 4 * l1_) / 2)


def test_lambda_one_asymmetric_loss_equals_symmetric():
    d, r, c = torch.rand(2, 3, 5, 5), torch.rand(2, 3, 5, 5), torch.rand(2, 3, 5, 5)
    torch.testing.assert_close(asymmetric_loss(d, r, c, 1.0), smape(d, r))


def test_larger_lambda_never_lowers_asymmetric_loss():
    d, r, c = torch.rand(2, 3, 5, 5), torch.rand(2, 3, 5, 5), torch.rand(2, 3, 5, 5)
    values = [asymmetric_loss(d, r, c, lam).item() for lam in (1, 1.5, 2, 5, 10)]
    assert values == sorted(values)
    per_pixel = torch.rand(2, 1, 5, 5) * 9 + 1
    assert asymmetric_loss(d, r, c, per_pixel) >= smape(d, r)
    assert asymmetric_loss(d, r, c, per_pixel + 1) >= asymmetric_loss(d, r, c, per_pixel)


def test_l1_and_report_metrics_on_known_images():
    a = torch.full((1, 3, 16, 16), 0.5)
    assert l1(a, a + 0.25).item() == pytest.approx(0.25)
    assert relmse(a, a).item() == 0
    assert psnr(a, a + 0.1).item() == pytest.approx(20.0, abs=1e-3)
    assert ssim(a, a).item() == pytest.approx(1.0)
    noisy = (a + torch.randn_like(a) * 0.2).clamp(0, 1)
    assert ssim(noisy, a) < 0.9
    assert ssim(torch.rand(1, 3, 1, 1), torch.rand(1, 3, 1, 1)).isfinite()
