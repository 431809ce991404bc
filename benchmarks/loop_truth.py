"""Each loop closure against the ground truth: does the fitted pose bring the keyframe closer to it?

The engine (``--config``, default ``tum``) runs on a TUM sequence (default: fr1_desk in
``.cache/datasets/``) from the first frame's ground-truth pose, so its poses and the ground truth share
one frame without alignment. At every loop event whose correction was fitted, the current keyframe's
ground-truth pose is compared with its tracked pose (before the correction) and with the loop fit's pose:

- ``tracked_cm`` / ``tracked_deg`` and ``fitted_cm`` / ``fitted_deg``: their distances to the truth;
- ``gain_cm``: ``tracked_cm - fitted_cm`` (positive: the loop moves the keyframe towards the truth);
- ``relative_cm`` / ``relative_deg``: how far the fitted pose relative to the loop keyframe is from the
  ground truth's relative pose (the loop measurement's own error, whatever the loop keyframe's drift);
- the fit's RMS (``rms_px``), whether the engine applied it, and why not.

Summary per band of fit RMS (``--bands``, pixels): events, mean ``gain_cm`` and ``relative_cm``. The
engine's loop gate (``loop.max_fit_rms_px``) decides which events are applied; ``--set`` overrides go to
the config (e.g. ``--set loop.max_fit_rms_px=2.0`` applies more of them).

Example::

    .venv/bin/python benchmarks/loop_truth.py --set loop.max_fit_rms_px=2.0
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
from common import REPO, record

from neb_slam_core.config_io import load_config
from neb_slam_core.datasets import open_dataset
from neb_slam_core.eval.trajectory_metrics import evaluate_ate
from neb_slam_core.io.trajectory import Trajectory
from neb_slam_core.loop import closer as closer_module
from neb_slam_core.loop.correction import correction_size
from neb_slam_core.slam import Slam

DESK = REPO / ".cache" / "datasets" / "rgbd_dataset_freiburg1_desk"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--source", type=Path, default=DESK, help="a TUM sequence folder (default: fr1_desk)")
    p.add_argument("--config", default="tum")
    p.add_argument("--set", dest="overrides", nargs="+", default=[], metavar="KEY=VALUE")
    p.add_argument("--frames", type=int, default=None, help="the first N frames (default: all)")
    p.add_argument("--bands", type=float, nargs="+", default=[1.0, 2.0], help="fit RMS band edges (px)")
    p.add_argument("--json", type=Path, default=None, help="a copy of the stamped figures (see benchmarks/results/)")
    p.add_argument(
        "--results-dir", type=Path, default=None, help="where the dated JSON goes (default benchmarks/results)"
    )
    args = p.parse_args()
    if not args.source.is_dir():
        raise SystemExit(f"{args.source} not found: unpack the TUM sequence there, or give --source")
    ds = open_dataset(args.source)
    n = len(ds) if args.frames is None else min(args.frames, len(ds))
    cfg = load_config(args.config, args.overrides)
    first = ds[0]
    slam = Slam(cfg, T_world_first=first.T_world_cam)
    if slam.loop_closer is None:
        raise SystemExit("loop closure is off in this config: nothing to measure")

    # the fit's pose is what the loop closer computes and then judges; the spy keeps the last one
    fitted: dict = {}
    fit = closer_module.fit_loop_pose

    def spy(*a, **k):
        fitted["fit"] = fit(*a, **k)
        return fitted["fit"]

    closer_module.fit_loop_pose = spy
    close = slam.loop_closer.close
    truth: dict[int, np.ndarray] = {}
    events = []

    def audited_close(keyframe_id, poses, frame):
        fitted.clear()
        event, corrected = close(keyframe_id, poses, frame)
        kfs = slam.keyframes.keyframes
        T_true = truth.get(kfs[keyframe_id].frame_index)
        loop_true = truth.get(kfs[event.loop_ids[0]].frame_index) if event is not None else None
        if event is not None and "fit" in fitted and T_true is not None and loop_true is not None:
            T_fit = fitted["fit"].T_world_cam
            tracked, fit_err = correction_size(T_true, poses[keyframe_id]), correction_size(T_true, T_fit)
            T_loop = poses[event.loop_ids[0]]
            relative = correction_size(np.linalg.inv(loop_true) @ T_true, np.linalg.inv(T_loop) @ T_fit)
            events.append(
                {
                    "frame": int(kfs[keyframe_id].frame_index),
                    "loop_frames": [int(kfs[i].frame_index) for i in event.loop_ids],
                    "rms_px": round(event.rms_px, 3),
                    "applied": bool(event.applied),
                    "reason": event.reason,
                    "tracked_cm": round(tracked[0], 2),
                    "tracked_deg": round(tracked[1], 2),
                    "fitted_cm": round(fit_err[0], 2),
                    "fitted_deg": round(fit_err[1], 2),
                    "gain_cm": round(tracked[0] - fit_err[0], 2),
                    "relative_cm": round(relative[0], 2),
                    "relative_deg": round(relative[1], 2),
                }
            )
            e = events[-1]
            print(
                f"frame {e['frame']} ({'applied' if e['applied'] else 'not applied'}): fit {e['rms_px']} px, "
                f"keyframe {e['tracked_cm']} -> {e['fitted_cm']} cm from the truth, measurement off by "
                f"{e['relative_cm']} cm / {e['relative_deg']} deg",
                flush=True,
            )
        return event, corrected

    slam.loop_closer.close = audited_close
    load_before = os.getloadavg()[0]
    t0 = time.perf_counter()
    frames = []
    for i in range(n):
        frame = first if i == 0 else ds[i]
        if frame.T_world_cam is not None:
            truth[i] = frame.T_world_cam
        slam.process(frame)
        frames.append(frame)
    ate = evaluate_ate(slam.trajectory(), Trajectory.of_frames(frames))
    edges = [0.0, *args.bands, float("inf")]
    bands = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        inside = [e for e in events if lo < e["rms_px"] <= hi]
        bands.append(
            {
                "rms_px": [lo, hi],
                "events": len(inside),
                "applied": sum(e["applied"] for e in inside),
                "gain_cm_mean": round(float(np.mean([e["gain_cm"] for e in inside])), 2) if inside else None,
                "relative_cm_mean": round(float(np.mean([e["relative_cm"] for e in inside])), 2) if inside else None,
                "relative_deg_mean": round(float(np.mean([e["relative_deg"] for e in inside])), 2) if inside else None,
            }
        )
        print(f"fit RMS ({lo:g}, {hi:g}] px: " + ", ".join(f"{k} {v}" for k, v in bands[-1].items() if k != "rms_px"))
    figures = {
        "source": str(args.source),
        "config": args.config,
        "overrides": args.overrides,
        "frames": n,
        "ate_cm": round(100 * ate.rmse_m, 3),
        "events": events,
        "bands": bands,
        "engine_s": round(time.perf_counter() - t0, 1),
        "load_average_before": round(load_before, 2),
    }
    print(f"ATE {figures['ate_cm']} cm over {n} frames, {sum(e['applied'] for e in events)} loops applied")
    record("loop_truth", figures, args.json, results_dir=args.results_dir)


if __name__ == "__main__":
    main()
