"""NeuralRGBD synthetic scenes: ``images/``, ``depth_filtered/`` or ``depth/``, ``poses.txt``, ``focal.txt``.

- ``images/imgN.png``: colour; ``depth_filtered/depthN.png`` (preferred, when the folder exists) or
  ``depth/depthN.png``: 16-bit depth in millimetres. A colour image without depth is skipped.
- ``poses.txt``: 4x4 camera-to-world matrices stacked, 4 rows each, in OpenGL camera axes (x right,
  y up, z backward); converted on load to OpenCV axes by ``T_cv = T_gl @ GL_TO_CV``. The k-th matrix
  belongs to the k-th colour image in numeric order (the counts must match). Some scenes mark frames
  without a pose with ``nan``: those frames are skipped (one summary warning).
- ``focal.txt``: one focal length in pixels (fx = fy). The principal point is the image centre
  ``(W / 2, H / 2)``, the convention the dataset's own ray generation uses (pixel ``i`` looks along
  ``(i - W/2) / f``); the size is that of the depth images. ``intrinsics=`` overrides all of it.
- No time stamps: image number N is at ``N / fps`` seconds (``fps`` default 30).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..errors import DatasetError
from ..geometry.se3 import GL_TO_CV
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
    read_matrix,
    read_number_rows,
    register,
    warn_skipped,
)

DEPTH_SCALE = 1000.0


def read_stacked_poses(path: Path) -> np.ndarray:
    """Read ``poses.txt``: 4x4 matrices stacked 4 rows each -> ``(N, 4, 4)`` float64 (may hold nan)."""
    rows = [
        values
        for _, values in read_number_rows(
            path,
            4,
            "one row of a 4x4",
            "pose file not found (expected 4x4 camera-to-world matrices stacked, 4 rows each)",
        )
    ]
    if len(rows) % 4:
        raise DatasetError(path, f"{len(rows)} rows is not a whole number of 4x4 matrices (4 rows each)")
    return np.asarray(rows, dtype=np.float64).reshape(-1, 4, 4)


@register("neural_rgbd")
class NeuralRgbdDataset(FrameListDataset):
    """A NeuralRGBD scene folder.

    Args:
        root: the scene folder.
        intrinsics: explicit intrinsics, overriding ``focal.txt`` and the image-centre principal point.
        fps: frame rate that turns image numbers into stamps.
    """

    depth_scale = DEPTH_SCALE

    def __init__(self, root: str | Path, intrinsics: Intrinsics | None = None, fps: float = 30.0):
        self.root = Path(root)
        fps = check_fps(fps)
        depth_dir = self.root / "depth_filtered"
        if not depth_dir.is_dir():
            depth_dir = self.root / "depth"
        rgb_files = numbered_files(self.root / "images", r"img(\d+)\.(?:png|jpg|jpeg)", "colour images (imgN.png)")
        depth_files = numbered_files(depth_dir, r"depth(\d+)\.png", "depth images (depthN.png)")
        if not rgb_files:
            raise DatasetError(self.root / "images", "no colour images named imgN.png")
        poses_path = self.root / "poses.txt"
        poses_gl = read_stacked_poses(poses_path)
        pose_of = poses_by_image_order(poses_gl, rgb_files, poses_path, "images")
        with_depth = pair_by_number(self.root, rgb_files, depth_files)

        self.frames = []
        n_invalid = 0
        for n in with_depth:
            T_gl = pose_of[n]
            if not np.all(np.isfinite(T_gl)):
                n_invalid += 1
                continue
            T_gl = check_rigid_pose(T_gl, poses_path, f"pose of {rgb_files[n].name}")
            self.frames.append(FrameFiles(rgb_files[n], depth_files[n], fps_stamp_ns(n, fps), T_gl @ GL_TO_CV))
        warn_skipped(self.root, n_invalid, len(with_depth), "pose is not finite (nan in poses.txt)")

        if intrinsics is not None:
            self.intrinsics = check_intrinsics(intrinsics, "intrinsics= argument")
        elif self.frames:
            focal_path = self.root / "focal.txt"
            focal = float(read_matrix(focal_path, (1,), "focal length (one number, pixels)")[0])
            raw = cv2.imread(str(self.frames[0].depth_path), cv2.IMREAD_UNCHANGED)
            if raw is None:
                raise DatasetError(
                    self.frames[0].depth_path, "depth image missing or unreadable (expected a 16-bit PNG)"
                )
            h, w = raw.shape[:2]
            self.intrinsics = check_intrinsics(Intrinsics(focal, focal, w / 2.0, h / 2.0, w, h), focal_path)
        else:
            raise DatasetError(self.root, "no usable frame (every frame lacks depth or a finite pose)")

    @classmethod
    def detect(cls, path: Path) -> bool:
        return (
            path.is_dir()
            and (path / "images").is_dir()
            and (path / "poses.txt").is_file()
            and (path / "focal.txt").is_file()
        )
