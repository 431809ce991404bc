"""How far apart tracked frames may be: the lockstep engine on every ``s``-th frame of a TUM sequence.

A live engine tracks only some of the camera's frames, so the motion between two tracked frames grows
with the time a frame costs. This benchmark runs the deterministic engine (``Slam``) on every
``s``-th frame (``--strides``, default 1 2 4 6 8: 30, 15, 7.5, 5 and 3.75 tracked frames per second of
a 30 Hz camera) with keyframes and mapping by stamp (``keyframes.every_s``, default 0.15 s, so that the
map is refreshed at the same rate of video whatever the stride), loop closure off, and reports per
stride and per ``--variant``:

- ``ate_cm`` over the processed frames, ``tracking_failures``;
- ``iterations_mean`` (Gauss-Newton steps per frame, both stages) and ``capped_share`` (frames that used
  every step of a stage);
- the tracking work per frame, counted and so independent of the machine's load: ``points_per_frame``
  (map queries at sample points) and ``gradient_points_per_frame`` (points whose spatial gradients the
  Gauss-Newton systems took), and ``track_ms_median`` (wall time; read it with the load average).

A variant is a label and ``--set`` overrides, e.g. ``--variant coarse tracking.coarse_rays=256``; the
``paper`` variant (no overrides beyond the above) always runs first.

Example::

    .venv/bin/python benchmarks/tracking_basin.py --frames 150 --variant coarse tracking.coarse_rays=256
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
from common import TUM, add_variant_and_output_arguments, record

from neb_slam_core.config_io import load_config
from neb_slam_core.datasets import open_dataset
from neb_slam_core.eval.trajectory_metrics import evaluate_ate
from neb_slam_core.io.trajectory import Trajectory
from neb_slam_core.slam import Slam


class _TrackingWork:
    """Wraps the engine's tracker: per tracked frame its steps, and the points its map queries and
    spatial gradients saw (the map is shared with mapping, so only calls made while tracking count)."""

    def __init__(self, slam: Slam):
        self.steps: list[int] = []
        self.points = 0
        self.gradient_points = 0
        self._tracking = False
        block_map, tracker = slam.frontend.block_map, slam.frontend.tracker
        query, gradients, track = block_map.query, block_map.spatial_gradients, tracker.track

        def counted_query(points, *args, **kwargs):
            self.points += int(points.shape[0]) if self._tracking else 0
            return query(points, *args, **kwargs)

        def counted_gradients(points, *args, **kwargs):
            self.gradient_points += int(points.shape[0]) if self._tracking else 0
            return gradients(points, *args, **kwargs)

        def counted_track(*args, **kwargs):
            self._tracking = True
            try:
                result = track(*args, **kwargs)
            finally:
                self._tracking = False
            self.steps.append(result.iterations)
            return result

        block_map.query = counted_query
        block_map.spatial_gradients = counted_gradients
        tracker.track = counted_track


def run_stride(frames: list, stride: int, overrides: list[str]) -> dict:
    """The engine on ``frames[::stride]`` with ``overrides`` on ``tum``: the figures of one stride."""
    cfg = load_config("tum", overrides)
    chosen = frames[::stride]
    slam = Slam(cfg, T_world_first=chosen[0].T_world_cam)
    work = _TrackingWork(slam)
    failures, track_ms = 0, []
    for frame in chosen:
        r = slam.process(frame)
        if r.frame_index > 0:
            failures += int(not r.tracking_ok)
            track_ms.append(r.timings.track_ms)
    gt = Trajectory.of_frames(chosen)
    ate = evaluate_ate(slam.trajectory(), gt)
    steps = np.array(work.steps)
    n = max(len(steps), 1)
    return {
        "stride": stride,
        "frames": len(chosen),
        "ate_cm": round(100 * ate.rmse_m, 3),
        "tracking_failures": failures,
        "iterations_mean": round(float(steps.mean()), 2),
        "capped_share": round(float(np.mean(steps >= cfg.tracking.iterations)), 3),
        "points_per_frame": round(work.points / n),
        "gradient_points_per_frame": round(work.gradient_points / n),
        "track_ms_median": round(float(np.median(track_ms)), 1),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=150, help="N frames of the sequence")
    p.add_argument("--start", type=int, default=0, help="from this frame on (the engine starts at its ground truth)")
    p.add_argument("--strides", type=int, nargs="+", default=[1, 2, 4, 6, 8])
    p.add_argument("--every-s", type=float, default=0.15, help="keyframes.every_s of every run")
    p.add_argument("--source", type=Path, default=TUM, help="a TUM sequence folder (default: the shared fr1_xyz)")
    add_variant_and_output_arguments(p)
    args = p.parse_args()
    if not args.source.is_dir():
        raise SystemExit(f"{args.source} not found: give --source, or set NEB_SLAM_SHARED_DATA")
    ds = open_dataset(args.source)
    frames = [ds[i] for i in range(args.start, min(args.start + args.frames, len(ds)))]
    base = ["loop.enabled=false", f"keyframes.every_s={args.every_s}"]
    variants = [["paper"]] + args.variant
    figures: dict = {"source": str(args.source), "start": args.start, "frames": len(frames), "every_s": args.every_s}
    figures["variants"] = {}
    for label, *sets in variants:
        rows = []
        for stride in args.strides:
            load = os.getloadavg()[0]
            t0 = time.perf_counter()
            row = run_stride(frames, stride, base + sets)
            row["load_before"] = round(load, 2)
            row["wall_s"] = round(time.perf_counter() - t0, 1)
            rows.append(row)
            print(f"{label:>10} stride {stride}: " + ", ".join(f"{k} {v}" for k, v in row.items() if k != "stride"))
        figures["variants"][label] = {"overrides": sets, "strides": rows}
    record("tracking_basin", figures, args.json, results_dir=args.results_dir)


if __name__ == "__main__":
    main()
