import torch

from models.error_predictor import ErrorPredictor, ErrorPredictorConfig
from tests.models.conftest import make_frame


def test_error_predictor_output_is_non_negative_with_right_shape():
    ep = ErrorPredictor(ErrorPredictorConfig(width=4, blocks=6))
    f = make_frame(5, 7, n=2)
    f.color[0, 0, 0, 0] = float("nan")
    out = ep(f, torch.rand(2, 3, 5, 7) * 1e7)
    assert out.shape == (2, 1, 5, 7)
    assert (out >= 0).all() and out.isfinite().all()
    out.mean().backward()
    assert all(p.grad.isfinite().all() for p in ep.parameters())
