import math

import torch

from neb_slam_core.config import OneBlobConfig
from neb_slam_core.scene.one_blob import OneBlob


def test_code_at_origin_is_hand_worked():
    enc = OneBlob(OneBlobConfig(n_bins=16, period_m=10.0))
    code = enc(torch.zeros(1, 3)).reshape(3, 16)
    # phase 0 lies 1/32 from the centres of bins 0 and 15 (on the circle), sigma = 1/16
    expected_edge = math.exp(-0.5 * (0.5) ** 2)
    assert torch.allclose(code[:, 0], torch.full((3,), expected_edge))
    assert torch.allclose(code[:, 15], torch.full((3,), expected_edge))
    # bin 8 is half a period away: distance 15/32 -> exp(-0.5 * 7.5^2)
    assert torch.allclose(code[:, 8], torch.full((3,), math.exp(-0.5 * 7.5 ** 2)))


def test_periodic_and_bound_free():
    enc = OneBlob(OneBlobConfig(n_bins=16, period_m=10.0))
    x = torch.tensor([[0.3, -7.2, 123.4]])
    assert torch.allclose(enc(x), enc(x + 10.0), atol=1e-4)
    assert torch.allclose(enc(x), enc(x - 20.0), atol=1e-4)
    assert enc(x).shape == (1, 48)
    assert enc.n_output_dims == 48


def test_smooth_and_differentiable_in_points():
    enc = OneBlob(OneBlobConfig())
    x = torch.tensor([[1.0, 2.0, 3.0]], requires_grad=True)
    enc(x).sum().backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    # a millimetre step changes the code by a millimetre's worth, not a jump
    d = (enc(x + 1e-3) - enc(x)).abs().max()
    assert d < 0.01
