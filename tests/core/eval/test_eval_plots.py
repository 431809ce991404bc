"""Evaluation figures are written off-screen as PNG files."""

from __future__ import annotations

import numpy as np

from neb_slam_core.eval.plots import plot_ate_over_time, plot_trajectory, save_figure, top_view_axes
from neb_slam_core.eval.trajectory_metrics import evaluate_ate
from neb_slam_core.io.trajectory import Trajectory

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def small_ate():
    n = 50
    t = np.linspace(0, 2 * np.pi, n)
    gt_poses = np.tile(np.eye(4), (n, 1, 1))
    gt_poses[:, :3, 3] = np.c_[np.cos(t), 0.1 * t, 2 * np.sin(t)]  # spread most in x and z
    est_poses = gt_poses.copy()
    est_poses[:, 1, 3] += 0.01 * np.sin(5 * t)
    stamps = (np.arange(n) * 0.1 * 1e9).astype(np.int64)
    return evaluate_ate(Trajectory(stamps, est_poses), Trajectory(stamps, gt_poses))


def test_top_view_uses_the_two_axes_of_largest_extent():
    ate = small_ate()
    assert top_view_axes(ate.gt_poses[:, :3, 3]) == (0, 2)
    assert top_view_axes(np.array([[0, 0, 0], [1, 5, 0.1]])) == (0, 1)


def test_plots_are_written(tmp_path):
    ate = small_ate()
    paths = [
        save_figure(plot_trajectory(ate), tmp_path / "trajectory.png"),
        save_figure(plot_ate_over_time(ate), tmp_path / "sub" / "ate_over_time.png"),
    ]
    for p in paths:
        assert p.is_file() and p.stat().st_size > 1000
        assert p.read_bytes()[:8] == PNG_MAGIC
    fig = plot_trajectory(ate)
    ax = fig.axes[0]
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("x [m]", "z [m]")


def test_loops_are_drawn_between_the_two_estimated_positions():
    ate = small_ate()
    s = ate.stamps_ns
    fig = plot_trajectory(ate, loops=[(s[40], s[2], True), (s[45], s[3], False), (s[45], 123, True)])
    lines = {line.get_label(): line for line in fig.axes[0].get_lines()}
    applied, skipped = lines["loop closure"], lines["loop (not applied)"]
    est = ate.aligned_poses[:, :3, 3]
    np.testing.assert_allclose(applied.get_xdata(), [est[40, 0], est[2, 0]])
    np.testing.assert_allclose(applied.get_ydata(), [est[40, 2], est[2, 2]])
    assert applied.get_linestyle() == "-" and skipped.get_linestyle() == ":"
    # the third loop names a stamp the trajectory does not have: not drawn
    assert sum(line.get_color() == "tab:red" for line in fig.axes[0].get_lines()) == 2
