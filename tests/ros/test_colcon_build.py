"""The ROS 2 workspace: colcon builds both packages, and the node executables start and stop cleanly.

The build goes to a temporary folder (never the repo's build/ install/ log/). Every process of this file
talks on its own random ROS_DOMAIN_ID and on localhost only, so parallel sessions do not see each other.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest

pytestmark = [pytest.mark.ros, pytest.mark.filterwarnings("ignore::DeprecationWarning:lark.*")]

REPO = Path(__file__).resolve().parents[2]
NODES = ("tracker", "mapper", "loop_closer", "bag_replay", "slam")
COLCON = Path(sys.executable).parent / "colcon"
START_TIMEOUT_S = 30.0
STOP_TIMEOUT_S = 15.0


def _start_line(node: str) -> str:
    return f"neb_slam {node} started"


@pytest.fixture(scope="module")
def install_base(tmp_path_factory: pytest.TempPathFactory, ros_domain_env: dict[str, str]) -> Path:
    """Runs ``colcon build`` of the repo's src/ into a temporary build/install/log; returns install/."""
    if not COLCON.is_file():
        pytest.skip(f"colcon is not installed beside {sys.executable} (pip install -r requirements.txt)")
    base = tmp_path_factory.mktemp("colcon")
    env = dict(ros_domain_env, COLCON_HOME=str(base / "colcon_home"))  # ignore a user's ~/.colcon defaults
    cmd = [
        str(COLCON),
        "--log-base",
        str(base / "log"),
        "build",
        "--base-paths",
        str(REPO / "src"),
        "--build-base",
        str(base / "build"),
        "--install-base",
        str(base / "install"),
    ]
    # cwd is the repo so that colcon reads its colcon.meta, as `make build` does
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, f"colcon build failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return base / "install"


def _wait_until(predicate: Callable[[], bool], timeout_s: float) -> bool:
    """Polls ``predicate`` every 0.1 s (DDS discovery runs in its own threads) until true or timeout."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.1)
    return True


class _NodeProcess:
    """A node subprocess whose stderr (where rclpy logs) is collected by a thread."""

    def __init__(self, cmd: list[str], env: dict[str, str]):
        self.proc = subprocess.Popen(
            cmd, env=env, cwd=REPO, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        self.stderr_lines: list[str] = []
        self.stdout = ""
        self._wanted: str | None = None
        self._seen = threading.Event()
        self._stderr_thread = threading.Thread(target=self._read_stderr, daemon=True)
        self._stdout_thread = threading.Thread(target=self._read_stdout, daemon=True)
        self._stderr_thread.start()
        self._stdout_thread.start()

    def _read_stderr(self) -> None:
        for line in self.proc.stderr:
            self.stderr_lines.append(line)
            if self._wanted is not None and self._wanted in line:
                self._seen.set()

    def _read_stdout(self) -> None:
        self.stdout = self.proc.stdout.read()

    def wait_for(self, text: str, timeout_s: float) -> bool:
        self._wanted = text
        if any(text in line for line in list(self.stderr_lines)):
            return True
        return self._seen.wait(timeout_s)

    def stop(self, sig: int) -> int:
        """Sends ``sig``, waits for the exit and the end of its output; returns the exit status."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            rc = self.proc.wait(timeout=STOP_TIMEOUT_S)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait()
        self._stderr_thread.join(5)
        self._stdout_thread.join(5)
        return rc

    @property
    def stderr(self) -> str:
        return "".join(self.stderr_lines)


def test_build_installs_the_five_node_executables(install_base: Path) -> None:
    lib = install_base / "neb_slam_ros" / "lib" / "neb_slam_ros"
    for node in NODES:
        exe = lib / node
        assert exe.is_file() and os.access(exe, os.X_OK), f"{exe} missing or not executable"
        shebang = exe.read_text().splitlines()[0]
        # the scripts run with the interpreter colcon ran from: the venv that has rclpy and torch
        assert shebang.startswith("#!") and Path(shebang[2:].strip()).parent == Path(sys.executable).parent, shebang
    # what `ros2 run` / `ros2 pkg` need to find the package
    assert (install_base / "neb_slam_ros/share/ament_index/resource_index/packages/neb_slam_ros").is_file()
    assert (install_base / "neb_slam_ros/share/neb_slam_ros/package.xml").is_file()
    # what `ros2 launch neb_slam_ros <file>` and the launch files' $(find-pkg-share neb_slam_ros) find
    share = install_base / "neb_slam_ros/share/neb_slam_ros"
    for name in ("launch/slam.launch.xml", "launch/suite.launch.xml", "config/neb_slam.yaml", "rviz/neb_slam.rviz"):
        assert (share / name).read_bytes() == (REPO / "src/neb_slam_ros" / name).read_bytes(), name
    # the core is a colcon package too, with its console script
    assert (install_base / "neb_slam_core/bin/neb-slam").is_file()
    assert (install_base / "setup.bash").is_file() and (install_base / "local_setup.sh").is_file()


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_installed_tracker_starts_and_stops_cleanly(
    install_base: Path, ros_domain_env: dict[str, str], sig: int
) -> None:
    bash = shutil.which("bash")
    if bash is None:
        pytest.skip("bash not found: needed to source install/setup.bash")
    exe = install_base / "neb_slam_ros" / "lib" / "neb_slam_ros" / "tracker"
    # exactly what a user does: source the workspace, run the executable `ros2 run` would run;
    # exec keeps the pid, so the signal reaches the node itself
    script = f'source "{install_base / "setup.bash"}" && exec "{exe}"'
    node = _NodeProcess([bash, "-c", script], ros_domain_env)
    try:
        started = node.wait_for(_start_line("tracker"), START_TIMEOUT_S)
    finally:
        rc = node.stop(sig)
    assert started, f"no start line within {START_TIMEOUT_S} s; stderr:\n{node.stderr}"
    assert rc == 0, f"exit status {rc} after {sig.name}; stderr:\n{node.stderr}"
    assert "Traceback" not in node.stderr + node.stdout, node.stderr


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_installed_tracker_stopped_while_importing_exits_cleanly(
    install_base: Path, ros_domain_env: dict[str, str], sig: int
) -> None:
    """A stop 1.2 s after launch arrives while the node's module still imports torch, rclpy and the engine
    (those imports take seconds; sourcing the workspace and the entry point's own import take a fraction
    of one): status 0, one line, no traceback."""
    bash = shutil.which("bash")
    if bash is None:
        pytest.skip("bash not found: needed to source install/setup.bash")
    exe = install_base / "neb_slam_ros" / "lib" / "neb_slam_ros" / "tracker"
    node = _NodeProcess([bash, "-c", f'source "{install_base / "setup.bash"}" && exec "{exe}"'], ros_domain_env)
    time.sleep(1.2)
    rc = node.stop(sig)
    assert rc == 0, f"exit status {rc} after {sig.name}; stderr:\n{node.stderr}"
    assert "Traceback" not in node.stderr + node.stdout, node.stderr
    if _start_line("tracker") not in node.stderr:  # the usual case: the import was still running
        assert f"neb_slam tracker: stopped during start-up ({sig.name})" in node.stderr, node.stderr


def test_tracker_module_is_visible_in_the_ros_graph(
    ros_domain_env: dict[str, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    rclpy = pytest.importorskip("rclpy", reason="rclpy (ros-jazzy wheels) not installed")
    from rclpy.signals import SignalHandlerOptions

    env = dict(ros_domain_env)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO / "src" / "neb_slam_ros"), env.get("PYTHONPATH", "")) if p)
    node_proc = _NodeProcess([sys.executable, "-m", "neb_slam_ros.tracker"], env)

    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
        monkeypatch.setenv(key, ros_domain_env[key])
    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    observer = None
    try:
        observer = rclpy.create_node("graph_observer", context=context)

        def tracker_seen() -> bool:
            return ("tracker", "/neb_slam") in observer.get_node_names_and_namespaces()

        try:
            seen = _wait_until(tracker_seen, START_TIMEOUT_S)
        finally:
            rc = node_proc.stop(signal.SIGINT)
        assert seen, f"/neb_slam/tracker not in the graph; its stderr:\n{node_proc.stderr}"
        assert rc == 0 and "Traceback" not in node_proc.stderr, node_proc.stderr
        # a clean shutdown removes the node from the graph (its participant says goodbye)
        assert _wait_until(lambda: not tracker_seen(), STOP_TIMEOUT_S), "tracker still in the graph after exit"
    finally:
        if observer is not None:
            observer.destroy_node()
        rclpy.try_shutdown(context=context)
