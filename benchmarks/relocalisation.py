"""Tracking loss and relocalisation on real frames: the TUM frames with a stretch of them removed (a
dropped link) or made black (a covered lens: no depth, black colour), against the same frames
uninterrupted.

Three runs of the deterministic engine (``Slam``, config ``--config`` with ``tracking.relocalise=true``)
over the shared TUM fr1_xyz frames (``--source`` for another TUM folder):

- ``uninterrupted``: every frame;
- ``gap``: frames ``--gap A B`` (default 121 180, two seconds at 30 Hz) left out;
- ``black``: the same frames replaced by black frames at their own stamps.

``--frames N`` takes the first N frames of the sequence and ``--stride s`` every s-th of them (the gap
still names frames of the sequence). Per interrupted run: ``recovered_after`` (frames fed after the view
returns until one tracks again; 0: the first returning frame tracks), ``tracking_failures`` (the
black frames among them), ``changes_while_lost`` (keyframes, map steps and new blocks from frames that
failed: none expected), ``failures_after_recovery``, and ``ate_cm_after`` against
``ate_cm_after_uninterrupted``: the ATE RMSE over the frames after recovery, each run aligned to the
ground truth over its own tracked frames (the uninterrupted run over all of them) and the errors taken
at the same frames, so that a relocalised pose off by a constant offset counts against it. ``ratio`` is
the one over the other.

Example::

    .venv/bin/python benchmarks/relocalisation.py
    .venv/bin/python benchmarks/relocalisation.py --config live --gap 100 160
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from pathlib import Path

import numpy as np
from common import TUM, record
from tqdm import tqdm

from neb_slam_core.config_io import load_config
from neb_slam_core.datasets import open_dataset
from neb_slam_core.eval.trajectory_metrics import evaluate_ate
from neb_slam_core.io.trajectory import Trajectory
from neb_slam_core.slam import Slam
from neb_slam_core.types import RgbdFrame


def blacked(frame: RgbdFrame) -> RgbdFrame:
    """``frame`` as a covered lens gives it: black colour, no depth, the same stamp."""
    return dataclasses.replace(frame, rgb=np.zeros_like(frame.rgb), depth_m=np.zeros_like(frame.depth_m))


def interrupted(frames: dict[int, RgbdFrame], gap: range, kind: str) -> list[RgbdFrame]:
    """The frames (by their index in the sequence) with those in ``gap`` left out (``kind`` "gap") or
    blacked out ("black")."""
    if kind == "gap":
        return [f for i, f in frames.items() if i not in gap]
    return [blacked(f) if i in gap else f for i, f in frames.items()]


def run(frames: list[RgbdFrame], cfg, label: str, progress: bool) -> tuple[Slam, list, float]:
    """The engine over ``frames``: itself, its results and the first frame's seconds."""
    slam = Slam(cfg, T_world_first=frames[0].T_world_cam)
    t0 = time.perf_counter()
    results = [slam.process(frames[0])]
    first_s = time.perf_counter() - t0
    results += [slam.process(f) for f in tqdm(frames[1:], desc=label, unit="frame", disable=not progress)]
    return slam, results, first_s


def errors_by_stamp(slam: Slam, results: list, gt: Trajectory) -> dict[int, float]:
    """Translation error (m) per stamp of ``slam``'s tracked frames, aligned to ``gt`` over those frames."""
    traj = slam.trajectory()
    tracked = np.array([r.tracking_ok for r in results])
    ate = evaluate_ate(Trajectory(traj.stamps_ns[tracked], traj.poses[tracked]), gt)
    return dict(zip(ate.stamps_ns.tolist(), ate.errors_m.tolist()))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--source", type=Path, default=TUM, help="a TUM sequence folder (default: the shared fr1_xyz)")
    p.add_argument("--config", default="tum")
    p.add_argument("--gap", type=int, nargs=2, default=[121, 180], metavar=("A", "B"), help="frames A..B (inclusive)")
    p.add_argument("--frames", type=int, default=None, help="the first N frames only")
    p.add_argument("--stride", type=int, default=1, help="every s-th frame of those (the gap in sequence frames)")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="more config overrides")
    p.add_argument("--json", type=Path, default=None, help="a copy of the stamped figures")
    p.add_argument("--results-dir", type=Path, default=None)
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args()
    if not args.source.is_dir():
        raise SystemExit(f"{args.source} not found: give --source, or set NEB_SLAM_SHARED_DATA")
    ds = open_dataset(args.source)
    n = len(ds) if args.frames is None else min(args.frames, len(ds))
    by_index = {i: ds[i] for i in range(0, n, args.stride)}
    frames = list(by_index.values())
    gap = range(args.gap[0], args.gap[1] + 1)
    if not any(i > gap[-1] for i in by_index):
        raise SystemExit(f"--gap {args.gap[0]} {args.gap[1]} leaves no frame after it in the first {n} frames")
    cfg = load_config(args.config, ["tracking.relocalise=true", *args.set])
    gt = Trajectory.of_frames(frames)
    progress = not args.no_progress
    load_before = os.getloadavg()[0]
    t0 = time.perf_counter()
    ref_slam, ref_results, first_s = run(frames, cfg, "uninterrupted", progress)
    ref_errors = errors_by_stamp(ref_slam, ref_results, gt)
    figures: dict = {
        "source": str(args.source),
        "config": args.config,
        "overrides": args.set,
        "frames": len(frames),
        "stride": args.stride,
        "gap": list(args.gap),
        "uninterrupted": {
            "ate_cm": round(100 * evaluate_ate(ref_slam.trajectory(), gt).rmse_m, 3),
            "tracking_failures": sum(not r.tracking_ok for r in ref_results[1:]),
        },
    }
    before = sum(i < gap.start for i in by_index)  # frames fed before the gap
    for kind in ("gap", "black"):
        fed = interrupted(by_index, gap, kind)
        slam, results, _ = run(fed, cfg, kind, progress)
        back = before + (sum(i in gap for i in by_index) if kind == "black" else 0)  # where the view returns
        after = results[back:]
        recovered = next((k for k, r in enumerate(after) if r.tracking_ok), None)
        row: dict = {
            "frames": len(fed),
            "tracking_failures": sum(not r.tracking_ok for r in results[1:]),
            "failures_before_gap": sum(not r.tracking_ok for r in results[1:before]),
            "changes_while_lost": sum(
                bool(r.is_keyframe or r.mapped or r.new_block_id is not None) for r in results if not r.tracking_ok
            ),
            "recovered_after": recovered,
        }
        if recovered is not None:
            errors = errors_by_stamp(slam, results, gt)
            later = [f.stamp_ns for f, r in zip(fed[back + recovered :], after[recovered:]) if r.tracking_ok]
            common = [t for t in later if t in errors and t in ref_errors]
            mine = np.array([errors[t] for t in common])
            ref = np.array([ref_errors[t] for t in common])
            row.update(
                failures_after_recovery=sum(not r.tracking_ok for r in after[recovered:]),
                ate_cm_after=round(100 * float(np.sqrt(np.mean(mine**2))), 3),
                ate_cm_after_uninterrupted=round(100 * float(np.sqrt(np.mean(ref**2))), 3),
            )
            row["ratio"] = round(row["ate_cm_after"] / row["ate_cm_after_uninterrupted"], 3)
        figures[kind] = row
        print(f"{kind}: " + ", ".join(f"{k} {v}" for k, v in row.items()))
    figures["wall_s"] = round(time.perf_counter() - t0, 1)
    figures["load_before"] = round(load_before, 2)
    figures["load_after"] = round(os.getloadavg()[0], 2)
    print(f"uninterrupted: {figures['uninterrupted']}")
    record("relocalisation", figures, args.json, args.results_dir, first_frame_s=first_s)


if __name__ == "__main__":
    main()
