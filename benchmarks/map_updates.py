"""Bandwidth of ``map_update`` (mapper to tracker) and what the lean encoding costs the tracker's poses.

The engine runs offline and deterministic on a sequence (``Slam``: tracking, mapping and loop closure in
order). After every frame whose mapping step (or loop correction) changed blocks, the update the mapper
node would publish is built twice from the same map:

- ``old``: every changed block whole, float32 (``capture`` without a mirror: the exact encoding);
- ``new``: through a :class:`~neb_slam_core.scene.map_update.ReceiverMirror` with the config's
  ``live.update_tolerance``, ``live.update_float16`` and ``live.update_delta_step`` (``--set`` changes
  them): a block's first update whole, then its changed rows or its changes in steps.

``mb_per_s_*`` is the bytes of all updates over the sequence's recorded duration, in MB (10^6 bytes) per
second: what a link carries when the engine keeps up with the camera; ``encode_ms_per_update_new`` and
``apply_ms_per_update_new`` what encoding a ``new`` update costs the sender and decoding and applying it
a receiver. The ``new`` updates are applied in
order to a receiver map, which then holds what a tracker fed by them holds. Every ``--track-every``-th
frame is then tracked twice from the same start (the previous frame's pose, with the same seed), against
the mapper's final map and against the receiver's: ``pose_diff_cm_*`` are the distances between the two
results (translation), the figure that says whether the lean encoding moves the tracker.

Example::

    .venv/bin/python benchmarks/map_updates.py --source demo --json updates.json
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
from common import REPO, TUM, record
from tqdm import tqdm

from neb_slam_core.config_io import load_config
from neb_slam_core.datasets import open_dataset
from neb_slam_core.geometry.rectify import Rectifier
from neb_slam_core.scene import map_update
from neb_slam_core.slam import Slam, new_block_map
from neb_slam_core.tracking.tracker import Tracker

#: where ``--source demo`` finds (or makes) the scene of ``make demo``
DEMO_SCENE = REPO / "bags" / "demo_scene"
SOURCES = {"demo": (DEMO_SCENE, "synthetic"), "tum": (TUM, "tum")}


def demo_scene() -> Path:
    """The ``make demo`` scene, generated once (the synthetic ``default`` preset) when it is missing."""
    if not (DEMO_SCENE / "groundtruth.txt").is_file():
        from neb_slam_core.synth.generate import generate

        generate("default", DEMO_SCENE)
    return DEMO_SCENE


def measure(frames, cfg, track_every: int = 5, progress: bool = True) -> dict:
    """The figures of the module docstring for ``frames`` under ``cfg``."""
    torch.manual_seed(cfg.seed)
    slam = Slam(cfg, frames[0].T_world_cam)
    mirror = map_update.ReceiverMirror(cfg.live.update_tolerance, cfg.live.update_float16, cfg.live.update_delta_step)
    receiver = new_block_map(cfg)
    old_bytes = new_bytes = n_updates = 0
    encode_s = apply_s = 0.0
    revisions: dict[int, int] = {}
    t0 = time.perf_counter()
    for frame in tqdm(frames, desc="engine", unit="frame", disable=not progress):
        slam.process(frame)
        now = slam.block_revisions
        changed = {b for b, r in now.items() if r != revisions.get(b)}
        changed |= set(range(len(receiver), len(slam.block_map)))  # blocks new since the last update
        revisions = dict(now)
        if not changed:
            continue
        poses = slam.keyframes.poses()
        stamps = [kf.stamp_ns for kf in slam.keyframes.keyframes]
        old = map_update.capture(slam.block_map, changed, 1, stamps[-1], stamps, poses)
        new = map_update.capture(slam.block_map, changed, 1, stamps[-1], stamps, poses, mirror=mirror)
        old_bytes += len(map_update.encode(old))
        t = time.perf_counter()
        data = map_update.encode(new)
        encode_s += time.perf_counter() - t
        new_bytes += len(data)
        t = time.perf_counter()
        map_update.apply(map_update.decode(data), receiver)
        apply_s += time.perf_counter() - t
        n_updates += 1
    engine_s = time.perf_counter() - t0
    span_s = (frames[-1].stamp_ns - frames[0].stamp_ns) * 1e-9
    values = sum(b.grid.table.numel() for b in slam.block_map.blocks)
    pairs = zip(slam.block_map.blocks, receiver.blocks)
    table_err = max(float((a.grid.table - b.grid.table).abs().max().detach()) for a, b in pairs)

    # the same frames tracked against the mapper's map and the receiver's, from the same start and seed
    diffs = []
    rectify = Rectifier()
    for i in range(1, len(frames), track_every):
        frame = rectify(frames[i])
        start = slam.pose_of(i - 1)
        exact = Tracker(cfg.tracking, cfg.render, seed=cfg.seed + i).track(slam.block_map, frame, start)
        lean = Tracker(cfg.tracking, cfg.render, seed=cfg.seed + i).track(receiver, frame, start)
        diffs.append(100 * float(np.linalg.norm(exact.T_world_cam[:3, 3] - lean.T_world_cam[:3, 3])))
    return {
        "frames": len(frames),
        "span_s": round(span_s, 3),
        "updates": n_updates,
        "blocks": len(slam.block_map),
        "table_values": values,
        "mb_per_s_old": old_bytes / 1e6 / span_s,
        "mb_per_s_new": new_bytes / 1e6 / span_s,
        "mb_per_s_ratio": new_bytes / old_bytes,
        "kb_per_update_old": old_bytes / 1e3 / n_updates,
        "kb_per_update_new": new_bytes / 1e3 / n_updates,
        "encode_ms_per_update_new": 1e3 * encode_s / n_updates,
        "apply_ms_per_update_new": 1e3 * apply_s / n_updates,
        "table_max_error": table_err,
        "tolerance": cfg.live.update_tolerance,
        "float16": cfg.live.update_float16,
        "delta_step": cfg.live.update_delta_step,
        "tracked_frames_compared": len(diffs),
        "pose_diff_cm_median": float(np.median(diffs)),
        "pose_diff_cm_max": float(np.max(diffs)),
        "engine_s_per_frame": engine_s / len(frames),
    }


def live_update_settings() -> list[str]:
    """``--set`` overrides that make any preset send updates as the ``live`` preset does."""
    live = load_config("live").live
    return [
        f"live.update_tolerance={live.update_tolerance!r}",
        f"live.update_float16={str(live.update_float16).lower()}",
        f"live.update_delta_step={live.update_delta_step!r}",
    ]


def figures_for(source: str, frames: int, overrides: list[str], track_every: int, progress: bool) -> dict:
    """:func:`measure` on a named source (``SOURCES``), its first ``frames`` frames (0: all)."""
    path, preset = SOURCES[source]
    path = demo_scene() if source == "demo" else path
    cfg = load_config(preset, overrides)
    ds = open_dataset(path)
    n = len(ds) if frames <= 0 else min(frames, len(ds))
    return {"source": source, "config": preset, **measure([ds[i] for i in range(n)], cfg, track_every, progress)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--source", choices=sorted(SOURCES), nargs="+", default=["demo", "tum"])
    p.add_argument("--frames", type=int, default=0, help="the first this many frames of each source (0: all)")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="config overrides")
    p.add_argument("--track-every", type=int, default=5, help="compare the tracked pose of every this-th frame")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--results-dir", type=Path, default=None)
    args = p.parse_args()
    figures = {}
    for source in args.source:
        f = figures_for(source, args.frames, args.set, args.track_every, not args.no_progress)
        figures[source] = f
        print(
            f"{source}: {f['mb_per_s_old']:.3f} MB/s whole float32 -> {f['mb_per_s_new']:.3f} MB/s "
            f"(x{f['mb_per_s_ratio']:.3f}; {f['updates']} updates, {f['blocks']} blocks); table error max "
            f"{f['table_max_error']:.2e}; tracked pose difference median {f['pose_diff_cm_median']:.4f} cm, "
            f"max {f['pose_diff_cm_max']:.4f} cm over {f['tracked_frames_compared']} frames"
        )
    record("map_updates", figures, args.json, args.results_dir)


if __name__ == "__main__":
    main()
