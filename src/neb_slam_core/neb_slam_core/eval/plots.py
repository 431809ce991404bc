"""Evaluation figures (matplotlib, drawn off-screen with the Agg canvas; no display needed).

Functions build :class:`matplotlib.figure.Figure` objects directly rather than through ``pyplot``, so
they hold no global state and work on a headless machine; :func:`save_figure` writes a PNG.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from .trajectory_metrics import AteResult

_AXIS_NAMES = ("x", "y", "z")


def _new_figure(width_in: float = 6.4, height_in: float = 4.8) -> Figure:
    fig = Figure(figsize=(width_in, height_in), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def top_view_axes(positions: np.ndarray) -> tuple[int, int]:
    """The two coordinate axes (indices, ascending) along which ``positions`` ``(n, 3)`` extend most."""
    extent = np.ptp(np.asarray(positions, dtype=np.float64).reshape(-1, 3), axis=0)
    a, b = sorted(np.argsort(-extent, kind="stable")[:2])
    return int(a), int(b)


def plot_trajectory(ate: AteResult, title: str | None = None) -> Figure:
    """Top view of the aligned estimate against the ground truth, with start markers and error segments.

    The view is the plane of the two axes along which the ground truth extends most.
    """
    gt = ate.gt_poses[:, :3, 3]
    est = ate.aligned_poses[:, :3, 3]
    a, b = top_view_axes(gt)
    fig = _new_figure()
    ax = fig.add_subplot()
    step = max(1, len(gt) // 200)  # thin grey residual segments, at most ~200 of them
    for p, q in zip(gt[::step], est[::step]):
        ax.plot([p[a], q[a]], [p[b], q[b]], color="0.75", linewidth=0.6, zorder=1)
    ax.plot(gt[:, a], gt[:, b], color="black", linewidth=1.5, label="ground truth", zorder=2)
    ax.plot(est[:, a], est[:, b], color="tab:blue", linewidth=1.2, label="estimate (aligned)", zorder=3)
    ax.scatter([gt[0, a]], [gt[0, b]], marker="o", s=60, facecolors="none", edgecolors="black", zorder=4, label="start")
    ax.scatter([est[0, a]], [est[0, b]], marker="x", s=40, color="tab:blue", zorder=4)
    ax.set_xlabel(f"{_AXIS_NAMES[a]} [m]")
    ax.set_ylabel(f"{_AXIS_NAMES[b]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, linewidth=0.3)
    ax.legend(loc="best", fontsize="small")
    ax.set_title(title or f"trajectory (ATE RMSE {ate.rmse_cm:.2f} cm, {ate.n_matched} poses)")
    return fig


def plot_ate_over_time(ate: AteResult, title: str | None = None) -> Figure:
    """Per-pose ATE (cm) against time since the first matched pose, with the RMSE as a dashed line."""
    t_s = (ate.stamps_ns - ate.stamps_ns[0]).astype(np.float64) * 1e-9
    fig = _new_figure(6.4, 3.6)
    ax = fig.add_subplot()
    ax.plot(t_s, ate.errors_m * 100.0, color="tab:red", linewidth=1.0, label="error")
    ax.axhline(ate.rmse_cm, color="black", linestyle="--", linewidth=0.8, label=f"RMSE {ate.rmse_cm:.2f} cm")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("ATE [cm]")
    ax.set_ylim(bottom=0.0)
    ax.grid(True, linewidth=0.3)
    ax.legend(loc="best", fontsize="small")
    ax.set_title(title or "absolute trajectory error over time")
    return fig


def save_figure(fig: Figure, path: str | Path, dpi: int = 120) -> Path:
    """Write ``fig`` as a PNG at ``path`` (parent folders created); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi, format="png")
    return path
