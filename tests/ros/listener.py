"""An independent subscriber process (what another robot's stack would be): it records what the suite
publishes on pose, path, blocks and mesh (the markers it holds, each message updating the blocks it names),
odometry (each pose covariance's diagonal), /diagnostics (the tracking statuses), /tf and /tf_static (every
transform), map_cloud and map_grid (their sizes), and on SIGINT writes a JSON summary to the path given as
argv[1]."""

import json
import sys

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import OccupancyGrid, Odometry, Path
from rclpy.executors import ExternalShutdownException
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import MarkerArray

seen = {
    "pose_stamps_ns": [],
    "poses": [],  # [stamp, frame_id, x, y, z, qx, qy, qz, qw]
    "tf": [],  # [stamp, parent, child, x, y, z, qx, qy, qz, qw]
    "tf_static": [],
    "map_cloud_points": 0,  # of the latest map_cloud
    "map_grid": None,  # [width, height, cells unknown, free, occupied, frame] of the latest map_grid
    "path_lengths": [],
    "path_stamps_ns": [],
    "block_ids": [],
    "mesh_markers": 0,
    "mesh_points": 0,
    "odometry": [],  # [stamp, the covariance's diagonal]
    "diagnostics": [],  # [level, message, {key: value}] of the tracking statuses, in order
}


def stamp(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def main() -> None:
    rclpy.init()
    node = rclpy.create_node("listener", namespace="neb_slam")
    state = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    stream = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)

    def on_pose(m):
        seen["pose_stamps_ns"].append(stamp(m))
        p, q = m.pose.position, m.pose.orientation
        seen["poses"].append([stamp(m), m.header.frame_id, p.x, p.y, p.z, q.x, q.y, q.z, q.w])

    def on_tf(key, m):
        for t in m.transforms:
            v, q = t.transform.translation, t.transform.rotation
            seen[key].append([stamp(t), t.header.frame_id, t.child_frame_id, v.x, v.y, v.z, q.x, q.y, q.z, q.w])

    node.create_subscription(PoseStamped, "pose", on_pose, stream)
    node.create_subscription(TFMessage, "/tf", lambda m: on_tf("tf", m), stream)
    node.create_subscription(TFMessage, "/tf_static", lambda m: on_tf("tf_static", m), state)

    def on_grid(m):
        cells = list(m.data)
        counts = [sum(1 for c in cells if c == v) for v in (-1, 0, 100)]
        seen["map_grid"] = [m.info.width, m.info.height, *counts, m.header.frame_id]

    node.create_subscription(PointCloud2, "map_cloud", lambda m: seen.update(map_cloud_points=m.width), state)
    node.create_subscription(OccupancyGrid, "map_grid", on_grid, state)

    def on_path(m):
        seen["path_lengths"].append(len(m.poses))
        seen["path_stamps_ns"] = [stamp(p) for p in m.poses]
        if m.poses:
            q, o = m.poses[0].pose.position, m.poses[0].pose.orientation
            seen["path_first"] = [q.x, q.y, q.z, o.x, o.y, o.z, o.w]  # the first frame's pose

    node.create_subscription(Path, "path", on_path, state)

    def on_blocks(m):
        seen["block_ids"] = sorted(k.id for k in m.markers)

    mesh: dict[int, int] = {}  # block id -> points of its marker, kept by id as RViz keeps them

    def on_mesh(m):
        for k in m.markers:
            if k.action == k.DELETE:
                mesh.pop(k.id, None)
            else:
                mesh[k.id] = len(k.points)
        seen["mesh_markers"] = len(mesh)
        seen["mesh_points"] = sum(mesh.values())

    node.create_subscription(
        Odometry, "odometry", lambda m: seen["odometry"].append([stamp(m), list(m.pose.covariance)[::7]]), stream
    )

    def on_diagnostics(m):
        for st in m.status:
            if st.name.endswith(": tracking"):
                values = {k.key: k.value for k in st.values}
                seen["diagnostics"].append([int.from_bytes(st.level, "little"), st.message, values])

    node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, stream)
    node.create_subscription(MarkerArray, "blocks", on_blocks, state)
    node.create_subscription(MarkerArray, "mesh", on_mesh, state)
    print("listener ready", file=sys.stderr, flush=True)
    try:
        # in slices, as the nodes' own main does (neb_slam_ros._node_main): rclpy.spin can miss the
        # SIGINT's wake-up of its wait set and never return
        while rclpy.ok():
            rclpy.spin_once(node, timeout_sec=0.5)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    with open(sys.argv[1], "w") as f:
        json.dump(seen, f)


if __name__ == "__main__":
    main()
