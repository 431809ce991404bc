"""Loop detector: the paper's query rule and the geometric check, on a small synthetic loop and on TUM."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from loop_scene import FRAME_NS, LOOP_FRAMES, pose_error

from neb_slam_core.config import LoopConfig
from neb_slam_core.geometry.se3 import invert, make_pose
from neb_slam_core.loop.detector import LoopDetector, backproject, keypoint_depths, match_descriptors
from neb_slam_core.loop.vocabulary import l1_score
from neb_slam_core.types import Intrinsics


@pytest.fixture(scope="module")
def loop_detector(vocabulary, loop_views):
    views, intr = loop_views
    cfg = LoopConfig(temporal_window=2, neighbours=1)
    det = LoopDetector(cfg, vocabulary)
    for i, f in enumerate(LOOP_FRAMES):
        det.add_keyframe(i, f * FRAME_NS, views[f][0].rgb, views[f][0].depth_m, intr)
    return det


def test_a_keyframe_matched_to_itself_scores_one(loop_detector):
    kf = loop_detector.keyframe(3)
    assert len(kf.features) > 200 and len(kf.bow) > 100
    assert l1_score(kf.bow, kf.bow) == pytest.approx(1.0)
    assert loop_detector.database.query(kf.bow).keyframe_ids[0] == 3


def test_the_end_of_the_loop_finds_its_start_with_the_right_relative_pose(loop_detector, loop_views):
    views, _ = loop_views
    q = loop_detector.query(len(LOOP_FRAMES) - 1)  # frame 290, next to frame 0 again
    assert q.detection is not None
    loop_ids = [c.keyframe_id for c in q.detection.loop_keyframes]
    assert 1 <= len(loop_ids) <= 2 and all(LOOP_FRAMES[i] <= 40 for i in loop_ids)
    for c in q.detection.loop_keyframes:
        T_gt = invert(views[LOOP_FRAMES[c.keyframe_id]][1]) @ views[290][1]
        err_m, err_deg = pose_error(c.T_cand_query, T_gt)
        assert err_m < 0.05 and err_deg < 2.0, (c.keyframe_id, err_m, err_deg)
        assert c.n_inliers >= loop_detector.cfg.min_inliers and c.score >= q.threshold


def test_the_papers_rule_threshold_window_and_choice_of_two(loop_detector):
    det, n = loop_detector, len(LOOP_FRAMES)
    n_pairs = 0
    for p in range(n):
        q = det.query(p)
        # threshold: the lowest similarity to the nearest keyframe on each side (neighbours = 1)
        kf = det.keyframe(p)
        side = [det.keyframe(i).bow for i in (p - 1, p + 1) if 0 <= i < n]
        assert q.threshold == pytest.approx(min(l1_score(kf.bow, b) for b in side))
        # candidates: never within the temporal window (2), best first, at most top_k
        assert all(abs(int(c) - p) > 2 for c in q.candidate_ids)
        assert len(q.candidate_ids) <= det.cfg.top_k and np.all(np.diff(q.candidate_scores) <= 0)
        # checked: exactly the candidates at or above the threshold
        assert [c for c, _ in q.checks] == [
            int(c) for c, s in zip(q.candidate_ids, q.candidate_scores) if s >= q.threshold
        ]
        verified = [c for c, check in q.checks if check.accepted]
        if q.detection is None:
            assert not verified
            continue
        r = q.detection.loop_keyframes
        assert r[0].keyframe_id == verified[0]  # r1: the highest score
        if len(verified) > 1:  # r2: the largest time gap of the others
            gaps = {c: abs(det.keyframe(c).stamp_ns - kf.stamp_ns) for c in verified[1:]}
            assert len(r) == 2 and gaps[r[1].keyframe_id] == max(gaps.values())
            n_pairs += 1
    assert n_pairs >= 1  # the rule for r2 was exercised (frame 270: r1 = frame 0, r2 = frame 10)


def test_the_first_keyframe_has_no_neighbour_and_no_query(vocabulary, loop_views):
    views, intr = loop_views
    det = LoopDetector(LoopConfig(), vocabulary)
    det.add_keyframe(7, 0, views[0][0].rgb, views[0][0].depth_m, intr)
    q = det.query(7)
    assert np.isnan(q.threshold) and q.detection is None and len(q.candidate_ids) == 0


def test_the_geometric_check_rejects_a_pair_that_does_not_overlap(loop_detector):
    start, far = loop_detector.keyframe(0), loop_detector.keyframe(LOOP_FRAMES.index(150))
    check = loop_detector.verify(far, start)
    assert not check.accepted and check.n_inliers < loop_detector.cfg.min_inliers and check.reason


def test_the_geometric_check_rejects_a_look_alike_with_wrong_geometry(loop_detector):
    """The same image over a world 0.6 times as deep (like a photograph of the place): the BoW score is
    1 and the pixels match perfectly, but no rigid motion explains both depths."""
    kf = loop_detector.keyframe(0)
    fake = replace(kf, keyframe_id=99, keypoint_depth_m=0.6 * kf.keypoint_depth_m)
    assert l1_score(kf.bow, fake.bow) == pytest.approx(1.0)
    assert not loop_detector.verify(kf, fake).accepted
    assert loop_detector.verify(kf, kf).accepted  # the unscrambled one passes


def test_keypoint_depths_drop_edges_and_holes():
    depth = np.full((10, 10), 2.0, np.float32)
    depth[:, 6:] = 4.0  # an occlusion edge between columns 5 and 6
    depth[8, 1] = 0.0  # a hole
    kp = np.array([[2.0, 2.0], [5.0, 5.0], [8.0, 5.0], [1.0, 7.0], [2.4, 3.6]], np.float32)
    assert keypoint_depths(depth, kp).tolist() == [2.0, 0.0, 4.0, 0.0, 2.0]


def test_backproject_and_match_descriptors_by_hand():
    k = Intrinsics(100.0, 100.0, 50.0, 40.0, 100, 80)
    pts = backproject(np.array([[50.0, 40.0], [150.0, 40.0]]), np.array([2.0, 1.0]), k)
    assert pts.tolist() == [[0.0, 0.0, 2.0], [1.0, 0.0, 1.0]]
    train = np.zeros((3, 32), np.uint8)
    train[1, :4] = 0xFF  # 32 bits from train 0
    train[2, :8] = 0xFF  # 64 bits from train 0
    query = train[[1, 0, 2, 0]].copy()
    query[2, 0] ^= 0x01  # 1 bit from train 2, 63 from train 0 -> passes the ratio test
    qi, ti = match_descriptors(query, train, ratio=0.8, max_distance=64)
    # query 3 duplicates query 1 (train 0): only the first (lowest query index) keeps train 0
    assert qi.tolist() == [0, 1, 2] and ti.tolist() == [1, 0, 2]
    qi, _ = match_descriptors(query, train, ratio=0.8, max_distance=0)
    assert qi.tolist() == [0, 1]


@pytest.fixture(scope="module")
def tum_pair(tum_dir, vocabulary):
    """Two rectified TUM fr1_xyz frames 150 apart that see the same desk, a fresh detector, and both
    frames described (not added)."""
    from neb_slam_core.datasets import open_dataset
    from neb_slam_core.geometry.rectify import Rectifier

    ds = open_dataset(tum_dir)
    rect = Rectifier()
    a, b = rect(ds[0]), rect(ds[150])
    det = LoopDetector(LoopConfig(), vocabulary)
    ka = det.describe(0, a.stamp_ns, a.rgb, a.depth_m, a.intrinsics)
    kb = det.describe(1, b.stamp_ns, b.rgb, b.depth_m, b.intrinsics)
    return det, (a, ka), (b, kb)


def test_tum_frames_far_apart_in_time_overlap_and_are_accepted_with_the_true_pose(tum_pair):
    det, (a, ka), (b, kb) = tum_pair
    assert len(ka.features) == det.cfg.n_features
    check = det.verify(kb, ka)
    assert check.accepted, check
    err_m, err_deg = pose_error(check.T_cand_query, invert(a.T_world_cam) @ b.T_world_cam)
    assert err_m < 0.05 and err_deg < 3.0


def test_a_kept_keyframe_holds_its_keypoints_with_depth_and_checks_as_the_whole_one(tum_pair):
    """The detector keeps a keyframe as a candidate: only its keypoints with depth (a candidate's check
    back-projects them), with the bag-of-words vector of all of them. A check against the kept part gives
    the outcome the whole keyframe gives."""
    described_by, (_, whole), (_, query) = tum_pair
    det = LoopDetector(described_by.cfg, described_by.vocabulary)  # the fixture's stays empty
    det.add(whole)
    assert det.keyframe(0) is whole  # the newest is kept whole until its query is done
    det.add(query)
    kept = det.keyframe(0)
    with_depth = whole.keypoint_depth_m > 0
    assert 0 < with_depth.sum() < len(whole.features)  # real depth has holes and edges
    assert len(kept.features) == with_depth.sum() and (kept.keypoint_depth_m > 0).all()
    assert np.array_equal(kept.features.descriptors, whole.features.descriptors[with_depth])
    assert np.array_equal(kept.features.keypoints_px, whole.features.keypoints_px[with_depth])
    assert kept.bow is whole.bow
    on_whole, on_kept = det.verify(query, whole), det.verify(query, kept)
    assert on_whole.accepted and on_kept.accepted
    assert (on_kept.n_matches, on_kept.n_inliers) == (on_whole.n_matches, on_whole.n_inliers)
    assert np.allclose(on_kept.T_cand_query, on_whole.T_cand_query, atol=1e-6)


def test_make_pose_convention_of_the_check(loop_detector):
    # a keyframe checked against itself: identity relative pose
    kf = loop_detector.keyframe(1)
    check = loop_detector.verify(kf, kf)
    assert check.accepted and np.allclose(check.T_cand_query, make_pose(np.eye(3), np.zeros(3)), atol=1e-6)
