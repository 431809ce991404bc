"""Where tracking starts: ``tracking.prediction`` ``features`` moves the last tracked pose by the ORB
matches' relative pose, and falls back to the motion model where they do not verify."""

from __future__ import annotations

import numpy as np
import pytest

from neb_slam_core.config_io import load_config
from neb_slam_core.geometry.se3 import invert
from neb_slam_core.slam import Frontend, new_block_map
from neb_slam_core.types import RgbdFrame

FRAME_NS = 33_333_333


@pytest.fixture(scope="module")
def route():
    """Frames 0, 1, 9, 18, 27 and 36 of the 'default' synthetic route (160x120), rendered, with their
    poses."""
    from neb_slam_core.synth.generate import build_sequence, resolve_spec
    from neb_slam_core.synth.render import Renderer

    spec = resolve_spec("default")
    seq = build_sequence(spec)
    intr = spec.camera.intrinsics()
    renderer = Renderer.for_scene(seq.scene, intr)
    poses = seq.trajectory.poses
    frames = {}
    for i in (0, 1, 9, 18, 27, 36):
        view = renderer.render(poses[i])
        frames[i] = RgbdFrame(view.rgb, view.depth_m, intr, i * FRAME_NS, T_world_cam=poses[i])
    return frames


def _error_m(T, T_true) -> float:
    return float(np.linalg.norm((invert(T_true) @ T)[:3, 3]))


def test_the_feature_prediction_lands_where_the_camera_is(route):
    """Nine frames (0.3 s, 56 cm of this route) after the last tracked one: the motion model can only
    predict the last pose (no velocity from one frame); the matches put it within 2 cm."""
    cfg = load_config("ci", ["tracking.prediction=features"])
    fe = Frontend(cfg, new_block_map(cfg), route[0].T_world_cam)
    fe.step(route[0])  # the first frame: the map starts here, the reference of the next prediction
    frame = route[9]
    features = fe.describe(frame)
    assert features is not None
    far = _error_m(fe.predict(frame.stamp_ns), frame.T_world_cam)
    near = _error_m(fe.prediction(frame.stamp_ns, features), frame.T_world_cam)
    assert far > 0.3 and near < 0.02, (far, near)


def test_without_verified_matches_or_with_motion_the_motion_model_predicts(route):
    for prediction in ("features", "motion"):
        cfg = load_config("ci", [f"tracking.prediction={prediction}"])
        fe = Frontend(cfg, new_block_map(cfg), route[0].T_world_cam)
        fe.step(route[0])
        black = RgbdFrame(np.zeros_like(route[1].rgb), route[1].depth_m, route[1].intrinsics, FRAME_NS)
        features = fe.describe(black)
        assert (features is None) == (prediction == "motion")
        np.testing.assert_array_equal(fe.prediction(FRAME_NS, features), fe.predict(FRAME_NS))
        assert fe.describe(route[1]) is None if prediction == "motion" else len(fe.describe(route[1]).features) > 100


def test_while_tracking_fails_the_matches_chain_from_failed_frame_to_failed_frame(route, monkeypatch):
    """Frames 9, 18 and 27 fail (as in a pan into space the map has not seen): each gets its pose from
    its matches with the frame before; frame 36 no longer matches frame 0, the last tracked one, but
    matches 27, and lands within 3 cm of the camera, where the motion model, which forgets the velocity
    at a failure, stays at frame 0's pose, over half a metre away."""
    cfg = load_config("ci", ["tracking.prediction=features"])
    fe = Frontend(cfg, new_block_map(cfg), route[0].T_world_cam)
    fe.step(route[0])
    monkeypatch.setattr(fe, "_tracking_ok", lambda tracked, record=True: (False, "failed (test)"))
    for i in (9, 18, 27):
        step = fe.step(route[i])
        assert not step.result.tracking_ok and fe.lost
        assert _error_m(step.result.T_world_cam, route[i].T_world_cam) < 0.03 * i / 9
    frame = route[36]
    features = fe.describe(frame)
    assert fe._motion.relative_pose(features, fe.describe(route[0])) is None  # out of frame 0's sight
    chained = _error_m(fe.prediction(frame.stamp_ns, features), frame.T_world_cam)
    frozen = _error_m(fe.predict(frame.stamp_ns), frame.T_world_cam)
    assert chained < 0.03 and frozen > 0.5, (chained, frozen)
