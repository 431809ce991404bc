"""Evaluation figures (matplotlib, drawn off-screen with the Agg canvas; no display needed).

Functions build :class:`matplotlib.figure.Figure` objects directly rather than through ``pyplot``, so
they hold no global state and work on a headless machine; :func:`save_figure` writes a PNG.
"""

from __future__ import annotations

from collections.abc import Sequence
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


def plot_trajectory(ate: AteResult, title: str | None = None, loops: Sequence[tuple[int, int, bool]] = ()) -> Figure:
    """Top view of the aligned estimate against the ground truth, with start markers and error segments.

    The view is the plane of the two axes along which the ground truth extends most. ``loops``: loop
    closures as ``(stamp_ns, loop_stamp_ns, applied)``, drawn as a segment between the two estimated
    positions (solid: applied, dotted: detected but not applied); stamps not in ``ate`` are left out.
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
    where = {int(s): i for i, s in enumerate(ate.stamps_ns)}
    labelled: set[bool] = set()
    for stamp, loop_stamp, applied in loops:
        if int(stamp) in where and int(loop_stamp) in where:
            p, q = est[where[int(stamp)]], est[where[int(loop_stamp)]]
            label = None if applied in labelled else ("loop closure" if applied else "loop (not applied)")
            labelled.add(applied)
            ax.plot(
                [p[a], q[a]],
                [p[b], q[b]],
                color="tab:red",
                linestyle="-" if applied else ":",
                linewidth=1.5,
                marker="o",
                markersize=3,
                zorder=5,
                label=label,
            )
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


def plot_block_allocation(
    positions_xyz: np.ndarray,
    block_centres_xyz: np.ndarray,
    edge_m: float,
    alloc_frame_indices: np.ndarray,
    alloc_cam_xyz: np.ndarray,
    title: str | None = None,
) -> Figure:
    """Top view of the neural blocks and the trajectory that allocated them (the paper's allocation figure).

    Each block is drawn as the outline of its ``edge_m`` square footprint around its centre, coloured by
    the index of the frame that allocated it (colour bar); that frame's camera centre is marked with a
    triangle of the same colour. The view is the plane of the two axes along which the trajectory
    extends most (as in :func:`plot_trajectory`).

    Args:
        positions_xyz: ``(N, 3)`` camera centres of the trajectory, world frame, metres.
        block_centres_xyz: ``(M, 3)`` block centres, same frame.
        edge_m: block edge length, metres.
        alloc_frame_indices: ``(M,)`` int index of the frame that allocated each block; -1 when unknown
            (such blocks are drawn grey and get no camera marker).
        alloc_cam_xyz: ``(M, 3)`` camera centre of the allocating frame (ignored where the index is -1).
    """
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.patches import Rectangle

    positions = np.asarray(positions_xyz, dtype=np.float64).reshape(-1, 3)
    centres = np.asarray(block_centres_xyz, dtype=np.float64).reshape(-1, 3)
    frames = np.asarray(alloc_frame_indices, dtype=np.int64).reshape(-1)
    cams = np.asarray(alloc_cam_xyz, dtype=np.float64).reshape(-1, 3)
    if not (len(centres) == len(frames) == len(cams)):
        raise ValueError(
            f"plot_block_allocation: {len(centres)} block centres, {len(frames)} frame indices and "
            f"{len(cams)} camera positions; expected one of each per block"
        )
    ref = positions if len(positions) else centres
    a, b = top_view_axes(ref) if len(ref) else (0, 1)
    known = frames >= 0
    cmap = colormaps["viridis"]
    lo, hi = (int(frames[known].min()), int(frames[known].max())) if known.any() else (0, 1)
    norm = Normalize(vmin=lo, vmax=hi if hi > lo else lo + 1)
    half = 0.5 * edge_m

    fig = _new_figure(6.4, 5.6)
    ax = fig.add_subplot()
    for m, (c, f) in enumerate(zip(centres, frames)):
        colour = cmap(norm(f)) if f >= 0 else "0.6"
        ax.add_patch(
            Rectangle(
                (c[a] - half, c[b] - half),
                edge_m,
                edge_m,
                fill=True,
                facecolor=colour,
                alpha=0.08,
                edgecolor="none",
                zorder=1,
            )
        )
        ax.add_patch(
            Rectangle(
                (c[a] - half, c[b] - half),
                edge_m,
                edge_m,
                fill=False,
                edgecolor=colour,
                linewidth=1.5,
                zorder=2,
                gid=f"block-{m}",
            )
        )
        ax.annotate(str(m), (c[a], c[b]), ha="center", va="center", fontsize="small", color="0.25", zorder=2)
    if len(positions):
        ax.plot(positions[:, a], positions[:, b], color="black", linewidth=1.0, label="trajectory", zorder=3)
    if known.any():
        ax.scatter(
            cams[known, a],
            cams[known, b],
            c=frames[known],
            cmap=cmap,
            norm=norm,
            marker="^",
            s=70,
            edgecolors="black",
            linewidths=0.6,
            zorder=4,
            label="allocating frame",
        )
    ax.autoscale_view()
    ax.set_xlabel(f"{_AXIS_NAMES[a]} [m]")
    ax.set_ylabel(f"{_AXIS_NAMES[b]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, linewidth=0.3)
    if len(positions) or known.any():
        ax.legend(loc="best", fontsize="small")
    fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), ax=ax, label="allocating frame index")
    n = len(centres)
    ax.set_title(title or f"block allocation: {n} block{'' if n == 1 else 's'} of {edge_m:g} m")
    return fig


def save_figure(fig: Figure, path: str | Path, dpi: int = 120) -> Path:
    """Write ``fig`` as a PNG at ``path`` (parent folders created); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi, format="png")
    return path
