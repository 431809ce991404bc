"""ROS parameters generated from the core's config dataclasses: one source of truth for every node.

Each node declares ``config`` (a preset name such as ``tum``, or the path of a YAML config file) and then
one parameter per leaf of :class:`~neb_slam_core.config.SlamConfig`, named by its dotted key
(``tracking.n_rays``) with the preset's value as default. In a params file the dots are nesting::

    /neb_slam/tracker:
      ros__parameters:
        config: tum
        tracking:
          n_rays: 512

Values the user set are applied over the preset and the result is validated by the core
(:func:`neb_slam_core.config_io.load_config`), so a bad value fails at start with the parameter's name.
The nodes read their parameters once, at start: every one is declared read-only, so ``ros2 param set``
is refused ("parameter is read-only") instead of appearing to succeed.
Node options that are not engine configuration (topics, rates, folders) are small frozen dataclasses
declared the same way by :func:`declare_options`.
"""

from __future__ import annotations

import array
import dataclasses
from typing import Any, TypeVar

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node

from neb_slam_core.config import SlamConfig, config_to_dict
from neb_slam_core.config_io import load_config
from neb_slam_core.errors import ConfigError

T = TypeVar("T")


class ParameterError(Exception):
    """A node parameter is out of range or of the wrong type; the message names it."""

    def __init__(self, name: str, problem: str):
        self.name = name
        super().__init__(f"parameter {name}: {problem}")


def _flatten(tree: dict, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(_flatten(value, name + "."))
        else:
            out[name] = value
    return out


def declare_config(node: Node, default_preset: str = "base") -> SlamConfig:
    """Declare ``config`` and every engine parameter on ``node``; returns the validated config."""
    preset = node.declare_parameter(
        "config",
        default_preset,
        ParameterDescriptor(
            description="engine config: a preset (base, tum, scannet, replica, synthetic, small, "
            "ci) or a YAML file; the parameters below override it",
            read_only=True,
        ),
    ).value
    try:
        base = load_config(str(preset))
    except ConfigError as exc:
        raise ParameterError("config", str(exc)) from None
    defaults = _flatten(config_to_dict(base))
    overrides = {}
    for name, default in defaults.items():
        # dynamic typing: a params file may write 1 for 1.0; the core's validation checks types and ranges
        value = node.declare_parameter(
            name,
            default,
            ParameterDescriptor(
                dynamic_typing=True,
                description=f"engine config {name} (see neb_slam_core configs/base.yaml)",
                read_only=True,
            ),
        ).value
        if value != default:
            overrides[name] = value
    try:
        return load_config(str(preset), overrides)
    except ConfigError as exc:
        raise ParameterError(next((k for k in overrides if k in str(exc)), "config"), str(exc)) from None


def declare_options(node: Node, cls: type[T]) -> T:
    """Declare one parameter per field of the frozen dataclass ``cls`` (defaults and docs from it) and
    build it; the dataclass' ``check()`` (when it has one) validates the values."""
    docs = getattr(cls, "PARAMETER_DOCS", {})
    values = {}
    for f in dataclasses.fields(cls):
        default = f.default
        descriptor = ParameterDescriptor(description=docs.get(f.name, ""), dynamic_typing=True, read_only=True)
        value = node.declare_parameter(f.name, default, descriptor).value
        kind = type(default)
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if kind is tuple and isinstance(value, (list, tuple, array.array)):  # a number list: float64 values
            if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
                raise ParameterError(f.name, f"expected numbers, got {list(value)!r}")
            value = tuple(float(v) for v in value)
        if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
            raise ParameterError(f.name, f"expected a {kind.__name__}, got {value!r}")
        values[f.name] = value
    options = cls(**values)
    check = getattr(options, "check", None)
    if check is not None:
        check()
    return options


def map_parameter(cfg, map_file: str, name: str = "map_file"):
    """The checkpoint ``map_file`` for a node to continue (:func:`~neb_slam_core.slam.load_map_for`), or
    None when it is empty (the node starts an empty map); a file that cannot be continued is a bad
    parameter."""
    from neb_slam_core.errors import DatasetError
    from neb_slam_core.slam import load_map_for

    if not map_file:
        return None
    try:
        return load_map_for(cfg, map_file)
    except DatasetError as exc:
        raise ParameterError(name, str(exc)) from None


def require(condition: bool, name: str, expected: str, value: Any) -> None:
    """Raise :class:`ParameterError` for ``name`` unless ``condition``."""
    if not condition:
        raise ParameterError(name, f"expected {expected}, got {value!r}")
