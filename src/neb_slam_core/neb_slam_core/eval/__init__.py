"""Evaluation (the protocol: docs/evaluation.md): trajectory accuracy (ATE, RPE), reconstruction metrics,
plots, and the report of a run.

- :mod:`.trajectory_metrics`: association by stamp, rigid Horn/Umeyama alignment, ATE, RPE.
- :mod:`.recon`: accuracy, completion, completion ratio, culling to the cameras' view, Depth L1.
- :mod:`.raycast`: Embree ray casting (first hits, depth images) used by :mod:`.recon`.
- :mod:`.plots`: trajectory and error figures (import it explicitly; it pulls in matplotlib).
- :mod:`.report`: the JSON-ready figures and standard plots of ``neb-slam eval``.
- :mod:`.run_report`: a run's metrics, plots, mesh and its evaluation, written into the run directory.
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
