"""What skipping the samples far behind the measured depth saves (``render.sampling.skip_behind_m``),
and that it changes nothing the engine relies on.

On TUM fr1_xyz (``../shared/data/tum_fr1_xyz_300``, ``tum`` config), in one run: a map fitted to
``--fit-frames`` frames with their ground-truth poses; then, on ``--frames`` later frames, with samples
skipped (the default, 0.3 m) and with every sample evaluated (0, the paper's way):

- a mapping step (the objective on the config's mapping rays at the true poses, and its backward pass):
  ``map_step_ms_skip``, ``map_step_ms_all`` and their ratio; the objective's largest relative difference
  between the two (``objective_rel_diff``); the share of samples evaluated (``evaluated_share``);
- tracking each frame from a pose 1 cm and 0.5 degree off: ``track_ms_skip``, ``track_ms_all`` and their
  ratio, the poses' distance to the ground truth both ways (``track_error_mm_*``) and to each other.

Timings are medians over ``--repeats`` passes, both settings measured in the same run.

Example::

    .venv/bin/python benchmarks/sample_skip.py --json sample_skip.json
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from common import fitted_tum_map, load_figures, median_ms, predicted_start, report

from neb_slam_core.config_io import load_config
from neb_slam_core.render.rays import sample_pixels
from neb_slam_core.render.renderer import objective
from neb_slam_core.render.sampling import evaluated_samples, sample_depths
from neb_slam_core.tracking.tracker import Tracker


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--fit-frames", type=int, default=30, help="frames 0, 2, 4, ... the map is fitted to")
    p.add_argument("--fit-iterations", type=int, default=1000)
    p.add_argument("--frames", type=int, default=5)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--json", type=Path, default=None, help="a copy of the stamped figures (see benchmarks/results/)")
    args = p.parse_args()
    cfg = load_config("tum")
    rng = np.random.default_rng(cfg.seed)
    block_map, frames = fitted_tum_map(cfg, args.fit_frames, args.fit_iterations, args.frames, rng)
    skip_m = cfg.render.sampling.skip_behind_m
    render = {"skip": cfg.render, "all": replace(cfg.render, sampling=replace(cfg.render.sampling, skip_behind_m=0.0))}

    map_ms = {k: [] for k in render}
    rel_diff, shares = [], []
    for f in frames:
        px = sample_pixels(f, cfg.mapping.n_rays, rng, valid_depth_only=False)
        rays = px.to_world(torch.as_tensor(f.T_world_cam, dtype=torch.float32))
        z = sample_depths(px.depth_m, cfg.render.sampling, generator=torch.Generator().manual_seed(cfg.seed))
        shares.append(float(evaluated_samples(z, px.depth_m, skip_m).float().mean()))
        values = {}
        for key, rc in render.items():

            def step(rc=rc):
                block_map.zero_grad(set_to_none=True)
                loss, _ = objective(block_map, rays, rc, None, generator=torch.Generator().manual_seed(1), z=z)
                loss.total.backward()
                return float(loss.total.detach())

            values[key] = step()
            map_ms[key].append(median_ms(step, args.repeats))
        rel_diff.append(abs(values["skip"] - values["all"]) / abs(values["all"]))
    block_map.zero_grad(set_to_none=True)

    track_ms = {k: [] for k in render}
    error_mm = {k: [] for k in render}
    steps = {k: [] for k in render}
    poses = {k: [] for k in render}
    for f in frames:
        start = predicted_start(f.T_world_cam)
        for key, rc in render.items():
            results = []
            track_ms[key].append(
                median_ms(
                    lambda rc=rc: results.append(Tracker(cfg.tracking, rc, seed=cfg.seed).track(block_map, f, start)),
                    args.repeats,
                )
            )
            result = results[-1]
            steps[key].append(result.iterations)
            poses[key].append(result.T_world_cam)
            error_mm[key].append(1e3 * float(np.linalg.norm(result.T_world_cam[:3, 3] - f.T_world_cam[:3, 3])))
    gap_mm = [1e3 * float(np.linalg.norm(a[:3, 3] - b[:3, 3])) for a, b in zip(poses["skip"], poses["all"])]

    med = {k: float(np.median(v)) for k, v in map_ms.items()}
    trk = {k: float(np.median(v)) for k, v in track_ms.items()}
    figures = {
        "skip_behind_m": skip_m,
        "evaluated_share": round(float(np.mean(shares)), 3),
        "map_step_ms_skip": round(med["skip"], 1),
        "map_step_ms_all": round(med["all"], 1),
        "map_step_ratio": round(med["all"] / med["skip"], 2),
        "objective_rel_diff": float(f"{max(rel_diff):.2e}"),
        "track_ms_skip": round(trk["skip"], 1),
        "track_ms_all": round(trk["all"], 1),
        "track_ratio": round(trk["all"] / trk["skip"], 2),
        "track_steps_skip": steps["skip"],
        "track_steps_all": steps["all"],
        "track_error_mm_skip": [round(e, 2) for e in error_mm["skip"]],
        "track_error_mm_all": [round(e, 2) for e in error_mm["all"]],
        "pose_gap_mm": [round(g, 3) for g in gap_mm],
        "mapping_rays": cfg.mapping.n_rays,
        **load_figures(),
    }
    print(
        f"mapping step {figures['map_step_ms_skip']} ms skipping, {figures['map_step_ms_all']} ms with every "
        f"sample (x{figures['map_step_ratio']}); tracking {figures['track_ms_skip']} against "
        f"{figures['track_ms_all']} ms per frame (x{figures['track_ratio']})"
    )
    report(figures, args.json, "sample_skip")


if __name__ == "__main__":
    main()
