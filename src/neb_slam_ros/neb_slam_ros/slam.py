"""``slam``: the whole suite in one process, one engine, no map serialisation.

Runs the engine on the camera input: by default the live one (:class:`~neb_slam_core.live.LiveSlam`:
tracking in the node's worker thread on the newest frame, within ``live.max_gap_s`` of the last processed
one, mapping and loop closure beside it: in a child process with ``live.mapping_process``, started with the
node so that its start is not the first frame's wait, or in threads of the node's process), or with
``live:=false`` :class:`~neb_slam_core.slam.Slam`, every frame in the paper's order (what ``neb-slam run``
computes). A lockstep replay (``lockstep:=true``) gives either engine every frame: the live one then tracks
each frame while mapping and loop closure run beside it. It publishes what the separate
``tracker`` and ``mapper`` publish for other stacks: ``pose``, ``odometry``, ``path``, ``blocks`` and
``mesh`` (keyframes and map updates stay inside the process). With a ``bag`` parameter the process also
runs ``bag_replay`` (its parameters: ``rate``, ``lockstep``, ``start``, ``count``, ``loop``) on the same
executor, and ends when the bag does (a live engine tracks one more frame then). On shutdown it
writes a complete run directory into ``output_dir``, the same files as ``neb-slam run`` (trajectory,
ground truth and ATE when ``ground_truth_topic`` is set, timings, metrics, plots, map, mesh), and
publishes the final mesh (``save_mesh`` also publishes the mesh it writes). With
``map_file`` it continues that map checkpoint (the first frame is tracked against it).

Checkpoints (the deterministic engine, ``live:=false``): every ``checkpoint_every``
keyframes and at shutdown the node writes ``checkpoint.pt`` into ``output_dir``
(:mod:`neb_slam_core.checkpoint`: the whole engine, the frames so far). Started again with the same
``output_dir``, it resumes from it: frames stamped at or before the last processed one get their stored
pose again (a replay that starts over from the beginning runs through them in lockstep) and are not
processed twice; a later frame is tracked from where the engine was.

Example::

    ros2 run neb_slam_ros slam --ros-args -p config:=tum -p bag:=bags/fr1_xyz -p lockstep:=true -p live:=false \\
        -p reliable_inputs:=true -p ground_truth_topic:=ground_truth/pose -p output_dir:=runs/fr1_ros
"""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from rclpy.node import Node

from neb_slam_core.checkpoint import CHECKPOINT_FILE, load_checkpoint, save_checkpoint
from neb_slam_core.eval.run_report import RunOutputOptions, write_run
from neb_slam_core.io.run_dir import RunLog
from neb_slam_core.live import LiveSlam
from neb_slam_core.live_mapping import ProcessMapping
from neb_slam_core.slam import Slam
from neb_slam_core.types import RgbdFrame, StepResult
from neb_slam_ros._node_main import run_nodes
from neb_slam_ros.camera_input import CameraInput, InputOptions
from neb_slam_ros.frames import FrameOptions, map_alignment
from neb_slam_ros.node import NebNode
from neb_slam_ros.outputs import (
    FINAL_MESH_ACK_S,
    HealthOutput,
    MapOutputs,
    MapTopicOptions,
    PoseOutputs,
    block_centres,
)
from neb_slam_ros.params import declare_options, map_parameter, require


@dataclass(frozen=True)
class SlamOptions:
    """The one-process node's own parameters (camera input: :class:`InputOptions`; engine: the config)."""

    output_dir: str = ""
    mesh_period_s: float = 30.0
    path_period_s: float = 1.0
    initial_pose_timeout_s: float = 10.0
    bag: str = ""
    map_file: str = ""
    live: bool = True
    lockstep: bool = False
    checkpoint_every: int = 20

    PARAMETER_DOCS = {
        "live": "tracking never waits: mapping and loop closure run beside it and the newest frame "
        "is tracked whenever the engine is free (false: every frame in the paper's order, as "
        "neb-slam run)",
        "lockstep": "with bag: the in-process replay publishes the next frame after this one's pose (bag_replay's "
        "parameter; the engine then processes every frame in order, live or not)",
        "map_file": "a map checkpoint (map.pt) to continue; empty: start from an empty map",
        "output_dir": "run directory written at shutdown (and by save_mesh / save_map); empty: runs/slam-<date>-<time>",
        "mesh_period_s": "publish the mesh this often (0: only on save_mesh and at shutdown)",
        "path_period_s": "publish the path at most this often, and at once after a loop correction (0: after "
        "every frame)",
        "initial_pose_timeout_s": "how long the first frame waits for its pose on ground_truth_topic",
        "bag": "also replay this bag in the process (bag_replay's parameters apply); the process ends with it",
        "checkpoint_every": "write output_dir/checkpoint.pt every this many keyframes and at shutdown, and resume "
        "from it when started again (0: never; the deterministic engine only: live false)",
    }

    def check(self) -> None:
        require(self.mesh_period_s >= 0, "mesh_period_s", ">= 0", self.mesh_period_s)
        require(self.path_period_s >= 0, "path_period_s", ">= 0", self.path_period_s)
        require(self.initial_pose_timeout_s >= 0, "initial_pose_timeout_s", ">= 0", self.initial_pose_timeout_s)
        require(self.checkpoint_every >= 0, "checkpoint_every", ">= 0 (0: never)", self.checkpoint_every)


class SlamNode(NebNode):
    """Tracking and mapping in one engine; see the module docstring."""

    def __init__(self) -> None:
        super().__init__("slam", SlamOptions)
        self.input_opt = declare_options(self, InputOptions)
        self.frame_opt = declare_options(self, FrameOptions)
        self.out = Path(self.opt.output_dir or time.strftime("runs/slam-%Y%m%d-%H%M%S"))
        self._map = map_parameter(self.cfg, self.opt.map_file)  # checked at start, used at the first frame
        self.live = self.opt.live
        self.slam: Slam | LiveSlam | None = None  # made at the first frame (its pose may come from a topic)
        # the live engine's mapping process is started now: importing the engine takes seconds
        self._mapping = ProcessMapping() if self.live and self.cfg.live.mapping_process else None
        self.frames_in = 0
        self.run_log = RunLog()
        self._t_first: float | None = None
        self.input = CameraInput(self, self.input_opt, self.cond, thin=self.live)
        self._loops_applied = 0
        #: called in the worker thread after every frame the engine processed, with its result (an
        #: embedding program's hook: benchmarks sample the engine's memory between frames)
        self.frame_hooks: list[Callable[[StepResult], None]] = []
        self.poses = PoseOutputs(
            self,
            self.frame_opt,
            self.cfg.block.edge_m,
            lambda: self.slam.trajectory(),
            lambda i: self.slam.pose_of(i),
            self.opt.path_period_s,
        )
        self.health = HealthOutput(self, self.input, self._health_values)
        self.map_outputs = MapOutputs(
            self,
            self.frame_opt.map_frame,
            self.cfg.mesh,
            self.out,
            self.opt.mesh_period_s,
            block_map=lambda: None if self.slam is None else self.slam.block_map,
            observed_points=lambda: self.slam.observed_points(),
            write_map=lambda run_dir: run_dir.write_map(self.slam, self.run_log.frames),
            block_revisions=lambda: self.slam.block_revisions,
            topics=declare_options(self, MapTopicOptions),
            truncation_m=self.cfg.render.truncation_m,
        )
        self._frames_in_before = self._frames_replayed = 0  # frames before the checkpoint resumed from
        self._checkpoint = self.out / CHECKPOINT_FILE if self.opt.checkpoint_every and not self.live else None
        self._resumed = self._resume() if self._checkpoint is not None and self._checkpoint.is_file() else ""
        self.start_worker()
        start = f", continuing {self.opt.map_file} ({len(self._map)} blocks)" if self._map is not None else ""
        start += self._resumed
        self.get_logger().info(
            f"neb_slam slam started (config {self.get_parameter('config').value}, output {self.out}{start})"
        )

    # ------------------------------------------------------------------ worker thread

    def has_work(self) -> bool:
        return self.input.has_frame

    def take_work(self) -> RgbdFrame | None:
        if not self.live:
            return self.input.pop()
        if self.slam is None:
            return self.input.pop_newest()
        return self.input.pop_chosen(self.slam.next_frame)

    def do_work(self, frame: RgbdFrame | None) -> None:
        if frame is None:
            return
        if self.live and self.slam is not None and self.slam.n_frames == 1:
            # the only wait of a live engine, for the first map; then the frame it picks from what arrived
            self.slam.wait_for_map()
            with self.cond:
                self.input.push_front(frame)
                frame = self.input.pop_chosen(self.slam.next_frame)
        try:
            self._process(frame)
        except Exception as exc:  # a frame must never kill the node
            self.get_logger().error(
                f"frame {frame.stamp_ns} failed in the engine ({type(exc).__name__}: {exc}); skipped"
            )

    def _resume(self) -> str:
        """Take the engine and the frames so far from ``output_dir``'s checkpoint; says what it resumed."""
        ckpt = load_checkpoint(self._checkpoint)
        self.slam, self.run_log = ckpt.slam, ckpt.run_log
        self._map = None
        r = ckpt.resume
        self._intrinsics, self._t_first = r["intrinsics"], time.perf_counter() - ckpt.wall_s
        self.poses.align(r["T_map_world"])
        self.map_outputs.align(r["T_map_world"])
        self._loops_applied = sum(1 for e in self.slam.loops if e.applied)
        self._frames_in_before = r["frames_in"]
        return f", resuming {self._checkpoint} after {self.slam.n_frames} frames"

    def _save_checkpoint(self) -> None:
        with self.cond:  # frames that arrived after this one are the next start's to count
            arrived = self.input.n_accepted - self.input.queued
        frames_in = self._frames_in_before + arrived - self._frames_replayed
        resume = {"intrinsics": self._intrinsics, "T_map_world": self.poses.T_map_world, "frames_in": frames_in}
        self.out.mkdir(parents=True, exist_ok=True)
        save_checkpoint(self._checkpoint, self.slam, self.run_log, resume, time.perf_counter() - self._t_first)

    def _replay_done(self, frame: RgbdFrame) -> bool:
        """A frame the engine processed before the checkpoint it resumed from: its stored pose goes out
        again (lockstep replay waits for it), nothing is processed."""
        if not self._resumed or self.slam is None or self.slam.n_frames == 0:
            return False
        done = self.run_log.frames
        if frame.stamp_ns > done[-1].stamp_ns:
            return False
        k = next((j for j, f in enumerate(done) if f.stamp_ns >= frame.stamp_ns), None)
        self._frames_replayed += 1
        if k is not None and done[k].stamp_ns == frame.stamp_ns and done[k].result is not None:
            r = dataclasses.replace(done[k].result, T_world_cam=self.slam.pose_of(k))
            self.poses.publish_frame(r, self.input.frame_id)
        return True

    def _process(self, frame: RgbdFrame) -> None:
        if self._replay_done(frame):
            return
        gt = None
        if self.input_opt.ground_truth_topic:
            gt = self.input.wait_for_ground_truth(
                frame.stamp_ns, self.opt.initial_pose_timeout_s if self.slam is None else 0.5, lambda: self.stopping
            )
            frame = dataclasses.replace(frame, T_world_cam=gt)
        if self.slam is None:
            if self.input_opt.ground_truth_topic and gt is None:
                self.get_logger().warning(
                    f"no pose on {self.input_opt.ground_truth_topic} near the first frame: starting from the identity"
                )
            if self.live:
                self.slam, self._mapping = LiveSlam(self.cfg, gt, self._map, self._mapping), None
            else:
                self.slam = Slam(self.cfg, gt, self._map)
            self._map = None
            self._t_first = time.perf_counter()
            self._intrinsics = frame.intrinsics
        self.run_log.begin(frame)
        r = self.slam.process(frame)
        self.run_log.end(r)
        if r.frame_index == 0:
            T_map_world = map_alignment(self.frame_opt, r.T_world_cam, frame, self.get_logger().warning)
            self.poses.align(T_map_world)
            self.map_outputs.align(T_map_world)
        self._t_last = time.perf_counter()
        # a loop correction applied in this step goes out at once (the live engine's reach the tracking
        # thread with a later map update, and the path within a period)
        applied = sum(1 for e in self.slam.loops if e.applied)
        self.poses.path.changed(now=applied > self._loops_applied)
        self._loops_applied = applied
        if r.new_block_id is not None:
            self.poses.publish_blocks(block_centres(self.slam.block_map), r.stamp_ns)
        self.poses.publish_frame(r, self.input.frame_id)
        self.health.frame(r)
        if not r.tracking_ok:
            self.get_logger().warning(
                f"frame {r.frame_index} ({r.stamp_ns}): tracking failed ({r.failure_reason}); "
                "kept the motion prediction"
            )
        for hook in self.frame_hooks:
            hook(r)
        if self._checkpoint is not None and r.is_keyframe and len(self.slam.keyframes) % self.opt.checkpoint_every == 0:
            self._save_checkpoint()

    def _health_values(self) -> dict[str, object]:
        slam = self.slam
        return {
            "frames_processed": 0 if slam is None else slam.n_frames,
            "mapping_lag": slam.stats.mapping_lag if isinstance(slam, LiveSlam) else 0,
            "blocks": 0 if slam is None else len(slam.block_map),
            "keyframes": 0 if slam is None else len(slam.frontend.keyframe_poses),
            "loops_applied": self._loops_applied,
        }

    # ------------------------------------------------------------------ shutdown

    def finish(self) -> None:
        """Write the run directory and publish the final mesh."""
        if self._mapping is not None:  # started for an engine that never came
            self._mapping.shutdown()
        if self.slam is None or self.slam.n_frames == 0:
            self.final_log("neb_slam slam stopped before any frame: nothing to write", "WARN")
            return
        if self.live:
            # the end of the input: one more frame, the one the engine would have taken next
            with self.cond:
                last = self.input.pop_chosen(self.slam.next_frame)
            self.do_work(last)
        with self.cond:
            self.input.drop_queued()  # arrived after the last frame the engine took
        if self.live:
            self.slam.close()
        if self._checkpoint is not None:  # the next start with this output_dir goes on from here
            self._save_checkpoint()
        run_dir = self.map_outputs.run_dir()
        run_dir.write_config(self.cfg)
        run_dir.write_intrinsics(self._intrinsics)
        first_gt = self.run_log.frames[0].T_world_cam_gt is not None
        options = RunOutputOptions(mesh_cfg=self.cfg.mesh, first_pose_from_gt=first_gt, progress=False)
        wall_s = time.perf_counter() - (self._t_first or time.perf_counter())
        summary = write_run(run_dir, self.slam, self.run_log, options, "complete", wall_s)
        # every frame that reached the node and got no pose (superseded, queued at the end, or failed in the
        # engine) counts as dropped
        frames_in = self._frames_in_before + self.input.n_accepted - self._frames_replayed
        summary.metrics["frames_in"] = frames_in
        summary.metrics["frames_dropped"] = frames_in - self.slam.n_frames
        if self.live:
            summary.metrics.update(self.slam.live_metrics(frames_in, self._t_last - self._t_first))
        run_dir.write_metrics(summary.metrics)
        self.poses.path.flush()
        if summary.mesh is not None:  # the final mesh, also to the topic's subscribers
            self.map_outputs.publish(summary.mesh, FINAL_MESH_ACK_S)
        m = summary.metrics
        ate = f", ATE {m['ate_rmse_cm']:.3f} cm" if "ate_rmse_cm" in m else ""
        self.final_log(
            f"neb_slam slam stopped: {self.slam.n_frames} frames, {m.get('n_blocks')} blocks, "
            f"{m.get('s_per_frame') or 0:.3f} s per frame{ate}, {m['frames_dropped']} dropped, "
            f"{self.input.warnings.total} input warnings; run directory {self.out}"
        )


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
    # in its own), so the process is multi-threaded where it matters. A multi-threaded executor's threads
    # would compete with the engine for the GIL.
    return run_nodes([make_slam, make_replay], args, multi_threaded=False)


if __name__ == "__main__":
    sys.exit(main())
