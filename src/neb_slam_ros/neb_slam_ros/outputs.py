"""What the nodes publish for other stacks, defined once for every node that publishes it.

- :class:`PoseOutputs`: ``pose``, ``odometry``, ``path`` and ``blocks`` of the tracking side (the
  ``tracker`` and the one-process ``slam``).
- :class:`MapOutputs`: ``mesh`` and the ``save_mesh`` / ``save_map`` services of the mapping side (the
  ``mapper`` and ``slam``), run in the node's worker thread (the map's owner).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from nav_msgs.msg import Path as PathMsg
from rclpy.duration import Duration
from visualization_msgs.msg import MarkerArray

from neb_slam_core.io.run_dir import RunDirectory
from neb_slam_core.io.trajectory import Trajectory
from neb_slam_core.types import StepResult
from neb_slam_ros import conversions, qos

#: at shutdown, how long a published mesh may wait for every subscriber's acknowledgement (the process
#: ends right after; a reliable message not yet received would be lost with it)
FINAL_MESH_ACK_S = 5.0

#: the camera frame named in odometry's child_frame_id
CAMERA_FRAME = "camera"


class PoseOutputs:
    """``pose`` and ``odometry`` per frame, ``path`` and ``blocks`` (transient local) of ``node``."""

    def __init__(self, node, frame_id: str, block_edge_m: float):
        self.frame_id = frame_id
        self.block_edge_m = block_edge_m
        self.pub_pose = node.create_publisher(PoseStamped, "pose", qos.stream())
        self.pub_odom = node.create_publisher(Odometry, "odometry", qos.stream())
        self.pub_path = node.create_publisher(PathMsg, "path", qos.state())
        self.pub_blocks = node.create_publisher(MarkerArray, "blocks", qos.state())
        self._prev: tuple[np.ndarray, int] | None = None

    def publish_path(self, trajectory: Trajectory) -> None:
        self.pub_path.publish(conversions.path_msg(trajectory.stamps_ns, trajectory.poses, self.frame_id))

    def publish_blocks(self, centres: np.ndarray, stamp_ns: int) -> None:
        self.pub_blocks.publish(conversions.block_markers(centres, self.block_edge_m, stamp_ns, self.frame_id))

    def publish_frame(self, r: StepResult) -> None:
        """``odometry`` (twist from the previous frame) and ``pose`` of a processed frame. The pose goes
        last: lockstep replay publishes the next frame (or ends the process) when it arrives."""
        prev_T, prev_ns = self._prev if self._prev is not None else (None, None)
        self.pub_odom.publish(
            conversions.odometry_msg(r.T_world_cam, r.stamp_ns, prev_T, prev_ns, self.frame_id, CAMERA_FRAME)
        )
        self._prev = (r.T_world_cam, r.stamp_ns)
        self.pub_pose.publish(conversions.pose_msg(r.T_world_cam, r.stamp_ns, self.frame_id))


def block_centres(block_map) -> np.ndarray:
    """``(M, 3)`` float64 centres of the map's blocks."""
    return block_map.centres().detach().cpu().double().numpy().reshape(-1, 3)


def split_by_block(mesh, block_map) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """A mesh's triangles grouped by the block that holds their centroid (the lowest id where blocks
    overlap): block id -> (vertices, faces, vertex colours), the vertex arrays shared."""
    verts, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    if len(faces) == 0:
        return {}
    colours = np.asarray(mesh.visual.vertex_colors)[:, :3]
    centroids = torch.as_tensor(verts[faces].mean(axis=1), dtype=torch.float32, device=block_map.device)
    inside = block_map.contains(centroids).cpu()
    owner = torch.where(inside.any(dim=1), inside.float().argmax(dim=1), -1).numpy()
    return {int(b): (verts, faces[owner == b], colours) for b in np.unique(owner) if b >= 0}


class MapOutputs:
    """The mesh topic and the map's services of ``node`` (a :class:`~neb_slam_ros.node.NebNode`).

    Args:
        frame_id: frame of the mesh.
        mesh_cfg: the engine's mesh settings (:class:`~neb_slam_core.config.MeshConfig`).
        out_dir: where ``save_mesh`` and ``save_map`` write (created on first use).
        mesh_period_s: publish the mesh this often (0: only on ``save_mesh`` and at shutdown).
        block_map: the map to mesh, or None while there is nothing to mesh.
        observed_points: the world points that cull the mesh (the keyframes' observed points).
        write_map: writes the map checkpoint into a run directory; returns its path.
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
    ):
        self.frame_id = frame_id
        self.mesh_cfg = mesh_cfg
        self.out_dir = out_dir
        self._block_map = block_map
        self._observed_points = observed_points
        self._write_map = write_map
        self.pub_mesh = node.create_publisher(MarkerArray, "mesh", qos.state())
        node.worker_service("save_mesh", self.save_mesh)
        node.worker_service("save_map", self.save_map)
        if mesh_period_s > 0:
            node.worker_timer(mesh_period_s, self.publish_current_mesh, "publish_mesh")

    def run_dir(self) -> RunDirectory:
        self.out_dir.mkdir(parents=True, exist_ok=True)
        return RunDirectory(self.out_dir)

    def mesh(self):
        """The current mesh (marching cubes over every block, culled to what the keyframes observed)."""
        from neb_slam_core.mesh import extract_mesh

        block_map = self._block_map()
        if block_map is None:
            raise RuntimeError("nothing mapped yet")
        if len(block_map) == 0:
            raise RuntimeError("the map has no blocks yet")
        return extract_mesh(block_map, self.mesh_cfg, self._observed_points())

    def publish(self, mesh, ack_timeout_s: float = 0.0) -> str:
        """Publish ``mesh`` as one marker per block; with ``ack_timeout_s``, then wait up to that long until
        every matched subscriber has acknowledged it. Returns what was published, for the log."""
        block_map = self._block_map()
        self.pub_mesh.publish(conversions.mesh_markers(split_by_block(mesh, block_map), time.time_ns(), self.frame_id))
        if ack_timeout_s > 0:
            self.pub_mesh.wait_for_all_acked(Duration(seconds=ack_timeout_s))
        return f"{len(mesh.faces)} faces"

    def publish_current_mesh(self) -> str:
        if self._block_map() is None:
            return "nothing mapped yet"
        return self.publish(self.mesh())

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
