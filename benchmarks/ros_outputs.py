"""Cost of the nodes' two growing outputs, ``mesh`` and ``path``, against the reference code in one run.

The reference is the code of commit ``REFERENCE_COMMIT`` of ``benchmarks/ros_outputs_reference.py``, read
from git and run unchanged: ``path`` rebuilt from the whole trajectory after every frame with one
PoseStamped per pose, ``mesh`` re-extracted over every block on each period with one Point and one
ColorRGBA per triangle corner. Both sides publish through real publishers of a node on a private ROS
domain (localhost only), to a subscription of the same process, which never spins: what is timed is what
the publishing node pays.

**Mesh**, on a map of ``--blocks`` blocks (15): 5 m blocks on a grid 4.5 m apart (they overlap by half a
metre, as allocation leaves them), the engine's default grid and decoders evaluated with the C++ kernels
on every query, whose SDF and colour are then replaced by a closed-form hall: a floor and, along the
hall's sides, walls, all observed (the points that cull the mesh are sampled on them). Extraction thus
pays the real network cost and finds known surfaces. ``--voxel`` (0.1 m) keeps the reference's full
extraction within seconds. Timed, per publication (median of ``--repeats``):

- ``mesh_old_ms``: the reference ``MapOutputs.publish`` of the reference ``extract_mesh`` (every block);
- ``mesh_new_all_ms``: ``MapOutputs.publish_current_map`` after every block's table changed (every block
  re-extracted, every marker sent);
- ``mesh_new_changed_ms``: the same after ``--changed`` blocks changed (those and the blocks within their
  reach are re-extracted and sent: ``mesh_new_changed_blocks``);
- ``mesh_conversion_old_ms`` / ``mesh_conversion_new_ms``: the markers alone, from the same parts, built
  and published (reference per-corner objects against the serialized form);
- ``mesh_new_no_subscriber_ms``: the periodic publication with no subscriber (nothing is built).

The new markers are checked against the reference's: as many triangles (``mesh_triangles``), the
largest corner difference (``mesh_max_point_diff_m``) and colour difference (``mesh_max_colour_diff``,
in 0..1 units) between the two sets of triangles, each sorted.

**Path**, at ``--frames`` frames (10,000), a keyframe every 5th: ``path_old_ms_per_frame`` is the
reference's work per frame (the trajectory, the message, the publication); ``path_new_ms_per_frame`` is
the average over ``--path-frames`` further frames arriving at ``--fps`` on a simulated clock, each one
marking the path changed, every 5th correcting the keyframe poses as a mapping step does, with the path
published at most every ``--path-period`` s (``path_new_publication_ms``: one publication of the whole
path). Keys ending in ``_ratio`` are new / old.

**Map updates** (``benchmarks/map_updates.py``, unless ``--no-updates``): the engine run offline on the
``make demo`` scene and on the TUM fr1_xyz frames (``--updates-frames``: the first this many of each, 0:
all), each mapping step's ``map_update`` built whole in float32 (old) and as the ``live`` preset sends it
(new: the ``live`` preset's ``live.update_*`` settings). ``map_update_mb_per_s_old`` / ``_new`` (demo) and
``map_update_tum_mb_per_s_old`` / ``_new``: MB per second of recording; ``map_update_pose_diff_cm_max``
(and ``_tum_``): how far the poses tracked on the map the new updates build are from those tracked on
the mapper's own map.

Every run ends with ``record`` (``benchmarks/common.py``): ``benchmarks/results/ros_outputs-<date>.json``,
and the same to ``--json FILE``.

Example::

    .venv/bin/python benchmarks/ros_outputs.py --json ros_outputs.json
"""

from __future__ import annotations

import argparse
import os
import random
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from common import load_figures, median_ms, record
from map_updates import figures_for as map_update_figures
from map_updates import live_update_settings
from ros_outputs_reference import load as load_reference

from neb_slam_core.config import MeshConfig, SlamConfig
from neb_slam_core.scene.block_map import BlockMap, MapSample
from neb_slam_core.slam import Frontend, new_block_map

EDGE_M = 5.0
SPACING_M = 4.5
FLOOR_Z = 0.013  # off the lattice's planes
WALL_HEIGHT_M = 2.0


class HallMap(BlockMap):
    """A block map that runs the real query (grid, one-blob, decoders) and then reports a closed-form hall:
    the floor ``z = FLOOR_Z`` and walls ``WALL_HEIGHT_M`` high at ``x = wall_x`` and ``y = wall_y`` (the
    SDF is the distance to the nearest, in truncation units of 0.1 m; colour a pattern of x and y)."""

    def __init__(self, walls_x: tuple[float, float], walls_y: tuple[float, float], **kwargs):
        super().__init__(**kwargs)
        self.walls_x, self.walls_y = walls_x, walls_y

    def query(self, points_world, block_ids=None, with_colour=True):
        q = super().query(points_world, block_ids, with_colour)
        p = points_world
        d = (p[:, 2] - FLOOR_Z).abs()
        low = p[:, 2] < FLOOR_Z + WALL_HEIGHT_M
        for w in self.walls_x:
            d = torch.where(low, torch.minimum(d, (p[:, 0] - w).abs()), d)
        for w in self.walls_y:
            d = torch.where(low, torch.minimum(d, (p[:, 1] - w).abs()), d)
        sdf = torch.where(p[:, 2] < FLOOR_Z, -d, d) / 0.1
        rgb = torch.stack([(torch.sin(p[:, 0]) + 1) / 2, (torch.cos(p[:, 1]) + 1) / 2, (p[:, 2] / 3).clamp(0, 1)], 1)
        mask = q.valid.to(sdf.dtype)
        return MapSample(sdf * mask, rgb * mask[:, None] if with_colour else q.rgb, q.valid)


def hall(n_blocks: int, rng: np.random.Generator) -> tuple[HallMap, np.ndarray]:
    """The map (``n_blocks`` on a grid of 5 columns) and the observed points: the floor and the walls
    sampled every 4 cm."""
    cols = 5
    rows = -(-n_blocks // cols)
    centres = [[SPACING_M * (i % cols), SPACING_M * (i // cols), 1.0] for i in range(n_blocks)]
    lo = np.array([-EDGE_M / 2, -EDGE_M / 2]) + 0.437  # walls off the lattice's planes
    hi = np.array([SPACING_M * (cols - 1), SPACING_M * (rows - 1)]) + EDGE_M / 2 - 0.437
    block_map = HallMap((lo[0], hi[0]), (lo[1], hi[1]))
    for c in centres:
        block_map.add_block(c)
    step = 0.04
    xs, ys = np.arange(lo[0], hi[0], step), np.arange(lo[1], hi[1], step)
    gx, gy = np.meshgrid(xs, ys)
    floor = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, FLOOR_Z)], axis=1)
    zs = np.arange(FLOOR_Z, FLOOR_Z + WALL_HEIGHT_M - 0.1, step)
    walls = []
    for w in (lo[0], hi[0]):
        a, z = np.meshgrid(ys, zs)
        walls.append(np.stack([np.full(a.size, w), a.ravel(), z.ravel()], axis=1))
    for w in (lo[1], hi[1]):
        a, z = np.meshgrid(xs, zs)
        walls.append(np.stack([a.ravel(), np.full(a.size, w), z.ravel()], axis=1))
    observed = np.concatenate([floor, *walls])
    return block_map, observed + rng.normal(scale=0.002, size=observed.shape)


def frontend_with(n_frames: int, rng: np.random.Generator) -> Frontend:
    """A frontend holding ``n_frames`` frames of a walk, a keyframe every 5th, recorded as
    :meth:`Frontend.step` records tracked frames."""
    cfg = SlamConfig()
    frontend = Frontend(cfg, new_block_map(cfg))
    for i in range(n_frames):
        add_frame(frontend, i, rng)
    return frontend


def add_frame(frontend: Frontend, i: int, rng: np.random.Generator) -> None:
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.0, 0.0, 0.01 * i] + 0.02 * rng.normal(size=3)).as_matrix()
    T[:3, 3] = [np.cos(0.001 * i) * 5, np.sin(0.001 * i) * 5, 1.2]
    if i % 5 == 0:
        frontend._add_keyframe(T)
    frontend._record(1_000_000_000 + 33_333_333 * i, T)


def triangles_of(markers) -> tuple[np.ndarray, np.ndarray]:
    """Every ADD marker's triangles: corners ``(T, 3, 3)`` and corner colours ``(T, 3, 4)``."""
    pts, cols = [], []
    for m in markers:
        if m.action == m.DELETE:
            continue
        pts.append(np.array([(p.x, p.y, p.z) for p in m.points]).reshape(-1, 3, 3))
        # float32 on the wire: a message object not yet serialized holds the float64 it was given
        cols.append(np.array([(c.r, c.g, c.b, c.a) for c in m.colors], dtype=np.float32).reshape(-1, 3, 4))
    return np.concatenate(pts), np.concatenate(cols)


def compare_meshes(old_markers, new_markers) -> dict:
    """The two marker sets' triangles (corners and their colours), each set in a canonical order: how
    many, and the largest differences."""
    rows = []
    for markers in (old_markers, new_markers):
        p, c = triangles_of(markers)
        r = np.concatenate([p.reshape(len(p), -1), c.reshape(len(c), -1)], axis=1)
        rows.append(r[np.lexsort(np.round(r, 6).T[::-1])])  # rounded: seam vertices differ in the last bits
    old, new = rows
    same = old.shape == new.shape
    return {
        "mesh_triangles_old": len(old),
        "mesh_triangles": len(new),
        "mesh_max_point_diff_m": float(np.abs(new[:, :9] - old[:, :9]).max()) if same else float("nan"),
        "mesh_max_colour_diff": float(np.abs(new[:, 9:] - old[:, 9:]).max()) if same else float("nan"),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--blocks", type=int, default=15)
    p.add_argument("--changed", type=int, default=1, help="blocks whose table changed, for mesh_new_changed_ms")
    p.add_argument("--voxel", type=float, default=0.1, help="mesh voxel size in m")
    p.add_argument("--frames", type=int, default=10_000, help="frames in the path")
    p.add_argument("--path-frames", type=int, default=40, help="further frames timed on the new path")
    p.add_argument("--fps", type=float, default=10.0, help="frame rate of the timed frames (simulated clock)")
    p.add_argument("--path-period", type=float, default=1.0, help="the new path's path_period_s")
    p.add_argument("--repeats", type=int, default=1, help="timed runs of each case (the median is kept)")
    p.add_argument("--updates-frames", type=int, default=0, help="frames of each map-update source (0: all)")
    p.add_argument("--no-updates", action="store_true", help="leave the map-update figures out")
    p.add_argument("--json", type=Path, default=None, help="a copy of the stamped figures (see benchmarks/results/)")
    args = p.parse_args()
    os.environ["ROS_DOMAIN_ID"] = str(random.SystemRandom().randint(1, 200))
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

    import rclpy
    from nav_msgs.msg import Path as PathMsg
    from rclpy.serialization import deserialize_message
    from rclpy.signals import SignalHandlerOptions
    from visualization_msgs.msg import MarkerArray

    from neb_slam_core.mesh import extract_block_meshes
    from neb_slam_ros import cdr, conversions, qos
    from neb_slam_ros.node import NebNode
    from neb_slam_ros.outputs import MapOutputs, PathOutput

    reference = load_reference()
    rng = np.random.default_rng(0)
    torch.manual_seed(0)
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    old_node = NebNode("reference", with_config=False)
    new_node = NebNode("current", with_config=False)
    listener = rclpy.create_node("listener", namespace=old_node.get_namespace())
    for topic, msg_type in (("mesh", MarkerArray), ("path", PathMsg)):
        listener.create_subscription(msg_type, topic, lambda m: None, qos.state())
    figures: dict = {"reference_commit": reference.commit, **load_figures()}

    # ------------------------------------------------------------------ mesh
    block_map, observed = hall(args.blocks, rng)
    mesh_cfg = MeshConfig(voxel_size_m=args.voxel)
    tmp = Path(tempfile.mkdtemp(prefix="ros_outputs-"))
    old = reference.outputs.MapOutputs(
        old_node, "map", mesh_cfg, tmp, 0.0, lambda: block_map, lambda: observed, lambda run_dir: tmp
    )
    revisions = {b: 1 for b in range(len(block_map))}
    new = MapOutputs(
        new_node, "map", mesh_cfg, tmp, 0.0, lambda: block_map, lambda: observed, lambda run_dir: tmp, lambda: revisions
    )
    for out in (old.pub_mesh, new.pub_mesh):
        deadline = time.monotonic() + 30
        while out.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
    sent: list = []
    publish = new.pub_mesh.publish
    new.pub_mesh.publish = lambda msg: (sent.append(msg), publish(msg))
    old_sent: list = []
    old_publish = old.pub_mesh.publish
    old.pub_mesh.publish = lambda msg: (old_sent.append(msg), old_publish(msg))

    def old_mesh() -> None:
        old.publish(reference.mesh.extract_mesh(block_map, mesh_cfg, observed))

    def bump(blocks) -> None:
        for b in blocks:
            revisions[b] += 1

    figures["mesh_old_ms"] = median_ms(old_mesh, args.repeats)
    new.publish_current_map()  # the first publication: every block to the subscriber
    figures.update(compare_meshes(old_sent[-1].markers, deserialize_message(sent[0], MarkerArray).markers))
    every = range(len(block_map))
    figures["mesh_new_all_ms"] = median_ms(lambda: (bump(every), new.publish_current_map()), args.repeats)
    changed = list(range(args.changed))
    figures["mesh_new_changed_ms"] = median_ms(lambda: (bump(changed), new.publish_current_map()), args.repeats)
    figures["mesh_new_changed_blocks"] = len(deserialize_message(sent[-1], MarkerArray).markers)
    figures["mesh_blocks_with_triangles"] = len(new._markers)

    parts = extract_block_meshes(block_map, mesh_cfg, observed, range(len(block_map)))
    split = {b: part for b, part in parts.items() if len(part[1])}
    stamp_ns = time.time_ns()
    figures["mesh_conversion_old_ms"] = median_ms(
        lambda: old.pub_mesh.publish(reference.conversions.mesh_markers(split, stamp_ns, "map")), args.repeats
    )

    def new_conversion() -> None:
        tri = {b: conversions.triangle_list(*part) for b, part in split.items()}
        new.pub_mesh.publish(cdr.mesh_marker_array(tri, stamp_ns, "map"))

    figures["mesh_conversion_new_ms"] = median_ms(new_conversion, args.repeats)
    new.pub_mesh.get_subscription_count = lambda: 0
    figures["mesh_new_no_subscriber_ms"] = median_ms(lambda: (bump(every), new.publish_current_map()), args.repeats)
    for key in ("all", "changed", "no_subscriber"):
        figures[f"mesh_{key}_ratio"] = figures[f"mesh_new_{key}_ms"] / figures["mesh_old_ms"]
    figures["mesh_conversion_ratio"] = figures["mesh_conversion_new_ms"] / figures["mesh_conversion_old_ms"]

    # ------------------------------------------------------------------ path
    frontend = frontend_with(args.frames, rng)
    old_poses = reference.outputs.PoseOutputs(old_node, "map", EDGE_M)
    figures["path_old_ms_per_frame"] = median_ms(lambda: old_poses.publish_path(frontend.trajectory()), args.repeats)
    clock = [0.0]
    pub_path = new_node.create_publisher(PathMsg, "path", qos.state())
    path = PathOutput(new_node, pub_path, "map", args.path_period, frontend.trajectory, lambda: clock[0])
    figures["path_new_publication_ms"] = median_ms(path.publish, args.repeats)
    total = 0.0
    published = path.n_published
    for k in range(args.path_frames):
        i = args.frames + k
        add_frame(frontend, i, rng)
        if i % 5 == 0:  # a mapping step: every keyframe pose moves a little
            poses = np.stack(frontend.keyframe_poses)
            poses[1:, :3, 3] += 1e-4 * rng.normal(size=(len(poses) - 1, 3))
            frontend.set_keyframe_poses(poses)
        clock[0] = (k + 1) / args.fps
        t0 = time.perf_counter()
        path.changed()
        total += time.perf_counter() - t0
    path.timer.cancel()
    figures["path_new_ms_per_frame"] = 1e3 * total / args.path_frames
    figures["path_new_publications"] = path.n_published - published
    figures["path_ratio"] = figures["path_new_ms_per_frame"] / figures["path_old_ms_per_frame"]
    figures["frames"] = args.frames
    figures["blocks"] = args.blocks

    for key in (
        "mesh_old_ms",
        "mesh_new_all_ms",
        "mesh_new_changed_ms",
        "mesh_new_no_subscriber_ms",
        "mesh_conversion_old_ms",
        "mesh_conversion_new_ms",
        "path_old_ms_per_frame",
        "path_new_ms_per_frame",
        "path_new_publication_ms",
    ):
        print(f"  {key:28s} {figures[key]:10.2f}")
    for key in sorted(k for k in figures if k.endswith("_ratio")):
        print(f"  {key:28s} {figures[key]:10.4f}")
    print(
        f"  mesh: {figures['mesh_triangles']} triangles in {figures['mesh_blocks_with_triangles']} blocks, "
        f"max point diff {figures['mesh_max_point_diff_m']:.2e} m, max colour diff "
        f"{figures['mesh_max_colour_diff']:.2e}; load average {os.getloadavg()[0]:.2f}"
    )
    listener.destroy_node()
    old_node.destroy_node()
    new_node.destroy_node()
    rclpy.try_shutdown()
    if not args.no_updates:
        for source, prefix in (("demo", "map_update_"), ("tum", "map_update_tum_")):
            # new: as the live preset sends them
            u = map_update_figures(source, args.updates_frames, live_update_settings(), 5, progress=True)
            for key in ("mb_per_s_old", "mb_per_s_new", "pose_diff_cm_median", "pose_diff_cm_max", "updates", "frames"):
                figures[prefix + key] = u[key]
            figures[prefix + "ratio"] = u["mb_per_s_ratio"]
            print(
                f"  {prefix}mb_per_s old {u['mb_per_s_old']:.3f} new {u['mb_per_s_new']:.3f} (x"
                f"{u['mb_per_s_ratio']:.3f}); tracked poses within {u['pose_diff_cm_max']:.4f} cm"
            )
    record("ros_outputs", figures, args.json)


if __name__ == "__main__":
    main()
