"""ScanNet scenes as exported for NICE-SLAM: ``frames/color``, ``frames/depth``, ``frames/pose``, ``frames/intrinsic``.

- ``color/N.jpg``: colour (ScanNet: 1296x968), resized to the depth size with area interpolation.
- ``depth/N.png``: 16-bit depth in millimetres (ScanNet: 640x480), 0 = no reading.
- ``pose/N.txt``: 4x4 camera-to-world, OpenCV axes. ScanNet marks frames that lost tracking with a
  pose of ``-inf``; those frames are skipped (one summary warning), as are colour images without depth.
- ``intrinsic/intrinsic_depth.txt``: 4x4 whose upper-left 3x3 is the depth camera matrix; the image
  size is that of the depth images. ``intrinsics=`` overrides it.
- Files are ordered by their number (``9.jpg`` before ``10.jpg``); no time stamps: frame N is at
  ``N / fps`` seconds (``fps`` default 30).

``root`` is the scene folder holding ``frames/``, or the ``frames`` folder itself.
"""

from __future__ import annotations

from pathlib import Path

import cv2
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
    read_matrix,
    register,
    warn_skipped,
)

DEPTH_SCALE = 1000.0
INTRINSICS_FILE = Path("intrinsic") / "intrinsic_depth.txt"


def frames_folder(root: Path) -> Path:
    """The folder holding ``color/``, ``depth/`` and ``pose/``: ``root/frames`` or ``root`` itself."""
    return root / "frames" if (root / "frames").is_dir() else root


def read_depth_intrinsics(path: Path, depth_image: Path) -> Intrinsics:
    """fx, fy, cx, cy from ScanNet's 4x4 ``intrinsic_depth.txt``; width and height from ``depth_image``."""
    K = read_matrix(path, (4, 4), "depth camera intrinsics (4x4)")
    raw = cv2.imread(str(depth_image), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise DatasetError(depth_image, "depth image missing or unreadable (expected a 16-bit single-channel PNG)")
    return check_intrinsics(Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], raw.shape[1], raw.shape[0]), path)


@register("scannet")
class ScanNetDataset(FrameListDataset):
    """A ScanNet scene exported for NICE-SLAM.

    Args:
        root: the scene folder (holding ``frames/``) or the ``frames`` folder.
        intrinsics: explicit intrinsics (for the depth image size), overriding ``intrinsic_depth.txt``.
        fps: frame rate that turns frame numbers into stamps.
    """

    depth_scale = DEPTH_SCALE
    resize_rgb = True

    def __init__(self, root: str | Path, intrinsics: Intrinsics | None = None, fps: float = 30.0):
        self.root = Path(root)
        fps = check_fps(fps)
        frames = frames_folder(self.root)
        rgb_files = numbered_files(frames / "color", r"(\d+)\.(?:jpg|jpeg|png)", "colour images (color/N.jpg)")
        depth_files = numbered_files(frames / "depth", r"(\d+)\.png", "depth images (depth/N.png)")
        pose_files = numbered_files(frames / "pose", r"(\d+)\.txt", "poses (pose/N.txt)")
        if not rgb_files:
            raise DatasetError(frames / "color", "no colour images named N.jpg")
        missing = [n for n in rgb_files if n not in pose_files]
        if missing or len(pose_files) != len(rgb_files):
            detail = f"; no pose for {rgb_files[missing[0]].name} (expected {missing[0]}.txt)" if missing else ""
            raise DatasetError(
                frames / "pose",
                f"{len(pose_files)} pose files for {len(rgb_files)} colour images; "
                f"expected one N.txt per colour image N.jpg{detail}",
            )
        with_depth = pair_by_number(self.root, rgb_files, depth_files)

        self.frames = []
        n_lost = 0
        for n in with_depth:
            T = read_matrix(pose_files[n], (4, 4), "camera-to-world pose (4x4)")
            if not np.all(np.isfinite(T)):
                n_lost += 1
                continue
            T = check_rigid_pose(T, pose_files[n], "camera-to-world pose")
            self.frames.append(FrameFiles(rgb_files[n], depth_files[n], fps_stamp_ns(n, fps), T))
        warn_skipped(self.root, n_lost, len(with_depth), "pose is not finite (ScanNet's mark of lost tracking)")

        if intrinsics is not None:
            self.intrinsics = check_intrinsics(intrinsics, "intrinsics= argument")
        elif self.frames:
            intr_path = frames / INTRINSICS_FILE
            if not intr_path.is_file() and (self.root / INTRINSICS_FILE).is_file():
                intr_path = self.root / INTRINSICS_FILE
            self.intrinsics = read_depth_intrinsics(intr_path, self.frames[0].depth_path)
        else:
            raise DatasetError(self.root, "no usable frame (every frame lacks depth or a finite pose)")

    @classmethod
    def detect(cls, path: Path) -> bool:
        frames = frames_folder(path)
        return path.is_dir() and all((frames / sub).is_dir() for sub in ("color", "depth", "pose"))
