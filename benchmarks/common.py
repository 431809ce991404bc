"""Pieces shared by the benchmark scripts (run as scripts: this folder is on ``sys.path``)."""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

REPO = Path(__file__).resolve().parents[1]
TUM = Path(os.environ.get("NEB_SLAM_SHARED_DATA", REPO.parent / "shared" / "data")) / "tum_fr1_xyz_300"


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


def report(figures: dict, json_path: Path | None) -> None:
    """Print the figures as JSON, and write them to ``json_path`` when given."""
    text = json.dumps(figures, indent=2)
    print(text)
    if json_path:
        Path(json_path).write_text(text + "\n")


def fitted_tum_map(cfg, fit_frames: int, fit_iterations: int, later_frames: int, rng: np.random.Generator):
    """A block map fitted with ground-truth poses to TUM frames 0, 2, 4, ... (``fit_frames`` of them, the
    config's mapping rays for ``fit_iterations``), and the ``later_frames`` rectified frames after them.
    Exits with a message when the TUM frames of ``../shared/data`` are absent."""
    import torch

    from neb_slam_core.datasets import open_dataset
    from neb_slam_core.geometry.rectify import Rectifier
    from neb_slam_core.mapping.fit import FitConfig, FrameRayPool, allocate_blocks, fit_map
    from neb_slam_core.slam import new_block_map

    if not TUM.is_dir():
        sys.exit(f"{TUM} not found: this benchmark needs the TUM frames of ../shared/data")
    torch.manual_seed(cfg.seed)
    rectify = Rectifier()
    ds = open_dataset(TUM)
    usable = [i for i in range(len(ds)) if ds[i].T_world_cam is not None]
    fit = [rectify(ds[i]) for i in usable[:2 * fit_frames:2]]
    later = [rectify(ds[i]) for i in usable[2 * fit_frames:2 * fit_frames + later_frames]]
    s = cfg.render.sampling
    block_map = new_block_map(cfg)
    allocate_blocks(block_map, fit, [f.T_world_cam for f in fit], s.near_m, s.far_m, rng)
    fit_map(block_map, FrameRayPool(fit, [f.T_world_cam for f in fit]), cfg.render,
            FitConfig(iterations=fit_iterations, rays_per_iteration=cfg.mapping.n_rays), seed=cfg.seed,
            progress=True)
    return block_map, later
