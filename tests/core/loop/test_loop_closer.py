"""Loop closer: a drifted end of the synthetic loop is detected against its start and put back."""

from __future__ import annotations

import numpy as np
import pytest
from loop_scene import FRAME_NS, LOOP_FRAMES, pose_error
from scipy.spatial.transform import Rotation

from neb_slam_core.config import LoopConfig
from neb_slam_core.geometry.se3 import invert, make_pose
from neb_slam_core.loop.closer import LoopCloser
from neb_slam_core.types import RgbdFrame

#: the drift the end of the loop (frames 270-290) carries: 25 cm and 4 degrees about the vertical,
#: applied in the world frame (what accumulated tracking error looks like)
DRIFT = make_pose(Rotation.from_euler("y", 4.0, degrees=True).as_matrix(), [0.20, 0.0, -0.15])


def frame_of(views, intr, f: int) -> RgbdFrame:
    view = views[f][0]
    return RgbdFrame(view.rgb, view.depth_m, intr, f * FRAME_NS)


@pytest.fixture(scope="module")
def closed(vocabulary, loop_views):
    """Keyframes of the loop added with their ground-truth poses, the end ones drifted, then the last
    one's loop closed. Returns (event, corrected poses, poses before, ground truth)."""
    views, intr = loop_views
    closer = LoopCloser(LoopConfig(temporal_window=2, neighbours=1), vocabulary, seed=0)
    gt = np.stack([views[f][1] for f in LOOP_FRAMES])
    drifted = np.array([DRIFT @ T if f >= 270 else T for f, T in zip(LOOP_FRAMES, gt)])
    for i, f in enumerate(LOOP_FRAMES[:-1]):
        closer.add_keyframe(i, frame_of(views, intr, f))
        event, _ = closer.close(i, drifted[: i + 1], frame_of(views, intr, f))
        assert event is None or event.loop_ids, "only the end of the loop may close it"
    last = len(LOOP_FRAMES) - 1
    closer.add_keyframe(last, frame_of(views, intr, LOOP_FRAMES[last]))
    event, corrected = closer.close(last, drifted, frame_of(views, intr, LOOP_FRAMES[last]))
    return event, corrected, drifted, gt


def test_the_drifted_end_is_put_back_on_the_ground_truth(closed):
    event, corrected, _, gt = closed
    assert event is not None and event.applied, event
    assert all(LOOP_FRAMES[i] <= 40 for i in event.loop_ids)
    err_m, err_deg = pose_error(corrected[-1], gt[-1])
    # the drift was 25 cm and 4 degrees; the fit through the start's depth removes it to about 1 cm
    assert err_m < 0.015 and err_deg < 0.3, (err_m, err_deg)
    drift_cm = 100 * pose_error(DRIFT @ gt[-1], gt[-1])[0]
    assert abs(event.correction_cm - drift_cm) < 1.5
    assert event.rms_px < event.rms_px_start


def test_keyframes_up_to_the_loop_start_keep_their_poses(closed):
    event, corrected, drifted, _ = closed
    start = event.start_id
    np.testing.assert_array_equal(corrected[: start + 1], drifted[: start + 1])
    # the end's neighbours (frames 270, 280) carried the same drift: they come back most of the way
    for i in (7, 8):
        before, _ = pose_error(drifted[i], closed[3][i])
        after, _ = pose_error(corrected[i], closed[3][i])
        assert after < 0.5 * before, (i, before, after)


def test_a_small_correction_is_detected_but_not_applied(vocabulary, loop_views):
    views, intr = loop_views
    closer = LoopCloser(LoopConfig(temporal_window=2, neighbours=1), vocabulary, seed=0)
    gt = np.stack([views[f][1] for f in LOOP_FRAMES])  # no drift at all
    for i, f in enumerate(LOOP_FRAMES):
        closer.add_keyframe(i, frame_of(views, intr, f))
    event, corrected = closer.close(len(LOOP_FRAMES) - 1, gt, frame_of(views, intr, LOOP_FRAMES[-1]))
    assert event is not None and not event.applied and corrected is None
    assert "nothing to correct" in event.reason
    assert event.correction_cm < 1.0


def test_keyframes_are_registered_against_the_ones_before_them(vocabulary, loop_views):
    """Frames 150, 160, 270, 280 as keyframes 0-3, keyframe 3 handed over 3 cm and 1 degree off its
    true place relative to keyframe 2 (what a tracking error looks like). Its depth registered against
    keyframe 2 gives the true relative pose (0.5 mm and 0.01 degree off when written; bound 3 mm and 0.1
    degree), and so does 160 against 150. Frames 150/160 and 270/280 see different parts of the loop:
    no registration joins them."""
    views, intr = loop_views
    frames = (150, 160, 270, 280)
    gt = np.stack([views[f][1] for f in frames])
    handed = gt.copy()
    handed[3] = gt[3] @ make_pose(Rotation.from_euler("y", 1.0, degrees=True).as_matrix(), [0.02, 0.0, 0.02])
    closer = LoopCloser(LoopConfig(temporal_window=2, neighbours=1), vocabulary, seed=0)
    for i, f in enumerate(frames):
        closer.add_keyframe(i, frame_of(views, intr, f))
        closer.close(i, handed[: i + 1], frame_of(views, intr, f))
    assert set(closer.registrations) == {(0, 1), (2, 3)}, sorted(closer.registrations)
    for (i, j), Z in closer.registrations.items():
        err_m, err_deg = pose_error(Z, invert(gt[i]) @ gt[j])
        assert err_m < 0.003 and err_deg < 0.1, ((i, j), err_m, err_deg)
    assert pose_error(invert(handed[2]) @ handed[3], invert(gt[2]) @ gt[3])[0] > 0.025  # what tracking said


def test_no_registration_edges_when_switched_off(vocabulary, loop_views):
    views, intr = loop_views
    closer = LoopCloser(LoopConfig(temporal_window=2, neighbours=1, register_neighbours=0), vocabulary, seed=0)
    gt = np.stack([views[f][1] for f in (270, 280)])
    for i, f in enumerate((270, 280)):
        closer.add_keyframe(i, frame_of(views, intr, f))
        closer.close(i, gt[: i + 1], frame_of(views, intr, f))
    assert closer.registrations == {}


def test_kept_depth_maps_read_back_in_tenths_of_millimetres(vocabulary):
    from neb_slam_core.loop.closer import DEPTH_UNIT_M
    from neb_slam_core.types import Intrinsics

    k = Intrinsics(40.0, 40.0, 15.5, 11.5, 32, 24)
    rng = np.random.default_rng(2)
    units = rng.integers(1, 20000, (24, 32))
    depth = (units / 5000.0).astype(np.float32)  # TUM depth: PNG value / 5000
    depth[0, 0], depth[2, 2], depth[4, 4] = 0.0, 14.0, np.nan  # no reading; beyond 13.1 m; not finite
    frame = RgbdFrame(rng.integers(0, 256, (24, 32, 3), dtype=np.uint8), depth, k, 0)
    closer = LoopCloser(LoopConfig(depth_stride=2), vocabulary, seed=0)
    closer.add_keyframe(0, frame)
    T = make_pose(np.eye(3), [1.0, 2.0, 3.0])
    view = closer.view(0, T)
    np.testing.assert_array_equal(view.T_world_cam, T)
    assert view.depth_m.shape == (12, 16) and view.intrinsics.fx == 20.0 and view.intrinsics.cx == 7.75
    expected = units[::2, ::2] * np.float32(DEPTH_UNIT_M)
    expected[0, 0] = expected[1, 1] = expected[2, 2] = 0.0
    np.testing.assert_allclose(view.depth_m, expected, rtol=1e-6)


def test_a_correction_that_is_not_rigid_is_not_applied(vocabulary, loop_views, monkeypatch):
    """The pose graph's output is checked before it goes out: poses that are not rigid motions (a
    numerical failure) leave the loop detected but not applied."""
    import neb_slam_core.loop.closer as closer_module

    real = closer_module.propagate_correction

    def broken(*args, **kwargs):
        poses = real(*args, **kwargs)
        poses[-1, :3, :3] *= 1e3
        return poses

    monkeypatch.setattr(closer_module, "propagate_correction", broken)
    views, intr = loop_views
    closer = LoopCloser(LoopConfig(temporal_window=2, neighbours=1), vocabulary, seed=0)
    gt = np.stack([views[f][1] for f in LOOP_FRAMES])
    drifted = np.array([DRIFT @ T if f >= 270 else T for f, T in zip(LOOP_FRAMES, gt)])
    for i, f in enumerate(LOOP_FRAMES):
        closer.add_keyframe(i, frame_of(views, intr, f))
    event, corrected = closer.close(len(LOOP_FRAMES) - 1, drifted, frame_of(views, intr, LOOP_FRAMES[-1]))
    assert event is not None and not event.applied and corrected is None
    assert event.reason == "the corrected poses are not rigid motions"
