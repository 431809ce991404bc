"""Convert a dataset (any registered format, or another bag) into a ROS 2 bag the node suite can play.

The bag has colour (rgb8), depth (16UC1 millimetres, or 32FC1 metres with --depth 32FC1), camera
info and, when the dataset has it, ground truth as geometry_msgs/PoseStamped in frame ``map``; every
message carries the frame's stamp. 16UC1 rounds depth to whole millimetres (TUM stores 1/5000 m, so
use --depth 32FC1 to keep it exact); the command prints the largest rounding error.

Examples:
    neb-slam convert tum ../shared/data/tum_fr1_xyz_300 bags/fr1_xyz
    neb-slam convert auto ../shared/data/tum_fr1_xyz_300 bags/fr1_xyz_sqlite --storage sqlite3 --depth 32FC1
    neb-slam convert bag rgbd_dataset_freiburg1_xyz.bag bags/fr1_xyz_ros2 --frames 100 --overwrite
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..io.bag import DEPTH_ENCODINGS, STORAGES

HELP = "convert a dataset folder or bag into a ROS 2 bag (sqlite3 or mcap)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("format", help="source format (a registered loader name, e.g. tum) or 'auto' to detect it")
    p.add_argument("source", type=Path, help="dataset folder or bag to read")
    p.add_argument("bag", type=Path, help="output bag directory (must not exist unless --overwrite)")
    p.add_argument("--storage", choices=STORAGES, default="mcap", help="rosbag2 storage plugin (default: mcap)")
    p.add_argument(
        "--depth",
        choices=DEPTH_ENCODINGS,
        default="16UC1",
        help="depth encoding: 16UC1 millimetres (default) or 32FC1 metres (exact)",
    )
    p.add_argument("--frames", type=int, default=None, metavar="N", help="convert only the first N frames")
    p.add_argument("--overwrite", action="store_true", help="replace an existing bag at the output path")


def _size_text(n_bytes: int) -> str:
    return f"{n_bytes / 2**20:.1f} MiB" if n_bytes >= 2**20 else f"{n_bytes / 2**10:.1f} KiB"


def run(args: argparse.Namespace) -> int:
    from ..datasets import open_dataset
    from ..errors import ConfigError
    from ..io.bag import BagWriteOptions, write_bag

    if args.frames is not None and args.frames < 1:
        raise ConfigError(f"--frames must be at least 1, got {args.frames}")
    fmt = None if args.format.lower() == "auto" else args.format
    dataset = open_dataset(args.source, fmt)
    options = BagWriteOptions(storage=args.storage, depth_encoding=args.depth, overwrite=args.overwrite)
    summary = write_bag(dataset, args.bag, options, max_frames=args.frames)

    print(f"wrote {summary.path} ({args.storage}): {summary.n_frames} frames from {dataset.name} {args.source}")
    width = max(len(t.topic) for t in summary.topics)
    for t in summary.topics:
        print(f"  {t.topic:<{width}}  {t.msgtype:<30}  {t.message_count} messages")
    print(f"size: {_size_text(summary.size_bytes)}")
    if args.depth == "16UC1":
        print(
            f"depth rounded to 1 mm: largest change {summary.depth_max_error_m * 1000:.3f} mm"
            + (" (use --depth 32FC1 to keep depth exact)" if summary.depth_max_error_m > 0 else "")
        )
    if summary.n_depth_out_of_range:
        print(f"{summary.n_depth_out_of_range} depth pixels beyond 65.535 m written as 0 (invalid)")
    return 0
