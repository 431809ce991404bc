"""Trajectory accuracy: association by stamp, rigid alignment, ATE and RPE (TUM benchmark style).

- Association: each estimated pose is paired with the ground-truth pose nearest in time within
  ``max_dt_s`` (0.02 s by default), each ground-truth pose used at most once (the benchmark's rule,
  :func:`~neb_slam_core.datasets.base.associate_unique`). Unmatched poses are dropped.
- Alignment: the rigid transform ``T_gt_est`` (rotation + translation, no scale) minimising
  ``sum_i |p_gt_i - (R p_est_i + t)|^2`` over the associated camera centres, in closed form
  (Horn / Umeyama, see :func:`align_rigid`).
- ATE: the translation residuals ``|p_gt_i - (R p_est_i + t)|`` after alignment; RMSE, mean, median, max.
- RPE: for pairs ``(i, j)`` a fixed number of frames or a fixed time apart, the error of the relative
  motion ``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` (``Q`` ground truth, ``P`` estimate); translational error
  ``|trans(E)|`` and rotational error ``angle(E)``. RPE needs no alignment.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..datasets.base import associate_unique
from ..errors import DatasetError
from ..geometry.se3 import invert, make_pose
from ..io.trajectory import Trajectory

#: the TUM benchmark's association window
DEFAULT_MAX_DT_S = 0.02
#: fewest associated poses for which a rigid alignment is determined
MIN_MATCHES = 3


@dataclass(frozen=True)
class TrajectoryPair:
    """Estimated and ground-truth poses associated by stamp.

    Attributes:
        stamps_ns: ``(n,)`` int64 stamps of the matched estimated poses, increasing.
        est_poses: ``(n, 4, 4)`` estimated ``T_world_cam`` (the estimate's world frame).
        gt_poses: ``(n, 4, 4)`` ground-truth ``T_world_cam`` matched to them.
        gt_stamps_ns: ``(n,)`` int64 stamps of the matched ground-truth poses.
        n_est: poses in the estimated trajectory before association.
        n_gt: poses in the ground-truth trajectory before association.
    """

    stamps_ns: np.ndarray
    est_poses: np.ndarray
    gt_poses: np.ndarray
    gt_stamps_ns: np.ndarray
    n_est: int
    n_gt: int

    def __len__(self) -> int:
        return len(self.stamps_ns)


@dataclass(frozen=True)
class AteResult:
    """Absolute trajectory error after rigid alignment.

    Attributes:
        rmse_m, mean_m, median_m, max_m: statistics of ``errors_m``, metres.
        errors_m: ``(n,)`` translation error of each matched pose after alignment, metres.
        stamps_ns: ``(n,)`` int64 stamps of the matched estimated poses.
        aligned_poses: ``(n, 4, 4)`` estimated poses mapped into the ground-truth frame, ``T_gt_est @ P_i``.
        gt_poses: ``(n, 4, 4)`` the matched ground-truth poses.
        T_gt_est: ``(4, 4)`` the alignment (identity when alignment was switched off).
        n_matched: number of associated poses (``n``).
        n_est, n_gt: poses in the two trajectories before association.
    """

    rmse_m: float
    mean_m: float
    median_m: float
    max_m: float
    errors_m: np.ndarray
    stamps_ns: np.ndarray
    aligned_poses: np.ndarray
    gt_poses: np.ndarray
    T_gt_est: np.ndarray
    n_matched: int
    n_est: int
    n_gt: int

    @property
    def rmse_cm(self) -> float:
        return self.rmse_m * 100.0

    @property
    def mean_cm(self) -> float:
        return self.mean_m * 100.0

    @property
    def median_cm(self) -> float:
        return self.median_m * 100.0

    @property
    def max_cm(self) -> float:
        return self.max_m * 100.0


@dataclass(frozen=True)
class RpeResult:
    """Relative pose error over pairs of matched poses a fixed step apart.

    Attributes:
        delta: the step, in ``delta_unit``.
        delta_unit: ``"frames"`` (pairs ``(i, i + delta)`` of matched poses) or ``"s"`` (pairs about
            ``delta`` seconds apart).
        pairs: ``(k, 2)`` indices ``(i, j)`` into the matched poses.
        trans_errors_m: ``(k,)`` translational error of each pair, metres.
        rot_errors_deg: ``(k,)`` rotational error of each pair, degrees.
        trans_rmse_m, trans_mean_m, trans_median_m, trans_max_m: statistics of ``trans_errors_m``
            (None when there are no pairs).
        rot_rmse_deg, rot_mean_deg, rot_median_deg, rot_max_deg: statistics of ``rot_errors_deg``.
    """

    delta: float
    delta_unit: str
    pairs: np.ndarray
    trans_errors_m: np.ndarray
    rot_errors_deg: np.ndarray
    trans_rmse_m: float | None
    trans_mean_m: float | None
    trans_median_m: float | None
    trans_max_m: float | None
    rot_rmse_deg: float | None
    rot_mean_deg: float | None
    rot_median_deg: float | None
    rot_max_deg: float | None

    @property
    def n_pairs(self) -> int:
        return len(self.pairs)

    @property
    def trans_rmse_cm(self) -> float | None:
        return None if self.trans_rmse_m is None else self.trans_rmse_m * 100.0


def _describe(source: str | Path | None, what: str) -> str:
    return f"{what} {source}" if source is not None else what


def _span_s(stamps_ns: np.ndarray) -> str:
    if len(stamps_ns) == 0:
        return "no stamps"
    return f"{stamps_ns.min() * 1e-9:.3f}..{stamps_ns.max() * 1e-9:.3f} s"


def associate_trajectories(
    est: Trajectory,
    gt: Trajectory,
    max_dt_s: float = DEFAULT_MAX_DT_S,
    est_source: str | Path | None = None,
    gt_source: str | Path | None = None,
    min_matches: int = MIN_MATCHES,
) -> TrajectoryPair:
    """Pair each estimated pose with the nearest unused ground-truth pose within ``max_dt_s``.

    Estimated poses with no ground truth in the window are dropped. ``est_source`` / ``gt_source``
    (file names) only make error messages precise.

    Raises:
        DatasetError: fewer than ``min_matches`` poses associate (names both sources and their time spans).
    """
    if not max_dt_s >= 0:
        raise ValueError(f"max_dt_s must be >= 0, got {max_dt_s}")
    idx = associate_unique(est.stamps_ns, gt.stamps_ns, int(round(max_dt_s * 1e9)))
    keep = np.flatnonzero(idx >= 0)
    if len(keep) < min_matches:
        raise DatasetError(
            est_source,
            f"only {len(keep)} of {len(est)} estimated poses have a pose in "
            f"{_describe(gt_source, 'the ground truth')} within {max_dt_s} s; at least {min_matches} are needed "
            f"(estimate spans {_span_s(est.stamps_ns)}, ground truth spans {_span_s(gt.stamps_ns)}; "
            "are both stamped in the same clock, in seconds?)",
        )
    # keep the estimate's order; sort by stamp in case the file was not ordered
    keep = keep[np.argsort(est.stamps_ns[keep], kind="stable")]
    return TrajectoryPair(
        stamps_ns=est.stamps_ns[keep].copy(),
        est_poses=est.poses[keep].copy(),
        gt_poses=gt.poses[idx[keep]].copy(),
        gt_stamps_ns=gt.stamps_ns[idx[keep]].copy(),
        n_est=len(est),
        n_gt=len(gt),
    )


def align_rigid(src_xyz: np.ndarray, dst_xyz: np.ndarray) -> np.ndarray:
    """Closed-form rigid fit ``dst ~ R src + t`` (Horn / Umeyama without scale).

    With centred point sets ``s_i``, ``d_i`` and the cross-covariance ``H = sum_i d_i s_i^T = U S V^T``,
    the rotation maximising ``trace(R^T H)`` is ``R = U D V^T`` with ``D = diag(1, 1, det(U V^T))``: the
    sign flip keeps ``det R = +1`` when the best orthogonal fit would be a reflection. Then
    ``t = mean(dst) - R mean(src)``. When the points are collinear the rotation about their line is not
    determined; any of the equally good rotations is returned.

    Args:
        src_xyz: ``(n, 3)`` points to be moved (e.g. estimated camera centres).
        dst_xyz: ``(n, 3)`` target points (e.g. ground-truth camera centres), ``n >= 3``.

    Returns:
        ``(4, 4)`` float64 transform ``T_dst_src``.
    """
    src = np.asarray(src_xyz, dtype=np.float64)
    dst = np.asarray(dst_xyz, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
        raise ValueError(f"align_rigid: expected two (n, 3) arrays of the same shape, got {src.shape} and {dst.shape}")
    if len(src) < MIN_MATCHES:
        raise ValueError(f"align_rigid: need at least {MIN_MATCHES} point pairs, got {len(src)}")
    if not (np.isfinite(src).all() and np.isfinite(dst).all()):
        raise ValueError("align_rigid: points must be finite")
    mu_src, mu_dst = src.mean(axis=0), dst.mean(axis=0)
    H = (dst - mu_dst).T @ (src - mu_src)
    U, _, Vt = np.linalg.svd(H)
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt)) or 1.0
    R = U @ D @ Vt
    return make_pose(R, mu_dst - R @ mu_src)


def _stats(values: np.ndarray) -> tuple[float, float, float, float]:
    """(rmse, mean, median, max) of ``values``."""
    v = np.asarray(values, dtype=np.float64)
    return (float(np.sqrt(np.mean(v * v))), float(np.mean(v)), float(np.median(v)), float(np.max(v)))


def compute_ate(pair: TrajectoryPair, align: bool = True) -> AteResult:
    """ATE of associated poses; with ``align`` the estimate is first mapped by the rigid fit to the ground truth."""
    if len(pair) < MIN_MATCHES:
        raise ValueError(f"compute_ate: need at least {MIN_MATCHES} associated poses, got {len(pair)}")
    p_est = pair.est_poses[:, :3, 3]
    p_gt = pair.gt_poses[:, :3, 3]
    T_gt_est = align_rigid(p_est, p_gt) if align else np.eye(4)
    aligned = T_gt_est @ pair.est_poses
    errors = np.linalg.norm(aligned[:, :3, 3] - p_gt, axis=1)
    rmse, mean, median, max_ = _stats(errors)
    return AteResult(
        rmse_m=rmse,
        mean_m=mean,
        median_m=median,
        max_m=max_,
        errors_m=errors,
        stamps_ns=pair.stamps_ns,
        aligned_poses=aligned,
        gt_poses=pair.gt_poses,
        T_gt_est=T_gt_est,
        n_matched=len(pair),
        n_est=pair.n_est,
        n_gt=pair.n_gt,
    )


def evaluate_ate(
    est: Trajectory,
    gt: Trajectory,
    max_dt_s: float = DEFAULT_MAX_DT_S,
    align: bool = True,
    est_source: str | Path | None = None,
    gt_source: str | Path | None = None,
) -> AteResult:
    """Associate ``est`` with ``gt`` by stamp, align rigidly, and compute the ATE (see the module docstring)."""
    return compute_ate(associate_trajectories(est, gt, max_dt_s, est_source, gt_source), align=align)


def rpe_pairs(
    stamps_ns: np.ndarray, delta: float, delta_unit: str = "s", tolerance_s: float | None = None
) -> np.ndarray:
    """Index pairs ``(i, j)``, ``j > i``, a fixed step apart.

    ``delta_unit="frames"``: ``j = i + delta``. ``delta_unit="s"``: ``j`` is the pose whose stamp is
    nearest to ``t_i + delta``, kept only when within ``tolerance_s`` of it (default: half the median
    interval between poses, so a pair is skipped where poses are missing rather than stretched).

    Args:
        stamps_ns: ``(n,)`` increasing int64 stamps.

    Returns:
        ``(k, 2)`` int64 indices.
    """
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    n = len(stamps_ns)
    if delta_unit == "frames":
        step = int(delta)
        if step != delta or step < 1:
            raise ValueError(f"rpe: a delta in frames must be a positive integer, got {delta}")
        i = np.arange(max(n - step, 0))
        return np.stack([i, i + step], axis=1).astype(np.int64)
    if delta_unit != "s":
        raise ValueError(f"rpe: delta_unit must be 'frames' or 's', got {delta_unit!r}")
    if not delta > 0:
        raise ValueError(f"rpe: delta must be > 0 s, got {delta}")
    if n < 2:
        return np.zeros((0, 2), np.int64)
    if tolerance_s is None:
        tolerance_ns = 0.5 * float(np.median(np.diff(stamps_ns)))
    else:
        tolerance_ns = tolerance_s * 1e9
    target = stamps_ns + int(round(delta * 1e9))
    pos = np.searchsorted(stamps_ns, target)
    lo = np.clip(pos - 1, 0, n - 1)
    hi = np.clip(pos, 0, n - 1)
    j = np.where(np.abs(stamps_ns[hi] - target) < np.abs(target - stamps_ns[lo]), hi, lo)
    i = np.arange(n)
    ok = (j > i) & (np.abs(stamps_ns[j] - target) <= tolerance_ns)
    return np.stack([i[ok], j[ok]], axis=1).astype(np.int64)


def compute_rpe(
    pair: TrajectoryPair, delta: float = 1.0, delta_unit: str = "s", tolerance_s: float | None = None
) -> RpeResult:
    """RPE of associated poses over pairs from :func:`rpe_pairs` (no alignment is needed)."""
    pairs = rpe_pairs(pair.stamps_ns, delta, delta_unit, tolerance_s)
    i, j = pairs[:, 0], pairs[:, 1]
    rel_gt = invert(pair.gt_poses[i]) @ pair.gt_poses[j]
    rel_est = invert(pair.est_poses[i]) @ pair.est_poses[j]
    E = invert(rel_gt) @ rel_est
    trans = np.linalg.norm(E[:, :3, 3], axis=1)
    rot = np.degrees(Rotation.from_matrix(E[:, :3, :3]).magnitude()) if len(E) else np.zeros(0)
    if len(pairs):
        t_stats: tuple = _stats(trans)
        r_stats: tuple = _stats(rot)
    else:
        t_stats = r_stats = (None,) * 4
    return RpeResult(
        delta=float(delta),
        delta_unit=delta_unit,
        pairs=pairs,
        trans_errors_m=trans,
        rot_errors_deg=np.asarray(rot, dtype=np.float64),
        trans_rmse_m=t_stats[0],
        trans_mean_m=t_stats[1],
        trans_median_m=t_stats[2],
        trans_max_m=t_stats[3],
        rot_rmse_deg=r_stats[0],
        rot_mean_deg=r_stats[1],
        rot_median_deg=r_stats[2],
        rot_max_deg=r_stats[3],
    )


def evaluate_rpe(
    est: Trajectory,
    gt: Trajectory,
    delta: float = 1.0,
    delta_unit: str = "s",
    max_dt_s: float = DEFAULT_MAX_DT_S,
    est_source: str | Path | None = None,
    gt_source: str | Path | None = None,
) -> RpeResult:
    """Associate ``est`` with ``gt`` by stamp and compute the RPE (see :func:`compute_rpe`)."""
    return compute_rpe(associate_trajectories(est, gt, max_dt_s, est_source, gt_source), delta, delta_unit)
