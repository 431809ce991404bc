"""Build the ROS 2 interface packages of interfaces/ that this Python environment lacks into it.

The nodes publish ``/tf`` (tf2_msgs/TFMessage), and the Jazzy PyPI wheels that ``make venv`` installs do
not include tf2_msgs. Where ``import tf2_msgs`` fails, this generates and compiles interfaces/tf2_msgs
with the rosidl/ament_cmake wheels and installs it into the environment's prefix (``sys.prefix``: its
Python package into site-packages, its libraries into lib/, which the ROS wheels put on the library
path). Where tf2_msgs comes from elsewhere (a sourced ROS 2 installation) nothing is built.

    python tools/build_interfaces.py            # what `make venv` runs
    python tools/build_interfaces.py --force    # rebuild even when tf2_msgs imports
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("tf2_msgs",)


def provider(package: str) -> Path | None:
    """Folder of the importable ``package``, or None when it does not import."""
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(next(iter(spec.submodule_search_locations))).resolve()


def ours(location: Path) -> bool:
    """Whether ``location`` is inside this environment (built here before), not a ROS installation."""
    return Path(sys.prefix).resolve() in location.parents


def build(package: str, jobs: int) -> None:
    prefix = Path(sys.prefix)
    source = REPO / "interfaces" / package
    build_dir = prefix / "build" / package
    env = dict(os.environ)
    env["AMENT_PREFIX_PATH"] = os.pathsep.join(p for p in (str(prefix), env.get("AMENT_PREFIX_PATH", "")) if p)
    env["CMAKE_PREFIX_PATH"] = os.pathsep.join(p for p in (str(prefix), env.get("CMAKE_PREFIX_PATH", "")) if p)
    steps = [
        [
            "cmake",
            "-S",
            str(source),
            "-B",
            str(build_dir),
            f"-DCMAKE_INSTALL_PREFIX={prefix}",
            f"-DPython3_EXECUTABLE={sys.executable}",
            "-DBUILD_TESTING=OFF",
        ],
        ["cmake", "--build", str(build_dir), "--parallel", str(jobs)],
        ["cmake", "--install", str(build_dir)],
    ]
    for cmd in steps:
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
        if proc.returncode != 0:
            sys.exit(
                f"building {package} from {source} failed at `{' '.join(cmd[:2])}`:\n"
                f"{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
            )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--force", action="store_true", help="rebuild even when the package imports")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="parallel compile jobs")
    args = parser.parse_args(argv)
    for package in PACKAGES:
        found = provider(package)
        if found is not None and not ours(found) and not args.force:
            print(f"{package}: using {found}")
            continue
        if shutil.which("cmake") is None:
            sys.exit(f"{package} is not installed and cmake is not on PATH to build it (install cmake)")
        build(package, args.jobs)
        print(f"{package}: built from interfaces/{package} into {sys.prefix}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
