"""The QoS profiles of the topic contract (docs/topics.md)."""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data


def camera(reliable: bool) -> QoSProfile:
    """Camera inputs: sensor-data QoS (best effort, shallow) by default; ``reliable`` for lossless replay."""
    if not reliable:
        return qos_profile_sensor_data
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=10,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


def events(depth: int = 100) -> QoSProfile:
    """Keyframes, map updates, loop closures: reliable, deep enough that none is lost."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


def keyframes(depth: int = 20) -> QoSProfile:
    """Keyframe parts: reliable, and transient local so that a mapper that subscribes late (discovery
    takes a moment) still receives the first keyframes."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


def state() -> QoSProfile:
    """Mesh, blocks, path: the latest state, kept for late subscribers (transient local)."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=1,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


def stream(depth: int = 100) -> QoSProfile:
    """Per-frame outputs (pose, odometry): reliable, volatile."""
    return events(depth)
