import numpy as np

from neb_slam_core.eval.seams import seam_step_errors
from neb_slam_core.types import Intrinsics


def test_seam_step_on_a_fronto_parallel_wall():
    """A wall at z = 2 seen head-on; two blocks meet at world x = 0 (the image centre column)."""
    k = Intrinsics(10.0, 10.0, 4.5, 2.5, 10, 6)
    gt = np.full((6, 10), 2.0, np.float32)
    centres = np.array([[-2.5, 0.0, 2.0], [2.5, 0.0, 2.0]])  # faces meet at x = 0
    rendered = gt.copy()
    rendered[:, 5:] += 0.004  # a 4 mm step where the surface enters the second block
    s = seam_step_errors(rendered, gt, np.eye(4), k, centres, edge_m=5.0)
    # pixel columns 4 and 5 straddle x = 0 (x = -0.1 and +0.1 at z = 2): one pair per row
    assert s.seam.size == 6
    assert np.allclose(s.seam, 0.004, atol=1e-6)
    assert np.allclose(s.elsewhere, 0.0, atol=1e-6)
    # a real step in the ground truth (an object edge) is not a seam error
    gt2 = gt.copy()
    gt2[:, 5:] = 1.5
    assert seam_step_errors(gt2, gt2, np.eye(4), k, centres, 5.0).seam.size == 0
