"""Loop closure for the engine: detect a loop at a new keyframe, fit the correction, spread it.

    closer = LoopCloser(cfg.loop)
    closer.add_keyframe(keyframe_id, frame)          # every keyframe, in order
    event, poses = closer.close(keyframe_id, keyframe_poses)
    if event is not None and event.applied: ...      # poses: the corrected (K, 4, 4) keyframe poses

Detection is :class:`~neb_slam_core.loop.detector.LoopDetector` (bag of words and a geometric check);
the correction is :mod:`~neb_slam_core.loop.correction` (the paper's reprojection objective through the
loop keyframes' depths, then a pose graph along the keyframes of the loop). What the map does with the
corrected poses (two-stage re-optimisation) is the engine's part. The closer holds no poses: it is
handed the current ones, so it works the same in one process and behind a ROS topic.

Each keyframe is also registered against the ``register_neighbours`` keyframes before it, by the loop
fit's objective through their depth maps, starting from the relative pose tracking gave: the pose
graph's registration edges (:func:`~neb_slam_core.loop.correction.propagate_correction`). A
registration is kept when it passes the same tests as a loop fit (RMS and share of valid pixels).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..config import LoopConfig
from ..geometry.se3 import invert
from ..types import LoopEvent, RgbdFrame
from .correction import DepthView, correction_size, fit_loop_pose, propagate_correction, sample_pixels, strided_view
from .detector import LoopDetector
from .vocabulary import Vocabulary


class LoopCloser:
    """Keyframe database plus the depth maps the correction needs (see the module docstring)."""

    def __init__(self, cfg: LoopConfig, vocabulary: Vocabulary | None = None, seed: int = 0):
        self.cfg = cfg
        self.detector = LoopDetector(cfg, vocabulary)
        self.rng = np.random.default_rng(seed)
        self._views: dict[int, DepthView] = {}  # strided depth; the pose is filled in at query time
        #: registration edges: (i, j) -> inv(T_i) T_j measured by depth registration of j against i
        self.registrations: dict[tuple[int, int], np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.detector)

    def add_keyframe(self, keyframe_id: int, frame: RgbdFrame) -> None:
        """Describe and store keyframe ``keyframe_id`` (a rectified frame); keyframes come in order."""
        self.detector.add_keyframe(keyframe_id, frame.stamp_ns, frame.rgb, frame.depth_m, frame.intrinsics)
        self._views[int(keyframe_id)] = strided_view(np.eye(4), frame.depth_m, frame.intrinsics, self.cfg.depth_stride)

    def close(
        self, keyframe_id: int, poses: np.ndarray, frame: RgbdFrame
    ) -> tuple[LoopEvent | None, np.ndarray | None]:
        """Query for keyframe ``keyframe_id`` (already added; ``frame`` is it) with the current keyframe
        poses ``(K, 4, 4)``; returns the loop event (None: no loop) and, when applied, the corrected poses."""
        cfg = self.cfg
        self.register(keyframe_id, poses, frame)
        query = self.detector.query(keyframe_id)
        detection = query.detection
        if detection is None:
            return None, None
        loops = detection.loop_keyframes
        ids = tuple(c.keyframe_id for c in loops)
        r1 = loops[0]
        T_old = poses[keyframe_id]
        T_init = poses[r1.keyframe_id] @ r1.T_cand_query
        views = [replace(self._views[i], T_world_cam=np.asarray(poses[i], dtype=np.float64)) for i in ids]
        pixels, depths = sample_pixels(frame.depth_m, cfg.correction_pixels, self.rng)
        fit = fit_loop_pose(T_init, pixels, depths, frame.intrinsics, views, loss_scale_px=1.0)
        cm, deg = correction_size(T_old, fit.T_world_cam)
        share = fit.n_valid / max(1, len(pixels) * len(views))

        def event(applied: bool, reason: str = "") -> LoopEvent:
            return LoopEvent(keyframe_id, ids, r1.score, applied, reason, cm, deg, fit.rms_px_start, fit.rms_px)

        if not fit.rms_px <= cfg.max_fit_rms_px:
            return event(False, f"fit RMS {fit.rms_px:.2f} px above {cfg.max_fit_rms_px:g} px"), None
        if share < cfg.min_valid_share:
            return event(
                False,
                f"only {100 * share:.0f}% of pixels seen in the loop keyframes (< {100 * cfg.min_valid_share:.0f}%)",
            ), None
        if cm < cfg.min_correction_cm and deg < cfg.min_correction_deg:
            return event(
                False,
                f"correction {cm:.2f} cm / {deg:.2f} deg below {cfg.min_correction_cm:g} cm / "
                f"{cfg.min_correction_deg:g} deg: nothing to correct",
            ), None
        corrected = propagate_correction(poses, min(ids), keyframe_id, fit.T_world_cam, self.registrations)
        return event(True), corrected

    def relocalise(self, frame: RgbdFrame, poses: np.ndarray, max_poses: int = 2) -> list[np.ndarray]:
        """World poses ``(4, 4)`` of ``frame`` (rectified, not a keyframe) from the keyframes it was
        verified against (:meth:`LoopDetector.place`), best match first, at most ``max_poses``; ``poses``
        are the current keyframe poses ``(K, 4, 4)``. Empty when no keyframe passes the geometric check."""
        found = self.detector.place(frame.stamp_ns, frame.rgb, frame.depth_m, frame.intrinsics, max_poses)
        return [np.asarray(poses[c.keyframe_id], dtype=np.float64) @ c.T_cand_query for c in found]

    def register(self, keyframe_id: int, poses: np.ndarray, frame: RgbdFrame) -> None:
        """Registration edges into :attr:`registrations` from the ``register_neighbours`` keyframes added
        before ``keyframe_id`` (added; ``frame`` is it), starting from the relative poses in ``poses``
        (K, 4, 4). :meth:`close` does this first."""
        cfg = self.cfg
        order = list(self._views)
        position = order.index(int(keyframe_id))
        earlier = order[max(0, position - cfg.register_neighbours) : position]
        if not earlier:
            return
        pixels, depths = sample_pixels(frame.depth_m, cfg.correction_pixels, self.rng)
        T_now = np.asarray(poses[keyframe_id], dtype=np.float64)
        for i in earlier:
            T_i = np.asarray(poses[i], dtype=np.float64)
            view = replace(self._views[i], T_world_cam=T_i)
            fit = fit_loop_pose(T_now, pixels, depths, frame.intrinsics, [view], loss_scale_px=1.0)
            if fit.rms_px <= cfg.max_fit_rms_px and fit.n_valid >= cfg.min_valid_share * len(pixels):
                self.registrations[(int(i), int(keyframe_id))] = invert(T_i) @ fit.T_world_cam
