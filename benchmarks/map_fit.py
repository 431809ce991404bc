"""Fit the neural block map alone to a synthetic scene with ground-truth poses, and measure it.

Generates (once, cached under .cache/scenes/) a synthetic preset and maps every ``--train-stride``-th
frame at its ground-truth pose with the engine's own steps (:class:`~neb_slam_core.slam.KnownPoseMapping`):
blocks allocated by the paper's tau rule, each frame a keyframe keeping ``--pixel-fraction`` of its
pixels, then ``--iterations`` mapping steps (N_m = ``--rays`` rays from all keyframes plus N_a from the
newest block's) with the poses held. Then it reports:

- blocks allocated and parameter MB (blocks x per-block grid + decoders);
- rendered depth L1 on held-out frames (frames between the training ones);
- mesh accuracy, completion and completion ratio (5 cm) against the scene's ground-truth mesh, both
  culled to what the training cameras saw;
- depth continuity across block seams (see neb_slam_core.eval.seams): max and 99th percentile of the
  step error at seam crossings, and the 99th percentile elsewhere for reference;
- fitting time per iteration.

Example::

    .venv/bin/python benchmarks/map_fit.py --preset default --iterations 1000 --json fit.json
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import trimesh
from common import record

from neb_slam_core.config import (
    BlockConfig,
    KeyframeConfig,
    MappingConfig,
    MeshConfig,
    RenderConfig,
    SamplingConfig,
    SlamConfig,
)
from neb_slam_core.datasets import open_dataset
from neb_slam_core.eval.recon import DepthL1Config, ReconConfig, evaluate_reconstruction
from neb_slam_core.eval.seams import seam_step_errors
from neb_slam_core.geometry.rays import backproject_depth
from neb_slam_core.mesh import extract_mesh
from neb_slam_core.render.images import render_depth_image
from neb_slam_core.slam import KnownPoseMapping
from neb_slam_core.synth.generate import generate

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="default", help="synthetic preset (small, default, large, corridor)")
    p.add_argument("--iterations", type=int, default=1000)
    p.add_argument("--rays", type=int, default=2048, help="rays per iteration from all keyframes (N_m)")
    p.add_argument(
        "--pixel-fraction",
        type=float,
        default=1.0,
        help="share of each training frame's pixels its keyframe keeps (1: all of them)",
    )
    p.add_argument("--train-stride", type=int, default=3, help="train on every n-th frame")
    p.add_argument("--held-out", type=int, default=10, help="held-out frames to render")
    p.add_argument("--truncation", type=float, default=0.05, help="truncation distance tr (m)")
    p.add_argument("--log2-table", type=int, default=15, help="hash table size per level (15 or 14)")
    p.add_argument("--voxel", type=float, default=0.02, help="mesh voxel size (m)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", type=Path, default=None, help="a copy of the stamped figures (see benchmarks/results/)")
    args = p.parse_args()

    scene = generate(args.preset, REPO / ".cache" / "scenes" / args.preset, progress=True)
    ds = open_dataset(scene)
    frames = [ds[i] for i in range(len(ds))]
    train = frames[:: args.train_stride]
    candidates = [f for i, f in enumerate(frames) if i % args.train_stride]
    held_out = [candidates[i] for i in np.linspace(0, len(candidates) - 1, args.held_out).round().astype(int)]
    poses = [f.T_world_cam for f in train]
    render = RenderConfig(truncation_m=args.truncation, sampling=SamplingConfig(far_m=6.0))
    block_cfg = BlockConfig()
    block_cfg = BlockConfig(grid=type(block_cfg.grid)(log2_hashmap_size=args.log2_table))
    cfg = SlamConfig(
        block=block_cfg,
        render=render,
        keyframes=KeyframeConfig(pixel_fraction=args.pixel_fraction),
        mapping=replace(MappingConfig(), n_rays=args.rays),
        seed=args.seed,
    )
    mapping = KnownPoseMapping(cfg)
    for f in train:
        mapping.add(f)
    block_map = mapping.block_map
    print(
        f"{args.preset}: {len(frames)} frames {frames[0].intrinsics.width}x{frames[0].intrinsics.height}, "
        f"training on {len(train)}, {len(block_map)} blocks allocated"
    )

    t0 = time.perf_counter()
    history = mapping.optimise(args.iterations, progress=True)
    fit_s = time.perf_counter() - t0

    centres = block_map.centres().numpy().astype(np.float64)
    l1, seam, elsewhere = [], [], []
    for f in held_out:
        depth, _ = render_depth_image(block_map, f, f.T_world_cam, render)
        ok = (f.depth_m > 0) & (depth > 0)
        l1.append(float(np.abs(depth[ok] - f.depth_m[ok]).mean()))
        steps = seam_step_errors(depth, f.depth_m, f.T_world_cam, f.intrinsics, centres, block_cfg.edge_m)
        seam.append(steps.seam)
        elsewhere.append(steps.elsewhere)
    seam_a, else_a = np.concatenate(seam), np.concatenate(elsewhere)

    t0 = time.perf_counter()
    observed = np.concatenate([backproject_depth(f.depth_m, f.intrinsics, f.T_world_cam, stride=2) for f in train])
    mesh = extract_mesh(block_map, MeshConfig(voxel_size_m=args.voxel), observed, progress=True)
    mesh_s = time.perf_counter() - t0
    gt = trimesh.load(scene / "mesh.ply", process=False)
    recon = evaluate_reconstruction(
        mesh, gt, ReconConfig(depth_l1=DepthL1Config(n_views=0)), np.stack(poses), train[0].intrinsics, progress=False
    )

    per_block = block_map.blocks[0].grid.param_bytes / 1e6
    decoders = block_map.decoder_param_bytes() / 1e6
    figures = {
        "preset": args.preset,
        "n_blocks": len(block_map),
        "block_mb": per_block,
        "decoder_mb": decoders,
        "param_mb": block_map.param_mb(),
        "iterations": args.iterations,
        "fit_s_per_iteration": fit_s / args.iterations,
        "final_loss": float(np.mean(history[-20:])),
        "held_out_depth_l1_cm": 100 * float(np.mean(l1)),
        "accuracy_cm": recon.accuracy_cm,
        "completion_cm": recon.completion_cm,
        "completion_ratio_pct": recon.completion_ratio_pct,
        "seam_pairs": int(seam_a.size),
        "seam_step_max_cm": 100 * float(seam_a.max()) if seam_a.size else None,
        "seam_step_p99_cm": 100 * float(np.percentile(seam_a, 99)) if seam_a.size else None,
        "other_step_p99_cm": 100 * float(np.percentile(else_a, 99)) if else_a.size else None,
        "mesh_s": mesh_s,
        "load_average": os.getloadavg()[0],
    }
    print()
    print(f"blocks allocated        {figures['n_blocks']}")
    print(
        f"parameters              {figures['param_mb']:.3f} MB = {figures['n_blocks']} x {per_block:.3f} MB "
        f"+ decoders {decoders:.3f} MB"
    )
    print(f"held-out depth L1       {figures['held_out_depth_l1_cm']:.2f} cm ({len(held_out)} views)")
    print(f"mesh accuracy           {recon.accuracy_cm:.2f} cm")
    print(f"mesh completion         {recon.completion_cm:.2f} cm")
    print(f"completion ratio (5 cm) {recon.completion_ratio_pct:.1f} %")
    if seam_a.size:
        print(
            f"seam step error         max {figures['seam_step_max_cm']:.2f} cm, "
            f"p99 {figures['seam_step_p99_cm']:.2f} cm "
            f"over {seam_a.size} seam pairs (elsewhere p99 {figures['other_step_p99_cm']:.2f} cm)"
        )
    else:
        print("seam step error         no seam crossings seen in the held-out views")
    print(
        f"fitting                 {1e3 * figures['fit_s_per_iteration']:.0f} ms / iteration of {args.rays} + "
        f"{cfg.mapping.n_rays_newest_block} rays "
        f"(load average {figures['load_average']:.1f})"
    )
    record(f"map_fit-{args.preset}", figures, args.json)


if __name__ == "__main__":
    main()
