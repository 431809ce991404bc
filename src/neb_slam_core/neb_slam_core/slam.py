"""The per-frame loop of NeB-SLAM: predict, track, allocate, keyframe, map. No I/O.

    slam = Slam(config)
    for frame in dataset:
        result = slam.process(frame)
    trajectory = slam.trajectory()   # corrected poses of every processed frame

Poses of non-keyframes are stored relative to the latest keyframe before them, so corrections of
keyframe poses (by mapping or loop closure) move them too.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from .config import SlamConfig
from .geometry.rays import backproject_depth
from .geometry.rectify import Rectifier
from .geometry.se3 import invert, orthonormalize
from .io.trajectory import Trajectory
from .mapping.keyframes import KeyframeStore
from .mapping.mapper import Mapper
from .render.rays import all_pixels
from .scene.block_map import BlockMap
from .tracking.tracker import Tracker
from .types import RgbdFrame, StepResult, StepTimings


@dataclass
class _FramePose:
    """A processed frame's pose: relative to keyframe ``keyframe_id`` (``T_kf_cam``)."""

    stamp_ns: int
    keyframe_id: int
    T_kf_cam: np.ndarray


class Slam:
    """NeB-SLAM engine for one RGB-D stream."""

    def __init__(self, cfg: SlamConfig = SlamConfig(), T_world_first: np.ndarray | None = None):
        self.cfg = cfg
        dev = torch.device(cfg.device)
        torch.manual_seed(cfg.seed)
        self.rng = np.random.default_rng(cfg.seed)
        self.block_map = BlockMap(cfg.block, cfg.one_blob, cfg.decoder, grid_backend=cfg.grid_backend,
                                  seed=cfg.seed).to(dev)
        self.keyframes = KeyframeStore(cfg.keyframes.pixel_fraction, seed=cfg.seed + 1, device=dev)
        self.tracker = Tracker(cfg.tracking, cfg.render, seed=cfg.seed + 2)
        self.mapper = Mapper(self.block_map, self.keyframes, cfg.mapping, cfg.render, seed=cfg.seed + 3)
        self.T_world_first = np.eye(4) if T_world_first is None else np.array(T_world_first, dtype=np.float64)
        self._frames: list[_FramePose] = []
        self._residuals: list[float] = []
        self._ok_streak = 0  # consecutive frames tracked (the first frame counts)
        self._rectify = Rectifier()

    # ------------------------------------------------------------------ state

    @property
    def n_frames(self) -> int:
        return len(self._frames)

    def pose_of(self, i: int) -> np.ndarray:
        """Current (corrected) pose of processed frame ``i``."""
        f = self._frames[i]
        return self.keyframes[f.keyframe_id].T_world_cam @ f.T_kf_cam

    def trajectory(self) -> Trajectory:
        """Corrected poses of every processed frame."""
        if not self._frames:
            return Trajectory(np.zeros(0, np.int64), np.zeros((0, 4, 4)))
        return Trajectory(np.array([f.stamp_ns for f in self._frames]),
                          np.stack([self.pose_of(i) for i in range(self.n_frames)]))

    def observed_points(self, max_points: int = 2_000_000) -> np.ndarray:
        """World points of all keyframes' kept pixels (for mesh culling), float64 ``(K, 3)``."""
        pts = np.concatenate([kf.observed_points() for kf in self.keyframes.keyframes]) if len(self.keyframes) else np.zeros((0, 3))
        if len(pts) > max_points:
            pts = pts[self.rng.choice(len(pts), max_points, replace=False)]
        return pts

    # ------------------------------------------------------------------ the loop

    def process(self, frame: RgbdFrame) -> StepResult:
        """Track ``frame`` (undistorted first when it carries lens distortion), then allocate, keyframe
        and map as the paper's loop does."""
        t_start = time.perf_counter()
        frame = self._rectify(frame)
        index = self.n_frames
        timings = StepTimings()
        if index == 0:
            return self._initialise(frame, t_start)

        # predict (constant velocity) and track
        # constant velocity from the last two frames, only when both were tracked: after a failure the
        # velocity is unknown, and extrapolating an extrapolation runs away
        T_prev = self.pose_of(index - 1)
        if index >= 2 and self._ok_streak >= 2:
            T_pred = orthonormalize(T_prev @ invert(self.pose_of(index - 2)) @ T_prev)
        else:
            T_pred = T_prev
        t0 = time.perf_counter()
        tracked = self.tracker.track(self.block_map, frame, T_pred)
        timings.track_ms = 1e3 * (time.perf_counter() - t0)
        ok, reason = self._tracking_ok(tracked)
        self._ok_streak = self._ok_streak + 1 if ok else 0
        T = tracked.T_world_cam if ok else T_pred

        # allocate (only from a trusted pose: a wrong one would put a block in the wrong place)
        t0 = time.perf_counter()
        new_block, tau = None, 0.0
        if ok:
            new_block, tau = self._allocate(frame, T)
        timings.allocate_ms = 1e3 * (time.perf_counter() - t0)

        is_keyframe = ok and (index % self.cfg.keyframes.every == 0 or new_block is not None)
        if is_keyframe:
            self._add_keyframe(frame, T, index)
        self._record(frame.stamp_ns, T)

        mapped = False
        if ok and (index % self.cfg.mapping.every == 0 or new_block is not None):
            t0 = time.perf_counter()
            self.mapper.optimise()
            timings.map_ms = 1e3 * (time.perf_counter() - t0)
            mapped = True
        timings.total_ms = 1e3 * (time.perf_counter() - t_start)
        return StepResult(index, frame.stamp_ns, self.pose_of(index), is_keyframe,
                          None if new_block is None else new_block.block_id, tau, ok, reason, mapped,
                          len(self.block_map), timings)

    # ------------------------------------------------------------------ steps

    def _initialise(self, frame: RgbdFrame, t_start: float) -> StepResult:
        T = self.T_world_first
        t0 = time.perf_counter()
        new_block, tau = self._allocate(frame, T)
        alloc_ms = 1e3 * (time.perf_counter() - t0)
        self._add_keyframe(frame, T, 0)
        self._record(frame.stamp_ns, T)
        self._ok_streak = 1
        t0 = time.perf_counter()
        rays = all_pixels(frame, device=self.block_map.device).to_world(torch.as_tensor(T, dtype=torch.float32))
        self.mapper.optimise_on_rays(rays, self.cfg.mapping.first_iterations)
        map_ms = 1e3 * (time.perf_counter() - t0)
        timings = StepTimings(0.0, alloc_ms, map_ms, 1e3 * (time.perf_counter() - t_start))
        return StepResult(0, frame.stamp_ns, T.copy(), True, None if new_block is None else new_block.block_id,
                          tau, True, "", True, len(self.block_map), timings)

    def _tracking_ok(self, tracked) -> tuple[bool, str]:
        c = self.cfg.tracking
        if tracked.n_valid_rays < c.min_valid_rays:
            return False, f"only {tracked.n_valid_rays} rays inside mapped blocks (< {c.min_valid_rays})"
        if not np.isfinite(tracked.depth_residual_m):
            return False, "no valid depth residual"
        if len(self._residuals) >= 5:
            level = float(np.median(self._residuals[-30:]))
            limit = max(c.failure_ratio * level, c.failure_min_residual_m)
            if tracked.depth_residual_m > limit:
                return False, (f"depth residual {100 * tracked.depth_residual_m:.1f} cm is above {100 * limit:.1f} cm "
                               f"({c.failure_ratio:g} x its running level {100 * level:.2f} cm, at least "
                               f"{100 * c.failure_min_residual_m:.1f} cm)")
        self._residuals.append(tracked.depth_residual_m)
        return True, ""

    def _allocate(self, frame: RgbdFrame, T: np.ndarray):
        pts = backproject_depth(frame.depth_m, frame.intrinsics, T)
        if len(pts) == 0:
            return None, 0.0
        n = min(self.cfg.block.alloc_n_points, len(pts))
        pts = pts[self.rng.choice(len(pts), n, replace=False)]
        s = self.cfg.render.sampling
        ids = self.block_map.blocks_in_frustum(T, frame.intrinsics, s.near_m, s.far_m)
        alloc = self.block_map.allocate_if_needed(torch.as_tensor(pts, dtype=torch.float32,
                                                                  device=self.block_map.device), ids)
        return alloc.block, alloc.tau

    def _add_keyframe(self, frame: RgbdFrame, T: np.ndarray, index: int) -> None:
        kf = self.keyframes.add(frame, T, index)
        pts = torch.as_tensor(kf.observed_points(), dtype=torch.float32, device=self.block_map.device)
        if len(pts):
            share = self.block_map.contains(pts).float().mean(dim=0)  # (M,)
            for block_id in (share > 0.1).nonzero(as_tuple=True)[0].tolist():
                kf.block_ids.append(block_id)
                self.block_map.blocks[block_id].keyframe_ids.append(kf.keyframe_id)

    def _record(self, stamp_ns: int, T: np.ndarray) -> None:
        kf = self.keyframes[len(self.keyframes) - 1]
        self._frames.append(_FramePose(stamp_ns, kf.keyframe_id, invert(kf.T_world_cam) @ T))
