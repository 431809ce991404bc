"""What the nodes publish for other stacks, defined once for every node that publishes it.

- :class:`PoseOutputs`: ``pose``, ``odometry``, ``/tf``, ``path`` (:class:`PathOutput`) and ``blocks`` of the
  tracking side (the ``tracker`` and the one-process ``slam``).
- :class:`MapOutputs`: ``mesh`` and the ``save_mesh`` / ``save_map`` services of the mapping side (the
  ``mapper`` and ``slam``), run in the node's worker thread (the map's owner).
- :class:`HealthOutput`: the tracking state and the node's counters on ``/diagnostics``.

``path`` and ``mesh`` grow with the run (every frame, every surface), so neither is rebuilt per frame:
the path goes out at most every ``path_period_s``, the mesh only to subscribers and only for the blocks
that changed, and both are serialized straight from numpy arrays (:mod:`neb_slam_ros.cdr`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import OccupancyGrid, Odometry
from nav_msgs.msg import Path as PathMsg
from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration
from rclpy.event_handler import PublisherEventCallbacks
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import MarkerArray

from neb_slam_core.io.run_dir import RunDirectory
from neb_slam_core.io.trajectory import Trajectory
from neb_slam_core.types import StepResult
from neb_slam_ros import cdr, conversions, qos
from neb_slam_ros.frames import FrameOptions, TfOutput
from neb_slam_ros.params import require

#: at shutdown, how long a published mesh or path may wait for every subscriber's acknowledgement (the
#: process ends right after; a reliable message not yet received would be lost with it)
FINAL_MESH_ACK_S = 5.0

#: the frame id of the keyframe images the tracker hands to the mapper (the engine's camera)
CAMERA_FRAME = "camera"

#: with ``path_period_s`` 0 (a path after every frame), how often a change held back while nobody
#: subscribed is looked at again
IDLE_PATH_CHECK_S = 1.0


class PathOutput:
    """``path`` (transient local): the whole trajectory with every correction applied, at bounded cost.

    nav_msgs/Path has no incremental form, so each publication carries every pose; what is bounded is how
    often one is built. A new frame or a correction only marks the path as changed (:meth:`changed`). It
    goes out when ``period_s`` (steady clock) has passed since the last publication, at once after a loop
    correction, and otherwise from a timer that looks every half period, so the last frames of a run wait
    at most one and a half periods; ``period_s`` 0 publishes after every change. While nobody subscribes
    nothing is built (the timer publishes the change once someone does). A publication reads the
    trajectory once (``trajectory()``: every frame's current pose, one vectorised pass) and serializes it
    in one piece.

    Args:
        node: the :class:`~neb_slam_ros.node.NebNode` (its worker thread calls every method).
        publisher: the ``path`` publisher.
        frame_id: frame of the path and its poses.
        period_s: shortest time between two publications (0: after every change).
        trajectory: the current trajectory.
        clock: seconds of a steady clock (a simulated one in benchmarks).
    """

    def __init__(
        self,
        node,
        publisher,
        frame_id: str,
        period_s: float,
        trajectory: Callable[[], Trajectory],
        clock: Callable[[], float] = time.monotonic,
    ):
        self.pub = publisher
        self.frame_id = frame_id
        self.period_s = period_s
        self._trajectory = trajectory
        self._clock = clock
        self.pending = False
        self.n_published = 0
        self._last = -float("inf")
        steady = Clock(clock_type=ClockType.STEADY_TIME)  # a paused or fast replay does not change the rate
        self.timer = node.create_timer(
            period_s / 2 if period_s > 0 else IDLE_PATH_CHECK_S,
            lambda: node.submit(self._on_timer, "publish_path", coalesce=True),
            clock=steady,
        )

    def changed(self, now: bool = False) -> None:
        """The trajectory gained a frame or corrected poses moved: publish when the period since the last
        publication has passed, or with ``now`` (a loop correction) at once; else the timer will."""
        self.pending = True
        if now or self._clock() - self._last >= self.period_s:
            self.publish_pending()

    def _on_timer(self) -> str:
        if self._clock() - self._last < self.period_s:
            return "within the period"
        return self.publish_pending()

    def publish_pending(self) -> str:
        """Publish the trajectory if it changed since the last publication and someone subscribes."""
        if not self.pending:
            return "no change"
        if self.pub.get_subscription_count() == 0:
            return "no subscriber"
        return self.publish()

    def publish(self, ack_timeout_s: float = 0.0) -> str:
        """Publish the current trajectory; with ``ack_timeout_s``, then wait up to that long for every
        subscriber's acknowledgement."""
        tr = self._trajectory()
        stamp = int(tr.stamps_ns[-1]) if len(tr.stamps_ns) else 0
        if cdr.supported():
            msg = cdr.path(tr.stamps_ns, cdr.pose_rows(tr.poses), self.frame_id, stamp)
        else:
            msg = conversions.path_msg(tr.stamps_ns, tr.poses, self.frame_id, stamp)
        self.pub.publish(msg)
        self.pending = False
        self.n_published += 1
        self._last = self._clock()
        if ack_timeout_s > 0:
            self.pub.wait_for_all_acked(Duration(seconds=ack_timeout_s))
        return f"{len(tr.stamps_ns)} poses"

    def flush(self, ack_timeout_s: float = FINAL_MESH_ACK_S) -> None:
        """At shutdown: publish a change not published yet (to whoever subscribes) and wait for it."""
        self.timer.cancel()
        if self.pending and self.pub.get_subscription_count() > 0:
            self.publish(ack_timeout_s)


class PoseOutputs:
    """``pose``, ``odometry``, ``/tf`` per frame, ``path`` and ``blocks`` (transient local) of ``node``, all in
    the level ``map_frame`` (:mod:`neb_slam_ros.frames`).

    The engine's poses are in its world frame; :meth:`align` sets ``T_map_world`` at the first frame and
    every output goes through it. ``trajectory``: every processed frame's current pose in the world frame
    (read when ``path`` is published); ``pose_of``: processed frame ``i``'s current pose (the previous
    frame's, for the motion ``odom -> base`` adds); ``path_period_s``: see :class:`PathOutput`.
    """

    def __init__(
        self,
        node,
        frames: FrameOptions,
        block_edge_m: float,
        trajectory: Callable[[], Trajectory],
        pose_of: Callable[[int], np.ndarray],
        path_period_s: float,
    ):
        self.frame_id = frames.map_frame
        self.block_edge_m = block_edge_m
        self.T_map_world = np.eye(4)
        self._pose_of = pose_of
        self.pub_pose = node.create_publisher(PoseStamped, "pose", qos.stream())
        self.pub_odom = node.create_publisher(Odometry, "odometry", qos.stream())
        self.pub_path = node.create_publisher(PathMsg, "path", qos.state())
        self.pub_blocks = node.create_publisher(MarkerArray, "blocks", qos.state())
        self.tf = TfOutput(node, frames)
        self.path = PathOutput(node, self.pub_path, self.frame_id, path_period_s, lambda: self.in_map(trajectory()))
        self._prev: tuple[np.ndarray, int] | None = None

    def align(self, T_map_world: np.ndarray) -> None:
        """Set the world frame's pose in ``map`` (before the first frame is published)."""
        self.T_map_world = np.asarray(T_map_world, dtype=np.float64)

    def in_map(self, tr: Trajectory) -> Trajectory:
        return Trajectory(tr.stamps_ns, self.T_map_world @ tr.poses if len(tr.poses) else tr.poses)

    def publish_blocks(self, centres: np.ndarray, stamp_ns: int) -> None:
        centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
        R, t = self.T_map_world[:3, :3], self.T_map_world[:3, 3]
        self.pub_blocks.publish(
            conversions.block_markers(centres @ R.T + t, self.block_edge_m, stamp_ns, self.frame_id, R)
        )

    def publish_frame(self, r: StepResult, camera_frame: str = "") -> None:
        """``/tf``, ``odometry`` (twist from the previous frame) and ``pose`` of a processed frame;
        ``camera_frame``: the image's frame id. The pose goes last: lockstep replay publishes the next
        frame (or ends the process) when it arrives."""
        T = self.T_map_world @ r.T_world_cam
        prev = self.T_map_world @ self._pose_of(r.frame_index - 1) if r.frame_index > 0 else None
        self.tf.frame(T, prev, r.stamp_ns, camera_frame)
        prev_T, prev_ns = self._prev if self._prev is not None else (None, None)
        cov = r.covariance
        if cov is not None:
            R6 = np.kron(np.eye(2), self.T_map_world[:3, :3])  # translation and rotation vector alike
            cov = R6 @ cov @ R6.T
        self.pub_odom.publish(
            conversions.odometry_msg(T, r.stamp_ns, prev_T, prev_ns, self.frame_id, self.tf.camera_frame, cov)
        )
        self._prev = (T, r.stamp_ns)
        self.pub_pose.publish(conversions.pose_msg(T, r.stamp_ns, self.frame_id))


class HealthOutput:
    """The tracking health of ``node`` on ``/diagnostics`` (diagnostic_msgs/DiagnosticArray, what
    ``rqt_robot_monitor`` and the diagnostic aggregator read): one status named ``<node name>: tracking``,
    level OK while frames are tracked and WARN from a failed frame until one is tracked again, the message
    saying which (with the failure's reason), and as key-values the counters ``values()`` returns (frames
    in, tracked, dropped, failures, queue, mapping lag, blocks, keyframes, loops). Published every
    ``period_s`` and at once when the state changes."""

    def __init__(self, node, inputs, values: Callable[[], dict[str, object]], period_s: float = 1.0):
        """``inputs``: the node's :class:`~neb_slam_ros.camera_input.CameraInput` (frames in, dropped,
        queued); ``values``: the engine's counters."""
        self.node = node
        self.inputs = inputs
        self.values = values
        self.name = f"{node.get_name()}: tracking"
        self.pub = node.create_publisher(DiagnosticArray, "/diagnostics", qos.events(10))
        self.tracking: bool | None = None  # None: no frame yet
        self.reason = ""
        self.failures = 0
        node.create_timer(period_s, self.publish)

    def frame(self, r: StepResult) -> None:
        """Account for a processed frame; a change of state goes out at once."""
        self.failures += int(not r.tracking_ok)
        changed = r.tracking_ok != self.tracking
        self.tracking, self.reason = r.tracking_ok, r.failure_reason
        if changed:
            self.publish()

    def status(self) -> DiagnosticStatus:
        if self.tracking is None:
            level, message = DiagnosticStatus.OK, "waiting for the first frame"
        elif self.tracking:
            level, message = DiagnosticStatus.OK, "tracking"
        else:
            level, message = DiagnosticStatus.WARN, f"lost: {self.reason}"
        values = {
            "tracking_failures": self.failures,
            "frames_in": self.inputs.n_accepted,
            "frames_dropped": self.inputs.n_dropped,
            "queue": self.inputs.queued,
            **self.values(),
        }
        return DiagnosticStatus(
            level=level,
            name=self.name,
            message=message,
            hardware_id="",
            values=[KeyValue(key=k, value=str(v)) for k, v in values.items()],
        )

    def publish(self) -> None:
        msg = DiagnosticArray(status=[self.status()])
        msg.header.stamp = self.node.get_clock().now().to_msg()
        self.pub.publish(msg)


def block_centres(block_map) -> np.ndarray:
    """``(M, 3)`` float64 centres of the map's blocks."""
    return block_map.centres().detach().cpu().double().numpy().reshape(-1, 3)


@dataclass(frozen=True)
class MapTopicOptions:
    """Parameters of ``map_grid`` (``mapper``, ``slam``)."""

    grid_height_m: float = 0.3
    grid_resolution_m: float = 0.1

    PARAMETER_DOCS = {
        "grid_height_m": "height of the map_grid slice in the map frame (z up, 0 at the first base position)",
        "grid_resolution_m": "cell size of map_grid",
    }

    def check(self) -> None:
        require(self.grid_resolution_m > 0, "grid_resolution_m", "> 0", self.grid_resolution_m)
        require(math.isfinite(self.grid_height_m), "grid_height_m", "a finite height", self.grid_height_m)


class MapOutputs:
    """The map topics (``mesh``, ``map_cloud``, ``map_grid``) and the map's services of ``node`` (a
    :class:`~neb_slam_ros.node.NebNode`).

    ``mesh`` (transient local) is one TRIANGLE_LIST marker per block; a message carries only the blocks
    whose part changed since the last one (RViz's MarkerArray display, like any subscriber that keeps
    markers by namespace and id, updates just those), with a DELETE marker for a block that lost its
    triangles. The periodic publication (:meth:`publish_current_map`) builds nothing while nobody
    subscribes; otherwise it re-extracts only the blocks whose table changed since they were last
    extracted, and the blocks within their reach (:func:`~neb_slam_core.mesh.affected_blocks`), and keeps
    every block's marker. A subscriber that arrives later receives the latest message at once (transient
    local), then every kept marker in one message as soon as the publisher matches it, and the next
    periodic message is again complete when the subscriber count rose in between. ``save_mesh`` and the
    final mesh extract every block and publish every marker. Stamps come from the node's clock (sim time
    under ``use_sim_time``). The decoders, which every mapping step refines, are shared by all blocks: a
    block that no step changes keeps the surface of its last extraction until then.

    ``map_cloud`` (PointCloud2, transient local) holds the mesh's vertices with their colours, every block's,
    from the same extraction (kept per block, so a publication re-extracts only what changed); it goes out
    when it changed or a subscriber came. ``map_grid`` (OccupancyGrid, transient local) is a horizontal slice
    of the SDF at ``grid_height_m`` of ``frame_id`` (:mod:`neb_slam_core.occupancy`: unknown where no
    keyframe looked), computed at each periodic publication while someone subscribes. Nothing is computed
    for a topic nobody subscribes.

    Args:
        frame_id: frame of the mesh.
        mesh_cfg: the engine's mesh settings (:class:`~neb_slam_core.config.MeshConfig`).
        out_dir: where ``save_mesh`` and ``save_map`` write (created on first use).
        mesh_period_s: publish the mesh this often (0: only on ``save_mesh`` and at shutdown).
        block_map: the map to mesh, or None while there is nothing to mesh.
        observed_points: the world points that cull the mesh (the keyframes' observed points).
        write_map: writes the map checkpoint into a run directory; returns its path.
        block_revisions: per block id, how many optimisation calls changed its table
            (:attr:`neb_slam_core.mapping.mapper.Mapper.revisions`).
        topics: the ``map_grid`` slice (:class:`MapTopicOptions`).
        truncation_m: the engine's truncation (the SDF's unit).
    """

    def __init__(
        self,
        node,
        frame_id: str,
        mesh_cfg,
        out_dir: Path,
        mesh_period_s: float,
        block_map: Callable[[], object | None],
        observed_points: Callable[[], np.ndarray],
        write_map: Callable[[RunDirectory], Path],
        block_revisions: Callable[[], dict[int, int]],
        topics: MapTopicOptions = MapTopicOptions(),
        truncation_m: float = 0.1,
    ):
        self.frame_id = frame_id
        self.topics = topics
        self.truncation_m = truncation_m
        self.mesh_cfg = mesh_cfg
        self.out_dir = out_dir
        self._node = node
        self._block_map = block_map
        self._observed_points = observed_points
        self._write_map = write_map
        self._block_revisions = block_revisions
        self.T_map_world = np.eye(4)  # the engine's world in frame_id (:meth:`align`)
        self._markers: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # block id -> (points, colors) published
        self._extracted: dict[int, int] = {}  # block id -> its revision when last extracted
        self._subscribers = 0  # subscription count at the last publication
        self._cloud: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # block id -> (vertices in frame_id, rgb)
        self._cloud_changed = False
        self._cloud_subscribers = 0
        self.pub_mesh = node.create_publisher(
            MarkerArray,
            "mesh",
            qos.state(),
            event_callbacks=PublisherEventCallbacks(matched=self._on_matched),
        )
        self.pub_cloud = node.create_publisher(PointCloud2, "map_cloud", qos.state())
        self.pub_grid = node.create_publisher(OccupancyGrid, "map_grid", qos.state())
        node.worker_service("save_mesh", self.save_mesh)
        node.worker_service("save_map", self.save_map)
        if mesh_period_s > 0:
            node.worker_timer(mesh_period_s, self.publish_current_map, "publish_map")

    def align(self, T_map_world: np.ndarray) -> None:
        """Publish from now on in ``frame_id`` = the engine's world moved by ``T_map_world``; markers
        already sent are sent again in it (files keep the world frame)."""
        T = np.asarray(T_map_world, dtype=np.float64)
        if np.array_equal(T, self.T_map_world):
            return
        self.T_map_world = T
        self._markers.clear()
        self._cloud.clear()
        self._extracted.clear()

    def run_dir(self) -> RunDirectory:
        self.out_dir.mkdir(parents=True, exist_ok=True)
        return RunDirectory(self.out_dir)

    def _map(self):
        block_map = self._block_map()
        if block_map is None:
            raise RuntimeError("nothing mapped yet")
        if len(block_map) == 0:
            raise RuntimeError("the map has no blocks yet")
        return block_map

    def mesh(self):
        """The current mesh (marching cubes over every block, culled to what the keyframes observed)."""
        from neb_slam_core.mesh import extract_mesh

        return extract_mesh(self._map(), self.mesh_cfg, self._observed_points())

    # ------------------------------------------------------------------ publication (worker thread)

    def _send(self, parts: dict[int, tuple[np.ndarray, np.ndarray] | None], ack_timeout_s: float = 0.0) -> None:
        """Publish the markers ``parts`` (None: DELETE) stamped with the node's clock."""
        ns = self._node.get_clock().now().nanoseconds
        if cdr.supported():
            msg = cdr.mesh_marker_array(parts, ns, self.frame_id)
        else:
            msg = conversions.mesh_marker_msgs(parts, ns, self.frame_id)
        self.pub_mesh.publish(msg)
        if ack_timeout_s > 0:
            self.pub_mesh.wait_for_all_acked(Duration(seconds=ack_timeout_s))

    def _keep(self, parts: dict[int, tuple]) -> dict[int, tuple[np.ndarray, np.ndarray] | None]:
        """Take mesh ``parts`` (block id -> vertices, faces, colours; empty for a block without triangles) as
        the blocks' markers; returns the markers to send for them (None: DELETE a marker sent before)."""
        out: dict[int, tuple[np.ndarray, np.ndarray] | None] = {}
        R, t = self.T_map_world[:3, :3], self.T_map_world[:3, 3]
        for b, (verts, faces, colours) in parts.items():
            if len(faces):
                verts = np.asarray(verts, dtype=np.float64) @ R.T + t
                out[b] = self._markers[b] = conversions.triangle_list(verts, faces, colours)
                self._cloud[b] = (verts, np.asarray(colours)[:, :3])
                self._cloud_changed = True
            else:
                self._cloud_changed |= self._cloud.pop(b, None) is not None
                if self._markers.pop(b, None) is not None:
                    out[b] = None
        return out

    def publish_current_map(self) -> str:
        """The periodic publication: ``mesh`` with the blocks whose part changed since the last one (every
        kept marker when the subscriber count rose since), ``map_cloud`` when it changed, ``map_grid``; only
        to topics someone subscribes, and nothing is extracted while nobody does."""
        from neb_slam_core.mesh import affected_blocks, extract_block_meshes

        n_mesh = self.pub_mesh.get_subscription_count()
        n_cloud = self.pub_cloud.get_subscription_count()
        n_grid = self.pub_grid.get_subscription_count()
        if n_mesh == 0:
            self._subscribers = 0
        if n_mesh + n_cloud + n_grid == 0:
            self._cloud_subscribers = 0
            return "no subscriber: nothing extracted"
        block_map = self._block_map()
        if block_map is None or len(block_map) == 0:
            return "nothing mapped yet"
        said = []
        if n_mesh or n_cloud:
            revisions = dict(self._block_revisions())
            now = {b: revisions.get(b, 0) for b in range(len(block_map))}
            changed = [b for b, r in now.items() if self._extracted.get(b) != r]
            redo = affected_blocks(block_map, self.mesh_cfg, changed)
            parts = extract_block_meshes(block_map, self.mesh_cfg, self._observed_points(), redo) if redo else {}
            self._extracted.update({b: now[b] for b in redo})
            send = self._keep(parts)
            said.append(f"{len(redo)} blocks re-extracted")
            if n_mesh:
                if n_mesh > self._subscribers:  # someone new: everything, not just what changed
                    send = {**self._markers, **send}
                self._subscribers = n_mesh
                if send:
                    self._send(send)
                    said.append(f"{len(send)} markers published")
            if n_cloud and (self._cloud_changed or n_cloud > self._cloud_subscribers):
                said.append(self._send_cloud())
            self._cloud_subscribers = n_cloud
        if n_grid:
            said.append(self._send_grid(block_map))
        return ", ".join(said)

    def _send_cloud(self) -> str:
        parts = list(self._cloud.values())
        points = np.concatenate([v for v, _ in parts]) if parts else np.zeros((0, 3))
        rgb = np.concatenate([c for _, c in parts]) if parts else np.zeros((0, 3), np.uint8)
        ns = self._node.get_clock().now().nanoseconds
        self.pub_cloud.publish(conversions.point_cloud_msg(points, rgb, ns, self.frame_id))
        self._cloud_changed = False
        return f"{len(points)} cloud points"

    def _send_grid(self, block_map) -> str:
        from neb_slam_core.geometry.se3 import invert
        from neb_slam_core.occupancy import occupancy_slice

        o = self.topics
        grid = occupancy_slice(
            block_map, self.truncation_m, invert(self.T_map_world), o.grid_height_m, o.grid_resolution_m
        )
        ns = self._node.get_clock().now().nanoseconds
        self.pub_grid.publish(conversions.occupancy_grid_msg(grid, ns, self.frame_id))
        return f"grid {grid.cells.shape[1]}x{grid.cells.shape[0]}"

    def publish(self, mesh, ack_timeout_s: float = 0.0) -> str:
        """Publish the whole mesh ``mesh`` (of every block: ``save_mesh``, the final one), every block's
        marker, with a DELETE for a block that no longer has triangles; with ``ack_timeout_s``, then wait up
        to that long until every matched subscriber has acknowledged it. Returns what was published, for
        the log."""
        from neb_slam_core.mesh import split_by_block

        block_map = self._map()
        parts = split_by_block(mesh, block_map)
        empty = (np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), np.zeros((0, 3), dtype=np.uint8))
        send = self._keep({b: parts.get(b, empty) for b in range(len(block_map))})  # every block
        revisions = dict(self._block_revisions())
        self._extracted = {b: revisions.get(b, 0) for b in range(len(block_map))}
        self._subscribers = self.pub_mesh.get_subscription_count()
        self._send(send, ack_timeout_s)
        if self.pub_cloud.get_subscription_count():
            self._send_cloud()
            self.pub_cloud.wait_for_all_acked(Duration(seconds=ack_timeout_s))
        if self.pub_grid.get_subscription_count():
            self._send_grid(block_map)
            self.pub_grid.wait_for_all_acked(Duration(seconds=ack_timeout_s))
        return f"{len(mesh.faces)} faces"

    def _on_matched(self, info) -> None:
        """A subscriber matched (executor thread): hand it every kept marker at once, from the worker."""
        if info.current_count_change > 0:
            self._node.submit(self._republish, "republish_mesh", coalesce=True)

    def _republish(self) -> str:
        if not self._markers:
            return "no mesh published yet"
        self._send(dict(self._markers))
        self._subscribers = max(self._subscribers, self.pub_mesh.get_subscription_count())
        return f"{len(self._markers)} markers republished"

    # ------------------------------------------------------------------ services (worker thread)

    def save_mesh(self, ack_timeout_s: float = 0.0) -> str:
        """Write ``mesh.ply`` and publish the same mesh; returns the file's path."""
        mesh = self.mesh()
        path = self.run_dir().write_mesh(mesh)
        self.publish(mesh, ack_timeout_s)
        return str(path)

    def save_map(self) -> str:
        if self._block_map() is None:
            raise RuntimeError("nothing mapped yet")
        return str(self._write_map(self.run_dir()))
