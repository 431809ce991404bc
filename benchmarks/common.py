"""Pieces shared by the benchmark scripts (run as scripts: this folder is on ``sys.path``).

Every script ends with :func:`record`: its figures, stamped with the commit, the date and what the
machine was doing, go to ``benchmarks/results/<benchmark>-<YYYYmmdd-HHMMSS>.json`` (and to ``--json FILE``
when given); ``benchmarks/report.py`` renders ``docs/benchmarks.md`` from that folder.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

REPO = Path(__file__).resolve().parents[1]
# the ROS package is built by colcon, not installed into the venv: the scripts import it from the source
# tree, as the tests and the node processes they start do
sys.path.insert(0, str(REPO / "src" / "neb_slam_ros"))
TUM = Path(os.environ.get("NEB_SLAM_SHARED_DATA", REPO.parent / "shared" / "data")) / "tum_fr1_xyz_300"
#: where every benchmark run leaves its stamped figures
RESULTS = REPO / "benchmarks" / "results"
#: the key of the stamp that :func:`record` adds to a benchmark's figures
STAMP_KEY = "stamp"


def predicted_start(T_world_cam: np.ndarray) -> np.ndarray:
    """A pose 1 cm and 0.5 degree off ``T_world_cam``, as a constant-velocity prediction would be."""
    T = np.array(T_world_cam, dtype=np.float64)
    T[:3, :3] = Rotation.from_rotvec(np.radians(0.5) * np.array([0.6, 0.0, 0.8])).as_matrix() @ T[:3, :3]
    T[:3, 3] += np.array([0.006, -0.006, 0.0057])
    return T


def median_ms(fn, repeats: int) -> float:
    """Median wall time of ``repeats`` calls of ``fn()``, in milliseconds."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(1e3 * (time.perf_counter() - t0))
    return float(np.median(times))


def load_figures() -> dict:
    """The torch thread count and the 1-minute load average: what a timing was measured under."""
    import torch

    return {"threads": torch.get_num_threads(), "load_average": round(os.getloadavg()[0], 2)}


def report(figures: dict, json_path: Path | None, benchmark: str | None = None) -> None:
    """Print the figures as JSON; with ``benchmark``, :func:`record` them (results folder and ``json_path``),
    else write them to ``json_path`` when given."""
    text = json.dumps(figures, indent=2)
    print(text)
    if benchmark:
        record(benchmark, figures, json_path)
    elif json_path:
        Path(json_path).write_text(text + "\n")


def commit_id(repo: Path = REPO) -> str:
    """``git rev-parse --short HEAD``, with ``-dirty`` when tracked files differ from it (untracked files,
    such as new result files, do not count); ``unknown`` outside a git checkout."""

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", *args], cwd=repo, capture_output=True, text=True, timeout=30)
        except (OSError, subprocess.SubprocessError):
            return None
        return done.stdout.strip() if done.returncode == 0 else None

    head = git("rev-parse", "--short", "HEAD")
    if not head:
        return "unknown"
    changes = git("status", "--porcelain", "--untracked-files=no")
    return head + ("-dirty" if changes else "")


def stamp(benchmark: str, figures: dict, first_frame_s: float | None = None, now: datetime | None = None) -> dict:
    """What a result was measured at and under: ``benchmark``, ``commit`` (:func:`commit_id`), ``date_utc``
    (ISO 8601, seconds), ``load_average`` (the machine's 1, 5 and 15 minute load averages at the end of the
    run), ``cpus``, ``argv`` (the script's arguments) and, when the benchmark has one (an argument, else
    ``figures["first_frame_s"]``), ``first_frame_s``: the same work in every run, so it tells the machine's
    speed at the time."""
    now = now or datetime.now(UTC)
    out = {
        "benchmark": benchmark,
        "commit": commit_id(),
        "date_utc": now.astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "load_average": [round(v, 2) for v in os.getloadavg()],
        "cpus": os.cpu_count(),
        "argv": sys.argv[1:],
    }
    if first_frame_s is None:
        first_frame_s = figures.get("first_frame_s")
    if first_frame_s is not None:
        out["first_frame_s"] = first_frame_s
    return out


def repo_relative(value):
    """``value`` (figures: dicts, lists, strings) with every absolute path inside the repository written
    relative to it: a recorded result names no folder of the machine it ran on."""
    if isinstance(value, dict):
        return {k: repo_relative(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [repo_relative(v) for v in value]
    if isinstance(value, str) and value.startswith(str(REPO) + os.sep):
        return str(Path(value).relative_to(REPO))
    return value


def add_variant_and_output_arguments(p, what: str = "config") -> None:
    """``--variant LABEL KEY=VALUE ...`` (repeatable: a label and its ``what`` overrides), ``--json`` and
    ``--results-dir``: the arguments of the benchmarks that compare configurations."""
    p.add_argument(
        "--variant",
        nargs="+",
        action="append",
        default=[],
        metavar=("LABEL", "KEY=VALUE"),
        help=f"a label and its {what} overrides (repeatable)",
    )
    p.add_argument("--json", type=Path, default=None, help="a copy of the stamped figures (see benchmarks/results/)")
    p.add_argument(
        "--results-dir", type=Path, default=None, help="where the dated JSON goes (default benchmarks/results)"
    )


def record(
    benchmark: str,
    figures: dict,
    json_path: Path | None = None,
    results_dir: Path | None = None,
    first_frame_s: float | None = None,
    now: datetime | None = None,
) -> Path:
    """Write ``figures`` with a :func:`stamp` (under the key ``stamp``; the figures' own keys unchanged) to
    ``<results_dir>/<benchmark>-<YYYYmmdd-HHMMSS>.json`` (UTC; default folder ``benchmarks/results``) and,
    when given, to ``json_path`` (the same content). Returns the results file's path."""
    now = now or datetime.now(UTC)
    stamped = {**repo_relative(figures), STAMP_KEY: stamp(benchmark, figures, first_frame_s, now)}
    text = json.dumps(stamped, indent=2) + "\n"
    folder = Path(results_dir) if results_dir is not None else RESULTS
    folder.mkdir(parents=True, exist_ok=True)
    base = f"{benchmark}-{now.astimezone(UTC).strftime('%Y%m%d-%H%M%S')}"
    path, k = folder / f"{base}.json", 1
    while path.exists():  # two runs within one second
        k += 1
        path = folder / f"{base}-{k}.json"
    path.write_text(text)
    if json_path:
        Path(json_path).write_text(text)
    shown = path.relative_to(REPO) if path.is_relative_to(REPO) else path
    print(f"results: {shown}", file=sys.stderr)
    return path


def fitted_tum_map(cfg, fit_frames: int, fit_iterations: int, later_frames: int, rng: np.random.Generator):
    """A block map fitted by the engine's own allocation and mapping at the ground-truth poses of TUM
    frames 0, 2, 4, ... (``fit_frames`` of them, each a keyframe; ``fit_iterations`` mapping steps with
    the poses held, :class:`~neb_slam_core.slam.KnownPoseMapping`), and the ``later_frames`` rectified
    frames after them. The fit draws nothing from ``rng`` (the engine's generators are seeded by
    ``cfg.seed``), so the caller's draws after it are its own. Exits with a message when the TUM frames of
    ``../shared/data`` are absent."""
    from neb_slam_core.datasets import open_dataset
    from neb_slam_core.geometry.rectify import Rectifier
    from neb_slam_core.slam import KnownPoseMapping

    if not TUM.is_dir():
        sys.exit(f"{TUM} not found: this benchmark needs the TUM frames of ../shared/data")
    rectify = Rectifier()
    ds = open_dataset(TUM)
    usable = [i for i in range(len(ds)) if ds[i].T_world_cam is not None]
    fit = [rectify(ds[i]) for i in usable[: 2 * fit_frames : 2]]
    later = [rectify(ds[i]) for i in usable[2 * fit_frames : 2 * fit_frames + later_frames]]
    mapping = KnownPoseMapping(cfg)
    for frame in fit:
        mapping.add(frame)
    mapping.optimise(fit_iterations, progress=True)
    return mapping.block_map, later
