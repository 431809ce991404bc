"""TUM RGB-D benchmark folders: ``rgb.txt``, ``depth.txt``, optional ``groundtruth.txt``.

Colour and depth are associated by the benchmark's rule (nearest stamp within 0.02 s, each frame used
once). A frame is stamped with its depth image's time (``frame_stamp``, see
:data:`~neb_slam_core.datasets.base.FRAME_STAMPS`; ``extras`` keeps both images' stamps); the
ground-truth pose is the nearest motion-capture sample within 0.02 s of that stamp. Bad lines of
``groundtruth.txt`` (malformed, non-finite) are skipped with one warning: ground truth only gives the
first pose and the evaluation, and both can use the other lines. Depth PNGs store
metres x 5000. Intrinsics are the benchmark's published values for the sensor named in the folder name
(``freiburg1`` or ``fr1``, ...), or an explicit override. A folder may also carry ``intrinsics.json``
(written by ``neb-slam synth`` and ``neb-slam convert``), which then takes precedence over the name.
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from ..io.trajectory import read_tum_trajectory, stamp_s_to_ns
from ..types import COLOUR_STAMP, DEPTH_STAMP, Intrinsics, RgbdFrame
from .base import (
    Dataset,
    associate,
    associate_unique,
    check_frame_stamp,
    frame_stamps,
    read_depth,
    read_rgb,
    register,
    warn_skipped,
)

#: The benchmark's published intrinsics (640x480) and distortion (k1 k2 p1 p2 k3) per sensor.
TUM_CAMERAS: dict[str, tuple[Intrinsics, tuple[float, ...]]] = {
    "fr1": (Intrinsics(517.3, 516.5, 318.6, 255.3, 640, 480), (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "fr2": (Intrinsics(520.9, 521.0, 325.1, 249.7, 640, 480), (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "fr3": (Intrinsics(535.4, 539.2, 320.1, 247.6, 640, 480), (0.0, 0.0, 0.0, 0.0, 0.0)),
}
DEPTH_SCALE = 5000.0
MAX_DT_NS = 20_000_000  # 0.02 s
INTRINSICS_FILE = "intrinsics.json"  # our extension: {"fx", "fy", "cx", "cy", "width", "height"}

log = logging.getLogger(__name__)


def camera_from_name(name: str) -> str | None:
    """``'rgbd_dataset_freiburg1_xyz'`` or ``'tum_fr1_xyz_300'`` -> ``'fr1'``; None when absent."""
    m = re.search(r"(?:freiburg|fr)([123])(?![0-9])", name.lower())
    return f"fr{m.group(1)}" if m else None


def read_index(path: Path) -> tuple[np.ndarray, list[str]]:
    """Read a ``timestamp filename`` index file -> (stamps_ns, relative file names)."""
    if not path.is_file():
        raise DatasetError(path, "index file not found (expected 'timestamp filename' lines)")
    stamps, names = [], []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) < 2:
            raise DatasetError(path, f"line {lineno}: expected 'timestamp filename', got {line!r}")
        try:
            stamps.append(stamp_s_to_ns(parts[0]))
        except ValueError:
            raise DatasetError(path, f"line {lineno}: timestamp {parts[0]!r} is not a number") from None
        names.append(parts[1])
    return np.asarray(stamps, dtype=np.int64), names


def read_intrinsics_json(path: Path) -> Intrinsics:
    """Read ``{"fx", "fy", "cx", "cy", "width", "height"}`` (written by ``neb-slam synth``)."""
    try:
        d = json.loads(path.read_text())
        return Intrinsics(
            float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]), int(d["width"]), int(d["height"])
        )
    except (ValueError, KeyError, TypeError) as exc:
        raise DatasetError(path, f"expected a JSON object with fx, fy, cx, cy, width, height ({exc})") from None


def write_intrinsics_json(path: Path, intr: Intrinsics) -> None:
    path.write_text(
        json.dumps(
            {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy, "width": intr.width, "height": intr.height},
            indent=2,
        )
        + "\n"
    )


@register("tum")
class TumDataset(Dataset):
    """A TUM RGB-D sequence folder.

    Args:
        root: the sequence folder.
        camera: ``'fr1'``, ``'fr2'`` or ``'fr3'``; default: from the folder name.
        intrinsics: explicit intrinsics, overriding ``camera``.
        frame_stamp: ``"depth"`` or ``"colour"``: which image's time stamps a frame (and picks its
            ground-truth pose).
    """

    def __init__(
        self,
        root: str | Path,
        camera: str | None = None,
        intrinsics: Intrinsics | None = None,
        frame_stamp: str = "depth",
    ):
        self.root = Path(root)
        self.frame_stamp = check_frame_stamp(self.root, frame_stamp)
        if intrinsics is None and camera is None and (self.root / INTRINSICS_FILE).is_file():
            intrinsics = read_intrinsics_json(self.root / INTRINSICS_FILE)
        if intrinsics is None:
            cam = camera or camera_from_name(self.root.resolve().name)
            if cam is None:
                raise DatasetError(
                    self.root,
                    "cannot tell the TUM sensor from the folder name (no 'freiburg1'/'fr1', "
                    f"'fr2', 'fr3'); pass camera= one of {', '.join(TUM_CAMERAS)} or explicit intrinsics",
                )
            if cam not in TUM_CAMERAS:
                raise DatasetError(self.root, f"unknown TUM camera {cam!r}; choose one of {', '.join(TUM_CAMERAS)}")
            intrinsics, self.distortion = TUM_CAMERAS[cam]
        else:
            self.distortion = (0.0,) * 5
        self.intrinsics = intrinsics

        rgb_ns, rgb_names = read_index(self.root / "rgb.txt")
        depth_ns, depth_names = read_index(self.root / "depth.txt")
        pair = associate_unique(rgb_ns, depth_ns, MAX_DT_NS)
        keep = np.flatnonzero(pair >= 0)
        warn_skipped(self.root, len(rgb_ns) - len(keep), len(rgb_ns), "colour frames with no depth within 0.02 s")
        stamps = frame_stamps(rgb_ns[keep], depth_ns[pair[keep]], frame_stamp)
        order = np.argsort(stamps, kind="stable")  # frames in the order of the chosen stamps
        keep, self._stamps_ns = keep[order], stamps[order]
        self._colour_ns, self._depth_ns = rgb_ns[keep], depth_ns[pair[keep]]
        self._rgb = [rgb_names[i] for i in keep]
        self._depth = [depth_names[j] for j in pair[keep]]

        # Frames with no ground truth within 0.02 s stay in the sequence (SLAM needs them); their
        # T_world_cam is None and evaluation associates by stamp.
        self._poses: list[np.ndarray | None] | None = None
        gt_path = self.root / "groundtruth.txt"
        if gt_path.is_file():
            gt = read_tum_trajectory(gt_path, skip_bad_lines=True)
            idx = associate(self._stamps_ns, gt.stamps_ns, MAX_DT_NS)
            n_missing = int((idx < 0).sum())
            if n_missing:
                log.warning(
                    "%s: %d of %d frames have no ground-truth pose within 0.02 s (kept, without pose)",
                    self.root,
                    n_missing,
                    len(idx),
                )
            self._poses = [gt.poses[j] if j >= 0 else None for j in idx]

    @classmethod
    def detect(cls, path: Path) -> bool:
        return path.is_dir() and (path / "rgb.txt").is_file() and (path / "depth.txt").is_file()

    @property
    def has_ground_truth(self) -> bool:
        return self._poses is not None

    @property
    def stamps_ns(self) -> np.ndarray:
        return self._stamps_ns

    def __len__(self) -> int:
        return len(self._stamps_ns)

    def _load(self, i: int) -> RgbdFrame:
        size = (self.intrinsics.width, self.intrinsics.height)
        rgb = read_rgb(self.root / self._rgb[i])
        if (rgb.shape[1], rgb.shape[0]) != size:
            raise DatasetError(
                self.root / self._rgb[i], f"colour image is {rgb.shape[1]}x{rgb.shape[0]}, expected {size[0]}x{size[1]}"
            )
        depth = read_depth(self.root / self._depth[i], DEPTH_SCALE, expected_size=size)
        pose = None if self._poses is None or self._poses[i] is None else self._poses[i].copy()
        extras = {
            "distortion": self.distortion,
            COLOUR_STAMP: int(self._colour_ns[i]),
            DEPTH_STAMP: int(self._depth_ns[i]),
        }
        return RgbdFrame(rgb, depth, self.intrinsics, int(self._stamps_ns[i]), pose, extras=extras)
