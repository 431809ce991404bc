"""The ROS package is built by colcon (ament_python), not pip-installed into the venv: its tests import it
from the source tree, as the node processes they start do (PYTHONPATH)."""

import os
import random
import sys
from pathlib import Path

import pytest

ROS_PACKAGE_ROOT = Path(__file__).resolve().parents[2] / "src" / "neb_slam_ros"
if str(ROS_PACKAGE_ROOT) not in sys.path:
    sys.path.insert(0, str(ROS_PACKAGE_ROOT))


def _private_domain_env() -> dict[str, str]:
    """This process's environment on a private random ROS domain, discovery limited to this machine."""
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(random.SystemRandom().randint(1, 200))
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["PYTHONUNBUFFERED"] = "1"
    return env


@pytest.fixture(scope="module")
def ros_domain_env() -> dict[str, str]:
    """A private ROS domain for the processes a test module starts (their own imports: installed nodes)."""
    return _private_domain_env()


@pytest.fixture(scope="module")
def ros_env() -> dict[str, str]:
    """A private ROS domain, with the node modules importable from the source tree (``python -m``)."""
    env = _private_domain_env()
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROS_PACKAGE_ROOT), env.get("PYTHONPATH", "")) if p)
    # a node process that crashes in native code prints every thread's Python stack into the output the
    # tests quote (a loop_closer ended with SIGSEGV after its last log line in 2 of about 40 runs)
    env["PYTHONFAULTHANDLER"] = "1"
    return env
