"""The node suite end to end over real DDS: separate processes and the one-process ``slam`` replay a small
synthetic bag in lockstep; an independent subscriber process receives pose, path, blocks and mesh; every
frame gets a pose; the trajectory matches the offline engine on the same bag and seed; the mapper's
shutdown files load. Plus: bad input on the camera topics is warned about and skipped, and the tracker
keeps running.

Every process of this file talks on its own random ROS_DOMAIN_ID, on localhost only.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytestmark = [pytest.mark.ros, pytest.mark.filterwarnings("ignore::DeprecationWarning:lark.*")]

REPO = Path(__file__).resolve().parents[2]
N_FRAMES = 8  # frames 0-7: the first keyframe's initialisation, tracking against it, a mapping keyframe at 5
CONFIG = "ci"


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory) -> Path:
    from neb_slam_core.datasets import open_dataset
    from neb_slam_core.io.bag import BagWriteOptions, write_bag
    from neb_slam_core.synth.generate import generate

    root = tmp_path_factory.mktemp("suite")
    ds = open_dataset(generate("small", root / "scene", progress=False))
    bag = root / "bag"
    write_bag([ds[i] for i in range(N_FRAMES)], bag, BagWriteOptions(depth_encoding="32FC1"), progress=False)
    return bag


@pytest.fixture(scope="module")
def offline(small_bag: Path):
    """The one-process engine on the same bag, config and seed: what `neb-slam run` computes."""
    from neb_slam_core.config_io import load_config
    from neb_slam_core.datasets.bag import BagDataset
    from neb_slam_core.slam import Slam

    with BagDataset(small_bag) as ds:
        frames = [ds[i] for i in range(len(ds))]
    slam = Slam(load_config(CONFIG), frames[0].T_world_cam)
    for f in frames:
        slam.process(f)
    return slam.trajectory(), frames, slam


def _ate_cm(traj, frames) -> float:
    from neb_slam_core.eval.trajectory_metrics import evaluate_ate
    from neb_slam_core.io.trajectory import Trajectory

    gt = Trajectory.of_frames(frames)
    return evaluate_ate(traj, gt).rmse_cm


def _run_suite(
    small_bag: Path, out: Path, env: dict[str, str], one_process: bool, mesh_period_s: float = 0.0, **launch_args
):
    from neb_slam_ros.suite import launch

    listener_json = out.parent / f"{out.name}-listener.json"
    listener = subprocess.Popen(
        [sys.executable, str(Path(__file__).with_name("listener.py")), str(listener_json)],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert "listener ready" in listener.stderr.readline()
        # the mesh goes out every mesh_period_s (0: never on a timer) and, whatever the period, once more at
        # shutdown, the node waiting for the listener's acknowledgement
        run = launch(
            small_bag, out, CONFIG, one_process=one_process, mesh_period_s=mesh_period_s, env=env, **launch_args
        )
        time.sleep(2.0)  # the last path and mesh messages reach the listener
    finally:
        listener.send_signal(signal.SIGINT)
        listener.wait(30)
    logs = {k: p.read_text() for k, p in run.logs.items()}
    return run, json.loads(listener_json.read_text()), logs


def _check(run, seen, logs, offline, small_bag: Path) -> None:
    from neb_slam_core.io.trajectory import read_tum_trajectory
    from neb_slam_core.scene.persistence import load_map

    traj_ref, frames = offline[:2]
    assert all(code == 0 for code in run.exit_codes.values()), (run.exit_codes, logs)
    for text in logs.values():
        assert "Traceback" not in text, text
    # every frame of the bag got a pose, in order: the path (transient local: complete for any subscriber)
    # holds them all; the volatile pose topic reaches the listener from the moment DDS discovery has
    # matched it with the node that just started (within the first frames)
    stamps = [f.stamp_ns for f in frames]
    assert seen["path_stamps_ns"] == stamps
    assert seen["path_lengths"] and seen["path_lengths"][-1] == N_FRAMES
    assert (
        len(seen["pose_stamps_ns"]) >= N_FRAMES - 1 and seen["pose_stamps_ns"] == stamps[-len(seen["pose_stamps_ns"]) :]
    )
    assert seen["block_ids"] == list(range(len(seen["block_ids"]))) and len(seen["block_ids"]) >= 1
    assert seen["mesh_markers"] >= 1 and seen["mesh_points"] > 0 and seen["mesh_points"] % 3 == 0
    # the written trajectory is the offline engine's (same bag, config, seed): within 10 % or 0.2 cm of its ATE
    est = read_tum_trajectory(run.run_dir / "trajectory.txt")
    assert est.stamps_ns.tolist() == stamps
    ate_suite, ate_offline = _ate_cm(est, frames), _ate_cm(traj_ref, frames)
    assert abs(ate_suite - ate_offline) <= max(0.1 * ate_offline, 0.2), (ate_suite, ate_offline)
    assert abs(run.metrics["ate_rmse_cm"] - ate_suite) < 1e-3
    # lockstep: every frame tracked, none dropped (the separate tracker's summary line, or the slam's metrics)
    assert run.metrics["frames_dropped"] == 0
    assert run.metrics.get("frames_tracked", run.metrics["n_frames"]) == N_FRAMES
    assert run.metrics["n_tracking_failures"] == 0
    # the shutdown files exist and load
    block_map, extra = load_map(run.run_dir / "map.pt")
    assert len(block_map) == len(seen["block_ids"])
    assert len(extra["keyframe_stamps_ns"]) >= 2
    import trimesh

    mesh = trimesh.load(run.run_dir / "mesh.ply")
    assert len(mesh.faces) > 100
    # the mesh the listener holds at the end is the final one, mesh.ply's (its triangles whose centroid lies in a block)
    assert 0.99 * 3 * len(mesh.faces) <= seen["mesh_points"] <= 3 * len(mesh.faces), (
        seen["mesh_points"],
        len(mesh.faces),
    )
    # the final map_cloud is the final mesh's vertices, kept per block (seams not merged); the final grid
    # covers the blocks with a cell for every 10 cm, some of them seen
    assert len(mesh.vertices) <= seen["map_cloud_points"] <= 3 * len(mesh.faces), seen["map_cloud_points"]
    width, height, unknown, free, occupied, frame = seen["map_grid"]
    assert frame == "map" and width * height == unknown + free + occupied and free + occupied > 0, seen["map_grid"]
    for name in ("groundtruth.txt", "metrics.json", "trajectory.png", "config.yaml"):
        assert (run.run_dir / name).is_file(), name
    # tracking health: the first pose defines the map frame (zero covariance), every tracked one has a
    # positive one, far below the variance of a pose without an estimate; /diagnostics says "tracking"
    from neb_slam_ros.conversions import UNKNOWN_VARIANCE

    odometry = dict((s, d) for s, d in seen["odometry"])
    assert set(odometry) <= set(stamps) and len(odometry) >= N_FRAMES - 1
    for s, diag in odometry.items():
        assert diag == [0.0] * 6 if s == stamps[0] else all(0 < v < 1e-2 * UNKNOWN_VARIANCE for v in diag), diag
    assert seen["diagnostics"] and seen["diagnostics"][-1][:2] == [0, "tracking"], seen["diagnostics"]
    _check_tf(seen, frames)


def _check_tf(seen: dict, frames) -> None:
    """REP-105 on /tf: for every published pose, map -> odom -> base_link at its stamp composed with the
    static base_link -> camera equals it; the map is level: its z axis is the scene's up (the synthetic
    scenes are z-up) within 2 degrees (the suite takes gravity from the first frame's floor)."""
    from neb_slam_core.geometry.se3 import pose_from_tum

    def pose(row) -> np.ndarray:
        return pose_from_tum(np.array(row[-7:], dtype=np.float64))

    assert len(seen["tf_static"]) == 1, seen["tf_static"]
    _, base, camera, *_ = seen["tf_static"][0]
    assert (base, camera) == ("base_link", "camera"), seen["tf_static"]  # camera: the images' frame_id
    T_base_cam = pose(seen["tf_static"][0])
    tf = {(row[0], row[1], row[2]): pose(row) for row in seen["tf"]}
    assert {(parent, child) for _, parent, child in tf} == {("map", "odom"), ("odom", "base_link")}
    assert seen["poses"] and all(row[1] == "map" for row in seen["poses"])
    for row in seen["poses"]:
        s = row[0]
        composed = tf[(s, "map", "odom")] @ tf[(s, "odom", "base_link")] @ T_base_cam
        np.testing.assert_allclose(composed, pose(row), atol=1e-6)
    # the first frame's pose in map against its ground truth in the scene: up in the first camera's frame
    first = {row[0]: pose(row) for row in seen["poses"]}.get(frames[0].stamp_ns)
    if first is None:  # the volatile pose topic may miss the first frame; the path holds it
        first = pose(["", *seen["path_first"]])
    up_map = first[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    up_scene = frames[0].T_world_cam[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    assert np.degrees(np.arccos(np.clip(up_map @ up_scene, -1.0, 1.0))) < 2.0, (up_map, up_scene)


def test_separate_processes_replay_a_bag_like_the_offline_engine(small_bag, offline, ros_env, tmp_path):
    # a period well inside the run (8 frames take several seconds from the nodes' start): timer and final
    # meshes
    run, seen, logs = _run_suite(small_bag, tmp_path / "suite", ros_env, one_process=False, mesh_period_s=2.0)
    _check(run, seen, logs, offline, small_bag)
    # lockstep with map_sync: exactly the one-process computation, to the last bit of the float64 poses
    # (up to the quaternion of the path messages the mapper corrects with)
    from neb_slam_core.io.trajectory import read_tum_trajectory

    est = read_tum_trajectory(run.run_dir / "trajectory.txt")
    np.testing.assert_allclose(est.poses, offline[0].poses, atol=1e-6)
    # the mapper counts what it published: an update per mapping keyframe at least (keyframes 0 and 5),
    # each with the block whole (float32 under ci: 4 bytes per table value)
    from neb_slam_core.config_io import load_config
    from neb_slam_core.scene.hash_grid import hash_grid_param_count

    table_mb = 4e-6 * hash_grid_param_count(load_config(CONFIG).block.grid)
    assert run.metrics["map_updates"] >= 2 and run.metrics["map_update_mb"] >= 2 * table_mb, run.metrics
    assert run.metrics["map_update_mb_per_s"] == pytest.approx(run.metrics["map_update_mb"] / run.replay_s)


def test_one_process_slam_replays_a_bag_like_the_offline_engine(small_bag, offline, ros_env, tmp_path):
    # no timer: the mesh the listener sees is the one published at shutdown
    run, seen, logs = _run_suite(small_bag, tmp_path / "slam", ros_env, one_process=True, mesh_period_s=0.0)
    _check(run, seen, logs, offline, small_bag)
    for name in ("timings.csv", "blocks.png", "ate_over_time.png"):
        assert (run.run_dir / name).is_file(), name


@pytest.mark.parametrize("one_process", [False, True], ids=["separate", "one-process"])
def test_the_suite_continues_a_saved_map(small_bag, offline, ros_env, tmp_path, one_process):
    """A mapper (or slam) with ``map_file`` continues the offline run's map: the replay of frames 4-7
    starts on it (the tracker, with ``wait_for_map``, gets the whole map before its first frame and
    tracks that frame against it) and computes what the offline engine computes on the same map."""
    from neb_slam_core.config_io import load_config
    from neb_slam_core.io.trajectory import read_tum_trajectory
    from neb_slam_core.scene.persistence import save_map
    from neb_slam_core.slam import Slam, load_map_for

    _, frames, made = offline
    map_file = save_map(made.block_map, tmp_path / "map.pt")
    cfg = load_config(CONFIG)
    resumed = Slam(cfg, frames[4].T_world_cam, load_map_for(cfg, map_file))
    results = [resumed.process(f) for f in frames[4:]]
    assert results[0].tracking_ok and results[0].mapped
    run, seen, logs = _run_suite(small_bag, tmp_path / "run", ros_env, one_process, start=4, count=4, map_file=map_file)
    assert all(code == 0 for code in run.exit_codes.values()), (run.exit_codes, logs)
    assert seen["path_stamps_ns"] == [f.stamp_ns for f in frames[4:]]
    est = read_tum_trajectory(run.run_dir / "trajectory.txt")
    np.testing.assert_allclose(est.poses, resumed.trajectory().poses, atol=1e-6)
    assert f"continuing {map_file}" in logs["slam" if one_process else "mapper"]


def test_one_process_slam_killed_half_way_resumes_from_its_checkpoint(small_bag, offline, ros_env, tmp_path):
    """SIGKILL of the slam node once it has written a checkpoint after its first frames; the same command
    again (the replay starts over) resumes from it: the frames done before the checkpoint get their stored
    pose, the rest are processed, and the run directory has a pose for every frame at the uninterrupted
    run's accuracy."""
    from neb_slam_core.io.trajectory import read_tum_trajectory
    from neb_slam_ros.suite import _node_cmd

    _, frames = offline[:2]
    out = tmp_path / "slam"
    params = {
        "config": CONFIG,
        "seed": 0,
        "reliable_inputs": True,
        "ground_truth_topic": "ground_truth/pose",
        "bag": str(small_bag),
        "lockstep": True,
        "rate": 0.0,
        "output_dir": str(out),
        "mesh_period_s": 0.0,
        "live": False,
        "checkpoint_every": 1,
    }
    checkpoint = out / "checkpoint.pt"
    first_log = tmp_path / "first.log"
    first = subprocess.Popen(
        _node_cmd("slam", params), env=ros_env, stdout=first_log.open("w"), stderr=subprocess.STDOUT
    )
    try:
        deadline, seen_ns = time.monotonic() + 300, []
        # the second checkpoint: a keyframe after the first frame
        while len(set(seen_ns)) < 2:
            assert first.poll() is None, first_log.read_text()
            assert time.monotonic() < deadline, "no second checkpoint"
            if checkpoint.is_file():
                seen_ns.append(checkpoint.stat().st_mtime_ns)
            time.sleep(0.01)
        first.kill()
        first.wait()
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    assert not (out / "trajectory.txt").exists()  # killed: only the checkpoint is there
    second = subprocess.run(_node_cmd("slam", params), env=ros_env, capture_output=True, text=True, timeout=600)
    log = second.stdout + second.stderr
    assert second.returncode == 0 and "Traceback" not in log, log
    assert f"resuming {checkpoint} after " in log, log
    est = read_tum_trajectory(out / "trajectory.txt")
    assert est.stamps_ns.tolist() == [f.stamp_ns for f in frames]
    ate_ref = _ate_cm(offline[0], frames)
    assert _ate_cm(est, frames) <= 1.5 * ate_ref, (_ate_cm(est, frames), ate_ref)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["n_frames"] == N_FRAMES and metrics["frames_dropped"] == 0 and metrics["n_tracking_failures"] == 0


def test_the_mapper_killed_half_way_resumes_and_the_tracker_sends_it_the_keyframes_it_lost(
    small_bag, offline, ros_env, tmp_path
):
    """The separate nodes on the small bag, the mapper checkpointing every keyframe. Once the tracker has
    sent keyframe 1 (the mapper's checkpoint holds keyframe 0 only: integrating keyframe 1 takes it
    longer than this test takes to react), SIGKILL, and the same mapper command again. It resumes from
    the checkpoint and gets keyframe 1 again (the keyframe topics keep their last messages for a late
    subscriber; older ones the tracker sends again), the tracker (not restarted) takes the resumed
    mapper's map, and the run directory has a pose for every frame at the uninterrupted run's accuracy."""
    rclpy = pytest.importorskip("rclpy")
    from rclpy.signals import SignalHandlerOptions
    from std_msgs.msg import String

    from neb_slam_core.io.trajectory import read_tum_trajectory
    from neb_slam_ros import qos
    from neb_slam_ros.keyframe_link import KeyframeMeta
    from neb_slam_ros.suite import launch

    _, frames = offline[:2]
    out = tmp_path / "suite"
    checkpoint = out / "checkpoint.pt"
    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
        os.environ[key] = ros_env[key]
    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("kill_the_mapper", namespace="neb_slam", context=context)
    sent: list[int] = []
    node.create_subscription(
        String, "keyframe/meta", lambda m: sent.append(KeyframeMeta.from_json(m.data).keyframe_id), qos.keyframes()
    )
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)

    def kill_and_restart_mapper(procs, start_node):
        deadline = time.monotonic() + 300
        while 1 not in sent:
            assert procs["mapper"].poll() is None, (out / "logs" / "mapper.log").read_text()
            assert time.monotonic() < deadline, f"keyframe 1 was not sent (sent: {sent})"
            executor.spin_once(timeout_sec=0.01)
        procs["mapper"].kill()
        procs["mapper"].wait()
        procs["mapper"] = start_node("mapper")

    try:
        run = launch(
            small_bag, out, CONFIG, env=ros_env, extra_params={"checkpoint_every": 1}, during=kill_and_restart_mapper
        )
    finally:
        node.destroy_node()
        rclpy.shutdown(context=context)
    logs = {k: p.read_text() for k, p in run.logs.items()}
    assert all(code == 0 for code in run.exit_codes.values()), (run.exit_codes, logs)
    assert f"resuming {checkpoint} with 1 keyframes" in logs["mapper"], logs["mapper"]
    assert "the mapper restarted with" in logs["tracker"], logs["tracker"]
    est = read_tum_trajectory(out / "trajectory.txt")
    assert est.stamps_ns.tolist() == [f.stamp_ns for f in frames]
    ate_ref = _ate_cm(offline[0], frames)
    assert _ate_cm(est, frames) <= 1.5 * ate_ref, (_ate_cm(est, frames), ate_ref)
    assert run.metrics["n_keyframes"] == 2
    assert not checkpoint.exists()  # stopped normally: map.pt continues the map


def test_bad_input_is_warned_about_and_skipped_and_the_tracker_keeps_running(ros_env):
    rclpy = pytest.importorskip("rclpy")
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import CameraInfo, Image

    from neb_slam_core.types import Intrinsics
    from neb_slam_ros import conversions

    tracker = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "neb_slam_ros.tracker",
            "--ros-args",
            "-p",
            f"config:={CONFIG}",
            "-p",
            "reliable_inputs:=true",
            "-p",
            "warn_period_s:=0.0",
        ],
        env=ros_env,
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
        os.environ[key] = ros_env[key]
    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("bad_input", namespace="neb_slam", context=context)
    try:
        reliable = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
        pub_rgb = node.create_publisher(Image, "rgb/image", reliable)
        pub_depth = node.create_publisher(Image, "depth/image", reliable)
        pub_info = node.create_publisher(CameraInfo, "rgb/camera_info", reliable)
        deadline = time.monotonic() + 60
        while min(p.get_subscription_count() for p in (pub_rgb, pub_depth, pub_info)) == 0:
            assert time.monotonic() < deadline, "the tracker did not subscribe"
            time.sleep(0.1)

        h, w = 24, 32
        intr = Intrinsics(30.0, 30.0, 16.0, 12.0, w, h)
        rgb = np.full((h, w, 3), 128, np.uint8)
        depth = np.full((h, w), 2.0, np.float32)
        sec = 1_000_000_000

        def send(k: int, rgb_img=rgb, depth_img=depth, rgb_enc=None, depth_stamp=None):
            m = conversions.rgb_msg(rgb_img, k * sec, "camera")
            if rgb_enc is not None:
                m.encoding = rgb_enc
            pub_rgb.publish(m)
            pub_depth.publish(conversions.depth_msg(depth_img, (depth_stamp or k) * sec, "camera"))
            time.sleep(0.3)

        for k in range(1, 5):  # 4 frames before any camera info: 3 are held, the oldest is dropped
            send(k)
        pub_info.publish(conversions.camera_info_msg(intr, None, 4 * sec, "camera"))
        time.sleep(0.5)
        send(5, rgb_enc="rgb16")  # wrong encoding
        send(6, rgb_img=np.zeros((10, 10, 3), np.uint8))  # size differs from camera info
        send(7, depth_img=np.full((h, w), np.nan, np.float32))  # only NaN depth
        send(8, depth_img=np.full((h, w), np.inf, np.float32))  # only Inf depth
        send(9, depth_img=np.zeros((h, w), np.float32))  # only zeros
        half_nan = depth.copy()
        half_nan[:, : w // 2] = np.nan
        send(10, depth_img=half_nan)  # REP 118: NaN = invalid, frame used
        send(10)  # duplicate stamp
        send(3)  # older stamp
        time.sleep(2.0)
        assert tracker.poll() is None, "the tracker died on bad input"
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        if tracker.poll() is None:
            tracker.send_signal(signal.SIGINT)
        out, _ = tracker.communicate(timeout=60)
    assert tracker.returncode == 0, out
    assert "Traceback" not in out, out
    expected = [
        "/neb_slam/depth/image: no camera info received yet on /neb_slam/rgb/camera_info: frame 1000000000 skipped",
        "/neb_slam/rgb/image: colour encoding 'rgb16' is not supported",
        "/neb_slam/rgb/image: image is 10x10 but /neb_slam/rgb/camera_info says 32x24",
        "/neb_slam/depth/image: no valid depth pixel (all 0, NaN, Inf or negative): frame 7000000000 skipped",
        "frame 8000000000 skipped",
        "frame 9000000000 skipped",
        "/neb_slam/depth/image: 384 depth pixels NaN or Inf in frame 10000000000: read as invalid (REP 118)",
        "is a duplicate of the last frame's",
        "is older than the last frame's",
    ]
    for text in expected:
        assert text in out, f"missing warning {text!r} in:\n{out}"
    # frames 2, 3, 4 (held for the camera info) and 10 were accepted: the summary line counts them
    assert "tracker stopped" in out


def test_a_failed_frame_shows_in_the_covariance_and_on_diagnostics(ros_env, tmp_path):
    """Frame 7 of a 9-frame replay has its depth blanked but for 4 pixels in a corner: tracking fails on
    it (no ray of the map's observed space left), and an independent subscriber sees the odometry
    covariance jump to the unknown-pose variance on exactly that frame and /diagnostics go from OK to
    WARN ("lost", with the reason) and back to OK when frame 8 is tracked."""
    import dataclasses

    from neb_slam_core.datasets import open_dataset
    from neb_slam_core.io.bag import BagWriteOptions, write_bag
    from neb_slam_core.synth.generate import generate
    from neb_slam_ros.conversions import UNKNOWN_VARIANCE

    ds = open_dataset(generate("small", tmp_path / "scene", n_frames=9, progress=False))
    frames = [ds[i] for i in range(9)]
    broken = {7}
    for i in broken:
        depth = np.zeros_like(frames[i].depth_m)  # a frame without any valid depth is refused as bad input
        depth[:2, :2] = frames[i].depth_m[:2, :2]
        frames[i] = dataclasses.replace(frames[i], depth_m=depth)
    bag = tmp_path / "bag"
    write_bag(frames, bag, BagWriteOptions(depth_encoding="32FC1"), progress=False)
    run, seen, logs = _run_suite(bag, tmp_path / "slam", ros_env, one_process=True)
    assert all(code == 0 for code in run.exit_codes.values()), (run.exit_codes, logs)
    stamps = [f.stamp_ns for f in frames]
    odometry = dict((s, d) for s, d in seen["odometry"])
    failed = {stamps.index(s) for s, d in odometry.items() if d == [UNKNOWN_VARIANCE] * 6}
    assert failed == broken, (failed, odometry)
    levels = [(level, message.split(":")[0]) for level, message, _ in seen["diagnostics"]]
    # every change of state goes out at once, in order; the periodic repeats in between say the same
    changes = [x for i, x in enumerate(levels) if i == 0 or x != levels[i - 1]]
    assert changes[-3:] == [(0, "tracking"), (1, "lost"), (0, "tracking")], levels
    last = seen["diagnostics"][-1][2]
    assert last["tracking_failures"] == "1" and last["frames_processed"] == "9", last
