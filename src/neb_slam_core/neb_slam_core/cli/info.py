"""Print what a dataset folder or bag holds: format, frame count, image size, intrinsics, ground truth.

Example:
    neb-slam info ../shared/data/tum_fr1_xyz_300
"""

from __future__ import annotations

import argparse

HELP = "show what a dataset folder or bag holds"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", help="dataset folder or bag")
    p.add_argument("--format", default=None, help="loader name (default: detect from the layout)")


def run(args: argparse.Namespace) -> int:
    from ..datasets import open_dataset

    ds = open_dataset(args.source, args.format)
    print(f"format:        {ds.name}")
    print(f"frames:        {len(ds)}")
    if len(ds):
        f0 = ds[0]
        k = f0.intrinsics
        print(f"image:         {k.width}x{k.height}")
        print(f"intrinsics:    fx={k.fx:.3f} fy={k.fy:.3f} cx={k.cx:.3f} cy={k.cy:.3f}")
        print(f"first stamp:   {f0.stamp_ns * 1e-9:.6f} s")
        valid = f0.depth_m[f0.depth_m > 0]
        if valid.size:
            print(f"depth (frame 0): {valid.min():.3f}..{valid.max():.3f} m, {valid.size / f0.depth_m.size:.0%} valid")
    print(f"ground truth:  {'yes' if ds.has_ground_truth else 'no'}")
    return 0
