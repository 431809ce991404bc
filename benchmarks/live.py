"""Live figures: a bag replayed at recorded speed (no lockstep) into the engine, beside its lockstep reference.

Each run replays the bag at ``--rate`` (1.0: as recorded) into

- ``one_process``: the ROS ``slam`` node (live: tracking in its worker thread, mapping and loop closure
  in a child process beside it), through ``neb_slam_ros.suite``;
- ``separate``: the ``tracker``, ``mapper`` and ``loop_closer`` nodes as separate processes over DDS
  (the tracker waits for no map update or loop verdict);
- ``cli_live``: ``neb-slam run --live`` (the same concurrent engine with a simulated real-time clock over
  the bag, no ROS);

and, once per invocation, ``offline``: ``neb-slam run`` on the same bag in the deterministic lockstep
order, with ``--offline-config`` (default ``tum``, the paper's): the reference every live figure stands
beside.

Per entry: ``tracked_fps`` (tracked frames per second of replay), ``ate_cm`` (ATE over the tracked frames
against the bag's ground truth), ``s_per_frame`` (1 / tracked_fps live; the engine's seconds per frame
offline), ``frames_in``, ``frames_tracked``, ``dropped``, ``tracking_failures``, ``mapping_lag_end`` and
``mapping_lag_max`` (keyframes waiting for the mapper), ``lag_trend`` (mean lag over the last third of the
replay minus the first third: near 0 when the lag does not grow), ``loops_applied``, ``first_frame_s``
(the engine's time for the first frame: when its pose is published), ``slowest_over_median`` (slowest
tracked frame's engine time over the median one), ``trajectory`` (its TUM file, to recompute the ATE).
With ``--runs N`` the live entries are the median over N runs (``runs`` holds each). The load average
before each run is recorded: time nothing beside another heavy job.

Default bag: the shared TUM fr1_xyz frames, converted once to ``.cache/bags/fr1_xyz`` (32FC1 depth).

Examples::

    .venv/bin/python benchmarks/live.py --runs 3 --json live.json
    .venv/bin/python benchmarks/live.py --bag bags/demo_scene_bag --config synthetic --offline-config synthetic
    .venv/bin/python benchmarks/live.py --only one_process cli_live --skip-offline
    .venv/bin/python benchmarks/live.py --only one_process --skip-offline --set mapping.iterations=10

Whether applied loops hold up tracking (``slowest_over_median`` on a route that returns to its start): the
noisy ``default`` synthetic scene at a tenth of its speed (its camera moves 1.5-1.8 m/s as recorded)::

    .venv/bin/neb-slam synth .cache/scenes/default-noise --noise
    .venv/bin/neb-slam convert auto .cache/scenes/default-noise .cache/bags/default-noise
    .venv/bin/python benchmarks/live.py --bag .cache/bags/default-noise --rate 0.1 --only one_process \
        --skip-offline --runs 3
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from common import REPO, TUM, record

from neb_slam_core.config_io import load_config
from neb_slam_core.errors import ConfigError

ENTRIES = ("one_process", "separate", "cli_live")


def default_bag() -> Path:
    bag = REPO / ".cache" / "bags" / "fr1_xyz"
    if not bag.exists():
        if not TUM.is_dir():
            sys.exit(f"{TUM} not found: give --bag, or set NEB_SLAM_SHARED_DATA to the folder of tum_fr1_xyz_300")
        bag.parent.mkdir(parents=True, exist_ok=True)
        subprocess.run(
            [sys.executable, "-m", "neb_slam_core.cli.main", "convert", "tum", str(TUM), str(bag), "--depth", "32FC1"],
            check=True,
        )
    return bag


def _timing_figures(run_dir: Path) -> dict:
    """``first_frame_s`` and ``slowest_over_median`` from a run directory's timings.csv."""
    from neb_slam_core.io.run_dir import TIMINGS_FILE, read_timings

    path = run_dir / TIMINGS_FILE
    if not path.is_file():
        return {}
    rows = read_timings(path)
    total = np.array([float(r["total_ms"]) for r in rows])
    if len(total) < 3:
        return {}
    rest = total[1:]  # the first frame starts the map: it is first_frame_s
    return {
        "first_frame_s": round(total[0] / 1e3, 3),
        "slowest_over_median": round(float(rest.max() / np.median(rest)), 3),
        "track_ms_median": round(float(np.median([float(r["track_ms"]) for r in rows[1:]])), 1),
    }


def _lag_trend(history: list[int]) -> float | None:
    if len(history) < 6:
        return None
    third = len(history) // 3
    return round(float(np.mean(history[-third:]) - np.mean(history[:third])), 3)


def figures_of(run_dir: Path, metrics: dict, live: bool) -> dict:
    """The entry's figures from its run directory and metrics."""
    ate = metrics.get("ate_rmse_cm")
    if live:
        fps = metrics.get("tracked_fps")
        if fps is None and metrics.get("replay_s"):
            fps = metrics.get("n_frames", 0) / metrics["replay_s"]
    else:  # frames per second of engine time
        fps = 1.0 / metrics["s_per_frame"] if metrics.get("s_per_frame") else None
    out = {
        "tracked_fps": None if fps is None else round(fps, 3),
        "ate_cm": None if ate is None else round(ate, 3),
        "s_per_frame": round(1.0 / fps, 3) if live and fps else metrics.get("s_per_frame"),
        "frames_in": metrics.get("frames_in", metrics.get("n_frames")),
        "frames_tracked": metrics.get("frames_tracked", metrics.get("n_frames")),
        "dropped": metrics.get("frames_dropped", 0),
        "tracking_failures": metrics.get("n_tracking_failures"),
        "mapping_lag_end": metrics.get("mapping_lag_end"),
        "mapping_lag_max": metrics.get("mapping_lag_max"),
        "lag_trend": _lag_trend(metrics.get("mapping_lag_history", [])),
        "loops_applied": metrics.get("n_loops_applied"),
        # the separate nodes: what the mapper published on map_update, per second of the replay
        "map_update_mb_per_s": metrics.get("map_update_mb_per_s"),
        "trajectory": str(run_dir / "trajectory.txt"),
    }
    out.update(_timing_figures(run_dir))
    return out


def run_cli(bag: Path, out: Path, config: str, live: bool, rate: float, overrides: list[str]) -> dict:
    cmd = [
        sys.executable,
        "-m",
        "neb_slam_core.cli.main",
        "run",
        str(bag),
        "--config",
        config,
        "--out",
        str(out),
        "--no-mesh",
    ]
    if live:
        cmd += ["--live", "--rate", str(rate)]
    if overrides:
        cmd += ["--set", *overrides]
    code = subprocess.run(cmd, stdout=subprocess.DEVNULL).returncode
    if not (out / "metrics.json").is_file():
        sys.exit(f"neb-slam run failed (exit code {code}): {' '.join(cmd)}")
    return figures_of(out, json.loads((out / "metrics.json").read_text()), live)


def run_suite(bag: Path, out: Path, config: str, one_process: bool, rate: float, overrides: list[str]) -> dict:
    from neb_slam_ros.suite import launch

    # the nodes take config values as dotted parameters, their text parsed as YAML as the CLI's --set does
    params = dict(o.split("=", 1) for o in overrides)
    run = launch(bag, out, config, one_process=one_process, live=True, rate=rate, extra_params=params)
    bad = {k: v for k, v in run.exit_codes.items() if v != 0}
    if bad:
        print(f"warning: non-zero exits {bad} (logs in {out / 'logs'})", file=sys.stderr)
    return figures_of(out, run.metrics, live=True)


def median_entry(runs: list[dict]) -> dict:
    """Per figure, the median over runs (numbers) or the first run's value."""
    out = {}
    for key in runs[0]:
        values = [r.get(key) for r in runs]
        numbers = [v for v in values if isinstance(v, (int, float)) and not isinstance(v, bool)]
        out[key] = round(float(np.median(numbers)), 3) if len(numbers) == len(values) else values[0]
    out["runs"] = runs
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--bag", type=Path, help="the bag (default: the shared TUM fr1_xyz frames, converted once)")
    p.add_argument("--config", default="live", help="engine config of the live entries (default live)")
    p.add_argument("--offline-config", default="tum", help="engine config of the offline reference (default tum)")
    p.add_argument("--rate", type=float, default=1.0, help="replay speed (default 1.0: as recorded)")
    p.add_argument("--runs", type=int, default=1, help="live runs per entry; figures are medians (default 1)")
    p.add_argument("--only", nargs="+", choices=ENTRIES, default=list(ENTRIES), help="live entries to run")
    p.add_argument("--skip-offline", action="store_true", help="no offline reference")
    p.add_argument("--out", type=Path, help="folder of the run directories (default runs/live-<date-time>)")
    p.add_argument("--json", type=Path, help="a copy of the stamped figures (see benchmarks/results/)")
    p.add_argument("--results-dir", type=Path, help="where the dated JSON goes (default benchmarks/results)")
    p.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE", help="config overrides of the live entries")
    args = p.parse_args()
    try:  # a bad key or value ends here, before any run, with the config's own message
        load_config(args.config, args.set)
    except ConfigError as exc:
        p.error(str(exc))
    bag = args.bag or default_bag()
    out = args.out or REPO / "runs" / f"live-{time.strftime('%Y%m%d-%H%M%S')}"
    figures: dict = {
        "bag": str(bag),
        "config": args.config,
        "overrides": args.set,
        "rate": args.rate,
        "cpus": os.cpu_count(),
    }
    per_entry: dict[str, list[dict]] = {e: [] for e in args.only}
    for r in range(args.runs):
        for entry in args.only:
            load = round(os.getloadavg()[0], 2)
            run_dir = out / f"{entry}-{r}"
            t0 = time.perf_counter()
            if entry == "cli_live":
                f = run_cli(bag, run_dir, args.config, True, args.rate, args.set)
            else:
                f = run_suite(bag, run_dir, args.config, entry == "one_process", args.rate, args.set)
            f["load_average_before"] = load
            f["wall_s"] = round(time.perf_counter() - t0, 1)
            per_entry[entry].append(f)
            print(f"{entry} run {r}: {json.dumps({k: v for k, v in f.items() if k != 'trajectory'})}", file=sys.stderr)
    for entry, runs in per_entry.items():
        figures[entry] = median_entry(runs)
    if not args.skip_offline:
        load = round(os.getloadavg()[0], 2)
        f = run_cli(bag, out / "offline", args.offline_config, False, args.rate, [])
        f.update(config=args.offline_config, load_average_before=load)
        figures["offline"] = f
    print(
        json.dumps(
            {
                k: ({kk: vv for kk, vv in v.items() if kk != "runs"} if isinstance(v, dict) else v)
                for k, v in figures.items()
            },
            indent=2,
        )
    )
    record("live", figures, args.json, args.results_dir)


if __name__ == "__main__":
    main()
