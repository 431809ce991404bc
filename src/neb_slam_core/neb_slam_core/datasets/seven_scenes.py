"""Microsoft 7-Scenes style sequences: ``frame-NNNNNN.color.png``, ``.depth.png``, ``.pose.txt`` per frame.

- ``frame-NNNNNN.color.png`` (or ``.color.jpg``): colour; ``frame-NNNNNN.depth.png``: 16-bit depth in
  millimetres, 65535 = no reading (read as 0). A colour image without depth is skipped (one summary
  warning).
- ``frame-NNNNNN.pose.txt``: 4x4 camera-to-world, OpenCV axes; every colour image needs one.
- ``root`` is either one sequence folder (holding the frame files) or a scene folder holding
  ``seq-XX`` folders. In the latter case ``seq`` picks one (``'seq-02'`` or ``2``); by default the
  first in sorted order is taken (the others are listed in an info log line).
- Intrinsics: the dataset's published values, fx = fy = 585, cx = 320, cy = 240, 640x480, unless
  ``intrinsics=`` overrides them. (In the original release colour and depth come from two Kinect
  cameras and are not registered; like most RGB-D SLAM work we use them as if they were.)
- No time stamps: frame number N is at ``N / fps`` seconds (``fps`` default 30).
"""

from __future__ import annotations

import logging
from pathlib import Path

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
)

SEVEN_SCENES_INTRINSICS = Intrinsics(585.0, 585.0, 320.0, 240.0, 640, 480)
DEPTH_SCALE = 1000.0
DEPTH_INVALID = 65535
SEQ_GLOB = "seq-*"
POSE_GLOB = "frame-*.pose.txt"

log = logging.getLogger(__name__)


def sequence_folder(root: Path, seq: str | int | None) -> Path:
    """The sequence folder to read: ``root`` itself when it holds frames, else its ``seq-XX`` folder ``seq``."""
    seqs = sorted(p for p in root.glob(SEQ_GLOB) if p.is_dir())
    if seq is None and not seqs:
        return root
    if not seqs:
        raise DatasetError(root, f"seq={seq!r} given but there are no seq-XX folders here")
    if seq is None:
        if len(seqs) > 1:
            log.info(
                "%s: reading %s (other sequences: %s; pick one with seq=)",
                root,
                seqs[0].name,
                ", ".join(p.name for p in seqs[1:]),
            )
        return seqs[0]
    name = f"seq-{int(seq):02d}" if isinstance(seq, int) else str(seq)
    if not (root / name).is_dir():
        raise DatasetError(root / name, f"sequence folder not found; choose one of {', '.join(p.name for p in seqs)}")
    return root / name


@register("seven_scenes")
class SevenScenesDataset(FrameListDataset):
    """One 7-Scenes sequence.

    Args:
        root: a sequence folder, or a scene folder holding ``seq-XX`` folders.
        seq: which sequence of a scene folder (``'seq-01'`` or ``1``); default the first.
        intrinsics: explicit intrinsics, overriding the published 7-Scenes camera.
        fps: frame rate that turns frame numbers into stamps.
    """

    depth_scale = DEPTH_SCALE
    depth_invalid_value = DEPTH_INVALID

    def __init__(
        self, root: str | Path, seq: str | int | None = None, intrinsics: Intrinsics | None = None, fps: float = 30.0
    ):
        self.root = Path(root)
        self.intrinsics = check_intrinsics(
            SEVEN_SCENES_INTRINSICS if intrinsics is None else intrinsics, "intrinsics= argument"
        )
        fps = check_fps(fps)
        if not self.root.is_dir():
            raise DatasetError(self.root, "sequence folder not found")
        self.seq_dir = sequence_folder(self.root, seq)
        rgb_files = numbered_files(self.seq_dir, r"frame-(\d+)\.color\.(?:png|jpg|jpeg)", "colour images")
        depth_files = numbered_files(self.seq_dir, r"frame-(\d+)\.depth\.png", "depth images")
        pose_files = numbered_files(self.seq_dir, r"frame-(\d+)\.pose\.txt", "poses")
        if not rgb_files:
            raise DatasetError(self.seq_dir, "no colour images named frame-NNNNNN.color.png")
        missing = [n for n in rgb_files if n not in pose_files]
        if missing or len(pose_files) != len(rgb_files):
            detail = ""
            if missing:
                name = rgb_files[missing[0]].name
                detail = f"; no pose for {name} (expected {name.split('.color.')[0]}.pose.txt)"
            raise DatasetError(
                self.seq_dir,
                f"{len(pose_files)} pose files for {len(rgb_files)} colour images; "
                f"expected one frame-NNNNNN.pose.txt per colour image{detail}",
            )
        self.frames = []
        for n in pair_by_number(self.seq_dir, rgb_files, depth_files):
            T = check_rigid_pose(
                read_matrix(pose_files[n], (4, 4), "camera-to-world pose (4x4)"), pose_files[n], "camera-to-world pose"
            )
            self.frames.append(FrameFiles(rgb_files[n], depth_files[n], fps_stamp_ns(n, fps), T))

    @classmethod
    def detect(cls, path: Path) -> bool:
        if not path.is_dir():
            return False
        if next(path.glob(POSE_GLOB), None) is not None:
            return True
        return any(next(s.glob(POSE_GLOB), None) is not None for s in path.glob(SEQ_GLOB) if s.is_dir())
