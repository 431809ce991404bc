"""What the registration edges do for the loop's pose graph, offline on a run without loop closure.

Takes a run directory of ``neb-slam run ... --set loop.enabled=false`` (its ``map.pt`` holds the final
keyframe poses and their frame indices, ``trajectory.txt`` and ``groundtruth.txt`` the rest) and the
dataset it ran on. Every keyframe is registered against the ones before it exactly as the loop closer
does (``LoopCloser.register`` with the run's config and keyframe poses); then, for each ``--ends``
frame (a keyframe), the keyframe is put at its ground-truth pose as a perfect loop fit would, the
correction is spread from keyframe 1 by the pose graph with tracked edges only and with the
registration edges too, and the whole trajectory's ATE is measured (frames move with their
keyframes as the engine moves them: ``slam.corrected_trajectory``). Keys: ``ate_cm_before``,
``ate_cm_keyframes_true`` (every keyframe at its true pose: the error left in the frames between
keyframes, which no keyframe correction removes), per end ``ate_cm_tracked_edges`` and ``ate_cm_with_registrations``,
``n_registrations``, ``registration_error_cm_mean`` against the ground truth's relative poses (and the
tracked relative poses' ``tracked_error_cm_mean`` for comparison), ``register_ms_mean``.

Example (the loop ablation's run without loop closure)::

    .venv/bin/python benchmarks/pose_graph_edges.py runs/loop-ablation-<date-time>/without \\
        .cache/scenes/default-noise --json pose_graph_edges.json
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from common import report

from neb_slam_core.config_io import load_config
from neb_slam_core.datasets import open_dataset
from neb_slam_core.eval.trajectory_metrics import evaluate_ate
from neb_slam_core.geometry.rectify import Rectifier
from neb_slam_core.geometry.se3 import invert
from neb_slam_core.io.trajectory import read_tum_trajectory
from neb_slam_core.loop.closer import LoopCloser
from neb_slam_core.loop.correction import correction_size, propagate_correction
from neb_slam_core.scene.persistence import load_map
from neb_slam_core.slam import corrected_trajectory


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", type=Path, help="run directory of a run without loop closure")
    p.add_argument("dataset", type=Path, help="the dataset that run processed")
    p.add_argument("--ends", type=int, nargs="+", default=[270, 285, 295], help="keyframes' frame indices")
    p.add_argument("--json", type=Path, default=None, help="a copy of the stamped figures (see benchmarks/results/)")
    args = p.parse_args()
    cfg = load_config(args.run / "config.yaml")
    est = read_tum_trajectory(args.run / "trajectory.txt")
    gt = read_tum_trajectory(args.run / "groundtruth.txt")
    _, extra = load_map(args.run / "map.pt")
    poses = extra["keyframe_poses"].numpy().astype(np.float64)
    frame_of = np.asarray(extra["keyframe_frame_indices"])
    keyframe_stamps = est.stamps_ns[frame_of]

    def ate_cm(keyframe_poses: np.ndarray) -> float:
        """The run's trajectory with its keyframes moved to ``keyframe_poses``, as the engine moves it."""
        moved = corrected_trajectory(est.stamps_ns, est.poses, keyframe_stamps, keyframe_poses)
        return round(evaluate_ate(moved, gt).rmse_cm, 3)

    closer = LoopCloser(cfg.loop, seed=cfg.seed + 4)
    rectify = Rectifier()
    ds = open_dataset(args.dataset)
    times = []
    for k, f in enumerate(frame_of):
        frame = rectify(ds[int(f)])
        closer.add_keyframe(k, frame)
        t0 = time.perf_counter()
        closer.register(k, poses, frame)
        times.append(time.perf_counter() - t0)
    truth = np.stack([gt.poses[int(f)] for f in frame_of])
    reg_err = [correction_size(Z, invert(truth[i]) @ truth[j])[0] for (i, j), Z in closer.registrations.items()]
    trk_err = [
        correction_size(invert(poses[i]) @ poses[j], invert(truth[i]) @ truth[j])[0] for (i, j) in closer.registrations
    ]

    figures: dict = {
        "run": str(args.run),
        "ate_cm_before": ate_cm(poses),
        "ate_cm_keyframes_true": ate_cm(truth),
        "n_keyframes": len(poses),
        "n_registrations": len(closer.registrations),
        "registration_error_cm_mean": round(float(np.mean(reg_err)), 3),
        "tracked_error_cm_mean": round(float(np.mean(trk_err)), 3),
        "register_ms_mean": round(1e3 * float(np.mean(times[1:])), 1),
        "ends": {},
    }
    for end_frame in args.ends:
        hits = np.flatnonzero(frame_of == end_frame)
        if len(hits) == 0:
            raise SystemExit(f"frame {end_frame} is not a keyframe of {args.run} (keyframes: {frame_of.tolist()})")
        end = int(hits[0])
        figures["ends"][str(end_frame)] = {
            "ate_cm_tracked_edges": ate_cm(propagate_correction(poses, 1, end, truth[end])),
            "ate_cm_with_registrations": ate_cm(propagate_correction(poses, 1, end, truth[end], closer.registrations)),
        }
    report(figures, args.json, "pose_graph_edges")


if __name__ == "__main__":
    main()
