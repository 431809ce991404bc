"""A stop that arrives while a node executable imports (``neb_slam_ros._launch``) ends it with status 0
and one line, whatever the import is doing when the signal lands."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

# a node module whose import receives the stop inside code that turns any exception raised there into
# ImportError, as a C extension's initialisation does (pybind11: "initialization failed")
NODE_MODULE = """
import os
import signal
import time

try:
    os.kill(os.getpid(), signal.{sig})
    time.sleep(5)  # the handler runs at the next bytecode boundary, within this sleep at the latest
except BaseException as exc:
    raise ImportError("initialization failed") from exc


def main():
    return 3
"""

RUNNER = """
import sys

import neb_slam_ros
from neb_slam_ros._launch import _run

neb_slam_ros.__path__.append(sys.argv[1])
sys.exit(_run("stopped_node"))
"""


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_stop_inside_an_extension_import_exits_cleanly(tmp_path: Path, sig: signal.Signals) -> None:
    (tmp_path / "stopped_node.py").write_text(NODE_MODULE.format(sig=sig.name))
    env = dict(
        os.environ, PYTHONPATH=os.pathsep.join([str(REPO / "src" / "neb_slam_ros"), os.environ.get("PYTHONPATH", "")])
    )
    done = subprocess.run(
        [sys.executable, "-c", RUNNER, str(tmp_path)], env=env, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr, done.stderr
    assert done.stderr.strip() == f"[INFO] neb_slam stopped_node: stopped during start-up ({sig.name})"
