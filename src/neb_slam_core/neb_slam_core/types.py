"""Typed containers passed between the stages of the pipeline.

Conventions (docs/conventions.md): poses are camera-to-world ``T_world_cam`` 4x4 float64 with OpenCV
optical axes (x right, y down, z forward), metres; depth is float32 metres with 0 = invalid; colour is
uint8 RGB; time is integer nanoseconds.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of an image of ``width`` x ``height`` pixels."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def K(self) -> np.ndarray:
        """The 3x3 camera matrix (float64)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, width: int, height: int) -> Intrinsics:
        """The same camera for an image resized to ``width`` x ``height``."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, width, height)

    def as_tuple(self) -> tuple[float, float, float, float, int, int]:
        return (self.fx, self.fy, self.cx, self.cy, self.width, self.height)


#: :attr:`RgbdFrame.extras` keys of the colour and the depth image's capture times (ns)
COLOUR_STAMP, DEPTH_STAMP = "colour_stamp_ns", "depth_stamp_ns"


@dataclass
class RgbdFrame:
    """One RGB-D frame.

    Attributes:
        rgb: ``(H, W, 3)`` uint8 RGB.
        depth_m: ``(H, W)`` float32 depth in metres, 0 where invalid.
        intrinsics: the camera of both images (colour is registered to depth).
        stamp_ns: capture time in integer nanoseconds.
        T_world_cam: optional ground-truth camera-to-world pose, ``(4, 4)`` float64.
        index: position of the frame in its source sequence.
        extras: loader-specific data; ``extras["distortion"]`` holds the lens distortion of both images
            as OpenCV/ROS ``plumb_bob`` coefficients (k1, k2, p1, p2, k3) when the images are not
            rectified (TUM's freiburg cameras); the engine rectifies such frames on input.
            ``extras[COLOUR_STAMP]`` and ``extras[DEPTH_STAMP]`` hold the two images' own capture times
            (ns) where the sensor took them apart (TUM, bags, the nodes); ``stamp_ns`` is one of them.
    """

    rgb: np.ndarray
    depth_m: np.ndarray
    intrinsics: Intrinsics
    stamp_ns: int
    T_world_cam: np.ndarray | None = None
    index: int = 0
    extras: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        h, w = self.depth_m.shape[:2]
        if self.rgb.shape != (h, w, 3) or self.rgb.dtype != np.uint8:
            raise ValueError(
                f"RgbdFrame: rgb must be ({h}, {w}, 3) uint8 to match depth, got {self.rgb.shape} {self.rgb.dtype}"
            )
        if self.depth_m.dtype != np.float32 or self.depth_m.ndim != 2:
            raise ValueError(
                f"RgbdFrame: depth_m must be (H, W) float32, got {self.depth_m.shape} {self.depth_m.dtype}"
            )
        if (w, h) != (self.intrinsics.width, self.intrinsics.height):
            raise ValueError(
                f"RgbdFrame: image is {w}x{h} but intrinsics are for {self.intrinsics.width}x{self.intrinsics.height}"
            )

    @property
    def stamp_s(self) -> float:
        return self.stamp_ns * 1e-9


@dataclass(slots=True)  # one per frame in a run's log: no per-object dict
class StepTimings:
    """Milliseconds spent on one frame, by stage."""

    track_ms: float = 0.0
    allocate_ms: float = 0.0
    map_ms: float = 0.0
    loop_ms: float = 0.0
    total_ms: float = 0.0


@dataclass(frozen=True)
class LoopEvent:
    """A loop detected at keyframe ``query_id``, and what became of it.

    Attributes:
        query_id: the keyframe that closed the loop (the newest).
        loop_ids: its loop keyframes (``r1``, then ``r2`` when there is one).
        score: ``r1``'s similarity score.
        applied: the correction was applied.
        reason: why not ('' when applied).
        correction_cm, correction_deg: how far the fitted pose is from the query's pose before.
        rms_px_start, rms_px: the reprojection objective's RMS at the geometric check's pose and at the fit.
    """

    query_id: int
    loop_ids: tuple[int, ...]
    score: float
    applied: bool
    reason: str
    correction_cm: float
    correction_deg: float
    rms_px_start: float
    rms_px: float

    @property
    def start_id(self) -> int:
        """The loop's older end: keyframes up to it keep their poses."""
        return min(self.loop_ids)

    def as_dict(self) -> dict:
        return {
            "query_keyframe": self.query_id,
            "loop_keyframes": list(self.loop_ids),
            "score": self.score,
            "applied": self.applied,
            "reason": self.reason,
            "correction_cm": self.correction_cm,
            "correction_deg": self.correction_deg,
            "rms_px_start": self.rms_px_start,
            "rms_px": self.rms_px,
        }


@dataclass(slots=True)  # one per frame in a run's log: no per-object dict
class StepResult:
    """What :meth:`neb_slam_core.slam.Slam.process` did with one frame.

    Attributes:
        frame_index: position of the frame in the stream (0 = first).
        stamp_ns: the frame's stamp.
        T_world_cam: estimated pose (float64 4x4) at the time the frame was processed.
        is_keyframe: the frame became a keyframe.
        new_block_id: id of the block it allocated, or None.
        tau: the allocation ratio measured on it.
        tracking_ok: False when tracking failed and the pose is the motion prediction.
        failure_reason: why tracking failed ('' when it did not).
        mapped: a mapping (joint optimisation) step ran after this frame.
        n_blocks: blocks in the map after this frame.
        timings: per-stage times.
        loop: the loop detected at this keyframe (applied or not), or None.
        covariance: the tracked pose's covariance, 6x6 over (tx, ty, tz, rx, ry, rz) in the world frame
            (:func:`~neb_slam_core.tracking.gauss_newton.pose_covariance`, fused with the motion prior's
            with ``tracking.motion_prior_*``: :func:`~neb_slam_core.tracking.tracker.fuse`): zeros for the
            first frame of an empty map (it defines the frame), None when tracking failed or gave none.
    """

    frame_index: int
    stamp_ns: int
    T_world_cam: np.ndarray
    is_keyframe: bool = False
    new_block_id: int | None = None
    tau: float = 0.0
    tracking_ok: bool = True
    failure_reason: str = ""
    mapped: bool = False
    n_blocks: int = 0
    timings: StepTimings = field(default_factory=StepTimings)
    loop: LoopEvent | None = None
    covariance: np.ndarray | None = None
