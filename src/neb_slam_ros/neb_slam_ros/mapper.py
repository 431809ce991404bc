"""``mapper``: the neural-block map, its joint optimisation with the keyframe poses, and the mesh.

Subscribes the tracker's keyframes (``keyframe/*``, assembled by stamp) and integrates them in order with the
engine's :class:`~neb_slam_core.slam.Backend`: the first keyframe initialises the map, keyframes marked
``map_now`` run a joint optimisation step. A ``loop_closure`` from the loop closer (corrected poses of
consecutive keyframes) is applied once those keyframes are integrated: keyframes after them move
rigidly with the last, and the map is re-optimised in the paper's two stages. After each step it publishes
``map_update`` (the changed
blocks, the decoders and the keyframe poses; layout in ``neb_slam_core/scene/map_update.py``). Every
``mesh_period_s`` it publishes ``mesh`` (one TRIANGLE_LIST marker per block). Services ``save_mesh`` and
``save_map`` write ``mesh.ply`` / ``map.pt`` into ``output_dir`` (``save_mesh`` also publishes that mesh);
on shutdown (SIGINT, SIGTERM) it publishes the final mesh and writes ``map.pt``, ``mesh.ply``,
``trajectory.txt`` (every frame of the tracker's latest ``path``, each moved
with the final pose of its keyframe) and ``config.yaml`` there.

With ``map_file`` (a ``map.pt`` of ``save_map`` or of ``neb-slam run``) it continues that map: its
blocks and decoders are the starting map, and until the first keyframe arrives the whole map goes out
on ``map_update`` (version 1) whenever a new subscriber appears, so a tracker started with
``wait_for_map`` tracks its first frame against it.

Example::

    ros2 run neb_slam_ros mapper --ros-args -p config:=tum -p output_dir:=runs/live
    ros2 run neb_slam_ros mapper --ros-args -p config:=tum -p map_file:=runs/live/map.pt
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from nav_msgs.msg import Path as PathMsg
from std_msgs.msg import UInt8MultiArray

from neb_slam_core.geometry.se3 import invert
from neb_slam_core.io.run_dir import MAP_FILE, TRAJECTORY_FILE, RunDirectory
from neb_slam_core.io.trajectory import Trajectory
from neb_slam_core.loop.correction import merge_correction
from neb_slam_core.scene import map_update
from neb_slam_core.scene.persistence import save_map
from neb_slam_core.slam import Backend, corrected_trajectory, new_block_map
from neb_slam_ros import conversions, qos
from neb_slam_ros._node_main import run_node
from neb_slam_ros.keyframe_link import KeyframeMeta, KeyframeSubscriber
from neb_slam_ros.node import NebNode
from neb_slam_ros.outputs import FINAL_MESH_ACK_S, MapOutputs, MapTopicOptions
from neb_slam_ros.params import declare_options, map_parameter, require


@dataclass(frozen=True)
class MapperOptions:
    """The mapper's own parameters (the engine's come from the config)."""

    output_dir: str = ""
    mesh_period_s: float = 30.0
    frame_id: str = "map"
    map_file: str = ""

    PARAMETER_DOCS = {
        "output_dir": "where save_mesh, save_map and the shutdown write; empty: runs/mapper-<date>-<time>",
        "map_file": "a map checkpoint (map.pt) to continue; empty: start from an empty map",
        "mesh_period_s": "publish the mesh this often (0: only on save_mesh and at shutdown)",
        "frame_id": "frame of the published mesh: the tracker's map_frame (its keyframes say how the engine's "
        "world sits in it)",
    }

    def check(self) -> None:
        require(self.mesh_period_s >= 0, "mesh_period_s", ">= 0", self.mesh_period_s)
        require(bool(self.frame_id), "frame_id", "a frame name", self.frame_id)


class MapperNode(NebNode):
    """Integrates keyframes and optimises the map; see the module docstring."""

    background = True

    def __init__(self) -> None:
        super().__init__("mapper", MapperOptions)
        self.out = Path(self.opt.output_dir or time.strftime("runs/mapper-%Y%m%d-%H%M%S"))
        torch.manual_seed(self.cfg.seed)
        loaded = map_parameter(self.cfg, self.opt.map_file)
        self.block_map = new_block_map(self.cfg) if loaded is None else loaded
        self.backend = Backend(self.cfg, self.block_map)
        self._rng = np.random.default_rng(self.cfg.seed)
        self._version = 0
        self._unsent_blocks: set[int] = set()
        self._path: tuple[np.ndarray, np.ndarray] | None = None  # the tracker's path, in frame_id
        self._T_map_world = np.eye(4)  # the engine's world in frame_id, from the keyframes
        self._loops: list[tuple[int, np.ndarray, np.ndarray]] = []  # corrections not applied yet
        self._loop_stamp = -1  # header stamp of the newest correction handled (map_update's loop_stamp_ns)
        self._n_loops = 0
        self._n_mapping_steps = 0
        self._map_ms = 0.0

        self._keyframes = KeyframeSubscriber(self, self.cond)
        self._assembler = self._keyframes.assembler
        self.create_subscription(PathMsg, "path", self._on_path, qos.state())
        self.create_subscription(PathMsg, "loop_closure", self._on_loop, qos.events(10))
        self.pub_update = self.create_publisher(UInt8MultiArray, "map_update", qos.events(10))
        self.map_outputs = MapOutputs(
            self,
            self.opt.frame_id,
            self.cfg.mesh,
            self.out,
            self.opt.mesh_period_s,
            block_map=lambda: self.block_map if len(self.backend.keyframes) else None,
            observed_points=lambda: self.backend.observed_points(self._rng),
            write_map=self._write_map,
            block_revisions=lambda: self.backend.mapper.revisions,
            topics=declare_options(self, MapTopicOptions),
            truncation_m=self.cfg.render.truncation_m,
        )
        self._n_update_subscribers = 0
        if self.opt.map_file:
            self._base_timer = self.create_timer(0.5, self._offer_loaded_map)
        self.start_worker()
        start = f", continuing {self.opt.map_file} ({len(self.block_map)} blocks)" if self.opt.map_file else ""
        self.get_logger().info(
            f"neb_slam mapper started (config {self.get_parameter('config').value}, output {self.out}{start})"
        )

    # ------------------------------------------------------------------ callbacks (executor thread)

    def _offer_loaded_map(self) -> None:
        """Until the first keyframe: the loaded map, whole, to each new map_update subscriber (a
        volatile topic gives a late subscriber nothing that was sent before it came)."""
        n = self.pub_update.get_subscription_count()
        if n > self._n_update_subscribers:
            self.submit(self._publish_loaded_map, "publish_loaded_map")
        self._n_update_subscribers = n

    def _on_path(self, msg: PathMsg) -> None:
        stamps = np.array([conversions.stamp_ns(p) for p in msg.poses], dtype=np.int64)
        poses = (
            np.stack([conversions.pose_from_msg(p, "path") for p in msg.poses]) if msg.poses else np.zeros((0, 4, 4))
        )
        with self.cond:
            self._path = (stamps, poses)

    def _on_loop(self, msg: PathMsg) -> None:
        if not msg.poses:
            return  # the loop closer checked a keyframe and found nothing to correct
        try:
            stamps = np.array([conversions.stamp_ns(p) for p in msg.poses], dtype=np.int64)
            poses = np.stack([conversions.pose_from_msg(p, "loop_closure") for p in msg.poses])
        except (ValueError, conversions.InputError) as exc:
            self.get_logger().error(f"{self.resolve_topic_name('loop_closure')}: {exc}: correction ignored")
            return
        with self.cond:
            self._loops.append((conversions.stamp_ns(msg), stamps, poses))
            self.cond.notify_all()

    # ------------------------------------------------------------------ worker thread

    def has_work(self) -> bool:
        return self._assembler.has_ready or bool(self._loops)

    def take_work(self) -> tuple[list[dict], list]:
        loops, self._loops = self._loops, []
        return self._assembler.pop_ready(), loops

    def do_work(self, work: tuple[list[dict], list]) -> None:
        ready, loops = work
        for parts in ready:
            try:
                self._integrate(parts)
            except Exception as exc:  # never let one keyframe kill the mapper
                self.get_logger().error(f"keyframe {parts['meta'].keyframe_id} failed: {type(exc).__name__}: {exc}")
        waiting = [loop for loop in loops if not self._correct(*loop)]
        if waiting:
            with self.cond:  # their keyframes have not all arrived: after the next keyframes
                self._loops[:0] = waiting

    def _integrate(self, parts: dict) -> None:
        meta: KeyframeMeta = parts["meta"]
        if meta.first and self.opt.map_file:
            self.get_logger().error(
                "the tracker started a new map instead of continuing map_file (start it with "
                "wait_for_map:=true): its map and this one differ from here on"
            )
        for centre in meta.block_centres[len(self.block_map) :]:
            block = self.block_map.add_block(torch.as_tensor(centre, dtype=torch.float32))
            self._unsent_blocks.add(block.block_id)
        if meta.T_map_world is not None and not np.array_equal(meta.T_map_world, self._T_map_world):
            with self.cond:
                self._T_map_world = meta.T_map_world
            self.map_outputs.align(meta.T_map_world)
        frame = KeyframeSubscriber.frame(parts)
        step = self.backend.add_keyframe(frame, meta.T_world_cam, meta.frame_index, meta.map_now, meta.first)
        if step.keyframe.keyframe_id != meta.keyframe_id:
            self.get_logger().error(
                f"keyframe ids diverged: tracker {meta.keyframe_id}, mapper {step.keyframe.keyframe_id}"
            )
        self.get_logger().debug(
            f"keyframe {meta.keyframe_id} (frame {meta.frame_index}) integrated"
            + (f", mapped in {step.map_ms:.0f} ms" if step.mapped else "")
        )
        self._unsent_blocks |= step.changed_block_ids  # without mapping: the blocks whose observed space grew
        if step.mapped:
            self._n_mapping_steps += 1
            self._map_ms += step.map_ms
            self._publish_update(self._unsent_blocks, meta.stamp_ns)
            self._unsent_blocks.clear()

    def _correct(self, loop_stamp_ns: int, stamps: np.ndarray, poses: np.ndarray) -> bool:
        """Apply the loop correction stamped ``loop_stamp_ns`` (corrected poses of consecutive keyframes,
        named by stamp) and re-optimise; False while some of its keyframes are not integrated yet (it is
        kept for later)."""
        kfs = self.backend.keyframes
        id_of = {int(kf.stamp_ns): kf.keyframe_id for kf in kfs.keyframes}
        if any(int(s) not in id_of for s in stamps):
            return False
        self._loop_stamp = max(self._loop_stamp, loop_stamp_ns)
        ids = [id_of[int(s)] for s in stamps]
        if ids != list(range(ids[0], ids[0] + len(ids))) or ids[0] == 0:
            self.get_logger().error(
                f"loop_closure: keyframes {ids} are not consecutive keyframes after the first: correction ignored"
            )
            return True
        step = self.backend.correct_loop(merge_correction(kfs.poses(), ids[0], poses), ids[0] - 1)
        self._n_loops += 1
        self.get_logger().info(
            f"loop correction applied to keyframes {ids[0]}..{len(kfs) - 1}, map re-optimised in {step.map_ms:.0f} ms"
        )
        self._publish_update(step.changed_block_ids | self._unsent_blocks, int(kfs[len(kfs) - 1].stamp_ns))
        self._unsent_blocks.clear()
        return True

    def _publish_loaded_map(self) -> str:
        if len(self.backend.keyframes):
            self._base_timer.cancel()  # the map is moving on: trackers get it from the updates now
            return "not sent: keyframes have arrived"
        data = map_update.encode(self.block_map, range(len(self.block_map)), 1, -1, [], np.zeros((0, 4, 4)))
        self.pub_update.publish(UInt8MultiArray(data=data))
        self._version = max(self._version, 1)
        return f"{len(self.block_map)} blocks sent"

    def _publish_update(self, block_ids, ack_stamp_ns: int) -> None:
        kfs = self.backend.keyframes
        self._version += 1
        data = map_update.encode(
            self.block_map,
            block_ids,
            self._version,
            ack_stamp_ns,
            [kf.stamp_ns for kf in kfs.keyframes],
            kfs.poses(),
            self._loop_stamp,
        )
        self.pub_update.publish(UInt8MultiArray(data=data))

    # ------------------------------------------------------------------ outputs (worker thread)

    def _write_map(self, run_dir: RunDirectory) -> Path:
        kfs = self.backend.keyframes
        extra = {
            "keyframe_poses": torch.from_numpy(kfs.poses() if len(kfs) else np.zeros((0, 4, 4))),
            "keyframe_stamps_ns": [int(kf.stamp_ns) for kf in kfs.keyframes],
            "keyframe_frame_indices": [int(kf.frame_index) for kf in kfs.keyframes],
        }
        return save_map(self.block_map, run_dir.file(MAP_FILE), extra=extra, block_keyframes=kfs.block_keyframes())

    def trajectory(self) -> Trajectory:
        kfs = self.backend.keyframes
        kf_stamps = np.array([kf.stamp_ns for kf in kfs.keyframes], dtype=np.int64)
        kf_poses = kfs.poses() if len(kfs) else np.zeros((0, 4, 4))
        with self.cond:
            path, T_map_world = self._path, self._T_map_world
        if path is None:
            return Trajectory(kf_stamps, kf_poses)
        return corrected_trajectory(path[0], invert(T_map_world) @ path[1], kf_stamps, kf_poses)

    # ------------------------------------------------------------------ shutdown

    def finish(self) -> None:
        """Finish the keyframes already received, then write map, mesh, trajectory and config."""
        while self._assembler.has_ready:  # keyframes and loop corrections that arrived before the stop
            self._integrate(self._assembler.pop_ready()[0])
        for loop in self._loops:
            self._correct(*loop)
        if len(self.backend.keyframes) == 0:
            self.final_log("neb_slam mapper stopped before any keyframe: nothing to write", "WARN")
            return
        run_dir = self.map_outputs.run_dir()
        run_dir.write_config(self.cfg)
        written = [str(self._write_map(run_dir))]
        traj = self.trajectory()
        written.append(
            str(run_dir.write_trajectory(traj, TRAJECTORY_FILE, f"neb_slam mapper: {len(traj)} frames, T_world_cam"))
        )
        try:
            written.append(self.map_outputs.save_mesh(ack_timeout_s=FINAL_MESH_ACK_S))
        except Exception as exc:
            self.final_log(f"mesh not written: {type(exc).__name__}: {exc}", "WARN")
        self.final_log(
            f"neb_slam mapper stopped: {len(self.backend.keyframes)} keyframes, {len(self.block_map)} "
            f"blocks, {self._n_mapping_steps} mapping steps "
            f"({self._map_ms / max(self._n_mapping_steps, 1):.0f} ms each), {self._n_loops} loop "
            f"corrections; wrote {', '.join(Path(w).name for w in written)} to {self.out}"
        )


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of the ``mapper`` executable; returns the exit status."""
    return run_node(MapperNode, args)


if __name__ == "__main__":
    sys.exit(main())
