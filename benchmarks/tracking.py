"""Tracking cost per frame, and what the Gauss-Newton Jacobian's spatial gradients cost three ways.

On TUM fr1_xyz (``../shared/data/tum_fr1_xyz_300``, ``tum`` config), in one run:

1. fit a map to ``--fit-frames`` frames with their ground-truth poses (``--fit-iterations`` of the
   config's mapping rays);
2. for ``--track-frames`` later frames, from a pose 1 cm and 0.5 degree off, evaluate the objective
   and build the Gauss-Newton system with the samples' spatial gradients in closed form (the C++
   features with their derivatives and the decoders' forward mode, the engine's way), by forward
   differences (one batched query of 4x the points, the way on other backends) and by autograd (one
   backward pass per output, the reference): ``normal_equations_ms_closed``, ``normal_equations_ms_fd``,
   ``normal_equations_ms_autograd`` and the ratios ``fd_over_closed`` and ``autograd_over_closed``;
   each system's largest difference to autograd's relative to its largest entry (``max_rel_diff_H_closed``,
   ``max_rel_diff_H_fd``);
3. track the same frames (the engine's tracker): ``track_ms`` per frame and its steps; and again with
   the autograd gradients: how far apart the two trackers' poses end (``pose_gap_to_autograd_mm``).

Each timing is the median over ``--repeats`` passes.

Example::

    .venv/bin/python benchmarks/tracking.py --json tracking.json
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
from common import fitted_tum_map, load_figures, median_ms, predicted_start, report

from neb_slam_core.config_io import load_config
from neb_slam_core.render.rays import sample_pixels
from neb_slam_core.render.sampling import sample_depths
from neb_slam_core.scene.freeze import frozen
from neb_slam_core.tracking.gauss_newton import (
    evaluate_pose,
    forward_difference_gradients,
    normal_equations,
    spatial_gradients,
    spatial_gradients_autograd,
)
from neb_slam_core.tracking.tracker import Tracker


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--fit-frames", type=int, default=30, help="frames 0, 2, 4, ... the map is fitted to")
    p.add_argument("--fit-iterations", type=int, default=1000)
    p.add_argument("--track-frames", type=int, default=5)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--json", type=Path, default=None, help="a copy of the stamped figures (see benchmarks/results/)")
    args = p.parse_args()
    cfg = load_config("tum")
    rng = np.random.default_rng(cfg.seed)
    block_map, tracked = fitted_tum_map(cfg, args.fit_frames, args.fit_iterations, args.track_frames, rng)
    s = cfg.render.sampling

    starts = [predicted_start(f.T_world_cam) for f in tracked]

    ways = {"closed": spatial_gradients, "fd": forward_difference_gradients, "autograd": spatial_gradients_autograd}
    ne_ms = {way: [] for way in ways}
    rel = {"closed": [], "fd": []}
    ev_ms = []
    with frozen(block_map):
        for f, T in zip(tracked, starts):
            px = sample_pixels(f, cfg.tracking.n_rays, rng, valid_depth_only=True)
            z = sample_depths(px.depth_m, s, stratified=True, generator=torch.Generator().manual_seed(cfg.seed))
            ids = block_map.blocks_in_frustum(T, f.intrinsics, s.near_m, s.far_m)
            ev_ms.append(median_ms(lambda: evaluate_pose(block_map, px, T, z, cfg.render, ids), args.repeats))
            ev = evaluate_pose(block_map, px, T, z, cfg.render, ids)
            for _ in range(args.repeats):  # the ways interleaved, so that drifts of the machine's speed hit all
                for way, gradients in ways.items():
                    ne_ms[way].append(median_ms(lambda: normal_equations(ev, block_map, ids, gradients), 1))
            H_auto, _ = normal_equations(ev, block_map, ids, spatial_gradients_autograd)
            for way in rel:
                H, _ = normal_equations(ev, block_map, ids, ways[way])
                rel[way].append(float(np.abs(H - H_auto).max() / np.abs(H_auto).max()))

    track_ms, steps, gaps = [], [], []
    for f, T in zip(tracked, starts):
        t0 = time.perf_counter()
        result = Tracker(cfg.tracking, cfg.render, seed=cfg.seed).track(block_map, f, T)
        track_ms.append(1e3 * (time.perf_counter() - t0))
        steps.append(result.iterations)
        reference = Tracker(cfg.tracking, cfg.render, seed=cfg.seed, gradients=spatial_gradients_autograd).track(
            block_map, f, T
        )
        gaps.append(1e3 * float(np.linalg.norm(result.T_world_cam[:3, 3] - reference.T_world_cam[:3, 3])))

    figures = {
        **{f"normal_equations_ms_{way}": round(float(np.median(ms)), 1) for way, ms in ne_ms.items()},
        "fd_over_closed": round(float(np.median(ne_ms["fd"]) / np.median(ne_ms["closed"])), 2),
        "autograd_over_closed": round(float(np.median(ne_ms["autograd"]) / np.median(ne_ms["closed"])), 2),
        "evaluate_pose_ms": round(float(np.median(ev_ms)), 1),
        "max_rel_diff_H_closed": float(f"{max(rel['closed']):.2g}"),
        "max_rel_diff_H_fd": round(max(rel["fd"]), 4),
        "track_ms": round(float(np.median(track_ms)), 1),
        "track_steps": steps,
        "pose_gap_to_autograd_mm": [round(g, 3) for g in gaps],
        "n_rays": cfg.tracking.n_rays,
        **load_figures(),
    }
    print(
        f"normal equations: {figures['normal_equations_ms_closed']} ms in closed form, "
        f"{figures['normal_equations_ms_fd']} ms by forward differences (x{figures['fd_over_closed']}), "
        f"{figures['normal_equations_ms_autograd']} ms by autograd (x{figures['autograd_over_closed']}); "
        f"tracking {figures['track_ms']} ms per frame"
    )
    report(figures, args.json, "tracking")


if __name__ == "__main__":
    main()
