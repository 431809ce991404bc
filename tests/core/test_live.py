"""The concurrent engine's parts: the motion scaled to a stamp, which frame an engine that fell behind
tracks next, the stamp-based constant-velocity prediction, and ``LiveSlam`` end to end on the ``small``
synthetic scene (every frame handed in, mapping and loop closure in a child process or in threads)."""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from neb_slam_core.config_io import load_config
from neb_slam_core.datasets import open_dataset
from neb_slam_core.eval.trajectory_metrics import evaluate_ate
from neb_slam_core.geometry.se3 import make_pose
from neb_slam_core.io.trajectory import Trajectory
from neb_slam_core.live import LiveSlam
from neb_slam_core.slam import Frontend, Slam, _FramePose, choose_frame, new_block_map, scale_motion


def screw(angle_rad: float, along_m: float) -> np.ndarray:
    """A rotation about z by ``angle_rad`` with a translation of ``along_m`` along z (a screw about z)."""
    return make_pose(Rotation.from_rotvec([0.0, 0.0, angle_rad]).as_matrix(), [0.0, 0.0, along_m])


def test_scale_motion_follows_the_screw():
    d = screw(0.4, 0.1)
    # a screw about z scales in angle and pitch together: half the angle, half the advance
    assert np.allclose(scale_motion(d, 0.5), screw(0.2, 0.05), atol=1e-12)
    assert np.allclose(scale_motion(d, 2.0), d @ d, atol=1e-12)
    assert np.allclose(scale_motion(d, 0.0), np.eye(4), atol=1e-12)
    assert np.array_equal(scale_motion(d, 1.0), d)
    # a general rigid motion: two halves make the whole
    g = make_pose(Rotation.from_rotvec([0.1, -0.2, 0.05]).as_matrix(), [0.3, -0.1, 0.2])
    half = scale_motion(g, 0.5)
    assert np.allclose(half @ half, g, atol=1e-12)


def test_choose_frame_newest_within_the_gap():
    ms = 1_000_000
    stamps = [100 * ms, 200 * ms, 300 * ms, 400 * ms]
    assert choose_frame(stamps, None, 0.2) == 3  # nothing tracked yet: the newest
    assert choose_frame(stamps, 50 * ms, 0.0) == 3  # no gap limit: the newest
    assert choose_frame(stamps, 50 * ms, 0.2) == 1  # 50 + 200 ms: 200 is the newest within
    assert choose_frame(stamps, 50 * ms, 0.25) == 2  # 300 ms lies exactly at the gap: still within
    assert choose_frame(stamps, 50 * ms, 1.0) == 3
    assert choose_frame(stamps, 0, 0.05) == 0  # all further: the oldest, the smallest step
    assert choose_frame(stamps, 50 * ms, 1.0, has_velocity=False) == 0  # no velocity: the next frame
    with pytest.raises(ValueError, match="no frame"):
        choose_frame([], 0, 0.1)


def test_predict_from_stamps_scales_the_last_tracked_motion():
    cfg = load_config(
        "ci", overrides=["tracking.motion_model=stamps", "tracking.max_extrapolation=4.0", "live.max_gap_s=0.3"]
    )
    fe = Frontend(cfg, new_block_map(cfg), np.eye(4))
    step = screw(0.02, 0.01)  # the motion between the last two tracked frames, 100 ms apart
    ms = 1_000_000
    fe.keyframe_poses = [np.eye(4)]
    fe._frames = [_FramePose(0, 0, np.eye(4)), _FramePose(100 * ms, 0, step), _FramePose(200 * ms, 0, step)]
    fe._tracked = [0, 1]  # frame 2 failed: it kept the prediction and does not count
    # 250 ms after frame 1: 2.5 times the last tracked motion ahead of it
    assert np.allclose(fe.predict(350 * ms), step @ screw(0.05, 0.025), atol=1e-9)
    # capped at max_extrapolation times that motion
    assert np.allclose(fe.predict(1100 * ms), step @ screw(0.08, 0.04), atol=1e-9)
    assert fe.last_tracked_stamp_ns == 100 * ms
    # the next step counts from the last frame processed (200 ms, failed), not from the last tracked one
    # (100 ms): the newest frame up to 500 ms
    assert fe.next_frame([250 * ms, 450 * ms, 500 * ms, 550 * ms]) == 2
    # the paper's model predicts from the last two frames by count and only after two tracked frames
    paper = Frontend(load_config("ci"), new_block_map(cfg), np.eye(4))
    paper.keyframe_poses, paper._frames, paper._ok_streak = fe.keyframe_poses, fe._frames, 0
    assert np.allclose(paper.predict(350 * ms), step)  # after a failure: the previous pose


def test_the_motion_prior_comes_with_the_velocity_and_grows_with_the_frame_gap():
    """``tracking.motion_prior_m_s2`` 2: with the last two tracked frames 100 ms apart, a frame 100 ms
    later gets a prior of ``a dt (dt + dt_prev) / 2 = 2 * 0.1 * 0.2 / 2 = 0.02`` m, one 200 ms later (a
    frame dropped) ``2 * 0.2 * 0.3 / 2 = 0.06`` m. Without two tracked frames there is no velocity and no
    prior, in either motion model."""
    ms = 1_000_000
    step = screw(0.02, 0.01)
    for model in ("frames", "stamps"):
        cfg = load_config("ci", overrides=[f"tracking.motion_model={model}", "tracking.motion_prior_m_s2=2.0"])
        fe = Frontend(cfg, new_block_map(cfg), np.eye(4))
        fe.keyframe_poses = [np.eye(4)]
        fe._frames, fe._tracked, fe._ok_streak = [_FramePose(0, 0, np.eye(4))], [0], 1
        assert fe._motion_prior(fe.predict(100 * ms), 100 * ms) is None
        fe._frames.append(_FramePose(100 * ms, 0, step))
        fe._tracked, fe._ok_streak = [0, 1], 2
        prior = fe._motion_prior(fe.predict(200 * ms), 200 * ms)
        np.testing.assert_array_equal(prior.T_world_cam, fe.predict(200 * ms))
        np.testing.assert_allclose(np.diag(prior.information), [1 / 0.02**2] * 3 + [0, 0, 0], rtol=1e-9)
        later = fe._motion_prior(fe.predict(300 * ms), 300 * ms)
        np.testing.assert_allclose(np.diag(later.information)[:3], 1 / 0.06**2, rtol=1e-9)
        fe._tracked, fe._ok_streak = [1], 0  # a failure since: the velocity is forgotten
        assert fe._motion_prior(fe.predict(300 * ms), 300 * ms) is None


def test_the_frontend_fuses_each_prediction_with_a_velocity(small_scene, monkeypatch):
    """Frame 1 (one tracked frame before it) is tracked without a prior; from frame 2 on each tracked
    pose is fused with the prior of the prediction it was tracked from."""
    import neb_slam_core.slam as slam_module

    seen = []
    real_fuse = slam_module.fuse

    def spy(tracked, prior):
        seen.append(prior)
        return real_fuse(tracked, prior)

    monkeypatch.setattr(slam_module, "fuse", spy)
    cfg = load_config("ci", overrides=["tracking.motion_prior_m_s2=2.0"])
    ds = open_dataset(small_scene)
    slam = Slam(cfg, T_world_first=ds[0].T_world_cam)
    predictions = []
    for k in range(4):
        if k >= 1:
            predictions.append(slam.frontend.predict(ds[k].stamp_ns))
        slam.process(ds[k])
    assert seen[0] is None
    for prior, T_pred in zip(seen[1:], predictions[1:], strict=True):
        np.testing.assert_array_equal(prior.T_world_cam, T_pred)
        assert prior.information[0, 0] > 0


def test_a_fast_turn_shortens_the_gap_to_max_turn_deg():
    ms = 1_000_000
    stamps = [(200 + 10 * k) * ms for k in range(1, 31)]  # frames every 10 ms after the last processed one
    for turned_deg, expected_gap_ms in ((1.0, 300), (4.0, 75), (30.0, 10)):
        cfg = load_config("ci", overrides=["tracking.motion_model=stamps", "live.max_gap_s=0.3", "live.max_turn_deg=3"])
        fe = Frontend(cfg, new_block_map(cfg), np.eye(4))
        turn = screw(np.radians(turned_deg), 0.01)
        fe.keyframe_poses = [np.eye(4)]
        fe._frames = [_FramePose(100 * ms, 0, np.eye(4)), _FramePose(200 * ms, 0, turn)]
        fe._tracked = [0, 1]
        # 3 degrees at the rate of the last 100 ms: 300 ms (max_gap_s bounds it) at 1 degree, 75 ms at
        # 4 degrees, 10 ms at 30; the newest frame within that gap of the last one (200 ms)
        assert fe.next_frame(stamps) == expected_gap_ms // 10 - 1, turned_deg
    # off (0): max_gap_s alone
    cfg = load_config("ci", overrides=["tracking.motion_model=stamps", "live.max_gap_s=0.3"])
    fe = Frontend(cfg, new_block_map(cfg), np.eye(4))
    fe.keyframe_poses, fe._frames, fe._tracked = (
        [np.eye(4)],
        [_FramePose(100 * ms, 0, np.eye(4)), _FramePose(200 * ms, 0, turn)],
        [0, 1],
    )
    assert fe.next_frame(stamps) == 29


def test_after_a_short_interval_the_gap_grows_at_most_max_gap_growth_times():
    ms = 1_000_000
    stamps = [(200 + 10 * k) * ms for k in range(1, 31)]  # frames every 10 ms after the last processed one
    for interval_ms, growth, expected_gap_ms in ((30, 2.0, 60), (100, 2.0, 200), (30, 0.0, 300), (200, 2.0, 300)):
        cfg = load_config(
            "ci",
            overrides=[
                "tracking.motion_model=stamps",
                "live.max_gap_s=0.3",
                "live.max_turn_deg=3",
                f"live.max_gap_growth={growth}",
            ],
        )
        fe = Frontend(cfg, new_block_map(cfg), np.eye(4))
        fe.keyframe_poses = [np.eye(4)]
        # a slow turn (0.1 degrees), which alone would allow max_gap_s (3 degrees take seconds)
        slow = screw(np.radians(0.1), 0.001)
        fe._frames = [_FramePose((200 - interval_ms) * ms, 0, np.eye(4)), _FramePose(200 * ms, 0, slow)]
        fe._tracked = [0, 1]
        # twice the last interval: 60 ms after 30, 200 after 100; off (0) or beyond max_gap_s: 300 ms
        assert fe.next_frame(stamps) == expected_gap_ms // 10 - 1, (interval_ms, growth)


@pytest.fixture(scope="module")
def frames(small_scene):
    ds = open_dataset(small_scene)
    return [ds[i] for i in range(30)]


@pytest.mark.parametrize("process", [True, False], ids=["mapping-process", "mapping-threads"])
def test_live_slam_tracks_and_integrates_every_keyframe(frames, process):
    """Through the mapping side (in a child process, or in threads), but each frame waits for the map
    updates of the keyframes before it and the first map is fitted in full before the second frame: the
    hand-over of keyframes, map updates and poses then reproduces the lockstep engine's accuracy, and the
    tracker's copy of the map ends equal to the mapper's (the live schedule itself depends on the
    machine's speed; the ROS live test runs it)."""
    cfg = load_config(
        "ci", overrides=["live.torch_threads=1", "live.first_iterations=200", f"live.mapping_process={process}"]
    )
    assert cfg.mapping.first_iterations == 200
    threads = torch.get_num_threads()
    slam = LiveSlam(cfg, frames[0].T_world_cam)
    assert torch.get_num_threads() == 1 or threads == 1
    results = []
    try:
        for f in frames:
            results.append(slam.process(f))
            assert slam.wait_integrated(timeout_s=120.0)
    finally:
        slam.close()
    assert torch.get_num_threads() == threads  # the caller's thread count is given back
    assert slam.errors == []
    assert all(r.tracking_ok for r in results)
    # every keyframe the tracker made reached the mapper, and its final poses came back
    assert len(slam.keyframes) == len(slam.frontend.keyframe_poses) > 1
    assert slam.stats.mapping_lag == 0 and slam.stats.mapping_steps == len(slam.keyframes)
    assert slam.stats.background_chunks == 0  # the first map was fitted in full: nothing left to refine
    assert np.allclose(np.stack(slam.frontend.keyframe_poses), slam.keyframes.poses())
    # the mesh culling's points are the mapper's keyframes' kept pixels
    n_points = sum(len(slam.keyframes.observed_points(kf)) for kf in slam.keyframes.keyframes)
    assert slam.observed_points().shape == (n_points, 3) and n_points > 0
    # the map updates carried every change: the tracker's map is the mapper's
    tracked, final = slam.frontend.block_map, slam.block_map
    assert len(tracked) == len(final) > 0 and set(slam.block_revisions) == set(range(len(final)))
    for a, b in zip(tracked.blocks, final.blocks):
        assert torch.equal(a.grid.table, b.grid.table) and torch.equal(a.observed, b.observed)
    assert torch.equal(
        torch.nn.utils.parameters_to_vector(tracked.decoders.parameters()),
        torch.nn.utils.parameters_to_vector(final.decoders.parameters()),
    )
    gt = Trajectory.of_frames(frames)
    est = slam.trajectory()
    assert np.array_equal(est.stamps_ns, gt.stamps_ns)
    assert np.allclose(est.poses[0], frames[0].T_world_cam, atol=1e-6)
    # the same frames through the lockstep engine
    lockstep = Slam(cfg, frames[0].T_world_cam)
    for f in frames:
        lockstep.process(f)
    ate_live = 100 * evaluate_ate(est, gt).rmse_m
    ate_lockstep = 100 * evaluate_ate(lockstep.trajectory(), gt).rmse_m
    assert ate_lockstep < 1.0, ate_lockstep
    assert abs(ate_live - ate_lockstep) < 0.2, (ate_live, ate_lockstep)


def test_keyframes_follow_the_stamps_when_every_s_is_set(frames):
    """With the frame counts out of reach (every 100th), ``keyframes.every_s`` 0.09 s at the scene's 30 Hz
    makes every third frame (0.1 s apart; two frames are 0.067 s) a keyframe, and the map is optimised
    after each."""
    stamps = np.array([f.stamp_ns for f in frames[:10]])
    assert np.allclose(np.diff(stamps), 1e9 / 30, atol=1e6)
    cfg = load_config(
        "ci", overrides=["keyframes.every=100", "mapping.every=100", "keyframes.every_s=0.09", "loop.enabled=false"]
    )
    slam = Slam(cfg, frames[0].T_world_cam)
    results = [slam.process(f) for f in frames[:10]]
    assert all(r.tracking_ok for r in results)
    by_time = [r.frame_index for r in results if r.is_keyframe and r.new_block_id is None]
    assert by_time == [3, 6, 9], [(r.frame_index, r.is_keyframe, r.new_block_id) for r in results]
    assert all(r.mapped for r in results if r.is_keyframe)


def test_background_refinement_advances_with_every_mapping_step(frames):
    """Every frame a keyframe and none waiting for the mapper, so that keyframes are always queued: the rest
    of the first map (170 of the ci budget's 200 steps, in 17 chunks of 10) still advances by one chunk with
    each mapping step, whatever the machine's speed, instead of waiting for a moment without keyframes."""
    cfg = load_config(
        "ci",
        overrides=[
            "live.torch_threads=1",
            "live.first_iterations=30",
            "live.chunk_iterations=10",
            "keyframes.every=1",
            "loop.enabled=false",
        ],
    )
    chunks_needed = (cfg.mapping.first_iterations - cfg.live.first_iterations) // cfg.live.chunk_iterations
    assert chunks_needed == 17
    slam = LiveSlam(cfg, frames[0].T_world_cam)
    try:
        results = [slam.process(f) for f in frames[:12]]
        assert slam.wait_integrated(timeout_s=120.0)
    finally:
        slam.close()
    assert slam.errors == [] and all(r.tracking_ok for r in results)
    steps, chunks = slam.stats.mapping_steps, slam.stats.background_chunks
    assert steps >= 2 and chunks >= min(steps, chunks_needed), (steps, chunks)


def test_a_mapping_process_that_dies_is_reported_not_waited_for(frames):
    """The mapping process killed under the engine: the tracker's next frame fails with a message naming it,
    nothing waits for it forever, and close() says the same."""
    cfg = load_config("ci", overrides=["live.first_iterations=5", "loop.enabled=false"])
    assert cfg.live.mapping_process
    slam = LiveSlam(cfg, frames[0].T_world_cam)
    slam.process(frames[0])
    assert slam.wait_integrated(timeout_s=120.0)
    slam._mapping._process.kill()
    deadline = time.monotonic() + 60.0
    while not slam.errors and time.monotonic() < deadline:
        time.sleep(0.05)
    assert slam.errors and "mapping process ended" in slam.errors[0]
    assert not slam.wait_integrated(timeout_s=1.0)
    with pytest.raises(RuntimeError, match="mapping process ended"):
        slam.process(frames[1])
    with pytest.raises(RuntimeError, match="mapping process"):
        slam.close(timeout_s=10.0)
    assert slam.n_frames == 1 and len(slam.trajectory()) == 1


def test_the_mapping_process_outlives_ctrl_c_and_sigterm(frames):
    """Ctrl-C (SIGINT to the terminal's process group) and a service manager's SIGTERM reach the mapping
    process too: it ignores them, so the engine still finishes its keyframes and hands over the final map."""
    cfg = load_config("ci", overrides=["live.first_iterations=5", "loop.enabled=false"])
    slam = LiveSlam(cfg, frames[0].T_world_cam)
    child = slam._mapping._process
    for sig in (signal.SIGINT, signal.SIGTERM):
        os.kill(child.pid, sig)
    for f in frames[:3]:
        slam.process(f)
    assert slam.wait_integrated(timeout_s=120.0) and child.is_alive()
    slam.close()
    assert slam.errors == [] and len(slam.keyframes) == len(slam.frontend.keyframe_poses) >= 1
    assert len(slam.block_map) >= 1 and child.exitcode == 0


def test_a_mapping_side_without_loop_thread_takes_outside_corrections(frames):
    """The ROS mapper's arrangement: a mapping side with no loop thread of its own. Each update acknowledges
    the newest keyframe it integrated; the first map goes back after the handoff's ``first_iterations``
    (the rest follows in background chunks); a correction from outside moves its keyframe at once (the
    keyframes after it rigidly with it, as ``merge_correction`` says) and the update that carries the move
    names the correction's stamp, before any re-optimisation step changed the poses again."""
    from neb_slam_core.live_mapping import Handoff, MappingSide
    from neb_slam_core.loop.correction import merge_correction

    cfg = load_config(
        "ci",
        overrides=[
            "mapping.first_iterations=25",
            "live.chunk_iterations=10",
            "loop.map_iterations=10",
            "loop.joint_iterations=10",
        ],
    )
    assert cfg.loop.enabled  # the loop thread is absent because of closes_loops, not of the config
    cond, messages = threading.Condition(), []

    def emit(kind, payload):
        with cond:
            messages.append((kind, payload))
            cond.notify_all()

    def updates():
        return [p for k, p in messages if k == "update"]

    def wait(predicate):
        with cond:
            assert cond.wait_for(predicate, timeout=120.0), messages[-3:]

    torch.manual_seed(cfg.seed)
    block_map = new_block_map(cfg)
    side = MappingSide(cfg, block_map, emit, closes_loops=False)
    chosen = [frames[i] for i in (0, 3, 6, 9)]
    try:
        assert side.loop_closer is None
        centres = np.round(chosen[0].T_world_cam[:3, 3][None], 0)  # one block, made by the tracker
        for kid, f in enumerate(chosen):
            side.submit(Handoff(f, f.T_world_cam, 3 * kid, kid, True, kid == 0, centres, np.zeros((0, 4, 4)), 5))
            if kid == 0:
                wait(lambda: updates())
                first = updates()[0]
                assert first.ack_stamp_ns == chosen[0].stamp_ns and first.loop_stamp_ns == -1
                assert first.block_ids == [0] and len(first.keyframe_poses) == 1
        wait(lambda: any(u.ack_stamp_ns == chosen[-1].stamp_ns for u in updates()))
        with cond:
            before = updates()[-1].keyframe_poses.copy()
        assert len(before) == 4
        shift = make_pose(np.eye(3), [0.01, 0.0, 0.0])
        by_id = np.zeros((3, 4, 4))
        by_id[2] = shift @ before[2]
        side.correct(2, 1, by_id, stamp_ns=777)
        wait(lambda: any(u.loop_stamp_ns == 777 for u in updates()))
        moved = next(u for u in updates() if u.loop_stamp_ns == 777).keyframe_poses
        np.testing.assert_allclose(moved, merge_correction(before, 2, by_id[2:3]), atol=1e-12)
        np.testing.assert_allclose(moved[3], shift @ before[3], atol=1e-9)
        # the first map's rest (20 steps: 2 chunks) and the loop's 10 + 10 steps (2 chunks) in the background
        wait(lambda: side.progress.background_chunks == 4)
    finally:
        side.close(120.0)
    assert [k for k, _ in messages if k not in ("update", "progress")] == []
    assert side.progress.checked == 0 and side.progress.integrated == 4


def test_a_failed_loop_check_skips_its_keyframe_and_loop_closure_goes_on(frames, monkeypatch):
    """A loop check that raises (a numerical failure on one keyframe) is logged and skipped: the mapping
    side reports no error, and the next keyframes are checked again."""
    from neb_slam_core.loop.closer import LoopCloser

    original, calls = LoopCloser.close, []

    def close(self, keyframe_id, poses, frame):
        calls.append(keyframe_id)
        if keyframe_id == 1:
            raise ValueError("not a rotation")
        return original(self, keyframe_id, poses, frame)

    monkeypatch.setattr(LoopCloser, "close", close)
    cfg = load_config("ci", overrides=["live.mapping_process=false", "live.first_iterations=20"])
    slam = LiveSlam(cfg, frames[0].T_world_cam)
    try:
        for f in frames:
            slam.process(f)
            assert slam.wait_integrated(timeout_s=120.0)
    finally:
        slam.close()
    assert slam.errors == []
    n = len(slam.frontend.keyframe_poses)
    assert n > 2 and calls == list(range(n))
