"""The per-frame loop of NeB-SLAM: predict, track, allocate, keyframe, map, loop check. No I/O.

    slam = Slam(config)
    for frame in dataset:
        result = slam.process(frame)
    trajectory = slam.trajectory()   # corrected poses of every processed frame

The engine has two halves that share nothing but the block map, so that they can also run in two
processes (the ROS ``tracker`` and ``mapper`` nodes) and still compute the same thing:

- :class:`Frontend` (tracking): rectify, predict, track, judge, allocate, decide keyframe and mapping,
  and keep every frame's pose relative to its keyframe;
- :class:`Backend` (mapping): the keyframe store, the first frame's map initialisation and the joint
  optimisation of blocks, decoders and keyframe poses.

:class:`Slam` runs both in one process on one block map. Across processes, what the frontend hands to the
backend is a :class:`FrontendStep` (a keyframe, its pose and whether to map now), and what comes back is
the map's changed blocks, its decoders and the corrected keyframe poses (``scene/map_update.py``).

Poses of non-keyframes are stored relative to the latest keyframe before them, so corrections of
keyframe poses (by mapping or loop closure) move them too. A frame between two keyframes also takes
its share (by frame count) of the next keyframe's correction relative to the one before: when the
joint optimisation or a loop's pose graph finds that tracking drifted between two keyframes, the
frames tracked in between are moved along instead of keeping the drift.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from .config import SlamConfig
from .geometry.colour_timing import colour_at_depth_time, colour_offset_ns
from .geometry.rays import backproject_pixels
from .geometry.rectify import Rectifier
from .geometry.se3 import interpolate_correction, invert, orthonormalize
from .io.trajectory import Trajectory
from .loop.closer import LoopCloser
from .loop.detector import FrameFeatures
from .loop.motion import FeatureMotion
from .mapping.keyframes import Keyframe, KeyframeStore
from .mapping.mapper import Mapper
from .render.rays import all_pixels
from .scene.block_map import BlockMap
from .tracking.tracker import MotionPrior, Tracker, TrackingResult, fuse, motion_prior
from .types import LoopEvent, RgbdFrame, StepResult, StepTimings


def new_block_map(cfg: SlamConfig) -> BlockMap:
    """The empty map of an engine with ``cfg`` (each process of a split engine makes its own, identical)."""
    return BlockMap(cfg.block, cfg.one_blob, cfg.decoder, grid_backend=cfg.grid_backend, seed=cfg.seed).to(
        torch.device(cfg.device)
    )


def load_map_for(cfg: SlamConfig, path) -> BlockMap:
    """The map checkpoint at ``path`` (``save_map``'s ``map.pt``), for an engine with ``cfg`` to continue.

    Its block, encoding and decoder configs must be ``cfg``'s (a map is only meaningful to the decoders
    that read it); a difference raises :class:`DatasetError` naming the file and the first differing
    field. The map comes without keyframes (those belong to the run that saved it): the engine's keyframe
    store starts empty and assigns its own keyframes to the blocks.
    """
    from .config import config_to_dict
    from .errors import DatasetError
    from .scene.persistence import load_map

    block_map, _ = load_map(path, torch.device(cfg.device), cfg.grid_backend)
    for section, stored in (
        ("block", block_map.block_cfg),
        ("one_blob", block_map.blob_cfg),
        ("decoder", block_map.decoder_cfg),
    ):
        mine, theirs = config_to_dict(getattr(cfg, section)), config_to_dict(stored)
        for key in sorted(set(mine) | set(theirs)):
            if mine.get(key) != theirs.get(key):
                raise DatasetError(
                    path,
                    f"the map was made with {section}.{key} = {theirs.get(key)!r}, this "
                    f"configuration has {mine.get(key)!r}: run with the map's configuration",
                )
    if len(block_map) == 0:
        raise DatasetError(path, "the map has no blocks")
    return block_map


def frame_pose(
    T_world_kf: np.ndarray,
    T_kf_cam: np.ndarray,
    share=0.0,
    T_world_next: np.ndarray | None = None,
    T_kf_next: np.ndarray | None = None,
) -> np.ndarray:
    """The pose of a frame kept relative to its keyframe (``T_kf_cam``), the keyframe now at ``T_world_kf``.

    With the next keyframe (now at ``T_world_next``; ``T_kf_next``: where tracking linked it from this
    keyframe) the frame also takes ``share`` (its place between the two, 0..1) of the next keyframe's
    move away from that link, turned about the frame's own position: the rule of the module docstring.
    Batched over leading axes (a frame with no next keyframe: ``T_world_next = T_world_kf``,
    ``T_kf_next`` identity, share 0).
    """
    T = T_world_kf @ T_kf_cam
    if T_world_next is None:
        return T
    drift = T_world_next @ invert(T_world_kf @ T_kf_next)
    return interpolate_correction(drift, T[..., :3, 3], share) @ T


def frames_with_keyframes(
    rows: np.ndarray,
    k: np.ndarray,
    T_kf_cam: np.ndarray,
    keyframe_poses: np.ndarray,
    keyframe_rows: np.ndarray,
    links: np.ndarray,
) -> np.ndarray:
    """:func:`frame_pose` of many frames at once: the frames at rows ``rows`` (F,) of their sequence, kept
    relative to keyframes ``k`` (F,) by ``T_kf_cam`` (F, 4, 4). Keyframe ``j`` is now at
    ``keyframe_poses[j]``, sits at row ``keyframe_rows[j]`` (-1: unknown, so the frames before it take no
    share of its move) and was linked by tracking to keyframe ``j - 1`` as ``links[j]`` (``links[0]``
    unused). A frame whose keyframe has no (known) next one moves rigidly with its keyframe."""
    last = len(keyframe_poses) - 1
    nxt = np.minimum(k + 1, last)
    has_next = (k < last) & (keyframe_rows[nxt] >= 0)
    span = np.where(has_next, keyframe_rows[nxt] - keyframe_rows[k], 1)
    share = np.where(has_next, (rows - keyframe_rows[k]) / span, 0.0)
    T_world_next = np.where(has_next[:, None, None], keyframe_poses[nxt], keyframe_poses[k])
    T_kf_next = np.where(has_next[:, None, None], links[nxt], np.eye(4))
    return frame_pose(keyframe_poses[k], T_kf_cam, share, T_world_next, T_kf_next)


def corrected_trajectory(
    stamps_ns: np.ndarray, poses: np.ndarray, keyframe_stamps_ns: np.ndarray, keyframe_poses: np.ndarray
) -> Trajectory:
    """A trajectory computed with earlier keyframe poses, after the keyframes moved to ``keyframe_poses``
    ``(K, 4, 4)`` (the keyframes are the frames with stamps ``keyframe_stamps_ns``, increasing): every
    frame follows the latest keyframe at or before it by :func:`frame_pose`, its place between that
    keyframe and the next counted in rows, the link between them read off ``poses`` as well. Frames
    before the first keyframe, or whose keyframe is not in the trajectory, keep their pose. What a
    process that only sees the trajectory (the ROS mapper, a benchmark on a run's output) can compute of
    :meth:`Frontend.pose_of`; the same when the keyframes have not moved since ``poses`` were computed."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    poses = np.array(poses, dtype=np.float64).reshape(-1, 4, 4)
    keyframe_poses = np.asarray(keyframe_poses, dtype=np.float64).reshape(-1, 4, 4)
    kf_stamps = np.asarray(keyframe_stamps_ns, dtype=np.int64)
    row_of = {int(s): i for i, s in enumerate(stamps)}
    kf_rows = np.array([row_of.get(int(s), -1) for s in kf_stamps], dtype=np.int64)
    owner = np.searchsorted(kf_stamps, stamps, side="right") - 1
    moved = np.flatnonzero((owner >= 0) & (kf_rows[np.maximum(owner, 0)] >= 0))
    out = poses.copy()
    if len(moved) == 0:
        return Trajectory(stamps, out)
    # the links between consecutive keyframes as the trajectory holds them
    links = np.tile(np.eye(4), (len(kf_rows), 1, 1))
    both = np.flatnonzero((kf_rows[1:] >= 0) & (kf_rows[:-1] >= 0)) + 1
    links[both] = invert(poses[kf_rows[both - 1]]) @ poses[kf_rows[both]]
    k = owner[moved]
    T_kf_cam = invert(poses[kf_rows[k]]) @ poses[moved]
    out[moved] = frames_with_keyframes(moved, k, T_kf_cam, keyframe_poses, kf_rows, links)
    return Trajectory(stamps, out)


def scale_motion(delta: np.ndarray, scale: float) -> np.ndarray:
    """``delta^scale`` of a rigid motion (4x4) on SE(3)'s one-parameter subgroup: the screw motion
    ``exp(scale * log(delta))`` (``scale`` 1: ``delta``, 0: identity, 2: ``delta @ delta``)."""
    from scipy.linalg import expm, logm

    if scale == 1.0:
        return np.array(delta, dtype=np.float64)
    return np.real(expm(scale * np.real(logm(np.asarray(delta, dtype=np.float64)))))


def choose_frame(stamps_ns, last_ns: int | None, max_gap_s: float, has_velocity: bool = True) -> int:
    """The index of the frame to track next among ``stamps_ns`` (arrived, not tracked yet, oldest first).

    The newest, but none more than ``max_gap_s`` after the last processed frame (``last_ns``; the oldest
    when all are further): a frame far ahead of the last pose lies outside the tracker's basin, so an
    engine that fell behind catches up in steps of at most that. Without a velocity (``has_velocity``
    False: one frame tracked so far) the prediction is the last pose itself, so the oldest frame is
    taken. ``max_gap_s`` 0 or nothing processed yet: the newest.
    """
    n = len(stamps_ns)
    if n == 0:
        raise ValueError("choose_frame: no frame to choose from")
    gap_ns = int(round(max_gap_s * 1e9))
    if gap_ns <= 0 or last_ns is None:
        return n - 1
    if not has_velocity:
        return 0
    within = int(np.searchsorted(np.asarray(stamps_ns, dtype=np.int64), last_ns + gap_ns, side="right"))
    return max(within - 1, 0)


@dataclass
class _FramePose:
    """A processed frame's pose: relative to keyframe ``keyframe_id`` (``T_kf_cam``)."""

    stamp_ns: int
    keyframe_id: int
    T_kf_cam: np.ndarray


@dataclass
class FrontendStep:
    """What the frontend did with one frame, and what the backend has to do with it.

    Attributes:
        result: the frame's :class:`StepResult` (``mapped`` and ``timings.map_ms`` are the backend's to fill).
        frame: the frame as tracked (rectified): what a keyframe stores.
        keyframe_id: the id of the keyframe it became, or None.
        map_now: the backend optimises after adding this keyframe (always a keyframe when True).
        first: the first frame: the backend initialises the map on it.
    """

    result: StepResult
    frame: RgbdFrame
    keyframe_id: int | None
    map_now: bool
    first: bool


class Frontend:
    """The tracking half of the engine over ``block_map`` (which it reads, and grows by allocation).

    Keyframe poses live here as a list indexed by keyframe id; the backend's corrections come back
    through :meth:`set_keyframe_poses`.

    After a tracking failure the frontend is :attr:`lost` until a frame passes the failure test again.
    ``relocaliser``, when given, maps a lost (rectified) frame to candidate world poses from a place
    recognition outside the frontend (in :class:`Slam`: the loop closer's keyframe database); the
    frontend only tracks from them, so it needs nothing of ``loop/``.

    ``own_map``: ``block_map`` is the tracker's own copy, fed by a backend elsewhere (the live engine's
    mapping thread, the ROS ``mapper``), so the frontend records the space each of its keyframes saw in
    it at once (:meth:`~neb_slam_core.scene.block_map.BlockMap.mark_observed`), without waiting for the
    backend's records to come back with a map update. Where frontend and backend share one map
    (:class:`Slam`), the backend records it as it integrates the keyframe.
    """

    def __init__(
        self,
        cfg: SlamConfig,
        block_map: BlockMap,
        T_world_first: np.ndarray | None = None,
        relocaliser: Callable[[RgbdFrame], list[np.ndarray]] | None = None,
        own_map: bool = False,
    ):
        self.cfg = cfg
        self.block_map = block_map
        self.own_map = own_map
        self.rng = np.random.default_rng(cfg.seed)
        self.tracker = Tracker(cfg.tracking, cfg.render, seed=cfg.seed + 2)
        self.T_world_first = np.eye(4) if T_world_first is None else np.array(T_world_first, dtype=np.float64)
        self.keyframe_poses: list[np.ndarray] = []
        # per keyframe: its frame index, and its pose relative to the keyframe before it as tracked
        self._keyframe_frames: list[int] = []
        self._keyframe_links: list[np.ndarray] = []
        self._frames: list[_FramePose] = []
        self._residuals: list[float] = []
        self._ok_streak = 0  # consecutive frames tracked (the first frame counts)
        self._tracked: list[int] = []  # the last two frames that were tracked (not failed), oldest first
        self._rectify = Rectifier()
        self.relocaliser = relocaliser
        #: the last frame failed tracking and none has passed since
        self.lost = False
        # tracking.prediction features: the last tracked frame's index and features, which the next
        # frame is matched against, and while tracking fails, the last failed frame whose pose came from
        # verified matches (the chain of matches through the loss, see _matched_pose())
        self._motion = FeatureMotion(cfg.loop) if cfg.tracking.prediction == "features" else None
        self._reference: tuple[int, FrameFeatures] | None = None
        self._chained: tuple[int, FrameFeatures] | None = None

    # ------------------------------------------------------------------ poses

    @property
    def n_frames(self) -> int:
        return len(self._frames)

    def pose_of(self, i: int) -> np.ndarray:
        """Current (corrected) pose of processed frame ``i``: with its keyframe, plus its share of the
        next keyframe's correction relative to its own (the module docstring)."""
        f = self._frames[i]
        k = f.keyframe_id
        if k + 1 == len(self.keyframe_poses):
            return frame_pose(self.keyframe_poses[k], f.T_kf_cam)
        first, last = self._keyframe_frames[k], self._keyframe_frames[k + 1]
        return frame_pose(
            self.keyframe_poses[k],
            f.T_kf_cam,
            (i - first) / (last - first),
            self.keyframe_poses[k + 1],
            self._keyframe_links[k + 1],
        )

    def keyframe_of(self, i: int) -> int:
        """Id of the keyframe that frame ``i``'s pose is kept relative to."""
        return self._frames[i].keyframe_id

    def trajectory(self) -> Trajectory:
        """Corrected poses of every processed frame (:meth:`pose_of` of all, in one batch: the ROS
        tracker publishes this after every frame)."""
        if not self._frames:
            return Trajectory(np.zeros(0, np.int64), np.zeros((0, 4, 4)))
        poses = frames_with_keyframes(
            np.arange(self.n_frames),
            np.array([f.keyframe_id for f in self._frames]),
            np.stack([f.T_kf_cam for f in self._frames]),
            np.stack(self.keyframe_poses),
            np.array(self._keyframe_frames),
            np.stack(self._keyframe_links),
        )
        return Trajectory(np.array([f.stamp_ns for f in self._frames]), poses)

    def memory(self) -> int:
        """Bytes of the per-frame and per-keyframe poses the frontend keeps (they grow with the frames)."""
        from .memory import deep_bytes

        return deep_bytes(
            self._frames, self._residuals, self.keyframe_poses, self._keyframe_frames, self._keyframe_links
        )

    def set_keyframe_poses(self, poses: np.ndarray) -> None:
        """Corrected poses ``(K, 4, 4)`` of the first K keyframes (from mapping or loop closure). Keyframes
        after them (made since the corrections were computed: another thread or process maps) move
        rigidly with keyframe K-1, keeping the relative poses tracking gave them."""
        # poses that went through optimisers and pipes come back rigid to rounding; keep them exactly so,
        # since every frame pose is composed from them
        poses = orthonormalize(np.asarray(poses, dtype=np.float64))
        if len(poses) == 0:
            return
        k_last = len(poses) - 1
        delta = poses[k_last] @ invert(self.keyframe_poses[k_last])
        for k, T in enumerate(poses):
            self.keyframe_poses[k] = T.copy()
        for k in range(len(poses), len(self.keyframe_poses)):
            self.keyframe_poses[k] = orthonormalize(delta @ self.keyframe_poses[k])

    # ------------------------------------------------------------------ the loop

    def step(self, frame: RgbdFrame) -> FrontendStep:
        """Track ``frame`` (undistorted first when it carries lens distortion), allocate, and decide
        whether it becomes a keyframe and whether the map is optimised after it.

        The first frame initialises an empty map at ``T_world_first``. On a map that already has blocks
        (a checkpoint continued) it is tracked like any other, from ``T_world_first`` as the prediction.
        """
        t_start = time.perf_counter()
        frame = self._rectify(frame)
        index = self.n_frames
        timings = StepTimings()
        if index == 0 and len(self.block_map) == 0:
            return self._first(frame, t_start)

        t0 = time.perf_counter()
        frame = self._colour_at_depth_time(frame)
        features = self.describe(frame)
        T_matched = self._matched_pose(features)
        T_motion = self.predict(frame.stamp_ns)
        T_pred = T_matched if T_matched is not None else T_motion
        tracked = fuse(self.tracker.track(self.block_map, frame, T_pred), self._motion_prior(T_motion, frame.stamp_ns))
        if self.cfg.tracking.relocalise and (self.lost or not self._passes(tracked)):
            tracked = self._relocalise(frame, T_pred, tracked)
        timings.track_ms = 1e3 * (time.perf_counter() - t0)
        ok, reason = self._tracking_ok(tracked)
        recovered = ok and self.lost
        self.lost = not ok
        self._ok_streak = self._ok_streak + 1 if ok else 0
        if recovered:
            self._tracked, self._ok_streak = [index], 1  # no velocity across the gap
        elif ok:
            self._tracked = (self._tracked + [index])[-2:]
        else:
            self._tracked = self._tracked[-1:]  # the motion before the loss is stale
        if ok and features is not None:
            self._reference, self._chained = (index, features), None
        elif T_matched is not None:  # failed, at a pose from verified matches: the next link of the chain
            self._chained = (index, features)
        T = tracked.T_world_cam if ok else T_pred

        # allocate (only from a trusted pose: a wrong one would put a block in the wrong place)
        t0 = time.perf_counter()
        new_block, tau = None, 0.0
        if ok:
            new_block, tau = self._allocate(frame, T)
        timings.allocate_ms = 1e3 * (time.perf_counter() - t0)

        # a mapping frame is a keyframe too, so that a backend in another process learns of every
        # mapping step from the keyframe that triggers it (with keyframes.every == mapping.every, the
        # paper's setting, this adds no keyframe)
        # (the first frame on a continued map is always a keyframe: frame poses hang off keyframes)
        c = self.cfg
        map_now = (ok or index == 0) and (
            index % c.mapping.every == 0 or new_block is not None or self._keyframe_due(frame.stamp_ns)
        )
        is_keyframe = (ok or index == 0) and (index % c.keyframes.every == 0 or map_now or recovered)
        keyframe_id = self._make_keyframe(frame, T) if is_keyframe else None
        self._record(frame.stamp_ns, T)
        timings.total_ms = 1e3 * (time.perf_counter() - t_start)
        result = StepResult(
            index,
            frame.stamp_ns,
            T.copy(),
            is_keyframe,
            None if new_block is None else new_block.block_id,
            tau,
            ok,
            reason,
            False,
            len(self.block_map),
            timings,
            covariance=tracked.covariance if ok else None,
        )
        return FrontendStep(result, frame, keyframe_id, map_now, False)

    @property
    def last_tracked_stamp_ns(self) -> int | None:
        """The stamp of the last frame tracked (not failed), None before the first."""
        return self._frames[self._tracked[-1]].stamp_ns if self._tracked else None

    def next_frame(self, stamps_ns) -> int:
        """For an engine that cannot take every frame: which of the frames that arrived and are not tracked
        yet (``stamps_ns``, oldest first) to track next (:func:`choose_frame` with ``live.max_gap_s``)."""
        # the step counts from the last frame processed, failed or not, so that a run of failures still
        # moves the engine forward
        last = self._frames[-1].stamp_ns if self._frames else None
        return choose_frame(stamps_ns, last, self._max_gap_s(), self._has_velocity)

    @property
    def _has_velocity(self) -> bool:
        """:meth:`predict` extrapolates a velocity: from the last two frames by count (``frames``, both
        tracked), or from any two tracked frames (``stamps``)."""
        if self.cfg.tracking.motion_model == "stamps":
            return len(self._tracked) >= 2
        return self._ok_streak >= 2

    def _motion_prior(self, T_motion: np.ndarray, stamp_ns: int) -> MotionPrior | None:
        """The prior of the frame stamped ``stamp_ns``: ``T_motion``, :meth:`predict`'s constant-velocity
        pose for it (``tracking.motion_prior_*``, :func:`~neb_slam_core.tracking.tracker.motion_prior`),
        where it extrapolates a velocity. It holds whichever pose tracking started from (a ``features``
        prediction too): the start only decides which minimum the optimiser finds."""
        if not self._has_velocity:
            return None
        older, newer = (self._frames[i].stamp_ns for i in self._tracked)
        return motion_prior(T_motion, (stamp_ns - newer) * 1e-9, (newer - older) * 1e-9, self.cfg.tracking)

    def _max_gap_s(self) -> float:
        """``live.max_gap_s``, shortened to the time the camera takes to turn ``live.max_turn_deg`` at the
        rate between the last two tracked frames, and to ``live.max_gap_growth`` times their interval
        (when there are two)."""
        live = self.cfg.live
        motion = self._tracked_motion() if live.max_turn_deg > 0 or live.max_gap_growth > 0 else None
        if motion is None or motion[1] <= 0:
            return live.max_gap_s
        delta, dt_ns = motion
        bounds = [live.max_gap_s] if live.max_gap_s > 0 else []
        turned_deg = float(np.degrees(Rotation.from_matrix(delta[:3, :3]).magnitude()))
        if live.max_turn_deg > 0 and turned_deg > 0:
            bounds.append(live.max_turn_deg * dt_ns * 1e-9 / turned_deg)
        if live.max_gap_growth > 0:
            bounds.append(live.max_gap_growth * dt_ns * 1e-9)
        return min(bounds) if bounds else 0.0

    def _tracked_motion(self) -> tuple[np.ndarray, int] | None:
        """The motion between the last two tracked frames (``inv(T_older) T_newer``) and the nanoseconds
        between their stamps; None before two frames are tracked."""
        if len(self._tracked) < 2:
            return None
        i2, i1 = self._tracked
        return invert(self.pose_of(i2)) @ self.pose_of(i1), self._frames[i1].stamp_ns - self._frames[i2].stamp_ns

    def _colour_at_depth_time(self, frame: RgbdFrame) -> RgbdFrame:
        """With ``tracking.colour_timing``, ``frame`` with its colour resampled to its depth image's time
        by the motion between the last two tracked frames; else, or without that motion or the two
        capture times, ``frame``."""
        offset_ns = colour_offset_ns(frame)
        motion = self._tracked_motion() if self.cfg.tracking.colour_timing and offset_ns else None
        if motion is None or motion[1] <= 0:
            return frame
        delta, dt_ns = motion
        return colour_at_depth_time(frame, scale_motion(delta, offset_ns / dt_ns))

    def predict(self, stamp_ns: int) -> np.ndarray:
        """The constant-velocity prediction of the pose of a frame stamped ``stamp_ns`` (the next one).

        ``tracking.motion_model``: ``frames`` (the paper's): ``T_{t-1} T_{t-2}^-1 T_{t-1}``, only when both
        previous frames were tracked (after a failure the velocity is unknown, and extrapolating an
        extrapolation runs away), else the previous pose. ``stamps``: the motion between the last two
        tracked frames, scaled to the time since the last one by their stamps (frames dropped in between
        do not matter), at most ``tracking.max_extrapolation`` times that motion. While :attr:`lost`,
        neither extrapolates further: ``frames`` keeps the previous frame's pose (the failed frames carry
        the one prediction made before the loss, so a single dropped frame costs nothing), ``stamps``
        the last tracked pose (its velocity is forgotten at a failure); after a recovery the velocity
        starts anew from the recovered frame.
        """
        index = self.n_frames
        if index == 0:
            return self.T_world_first
        c = self.cfg.tracking
        if c.motion_model == "frames":
            if index >= 2 and self._ok_streak >= 2:
                T_prev = self.pose_of(index - 1)
                return orthonormalize(T_prev @ invert(self.pose_of(index - 2)) @ T_prev)
            return self.pose_of(index - 1)
        motion = self._tracked_motion()
        if motion is None:
            return self.pose_of(self._tracked[-1] if self._tracked else index - 1)
        delta, dt_prev = motion
        last = self.last_tracked_stamp_ns
        scale = (stamp_ns - last) / dt_prev if dt_prev > 0 else 1.0
        step = scale_motion(delta, min(max(scale, 0.0), c.max_extrapolation))
        return orthonormalize(self.pose_of(self._tracked[-1]) @ step)

    def describe(self, frame: RgbdFrame) -> FrameFeatures | None:
        """What :meth:`prediction` matches of a rectified frame: its ORB features with
        ``tracking.prediction`` ``features``, else None."""
        return None if self._motion is None else self._motion.describe(frame)

    def prediction(self, stamp_ns: int, features: FrameFeatures | None = None) -> np.ndarray:
        """The pose tracking starts from for the next frame, stamped ``stamp_ns``, with ``features`` its
        :meth:`describe`: :meth:`_matched_pose` with ``tracking.prediction`` ``features`` where the matches
        verify; otherwise, and with ``motion``, the motion model's :meth:`predict`."""
        T = self._matched_pose(features)
        return T if T is not None else self.predict(stamp_ns)

    def _matched_pose(self, features: FrameFeatures | None) -> np.ndarray | None:
        """The pose of the frame described by ``features`` from its ORB matches
        (:class:`~neb_slam_core.loop.motion.FeatureMotion`, where the geometric check accepts the pair):
        the last tracked frame's (corrected) pose moved by the two frames' relative pose. While tracking
        fails, a frame that no longer matches the last tracked one is matched against the last failed
        frame that got its pose this way, so the poses of a loss follow the camera from match to match
        (a pan into space the map has not seen), and the frame that passes again starts near where the
        camera is. None without features or verified matches."""
        if features is None:
            return None
        for reference in (self._reference, self._chained):
            if reference is None:
                continue
            ref_index, ref_features = reference
            T_ref_cur = self._motion.relative_pose(features, ref_features)
            if T_ref_cur is not None:
                return orthonormalize(self.pose_of(ref_index) @ T_ref_cur)
        return None

    # ------------------------------------------------------------------ steps

    def _first(self, frame: RgbdFrame, t_start: float) -> FrontendStep:
        T = self.T_world_first
        if self._motion is not None:
            self._reference = (0, self._motion.describe(frame))
        t0 = time.perf_counter()
        new_block, tau = self._allocate(frame, T)
        timings = StepTimings(allocate_ms=1e3 * (time.perf_counter() - t0))
        keyframe_id = self._make_keyframe(frame, T)
        self._record(frame.stamp_ns, T)
        self._ok_streak = 1
        self._tracked = [0]
        timings.total_ms = 1e3 * (time.perf_counter() - t_start)
        result = StepResult(
            0,
            frame.stamp_ns,
            T.copy(),
            True,
            None if new_block is None else new_block.block_id,
            tau,
            True,
            "",
            False,
            len(self.block_map),
            timings,
            covariance=np.zeros((6, 6)),
        )
        return FrontendStep(result, frame, keyframe_id, True, True)

    def _relocalise(self, frame: RgbdFrame, T_pred: np.ndarray, tracked: TrackingResult) -> TrackingResult:
        """``tracked`` (from ``T_pred``) or the frame tracked from another start, whichever has the lowest
        depth residual with enough rays inside blocks: the starts are the last tracked pose and the
        ``relocaliser``'s poses. Tracking from a far-off start converges to a wrong pose or leaves the
        map, which the depth residual shows; it is the quantity the failure test judges."""
        starts = [] if self.relocaliser is None else list(self.relocaliser(frame))
        if self._tracked:
            starts.insert(0, self.pose_of(self._tracked[-1]))
        best = tracked
        for T in starts:
            if np.allclose(T, T_pred, atol=1e-9):
                continue
            other = self.tracker.track(self.block_map, frame, T)
            if self._better(other, best):
                best = other
        return best

    def _better(self, a: TrackingResult, b: TrackingResult) -> bool:
        """``a`` has enough rays inside blocks and a lower depth residual than ``b`` (or ``b`` has too few)."""
        enough = self.cfg.tracking.min_valid_rays
        if a.n_valid_rays < enough or not np.isfinite(a.depth_residual_m):
            return False
        return b.n_valid_rays < enough or not a.depth_residual_m >= b.depth_residual_m

    def _passes(self, tracked: TrackingResult) -> bool:
        """The failure test of :meth:`_tracking_ok`, without recording the residual."""
        ok, _ = self._tracking_ok(tracked, record=False)
        return ok

    def _tracking_ok(self, tracked: TrackingResult, record: bool = True) -> tuple[bool, str]:
        c = self.cfg.tracking
        if tracked.n_valid_rays < c.min_valid_rays:
            return False, f"only {tracked.n_valid_rays} rays inside mapped blocks (< {c.min_valid_rays})"
        if not np.isfinite(tracked.depth_residual_m):
            return False, "no valid depth residual"
        if len(self._residuals) >= 5:
            level = float(np.median(self._residuals[-30:]))
            limit = max(c.failure_ratio * level, c.failure_min_residual_m)
            if tracked.depth_residual_m > limit:
                return False, (
                    f"depth residual {100 * tracked.depth_residual_m:.1f} cm is above {100 * limit:.1f} cm "
                    f"({c.failure_ratio:g} x its running level {100 * level:.2f} cm, at least "
                    f"{100 * c.failure_min_residual_m:.1f} cm)"
                )
        if record:
            self._residuals.append(tracked.depth_residual_m)
        return True, ""

    def _keyframe_due(self, stamp_ns: int) -> bool:
        """``keyframes.every_s`` has passed since the last keyframe's stamp."""
        every_s = self.cfg.keyframes.every_s
        if every_s <= 0 or not self._keyframe_frames:
            return False
        last_ns = self._frames[self._keyframe_frames[-1]].stamp_ns
        return stamp_ns - last_ns >= every_s * 1e9

    def _allocate(self, frame: RgbdFrame, T: np.ndarray):
        v, u = np.nonzero(frame.depth_m > 0)
        if len(u) == 0:
            return None, 0.0
        pick = self.rng.choice(len(u), min(self.cfg.block.alloc_n_points, len(u)), replace=False)
        u, v = u[pick], v[pick]
        pts = backproject_pixels(u, v, frame.depth_m[v, u], frame.intrinsics, T)
        s = self.cfg.render.sampling
        ids = self.block_map.blocks_in_frustum(T, frame.intrinsics, s.near_m, s.far_m)
        alloc = self.block_map.allocate_if_needed(
            torch.as_tensor(pts, dtype=torch.float32, device=self.block_map.device), ids
        )
        return alloc.block, alloc.tau

    def _make_keyframe(self, frame: RgbdFrame, T: np.ndarray) -> int:
        """``frame`` at ``T`` becomes the next keyframe (its view recorded as observed with ``own_map``)."""
        if self.own_map:
            self.block_map.mark_observed(frame.depth_m, frame.intrinsics, T, self.cfg.render.truncation_m)
        return self._add_keyframe(T)

    def _add_keyframe(self, T: np.ndarray) -> int:
        link = invert(self.keyframe_poses[-1]) @ T if self.keyframe_poses else np.eye(4)
        self._keyframe_links.append(np.array(link, dtype=np.float64))
        self._keyframe_frames.append(self.n_frames)
        self.keyframe_poses.append(np.array(T, dtype=np.float64))
        return len(self.keyframe_poses) - 1

    def _record(self, stamp_ns: int, T: np.ndarray) -> None:
        kf_id = len(self.keyframe_poses) - 1
        self._frames.append(_FramePose(stamp_ns, kf_id, invert(self.keyframe_poses[kf_id]) @ T))


@dataclass
class MappingStep:
    """What the backend did with one keyframe: the map steps it took and the blocks they changed."""

    keyframe: Keyframe
    mapped: bool
    map_ms: float
    changed_block_ids: set[int] = field(default_factory=set)


class Backend:
    """The mapping half of the engine over ``block_map``: keyframes in, optimised map and poses out."""

    def __init__(self, cfg: SlamConfig, block_map: BlockMap):
        self.cfg = cfg
        self.block_map = block_map
        self.keyframes = KeyframeStore(cfg.keyframes.pixel_fraction, seed=cfg.seed + 1, device=block_map.device)
        self.mapper = Mapper(block_map, self.keyframes, cfg.mapping, cfg.render, seed=cfg.seed + 3)

    def add_keyframe(
        self,
        frame: RgbdFrame,
        T_world_cam: np.ndarray,
        frame_index: int,
        map_now: bool,
        first: bool = False,
        first_iterations: int | None = None,
    ) -> MappingStep:
        """Store keyframe ``frame`` (rectified) at ``T_world_cam`` and record the space it saw in the map's
        blocks (:meth:`~neb_slam_core.scene.block_map.BlockMap.mark_observed`, the space tracking uses with
        ``tracking.observed_only``); then initialise the map on it (``first``: ``first_iterations``
        map-only steps on all its pixels, ``mapping.first_iterations`` when None) or run a joint
        optimisation step (``map_now``). The step's changed blocks include those whose record grew."""
        kf = self.keyframes.add(frame, T_world_cam, frame_index)
        self._assign_blocks(kf)
        marked = self.block_map.mark_observed(
            frame.depth_m, frame.intrinsics, T_world_cam, self.cfg.render.truncation_m
        )
        if not (first or map_now):
            return MappingStep(kf, False, 0.0, marked)
        t0 = time.perf_counter()
        if first:
            rays = all_pixels(frame, device=self.block_map.device).to_world(
                torch.as_tensor(T_world_cam, dtype=torch.float32)
            )
            n = self.cfg.mapping.first_iterations if first_iterations is None else first_iterations
            res = self.mapper.optimise_on_rays(rays, n)
        else:
            res = self.mapper.optimise()
        return MappingStep(kf, True, 1e3 * (time.perf_counter() - t0), res.changed_block_ids | marked)

    def _assign_blocks(self, kf: Keyframe) -> None:
        """Make ``kf`` a keyframe of every block holding more than a tenth of its observed points at its
        current pose, and of no other (the blocks whose newest keyframes get the extra N_a rays)."""
        pts = torch.as_tensor(self.keyframes.observed_points(kf), dtype=torch.float32, device=self.block_map.device)
        block_ids = []
        if len(pts):
            share = self.block_map.contains(pts).float().mean(dim=0)  # (M,)
            block_ids = (share > 0.1).nonzero(as_tuple=True)[0].tolist()
        self.keyframes.assign(kf, block_ids)

    def correct_loop(self, poses: np.ndarray, start_id: int, reoptimise: bool = True) -> MappingStep:
        """Apply a loop correction: keyframe poses ``(K, 4, 4)`` (those after ``start_id`` moved), then
        re-optimise in two stages, the paper's: the map with the poses fixed, then poses and map jointly
        (keyframes up to ``start_id`` held). Blocks stay where they are in the world: the moved keyframes
        are re-assigned to the blocks their points now fall in, and re-train those. Without
        ``reoptimise`` the caller runs the two stages itself (in chunks, between keyframes)."""
        t0 = time.perf_counter()
        self.keyframes.set_poses(poses)
        for kf in self.keyframes.keyframes[start_id + 1 :]:
            self._assign_blocks(kf)
        if not reoptimise:
            return MappingStep(self.keyframes[len(self.keyframes) - 1], False, 1e3 * (time.perf_counter() - t0))
        c = self.cfg.loop
        first = self.mapper.optimise(c.map_iterations, optimise_poses=False)
        second = self.mapper.optimise(c.joint_iterations, optimise_poses=True, fixed_until=start_id)
        return MappingStep(
            self.keyframes[len(self.keyframes) - 1],
            True,
            1e3 * (time.perf_counter() - t0),
            first.changed_block_ids | second.changed_block_ids,
        )

    def observed_points(self, rng: np.random.Generator, max_points: int = 2_000_000) -> np.ndarray:
        """World points of all keyframes' kept pixels (for mesh culling), float64 ``(K, 3)``."""
        return keyframe_points(self.keyframes, rng, max_points)

    def memory(self, loop_closer: LoopCloser | None = None) -> dict[str, int]:
        """Bytes of the backend's stores and of ``loop_closer``'s: ``keyframes`` (the keyframe store's
        pixels and poses), ``loop_closer`` (ORB features, bag-of-words vectors, inverted index, depth
        maps, registrations; not the vocabulary), ``map`` (the block map) and ``optimiser`` (the mapper's
        optimiser state). The first two grow with the keyframes, the last two with the blocks."""
        from .memory import deep_bytes

        closer = loop_closer
        return {
            "keyframes": deep_bytes(self.keyframes),
            "loop_closer": 0 if closer is None else deep_bytes(closer, exclude=(closer.detector.vocabulary,)),
            "map": deep_bytes(self.block_map),
            "optimiser": deep_bytes(self.mapper, exclude=(self.block_map, self.keyframes)),
        }


def keyframe_points(keyframes: KeyframeStore, rng: np.random.Generator, max_points: int = 2_000_000) -> np.ndarray:
    """World points of the kept pixels of every keyframe in ``keyframes``, float64 ``(K, 3)``; at most
    ``max_points`` of them, drawn with ``rng`` (what culls a mesh to the observed space)."""
    kfs = keyframes.keyframes
    if not kfs:
        return np.zeros((0, 3))
    if keyframes.n_pixels <= max_points:
        return np.concatenate([keyframes.observed_points(kf) for kf in kfs])
    # an equal share of each keyframe, so that no more than about max_points points exist at once
    share = max_points / keyframes.n_pixels
    parts = []
    for kf in kfs:
        pts = keyframes.observed_points(kf)
        parts.append(pts[rng.random(len(pts)) < share])
    return np.concatenate(parts)[:max_points]


class KnownPoseMapping:
    """The engine's allocation and mapping on frames at known poses (e.g. ground truth), without tracking:
    a map fitted to a scene by the allocation, keyframe store and mapper a run uses (tests and
    benchmarks of the map alone).

    :meth:`add` runs a frame through what a run does with a keyframe once it has its pose: rectify it,
    allocate by the frontend's rule (:meth:`Frontend._allocate`, the paper's tau test), store it in the
    backend (:meth:`Backend.add_keyframe`: its kept pixels, its blocks). :meth:`optimise` takes the
    backend mapper's steps over all keyframes with the poses held (:meth:`Mapper.optimise` with
    ``optimise_poses=False``: N_m rays from all keyframes plus N_a from the newest block's).
    """

    def __init__(self, cfg: SlamConfig, block_map: BlockMap | None = None):
        self.cfg = cfg
        torch.manual_seed(cfg.seed)  # as Slam does: same seed, same map
        self.block_map = new_block_map(cfg) if block_map is None else block_map
        self.frontend = Frontend(cfg, self.block_map)
        self.backend = Backend(cfg, self.block_map)

    @property
    def keyframes(self) -> KeyframeStore:
        return self.backend.keyframes

    def allocate(self, frame: RgbdFrame, T_world_cam: np.ndarray | None = None) -> int | None:
        """Allocate by the frontend's rule on ``frame`` at ``T_world_cam`` (the frame's own pose when None),
        without keeping the frame; returns the id of the block it added, or None."""
        frame = self.frontend._rectify(frame)
        block, _ = self.frontend._allocate(frame, self._pose(frame, T_world_cam))
        return None if block is None else block.block_id

    def add(self, frame: RgbdFrame, T_world_cam: np.ndarray | None = None) -> Keyframe:
        """Allocate on ``frame`` at ``T_world_cam`` (the frame's own pose when None), then store it as a
        keyframe, assigned to its blocks; no mapping step. Its ``frame_index`` is its place among the
        frames added."""
        frame = self.frontend._rectify(frame)
        T = self._pose(frame, T_world_cam)
        self.frontend._allocate(frame, T)
        return self.backend.add_keyframe(frame, T, len(self.keyframes), map_now=False).keyframe

    def optimise(self, iterations: int, progress: bool = False) -> list[float]:
        """``iterations`` mapping steps over all keyframes, poses held; returns each step's total loss.
        One mapper call per step: the same steps and draws as a single call of ``iterations``."""
        steps = range(iterations)
        if progress:
            from tqdm import tqdm

            steps = tqdm(steps, desc="fit map", unit="it")
        return [self.backend.mapper.optimise(1, optimise_poses=False).loss for _ in steps]

    @staticmethod
    def _pose(frame: RgbdFrame, T_world_cam: np.ndarray | None) -> np.ndarray:
        T = frame.T_world_cam if T_world_cam is None else T_world_cam
        if T is None:
            raise ValueError(f"frame {frame.index} has no pose: pass T_world_cam")
        return np.array(T, dtype=np.float64)


class Slam:
    """NeB-SLAM engine for one RGB-D stream: a frontend and a backend on one block map."""

    def __init__(
        self, cfg: SlamConfig = SlamConfig(), T_world_first: np.ndarray | None = None, block_map: BlockMap | None = None
    ):
        """An engine starting from ``T_world_first`` (identity when omitted) on an empty map, or on
        ``block_map`` (a previous run's, :func:`load_map_for`) when one is given: the first frame is
        then tracked against it, and blocks are added where it does not reach."""
        self.cfg = cfg
        torch.manual_seed(cfg.seed)
        self.block_map = new_block_map(cfg) if block_map is None else block_map
        self.frontend = Frontend(cfg, self.block_map, T_world_first)
        self.backend = Backend(cfg, self.block_map)
        self.loop_closer = LoopCloser(cfg.loop, seed=cfg.seed + 4) if cfg.loop.enabled else None
        if self.loop_closer is not None:
            self.frontend.relocaliser = self._relocalisation_poses
        self.loops: list[LoopEvent] = []

    # ------------------------------------------------------------------ state

    @property
    def keyframes(self) -> KeyframeStore:
        return self.backend.keyframes

    @property
    def n_frames(self) -> int:
        return self.frontend.n_frames

    def pose_of(self, i: int) -> np.ndarray:
        """Current (corrected) pose of processed frame ``i``."""
        return self.frontend.pose_of(i)

    def trajectory(self) -> Trajectory:
        """Corrected poses of every processed frame."""
        return self.frontend.trajectory()

    def observed_points(self, max_points: int = 2_000_000) -> np.ndarray:
        """World points of all keyframes' kept pixels (for mesh culling), float64 ``(K, 3)``."""
        return self.backend.observed_points(self.frontend.rng, max_points)

    @property
    def block_revisions(self) -> dict[int, int]:
        """Per block id, how many optimisation calls changed its table (what a mesh re-extracts by)."""
        return self.backend.mapper.revisions

    def memory(self) -> dict[str, int]:
        """Bytes held by each of the engine's stores (:func:`~neb_slam_core.memory.deep_bytes`): those of
        :meth:`Backend.memory`, ``frames`` (:meth:`Frontend.memory`) and ``loops`` (the loop events)."""
        from .memory import deep_bytes

        return {
            **self.backend.memory(self.loop_closer),
            "frames": self.frontend.memory(),
            "loops": deep_bytes(self.loops),
        }

    def set_keyframe_poses(self, poses: np.ndarray) -> None:
        """Correct the poses ``(K, 4, 4)`` of the first K keyframes (e.g. a loop closure); the frames
        kept relative to them move with them."""
        self.keyframes.set_poses(poses)
        self.frontend.set_keyframe_poses(poses)

    # ------------------------------------------------------------------ the loop

    def process(self, frame: RgbdFrame) -> StepResult:
        """Track ``frame`` (undistorted first when it carries lens distortion), then allocate, keyframe
        and map as the paper's loop does."""
        t_start = time.perf_counter()
        step = self.frontend.step(frame)
        result = step.result
        if step.keyframe_id is not None:
            mapping = self.backend.add_keyframe(
                step.frame, result.T_world_cam, result.frame_index, step.map_now, step.first
            )
            assert mapping.keyframe.keyframe_id == step.keyframe_id, "frontend and backend keyframes diverged"
            if mapping.mapped:
                result.mapped = True
                result.timings.map_ms = mapping.map_ms
                self.frontend.set_keyframe_poses(self.keyframes.poses())
            if self.loop_closer is not None:
                t0 = time.perf_counter()
                result.loop = self._close_loop(step)
                result.timings.loop_ms = 1e3 * (time.perf_counter() - t0)
            result.T_world_cam = self.pose_of(result.frame_index)
        result.timings.total_ms = 1e3 * (time.perf_counter() - t_start)
        return result

    def _relocalisation_poses(self, frame: RgbdFrame) -> list[np.ndarray]:
        """Candidate poses of a lost frame: the loop closer's keyframes verified against it (bag of words,
        then the loop detector's geometric check), each keyframe's current pose times the verified
        relative pose."""
        return self.loop_closer.relocalise(frame, self.keyframes.poses())

    def _close_loop(self, step: FrontendStep) -> LoopEvent | None:
        """Loop check of a new keyframe (the paper's last step of the loop); on an applied loop, correct
        the keyframe poses and re-optimise the map."""
        kid = step.keyframe_id
        self.loop_closer.add_keyframe(kid, step.frame)
        event, poses = self.loop_closer.close(kid, self.keyframes.poses(), step.frame)
        if event is None:
            return None
        self.loops.append(event)
        if event.applied:
            self.backend.correct_loop(poses, event.start_id)
            self.frontend.set_keyframe_poses(self.keyframes.poses())
        return event
