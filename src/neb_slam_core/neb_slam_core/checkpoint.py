"""Checkpoints of a running engine: everything needed to go on after a crash, a ``SIGKILL`` or a stop.

A checkpoint holds the whole deterministic engine (:class:`~neb_slam_core.slam.Slam`: the block map and
its optimiser's state, the keyframe store, every keyframe and frame pose, the loop closer's features,
inverted index, depth maps and registrations, the random generators), the run log of the frames
processed so far, torch's global random state and what the caller needs to go on (``resume``: for
``neb-slam run``, the input and the options). Restored, the engine continues exactly as the run that
wrote it would have: the same frames in give the same poses out.

The file (``checkpoint.pt`` in the run directory) is written to a temporary name, flushed to disk and
renamed over the previous one, so a kill at any moment leaves the last complete checkpoint readable. It
is a pickle (through ``torch.save``): load only checkpoints your own runs wrote.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from .errors import DatasetError

if TYPE_CHECKING:
    from .io.run_dir import RunLog
    from .slam import Slam

CHECKPOINT_FILE = "checkpoint.pt"
#: bumped when the checkpoint's content changes incompatibly
FORMAT_VERSION = 4


@dataclass
class Checkpoint:
    """One checkpoint (module docstring).

    Attributes:
        slam: the engine; run_log: the frames it processed, with their results.
        resume: what the caller needs to go on (plain values).
        torch_rng: torch's global random state when it was taken.
        wall_s: the run's wall time until then; saved_at: the Unix time it was written.
    """

    slam: Slam
    run_log: RunLog
    resume: dict = field(default_factory=dict)
    torch_rng: torch.Tensor | None = None
    wall_s: float = 0.0
    saved_at: float = 0.0
    version: int = FORMAT_VERSION


def save_checkpoint(path: str | Path, slam: Slam, run_log: RunLog, resume: dict | None = None, wall_s: float = 0.0):
    """Write a checkpoint of ``slam`` and ``run_log`` to ``path`` atomically (see the module docstring)."""
    ckpt = Checkpoint(slam, run_log, dict(resume or {}), torch.get_rng_state(), wall_s, time.time())
    return write_atomically(path, ckpt)


def write_atomically(path: str | Path, state: object) -> Path:
    """``torch.save`` ``state`` to ``path`` through a temporary file that is synced and renamed over it: a
    kill at any moment leaves either the previous file or the new one, whole."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("wb") as fh:
        torch.save(state, fh)
        fh.flush()
        os.fsync(fh.fileno())
    tmp.replace(path)
    try:  # the rename itself survives a power loss once the folder is synced
        fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError:
        pass
    return path


def read_state(path: str | Path, kind: type) -> object:
    """What :func:`write_atomically` wrote to ``path``, which must be a ``kind``; errors name the file."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "checkpoint not found")
    try:
        state = torch.load(path, weights_only=False)
    except Exception as exc:
        raise DatasetError(path, f"not a readable checkpoint ({type(exc).__name__}: {exc})") from None
    if not isinstance(state, kind):
        raise DatasetError(path, f"not a {kind.__name__} (holds a {type(state).__name__})")
    return state


def load_checkpoint(path: str | Path, restore_rng: bool = True) -> Checkpoint:
    """Read a checkpoint written by :func:`save_checkpoint`; with ``restore_rng`` torch's global random
    state is set back to the checkpoint's. Errors name the file."""
    path = Path(path)
    ckpt = read_state(path, Checkpoint)
    if ckpt.version != FORMAT_VERSION:
        raise DatasetError(path, f"checkpoint format {ckpt.version}; this version reads {FORMAT_VERSION}")
    if restore_rng and ckpt.torch_rng is not None:
        torch.set_rng_state(ckpt.torch_rng)
    return ckpt
