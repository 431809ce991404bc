"""Replica sequences in the layout NICE-SLAM distributes: ``results/`` and ``traj.txt``.

- ``results/frameNNNNNN.jpg``: colour; ``results/depthNNNNNN.png``: 16-bit depth, metres = value / 6553.5.
  Colour and depth are paired by the number in the name; a colour image without depth is skipped
  (one summary warning).
- ``traj.txt``: one camera-to-world pose per line, a row-major 4x4 (16 numbers), in OpenCV axes.
  Line k belongs to the k-th colour image in numeric order (the counts must match).
- No time stamps: frame number n gets ``n / fps`` seconds (``fps`` default 30).
- Intrinsics: the values of NICE-SLAM's Replica config (1200x680, fx = fy = 600, cx = 599.5,
  cy = 339.5) unless ``intrinsics=`` overrides them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import DatasetError
from ..io.trajectory import check_rigid_pose
from ..types import Intrinsics
from .base import (
    FrameFiles,
    FrameListDataset,
    check_fps,
    check_intrinsics,
    fps_stamp_ns,
    numbered_files,
    pair_by_number,
    poses_by_image_order,
    read_number_rows,
    register,
)

REPLICA_INTRINSICS = Intrinsics(600.0, 600.0, 599.5, 339.5, 1200, 680)
DEPTH_SCALE = 6553.5
TRAJ_FILE = "traj.txt"
RGB_PATTERN = r"frame(\d+)\.(?:jpg|jpeg|png)"
DEPTH_PATTERN = r"depth(\d+)\.png"


def read_replica_trajectory(path: Path) -> list[np.ndarray]:
    """Read ``traj.txt``: one row-major 4x4 camera-to-world per non-empty line -> list of ``(4, 4)`` float64."""
    rows = read_number_rows(
        path,
        16,
        "a row-major 4x4",
        "trajectory file not found (expected one row-major 4x4 camera-to-world, 16 numbers, per line)",
    )
    poses = [check_rigid_pose(values.reshape(4, 4), path, f"line {lineno}") for lineno, values in rows]
    return poses


@register("replica")
class ReplicaDataset(FrameListDataset):
    """A Replica sequence folder (NICE-SLAM layout).

    Args:
        root: the sequence folder holding ``results/`` and ``traj.txt``.
        intrinsics: explicit intrinsics, overriding NICE-SLAM's Replica camera.
        fps: frame rate that turns frame numbers into stamps.
    """

    depth_scale = DEPTH_SCALE

    def __init__(self, root: str | Path, intrinsics: Intrinsics | None = None, fps: float = 30.0):
        self.root = Path(root)
        self.intrinsics = check_intrinsics(
            REPLICA_INTRINSICS if intrinsics is None else intrinsics, "intrinsics= argument"
        )
        fps = check_fps(fps)
        results = self.root / "results"
        rgb_files = numbered_files(results, RGB_PATTERN, "colour images (frameNNNNNN.jpg)")
        depth_files = numbered_files(results, DEPTH_PATTERN, "depth images (depthNNNNNN.png)")
        if not rgb_files:
            raise DatasetError(results, "no colour images named frameNNNNNN.jpg")
        traj_path = self.root / TRAJ_FILE
        poses = read_replica_trajectory(traj_path)
        pose_of = poses_by_image_order(poses, rgb_files, traj_path, results.name)
        self.frames = [
            FrameFiles(rgb_files[n], depth_files[n], fps_stamp_ns(n, fps), pose_of[n])
            for n in pair_by_number(self.root, rgb_files, depth_files)
        ]

    @classmethod
    def detect(cls, path: Path) -> bool:
        return path.is_dir() and (path / TRAJ_FILE).is_file() and (path / "results").is_dir()
