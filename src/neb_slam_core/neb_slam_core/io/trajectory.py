"""TUM trajectory files: ``timestamp tx ty tz qx qy qz qw`` per line, ``#`` comments.

Readable and written in the format the TUM benchmark tools (and evo) use.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from ..geometry.se3 import is_rigid, pose_from_tum, pose_to_tum


@dataclass
class Trajectory:
    """Stamped camera-to-world poses.

    Attributes:
        stamps_ns: ``(N,)`` int64 nanoseconds, increasing.
        poses: ``(N, 4, 4)`` float64 ``T_world_cam``.
    """

    stamps_ns: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        self.stamps_ns = np.asarray(self.stamps_ns, dtype=np.int64)
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        if len(self.stamps_ns) != len(self.poses):
            raise ValueError(f"Trajectory: {len(self.stamps_ns)} stamps but {len(self.poses)} poses")

    def __len__(self) -> int:
        return len(self.stamps_ns)

    @property
    def positions(self) -> np.ndarray:
        """``(N, 3)`` camera centres in the world frame."""
        return self.poses[:, :3, 3]

    @property
    def stamps_s(self) -> np.ndarray:
        return self.stamps_ns.astype(np.float64) * 1e-9


def stamp_s_to_ns(text_or_float) -> int:
    """Seconds (as text like ``'1305031102.160407'`` or a float) -> integer nanoseconds, exactly for text."""
    if isinstance(text_or_float, str):
        whole, _, frac = text_or_float.strip().partition(".")
        frac = (frac + "000000000")[:9]
        sign = -1 if whole.startswith("-") else 1
        return int(whole) * 1_000_000_000 + sign * int(frac)
    return int(round(float(text_or_float) * 1e9))


def stamp_ns_to_text(stamp_ns: int) -> str:
    """Integer nanoseconds -> ``'seconds.fraction'`` with 9 decimals, exact."""
    sign = "-" if stamp_ns < 0 else ""
    s, ns = divmod(abs(int(stamp_ns)), 1_000_000_000)
    return f"{sign}{s}.{ns:09d}"


def read_tum_trajectory(path: str | Path) -> Trajectory:
    """Read a TUM-format trajectory; raises :class:`DatasetError` naming the line on bad input."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "trajectory file not found (expected 'timestamp tx ty tz qx qy qz qw' lines)")
    stamps, rows = [], []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise DatasetError(
                path, f"line {lineno}: expected 8 numbers 'timestamp tx ty tz qx qy qz qw', got {len(parts)}"
            )
        try:
            stamps.append(stamp_s_to_ns(parts[0]))
            rows.append([float(p) for p in parts[1:]])
        except ValueError:
            raise DatasetError(path, f"line {lineno}: not a number in {line!r}") from None
    if not rows:
        return Trajectory(np.zeros(0, np.int64), np.zeros((0, 4, 4)))
    rows_a = np.asarray(rows)
    q_norm = np.linalg.norm(rows_a[:, 3:], axis=1)
    bad = np.flatnonzero(~np.isfinite(rows_a).all(axis=1) | (np.abs(q_norm - 1.0) > 1e-2))
    if len(bad):
        raise DatasetError(
            path, f"pose {bad[0]} is not finite or its quaternion is not unit length (|q| = {q_norm[bad[0]]:.4f})"
        )
    rows_a[:, 3:] /= q_norm[:, None]
    return Trajectory(np.asarray(stamps, np.int64), pose_from_tum(rows_a))


def write_tum_trajectory(path: str | Path, traj: Trajectory, header: str | None = None) -> None:
    """Write ``traj`` as a TUM-format file (stamps with 9 decimals, poses with 8)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = [f"# {header}"] if header else []
    lines.append("# timestamp tx ty tz qx qy qz qw")
    for stamp, row in zip(traj.stamps_ns, pose_to_tum(traj.poses) if len(traj) else []):
        lines.append(stamp_ns_to_text(int(stamp)) + " " + " ".join(f"{v:.8f}" for v in row))
    path.write_text("\n".join(lines) + "\n")


def check_rigid_pose(T: np.ndarray, source: str | Path, what: str) -> np.ndarray:
    """Return ``T`` as float64 4x4 or raise :class:`DatasetError` saying it is not a rigid transform."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise DatasetError(source, f"{what}: expected a 4x4 matrix, got shape {T.shape}")
    if not is_rigid(T):
        raise DatasetError(
            source,
            f"{what}: not a rigid transform (rotation part is not orthonormal with det 1, "
            f"or last row is not 0 0 0 1):\n{np.array2string(T, precision=4)}",
        )
    return T
