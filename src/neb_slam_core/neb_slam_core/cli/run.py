"""Run NeB-SLAM offline on a dataset folder or a bag and write a run directory.

The run directory (default ``runs/<dataset-name>-<YYYYmmdd-HHMMSS>``) holds config.yaml (the resolved
configuration), intrinsics.json, trajectory.txt (TUM format: the input frames' stamps, corrected
poses), groundtruth.txt (the input's ground truth at those stamps, when it has one), timings.csv (per
frame), map.pt (map checkpoint with the keyframe poses), mesh.ply, metrics.json, and the plots
trajectory.png and ate_over_time.png (with ground truth) and blocks.png (block allocation, top view).
See ``neb_slam_core.io.run_dir`` for each file's contents.

Configuration: --config takes a preset name (base, tum, scannet, replica, synthetic, small, ci) or a
YAML file; by default it follows the dataset: TUM -> tum, ScanNet -> scannet, Replica -> replica, a
folder written by ``neb-slam synth`` (it holds scene.json) -> synthetic, anything else -> base.
--set key=value (repeatable; dotted keys such as tracking.iterations=20) overrides single values;
--seed, --device and --mesh-voxel override seed, device and mesh.voxel_size_m.

First pose: the run starts from the first processed frame's ground-truth pose when the dataset has
one, so the trajectory and the mesh are in the ground truth's world frame and the mesh compares with
a ground-truth mesh without alignment; otherwise from the identity.

Continuing a map: --map takes a previous run's map.pt (same block, encoding and decoder configuration).
Its blocks and decoders are the starting map. The first frame is tracked against it, from the first
pose above as the prediction (so that pose must be in the map's world frame: ground truth of the same
scene, or the identity when the map's run started at this frame's place). New blocks are allocated
where the map does not reach. The mesh is culled to what this run's keyframes saw.

Metrics: ATE / RPE when the input has ground truth; accuracy, completion and Depth L1 when a
ground-truth mesh is given with --gt-mesh or the input folder holds the mesh.ply of ``neb-slam synth``
(both meshes culled to what the ground-truth cameras saw).

Live (--live): a simulated real-time camera over the dataset. Frames arrive at their stamps (--rate
scales the clock); the concurrent engine (``neb_slam_core.live``: mapping and loop closure in a process of
their own) tracks the newest frame whenever it is free (at most ``live.max_gap_s`` after the last
processed one), and the frames before it are dropped. The run directory then holds the tracked frames
only, and metrics.json adds frames in, frames dropped, tracked frames per second and the mapping lag.
Without --live every frame is processed in the deterministic order of the paper's loop.

Damaged recordings: a frame whose colour or depth cannot be read (a missing or truncated image file, a
bag message that does not decode) is skipped, the run goes on, and one warning at the end names the
skipped files; metrics.json counts them in ``frames_unreadable``. Any other bad frame (an image of the
wrong size, say) stops the run with an error naming the file.

Ctrl-C stops processing after the current frame; a checkpoint and everything computed so far
(trajectory of the processed frames, map, mesh, metrics, plots) are then written and the command exits
with code 130. SIGTERM does the same and exits with code 143. A second Ctrl-C or SIGTERM aborts the
writing. A crash inside the engine also writes what exists before the error is reported. The last line
printed is the run directory.

Checkpoints (not with --live): every --checkpoint-every keyframes (default 20) and at Ctrl-C or SIGTERM
the run directory's checkpoint.pt holds the engine, the frames so far, the input and the options
(``neb_slam_core.checkpoint``); --resume RUN_DIR goes on from it after a crash, a kill or a stop, and
the frames after it get the poses the uninterrupted run would have given. A completed run removes it.

Examples:
    neb-slam run ../shared/data/tum_fr1_xyz_300 --frames 100
    neb-slam run data/synth_small --config ci --out runs/smoke --no-mesh
    neb-slam run bags/fr1_xyz --config tum --set tracking.iterations=20 mapping.every=4 --stride 2
    neb-slam run bags/fr1_xyz --config tum --start 150 --map runs/fr1_first_half/map.pt
    neb-slam run --resume runs/fr1_xyz-20260101-120000
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ..datasets.base import FrameSkipper
    from ..types import RgbdFrame

HELP = "run SLAM offline on a dataset folder or bag and write a run directory (trajectory, map, mesh, metrics)"

log = logging.getLogger(__name__)

#: dataset loader name -> config preset
PRESET_OF_FORMAT = {"tum": "tum", "scannet": "scannet", "replica": "replica"}
SYNTH_SCENE_FILE = "scene.json"  # written by `neb-slam synth`
SYNTH_MESH_FILE = "mesh.ply"
#: keyframes between two checkpoints by default
DEFAULT_CHECKPOINT_EVERY = 20
#: options that --resume takes from the checkpoint, with their defaults (given otherwise: an error)
RESUME_FIXED = {
    "source": None,
    "config": None,
    "overrides": [],
    "frames": None,
    "stride": 1,
    "start": 0,
    "seed": None,
    "device": None,
    "format": None,
    "frame_stamp": None,
    "map": None,
    "live": False,
    "out": None,
    "no_mesh": False,
    "mesh_voxel": None,
    "gt_mesh": None,
    "recon_points": 200_000,
    "depth_views": 1000,
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", type=Path, nargs="?", help="dataset folder or bag (not with --resume)")
    p.add_argument("--config", metavar="NAME|PATH", help="config preset or YAML file (default: from the dataset)")
    p.add_argument(
        "--set",
        dest="overrides",
        action="extend",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        help="override config values, e.g. --set tracking.iterations=20 mapping.every=4",
    )
    p.add_argument("--out", type=Path, metavar="DIR", help="run directory (default: runs/<dataset>-<date>-<time>)")
    p.add_argument("--frames", type=int, metavar="N", help="process at most N frames (after --start, with --stride)")
    p.add_argument("--stride", type=int, default=1, metavar="K", help="use every K-th frame (default 1)")
    p.add_argument("--start", type=int, default=0, metavar="I", help="first frame index (default 0)")
    p.add_argument("--seed", type=int, metavar="S", help="random seed (default: the config's)")
    p.add_argument("--device", choices=("cpu", "cuda"), help="torch device (default: the config's)")
    p.add_argument("--format", metavar="FMT", help="dataset loader (default: detect from the layout)")
    p.add_argument(
        "--frame-stamp",
        choices=("depth", "colour"),  # neb_slam_core.datasets.base.FRAME_STAMPS (not imported: the CLI starts lazily)
        help="TUM folders and bags, whose colour and depth images are taken apart: which image's time stamps a "
        "frame, its pose and its ground truth (default: depth)",
    )
    p.add_argument(
        "--map",
        type=Path,
        metavar="MAP_PT",
        help="continue this map checkpoint (a run's map.pt) instead of starting from an empty map",
    )
    p.add_argument(
        "--resume",
        type=Path,
        metavar="RUN_DIR",
        help="continue the run in RUN_DIR from its checkpoint.pt (after a crash, a kill, Ctrl-C or SIGTERM) "
        "with the input and options it was started with",
    )
    p.add_argument(
        "--checkpoint-every",
        type=int,
        default=DEFAULT_CHECKPOINT_EVERY,
        metavar="K",
        help=f"write the run directory's checkpoint.pt every K keyframes and when stopped (0: never; "
        f"default {DEFAULT_CHECKPOINT_EVERY}; not with --live)",
    )
    p.add_argument(
        "--live",
        action="store_true",
        help="simulate a real-time camera: frames arrive at their "
        "stamps and the engine tracks the newest one when free",
    )
    p.add_argument(
        "--rate",
        type=float,
        default=1.0,
        metavar="R",
        help="with --live: clock speed against the stamps (default 1.0, as recorded)",
    )
    g = p.add_argument_group("mesh and reconstruction")
    g.add_argument("--no-mesh", action="store_true", help="do not extract the mesh")
    g.add_argument(
        "--mesh-voxel",
        type=float,
        metavar="M",
        help="marching-cubes voxel size in metres (default: the config's mesh.voxel_size_m)",
    )
    g.add_argument(
        "--gt-mesh",
        type=Path,
        metavar="PATH",
        help="ground-truth mesh for accuracy / completion (default: the synth folder's mesh.ply)",
    )
    g.add_argument(
        "--recon-points",
        type=int,
        default=200_000,
        metavar="N",
        help="points sampled per mesh for the reconstruction metrics (default 200000)",
    )
    g.add_argument(
        "--depth-views",
        type=int,
        default=1000,
        metavar="N",
        help="virtual views for Depth L1, 0 to skip (default 1000)",
    )


def default_preset(dataset) -> str:
    """The config preset for a dataset (see the module docstring)."""
    root = Path(dataset.root)
    if root.is_dir() and (root / SYNTH_SCENE_FILE).is_file():
        return "synthetic"
    return PRESET_OF_FORMAT.get(dataset.name, "base")


def select_frames(n_available: int, start: int = 0, stride: int = 1, frames: int | None = None) -> range:
    """Input indices to process: from ``start`` every ``stride``-th, at most ``frames`` of them."""
    from ..errors import ConfigError

    if stride < 1:
        raise ConfigError(f"--stride must be >= 1, got {stride}")
    if frames is not None and frames < 1:
        raise ConfigError(f"--frames must be >= 1, got {frames}")
    if not 0 <= start < n_available:
        raise ConfigError(f"--start {start} is outside the dataset's {n_available} frames (0..{n_available - 1})")
    picked = range(start, n_available, stride)
    return picked if frames is None else picked[:frames]


def default_out_dir(source: Path, now: time.struct_time | None = None, parent: Path = Path("runs")) -> Path:
    """``runs/<dataset-name>-<YYYYmmdd-HHMMSS>`` (with ``-2``, ``-3``... when it exists already)."""
    src = Path(source).resolve()
    name = src.stem if src.is_file() else src.name
    base = parent / f"{name}-{time.strftime('%Y%m%d-%H%M%S', now or time.localtime())}"
    out, k = base, 1
    while out.exists():
        k += 1
        out = base.with_name(f"{base.name}-{k}")
    return out


def resolve_config(args: argparse.Namespace, dataset):
    """The run's :class:`~neb_slam_core.config.SlamConfig`: preset or file, then --set, then --seed,
    --device and --mesh-voxel (all validated by :func:`~neb_slam_core.config_io.load_config`)."""
    from ..config_io import load_config
    from ..errors import ConfigError

    overrides = list(args.overrides or [])
    if args.seed is not None:
        overrides.append(f"seed={args.seed}")
    if args.device is not None:
        overrides.append(f"device={args.device}")
    if args.mesh_voxel is not None:
        overrides.append(f"mesh.voxel_size_m={args.mesh_voxel!r}")
    cfg = load_config(args.config or default_preset(dataset), overrides)
    if cfg.device.startswith("cuda"):
        import torch

        if not torch.cuda.is_available():
            raise ConfigError(f"device {cfg.device!r}: CUDA is not available on this machine (use --device cpu)")
    return cfg


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from ..datasets import open_dataset
    from ..datasets.base import FrameSkipper
    from ..errors import ConfigError, DatasetError
    from ..eval.run_report import RunOutputOptions
    from ..io.run_dir import RunDirectory, RunLog

    if args.resume is not None:
        return _resume(args)
    if args.source is None:
        raise ConfigError("give the dataset folder or bag to run on (or --resume RUN_DIR)")
    # --- check everything before the (long) run starts
    loader_options = {} if args.frame_stamp is None else {"frame_stamp": args.frame_stamp}
    dataset = open_dataset(args.source, args.format, **loader_options)
    cfg = resolve_config(args, dataset)
    if len(dataset) == 0:
        raise DatasetError(args.source, "the dataset has no frames")
    indices = select_frames(len(dataset), args.start, args.stride, args.frames)
    if args.rate <= 0:
        raise ConfigError(f"--rate must be > 0, got {args.rate}")
    if args.recon_points < 1 or args.depth_views < 0:
        raise ConfigError("--recon-points must be >= 1 and --depth-views >= 0")
    if args.checkpoint_every < 0:
        raise ConfigError(f"--checkpoint-every must be >= 0, got {args.checkpoint_every}")
    if args.live and args.checkpoint_every not in (0, DEFAULT_CHECKPOINT_EVERY):
        raise ConfigError("--checkpoint-every: a live run (--live) is not checkpointed")
    gt_mesh = args.gt_mesh
    if gt_mesh is not None and not gt_mesh.is_file():
        raise DatasetError(gt_mesh, "ground-truth mesh not found")
    root = Path(dataset.root)
    if gt_mesh is None and root.is_dir() and (root / SYNTH_SCENE_FILE).is_file() and (root / SYNTH_MESH_FILE).is_file():
        gt_mesh = root / SYNTH_MESH_FILE
    from ..engine_process import prepare_engine_process
    from ..slam import Slam, load_map_for

    block_map = None if args.map is None else load_map_for(cfg, args.map)
    skipper = FrameSkipper(dataset)
    first, indices = _first_readable(skipper, indices)
    if first.T_world_cam is not None:
        T_world_first = first.T_world_cam
    else:
        T_world_first = np.eye(4)
        if dataset.has_ground_truth:
            log.warning(
                "frame %d has no ground-truth pose: the run starts from the identity, and the mesh is "
                "aligned by the ATE fit before it is compared",
                first.index,
            )

    run_dir = RunDirectory.create(args.out or default_out_dir(args.source))
    run_dir.write_config(cfg)
    run_dir.write_intrinsics(first.intrinsics)
    options = RunOutputOptions(
        mesh=not args.no_mesh,
        mesh_cfg=cfg.mesh,
        gt_mesh=gt_mesh,
        first_pose_from_gt=first.T_world_cam is not None,
        recon_points=args.recon_points,
        depth_views=args.depth_views,
    )
    print(
        f"{dataset!r}: {len(indices)} frames, config {args.config or default_preset(dataset)}, "
        + ("" if block_map is None else f"continuing {args.map} ({len(block_map)} blocks), ")
        + f"writing to {run_dir.path}",
        file=sys.stderr,
    )

    # loading the C++ kernels (compiling them, in the fallback) and torch's first-use costs are not the
    # first frame's time
    prepare_engine_process(cfg.grid_backend)
    if args.live:
        from ..live import LiveSlam

        slam = LiveSlam(cfg, T_world_first, block_map)
        checkpoints = None
    else:
        slam = Slam(cfg, T_world_first, block_map)
        resume = {
            "source": str(Path(args.source).resolve()),
            "format": dataset.name,
            "loader_options": loader_options,
            "options": options,
        }
        checkpoints = _Checkpoints(run_dir, args.checkpoint_every, resume)
    return _execute(slam, skipper, indices, first, RunLog(), run_dir, options, args, checkpoints)


def _resume(args: argparse.Namespace) -> int:
    """``--resume RUN_DIR``: the engine, run log and remaining input from RUN_DIR's checkpoint."""
    from ..checkpoint import CHECKPOINT_FILE, load_checkpoint
    from ..datasets import open_dataset
    from ..datasets.base import FrameSkipper
    from ..engine_process import prepare_engine_process
    from ..errors import ConfigError
    from ..io.run_dir import RunDirectory

    given = [name for name, default in RESUME_FIXED.items() if getattr(args, name) != default]
    if given:
        flags = ", ".join("source" if n == "source" else "--" + n.replace("_", "-") for n in given)
        raise ConfigError(f"--resume continues the run as it was started: drop {flags}")
    ckpt = load_checkpoint(Path(args.resume) / CHECKPOINT_FILE)
    r = ckpt.resume
    dataset = open_dataset(r["source"], r["format"], **r.get("loader_options", {}))
    skipper = FrameSkipper(dataset)
    skipper.unreadable = list(r.get("unreadable", []))
    remaining = r["remaining"]
    slam, run_log = ckpt.slam, ckpt.run_log
    prepare_engine_process(slam.cfg.grid_backend)
    print(
        f"{dataset!r}: resuming {args.resume} after {slam.n_frames} frames, {len(remaining)} to go",
        file=sys.stderr,
    )
    checkpoints = _Checkpoints(RunDirectory(args.resume), args.checkpoint_every, r)
    return _execute(
        slam, skipper, remaining, None, run_log, RunDirectory(args.resume), r["options"], args, checkpoints, ckpt.wall_s
    )


class _Checkpoints:
    """Writes the run directory's checkpoint every ``every`` keyframes (0: never) and at a stop; ``resume``
    is what ``--resume`` needs besides the engine (input, options), completed with the frames left."""

    def __init__(self, run_dir, every: int, resume: dict):
        from ..checkpoint import CHECKPOINT_FILE

        self.path = run_dir.file(CHECKPOINT_FILE)
        self.every = every
        self.resume = {k: v for k, v in resume.items() if k not in ("remaining", "unreadable")}

    def after_frame(self, slam, run_log, skipper, remaining: range, wall_s: float, keyframe: bool, stop: bool) -> None:
        """After a whole frame (``keyframe``: it made one): write when it made the every-th keyframe, or
        at a ``stop``."""
        if self.every <= 0:
            return
        if (keyframe and len(slam.keyframes) % self.every == 0) or stop:
            from ..checkpoint import save_checkpoint

            state = {**self.resume, "remaining": remaining, "unreadable": list(skipper.unreadable)}
            save_checkpoint(self.path, slam, run_log, state, wall_s)

    def discard(self) -> None:
        """The run completed: its checkpoint has nothing left to resume."""
        self.path.unlink(missing_ok=True)


def _execute(
    slam, skipper, indices: range, first, run_log, run_dir, options, args, checkpoints, wall_before: float = 0.0
) -> int:
    """Process ``indices`` (the first one already read as ``first``, or None), then write the run
    directory, also after an interruption or a crash; the command's exit status."""
    from ..eval.run_report import write_run
    from .interrupt import describe, exit_status

    t_start = time.perf_counter() - wall_before
    try:
        if args.live:
            interrupt, live_metrics = _process_live(slam, skipper, indices, first, run_log, args.rate)
        else:
            interrupt = _process(slam, skipper, indices, first, run_log, checkpoints, t_start)
            live_metrics = {}
    except Exception as exc:
        wall_s = time.perf_counter() - t_start
        log.error(
            "the run failed (%s: %s); writing the %d frames processed so far to %s",
            type(exc).__name__,
            exc,
            slam.n_frames,
            run_dir.path,
        )
        skipper.warn()
        try:
            if args.live:
                slam.close(timeout_s=60.0)
            write_run(run_dir, slam, run_log, options, "crashed", wall_s, {"frames_unreadable": len(skipper)})
        except KeyboardInterrupt as again:
            log.error("writing aborted by %s: %s is incomplete", describe(again), run_dir.path)
        except Exception as write_exc:  # report, but the original error is the one that matters
            log.error("writing the partial run failed too (%s: %s)", type(write_exc).__name__, write_exc)
        print(run_dir.path)
        raise
    wall_s = time.perf_counter() - t_start
    skipper.warn()
    status = "complete" if interrupt is None else "interrupted"
    if interrupt is not None:
        print(
            f"interrupted by {describe(interrupt)} after {slam.n_frames} frames: writing what was computed "
            f"(Ctrl-C or SIGTERM again to abort)",
            file=sys.stderr,
        )
    try:
        extra_metrics = {"frames_unreadable": len(skipper), **live_metrics}
        summary = write_run(run_dir, slam, run_log, options, status, wall_s, extra_metrics)
    except KeyboardInterrupt as again:
        print(f"writing aborted by {describe(again)}: {run_dir.path} is incomplete", file=sys.stderr)
        return exit_status(again)
    if interrupt is None and checkpoints is not None:
        checkpoints.discard()
    _print_summary(summary)
    print(run_dir.path)
    return 0 if interrupt is None else exit_status(interrupt)


def _first_readable(skipper: FrameSkipper, indices: range) -> tuple[RgbdFrame, range]:
    """The first selected frame that can be read and the selection from it on; :class:`DatasetError`
    when none can."""
    from ..errors import DatasetError

    for k, i in enumerate(indices):
        frame = skipper.read(i)
        if frame is not None:
            return frame, indices[k:]
    skipper.warn()
    raise DatasetError(skipper.dataset.root, f"none of the {len(indices)} selected frames can be read")


def _process(slam, skipper: FrameSkipper, indices: range, first, run_log, checkpoints, t_start: float):
    """The per-frame loop with its progress bar; returns the interruption (Ctrl-C or SIGTERM, see
    :mod:`.interrupt`) that stopped it after the current frame, or None when every frame was processed.
    ``first`` is ``indices[0]``'s frame, already read (None: read it). Frames ``skipper`` cannot read are
    skipped (it keeps them for the summary warning). ``checkpoints`` (or None) is told of every frame."""
    from tqdm import tqdm
    from tqdm.contrib.logging import logging_redirect_tqdm

    from .interrupt import deferred_interrupts

    t0 = time.perf_counter()
    with (
        logging_redirect_tqdm(),
        tqdm(total=len(indices), desc="slam", unit="frame", dynamic_ncols=True) as bar,
        deferred_interrupts() as pending,
    ):
        try:
            for k, i in enumerate(indices):
                frame = first if k == 0 and first is not None else skipper.read(i)
                keyframe = False
                if frame is not None:
                    run_log.begin(frame)
                    result = slam.process(frame)
                    run_log.end(result)
                    keyframe = result.is_keyframe
                    bar.set_postfix(
                        fps=f"{bar.n / max(time.perf_counter() - t0, 1e-9):.2f}",
                        blocks=result.n_blocks,
                        kf=len(slam.keyframes),
                        refresh=False,
                    )
                bar.update(1)
                stop = pending.exc is not None
                if checkpoints is not None:
                    wall_s = time.perf_counter() - t_start
                    checkpoints.after_frame(slam, run_log, skipper, indices[k + 1 :], wall_s, keyframe, stop)
                if stop:
                    return pending.exc
        except KeyboardInterrupt as exc:
            return exc
    return None


def _process_live(
    slam, skipper: FrameSkipper, indices: range, first, run_log, rate: float
) -> tuple[KeyboardInterrupt | None, dict]:
    """The simulated real-time camera of ``--live`` (module docstring): returns the interruption that
    stopped it (None when every frame arrived) and the live figures for metrics.json, where frames in
    and dropped count readable frames only. The engine is closed (its queued keyframes integrated)
    before it returns."""
    import numpy as np
    from tqdm import tqdm
    from tqdm.contrib.logging import logging_redirect_tqdm

    stamps = np.asarray(skipper.dataset.stamps_ns, dtype=np.int64)[np.asarray(indices)]
    arrival_s = (stamps - stamps[0]) * 1e-9 / rate  # when each frame reaches the engine, from the start
    interrupt, k, n_unreadable = None, 0, 0
    t0 = time.perf_counter()
    with logging_redirect_tqdm(), tqdm(total=len(indices), desc="live", unit="frame", dynamic_ncols=True) as bar:
        try:
            while k < len(indices):
                slam.wait_for_map()
                now = time.perf_counter() - t0
                newest = int(np.searchsorted(arrival_s, now, side="right")) - 1
                if newest < k:  # the next frame has not arrived yet
                    time.sleep(arrival_s[k] - now)
                    continue
                chosen = k + slam.next_frame(stamps[k : newest + 1])
                frame = first if chosen == 0 else skipper.read(indices[chosen])
                if frame is None:
                    n_unreadable += 1
                    bar.update(chosen + 1 - k)
                    k = chosen + 1
                    continue
                run_log.begin(frame)
                result = slam.process(frame)
                run_log.end(result)
                bar.update(chosen + 1 - k)
                k = chosen + 1
                bar.set_postfix(
                    tracked=slam.n_frames, dropped=k - slam.n_frames, lag=slam.stats.mapping_lag, refresh=False
                )
        except KeyboardInterrupt as exc:
            interrupt = exc
    span_s = time.perf_counter() - t0
    slam.close()
    return interrupt, {"rate": rate, **slam.live_metrics(k - n_unreadable, span_s)}


def _print_summary(summary) -> None:
    m = summary.metrics

    def fmt(key: str, unit: str = "", digits: int = 3) -> str:
        v = m.get(key)
        return "n/a" if v is None else f"{v:.{digits}f}{' ' + unit if unit else ''}"

    rows = [
        ("status", f"{summary.status}, {summary.n_frames} frames"),
        ("blocks / parameters", f"{m.get('n_blocks')} / {fmt('param_mb', 'MB', 2)}"),
        ("keyframes", str(m.get("n_keyframes"))),
        ("tracking failures", str(m.get("n_tracking_failures"))),
        ("time per frame", f"{fmt('s_per_frame', 's')} engine, {fmt('wall_s_per_frame', 's')} wall"),
        ("tracking / mapping per frame", f"{fmt('track_ms_mean', 'ms', 1)} / {fmt('map_ms_mean', 'ms', 1)}"),
    ]
    if "ate_rmse_cm" in m:
        rows.append(("ATE RMSE", f"{fmt('ate_rmse_cm', 'cm')} ({m.get('n_poses')} poses)"))
    if "accuracy_cm" in m:
        rows += [
            (
                "accuracy / completion",
                f"{fmt('accuracy_cm', 'cm')} / {fmt('completion_cm', 'cm')} "
                f"(sampling floor {fmt('recon_floor_cm', 'cm')})",
            ),
            ("completion ratio", fmt("completion_ratio_pct", "%", 2)),
            ("depth L1", fmt("depth_l1_cm", "cm")),
        ]
    if m.get("frames_unreadable"):
        rows.append(("unreadable frames", f"{m['frames_unreadable']} skipped (see the warning above)"))
    for s in summary.skipped:
        rows.append(("skipped", s))
    width = max(len(name) for name, _ in rows)
    for name, value in rows:
        print(f"  {name:<{width}}  {value}")
