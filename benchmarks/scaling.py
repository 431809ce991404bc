"""Tracking cost against the number of neural blocks: only the blocks in the camera's frustum take part.

On the synthetic ``corridor`` preset (a 28 m corridor with rooms on both sides), in one run:

1. allocate blocks with the paper's tau rule along the first ``--start-frames`` ground-truth poses
   (one block), fit the map to those frames, and time tracking of ``--track-frames`` of them from a
   perturbed pose (``track_ms_one_block``);
2. allocate the rest of the corridor's blocks along the whole trajectory (``n_blocks``, at least 6)
   and time tracking of the same frames from the same perturbed poses again
   (``track_ms_many_blocks``).

The frames, poses, rays and iterations are the same in both timings (the tracker runs a fixed number
of steps: ``gn_stop_step_m`` is 0), so the ratio measures what the extra blocks cost. Each timing is
the median over ``--repeats`` passes. Tracking also reports the blocks in each frustum.

Example::

    .venv/bin/python benchmarks/scaling.py --json scaling.json
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from common import predicted_start, report
from neb_slam_core.config_io import load_config
from neb_slam_core.datasets import open_dataset
from neb_slam_core.mapping.fit import FitConfig, FrameRayPool, allocate_blocks, fit_map
from neb_slam_core.scene.block_map import BlockMap
from neb_slam_core.synth.generate import generate
from neb_slam_core.tracking.tracker import Tracker

REPO = Path(__file__).resolve().parents[1]


def time_tracking(tracker_cfg, render_cfg, block_map, frames, starts, repeats: int) -> tuple[float, list[int]]:
    """Median over ``repeats`` of the mean tracking time per frame (ms); frustum block counts."""
    s = render_cfg.sampling
    per_pass = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for frame, T0 in zip(frames, starts):
            Tracker(tracker_cfg, render_cfg, seed=0).track(block_map, frame, T0)
        per_pass.append(1e3 * (time.perf_counter() - t0) / len(frames))
    in_view = [len(block_map.blocks_in_frustum(T0, f.intrinsics, s.near_m, s.far_m)) for f, T0 in zip(frames, starts)]
    return float(np.median(per_pass)), in_view


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default="synthetic", help="engine config (tracking and rendering settings)")
    p.add_argument("--start-frames", type=int, default=12, help="frames mapped while there is one block")
    p.add_argument("--track-frames", type=int, default=4, help="frames whose tracking is timed")
    p.add_argument("--fit-iterations", type=int, default=150)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    p.add_argument("--json", type=Path, default=None, help="write the figures to this JSON file")
    args = p.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    cfg = load_config(args.config)
    tracker_cfg = replace(cfg.tracking, gn_stop_step_m=0.0)  # a fixed number of steps in both timings
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)

    scene = generate("corridor", REPO / ".cache" / "scenes" / "corridor", progress=True)
    ds = open_dataset(scene)
    frames = [ds[i] for i in range(len(ds))]
    s = cfg.render.sampling
    block_map = BlockMap(cfg.block, cfg.one_blob, cfg.decoder, grid_backend=cfg.grid_backend, seed=cfg.seed)
    start = frames[:args.start_frames]
    allocate_blocks(block_map, start, [f.T_world_cam for f in start], s.near_m, s.far_m, rng)
    n_start = len(block_map)
    fit_map(block_map, FrameRayPool(start, [f.T_world_cam for f in start]), cfg.render,
            FitConfig(iterations=args.fit_iterations, rays_per_iteration=cfg.mapping.n_rays), seed=cfg.seed,
            progress=True)

    timed = start[1::max(1, len(start) // args.track_frames)][:args.track_frames]
    starts = [predicted_start(f.T_world_cam) for f in timed]
    one_ms, one_view = time_tracking(tracker_cfg, cfg.render, block_map, timed, starts, args.repeats)

    allocate_blocks(block_map, frames, [f.T_world_cam for f in frames], s.near_m, s.far_m, rng)
    many_ms, many_view = time_tracking(tracker_cfg, cfg.render, block_map, timed, starts, args.repeats)

    figures = {
        "track_ms_one_block": round(one_ms, 1),
        "track_ms_many_blocks": round(many_ms, 1),
        "ratio": round(many_ms / one_ms, 3),
        "n_blocks_start": n_start,
        "n_blocks": len(block_map),
        "frustum_blocks_one": one_view,
        "frustum_blocks_many": many_view,
        "tracking_method": tracker_cfg.method,
        "tracking_iterations": tracker_cfg.iterations,
        "n_rays": tracker_cfg.n_rays,
        "threads": torch.get_num_threads(),
        "cpus": os.cpu_count(),
    }
    print(f"tracking per frame: {one_ms:.1f} ms with {n_start} block(s), {many_ms:.1f} ms with {len(block_map)} "
          f"blocks (x{many_ms / one_ms:.3f}); blocks in the timed frusta: {one_view} -> {many_view}")
    report(figures, args.json)


if __name__ == "__main__":
    main()
