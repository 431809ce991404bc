"""The reference for ``benchmarks/ros_outputs.py``: the ``mesh`` and ``path`` outputs as they were at commit
:data:`REFERENCE_COMMIT`, read from git and run unchanged beside the current code.

At that commit ``path`` was rebuilt from the whole trajectory after every frame, one PoseStamped per
pose (``PoseOutputs.publish_path``), and ``mesh`` re-extracted every block on each period and built one
Point and one ColorRGBA per triangle corner (``MapOutputs.publish``). :func:`load` executes those files'
own source (``git show COMMIT:PATH``) as modules of their package, so their relative imports resolve;
the outputs module is then bound to the reference conversions.
"""

from __future__ import annotations

import subprocess
import types
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: the last commit before ``mesh`` and ``path`` were made incremental
REFERENCE_COMMIT = "5a6aab1"


def _module(path: str, name: str, package: str) -> types.ModuleType:
    """The file ``path`` of :data:`REFERENCE_COMMIT`, executed as module ``name`` of ``package``."""
    try:
        done = subprocess.run(
            ["git", "show", f"{REFERENCE_COMMIT}:{path}"], cwd=REPO, capture_output=True, text=True, check=True
        )
    except (OSError, subprocess.CalledProcessError) as exc:
        missing = f"{REFERENCE_COMMIT}:{path}"
        raise SystemExit(f"the reference needs the git history of this checkout ({missing}): {exc}") from None
    module = types.ModuleType(name)
    module.__package__ = package
    module.__file__ = f"{REFERENCE_COMMIT}:{path}"
    exec(compile(done.stdout, module.__file__, "exec"), module.__dict__)
    return module


def load() -> types.SimpleNamespace:
    """The reference modules: ``mesh`` (``neb_slam_core/mesh.py``), ``conversions`` and ``outputs``
    (``neb_slam_ros``), the last using the reference ``conversions``."""
    mesh = _module("src/neb_slam_core/neb_slam_core/mesh.py", "neb_slam_core.reference_mesh", "neb_slam_core")
    conversions = _module(
        "src/neb_slam_ros/neb_slam_ros/conversions.py", "neb_slam_ros.reference_conversions", "neb_slam_ros"
    )
    outputs = _module("src/neb_slam_ros/neb_slam_ros/outputs.py", "neb_slam_ros.reference_outputs", "neb_slam_ros")
    outputs.conversions = conversions
    return types.SimpleNamespace(mesh=mesh, conversions=conversions, outputs=outputs, commit=REFERENCE_COMMIT)
