import torch

from neb_slam_core.config import LossWeights
from neb_slam_core.render.losses import colour_loss, combine, depth_loss, sdf_losses, smoothness_loss


def test_colour_and_depth_losses_hand_worked():
    pred = torch.tensor([[0.5, 0.5, 0.5], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    obs = torch.tensor([[0.5, 0.5, 0.8], [1.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    mask = torch.tensor([True, True, False])  # the third ray had no valid sample
    assert torch.isclose(colour_loss(pred, obs, mask), torch.tensor((0.09 / 3 + 0.0) / 2))
    d_pred = torch.tensor([1.0, 2.0, 3.0, 4.0])
    d_obs = torch.tensor([1.1, 0.0, 2.8, 9.0])  # ray 1 has no depth; ray 3 is masked
    m = torch.tensor([True, True, True, False])
    assert torch.isclose(depth_loss(d_pred, d_obs, m), torch.tensor((0.01 + 0.04) / 2))


def test_sdf_and_free_space_hand_worked():
    tr = 0.1
    z = torch.tensor([[1.0, 1.95, 2.05, 2.5], [0.5, 1.0, 1.5, 2.0]])
    depth = torch.tensor([2.0, 0.0])  # the second ray has no depth: ignored
    valid = torch.ones(2, 4, dtype=torch.bool)
    # perfect prediction: free space 1 (= tr), band sdf = (d - z) / tr
    sdf = torch.tensor([[1.0, 0.5, -0.5, -3.0], [9.0, 9.0, 9.0, 9.0]])
    l_sdf, l_fs = sdf_losses(sdf, z, depth, valid, tr)
    assert torch.isclose(l_sdf, torch.tensor(0.0), atol=1e-12) and torch.isclose(l_fs, torch.tensor(0.0))
    # errors: free-space sample predicts 0.5 (-> (0.5-1)^2); band samples off by 1 cm and 3 cm
    sdf = torch.tensor([[0.5, 0.6, -0.2, 7.0], [9.0, 9.0, 9.0, 9.0]])
    l_sdf, l_fs = sdf_losses(sdf, z, depth, valid, tr)
    assert torch.isclose(l_fs, torch.tensor(0.25))
    assert torch.isclose(l_sdf, torch.tensor((0.01 ** 2 + 0.03 ** 2) / 2), atol=1e-9)
    # invalid samples do not count
    valid[0, 1] = False
    l_sdf, _ = sdf_losses(sdf, z, depth, valid, tr)
    assert torch.isclose(l_sdf, torch.tensor(0.03 ** 2), atol=1e-9)


def test_smoothness_and_weighted_total():
    f = torch.zeros(2, 4)
    nb = torch.ones(2, 3, 4)
    nb[1] *= 2
    valid = torch.tensor([True, False])
    assert torch.isclose(smoothness_loss(f, nb, valid), torch.tensor(12.0))
    w = LossWeights(colour=5, depth=0.1, sdf=1000, free_space=10, smoothness=1e-6)
    t = combine(w, *(torch.tensor(1.0),) * 5)
    assert torch.isclose(t.total, torch.tensor(5 + 0.1 + 1000 + 10 + 1e-6))
    assert set(t.as_floats()) == {"colour", "depth", "sdf", "free_space", "smoothness", "total"}
