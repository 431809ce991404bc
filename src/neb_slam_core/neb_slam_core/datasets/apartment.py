"""NICE-SLAM's Apartment sequence (Azure Kinect): ``color/``, ``depth/``, ``scene/trajectory.log``.

- ``color/N.jpg``: colour; ``depth/N.png``: 16-bit depth in millimetres, registered to colour.
  Colour and depth are paired by the number in the name (any non-digit prefix is allowed); a colour
  image without depth is skipped (one summary warning).
- ``scene/trajectory.log``: the Open3D trajectory log format, per frame a metadata line of three
  numbers followed by the 4 rows of a 4x4 camera-to-world, in OpenCV axes. The k-th record belongs
  to the k-th colour image in numeric order (the counts must match); the metadata is not used.
- Intrinsics: the values of NICE-SLAM's ``configs/Apartment/apartment.yaml`` (1280x720,
  fx 607.469, fy 607.453, cx 636.997, cy 369.269), unless ``intrinsics=`` overrides them.
- No time stamps: frame number N is at ``N / fps`` seconds (``fps`` default 30, the Azure Kinect rate).
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
    register,
)

APARTMENT_INTRINSICS = Intrinsics(607.4694213867188, 607.4534912109375, 636.9967041015625, 369.2689514160156, 1280, 720)
DEPTH_SCALE = 1000.0
TRAJECTORY_FILE = Path("scene") / "trajectory.log"


def read_trajectory_log(path: Path) -> list[np.ndarray]:
    """Read an Open3D ``.log`` trajectory -> list of ``(4, 4)`` float64 camera-to-world poses.

    Each record is 5 non-empty lines: ``id id value`` metadata, then the 4 rows of the matrix.
    """
    if not path.is_file():
        raise DatasetError(
            path,
            "trajectory file not found (expected the Open3D .log format: per frame a "
            "metadata line, then 4 rows of a 4x4 camera-to-world)",
        )
    lines = [
        (lineno, line.split()) for lineno, line in enumerate(path.read_text().splitlines(), start=1) if line.strip()
    ]
    if len(lines) % 5:
        raise DatasetError(
            path,
            f"{len(lines)} non-empty lines is not a whole number of 5-line records (metadata line + 4 matrix rows)",
        )
    poses = []
    for r in range(0, len(lines), 5):
        meta_lineno, meta = lines[r]
        if len(meta) != 3:
            raise DatasetError(
                path, f"line {meta_lineno}: expected a metadata line of 3 numbers, got {' '.join(meta)!r}"
            )
        rows = lines[r + 1 : r + 5]
        for lineno, parts in rows:
            if len(parts) != 4:
                raise DatasetError(path, f"line {lineno}: expected 4 numbers (one row of a 4x4), got {len(parts)}")
        try:
            T = np.array([parts for _, parts in rows], dtype=np.float64)
        except ValueError:
            raise DatasetError(path, f"lines {rows[0][0]}-{rows[-1][0]}: not numbers") from None
        poses.append(check_rigid_pose(T, path, f"pose at lines {rows[0][0]}-{rows[-1][0]}"))
    return poses


@register("apartment")
class ApartmentDataset(FrameListDataset):
    """NICE-SLAM's Apartment folder.

    Args:
        root: the folder holding ``color/``, ``depth/`` and ``scene/trajectory.log``.
        intrinsics: explicit intrinsics, overriding NICE-SLAM's Apartment camera.
        fps: frame rate that turns frame numbers into stamps.
    """

    depth_scale = DEPTH_SCALE

    def __init__(self, root: str | Path, intrinsics: Intrinsics | None = None, fps: float = 30.0):
        self.root = Path(root)
        self.intrinsics = check_intrinsics(
            APARTMENT_INTRINSICS if intrinsics is None else intrinsics, "intrinsics= argument"
        )
        fps = check_fps(fps)
        rgb_files = numbered_files(self.root / "color", r"\D*(\d+)\.(?:jpg|jpeg|png)", "colour images (color/N.jpg)")
        depth_files = numbered_files(self.root / "depth", r"\D*(\d+)\.png", "depth images (depth/N.png)")
        if not rgb_files:
            raise DatasetError(self.root / "color", "no colour images named N.jpg")
        traj_path = self.root / TRAJECTORY_FILE
        poses = read_trajectory_log(traj_path)
        pose_of = poses_by_image_order(poses, rgb_files, traj_path, "color")
        self.frames = [
            FrameFiles(rgb_files[n], depth_files[n], fps_stamp_ns(n, fps), pose_of[n])
            for n in pair_by_number(self.root, rgb_files, depth_files)
        ]

    @classmethod
    def detect(cls, path: Path) -> bool:
        return (
            path.is_dir()
            and (path / "color").is_dir()
            and (path / "depth").is_dir()
            and (path / TRAJECTORY_FILE).is_file()
        )
