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

A keyframe's depth map (every ``depth_stride``-th pixel) is kept PNG-compressed, in steps of 0.2 mm
(TUM's depth unit) up to 13.1 m (farther readings count as none), and decoded when a fit reads it: a
fraction of its raw size, for a map that every keyframe adds to and only the registrations and loop fits
read.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..config import LoopConfig
from ..geometry.se3 import invert, rigidity_error
from ..types import Intrinsics, LoopEvent, RgbdFrame
from .correction import DepthView, correction_size, fit_loop_pose, propagate_correction, sample_pixels, strided_view
from .detector import LoopDetector
from .vocabulary import Vocabulary

#: the unit of the kept depth maps (metres): TUM's, so its depth is kept exactly
DEPTH_UNIT_M = 1.0 / 5000.0
#: a correction whose poses are further than this from rigid motions (numerical failure) is not applied
MAX_RIGIDITY_ERROR = 1e-6


class LoopCloser:
    """Keyframe database plus the depth maps the correction needs (see the module docstring)."""

    def __init__(self, cfg: LoopConfig, vocabulary: Vocabulary | None = None, seed: int = 0):
        self.cfg = cfg
        self.detector = LoopDetector(cfg, vocabulary)
        self.rng = np.random.default_rng(seed)
        # per keyframe: strided depth as PNG and its camera; a view's pose is filled in when it is read
        self._views: dict[int, tuple[bytes, Intrinsics]] = {}
        self._order: list[int] = []  # keyframe ids as added
        #: registration edges: (i, j) -> inv(T_i) T_j measured by depth registration of j against i
        self.registrations: dict[tuple[int, int], np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.detector)

    def add_keyframe(self, keyframe_id: int, frame: RgbdFrame) -> None:
        """Describe and store keyframe ``keyframe_id`` (a rectified frame); keyframes come in order."""
        self.detector.add_keyframe(keyframe_id, frame.stamp_ns, frame.rgb, frame.depth_m, frame.intrinsics)
        view = strided_view(np.eye(4), frame.depth_m, frame.intrinsics, self.cfg.depth_stride)
        units = np.rint(view.depth_m / DEPTH_UNIT_M)
        units[~(units <= np.iinfo(np.uint16).max)] = 0  # beyond the range (or not finite): no reading
        ok, png = cv2.imencode(".png", units.astype(np.uint16))
        if not ok:
            raise RuntimeError(f"LoopCloser: could not encode the depth of keyframe {keyframe_id}")
        self._views[int(keyframe_id)] = (png.tobytes(), view.intrinsics)
        self._order.append(int(keyframe_id))

    def view(self, keyframe_id: int, T_world_cam: np.ndarray) -> DepthView:
        """Keyframe ``keyframe_id``'s kept depth map at pose ``T_world_cam``."""
        png, intrinsics = self._views[int(keyframe_id)]
        units = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
        depth = units.astype(np.float32) * np.float32(DEPTH_UNIT_M)
        return DepthView(np.asarray(T_world_cam, dtype=np.float64), depth, intrinsics)

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
        views = [self.view(i, poses[i]) for i in ids]
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
        if rigidity_error(corrected) > MAX_RIGIDITY_ERROR:
            return event(False, "the corrected poses are not rigid motions"), None
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
        order = self._order
        position = len(order) - 1 if order[-1] == int(keyframe_id) else order.index(int(keyframe_id))
        earlier = order[max(0, position - cfg.register_neighbours) : position]
        if not earlier:
            return
        pixels, depths = sample_pixels(frame.depth_m, cfg.correction_pixels, self.rng)
        T_now = np.asarray(poses[keyframe_id], dtype=np.float64)
        for i in earlier:
            T_i = np.asarray(poses[i], dtype=np.float64)
            view = self.view(i, T_i)
            fit = fit_loop_pose(T_now, pixels, depths, frame.intrinsics, [view], loss_scale_px=1.0)
            if fit.rms_px <= cfg.max_fit_rms_px and fit.n_valid >= cfg.min_valid_share * len(pixels):
                self.registrations[(int(i), int(keyframe_id))] = invert(T_i) @ fit.T_world_cam
