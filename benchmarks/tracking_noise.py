"""How much a frame's tracked pose depends on the pixels drawn, and how far it lies from the ground truth.

The engine (config ``tum``, loop closure off) runs on the first ``--frames`` frames of a TUM sequence. At
every ``--every``-th frame, before the engine processes it, the frame is tracked from the engine's own
prediction on the engine's map at that moment, ``--seeds`` times per ``--variant`` (a tracker with a
different seed draws other pixels and sample depths each time). All variants see the same map and the
same starts, so they differ only in how a pose is found. Per variant:

- ``spread_mm`` / ``spread_deg``: the RMS, over the frames, of how far the seeds' poses lie from their
  mean (position in mm, rotation in degrees): the noise a frame's pose gets from its pixels;
- ``error_mm`` / ``error_deg``: the RMS over frames and seeds of the distance to the ground-truth pose
  (the engine starts at the first frame's ground truth, so both share a frame). It includes the map's
  own error at that moment, which all variants share;
- ``error_of_mean_mm``: the same for the seeds' mean pose: what is left when the draws are averaged;
- ``track_ms_median``: wall time per tracking (read it with the load average).

A variant is a label and ``--set`` overrides of ``tracking.*``, e.g. ``--variant rays2048 tracking.n_rays=2048``;
``paper`` (no overrides) always runs first. ``--source`` takes any TUM sequence folder (default: the
shared fr1_xyz frames; ``desk`` names fr1_desk in ``.cache/datasets/``).

Example::

    .venv/bin/python benchmarks/tracking_noise.py --source desk --frames 200 --variant rays2048 tracking.n_rays=2048
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
from common import REPO, TUM, add_variant_and_output_arguments, record
from scipy.spatial.transform import Rotation

from neb_slam_core.config_io import load_config
from neb_slam_core.datasets import open_dataset
from neb_slam_core.slam import Slam
from neb_slam_core.tracking.tracker import Tracker

DESK = REPO / ".cache" / "datasets" / "rgbd_dataset_freiburg1_desk"


def mean_pose(poses: list[np.ndarray]) -> tuple[np.ndarray, Rotation]:
    """The mean position and the chordal mean rotation of ``poses`` (4x4)."""
    t = np.mean([T[:3, 3] for T in poses], axis=0)
    return t, Rotation.from_matrix(np.stack([T[:3, :3] for T in poses])).mean()


def deviations(poses: list[np.ndarray], t_ref: np.ndarray, r_ref: Rotation) -> tuple[np.ndarray, np.ndarray]:
    """Each pose's distance (m) and rotation angle (degrees) from ``(t_ref, r_ref)``."""
    dt = np.array([np.linalg.norm(T[:3, 3] - t_ref) for T in poses])
    rots = Rotation.from_matrix(np.stack([T[:3, :3] for T in poses]))
    dr = np.degrees((rots * r_ref.inv()).magnitude())
    return dt, dr


def rms(values) -> float:
    a = np.asarray(values, dtype=float)
    return float(np.sqrt(np.mean(a * a))) if a.size else float("nan")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--source", default=str(TUM), help="a TUM sequence folder, or 'desk' (default: the shared fr1_xyz)")
    p.add_argument("--frames", type=int, default=200, help="the first N frames of the sequence")
    p.add_argument("--every", type=int, default=10, help="measure every N-th frame")
    p.add_argument("--seeds", type=int, default=6, help="trackings per frame and variant")
    add_variant_and_output_arguments(p, "tracking.*")
    args = p.parse_args()
    source = DESK if args.source == "desk" else Path(args.source)
    if not source.is_dir():
        raise SystemExit(f"{source} not found: give --source (a TUM folder), or set NEB_SLAM_SHARED_DATA")
    ds = open_dataset(source)
    n = min(args.frames, len(ds))
    cfg = load_config("tum", ["loop.enabled=false"])
    variants = [["paper"]] + args.variant
    trackers = {}
    for label, *sets in variants:
        tracking = load_config("tum", sets).tracking
        trackers[label] = [Tracker(tracking, cfg.render, seed=1000 + s) for s in range(args.seeds)]
    per = {label: {"dt": [], "dr": [], "et": [], "er": [], "emt": [], "ms": []} for label in trackers}
    load_before = os.getloadavg()[0]
    frame0 = ds[0]
    slam = Slam(cfg, T_world_first=frame0.T_world_cam)
    t_start = time.perf_counter()
    for i in range(n):
        frame = frame0 if i == 0 else ds[i]
        if i > 0 and i % args.every == 0 and frame.T_world_cam is not None:
            rectified = slam.frontend._rectify(frame)
            T_pred = slam.frontend.predict(frame.stamp_ns)
            gt = frame.T_world_cam
            r_gt = Rotation.from_matrix(gt[:3, :3])
            for label, seeds in trackers.items():
                poses = []
                for tracker in seeds:
                    t0 = time.perf_counter()
                    poses.append(tracker.track(slam.frontend.block_map, rectified, T_pred).T_world_cam)
                    per[label]["ms"].append(1e3 * (time.perf_counter() - t0))
                t_mean, r_mean = mean_pose(poses)
                dt, dr = deviations(poses, t_mean, r_mean)
                et, er = deviations(poses, gt[:3, 3], r_gt)
                per[label]["dt"].append(rms(dt))
                per[label]["dr"].append(rms(dr))
                per[label]["et"].extend(et)
                per[label]["er"].extend(er)
                per[label]["emt"].append(np.linalg.norm(t_mean - gt[:3, 3]))
            row = ", ".join(f"{k} {1e3 * per[k]['dt'][-1]:.1f}/{1e3 * per[k]['emt'][-1]:.1f} mm" for k in trackers)
            print(f"frame {i}: spread/error of mean {row}", flush=True)
        slam.process(frame)
    figures: dict = {
        "source": str(source),
        "frames": n,
        "every": args.every,
        "seeds": args.seeds,
        "engine_s": round(time.perf_counter() - t_start, 1),
        "load_average_before": round(load_before, 2),
        "variants": {},
    }
    for label, *sets in variants:
        v = per[label]
        figures["variants"][label] = {
            "overrides": sets,
            "spread_mm": round(1e3 * rms(v["dt"]), 2),
            "spread_deg": round(rms(v["dr"]), 3),
            "error_mm": round(1e3 * rms(v["et"]), 2),
            "error_deg": round(rms(v["er"]), 3),
            "error_of_mean_mm": round(1e3 * rms(v["emt"]), 2),
            "track_ms_median": round(float(np.median(v["ms"])), 1),
        }
        row = figures["variants"][label]
        print(f"{label:>12}: " + ", ".join(f"{k} {x}" for k, x in row.items() if k != "overrides"))
    record("tracking_noise", figures, args.json, results_dir=args.results_dir)


if __name__ == "__main__":
    main()
