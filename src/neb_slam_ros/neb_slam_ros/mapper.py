"""``mapper``: the neural-block map, its joint optimisation with the keyframe poses, and the mesh.

Subscribes the tracker's keyframes (``keyframe/*``, assembled by stamp) and hands them, in order, to the
engine's mapping side (:class:`~neb_slam_core.live_mapping.MappingSide`: the mapper in a thread of its
own, as in the one-process live engine). The first keyframe initialises the map with the number of
map-only steps the tracker waits for (its ``keyframe/meta`` says: all of ``mapping.first_iterations`` for
a tracker with ``map_sync``, ``live.first_iterations`` otherwise, the rest then refined in the
background); keyframes marked ``map_now`` run a joint optimisation step, and keyframes that queued up
while the mapper was busy share one step. A ``loop_closure`` from the loop closer (corrected poses of
consecutive keyframes) is applied once those keyframes have arrived: the keyframes move at once (those
after them rigidly with the last), and the map is re-optimised in the paper's two stages in the
background, a chunk of ``live.chunk_iterations`` at a time. After each step it publishes ``map_update``
(the changed blocks, the decoders and the keyframe poses; layout in
``neb_slam_core/scene/map_update.py``). Every ``mesh_period_s`` it publishes ``mesh`` (one TRIANGLE_LIST
marker per block). Services ``save_mesh`` and ``save_map`` write ``mesh.ply`` / ``map.pt`` into
``output_dir`` (``save_mesh`` also publishes that mesh); on shutdown (SIGINT, SIGTERM) it integrates the
keyframes received, publishes the final mesh and writes ``map.pt``, ``mesh.ply``, ``trajectory.txt``
(every frame of the tracker's latest ``path``, each moved with the final pose of its keyframe) and
``config.yaml`` there.

Updates carry the changes since the last one (changed table rows, ``scene/map_update.py``), so a receiver
needs every update from its first on. Whenever another node subscribes to ``map_update`` (a tracker
started late or again, the loop closer) the whole map goes out as the next update, to every subscriber.

Every ``checkpoint_every`` integrated keyframes it writes ``output_dir/checkpoint.pt`` (atomically: the
map and its optimiser, the keyframe store and poses, which keyframe stamp has which id). Started again
with the same ``output_dir`` (after a crash or a ``SIGKILL``) it resumes from it: it offers the whole map
with the keyframes it kept on ``map_update``, under a new ``epoch``, and the tracker, which keeps the
keyframes the mapper's last checkpoint does not hold, sends those again. Loop corrections that came while
it was down are lost (the loop closer's next ones carry on). Every update says how many keyframes the
last checkpoint holds (``durable_keyframes``), so that the tracker can forget the older ones. A mapper
that stops normally removes its checkpoint (``map_file`` continues its ``map.pt``).

With ``map_file`` (a ``map.pt`` of ``save_map`` or of ``neb-slam run``) it continues that map: its
blocks and decoders are the starting map, which goes out whole on ``map_update`` to each new subscriber,
so a tracker started with ``wait_for_map`` tracks its first frame against it.

Example::

    ros2 run neb_slam_ros mapper --ros-args -p config:=tum -p output_dir:=runs/live
    ros2 run neb_slam_ros mapper --ros-args -p config:=tum -p map_file:=runs/live/map.pt
"""

from __future__ import annotations

import sys
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from nav_msgs.msg import Path as PathMsg
from std_msgs.msg import UInt8MultiArray

from neb_slam_core.checkpoint import CHECKPOINT_FILE, read_state, write_atomically
from neb_slam_core.geometry.se3 import invert
from neb_slam_core.io.run_dir import MAP_FILE, TRAJECTORY_FILE, RunDirectory
from neb_slam_core.io.trajectory import Trajectory
from neb_slam_core.live_mapping import Handoff, MappingSide, Progress
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
    checkpoint_every: int = 20

    PARAMETER_DOCS = {
        "output_dir": "where save_mesh, save_map and the shutdown write; empty: runs/mapper-<date>-<time>",
        "map_file": "a map checkpoint (map.pt) to continue; empty: start from an empty map",
        "mesh_period_s": "publish the mesh this often (0: only on save_mesh and at shutdown)",
        "frame_id": "frame of the published mesh: the tracker's map_frame (its keyframes say how the engine's "
        "world sits in it)",
        "checkpoint_every": "write output_dir/checkpoint.pt every this many keyframes, and resume from it when "
        "started again with the same output_dir (0: never)",
    }

    def check(self) -> None:
        require(self.mesh_period_s >= 0, "mesh_period_s", ">= 0", self.mesh_period_s)
        require(self.checkpoint_every >= 0, "checkpoint_every", ">= 0 (0: never)", self.checkpoint_every)
        require(bool(self.frame_id), "frame_id", "a frame name", self.frame_id)


@dataclass
class MapperState:
    """What the mapper's checkpoint holds: the mapping side's backend (map, optimiser, keyframes and their
    poses), the id of each keyframe stamp, the update counter, the map frame and the loops applied."""

    backend: Backend
    keyframe_ids: dict[int, int]
    version: int
    T_map_world: np.ndarray
    n_loops: int
    torch_rng: torch.Tensor


class MapperNode(NebNode):
    """Integrates keyframes and optimises the map; see the module docstring."""

    background = True

    def __init__(self) -> None:
        super().__init__("mapper", MapperOptions)
        self.out = Path(self.opt.output_dir or time.strftime("runs/mapper-%Y%m%d-%H%M%S"))
        torch.manual_seed(self.cfg.seed)
        self._checkpoint = self.out / CHECKPOINT_FILE if self.opt.checkpoint_every else None
        state = self._checkpoint_state()
        loaded = map_parameter(self.cfg, self.opt.map_file) if state is None else None
        if state is not None:
            self.block_map = state.backend.block_map
        else:
            self.block_map = new_block_map(self.cfg) if loaded is None else loaded
        self._rng = np.random.default_rng(self.cfg.seed)
        self._version = 0
        self._epoch = time.time_ns()  # this start's: trackers tell a restarted mapper by it
        self._durable = -1 if self._checkpoint is None else 0  # keyframes in the last checkpoint
        self._path: tuple[np.ndarray, np.ndarray] | None = None  # the tracker's path, in frame_id
        self._T_map_world = np.eye(4)  # the engine's world in frame_id, from the keyframes
        self._new_loops: list[tuple[int, np.ndarray, np.ndarray]] = []  # corrections not looked at yet
        self._waiting_loops: list[tuple[int, np.ndarray, np.ndarray]] = []  # ... waiting for their keyframes
        self._keyframe_ids: dict[int, int] = {}  # stamp -> id of every keyframe handed to the mapping side
        self._messages: deque[tuple[str, object]] = deque()  # from the mapping side, to publish or log
        self._progress = Progress()
        self._n_loops = 0
        if state is not None:
            self._keyframe_ids, self._version = dict(state.keyframe_ids), state.version
            self._T_map_world, self._n_loops = state.T_map_world, state.n_loops
            self._durable = len(state.backend.keyframes)
            torch.set_rng_state(state.torch_rng)

        self._keyframes = KeyframeSubscriber(self, self.cond)
        self._assembler = self._keyframes.assembler
        self._assembler.next_id = len(self._keyframe_ids)  # a tracker may send the checkpoint's keyframes again
        self.create_subscription(PathMsg, "path", self._on_path, qos.state())
        self.create_subscription(PathMsg, "loop_closure", self._on_loop, qos.events(10))
        self.pub_update = self.create_publisher(UInt8MultiArray, "map_update", qos.events(10))
        # the engine's mapping side: the mapper in a thread of its own, loop corrections from the loop closer
        self.side = MappingSide(
            self.cfg, self.block_map, self._on_side, False, None if state is None else state.backend
        )
        self.backend = self.side.backend
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
        self._updates_sent, self._update_bytes = 0, 0  # published on map_update since this start
        self.create_timer(0.5, self._offer_whole_map)
        if state is not None:
            self.map_outputs.align(self._T_map_world)
        self.start_worker()
        start = f", continuing {self.opt.map_file} ({len(self.block_map)} blocks)" if loaded is not None else ""
        if state is not None:
            start = f", resuming {self._checkpoint} with {self._durable} keyframes"
        self.get_logger().info(
            f"neb_slam mapper started (config {self.get_parameter('config').value}, output {self.out}{start})"
        )

    # ------------------------------------------------------------------ callbacks (executor thread)

    def _offer_whole_map(self) -> None:
        """The whole map as the next update when a node subscribed to map_update since the last look (a
        volatile topic gives a late subscriber nothing that was sent before it came)."""
        n = self.pub_update.get_subscription_count()
        if n > self._n_update_subscribers:
            self.submit(self._publish_whole_map, "publish_whole_map")
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
            self._new_loops.append((conversions.stamp_ns(msg), stamps, poses))
            self.cond.notify_all()

    # ------------------------------------------------------------------ the mapping side's threads

    def _on_side(self, kind: str, payload: object) -> None:
        """A message of the mapping side (its thread, its lock held): queued for the worker."""
        with self.cond:
            if kind == "progress":
                self._progress = payload
                return
            self._messages.append((kind, payload))
            self.cond.notify_all()

    def state_lock(self):
        return self.side.map_lock

    # ------------------------------------------------------------------ worker thread

    def has_work(self) -> bool:
        return self._assembler.has_ready or bool(self._new_loops) or bool(self._messages)

    def take_work(self) -> tuple[list[dict], list, list]:
        loops, self._new_loops = self._new_loops, []
        messages = list(self._messages)
        self._messages.clear()
        return self._assembler.pop_ready(), loops, messages

    def do_work(self, work: tuple[list[dict], list, list]) -> None:
        ready, loops, messages = work
        for kind, payload in messages:
            if kind == "update":
                self._publish_update(payload)
            elif kind == "error":
                self.get_logger().error(f"mapping failed: {payload}")
        if self._checkpoint is not None and len(self.backend.keyframes) >= self._durable + self.opt.checkpoint_every:
            self._save_checkpoint()
        for parts in ready:
            try:
                self._submit(parts)
            except Exception as exc:  # never let one keyframe kill the mapper
                self.get_logger().error(f"keyframe {parts['meta'].keyframe_id} failed: {type(exc).__name__}: {exc}")
        # corrections whose keyframes have not all arrived wait for the next keyframes
        self._waiting_loops = [loop for loop in self._waiting_loops + loops if not self._correct(*loop)]

    def _submit(self, parts: dict) -> None:
        """Hand a keyframe to the mapping side (the blocks the tracker allocated come with it)."""
        meta: KeyframeMeta = parts["meta"]
        if meta.first and self.opt.map_file:
            self.get_logger().error(
                "the tracker started a new map instead of continuing map_file (start it with "
                "wait_for_map:=true): its map and this one differ from here on"
            )
        if meta.keyframe_id != len(self._keyframe_ids):
            self.get_logger().error(
                f"keyframe ids diverged: tracker {meta.keyframe_id}, mapper {len(self._keyframe_ids)}"
            )
        if meta.T_map_world is not None and not np.array_equal(meta.T_map_world, self._T_map_world):
            with self.cond:
                self._T_map_world = meta.T_map_world
            self.map_outputs.align(meta.T_map_world)
        first_iterations = self.cfg.mapping.first_iterations if meta.first_iterations is None else meta.first_iterations
        self.side.submit(
            Handoff(
                KeyframeSubscriber.frame(parts),
                meta.T_world_cam,
                meta.frame_index,
                meta.keyframe_id,
                meta.map_now,
                meta.first,
                meta.block_centres,
                np.zeros((0, 4, 4)),
                first_iterations,
            )
        )
        self._keyframe_ids[meta.stamp_ns] = len(self._keyframe_ids)
        self.get_logger().debug(f"keyframe {meta.keyframe_id} (frame {meta.frame_index}) handed to the mapper")

    def _correct(self, loop_stamp_ns: int, stamps: np.ndarray, poses: np.ndarray) -> bool:
        """Hand the loop correction stamped ``loop_stamp_ns`` (corrected poses of consecutive keyframes,
        named by stamp) to the mapping side, which moves the keyframes at once and re-optimises in the
        background; False while some of its keyframes have not arrived yet (it is kept for later)."""
        if any(int(s) not in self._keyframe_ids for s in stamps):
            return False
        ids = [self._keyframe_ids[int(s)] for s in stamps]
        if ids != list(range(ids[0], ids[0] + len(ids))) or ids[0] == 0:
            self.get_logger().error(
                f"loop_closure: keyframes {ids} are not consecutive keyframes after the first: correction ignored"
            )
            return True
        by_id = np.zeros((ids[-1] + 1, 4, 4))
        by_id[ids] = poses
        self.side.correct(ids[-1], ids[0] - 1, by_id, loop_stamp_ns)
        self._n_loops += 1
        self.get_logger().info(f"loop correction of keyframes {ids[0]}..{ids[-1]} handed to the mapper")
        return True

    def _publish_whole_map(self) -> str:
        if not len(self.block_map):
            return "not sent: no blocks yet"
        with self.side.map_lock:
            kfs = self.backend.keyframes
            stamps = np.array([kf.stamp_ns for kf in kfs.keyframes], dtype=np.int64)
            poses = kfs.poses() if len(kfs) else np.zeros((0, 4, 4))
            ack = int(stamps[-1]) if len(stamps) else -1
            # whole: a tracker that starts over gets every block; the mirror then holds what it has
            update = map_update.capture(
                self.block_map, range(len(self.block_map)), 0, ack, stamps, poses, mirror=self.side.mirror, whole=True
            )
        # a new version: every receiver applies it, and the next updates are changes against it
        self._publish_update(update)
        return f"{len(self.block_map)} blocks and {len(stamps)} keyframe poses sent"

    def _publish_update(self, update: map_update.MapUpdate) -> None:
        # this node numbers what it sends in the order it publishes them, and says which start sent it and
        # what its last checkpoint holds
        self._version += 1
        update.version = self._version
        update.epoch, update.durable_keyframes = self._epoch, self._durable
        data = map_update.encode(update)
        self.pub_update.publish(UInt8MultiArray(data=data))
        self._updates_sent += 1
        self._update_bytes += len(data)

    # ------------------------------------------------------------------ checkpoints (worker thread)

    def _checkpoint_state(self) -> MapperState | None:
        """The state of ``output_dir``'s checkpoint, when there is one to resume from."""
        if self._checkpoint is None or not self._checkpoint.is_file():
            return None
        if self.opt.map_file:
            raise ValueError(
                f"map_file {self.opt.map_file} and the checkpoint {self._checkpoint} to resume from: give "
                "another output_dir, or leave map_file out to resume"
            )
        return read_state(self._checkpoint, MapperState)

    def _save_checkpoint(self) -> None:
        """The integrated keyframes, their map and the node's bookkeeping, atomically into ``checkpoint.pt``."""
        with self.side.map_lock:  # the mapping thread changes none of it meanwhile
            n = len(self.backend.keyframes)
            ids = {stamp: i for stamp, i in self._keyframe_ids.items() if i < n}
            with self.cond:
                T_map_world = self._T_map_world.copy()
            state = MapperState(self.backend, ids, self._version, T_map_world, self._n_loops, torch.get_rng_state())
            self.out.mkdir(parents=True, exist_ok=True)
            write_atomically(self._checkpoint, state)
        self._durable = n

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
        """Finish the keyframes and loop corrections already received, then write map, mesh, trajectory
        and config."""
        with self.cond:
            ready, loops, _ = self.take_work()
        for parts in ready:
            self._submit(parts)
        for loop in self._waiting_loops + loops:
            self._correct(*loop)
        self.side.close(self._join_timeout_s)
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
        if self._checkpoint is not None:  # stopped, not crashed: map.pt (map_file) continues this map
            self._checkpoint.unlink(missing_ok=True)
        p = self._progress
        self.final_log(
            f"neb_slam mapper stopped: {len(self.backend.keyframes)} keyframes, {len(self.block_map)} "
            f"blocks, {p.mapping_steps} mapping steps and {p.background_chunks} background chunks, "
            f"{self._n_loops} loop corrections, {self._updates_sent} map updates ({self._update_bytes / 1e6:.1f} MB); "
            f"wrote {', '.join(Path(w).name for w in written)} to {self.out}"
        )


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of the ``mapper`` executable; returns the exit status."""
    return run_node(MapperNode, args)


if __name__ == "__main__":
    sys.exit(main())
