"""Evaluation (the protocol: docs/evaluation.md): trajectory accuracy (ATE, RPE), reconstruction metrics,
plots.

- :mod:`.trajectory_metrics`: association by stamp, rigid Horn/Umeyama alignment, ATE, RPE.
- :mod:`.recon`: accuracy, completion, completion ratio, culling to the cameras' view, Depth L1.
- :mod:`.raycast`: Embree ray casting (first hits, depth images) used by :mod:`.recon`.
- :mod:`.plots`: trajectory and error figures (import it explicitly; it pulls in matplotlib).
"""

from .trajectory_metrics import (
    AteResult,
    RpeResult,
    TrajectoryPair,
    align_rigid,
    associate_trajectories,
    compute_ate,
    compute_rpe,
    evaluate_ate,
    evaluate_rpe,
)

__all__ = [
    "AteResult",
    "RpeResult",
    "TrajectoryPair",
    "align_rigid",
    "associate_trajectories",
    "compute_ate",
    "compute_rpe",
    "evaluate_ate",
    "evaluate_rpe",
]
