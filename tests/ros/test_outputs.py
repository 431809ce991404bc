"""The large outputs, ``mesh`` and ``path`` (:mod:`neb_slam_ros.outputs`), in one process on a map whose SDF is
known in closed form: a changed block's marker holds what the per-point message conversion holds; a block
that loses its triangles gets a DELETE marker; nothing is extracted while nobody subscribes, and a new
subscriber gets every block; the path after a correction is the corrected trajectory while frames in
between publish nothing; stamps come from the node's clock. The serialized messages read back, through
the middleware's own deserializer, as the message objects they stand for."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch

pytestmark = [pytest.mark.ros, pytest.mark.filterwarnings("ignore::DeprecationWarning:lark.*")]

PLANE_Z = 0.311
SIM_NS = 1234 * 1_000_000_000 + 5  # the node's (simulated) clock


class SpyPublisher:
    """Stands in for a publisher: records what is published, with a settable subscriber count."""

    def __init__(self, subscribers: int = 1):
        self.subscribers = subscribers
        self.sent: list = []

    def get_subscription_count(self) -> int:
        return self.subscribers

    def publish(self, msg) -> None:
        self.sent.append(msg)

    def wait_for_all_acked(self, timeout) -> bool:
        return True


def _read(msg, msg_type):
    from rclpy.serialization import deserialize_message

    return deserialize_message(msg, msg_type) if isinstance(msg, bytes) else msg


@pytest.fixture(scope="module")
def node(ros_env):
    """A node of ours on simulated time, its clock set to :data:`SIM_NS`."""
    rclpy = pytest.importorskip("rclpy")
    from rclpy.parameter import Parameter
    from rclpy.signals import SignalHandlerOptions
    from rclpy.time import Time

    from neb_slam_ros.node import NebNode

    saved = {key: os.environ.get(key) for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")}
    os.environ.update({key: ros_env[key] for key in saved})
    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    n = NebNode(
        "outputs_test",
        with_config=False,
        namespace="/",
        context=context,
        parameter_overrides=[Parameter("use_sim_time", Parameter.Type.BOOL, True)],
    )
    n.get_clock().set_ros_time_override(Time(nanoseconds=SIM_NS))
    yield n
    n.destroy_node()
    rclpy.try_shutdown(context=context)
    for key, value in saved.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value


def _plane_map(centres):
    """Blocks of 2 m over the plane z = PLANE_Z (coloured by x), which ends at x = ``cut`` (settable)."""
    from neb_slam_core.config import BlockConfig, HashGridConfig
    from neb_slam_core.scene.block_map import BlockMap, MapSample

    class PlaneMap(BlockMap):
        cut = np.inf

        def query(self, points_world, block_ids=None, with_colour=True):
            valid = self.contains(points_world, block_ids).any(dim=1)
            sdf = (points_world[:, 2] - PLANE_Z) / 0.1
            sdf = torch.where(points_world[:, 0] < self.cut, sdf, torch.ones_like(sdf))  # no surface past the cut
            rgb = torch.stack([(points_world[:, 0] / 4 + 0.5).clamp(0, 1)] * 3, dim=1) * valid[:, None]
            return MapSample(torch.where(valid, sdf, torch.zeros_like(sdf)), rgb, valid)

    grid = HashGridConfig(n_levels=2, n_features_per_level=2, log2_hashmap_size=10, base_resolution=4, max_resolution=8)
    m = PlaneMap(BlockConfig(edge_m=2.0, grid=grid), grid_backend="reference")
    for c in centres:
        m.add_block(c)
    return m


def _observed(x0, x1, y0=-0.8, y1=0.8, step=0.02):
    xs, ys = np.meshgrid(np.arange(x0, x1, step), np.arange(y0, y1, step))
    return np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, PLANE_Z)], axis=1)


def _map_outputs(node, block_map, observed, revisions, tmp_path):
    from neb_slam_core.config import MeshConfig
    from neb_slam_ros.outputs import MapOutputs

    out = MapOutputs(
        node,
        "map",
        MeshConfig(voxel_size_m=0.05, cull_distance_m=0.1),
        tmp_path,
        0.0,
        block_map=lambda: block_map,
        observed_points=lambda: observed,
        write_map=lambda run_dir: run_dir.file("map.pt"),
        block_revisions=lambda: revisions,
    )
    out.pub_mesh = SpyPublisher()
    return out


def _markers(msg) -> dict:
    from visualization_msgs.msg import MarkerArray

    return {m.id: m for m in _read(msg, MarkerArray).markers}


def _triangles(points, colors) -> np.ndarray:
    """Triangles as rows of 3 corners x (x, y, z, r, g, b, a), in a canonical order."""
    rows = np.concatenate([np.asarray(points, float), np.asarray(colors, float)], axis=1).reshape(-1, 21)
    return rows[np.lexsort(rows.T[::-1])]


def _old_conversion(mesh, block_map, block_id: int) -> np.ndarray:
    """The triangles the per-point conversion put into block ``block_id``'s marker: one Point and one
    ColorRGBA per corner of the triangles whose centroid lies in the block (blocks that do not overlap)."""
    from geometry_msgs.msg import Point
    from std_msgs.msg import ColorRGBA

    centroids = torch.as_tensor(mesh.vertices[mesh.faces].mean(axis=1), dtype=torch.float32)
    faces = mesh.faces[block_map.contains(centroids)[:, block_id].numpy()]
    corners = faces.reshape(-1)
    colours = np.asarray(mesh.visual.vertex_colors, dtype=np.float64)[corners, :3] / 255.0
    points = [Point(x=x, y=y, z=z) for x, y, z in np.asarray(mesh.vertices)[corners].tolist()]
    colors = [ColorRGBA(r=r, g=g, b=b, a=1.0) for r, g, b in colours.tolist()]
    return _triangles([(p.x, p.y, p.z) for p in points], [(c.r, c.g, c.b, c.a) for c in colors])


def test_a_changed_block_is_published_alone_as_the_per_point_conversion_had_it(node, tmp_path):
    from neb_slam_core.config import MeshConfig
    from neb_slam_core.mesh import extract_mesh

    block_map = _plane_map([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]])  # 1 m apart: neither reaches the other
    observed = _observed(-0.9, 3.9)
    revisions = {0: 1, 1: 1}
    out = _map_outputs(node, block_map, observed, revisions, tmp_path)
    out.publish_current_map()  # the first subscriber: every block
    assert sorted(_markers(out.pub_mesh.sent[-1])) == [0, 1]
    revisions[1] = 2  # a mapping step changed block 1's table
    out.publish_current_map()
    markers = _markers(out.pub_mesh.sent[-1])
    assert list(markers) == [1]  # block 0 did not change: not sent again
    m = markers[1]
    assert (m.ns, m.type, m.action, m.header.frame_id) == ("neb_blocks", m.TRIANGLE_LIST, m.ADD, "map")
    mesh = extract_mesh(block_map, MeshConfig(voxel_size_m=0.05, cull_distance_m=0.1), observed)
    expected = _old_conversion(mesh, block_map, 1)
    got = _triangles([(p.x, p.y, p.z) for p in m.points], [(c.r, c.g, c.b, c.a) for c in m.colors])
    assert len(got) == len(expected) > 100
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9)
    out.publish_current_map()  # nothing changed since: nothing published
    assert len(out.pub_mesh.sent) == 2


def test_a_block_that_loses_its_triangles_gets_a_delete_marker(node, tmp_path):
    block_map = _plane_map([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    revisions = {0: 1, 1: 1}
    out = _map_outputs(node, block_map, _observed(-0.9, 3.9), revisions, tmp_path)
    out.publish_current_map()
    assert len(_markers(out.pub_mesh.sent[-1])[1].points) > 0
    block_map.cut = 1.5  # the surface now ends between the blocks
    revisions[1] = 2
    out.publish_current_map()
    markers = _markers(out.pub_mesh.sent[-1])
    assert list(markers) == [1]
    assert markers[1].action == markers[1].DELETE and len(markers[1].points) == 0
    revisions[1] = 3
    out.publish_current_map()  # still no triangles: nothing to delete again
    assert len(out.pub_mesh.sent) == 2


def test_nothing_is_extracted_without_a_subscriber_and_a_new_one_gets_every_block(node, tmp_path, monkeypatch):
    import neb_slam_core.mesh as mesh_module

    calls: list[list[int]] = []
    extract = mesh_module.extract_block_meshes

    def spy(block_map, cfg, observed, block_ids):
        calls.append(sorted(block_ids))
        return extract(block_map, cfg, observed, block_ids)

    monkeypatch.setattr(mesh_module, "extract_block_meshes", spy)
    block_map = _plane_map([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    revisions = {0: 1, 1: 1}
    out = _map_outputs(node, block_map, _observed(-0.9, 3.9), revisions, tmp_path)
    out.pub_mesh.subscribers = 0
    for step in range(2, 5):
        revisions[0] = step
        assert "no subscriber" in out.publish_current_map()
    assert calls == [] and out.pub_mesh.sent == []
    out.pub_mesh.subscribers = 1
    out.publish_current_map()
    assert calls == [[0, 1]] and sorted(_markers(out.pub_mesh.sent[-1])) == [0, 1]
    revisions[0] = 5
    out.pub_mesh.subscribers = 2  # a second subscriber arrived since: every block again, block 0 re-extracted
    out.publish_current_map()
    assert calls[-1] == [0] and sorted(_markers(out.pub_mesh.sent[-1])) == [0, 1]


def test_the_mesh_is_stamped_with_the_node_clock(node, tmp_path):
    block_map = _plane_map([[0.0, 0.0, 0.0]])
    out = _map_outputs(node, block_map, _observed(-0.9, 0.9), {0: 1}, tmp_path)
    out.publish_current_map()
    stamp = _markers(out.pub_mesh.sent[-1])[0].header.stamp
    assert stamp.sec * 1_000_000_000 + stamp.nanosec == SIM_NS  # simulated time, not the wall clock


def _cloud_rows(msg) -> np.ndarray:
    """A map_cloud message's points as rows (x, y, z, r, g, b), read from its bytes by its field layout."""
    from sensor_msgs.msg import PointCloud2

    msg = _read(msg, PointCloud2)
    assert [(f.name, f.offset, f.datatype) for f in msg.fields] == [
        ("x", 0, 7),
        ("y", 4, 7),
        ("z", 8, 7),
        ("rgb", 12, 7),
    ]  # 7: FLOAT32
    assert msg.point_step == 16 and msg.row_step == 16 * msg.width and msg.height == 1
    raw = np.frombuffer(bytes(msg.data), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
    rgb = np.stack([(raw["rgb"] >> 16) & 255, (raw["rgb"] >> 8) & 255, raw["rgb"] & 255], axis=1)
    rows = np.concatenate([np.stack([raw["x"], raw["y"], raw["z"]], axis=1).astype(np.float64), rgb], axis=1)
    return rows[np.lexsort(rows.T[::-1])]


def test_the_map_cloud_holds_every_blocks_mesh_vertices_in_the_map_frame(node, tmp_path):
    from neb_slam_core.config import MeshConfig
    from neb_slam_core.mesh import extract_block_meshes

    block_map = _plane_map([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    observed = _observed(-0.9, 3.9)
    revisions = {0: 1, 1: 1}
    out = _map_outputs(node, block_map, observed, revisions, tmp_path)
    out.pub_mesh.subscribers = 0  # only the cloud is wanted: it is extracted all the same
    out.pub_cloud = SpyPublisher()
    T = np.eye(4)
    T[:3, :3] = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]
    T[:3, 3] = [0.5, -0.2, 1.0]
    out.align(T)
    out.publish_current_map()
    assert out.pub_mesh.sent == [] and len(out.pub_cloud.sent) == 1
    parts = extract_block_meshes(block_map, MeshConfig(voxel_size_m=0.05, cull_distance_m=0.1), observed, [0, 1])
    verts = np.concatenate([v for v, _, _ in parts.values()]) @ T[:3, :3].T + T[:3, 3]
    rgb = np.concatenate([c for _, _, c in parts.values()]).astype(np.float64)
    expected = np.concatenate([verts, rgb], axis=1)
    expected = expected[np.lexsort(expected.T[::-1])]
    got = _cloud_rows(out.pub_cloud.sent[0])
    assert len(got) == len(expected) > 100
    np.testing.assert_allclose(got[:, :3], expected[:, :3], atol=1e-6)  # float32 coordinates
    np.testing.assert_array_equal(got[:, 3:], expected[:, 3:])
    out.publish_current_map()  # nothing changed: the latched cloud stands
    assert len(out.pub_cloud.sent) == 1
    block_map.cut = 1.5  # block 1 loses its surface: the cloud goes out without it
    revisions[1] = 2
    out.publish_current_map()
    assert len(out.pub_cloud.sent) == 2 and len(_cloud_rows(out.pub_cloud.sent[1])) < len(got)


def test_the_map_grid_is_the_sdf_slice_at_its_height_unknown_where_unseen(node, tmp_path):
    from nav_msgs.msg import OccupancyGrid

    from neb_slam_ros.outputs import MapTopicOptions

    block_map = _plane_map([[0.0, 0.0, 0.0]])  # x, y in -1..1; the plane z = PLANE_Z
    for b in block_map.blocks:
        b.observed[:] = True
        b.observed[: b.observed.shape[0] // 2] = False  # x < 0 unseen
    out = _map_outputs(node, block_map, _observed(-0.9, 0.9), {0: 1}, tmp_path)
    out.pub_mesh.subscribers = 0
    out.pub_grid = SpyPublisher()
    for height, inside in ((0.3, 100), (0.7, 0)):  # 1.1 cm below the plane: occupied; 39 cm above: free
        out.topics = MapTopicOptions(grid_height_m=height, grid_resolution_m=0.25)
        out.truncation_m = 0.1  # the plane map's SDF unit
        out.publish_current_map()
        grid = _read(out.pub_grid.sent[-1], OccupancyGrid)
        assert grid.header.frame_id == "map"
        assert (grid.info.width, grid.info.height, grid.info.resolution) == (8, 8, 0.25)
        o = grid.info.origin.position
        assert (o.x, o.y, o.z) == (-1.0, -1.0, height)
        cells = np.array(grid.data, dtype=np.int8).reshape(8, 8)
        assert (cells[:, :4] == -1).all() and (cells[:, 4:] == inside).all(), cells


def _frontend(n_frames: int):
    """A frontend holding ``n_frames`` frames, a keyframe every 5th, as :meth:`Frontend.step` records them."""
    from scipy.spatial.transform import Rotation

    from neb_slam_core.config import SlamConfig
    from neb_slam_core.slam import Frontend, new_block_map

    cfg = SlamConfig()
    frontend = Frontend(cfg, new_block_map(cfg))
    rng = np.random.default_rng(0)
    for i in range(n_frames):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(0.1 * rng.normal(size=3)).as_matrix()
        T[:3, 3] = [0.05 * i, 0.01 * i, 0.0]
        if i % 5 == 0:
            frontend._add_keyframe(T)
        frontend._record(1_000_000_000 + 33_000_000 * i, T)
    return frontend


def test_the_path_after_a_correction_is_the_corrected_trajectory_and_frames_between_publish_nothing(node):
    from nav_msgs.msg import Path

    from neb_slam_ros import conversions
    from neb_slam_ros.outputs import PathOutput

    frontend = _frontend(20)
    reads = []

    def trajectory():
        reads.append(1)
        return frontend.trajectory()

    pub = SpyPublisher()
    out = PathOutput(node, pub, "map", 3600.0, trajectory)
    try:
        for _ in range(20):
            out.changed()  # a frame: only the first goes out within the period
        assert len(pub.sent) == 1 and len(reads) == 1 and out.pending
        before = frontend.trajectory().poses
        corrected = np.stack(frontend.keyframe_poses)
        corrected[2:, :3, 3] += [0.0, 0.3, -0.1]  # a loop correction moves keyframes 2..
        frontend.set_keyframe_poses(corrected)
        out.changed(now=True)
        assert len(pub.sent) == 2 and not out.pending
        after = frontend.trajectory()
        assert np.abs(after.poses - before).max() > 0.05
        expected = conversions.path_msg(after.stamps_ns, after.poses, "map", int(after.stamps_ns[-1]))
        got = _read(pub.sent[-1], Path)
        assert got == expected and len(got.poses) == 20
        pub.subscribers = 0
        out.changed(now=True)  # nobody to send it to: nothing built
        assert len(pub.sent) == 2 and len(reads) == 2 and out.pending
        pub.subscribers = 1
        out.publish_pending()  # what the timer does once the period has passed
        assert len(pub.sent) == 3
    finally:
        out.timer.cancel()
        node.destroy_timer(out.timer)


def test_serialized_markers_and_paths_read_back_as_the_message_objects():
    from rclpy.serialization import deserialize_message, serialize_message
    from scipy.spatial.transform import Rotation
    from visualization_msgs.msg import MarkerArray

    from neb_slam_ros import cdr, conversions

    assert cdr.supported()
    rng = np.random.default_rng(1)
    verts = rng.normal(size=(40, 3))
    colours = rng.integers(0, 256, size=(40, 3)).astype(np.uint8)
    for frame_id in ("", "m", "map", "odom_frame"):
        parts = {b: conversions.triangle_list(verts, rng.integers(0, 40, size=(b + 1, 3)), colours) for b in (0, 3)}
        parts[7] = None
        expected = conversions.mesh_marker_msgs(parts, SIM_NS, frame_id)
        data = cdr.mesh_marker_array(parts, SIM_NS, frame_id)
        assert len(data) == len(serialize_message(expected))
        assert deserialize_message(data, MarkerArray) == expected
        for n in (0, 1, 2, 5):
            poses = np.tile(np.eye(4), (n, 1, 1))
            poses[:, :3, :3] = Rotation.random(n, random_state=n).as_matrix() if n else poses[:, :3, :3]
            poses[:, :3, 3] = rng.normal(size=(n, 3))
            stamps = rng.integers(0, 10**12, size=n)
            expected = conversions.path_msg(stamps, poses, frame_id, 42)
            data = cdr.path(stamps, cdr.pose_rows(poses), frame_id, 42)
            assert len(data) == len(serialize_message(expected))
            assert deserialize_message(data, type(expected)) == expected
