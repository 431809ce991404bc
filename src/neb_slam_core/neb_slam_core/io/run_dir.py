"""The run directory of ``neb-slam run``: the files a run leaves, their names and formats, and the writers
and readers of each file.

::

    <run>/
        config.yaml        the resolved configuration (loadable again with ``--config <run>/config.yaml``)
        intrinsics.json    the camera: fx, fy, cx, cy, width, height
        trajectory.txt     TUM format: the processed input frames' stamps and corrected poses (T_world_cam)
        groundtruth.txt    the input's ground-truth poses at those stamps (frames without one are skipped)
        timings.csv        one row per processed frame, columns :data:`TIMINGS_COLUMNS`
        map.pt             block-map checkpoint (:func:`~neb_slam_core.scene.persistence.save_map`); its
                           ``extra`` holds the keyframe poses and frame indices (see :func:`map_extra`)
        mesh.ply           the reconstruction, world frame, vertex colours
        metrics.json       the run's figures (:func:`~neb_slam_core.eval.run_report.run_metrics`), with
                           ground truth ATE / RPE (the figures of ``neb-slam eval``), with a ground-truth
                           mesh the reconstruction metrics
        loops.json         every loop detected (:func:`loop_log`): frames, score, whether it was applied
                           and why not, the size of the correction
        trajectory.png, ate_over_time.png    with ground truth (as ``neb-slam eval`` draws them; loops
                           marked on the trajectory)
        blocks.png         the block allocation, top view (:func:`~neb_slam_core.eval.plots.plot_block_allocation`)
        checkpoint.pt      while a run goes on, and after it was stopped, killed or crashed: the engine's
                           state to resume from (:mod:`~neb_slam_core.checkpoint`); a completed
                           ``neb-slam run`` removes it

:class:`RunDirectory` has one writer per file; each writes under a temporary name and renames, so no file
is ever left half-written. Computing what goes into the report files (metrics, plots, the mesh and its
evaluation) is the evaluation layer's: :func:`~neb_slam_core.eval.run_report.write_run` writes a whole run
directory through these writers from a :class:`~neb_slam_core.slam.Slam` and the :class:`RunLog` the loop
kept. This module reads and writes files only (the layering of ``docs/architecture.md``: ``io`` does
not import ``eval``, the mesh extraction or plotting).
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..config import SlamConfig
from ..errors import DatasetError
from ..types import Intrinsics, RgbdFrame, StepResult
from .trajectory import Trajectory, write_tum_trajectory

if TYPE_CHECKING:  # the engine pulls torch; only needed for type hints here
    from ..slam import Slam

CONFIG_FILE = "config.yaml"
INTRINSICS_FILE = "intrinsics.json"
TRAJECTORY_FILE = "trajectory.txt"
GROUNDTRUTH_FILE = "groundtruth.txt"
TIMINGS_FILE = "timings.csv"
MAP_FILE = "map.pt"
MESH_FILE = "mesh.ply"
METRICS_FILE = "metrics.json"
LOOPS_FILE = "loops.json"
BLOCKS_PLOT_FILE = "blocks.png"

#: columns of timings.csv: the input frame index, its stamp (integer ns), the engine's per-stage times
#: (ms), whether it became a keyframe, the id of the block it allocated (empty: none), whether tracking
#: succeeded, then the allocation ratio tau, the blocks in the map after it and the failure reason.
TIMINGS_COLUMNS = (
    "index",
    "stamp_ns",
    "track_ms",
    "allocate_ms",
    "map_ms",
    "loop_ms",
    "total_ms",
    "keyframe",
    "new_block",
    "tracking_ok",
    "tau",
    "n_blocks",
    "failure_reason",
)

#: how a run ended, as stored in metrics.json ``status``
STATUSES = ("complete", "interrupted", "crashed")


@dataclass(slots=True)  # one per frame: no per-object dict
class FrameLog:
    """One input frame handed to the engine.

    Attributes:
        index: the frame's position in the input dataset.
        stamp_ns: its stamp.
        T_world_cam_gt: its ground-truth pose ``(4, 4)`` float64, or None.
        result: what the engine did with it; None when processing did not finish.
    """

    index: int
    stamp_ns: int
    T_world_cam_gt: np.ndarray | None
    result: StepResult | None = None


@dataclass
class RunLog:
    """What the run loop handed to the engine and got back, in order."""

    frames: list[FrameLog] = field(default_factory=list)

    def begin(self, frame: RgbdFrame) -> None:
        """Call before ``slam.process(frame)``."""
        gt = None if frame.T_world_cam is None else np.array(frame.T_world_cam, dtype=np.float64)
        self.frames.append(FrameLog(int(frame.index), int(frame.stamp_ns), gt))

    def end(self, result: StepResult) -> None:
        """Call with what ``slam.process`` returned for the frame of the last :meth:`begin`."""
        if not self.frames or self.frames[-1].result is not None:
            raise RuntimeError("RunLog.end without a matching begin")
        self.frames[-1].result = result

    @property
    def completed(self) -> list[FrameLog]:
        """The frames the engine finished (their ``result`` is set)."""
        return [f for f in self.frames if f.result is not None]

    def groundtruth(self, n_frames: int) -> Trajectory:
        """Ground-truth poses of the first ``n_frames`` frames, skipping frames that have none."""
        with_gt = [f for f in self.frames[:n_frames] if f.T_world_cam_gt is not None]
        if not with_gt:
            return Trajectory(np.zeros(0, np.int64), np.zeros((0, 4, 4)))
        return Trajectory(np.array([f.stamp_ns for f in with_gt]), np.stack([f.T_world_cam_gt for f in with_gt]))


class RunDirectory:
    """The folder of one run and its writers (one method per file)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)

    @classmethod
    def create(cls, path: str | Path) -> RunDirectory:
        """Make a new, empty run folder (parents too); an existing non-empty folder is an error."""
        path = Path(path)
        if path.exists():
            if not path.is_dir():
                raise DatasetError(path, "output path exists and is not a folder")
            if any(path.iterdir()):
                raise DatasetError(
                    path, "output folder is not empty (it may hold another run); choose another --out or remove it"
                )
        path.mkdir(parents=True, exist_ok=True)
        return cls(path)

    def file(self, name: str) -> Path:
        return self.path / name

    def _write_atomic(self, name: str, write: Callable[[Path], object]) -> Path:
        """Write file ``name`` through ``write(tmp_path)`` then rename, so a crash never leaves half a file."""
        path = self.file(name)
        tmp = path.with_name(path.name + ".tmp")
        write(tmp)
        tmp.replace(path)
        return path

    def _write_text(self, name: str, text: str) -> Path:
        return self._write_atomic(name, lambda tmp: tmp.write_text(text))

    def write_config(self, cfg: SlamConfig) -> Path:
        from ..config_io import dump_config

        return self._write_atomic(CONFIG_FILE, lambda tmp: dump_config(cfg, tmp))

    def write_intrinsics(self, intrinsics: Intrinsics) -> Path:
        from ..datasets.tum import write_intrinsics_json

        return self._write_atomic(INTRINSICS_FILE, lambda tmp: write_intrinsics_json(tmp, intrinsics))

    def write_trajectory(self, traj: Trajectory, name: str = TRAJECTORY_FILE, header: str | None = None) -> Path:
        return self._write_atomic(name, lambda tmp: write_tum_trajectory(tmp, traj, header))

    def write_timings(self, frames: list[FrameLog]) -> Path:
        """timings.csv: one row per finished frame (columns :data:`TIMINGS_COLUMNS`)."""
        buf = io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        writer.writerow(TIMINGS_COLUMNS)
        for f in frames:
            r = f.result
            if r is None:
                continue
            t = r.timings
            writer.writerow(
                [
                    f.index,
                    f.stamp_ns,
                    f"{t.track_ms:.3f}",
                    f"{t.allocate_ms:.3f}",
                    f"{t.map_ms:.3f}",
                    f"{t.loop_ms:.3f}",
                    f"{t.total_ms:.3f}",
                    int(r.is_keyframe),
                    "" if r.new_block_id is None else r.new_block_id,
                    int(r.tracking_ok),
                    f"{r.tau:.4f}",
                    r.n_blocks,
                    r.failure_reason,
                ]
            )
        return self._write_text(TIMINGS_FILE, buf.getvalue())

    def write_loops(self, loops: list[dict]) -> Path:
        return self._write_text(LOOPS_FILE, json.dumps(_json_safe(loops), indent=2) + "\n")

    def write_metrics(self, metrics: dict) -> Path:
        return self._write_text(METRICS_FILE, json.dumps(_json_safe(metrics), indent=2, sort_keys=True) + "\n")

    def write_map(self, slam: Slam, frames: list[FrameLog]) -> Path:
        from ..scene.persistence import save_map

        return save_map(
            slam.block_map,
            self.file(MAP_FILE),
            extra=map_extra(slam, frames),
            block_keyframes=slam.keyframes.block_keyframes(),
        )

    def write_mesh(self, mesh) -> Path:
        """mesh.ply: ``mesh`` (a ``trimesh.Trimesh``) as binary PLY with its vertex colours."""
        return self._write_atomic(MESH_FILE, lambda tmp: mesh.export(str(tmp), file_type="ply"))


def read_timings(path: str | Path) -> list[dict[str, str]]:
    """The rows of a timings.csv as dicts keyed by :data:`TIMINGS_COLUMNS` (values as text)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "timings file not found")
    with path.open(newline="") as fh:
        reader = csv.DictReader(fh)
        if tuple(reader.fieldnames or ()) != TIMINGS_COLUMNS:
            raise DatasetError(path, f"expected the columns {', '.join(TIMINGS_COLUMNS)}, got {reader.fieldnames}")
        return list(reader)


def map_extra(slam: Slam, frames: list[FrameLog]) -> dict:
    """What map.pt stores beside the map (plain tensors and lists, loadable with ``weights_only``).

    ``keyframe_poses``: ``(K, 4, 4)`` float64 tensor of the keyframes' current ``T_world_cam``;
    ``keyframe_frame_indices`` / ``keyframe_stamps_ns``: each keyframe's input frame index and stamp;
    ``frame_indices`` / ``stamps_ns``: those of every processed frame.
    """
    import torch

    kfs = slam.keyframes.keyframes
    poses = slam.keyframes.poses() if kfs else np.zeros((0, 4, 4))
    n = slam.n_frames
    return {
        "keyframe_poses": torch.from_numpy(np.ascontiguousarray(poses, dtype=np.float64)),
        "keyframe_frame_indices": [frames[kf.frame_index].index for kf in kfs],
        "keyframe_stamps_ns": [int(kf.stamp_ns) for kf in kfs],
        "frame_indices": [f.index for f in frames[:n]],
        "stamps_ns": [f.stamp_ns for f in frames[:n]],
    }


def loop_log(slam: Slam, frames: list[FrameLog]) -> list[dict]:
    """Every loop the engine detected, in order: :meth:`~neb_slam_core.types.LoopEvent.as_dict` plus the
    input frame index and stamp of the query keyframe (``frame``, ``stamp_ns``) and of its loop
    keyframes (``loop_frames``, ``loop_stamps_ns``)."""
    kfs = slam.keyframes.keyframes

    def frame_of(keyframe_id: int) -> int:
        return frames[kfs[keyframe_id].frame_index].index

    out = []
    for event in slam.loops:
        entry = {"frame": frame_of(event.query_id), "stamp_ns": int(kfs[event.query_id].stamp_ns)}
        entry.update(event.as_dict())
        entry["loop_frames"] = [frame_of(i) for i in event.loop_ids]
        entry["loop_stamps_ns"] = [int(kfs[i].stamp_ns) for i in event.loop_ids]
        out.append(entry)
    return out


def _json_safe(value):
    """Metrics -> JSON: numpy scalars to Python numbers, non-finite floats to None (JSON has no NaN)."""
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
