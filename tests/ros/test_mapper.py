"""The mapper's final trajectory from the tracker's path and the corrected keyframe poses."""

import numpy as np
from scipy.spatial.transform import Rotation

from neb_slam_core.geometry.se3 import make_pose
from neb_slam_ros.mapper import corrected_trajectory


def test_path_frames_follow_their_keyframe_and_take_their_share_of_the_next_ones_move():
    """A path of 11 frames 10 cm apart along x (turning 1 degree each), keyframes at rows 0, 5 and 10.
    Corrected poses: keyframe 0 unchanged; keyframe 5 moved 3 cm along y and turned 4 degrees about its
    own centre; keyframe 10 moved with it. Frame 2 (2/5 of the way from keyframe 0 to 5) turns by 0.4 of
    the 4 degrees about its own position and moves by 0.4 of the displacement the move gives that
    position (frames 1 and 4 likewise with 0.2 and 0.8); frames 6-9 move rigidly with keyframes 5 and 10,
    which moved together; keyframes end where they were put."""
    stamps = np.arange(11, dtype=np.int64) * 1000
    path = np.stack([make_pose(Rotation.from_euler("z", i, degrees=True).as_matrix(), [0.1 * i, 0.0, 0.0])
                     for i in range(11)])
    kf_rows = [0, 5, 10]
    kf_then = path[kf_rows]
    R = Rotation.from_euler("z", 4.0, degrees=True).as_matrix()
    move = make_pose(R, np.zeros(3))
    move[:3, 3] = kf_then[1][:3, 3] - R @ kf_then[1][:3, 3] + [0.0, 0.03, 0.0]
    kf_now = kf_then.copy()
    kf_now[1:] = move @ kf_then[1:]
    out = corrected_trajectory(stamps, path, stamps[kf_rows], kf_now).poses

    np.testing.assert_allclose(out[kf_rows], kf_now, atol=1e-12)
    for i, share in ((1, 0.2), (2, 0.4), (4, 0.8)):
        p = path[i][:3, 3]
        turn = Rotation.from_rotvec(share * Rotation.from_matrix(R).as_rotvec()).as_matrix()
        np.testing.assert_allclose(out[i][:3, :3], turn @ path[i][:3, :3], atol=1e-12)
        np.testing.assert_allclose(out[i][:3, 3], p + share * (move[:3, :3] @ p + move[:3, 3] - p), atol=1e-12)
    for i in range(6, 10):
        np.testing.assert_allclose(out[i], move @ path[i], atol=1e-12)
