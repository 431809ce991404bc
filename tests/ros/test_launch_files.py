"""The package's launch files, params file and RViz view against the nodes they name.

``ros2 launch`` is not available as a wheel, so the launch files are not run here. What is checked: the
XML is what the launch front end reads (only the substitutions ``$(var ...)`` and ``$(find-pkg-share
neb_slam_ros)``; every argument used is declared); every node is one of the package's executables; each
is started as the launch file would start it (its parameters, the params file, its remaps and namespace)
and then asked over DDS for its parameters (every one the files set is declared, with the value they set)
and its topics (every remap moved a topic the node really has); every topic of the RViz view is one the
nodes publish, with the publisher's durability.
"""

from __future__ import annotations

import re
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import yaml

pytestmark = [pytest.mark.ros, pytest.mark.filterwarnings("ignore::DeprecationWarning:lark.*")]

REPO = Path(__file__).resolve().parents[2]
PACKAGE = REPO / "src" / "neb_slam_ros"
LAUNCH_FILES = sorted((PACKAGE / "launch").glob("*.launch.xml"))
START_TIMEOUT_S = 60.0


def _substitute(text: str, args: dict[str, str]) -> str:
    """The launch front end's substitutions the files may use; anything else fails the test."""

    def one(m: re.Match) -> str:
        kind, _, value = m.group(1).partition(" ")
        if kind == "var":
            assert value in args, f"$(var {value}) without an <arg name={value!r}>"
            return args[value]
        assert (kind, value) == ("find-pkg-share", "neb_slam_ros"), f"unexpected substitution $({m.group(1)})"
        return str(PACKAGE)  # the installed share/neb_slam_ros has the same layout (setup.py data_files)

    return re.sub(r"\$\(([^)]*)\)", one, text)


def _nodes(launch: Path) -> list[dict]:
    """The launch file's nodes with their arguments at their defaults: pkg, exec, name, namespace,
    condition, params (name -> value), params files, remaps (from -> to), args."""
    root = ET.parse(launch).getroot()
    assert root.tag == "launch"
    args = {}
    for a in root.findall("arg"):
        assert a.get("description"), f"{launch.name}: argument {a.get('name')} has no description"
        args[a.get("name")] = _substitute(a.get("default", ""), args)  # defaults may use earlier ones
    out = []
    for n in root.findall("node"):
        sub = {k: _substitute(v, args) for k, v in n.attrib.items()}
        out.append(
            {
                **sub,
                "params": {
                    p.get("name"): _substitute(p.get("value"), args) for p in n.findall("param") if p.get("name")
                },
                "param_files": [_substitute(p.get("from"), args) for p in n.findall("param") if p.get("from")],
                "remaps": {r.get("from"): _substitute(r.get("to"), args) for r in n.findall("remap")},
            }
        )
    return out


def _typed(value: str):
    """A launch parameter's text as the launch front end types it (YAML rules)."""
    return yaml.safe_load(value) if value != "" else ""


@pytest.mark.parametrize("launch", LAUNCH_FILES, ids=[p.name for p in LAUNCH_FILES])
def test_a_launch_file_names_only_the_packages_executables_and_existing_files(launch):
    from neb_slam_ros._launch import NODES  # the executables setup.py installs

    nodes = _nodes(launch)
    ours = [n for n in nodes if n["pkg"] == "neb_slam_ros"]
    assert ours
    for n in ours:
        assert n["exec"] in NODES and n["name"] == n["exec"], n
        for f in n["param_files"]:
            assert Path(f).is_file(), f
    for n in nodes:
        if n["pkg"] == "rviz2":
            view = n["args"].split("-d ", 1)[1].strip()
            assert Path(view).is_file(), view


def _start(node: dict, env: dict[str, str], log: Path) -> subprocess.Popen:
    cmd = [sys.executable, "-m", f"neb_slam_ros.{node['exec']}", "--ros-args", "-r", f"__ns:=/{node['namespace']}"]
    for f in node["param_files"]:
        cmd += ["--params-file", f]
    for name, value in node["params"].items():
        cmd += ["-p", f"{name}:={value}" if value != "" else f"{name}:=''"]
    for a, b in node["remaps"].items():
        cmd += ["-r", f"{a}:={b}"]
    return subprocess.Popen(cmd, env=env, cwd=REPO, stdout=subprocess.DEVNULL, stderr=log.open("w"))


def _params_file_values(path: str, node_name: str) -> dict:
    """The values the params file gives ``node_name`` (its ``/**/<name>`` section), dotted names flat."""
    data = yaml.safe_load(Path(path).read_text())
    section = data.get(f"/**/{node_name}", {}).get("ros__parameters", {})

    def flat(tree, prefix=""):
        for k, v in tree.items():
            if isinstance(v, dict):
                yield from flat(v, f"{prefix}{k}.")
            else:
                yield f"{prefix}{k}", v

    return dict(flat(section))


def test_every_parameter_and_remap_of_the_launch_files_reaches_a_running_node(ros_env, monkeypatch, tmp_path):
    rclpy = pytest.importorskip("rclpy")
    from rcl_interfaces.srv import GetParameters
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import NodeNameNonExistentError
    from rclpy.parameter import parameter_value_to_python

    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
        monkeypatch.setenv(key, ros_env[key])
    plan = {}  # (namespace, name) -> node: every distinct node of every launch file
    for launch in LAUNCH_FILES:
        for n in _nodes(launch):
            if n["pkg"] == "neb_slam_ros":
                plan[(n["namespace"], n["name"])] = n
    logs = {key: tmp_path / f"{key[1]}.log" for key in plan}
    procs = {key: _start(n, ros_env, logs[key]) for key, n in plan.items()}
    context = rclpy.Context()
    rclpy.init(context=context)
    probe = rclpy.create_node("launch_probe", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(probe)
    try:
        for (ns, name), n in plan.items():
            expected = {k: _typed(v) for k, v in n["params"].items()}
            for f in n["param_files"]:
                expected = {**_params_file_values(f, name), **expected}
            client = probe.create_client(GetParameters, f"/{ns}/{name}/get_parameters")
            assert client.wait_for_service(START_TIMEOUT_S), (name, logs[(ns, name)].read_text())
            for key, want in expected.items():  # one by one: a request naming an undeclared one gets nothing
                future = client.call_async(GetParameters.Request(names=[key]))
                executor.spin_until_future_complete(future, timeout_sec=30.0)
                values = future.result().values
                assert len(values) == 1, f"{name}: parameter {key} is not declared"
                got = parameter_value_to_python(values[0])
                got = list(got) if isinstance(got, (list, tuple)) or hasattr(got, "tolist") else got
                assert got == (list(want) if isinstance(want, (list, tuple)) else want), (name, key, got, want)
            # every remap moved one of the node's topics: the target is among its subscriptions
            deadline = time.monotonic() + START_TIMEOUT_S
            while True:
                try:
                    subs = {t for t, _ in probe.get_subscriber_names_and_types_by_node(name, f"/{ns}")}
                except NodeNameNonExistentError:  # not discovered by the probe yet
                    subs = set()
                if set(n["remaps"].values()) <= subs or time.monotonic() > deadline:
                    break
                time.sleep(0.2)
            assert set(n["remaps"].values()) <= subs, (name, n["remaps"], subs, logs[(ns, name)].read_text())
            if name == "slam":
                _check_rviz_view(probe, ns, name)
    finally:
        probe.destroy_node()
        rclpy.try_shutdown(context=context)
        for p in procs.values():
            p.send_signal(2)
        for p in procs.values():
            try:
                p.wait(60)
            except subprocess.TimeoutExpired:
                p.kill()


def _check_rviz_view(probe, ns: str, name: str) -> None:
    """The RViz view's fixed frame is the map and each of its topics is one ``name`` publishes, with the
    publisher's durability (a transient-local display of a volatile topic would show nothing)."""
    from rclpy.qos import DurabilityPolicy

    view = yaml.safe_load((PACKAGE / "rviz" / "neb_slam.rviz").read_text())
    manager = view["Visualization Manager"]
    assert manager["Global Options"]["Fixed Frame"] == "map"
    pubs = {}
    for info_topic, _ in probe.get_publisher_names_and_types_by_node(name, f"/{ns}"):
        infos = probe.get_publishers_info_by_topic(info_topic)
        pubs[info_topic] = {i.qos_profile.durability for i in infos if i.node_name == name}
    topics = [d["Topic"] for d in manager["Displays"] if "Topic" in d]
    assert topics
    for t in topics:
        assert t["Value"] in pubs, (t["Value"], sorted(pubs))
        durability = {
            "Transient Local": DurabilityPolicy.TRANSIENT_LOCAL,
            "Volatile": DurabilityPolicy.VOLATILE,
        }[t["Durability Policy"]]
        assert pubs[t["Value"]] == {durability}, (t["Value"], pubs[t["Value"]])
    assert any(d["Class"] == "rviz_default_plugins/TF" for d in manager["Displays"])
