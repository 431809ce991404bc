"""Camera motion between two frames from their ORB matches: a prediction for tracking that does not
assume constant velocity.

The tracker's Levenberg-Marquardt converges from a prediction within a few centimetres of the pose.
A constant-velocity prediction stays that close only while the frames come fast: an engine that
tracks a few frames per second of a hand-held camera (the live engine drops the rest), or a camera
that turns or stops abruptly, leaves it far behind. The relative pose from feature matches does not
depend on the motion model, only on the two images overlapping.

    motion = FeatureMotion(cfg.loop)
    ref = motion.describe(previous_frame)
    cur = motion.describe(frame)
    T_ref_cur = motion.relative_pose(cur, ref)   # None when the geometric check fails

It is the loop detector's geometric check (:func:`~.detector.geometric_check`: ratio-test matches, PnP
RANSAC on the reference's depth, refinement with the current frame's depth) with the loop
configuration's ORB and matching settings, without the bag of words. Where the check rejects the pair
only because the current frame's depth disagrees, its PnP pose is taken when PnP's own inliers pass the
check's thresholds: a sensor whose colour and depth are not taken at the same instant (a Kinect v1;
TUM pairs them within 20 ms) samples the keypoints' depths beside their corners during a fast turn,
which the loop check must refuse, while for a prediction the dense tracking after it (and its failure
test) is the verification.
"""

from __future__ import annotations

import numpy as np

from ..config import LoopConfig
from ..types import RgbdFrame
from .detector import FrameFeatures, enough_inliers, frame_features, geometric_check, orb_params
from .features import OrbExtractor


class FeatureMotion:
    """Relative camera poses between frames from ORB matches (see the module docstring)."""

    def __init__(self, cfg: LoopConfig):
        self.cfg = cfg
        self.extractor = OrbExtractor(orb_params(cfg))

    def describe(self, frame: RgbdFrame) -> FrameFeatures:
        """ORB features and keypoint depths of a rectified frame."""
        return frame_features(self.extractor, frame.rgb, frame.depth_m, frame.intrinsics)

    def relative_pose(self, current: FrameFeatures, reference: FrameFeatures) -> np.ndarray | None:
        """``T_ref_cur`` (4, 4) float64, the current camera in the reference camera's frame, when the
        geometric check accepts the pair, or its PnP pose has enough inliers (module docstring); else
        None."""
        check = geometric_check(current, reference, self.cfg)
        if check.accepted:
            return check.T_cand_query
        if check.T_pnp_cand_query is not None and enough_inliers(check.n_pnp_inliers, check.n_matches, self.cfg):
            return check.T_pnp_cand_query
        return None
