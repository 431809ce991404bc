"""Pieces shared by the benchmark scripts (run as scripts: this folder is on ``sys.path``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation


def predicted_start(T_world_cam: np.ndarray) -> np.ndarray:
    """A pose 1 cm and 0.5 degree off ``T_world_cam``, as a constant-velocity prediction would be."""
    T = np.array(T_world_cam, dtype=np.float64)
    T[:3, :3] = Rotation.from_rotvec(np.radians(0.5) * np.array([0.6, 0.0, 0.8])).as_matrix() @ T[:3, :3]
    T[:3, 3] += np.array([0.006, -0.006, 0.0057])
    return T


def report(figures: dict, json_path: Path | None) -> None:
    """Print the figures as JSON, and write them to ``json_path`` when given."""
    text = json.dumps(figures, indent=2)
    print(text)
    if json_path:
        Path(json_path).write_text(text + "\n")
