"""``slam``: the whole suite in one process, one engine, no map serialisation.

Runs the engine's :class:`~neb_slam_core.slam.Slam` (tracking and mapping on one block map) on the camera
input and publishes what the separate ``tracker`` and ``mapper`` publish for other stacks: ``pose``,
``odometry``, ``path``, ``blocks`` and ``mesh`` (keyframes and map updates stay inside the process). With
a ``bag`` parameter the process also runs ``bag_replay`` (its parameters: ``rate``, ``lockstep``, ``start``,
``count``, ``loop``) on the same executor, and ends when the bag does. On shutdown it
writes a complete run directory into ``output_dir``, the same files as ``neb-slam run`` (trajectory,
ground truth and ATE when ``ground_truth_topic`` is set, timings, metrics, plots, map, mesh), and
publishes the final mesh (``save_mesh`` also publishes the mesh it writes). With
``map_file`` it continues that map checkpoint (the first frame is tracked against it).

Example::

    ros2 run neb_slam_ros slam --ros-args -p config:=tum -p bag:=bags/fr1_xyz -p lockstep:=true \\
        -p reliable_inputs:=true -p ground_truth_topic:=ground_truth/pose -p output_dir:=runs/fr1_ros
"""

from __future__ import annotations

import dataclasses
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry, Path as PathMsg
from rclpy.node import Node
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from neb_slam_core.io.run_dir import RunDirectory, RunLog, RunOutputOptions, write_run
from neb_slam_core.slam import Slam
from neb_slam_ros import NAMESPACE, conversions, qos
from neb_slam_ros._node_main import WorkerNode, final_log, run_nodes
from neb_slam_ros.camera_input import CameraInput, InputOptions
from neb_slam_ros.mapper import FINAL_MESH_ACK_S, publish_mesh
from neb_slam_ros.requests import Requests
from neb_slam_ros.params import declare_config, declare_options, map_parameter, require


@dataclass(frozen=True)
class SlamOptions:
    """The one-process node's own parameters (camera input: :class:`InputOptions`; engine: the config)."""

    output_dir: str = ""
    mesh_period_s: float = 30.0
    frame_id: str = "map"
    initial_pose_timeout_s: float = 10.0
    bag: str = ""
    map_file: str = ""

    PARAMETER_DOCS = {
        "map_file": "a map checkpoint (map.pt) to continue; empty: start from an empty map",
        "output_dir": "run directory written at shutdown (and by save_mesh / save_map); empty: runs/slam-<date>-<time>",
        "mesh_period_s": "publish the mesh this often (0: only on save_mesh and at shutdown)",
        "frame_id": "frame of the published poses and mesh",
        "initial_pose_timeout_s": "how long the first frame waits for its pose on ground_truth_topic",
        "bag": "also replay this bag in the process (bag_replay's parameters apply); the process ends with it",
    }

    def check(self) -> None:
        require(self.mesh_period_s >= 0, "mesh_period_s", ">= 0", self.mesh_period_s)
        require(bool(self.frame_id), "frame_id", "a frame name", self.frame_id)
        require(self.initial_pose_timeout_s >= 0, "initial_pose_timeout_s", ">= 0", self.initial_pose_timeout_s)


class SlamNode(WorkerNode):
    """Tracking and mapping in one engine; see the module docstring."""

    def __init__(self) -> None:
        super().__init__("slam", namespace=NAMESPACE)
        self.cfg = declare_config(self)
        self.opt = declare_options(self, SlamOptions)
        self.input_opt = declare_options(self, InputOptions)
        self.out = Path(self.opt.output_dir or time.strftime("runs/slam-%Y%m%d-%H%M%S"))
        self._map = map_parameter(self.cfg, self.opt.map_file)  # checked at start, used at the first frame
        self.slam: Slam | None = None  # made at the first frame (its pose may come from a topic)
        self.run_log = RunLog()
        self._cond = threading.Condition()
        self._requests = Requests(self._cond)
        self._stop = False
        self._t_first: float | None = None
        self._prev: tuple[np.ndarray, int] | None = None
        self.input = CameraInput(self, self.input_opt, self._cond)
        self.pub_pose = self.create_publisher(PoseStamped, "pose", qos.stream())
        self.pub_odom = self.create_publisher(Odometry, "odometry", qos.stream())
        self.pub_path = self.create_publisher(PathMsg, "path", qos.state())
        self.pub_blocks = self.create_publisher(MarkerArray, "blocks", qos.state())
        self.pub_mesh = self.create_publisher(MarkerArray, "mesh", qos.state())
        self.create_service(Trigger, "save_mesh", lambda req, res: self._requests.serve("save_mesh", res))
        self.create_service(Trigger, "save_map", lambda req, res: self._requests.serve("save_map", res))
        if self.opt.mesh_period_s > 0:
            self.create_timer(self.opt.mesh_period_s, lambda: self._requests.submit("publish_mesh"))
        self._worker = threading.Thread(target=self._work, name="slam-worker", daemon=True)
        self._worker.start()
        start = f", continuing {self.opt.map_file} ({len(self._map)} blocks)" if self._map is not None else ""
        self.get_logger().info(f"neb_slam slam started (config {self.get_parameter('config').value}, "
                               f"output {self.out}{start})")

    # ------------------------------------------------------------------ worker thread

    def _work(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._stop or self._requests or self.input.has_frame, timeout=1.0)
                if self._stop:
                    return
                frame = self.input.pop()
                requests = self._requests.take()
            if frame is not None:
                try:
                    self._process(frame)
                except Exception as exc:  # a frame must never kill the node
                    self.get_logger().error(f"frame {frame.stamp_ns} failed in the engine "
                                            f"({type(exc).__name__}: {exc}); skipped")
            Requests.run(requests, self, self._stop)

    def _process(self, frame) -> None:
        gt = None
        if self.input_opt.ground_truth_topic:
            gt = self.input.wait_for_ground_truth(frame.stamp_ns, self.opt.initial_pose_timeout_s if self.slam is None
                                                  else 0.5, lambda: self._stop)
            frame = dataclasses.replace(frame, T_world_cam=gt)
        if self.slam is None:
            if self.input_opt.ground_truth_topic and gt is None:
                self.get_logger().warning(f"no pose on {self.input_opt.ground_truth_topic} near the first frame: "
                                          "starting from the identity")
            self.slam, self._map = Slam(self.cfg, gt, self._map), None
            self._t_first = time.perf_counter()
            self._intrinsics = frame.intrinsics
        self.run_log.begin(frame)
        r = self.slam.process(frame)
        self.run_log.end(r)
        fid = self.opt.frame_id
        traj = self.slam.trajectory()
        self.pub_path.publish(conversions.path_msg(traj.stamps_ns, traj.poses, fid))
        if r.new_block_id is not None:
            centres = self.slam.block_map.centres().detach().cpu().double().numpy().reshape(-1, 3)
            self.pub_blocks.publish(conversions.block_markers(centres, self.cfg.block.edge_m, r.stamp_ns, fid))
        prev_T, prev_ns = self._prev if self._prev is not None else (None, None)
        self.pub_odom.publish(conversions.odometry_msg(r.T_world_cam, r.stamp_ns, prev_T, prev_ns, fid, "camera"))
        self._prev = (r.T_world_cam, r.stamp_ns)
        # the pose goes last: lockstep replay publishes the next frame (or ends the process) on it
        self.pub_pose.publish(conversions.pose_msg(r.T_world_cam, r.stamp_ns, fid))
        if not r.tracking_ok:
            self.get_logger().warning(f"frame {r.frame_index} ({r.stamp_ns}): tracking failed ({r.failure_reason}); "
                                      "kept the motion prediction")

    # ------------------------------------------------------------------ outputs (worker thread)

    def _mesh(self):
        from neb_slam_core.mesh import extract_mesh

        if self.slam is None or len(self.slam.block_map) == 0:
            raise RuntimeError("the map has no blocks yet")
        return extract_mesh(self.slam.block_map, self.cfg.mesh, self.slam.observed_points())

    def _do_publish_mesh(self) -> str:
        if self.slam is None:
            return "no frame yet"
        return publish_mesh(self.pub_mesh, self._mesh(), self.slam.block_map, self.opt.frame_id)

    def _run_dir(self) -> RunDirectory:
        self.out.mkdir(parents=True, exist_ok=True)
        return RunDirectory(self.out)

    def _do_save_mesh(self) -> str:
        """Write ``mesh.ply`` and publish the same mesh."""
        mesh = self._mesh()
        path = self._run_dir().write_mesh(mesh)
        publish_mesh(self.pub_mesh, mesh, self.slam.block_map, self.opt.frame_id)
        return str(path)

    def _do_save_map(self) -> str:
        if self.slam is None:
            raise RuntimeError("no frame yet")
        return str(self._run_dir().write_map(self.slam, self.run_log.frames))

    # ------------------------------------------------------------------ shutdown

    def close(self) -> None:
        """Finish the frame in progress, then write the run directory."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._worker.join(timeout=600)
        if self.slam is None or self.slam.n_frames == 0:
            final_log(self, "neb_slam slam stopped before any frame: nothing to write", "WARN")
            return
        run_dir = self._run_dir()
        run_dir.write_config(self.cfg)
        run_dir.write_intrinsics(self._intrinsics)
        first_gt = self.run_log.frames[0].T_world_cam_gt is not None
        options = RunOutputOptions(mesh_cfg=self.cfg.mesh, first_pose_from_gt=first_gt, progress=False)
        wall_s = time.perf_counter() - (self._t_first or time.perf_counter())
        summary = write_run(run_dir, self.slam, self.run_log, options, "complete", wall_s)
        if summary.mesh is not None:  # the final mesh, also to the topic's subscribers
            publish_mesh(self.pub_mesh, summary.mesh, self.slam.block_map, self.opt.frame_id, FINAL_MESH_ACK_S)
        m = summary.metrics
        ate = f", ATE {m['ate_rmse_cm']:.3f} cm" if "ate_rmse_cm" in m else ""
        final_log(self, f"neb_slam slam stopped: {self.slam.n_frames} frames, {m.get('n_blocks')} blocks, "
                        f"{m.get('s_per_frame') or 0:.3f} s per frame{ate}, {self.input.n_dropped} dropped, "
                        f"{self.input.warnings.total} input warnings; run directory {self.out}")


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of the ``slam`` executable; returns the exit status."""
    made: dict[str, Node] = {}

    def make_slam() -> Node:
        made["slam"] = SlamNode()
        return made["slam"]

    def make_replay() -> Node | None:
        if not made["slam"].opt.bag:
            return None
        from neb_slam_ros.bag_replay import BagReplayNode

        return BagReplayNode()

    # One executor thread for the callbacks; the engine runs in the node's own worker thread (and the replay
    # in its own), so the process is multi-threaded where it matters. rclpy's MultiThreadedExecutor was
    # measured 26 % slower here (0.34 against 0.46 frames per second, benchmarks/ros_suite.py): its
    # threads compete with the engine for the GIL.
    return run_nodes([make_slam, make_replay], args, multi_threaded=False)


if __name__ == "__main__":
    sys.exit(main())
