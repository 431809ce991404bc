"""Tracking cost against the number of neural blocks: only the blocks in the camera's frustum take part.

On the synthetic ``corridor`` preset (a 28 m corridor with rooms on both sides), in one run:

1. the one-block map: the first ``--start-frames`` frames mapped at their ground-truth poses with the
   engine's own steps (:class:`~neb_slam_core.slam.KnownPoseMapping`: blocks allocated by the paper's
   tau rule, one block; each frame a keyframe), ``--fit-iterations`` mapping steps with the poses held;
2. the many-block map: the same block, then the rest of the corridor's blocks allocated along the
   whole trajectory (``n_blocks``, at least 6), fitted to the same keyframes with the same draws (the
   fit takes no extra N_a rays from the newest block's keyframes, which only one of the maps has). Both
   maps are trained where the timed views look, as a running engine's would be: blocks allocated and
   never trained would blend untrained features into their overlap with the first block, change the
   rendered surface and with it how many samples tracking evaluates, which is not what more blocks
   cost;
3. time tracking of ``--track-frames`` of the first frames from perturbed poses in each map
   (``track_ms_one_block``, ``track_ms_many_blocks``), passes alternating between the two maps so that
   the machine's changing speed reaches both alike.

The timed tracking is the tracker's Levenberg-Marquardt with every one of its 10 steps taken
(:func:`track_every_step`): the same pixels, samples and number of Gauss-Newton systems in both maps, so
the ratio measures what the extra blocks cost. The tracker as it runs stops building systems after a
rejected step, and how many it rejects depends on how each map happens to fit the frame; its times are
reported too (``tracker_ms_*``, ``tracker_ratio``; ``gn_stop_step_m`` is 0 there, so it never stops
early). Each timing is the median over ``--repeats`` passes (``ratio_per_pass`` shows their spread).
Tracking also reports the blocks in each frustum.

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
from neb_slam_core.render.rays import sample_pixels
from neb_slam_core.render.sampling import sample_depths
from neb_slam_core.scene.block_map import BlockMap
from neb_slam_core.scene.freeze import frozen
from neb_slam_core.slam import KnownPoseMapping
from neb_slam_core.synth.generate import generate
from neb_slam_core.tracking.gauss_newton import apply_step, damped_step, evaluate_pose, normal_equations
from neb_slam_core.tracking.tracker import Tracker

REPO = Path(__file__).resolve().parents[1]


def track_every_step(tracker_cfg, render_cfg, block_map, frame, T0) -> None:
    """The tracker's Levenberg-Marquardt with every step taken: ``iterations`` Gauss-Newton systems and
    one more evaluation than that, on the tracker's pixels and samples. :class:`Tracker` judges each step
    and builds the next system only after an accepted one, so how much work it does depends on how the
    map fits the frame, which differs between two maps for reasons other than their number of blocks;
    this is its most expensive case, the same work in both maps."""
    px = sample_pixels(
        frame, tracker_cfg.n_rays, np.random.default_rng(0), valid_depth_only=True, border=tracker_cfg.border_px
    )
    s = render_cfg.sampling
    ids = block_map.blocks_in_frustum(T0, frame.intrinsics, s.near_m, s.far_m)
    with frozen(block_map):
        z = sample_depths(px.depth_m, s, stratified=True, generator=torch.Generator().manual_seed(0))
        T = np.array(T0, dtype=np.float64)
        ev = evaluate_pose(block_map, px, T, z, render_cfg, ids)
        for _ in range(tracker_cfg.iterations):
            H, g = normal_equations(ev, block_map, ids)
            T = apply_step(T, damped_step(H, g, tracker_cfg.gn_damping))
            ev = evaluate_pose(block_map, px, T, z, render_cfg, ids)


def time_pass(track, block_map, frames, starts) -> float:
    """Mean time per frame (ms) of ``track(block_map, frame, T0)`` over ``frames`` from the poses ``starts``."""
    t0 = time.perf_counter()
    for frame, T0 in zip(frames, starts):
        track(block_map, frame, T0)
    return 1e3 * (time.perf_counter() - t0) / len(frames)


def frustum_blocks(render_cfg, block_map, frames, starts) -> list[int]:
    """Blocks in each frame's frustum at its start pose."""
    s = render_cfg.sampling
    return [len(block_map.blocks_in_frustum(T0, f.intrinsics, s.near_m, s.far_m)) for f, T0 in zip(frames, starts)]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default="synthetic", help="engine config (tracking and rendering settings)")
    p.add_argument("--start-frames", type=int, default=12, help="frames mapped while there is one block")
    p.add_argument("--track-frames", type=int, default=4, help="frames whose tracking is timed")
    p.add_argument("--fit-iterations", type=int, default=150)
    p.add_argument("--repeats", type=int, default=5, help="timed passes per map, alternating")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    p.add_argument("--json", type=Path, default=None, help="a copy of the stamped figures (see benchmarks/results/)")
    args = p.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    cfg = load_config(args.config)
    tracker_cfg = replace(cfg.tracking, gn_stop_step_m=0.0)  # the tracker never stops early
    torch.manual_seed(cfg.seed)

    scene = generate("corridor", REPO / ".cache" / "scenes" / "corridor", progress=True)
    ds = open_dataset(scene)
    frames = [ds[i] for i in range(len(ds))]
    start = frames[: args.start_frames]
    fit_cfg = replace(cfg, mapping=replace(cfg.mapping, n_rays_newest_block=0))

    def build(all_blocks: bool) -> tuple[BlockMap, int]:
        """The map of the first frames: their block(s), then (``all_blocks``) the rest of the corridor's,
        fitted to those frames (the same draws either way)."""
        mapping = KnownPoseMapping(fit_cfg)
        for f in start:
            mapping.add(f)
        n_start = len(mapping.block_map)
        if all_blocks:
            for f in frames:
                mapping.allocate(f)
        mapping.optimise(args.fit_iterations, progress=True)
        return mapping.block_map, n_start

    one_map, n_start = build(all_blocks=False)
    block_map, _ = build(all_blocks=True)
    timed = start[1 :: max(1, len(start) // args.track_frames)][: args.track_frames]
    starts = [predicted_start(f.T_world_cam) for f in timed]

    # Passes alternate between the two maps, so that a change in the machine's speed during the run
    # (other load, clock) reaches both timings alike; each is the median over its passes.
    def fixed(block_map, frame, T0):
        track_every_step(tracker_cfg, cfg.render, block_map, frame, T0)

    def tracker(block_map, frame, T0):
        Tracker(tracker_cfg, cfg.render, seed=0).track(block_map, frame, T0)

    times = {(kind, m): [] for kind in ("fixed", "tracker") for m in ("one", "many")}
    maps = {"one": one_map, "many": block_map}
    for kind, track in (("fixed", fixed), ("tracker", tracker)):
        time_pass(track, one_map, timed, starts)  # warm-up (kernels, allocator)
        for _ in range(args.repeats):
            for m in ("one", "many"):
                times[kind, m].append(time_pass(track, maps[m], timed, starts))
    med = {key: float(np.median(v)) for key, v in times.items()}
    one_ms, many_ms = med["fixed", "one"], med["fixed", "many"]
    one_view = frustum_blocks(cfg.render, one_map, timed, starts)
    many_view = frustum_blocks(cfg.render, block_map, timed, starts)

    figures = {
        "track_ms_one_block": round(one_ms, 1),
        "track_ms_many_blocks": round(many_ms, 1),
        "ratio": round(many_ms / one_ms, 3),
        "ratio_per_pass": [round(b / a, 3) for a, b in zip(times["fixed", "one"], times["fixed", "many"])],
        "tracker_ms_one_block": round(med["tracker", "one"], 1),
        "tracker_ms_many_blocks": round(med["tracker", "many"], 1),
        "tracker_ratio": round(med["tracker", "many"] / med["tracker", "one"], 3),
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
    print(
        f"tracking per frame, every step taken: {one_ms:.1f} ms with {n_start} block(s), {many_ms:.1f} ms with "
        f"{len(block_map)} blocks (x{many_ms / one_ms:.3f}); the tracker as it runs: "
        f"x{figures['tracker_ratio']:.3f}; blocks in the timed frusta: {one_view} -> {many_view}"
    )
    report(figures, args.json, "scaling")


if __name__ == "__main__":
    main()
