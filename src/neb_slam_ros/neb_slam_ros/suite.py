"""Replay a bag through the node suite and evaluate it: what ``make demo`` and the integration tests run.

``ros2 launch`` is not available as a wheel, so this small launcher starts the nodes as processes (the
installed executables' modules, exactly what ``ros2 run`` starts), replays the bag in lockstep, stops the
suite in order when the bag ends (the loop closer first: it checks its last keyframes; then the mapper:
it finishes its keyframes and loop corrections and writes its files; then the tracker), and turns the mapper's
output folder into a run directory with the layout of ``neb-slam run``:
``trajectory.txt``, ``groundtruth.txt``, ``mesh.ply``, ``map.pt``, ``metrics.json`` and the plots.

    python -m neb_slam_ros.suite bags/demo_scene_bag --config synthetic --out runs/demo
    python -m neb_slam_ros.suite bags/fr1_xyz --config tum --one-process
    python -m neb_slam_ros.suite bags/fr1_xyz --config tum --start 150 --map runs/first_half/map.pt

Separate processes: ``tracker``, ``mapper``, ``loop_closer``, ``bag_replay``. ``--one-process``: the
``slam`` executable with the replay inside.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

STOP_TIMEOUT_S = 600.0


@dataclass
class SuiteRun:
    """One replay: the run directory, its metrics, and each process' exit status and log file.

    ``wall_s``: from the start of the processes to the end of the replay (start-up included);
    ``replay_s``: from the replay's first frame to its end, read from bag_replay's log stamps (the same
    span in both modes, whatever the processes do before and after).
    """

    run_dir: Path
    metrics: dict
    wall_s: float
    replay_s: float = 0.0
    exit_codes: dict[str, int] = field(default_factory=dict)
    logs: dict[str, Path] = field(default_factory=dict)


def _node_cmd(node: str, params: dict[str, object]) -> list[str]:
    cmd = [sys.executable, "-m", f"neb_slam_ros.{node}", "--ros-args"]
    for name, value in params.items():
        text = str(value).lower() if isinstance(value, bool) else str(value)
        cmd += ["-p", f"{name}:={text}"]
    return cmd


def _env() -> dict[str, str]:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    here = str(Path(__file__).resolve().parents[1])  # makes the modules importable without colcon
    env["PYTHONPATH"] = os.pathsep.join(p for p in (here, env.get("PYTHONPATH", "")) if p)
    return env


def launch(
    bag: Path,
    out: Path,
    config: str = "synthetic",
    count: int = 0,
    one_process: bool = False,
    seed: int = 0,
    mesh_period_s: float = 0.0,
    env: dict[str, str] | None = None,
    extra_params: dict[str, object] | None = None,
    start: int = 0,
    map_file: Path | None = None,
    live: bool = False,
    rate: float = 1.0,
    during: Callable[[dict[str, subprocess.Popen], Callable[[str], subprocess.Popen]], None] | None = None,
) -> SuiteRun:
    """Replay ``bag`` (``count`` frames from frame ``start``; 0: all) through the suite into run directory
    ``out``, on an empty map or continuing the checkpoint ``map_file``. By default in lockstep, as fast as
    the engine goes; ``live``: at ``rate`` times the recorded speed without lockstep, the engine taking
    the newest frame whenever it is free (the tracker waits for no map update or loop verdict).
    ``during`` is called once every node runs, with the processes by node name and a function that starts
    a node again (its log goes on): a test kills and restarts nodes with it."""
    out.mkdir(parents=True, exist_ok=True)
    logs_dir = out / "logs"
    logs_dir.mkdir(exist_ok=True)
    env = env or _env()
    engine = {"config": config, "seed": seed, **(extra_params or {})}
    # datasets are recorded with hand-held cameras: the map's up from the first frame's floor
    camera = {"reliable_inputs": True, "ground_truth_topic": "ground_truth/pose", "gravity": "floor"}
    replay = {"bag": str(bag), "lockstep": not live, "rate": rate if live else 0.0, "count": count, "start": start}
    resume = {} if map_file is None else {"map_file": str(map_file)}
    if one_process:
        plan = {
            "slam": {
                **engine,
                **camera,
                **replay,
                **resume,
                "output_dir": str(out),
                "mesh_period_s": mesh_period_s,
                "live": live,
            }
        }
    else:
        sync = {"map_sync": not live, "loop_sync": not live}
        # the mapper writes trajectory.txt from the tracker's latest path: the tracker publishes its path
        # after every frame, so that the latest one holds the last frame
        plan = {
            "mapper": {**engine, **resume, "output_dir": str(out), "mesh_period_s": mesh_period_s},
            "loop_closer": engine,
            "tracker": {**engine, **camera, **sync, "wait_for_map": map_file is not None, "path_period_s": 0.0},
            "bag_replay": replay,
        }
    procs: dict[str, subprocess.Popen] = {}
    run = SuiteRun(out, {}, 0.0)
    t0 = time.perf_counter()

    def start_node(node: str) -> subprocess.Popen:
        again = node in run.logs  # a restart: its log goes on
        run.logs[node] = logs_dir / f"{node}.log"
        return subprocess.Popen(
            _node_cmd(node, plan[node]),
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=run.logs[node].open("a" if again else "w"),
            stderr=subprocess.STDOUT,
        )

    try:
        for node in plan:
            procs[node] = start_node(node)
        if during is not None:
            during(procs, start_node)
        driver = "slam" if one_process else "bag_replay"
        run.exit_codes[driver] = procs[driver].wait()  # the replay ends the process when the bag ends
        run.wall_s = time.perf_counter() - t0
        # the tracker stops with the input (frames still queued count as dropped), the loop closer checks
        # its last keyframes, then the mapper finishes its keyframes and corrections and writes its files
        for node in ("tracker", "loop_closer", "mapper"):
            if node in procs:
                procs[node].send_signal(signal.SIGINT)
                run.exit_codes[node] = procs[node].wait(STOP_TIMEOUT_S)
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
                p.wait()
    run.replay_s = _replay_span_s(run.logs["slam" if one_process else "bag_replay"].read_text())
    if not one_process:
        run.metrics = finish_run_directory(out, bag, config, run.wall_s)
        run.metrics.update(tracker_summary(run.logs["tracker"].read_text()))
        run.metrics.update(mapper_summary(run.logs["mapper"].read_text()))
    else:
        run.metrics = json.loads((out / "metrics.json").read_text()) if (out / "metrics.json").is_file() else {}
    if run.replay_s > 0:
        run.metrics["replay_s"] = run.replay_s
        run.metrics["fps"] = run.metrics["n_frames"] / run.replay_s
        if "map_update_mb" in run.metrics:
            run.metrics["map_update_mb_per_s"] = run.metrics["map_update_mb"] / run.replay_s
        (out / "metrics.json").write_text(json.dumps(run.metrics, indent=2) + "\n")
    return run


_MAPPER_SUMMARY = re.compile(r"mapper stopped: .*, (\d+) map updates \(([\d.]+) MB\)")
_TRACKER_SUMMARY = re.compile(
    r"tracker stopped: (\d+) frames tracked \((\d+) failed\), .* (\d+) dropped, .*; (\d+) frames in, "
    r"mapping lag (\d+) \(max (\d+)\)"
)


def tracker_summary(log_text: str) -> dict:
    """What the tracker's last log line says: frames tracked, failed, in and dropped, the mapping lag at the
    end and its maximum (empty when the line is missing)."""
    found = _TRACKER_SUMMARY.findall(log_text)
    if not found:
        return {}
    tracked, failed, dropped, frames_in, lag, lag_max = map(int, found[-1])
    return {
        "frames_tracked": tracked,
        "n_tracking_failures": failed,
        "frames_in": frames_in,
        "frames_dropped": dropped,
        "mapping_lag_end": lag,
        "mapping_lag_max": lag_max,
    }


def mapper_summary(log_text: str) -> dict:
    """What the mapper's last log line says of its map updates: how many, and their MB (empty when the
    line is missing)."""
    found = _MAPPER_SUMMARY.findall(log_text)
    if not found:
        return {}
    n, mb = found[-1]
    return {"map_updates": int(n), "map_update_mb": float(mb)}


def _replay_span_s(log_text: str) -> float:
    """Seconds between bag_replay's first published frame and its 'finished' line (0 when absent)."""
    stamps = {}
    for line in log_text.splitlines():
        for key in ("publishing frames", "bag_replay finished"):
            if key in line and "[neb_slam.bag_replay]" in line:
                stamps[key] = float(line.split("] [", 2)[1].split("]")[0])
    if len(stamps) < 2:
        return 0.0
    return stamps["bag_replay finished"] - stamps["publishing frames"]


def finish_run_directory(out: Path, bag: Path, config: str, wall_s: float) -> dict:
    """Add ground truth, metrics and plots to the mapper's output folder ``out``."""
    from neb_slam_core.datasets.bag import BagDataset
    from neb_slam_core.errors import DatasetError
    from neb_slam_core.eval.report import trajectory_metrics, write_trajectory_plots
    from neb_slam_core.io.run_dir import GROUNDTRUTH_FILE, METRICS_FILE, TRAJECTORY_FILE, RunDirectory
    from neb_slam_core.io.trajectory import Trajectory, read_tum_trajectory
    from neb_slam_core.scene.persistence import load_map

    run_dir = RunDirectory(out)
    est = read_tum_trajectory(run_dir.file(TRAJECTORY_FILE))
    block_map, extra = load_map(run_dir.file("map.pt"))
    metrics = {
        "status": "complete",
        "n_frames": len(est),
        "n_blocks": len(block_map),
        "param_mb": block_map.param_mb(),
        "n_keyframes": len(extra.get("keyframe_stamps_ns", [])),
        "wall_s": wall_s,
        "fps": len(est) / wall_s if wall_s > 0 else None,
        "config": config,
        "bag": str(bag),
    }
    with BagDataset(bag) as ds:
        gt_all = ds.ground_truth()
        if len(gt_all):
            rows = [np.flatnonzero(gt_all.stamps_ns == s) for s in est.stamps_ns]
            keep = [r[0] for r in rows if len(r)]
            gt = Trajectory(gt_all.stamps_ns[keep], gt_all.poses[keep])
            run_dir.write_trajectory(gt, GROUNDTRUTH_FILE, "ground truth of the processed frames")
            try:
                ate_metrics, ate = trajectory_metrics(
                    est, gt, est_source=run_dir.file(TRAJECTORY_FILE), gt_source=run_dir.file(GROUNDTRUTH_FILE)
                )
                metrics.update(ate_metrics)
                write_trajectory_plots(ate, out)
            except DatasetError as exc:
                metrics["ate_skipped"] = str(exc)
    run_dir.write_metrics(metrics)
    assert run_dir.file(METRICS_FILE).is_file()
    return metrics


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bag", type=Path)
    p.add_argument("--config", default="synthetic", help="engine config preset or YAML file (default synthetic)")
    p.add_argument("--out", type=Path, help="run directory (default runs/suite-<bag>-<date>-<time>)")
    p.add_argument("--count", type=int, default=0, help="frames to replay (0: all)")
    p.add_argument("--start", type=int, default=0, help="first frame of the bag to replay (default 0)")
    p.add_argument("--map", type=Path, help="continue this map checkpoint (a run's map.pt)")
    p.add_argument("--one-process", action="store_true", help="the slam executable instead of separate nodes")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--mesh-period", type=float, default=0.0, help="mesh topic period in s (0: at the end only)")
    args = p.parse_args(argv)
    out = args.out or Path(time.strftime(f"runs/suite-{args.bag.name}-%Y%m%d-%H%M%S"))
    run = launch(
        args.bag,
        out,
        args.config,
        args.count,
        args.one_process,
        args.seed,
        args.mesh_period,
        start=args.start,
        map_file=args.map,
    )
    bad = {k: v for k, v in run.exit_codes.items() if v != 0}
    m = run.metrics
    print(f"  frames / fps       {m.get('n_frames')} / {m.get('fps') or (m.get('n_frames', 0) / run.wall_s):.3f}")
    print(f"  blocks / MB        {m.get('n_blocks')} / {m.get('param_mb', float('nan')):.3f}")
    if "ate_rmse_cm" in m:
        print(f"  ATE RMSE           {m['ate_rmse_cm']:.3f} cm")
    print(f"  process logs       {out / 'logs'}")
    if bad:
        print(f"  non-zero exits     {bad}", file=sys.stderr)
    print(out)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
