"""Frame-to-map tracking: optimise one camera pose by rendering the blocks in its frustum.

N_t random pixels with valid depth and the paper's objective without the smoothness term (which does
not depend on the pose), its colour loss weighed by ``tracking.colour_scale`` (1: as the paper). Only
rays whose observed surface lies inside a block in the frustum contribute
(:func:`~neb_slam_core.render.volume.observed_rays`), and with ``observed_only`` only samples in space
some keyframe has seen (``block.observed_voxel_m``), so unmapped space never pulls the pose. Two
optimisers (``TrackingConfig.method``):

- ``adam``, the paper's: a fixed number of Adam steps with fresh stratified samples each; the pose
  with the lowest loss seen is kept.
- ``gauss_newton``: Levenberg-Marquardt on the same objective (see :mod:`.gauss_newton`), a few steps
  with no learning rate, to the pose Adam approaches in tens of steps (``benchmarks/tracking.py``).

A tracked pose comes with its covariance (``TrackingResult.covariance``). :func:`fuse` combines it with
a :class:`MotionPrior`, the motion model's prediction and the covariance of its error
(``tracking.motion_prior_m_s2``, ``motion_prior_rad_s2``): a Kalman update, the two estimates weighed by
their information.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from ..config import RenderConfig, TrackingConfig
from ..geometry.lie import PoseSet
from ..render.rays import PixelSamples, sample_pixels
from ..render.renderer import objective
from ..render.sampling import sample_depths
from ..scene.block_map import BlockMap
from ..scene.freeze import frozen
from ..types import RgbdFrame
from .gauss_newton import (
    COVARIANCE_ORDER,
    PoseEvaluation,
    apply_step,
    damped_step,
    evaluate_pose,
    normal_equations,
    pose_covariance,
    spatial_gradients,
)


@dataclass
class TrackingResult:
    """Outcome of tracking one frame.

    Attributes:
        T_world_cam: the optimised pose (float64 4x4).
        loss: objective at that pose.
        depth_residual_m: median |rendered - measured| depth over the valid rays at that pose (the median,
            so rays into parts of a block the map has not learnt yet do not dominate it).
        n_valid_rays: rays whose observed surface lies inside a consulted block.
        iterations: optimisation steps taken.
        covariance: the pose's covariance over (tx, ty, tz, rx, ry, rz) from the Gauss-Newton system at
            that pose (:func:`~neb_slam_core.tracking.gauss_newton.pose_covariance`), or None.
    """

    T_world_cam: np.ndarray
    loss: float
    depth_residual_m: float
    n_valid_rays: int
    iterations: int
    covariance: np.ndarray | None = None


@dataclass(frozen=True)
class MotionPrior:
    """The motion model's prediction of a frame's pose and the information (inverse covariance) of its
    error, over the order of ``TrackingResult.covariance``: (tx, ty, tz, rx, ry, rz), a translation and
    a world-frame rotation vector, applied as ``t = t_pred + dt``, ``R = exp(omega) R_pred``
    (1/m^2, 1/rad^2)."""

    T_world_cam: np.ndarray
    information: np.ndarray

    def offset(self, T_world_cam: np.ndarray) -> np.ndarray:
        """(tx, ty, tz, rx, ry, rz) of ``T_world_cam`` from the prediction."""
        omega = Rotation.from_matrix(T_world_cam[:3, :3] @ self.T_world_cam[:3, :3].T).as_rotvec()
        return np.concatenate([omega, T_world_cam[:3, 3] - self.T_world_cam[:3, 3]])[COVARIANCE_ORDER]

    def moved(self, offset: np.ndarray) -> np.ndarray:
        """The prediction moved by ``offset`` (the inverse of :meth:`offset`)."""
        return apply_step(self.T_world_cam, np.asarray(offset)[COVARIANCE_ORDER])


def motion_prior(T_pred: np.ndarray, dt_s: float, dt_prev_s: float, cfg: TrackingConfig) -> MotionPrior | None:
    """The prior of a constant-velocity prediction ``T_pred`` made ``dt_s`` after the last tracked frame
    from the motion over the ``dt_prev_s`` before it; None when ``cfg`` sets no prior or a time is not
    positive.

    The velocity extrapolated is the mean over the previous interval, the velocity half that interval
    before the last frame. Under an acceleration ``a`` the prediction is then off by
    ``a dt (dt + dt_prev) / 2`` (``a dt^2`` at a steady frame rate), so ``tracking.motion_prior_m_s2`` and
    ``motion_prior_rad_s2``, the accelerations expected of the camera, give the prediction's standard
    deviation in metres and radians; a setting of 0 leaves that part free."""
    if dt_s <= 0 or dt_prev_s <= 0 or (cfg.motion_prior_m_s2 <= 0 and cfg.motion_prior_rad_s2 <= 0):
        return None
    span = dt_s * (dt_s + dt_prev_s) / 2.0
    info = [1.0 / (a * span) ** 2 if a > 0 else 0.0 for a in (cfg.motion_prior_m_s2, cfg.motion_prior_rad_s2)]
    return MotionPrior(np.array(T_pred, dtype=np.float64), np.diag(np.repeat(info, 3)))


def fuse(tracked: TrackingResult, prior: MotionPrior | None) -> TrackingResult:
    """``tracked`` with its pose and covariance fused with ``prior`` (a Kalman update: the offset from
    the prediction ``(I_m + I_p)^-1 I_m d``, of covariance ``(I_m + I_p)^-1``, with ``I_m`` the tracked
    pose's information, ``d`` its offset and ``I_p`` the prior's); ``tracked`` itself without a prior or
    a covariance. The loss and depth residual stay those of the pose the frame gave."""
    if prior is None or tracked.covariance is None:
        return tracked
    info = np.linalg.inv(tracked.covariance)
    covariance = np.linalg.inv(info + prior.information)
    offset = covariance @ info @ prior.offset(tracked.T_world_cam)
    return replace(tracked, T_world_cam=prior.moved(offset), covariance=0.5 * (covariance + covariance.T))


class Tracker:
    """Pose optimisation against a fixed map, by Adam (the paper) or Levenberg-Marquardt."""

    def __init__(self, cfg: TrackingConfig, render_cfg: RenderConfig, seed: int = 0, gradients=spatial_gradients):
        """``gradients``: how Levenberg-Marquardt gets the samples' spatial gradients
        (:func:`~neb_slam_core.tracking.gauss_newton.spatial_gradients`, or its autograd reference)."""
        self.cfg = cfg
        # the objective tracking minimises: the paper's, its colour loss weighed by tracking.colour_scale
        weights = render_cfg.weights
        self.render_cfg = replace(render_cfg, weights=replace(weights, colour=weights.colour * cfg.colour_scale))
        self.gradients = gradients
        self.rng = np.random.default_rng(seed)
        self.generator = torch.Generator().manual_seed(seed)

    def track(self, block_map: BlockMap, frame: RgbdFrame, T_init: np.ndarray) -> TrackingResult:
        dev = block_map.device
        T_init = np.array(T_init, dtype=np.float64)
        px = sample_pixels(
            frame, self.cfg.n_rays, self.rng, valid_depth_only=True, border=self.cfg.border_px, device=dev
        )
        if len(px) == 0:
            return TrackingResult(T_init, float("inf"), float("inf"), 0, 0)
        s = self.render_cfg.sampling
        ids = block_map.blocks_in_frustum(T_init, frame.intrinsics, s.near_m, s.far_m)
        with frozen(block_map):
            if self.cfg.method == "gauss_newton":
                return self._levenberg_marquardt(block_map, px, T_init, ids)
            return self._adam(block_map, px, T_init, ids)

    def _adam(self, block_map: BlockMap, px: PixelSamples, T_init: np.ndarray, ids: list[int]) -> TrackingResult:
        """The paper's tracking: ``iterations`` Adam steps, fresh stratified samples each; the pose with
        the lowest loss seen is kept."""
        pose = PoseSet(T_init).to(block_map.device)
        opt = torch.optim.Adam([pose.delta], lr=self.cfg.lr)
        best = (float("inf"), T_init, float("inf"), 0)
        for _ in range(self.cfg.iterations):
            rays = px.to_world(pose.matrices()[0])
            loss, out = objective(
                block_map,
                rays,
                self.render_cfg,
                ids,
                generator=self.generator,
                with_smoothness=False,
                observed_only=self.cfg.observed_only,
            )
            n_valid = int(out.observed.sum())
            value = float(loss.total.detach())
            if n_valid >= self.cfg.min_valid_rays and value < best[0]:
                ok = out.observed & (rays.depth_m > 0)
                resid = float((out.depth_m - rays.depth_m)[ok].abs().median().detach()) if ok.any() else float("inf")
                best = (value, pose.numpy()[0], resid, n_valid)
            opt.zero_grad(set_to_none=True)
            loss.total.backward()
            opt.step()
        value, T, resid, n_valid = best
        if not np.isfinite(value):  # never enough valid rays
            return TrackingResult(T, value, resid, int(out.observed.sum()), self.cfg.iterations)
        z = sample_depths(px.depth_m, self.render_cfg.sampling, stratified=True, generator=self.generator)
        ev = evaluate_pose(block_map, px, T, z, self.render_cfg, ids, self.cfg.observed_only)
        H, _ = normal_equations(ev, block_map, ids, self.gradients)
        return TrackingResult(T, value, resid, n_valid, self.cfg.iterations, pose_covariance(H, ev.cost, n_valid))

    def _levenberg_marquardt(
        self, block_map: BlockMap, px: PixelSamples, T_init: np.ndarray, ids: list[int]
    ) -> TrackingResult:
        """Damped Gauss-Newton on the same objective with one fixed set of stratified samples (so the
        objective is a deterministic function of the pose and each step is accepted only if it lowers
        it). A rejected step costs one evaluation; an accepted one also its Jacobian.

        With ``coarse_rays`` set, a coarse stage first solves on that many of the drawn pixels (a random
        subset: the pixels are drawn in random order) until a step moves less than ``coarse_stop_step_m``;
        the stage on all pixels then starts from its pose. Far from the minimum, where a poor prediction
        costs many steps, each coarse step costs a fraction of a full one."""
        c = self.cfg
        z = sample_depths(px.depth_m, self.render_cfg.sampling, stratified=True, generator=self.generator)
        T = T_init
        coarse_steps = 0
        if 0 < c.coarse_rays < len(px):
            n = c.coarse_rays
            subset = PixelSamples(px.dirs_cam[:n], px.rgb[:n], px.depth_m[:n], px.uv[:n])
            min_rays = max(1, c.min_valid_rays * n // len(px))
            T, ev, coarse_steps, _ = self._lm_stage(block_map, subset, z[:n], T, ids, c.coarse_stop_step_m, min_rays)
        T, ev, steps, H = self._lm_stage(block_map, px, z, T, ids, c.gn_stop_step_m, c.min_valid_rays)
        cov = None if H is None else pose_covariance(H, ev.cost, ev.n_valid_rays)
        return TrackingResult(T, ev.cost, ev.depth_residual_m, ev.n_valid_rays, coarse_steps + steps, cov)

    def _lm_stage(
        self,
        block_map: BlockMap,
        px: PixelSamples,
        z: torch.Tensor,
        T: np.ndarray,
        ids: list[int],
        stop_step_m: float,
        min_valid_rays: int,
    ) -> tuple[np.ndarray, PoseEvaluation, int, np.ndarray | None]:
        """At most ``iterations`` Levenberg-Marquardt steps from ``T`` on the pixels ``px`` with sample
        depths ``z``: the pose, its evaluation, the steps evaluated and the Gauss-Newton matrix last built
        (at the pose, or at the one before the last step when the stage ends at ``iterations``; None with
        too few valid rays).

        The stage stops once the step it proposes moves less than ``stop_step_m`` (a step of (omega, dt)
        moves the camera by |dt| and points 1 m ahead by about |omega| m more). That step is neither
        evaluated nor taken: the pose is converged to within it, and its evaluation would cost as much as
        a step that counts (the parameter tolerance of trust-region solvers such as Ceres)."""
        c = self.cfg
        ev = evaluate_pose(block_map, px, T, z, self.render_cfg, ids, c.observed_only)
        if ev.n_valid_rays < min_valid_rays:
            return T, ev, 0, None
        H, g = normal_equations(ev, block_map, ids, self.gradients)
        damping = c.gn_damping
        steps = 0
        while steps < c.iterations:
            try:
                step = damped_step(H, g, damping)
            except np.linalg.LinAlgError:
                break
            if np.linalg.norm(step[3:]) + np.linalg.norm(step[:3]) < stop_step_m:
                break
            steps += 1
            T_new = apply_step(T, step)
            new = evaluate_pose(block_map, px, T_new, z, self.render_cfg, ids, c.observed_only)
            if new.n_valid_rays >= min_valid_rays and new.cost < ev.cost:
                T, ev = T_new, new
                damping = max(damping / 3.0, 1e-7)
                if steps < c.iterations:
                    H, g = normal_equations(ev, block_map, ids, self.gradients)
            else:
                damping *= 8.0
        return T, ev, steps, H
