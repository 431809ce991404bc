"""Gauss-Newton linearisation of the tracking objective in the camera pose.

The paper optimises the pose with Adam (a learning rate, a fixed number of steps). Each step costs a
full render, and Adam needs tens of them to settle to within a millimetre (it moves each pose component
by about the learning rate per step, whatever the curvature). The objective
is, however, a weighted sum of squares: the colour and depth residuals of the rendered rays and the
SDF and free-space residuals of their samples. So the pose can be solved for as a least-squares
problem, with the exact same objective, by Levenberg-Marquardt: a handful of damped Gauss-Newton
steps reach the minimum that Adam approaches slowly.

The Jacobian of every residual in the 6 pose parameters is built without 6 passes over the map:

* each sample's SDF and colour depend only on its own point, so their spatial gradients ``d sdf / d p``
  (and per colour channel) are those of the map at that point: in closed form where the map's C++
  kernels run (the hash features with their derivatives from the same 8 rows per level, the one-blob
  slopes, the decoders in forward mode along the three axes:
  :meth:`~neb_slam_core.scene.block_map.BlockMap.spatial_gradients`), else by forward differences, one
  batched map query at the points and at the points moved by a fifth of a millimetre along each axis
  (:func:`forward_difference_gradients`; within a cell of every grid level the encoding is linear
  along each axis, so the difference is the derivative there, and crossing a cell face averages the
  two cells' slopes). Either costs less than the four backward passes (SDF and three colours) autograd
  would need;
* a sample's point moves with the pose as ``dp = domega x (p - t) + dt`` (the parameterisation of
  :mod:`neb_slam_core.geometry.lie`: ``R = exp(omega) R0``, ``t = t0 + dt``);
* a ray's rendered depth and colour depend only on that ray's samples, through the normalised
  rendering weights, whose slopes have a closed form (:func:`~neb_slam_core.render.volume.sdf_weight_slopes`):
  ``d depth_i / d sdf_ij = a_ij (z_ij - depth_i)``, and likewise per colour channel.

The residuals and their weights are the objective's own terms
(:func:`~neb_slam_core.render.losses.render_residuals`): each is an affine function of the rendered
colour, the rendered depth or the samples' SDF, whose Jacobians are built here once. Only the samples
that move the objective (see :func:`evaluate_pose`) get a spatial gradient, and the Jacobians are
assembled on those samples alone, then summed per ray.

Torch has no batched per-residual Jacobian for a custom C++ autograd function (no forward mode in the
hash-grid kernel), hence this chain rule by hand; :func:`normal_equations` is checked against autograd's
gradient of :func:`neb_slam_core.render.renderer.objective` in the tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..config import RenderConfig
from ..geometry.lie import compose_delta
from ..render.losses import Residual, combine, render_residuals
from ..render.rays import PixelSamples
from ..render.renderer import query_samples
from ..render.volume import composite, observed_rays, sdf_weight_slopes
from ..scene.block_map import BlockMap


@dataclass
class PoseEvaluation:
    """The tracking objective at one pose, with what its Gauss-Newton model needs.

    Attributes:
        cost: the objective (the paper's weighted colour + depth + SDF + free-space losses).
        n_valid_rays: rays whose observed surface lies in a consulted block (:func:`observed_rays`).
        depth_residual_m: median |rendered - measured| depth over those rays with depth.
    The remaining fields are internal to :func:`normal_equations`.
    """

    cost: float
    n_valid_rays: int
    depth_residual_m: float
    T: torch.Tensor
    points: torch.Tensor  # (R, S, 3)
    z: torch.Tensor  # (R, S) sample depths
    sample_rgb: torch.Tensor  # (R, S, 3) the samples' colours
    weights: torch.Tensor  # (R, S) rendering weights
    slopes: torch.Tensor  # (R, S) d composite / d sdf factors (:func:`sdf_weight_slopes`)
    depth: torch.Tensor  # (R,) rendered
    colour: torch.Tensor  # (R, 3) rendered
    active: torch.Tensor  # (R, S) samples whose spatial gradient enters the model
    terms: dict[str, Residual]  # the objective's terms at this pose


def _pose_jacobian(grad_p: torch.Tensor, lever: torch.Tensor) -> torch.Tensor:
    """``d f / d(omega, dt)`` of a point function with spatial gradient ``grad_p`` (..., 3) at lever arm
    ``lever = p - t`` (..., 3): ``(lever x grad_p, grad_p)`` (..., 6)."""
    return torch.cat([torch.cross(lever, grad_p, dim=-1), grad_p], dim=-1)


#: forward-difference step of the spatial gradients (metres): far below the finest grid cell (2 cm at the
#: default 250 levels over 5 m), far above float32 rounding of world coordinates (the actual step is
#: measured after rounding)
FD_STEP_M = 2e-4


def spatial_gradients(block_map: BlockMap, points: torch.Tensor, block_ids: list[int] | None) -> torch.Tensor:
    """``(4, A, 3)``: the gradients of SDF, red, green and blue at ``(A, 3)`` world points: in closed form
    (:meth:`~neb_slam_core.scene.block_map.BlockMap.spatial_gradients`) where the map's C++ kernels run,
    else by :func:`forward_difference_gradients`."""
    grads = block_map.spatial_gradients(points, block_ids)
    return grads if grads is not None else forward_difference_gradients(block_map, points, block_ids)


def forward_difference_gradients(
    block_map: BlockMap, points: torch.Tensor, block_ids: list[int] | None
) -> torch.Tensor:
    """The same ``(4, A, 3)`` by forward differences along the world axes in one batched query (any
    backend and device). Where a moved point leaves the consulted blocks, the gradient is 0 (the masked
    value jumps there)."""
    n = points.shape[0]
    shifted = points[None].repeat(4, 1, 1)
    for axis in range(3):
        shifted[axis + 1, :, axis] += FD_STEP_M
    steps = torch.stack([shifted[axis + 1, :, axis] - points[:, axis] for axis in range(3)])  # (3, A)
    with torch.no_grad():
        q = block_map.query(shifted.reshape(-1, 3), block_ids, with_colour=True)
    values = torch.cat([q.sdf[:, None], q.rgb], dim=1).reshape(4, n, 4)
    inside = q.valid.reshape(4, n).all(dim=0)
    grads = (values[1:] - values[0]) / steps[..., None]  # (axis, A, output)
    return grads.permute(2, 1, 0) * inside[None, :, None].to(grads.dtype)


def spatial_gradients_autograd(block_map: BlockMap, points: torch.Tensor, block_ids: list[int] | None) -> torch.Tensor:
    """The reference for :func:`spatial_gradients`: the same ``(4, A, 3)`` by autograd, one backward pass
    per output (the tests and ``benchmarks/tracking.py`` compare against it)."""
    p = points.detach().clone().requires_grad_(True)
    with torch.enable_grad():
        q = block_map.query(p, block_ids, with_colour=True)
        outputs = [q.sdf] + [q.rgb[:, k] for k in range(3)]
        grads = [torch.autograd.grad(o.sum(), p, retain_graph=k < 3)[0] for k, o in enumerate(outputs)]
    return torch.stack(grads)


def evaluate_pose(
    block_map: BlockMap,
    pixels: PixelSamples,
    T_world_cam: np.ndarray,
    z: torch.Tensor,
    cfg: RenderConfig,
    block_ids: list[int] | None,
    observed_only: bool = False,
) -> PoseEvaluation:
    """The tracking objective at ``T_world_cam`` with fixed sample depths ``z`` (R, S).

    The residuals are the objective's terms (:func:`~neb_slam_core.render.losses.render_residuals`), so
    ``cost`` equals ``objective(...).total`` without smoothness for the same ``z`` and ``observed_only``
    (:func:`~neb_slam_core.render.renderer.query_samples`). Call it with the map's parameters frozen.
    """
    T = torch.as_tensor(T_world_cam, dtype=torch.float32, device=z.device)
    rays = pixels.to_world(T)
    r_count, s_count = z.shape
    points = rays.origins[:, None, :] + z[..., None] * rays.dirs[:, None, :]  # (R, S, 3)
    with torch.no_grad():
        sample = query_samples(
            block_map, points, z, pixels.depth_m, cfg.sampling, block_ids, observed_only=observed_only
        )
    valid = sample.valid.reshape(r_count, s_count)

    # rendering, with the weights' slopes in the samples' SDF (colours enter linearly)
    sd = sample.sdf.reshape(r_count, s_count)
    c = sample.rgb.reshape(r_count, s_count, 3)
    tr = cfg.truncation_m
    w, slopes = sdf_weight_slopes(sd, z, valid, tr)
    depth, colour = composite(w, z, c)
    obs_d = pixels.depth_m
    ray_valid = observed_rays(valid, z, obs_d, tr)
    terms = render_residuals(
        cfg.weights, tr, colour, depth, sd, z, valid, ray_valid, pixels.rgb, obs_d, cfg.depth_noise_weights
    )
    cost = float(combine(terms).total)
    # Spatial gradients are needed only where a sample moves the objective: carrying rendering weight, or
    # an active entry of a term on the samples' SDF. Elsewhere a residual's Jacobian is ~0; leaving those
    # samples out only coarsens the Gauss-Newton matrix, never the cost a step is judged by.
    active = valid & (w > 1e-4)
    for term in terms.values():
        if term.source == "sdf":
            active = active | _active_entries(term)
    m_d = ray_valid & (obs_d > 0)
    resid = float((depth - obs_d)[m_d].abs().median()) if bool(m_d.any()) else float("inf")
    return PoseEvaluation(cost, int(ray_valid.sum()), resid, T, points, z, c, w, slopes, depth, colour, active, terms)


def _active_entries(term: Residual) -> torch.Tensor:
    """The masked entries of ``term`` that enter the Gauss-Newton matrix (``Residual.active_above``)."""
    if term.active_above == 0:
        return term.mask
    return term.mask & (term.r.abs() > term.active_above)


def normal_equations(
    ev: PoseEvaluation, block_map: BlockMap, block_ids: list[int] | None, gradients=spatial_gradients
) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton system at ``ev``: ``H = J^T W J`` (6, 6) and ``g = J^T W r`` (6,), float64; ``2 g`` is
    the objective's gradient in (omega, dt). ``gradients``: how the samples' spatial gradients are
    computed (:func:`spatial_gradients`, or its autograd reference)."""
    r_count = ev.active.shape[0]
    ray, sample = ev.active.nonzero(as_tuple=True)  # the active samples, by ray
    p_act = ev.points[ray, sample]
    grads = gradients(block_map, p_act, block_ids)  # (4, A, 3)
    jac = _pose_jacobian(grads, (p_act - ev.T[:3, 3]).expand_as(grads))  # (4, A, 6): d (sdf, r, g, b) / d pose
    A = jac[0]
    a = ev.slopes[ray, sample]
    # per ray: d depth_i = sum_j a_ij (z_ij - depth_i) d sdf_ij; per colour channel likewise, plus the
    # samples' own colour change w_ij d c_ij
    d_depth = (a * (ev.z[ray, sample] - ev.depth[ray]))[:, None] * A
    d_colour = (a[:, None] * (ev.sample_rgb[ray, sample] - ev.colour[ray])).T[..., None] * A + ev.weights[ray, sample][
        None, :, None
    ] * jac[1:]  # (3, A, 6)
    # the Jacobians of what the terms' residuals are affine functions of (rows: rays, or active samples)
    jacobians = {
        "rgb": A.new_zeros(r_count, 3, 6).index_add_(0, ray, d_colour.permute(1, 0, 2)),
        "depth": A.new_zeros(r_count, 1, 6).index_add_(0, ray, d_depth[:, None]),
        "sdf": A[:, None],  # rows of the active samples: elsewhere the Jacobian is taken as 0
    }
    H = A.new_zeros(6, 6)
    g = A.new_zeros(6)
    for name, term in ev.terms.items():
        if term.source is None:
            continue  # independent of the pose
        if term.source not in jacobians:
            raise ValueError(f"objective term {name!r}: no Jacobian for source {term.source!r}")
        r, wt = term.r, term.entry_weights()
        if term.source == "sdf":
            r, wt = r[ray, sample], wt[ray, sample]
        J = (term.slope * jacobians[term.source]).reshape(-1, 6)
        Jw = J * wt.reshape(-1, 1)
        H += Jw.T @ J
        g += Jw.T @ r.reshape(-1)
    return H.double().cpu().numpy(), g.double().cpu().numpy()


#: the indices of the update's (omega, dt) in the order of a reported covariance, (tx, ty, tz, rx, ry, rz);
#: the permutation is its own inverse
COVARIANCE_ORDER = [3, 4, 5, 0, 1, 2]


def pose_covariance(H: np.ndarray, cost: float, n_rays: int) -> np.ndarray | None:
    """The pose's covariance from the Gauss-Newton system ``H`` (6, 6 in (omega, dt)) at the optimum of an
    objective of value ``cost`` over ``n_rays`` rays: ``s^2 H^-1`` with ``s^2 = cost / (n_rays - 6)``,
    the objective's residual scale per measurement (weighted least squares whose weights are known up
    to a common factor). A ray's colour, depth and SDF residuals share its pixel, so the rays, not the
    residuals, count as the independent measurements. Returned over ``(tx, ty, tz, rx, ry, rz)`` (metres
    and radians: the translation and the world-frame rotation vector of the update, the order of ROS
    covariances); None when ``H`` is singular or there are no more rays than parameters."""
    if n_rays <= 6 or not np.isfinite(cost):
        return None
    try:
        cov = np.linalg.inv(H) * (cost / (n_rays - 6))
    except np.linalg.LinAlgError:
        return None
    cov = cov[np.ix_(COVARIANCE_ORDER, COVARIANCE_ORDER)]
    cov = 0.5 * (cov + cov.T)
    if not np.all(np.isfinite(cov)) or np.any(np.diag(cov) <= 0):
        return None
    return cov


def damped_step(H: np.ndarray, g: np.ndarray, damping: float) -> np.ndarray:
    """The Levenberg-Marquardt step (omega, dt) of the system ``H``, ``g``: ``-(H + damping diag(H))^-1 g``,
    the diagonal floored at 1e-12 of its largest entry so that a direction the rays do not constrain
    stays solvable. Raises ``numpy.linalg.LinAlgError`` when it is not."""
    diag = np.maximum(np.diag(H), 1e-12 * max(float(np.diag(H).max()), 1e-30))
    return -np.linalg.solve(H + damping * np.diag(diag), g)


def apply_step(T_world_cam: np.ndarray, step: np.ndarray) -> np.ndarray:
    """The pose after the update ``step`` = (omega, dt): ``R = exp(omega) R``, ``t = t + dt`` (float64), the
    parameterisation of :func:`~neb_slam_core.geometry.lie.compose_delta`."""
    T = torch.as_tensor(np.asarray(T_world_cam, dtype=np.float64))
    return compose_delta(T, torch.as_tensor(np.asarray(step, dtype=np.float64))).numpy()
