"""Soak: a bag looped through the one-process ``slam`` node for thousands of frames; memory and time.

The ``slam`` node and ``bag_replay`` run in this process (as ``ros2 run neb_slam_ros slam`` with a ``bag``
runs them), in lockstep: every frame is processed, in order, by the node's default engine, the live one
(tracking in the node's worker thread, mapping and loop closure in their own process beside it;
``--deterministic``: the deterministic engine, mapping and loop closure between frames). The replay loops
the bag, every second pass backwards (``loop_reverse``), stamped forward in time, so the camera moves
continuously through the same scene for as long as asked. Every ``--every`` frames, between two frames,
the benchmark records the resident memory (RSS) of this process and of the mapping process, the bytes
of each of the engine's stores (:meth:`~neb_slam_core.live.LiveSlam.memory`, plus the node's per-frame
log), the mapping lag and the engine's time of the frames since the last sample.

Top-level figures of the JSON:

- ``rss_mb_per_keyframe``: the slope of RSS over keyframes, fitted over the samples after the first
  ``--window`` frames (the start-up's allocations left out);
- ``store_kb_per_keyframe``: the same slope per store, and ``stores_kb_per_keyframe`` their sum;
- ``time_ratio_last_vs_early``: the median engine time per frame of the last ``--window`` frames over
  that of frames ``window .. 2 * window``;
- ``ate_cm`` over all frames (the bag's ground truth, stamped like the frames), ``tracking_failures``.

It writes a plot (RSS and stores over keyframes, time per frame over frames) beside the results JSON.

Examples::

    .venv/bin/python benchmarks/soak.py --frames 10000
    .venv/bin/python benchmarks/soak.py --bag bags/demo_scene_bag --config ci --frames 300 --window 100
"""

from __future__ import annotations

import argparse
import json
import os
import random
import sys
import time
from pathlib import Path

import numpy as np
from common import REPO, record
from live import default_bag


def rss_mb(pid: int | str = "self") -> float:
    """A process's resident memory (Linux ``/proc/<pid>/statm``), MB; 0 when it is gone."""
    try:
        pages = int(Path(f"/proc/{pid}/statm").read_text().split()[1])
    except (OSError, ValueError, IndexError):
        return 0.0
    return pages * os.sysconf("SC_PAGE_SIZE") / 1e6


class Sampler:
    """The node's frame hook: a sample every ``every`` frames, and the stop after ``frames``."""

    def __init__(self, frames: int, every: int, progress: bool):
        self.frames, self.every = frames, every
        self.node = None
        self.samples: list[dict] = []
        self.frame_ms: list[float] = []
        self._bar = None
        if progress:
            from tqdm import tqdm

            self._bar = tqdm(total=frames, desc="soak", unit="frame")

    def __call__(self, result) -> None:
        from neb_slam_core.memory import deep_bytes
        from neb_slam_ros._node_main import request_stop

        if len(self.frame_ms) >= self.frames:
            # frames the node still takes while the stop takes effect (the replay goes on meanwhile, a
            # frame per pose) are not part of the soak
            request_stop()
            return
        self.frame_ms.append(float(result.timings.total_ms))
        slam = self.node.slam
        n = slam.n_frames
        if self._bar is not None:
            self._bar.update(1)
        if n % self.every == 0 or n == self.frames:
            stores = slam.memory()
            stores["run_log"] = deep_bytes(self.node.run_log)
            recent = self.frame_ms[-self.every :]
            mapping_pid = getattr(slam, "mapping_pid", None)
            own, mapping = rss_mb(), 0.0 if mapping_pid is None else rss_mb(mapping_pid)
            self.samples.append(
                {
                    "frames": n,
                    "keyframes": len(slam.frontend.keyframe_poses),
                    "blocks": len(slam.block_map),
                    "mapping_lag": getattr(getattr(slam, "stats", None), "mapping_lag", 0),
                    "rss_mb": round(own + mapping, 2),
                    "rss_mb_mapping": round(mapping, 2),
                    "stores_mb": {k: round(v / 1e6, 4) for k, v in stores.items()},
                    "median_frame_ms": round(float(np.median(recent)), 2),
                }
            )
            if self._bar is not None:
                self._bar.set_postfix(kf=self.samples[-1]["keyframes"], rss_mb=f"{self.samples[-1]['rss_mb']:.0f}")
        if n >= self.frames:
            request_stop()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()


def slope(x: list[float], y: list[float]) -> float | None:
    """Least-squares slope of ``y`` over ``x`` (None with fewer than two distinct ``x``)."""
    if len(set(x)) < 2:
        return None
    return float(np.polyfit(np.asarray(x, float), np.asarray(y, float), 1)[0])


def figures(sampler: Sampler, window: int) -> dict:
    """The top-level figures of the module docstring from the samples and per-frame times."""
    late = [s for s in sampler.samples if s["frames"] >= window]
    kf = [s["keyframes"] for s in late]
    out: dict = {"rss_mb_per_keyframe": slope(kf, [s["rss_mb"] for s in late])}
    per_store = {}
    for name in sampler.samples[-1]["stores_mb"] if sampler.samples else ():
        k = slope(kf, [s["stores_mb"][name] for s in late])
        per_store[name] = None if k is None else round(1e3 * k, 2)
    out["store_kb_per_keyframe"] = per_store
    known = [v for v in per_store.values() if v is not None]
    out["stores_kb_per_keyframe"] = round(sum(known), 2) if known else None
    ms = np.asarray(sampler.frame_ms)
    if len(ms) >= 3 * window:
        out["time_ratio_last_vs_early"] = round(float(np.median(ms[-window:]) / np.median(ms[window : 2 * window])), 3)
    else:
        out["time_ratio_last_vs_early"] = None
    if out["rss_mb_per_keyframe"] is not None:
        out["rss_mb_per_keyframe"] = round(out["rss_mb_per_keyframe"], 4)
    return out


def plot(samples: list[dict], frame_ms: list[float], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4.5))
    kf = [s["keyframes"] for s in samples]
    a.plot(kf, [s["rss_mb"] - samples[0]["rss_mb"] for s in samples], "k-", lw=2, label="RSS (from the first sample)")
    for name in samples[0]["stores_mb"]:
        a.plot(kf, [s["stores_mb"][name] for s in samples], label=name)
    a.set_xlabel("keyframes")
    a.set_ylabel("MB")
    a.legend(fontsize=8)
    a.grid(alpha=0.3)
    ms = np.asarray(frame_ms)
    b.plot(np.arange(1, len(ms) + 1), ms, ".", ms=1, alpha=0.3, color="0.5", label="per frame")
    w = max(1, min(100, len(ms) // 10))
    if len(ms) >= w:
        rolling = np.array([np.median(ms[i : i + w]) for i in range(0, len(ms) - w + 1, w)])
        b.plot(np.arange(w, len(ms) + 1, w), rolling, "b-", lw=2, label=f"median of {w}")
    b.set_yscale("log")
    b.set_xlabel("frames")
    b.set_ylabel("engine time per frame (ms)")
    b.legend(fontsize=8)
    b.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--bag", type=Path, help="bag to loop (default: the shared TUM fr1_xyz frames)")
    p.add_argument("--config", default="live", help="engine configuration (default: live)")
    p.add_argument("--frames", type=int, default=10000, help="frames to process")
    p.add_argument("--every", type=int, default=100, help="sample every this many frames")
    p.add_argument("--window", type=int, default=1000, help="frames left out at the start; the time windows")
    p.add_argument("--out", type=Path, help="the run directory (default: runs/soak-<date>-<time>)")
    p.add_argument("--json", type=Path, help="a copy of the stamped figures")
    p.add_argument("--results-dir", type=Path, help="where the dated JSON and plot go (default benchmarks/results)")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="config overrides (as neb-slam run)")
    p.add_argument("--deterministic", action="store_true", help="the deterministic engine (live:=false)")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args()
    if args.frames < 1 or args.every < 1 or args.window < 1:
        p.error("--frames, --every and --window must be positive")
    bag = (args.bag or default_bag()).resolve()
    out = args.out or REPO / "runs" / time.strftime("soak-%Y%m%d-%H%M%S")
    load = os.getloadavg()[0]
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.SystemRandom().randint(1, 200)))
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

    from neb_slam_ros._node_main import run_nodes
    from neb_slam_ros.bag_replay import BagReplayNode
    from neb_slam_ros.slam import SlamNode

    params = {
        "config": args.config,
        "bag": str(bag),
        "lockstep": True,
        "loop": True,
        "loop_reverse": True,
        "rate": 0.0,
        "reliable_inputs": True,
        "ground_truth_topic": "ground_truth/pose",
        "output_dir": str(out),
        "mesh_period_s": 0.0,
        "live": not args.deterministic,
        "checkpoint_every": 0,
        **dict(o.split("=", 1) for o in args.set),
    }
    ros_args = ["--ros-args"]
    for name, value in params.items():
        ros_args += ["-p", f"{name}:={str(value).lower() if isinstance(value, bool) else value}"]
    sampler = Sampler(args.frames, args.every, not args.no_progress)

    def make_slam():
        sampler.node = SlamNode()
        sampler.node.frame_hooks.append(sampler)
        return sampler.node

    t0 = time.perf_counter()
    code = run_nodes([make_slam, BagReplayNode], ros_args, multi_threaded=False)
    wall_s = time.perf_counter() - t0
    sampler.close()
    if code != 0 or not sampler.samples:
        print(f"soak: the node ended with status {code} after {len(sampler.frame_ms)} frames", file=sys.stderr)
        return 1
    metrics = json.loads((out / "metrics.json").read_text()) if (out / "metrics.json").is_file() else {}
    result = {
        "bag": str(bag),
        "config": args.config,
        "engine": "deterministic" if args.deterministic else "live",
        "overrides": args.set,
        "frames": len(sampler.frame_ms),
        "keyframes": sampler.samples[-1]["keyframes"],
        "window": args.window,
        **figures(sampler, args.window),
        "ate_cm": metrics.get("ate_rmse_cm"),
        "tracking_failures": metrics.get("n_tracking_failures"),
        "loops_applied": metrics.get("n_loops_applied"),
        "mapping_lag_max": max(s["mapping_lag"] for s in sampler.samples),
        "wall_s": round(wall_s, 1),
        "load_before": round(load, 2),
        "load_after": round(os.getloadavg()[0], 2),
        "trajectory": str(out / "trajectory.txt"),
        "samples": sampler.samples,
        "frame_ms": [round(v, 1) for v in sampler.frame_ms],
    }
    path = record("soak", result, args.json, args.results_dir, first_frame_s=sampler.frame_ms[0] / 1e3)
    png = path.with_suffix(".png")
    plot(sampler.samples, sampler.frame_ms, png, f"soak: {bag.name}, config {args.config}, {result['frames']} frames")
    for key in ("frames", "keyframes", "rss_mb_per_keyframe", "stores_kb_per_keyframe", "time_ratio_last_vs_early"):
        print(f"{key:28s} {result[key]}")
    print(f"{'store_kb_per_keyframe':28s} {result['store_kb_per_keyframe']}")
    print(
        f"{'ate_cm':28s} {result['ate_cm']}  (failures {result['tracking_failures']}, loops {result['loops_applied']})"
    )
    print(f"plot: {png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
