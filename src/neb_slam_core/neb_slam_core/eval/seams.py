"""Continuity of rendered depth across block seams.

Where the observed surface crosses a block face that lies inside another block, the set of blocks
answering for neighbouring pixels changes; the map's depth must not step there. For horizontally
adjacent pixel pairs on one smooth surface (ground-truth depth locally linear along the row: no object
edge or corner, where a step is real) whose surface points lie in different sets of blocks, we compare
the rendered depth step with the ground-truth step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class SeamSteps:
    """Step errors (metres) at seam crossings and, for reference, at all other smooth pixel pairs."""

    seam: np.ndarray
    elsewhere: np.ndarray

    def summary_cm(self) -> dict[str, float]:
        def pct(x, q):
            return float(np.percentile(x, q) * 100) if x.size else float("nan")

        return {
            "seam_pairs": int(self.seam.size),
            "seam_step_max_cm": pct(self.seam, 100),
            "seam_step_p99_cm": pct(self.seam, 99),
            "other_step_p99_cm": pct(self.elsewhere, 99),
        }


def seam_step_errors(
    rendered_depth: np.ndarray,
    gt_depth: np.ndarray,
    T_world_cam: np.ndarray,
    intrinsics,
    block_centres: np.ndarray,
    edge_m: float,
    linear_tol_m: float = 0.002,
) -> SeamSteps:
    """Step errors for one view.

    Args:
        rendered_depth: ``(H, W)`` depth rendered from the map (0 = no surface).
        gt_depth: ``(H, W)`` ground-truth depth at the same pose.
        block_centres: ``(M, 3)`` block centres; ``edge_m`` their edge.
        linear_tol_m: bound on the second difference of ground-truth depth along the row.
    """
    h, w = gt_depth.shape
    v, u = np.mgrid[0:h, 0:w]
    k = intrinsics
    z = gt_depth.astype(np.float64)
    d = rendered_depth.astype(np.float64)
    cam = np.stack([(u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z], axis=-1)
    world = cam @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
    inside = np.all(np.abs(world[..., None, :] - block_centres) <= 0.5 * edge_m, axis=-1)  # (H, W, M)
    code = (inside * (1 << np.arange(len(block_centres)))).sum(-1)
    a, b = (slice(None), slice(1, w - 2)), (slice(None), slice(2, w - 1))  # pairs (j, j+1)
    before, after = (slice(None), slice(0, w - 3)), (slice(None), slice(3, w))
    linear = (np.abs(z[before] - 2 * z[a] + z[b]) < linear_tol_m) & (np.abs(z[a] - 2 * z[b] + z[after]) < linear_tol_m)
    usable = linear & (z[before] > 0) & (z[a] > 0) & (z[b] > 0) & (z[after] > 0) & (d[a] > 0) & (d[b] > 0)
    seam = (code[a] != code[b]) & (code[a] > 0) & (code[b] > 0)
    err = np.abs((d[b] - d[a]) - (z[b] - z[a]))
    return SeamSteps(err[usable & seam], err[usable & ~seam])
