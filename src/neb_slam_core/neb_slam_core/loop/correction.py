"""Loop correction: the current keyframe's pose by the paper's reprojection objective, then the
correction spread along the keyframes of the loop.

Reprojection objective (paper, "Loop Closure", its equation for T_c): a pixel ``u_j`` of the current
keyframe with depth ``d_j`` becomes the world point ``P_j = T_c pi^-1(u_j, d_j)``; projected into loop
keyframe ``r``, it lands on ``u_rj = pi(T_r^-1 P_j)``, where that keyframe's depth map, interpolated,
gives ``d'_rj``; the point ``pi'^-1(u_rj, d'_rj)`` taken back through ``T_c^-1 T_r`` projects to
``u'_rj`` in the current keyframe, and ``T_c`` minimises ``sum_r sum_j |u'_rj - u_j|^2``. It is a
projective point-to-surface alignment: with the right pose the loop keyframe's surface passes through
``P_j`` and the point comes back to its own pixel.

One addition of ours: the surface point differs from ``P_j`` only along loop keyframe ``r``'s ray, so
``u'_rj - u_j`` sees that difference only through the parallax between the two views. A loop keyframe
is typically close to the current one (that is why it was found): on a box corner seen from 10-40 cm
away at 2-4 m, a pose 7 cm and 2 degrees off leaves 0.2 px RMS, and the minimiser stops 4 cm from the
truth. So each pair also has the depth disagreement itself, ``d'_rj - z_rj`` (``z_rj`` = the depth of
``P_j`` in ``r``), expressed in pixels as ``f (d'_rj - z_rj) / z_rj``: what the paper's term would show
if ``r`` looked at the point from the side. With it the fit converges to the pose (see the tests).

We solve it with scipy's trust-region least squares on a 6-vector (rotation vector and translation),
robustly (:func:`fit_loop_pose`): occlusions and depth edges give a few large residuals that a plain
square would follow.

Depth interpolation is bilinear where all four neighbours have depth; elsewhere the residual is zero
(and the pixel does not count as valid). Depth maps are kept at a stride (``LoopConfig.depth_stride``)
with intrinsics scaled to match.

Propagation, a pose graph over the loop: the keyframes from the loop's older end (held) to the current
one are the nodes; each consecutive pair is an edge that wants their relative pose as tracking and
mapping left it, and the loop is one more edge that puts the current keyframe at its fitted pose. The
nodes minimise the edges' squared errors (rotation vector times 1 m, and translation, in metres), each
edge weighted by the inverse of the path length it spans (plus 1 cm): tracking drift accumulates with
the distance travelled, so a long step may absorb more of the correction than a short one. A pure
translation is then spread in proportion to the path travelled; a rotation is spread over the edges as
small turns, with the positions following the turned edges. That is how drift accrues: a uniform
turning drift along a chain is undone exactly (see the tests), where rotating every keyframe by a
share of the rotation about one point would not. It starts from that simpler spreading and is solved
with scipy's sparse least squares (each edge sees only its two nodes). Keyframes after the current one
(a loop closed while tracking went on) move rigidly with it.

Registration edges (ours): path lengths alone cannot say where along the loop the drift came in, and
drift often comes in a few steps (a stretch where tracking is weak). Each keyframe's depth is also
registered against the keyframes just before it (the same objective as the loop fit, see
:class:`~neb_slam_core.loop.closer.LoopCloser`), and those relative poses join the graph as edges beside
the tracked ones, weighted the same way. Where tracking drifted, the two disagree and the loop's
correction goes there; where they agree, the chain is stiffer. ``benchmarks/pose_graph_edges.py``
measures the effect on runs without loop closure.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from ..geometry.se3 import interpolate_correction, invert, so3_left_jacobian
from ..types import Intrinsics


@dataclass(frozen=True)
class DepthView:
    """A keyframe as the correction sees it: pose and depth map (metres, 0 = none) with its camera."""

    T_world_cam: np.ndarray
    depth_m: np.ndarray
    intrinsics: Intrinsics


@dataclass(frozen=True)
class PoseFit:
    """Outcome of :func:`fit_loop_pose`.

    Attributes:
        T_world_cam: the optimised pose of the current keyframe.
        rms_px_start, rms_px: RMS of the paper's reprojection error (pixels, over valid pairs) at the start
            and at the end.
        n_valid: pixel/loop-keyframe pairs with a valid residual at the end.
        n_pixels: pixels of the current keyframe used.
    """

    T_world_cam: np.ndarray
    rms_px_start: float
    rms_px: float
    n_valid: int
    n_pixels: int


def strided_view(T_world_cam: np.ndarray, depth_m: np.ndarray, intrinsics: Intrinsics, stride: int) -> DepthView:
    """A :class:`DepthView` keeping every ``stride``-th depth pixel (nearest: no blending across edges)."""
    depth = np.ascontiguousarray(np.asarray(depth_m, dtype=np.float32)[::stride, ::stride])
    k = intrinsics
    h, w = depth.shape
    # pixel centres: strided pixel i is full-resolution pixel stride * i
    scaled = Intrinsics(k.fx / stride, k.fy / stride, k.cx / stride, k.cy / stride, w, h)
    return DepthView(np.array(T_world_cam, dtype=np.float64), depth, scaled)


def sample_pixels(depth_m: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``n`` random pixels ``(N, 2)`` (u, v) with valid depth, and their depths ``(N,)``."""
    v, u = np.nonzero(np.asarray(depth_m) > 0)
    if len(u) > n:
        keep = rng.choice(len(u), n, replace=False)
        u, v = u[keep], v[keep]
    return np.stack([u, v], axis=1).astype(np.float64), np.asarray(depth_m)[v, u].astype(np.float64)


def _project(points_cam: np.ndarray, k: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    z = points_cam[:, 2]
    in_front = z > 1e-6
    z = np.where(in_front, z, 1.0)
    return np.stack([k.fx * points_cam[:, 0] / z + k.cx, k.fy * points_cam[:, 1] / z + k.cy], axis=1), in_front


def _backproject(pixels: np.ndarray, depth: np.ndarray, k: Intrinsics) -> np.ndarray:
    return np.stack([(pixels[:, 0] - k.cx) / k.fx * depth, (pixels[:, 1] - k.cy) / k.fy * depth, depth], axis=1)


class _Interpolator:
    """Bilinear depth lookup of one view, valid only where the four neighbours all have depth, with its
    slope in the pixel coordinates (within the cell; the fit's Jacobian needs it).

    In float64 numpy rather than ``cv2.remap``, whose weights are quantised to 1/32 px."""

    def __init__(self, depth_m: np.ndarray):
        self.depth = np.asarray(depth_m, dtype=np.float64)

    def __call__(self, pixels: np.ndarray, slope: bool = False):
        """Depths ``(N,)`` at ``(N, 2)`` pixels (u, v) and their validity; with ``slope``, also
        ``(N, 2)`` d depth / d (u, v)."""
        h, w = self.depth.shape
        x, y = pixels[:, 0], pixels[:, 1]
        inside = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
        x0 = np.clip(np.floor(x), 0, w - 2).astype(np.int64)
        y0 = np.clip(np.floor(y), 0, h - 2).astype(np.int64)
        fx, fy = np.clip(x - x0, 0.0, 1.0), np.clip(y - y0, 0.0, 1.0)
        flat = self.depth.ravel()
        i00 = y0 * w + x0  # one index into the flat map: four 1-D takes are cheaper than 2-D fancy indexing
        d00, d01 = flat.take(i00), flat.take(i00 + 1)
        d10, d11 = flat.take(i00 + w), flat.take(i00 + w + 1)
        d = (d00 * (1 - fx) + d01 * fx) * (1 - fy) + (d10 * (1 - fx) + d11 * fx) * fy
        ok = inside & (d00 > 0) & (d01 > 0) & (d10 > 0) & (d11 > 0)
        if not slope:
            return np.where(ok, d, 0.0), ok
        grad = np.stack([(d01 - d00) * (1 - fy) + (d11 - d10) * fy, (d10 - d00) * (1 - fx) + (d11 - d01) * fx], axis=1)
        return np.where(ok, d, 0.0), ok, grad


def _projection_slopes(d_points: np.ndarray, points: np.ndarray, k: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """How the pinhole pixel (u, v) of camera-frame ``points`` (N, 3) moves with them: ``d_points`` is
    ``(3, N, 6)`` (component, point, parameter); returns ``du``, ``dv``, each ``(N, 6)``."""
    z = np.where(points[:, 2] > 1e-6, points[:, 2], 1.0)[:, None]
    du = k.fx * (d_points[0] - points[:, 0:1] / z * d_points[2]) / z
    dv = k.fy * (d_points[1] - points[:, 1:2] / z * d_points[2]) / z
    return du, dv


def _rotate(R: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``R @`` every column of the ``(3, N, 6)`` derivative ``d`` (one matrix product)."""
    return (R @ d.reshape(3, -1)).reshape(d.shape)


def _add_cross(d: np.ndarray, a: np.ndarray, sign: float) -> None:
    """``d[:, :, :3] += sign * skew(a)`` in place: the rotation columns of ``(3, N, 6)`` ``d`` gain
    ``sign * (a x phi)`` for ``(N, 3)`` ``a``."""
    d[0, :, 1] -= sign * a[:, 2]
    d[0, :, 2] += sign * a[:, 1]
    d[1, :, 0] += sign * a[:, 2]
    d[1, :, 2] -= sign * a[:, 0]
    d[2, :, 0] -= sign * a[:, 1]
    d[2, :, 1] += sign * a[:, 0]


def reprojection_residuals(
    T_world_cur: np.ndarray,
    pixels: np.ndarray,
    depths: np.ndarray,
    intrinsics: Intrinsics,
    views: list[DepthView],
    _lookups: list[_Interpolator] | None = None,
    jacobian: bool = False,
):
    """The loop residuals for every view ``r`` and pixel ``j``: the paper's ``u'_rj - u_j`` and the depth
    disagreement in pixels (see the module docstring), at the current keyframe's pose ``T_world_cur``.

    Returns:
        ``(R, N, 3)`` residuals in pixels (0 where invalid) and the ``(R, N)`` validity mask; with
        ``jacobian``, also ``(R, N, 3, 6)``: their derivatives in a perturbation ``(phi, delta)`` of the pose,
        ``R -> exp(phi) R``, ``t -> t + delta`` (0 where invalid; within a depth pixel's bilinear cell).
    """
    lookups = _lookups or [_Interpolator(v.depth_m) for v in views]
    T = np.asarray(T_world_cur, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    n = len(pixels)
    points_world = _backproject(pixels, depths, intrinsics) @ R.T + t
    res = np.zeros((len(views), n, 3))
    valid = np.zeros((len(views), n), bool)
    jac = np.zeros((len(views), n, 3, 6)) if jacobian else None
    for r, (view, lookup) in enumerate(zip(views, lookups)):
        R_r, t_r, k_r = view.T_world_cam[:3, :3], view.T_world_cam[:3, 3], view.intrinsics
        in_r = (points_world - t_r) @ R_r
        u_r, front = _project(in_r, k_r)
        d_r, ok, *slope = lookup(u_r, slope=jacobian)
        ok &= front & (d_r > 0)
        surface_r = _backproject(u_r, d_r, k_r)
        surface_w = surface_r @ R_r.T + t_r
        back = (surface_w - t) @ R
        u_back, front_back = _project(back, intrinsics)
        ok &= front_back
        z_r = np.where(front, in_r[:, 2], 1.0)
        r_all = np.concatenate([u_back - pixels, (intrinsics.fx * (d_r - z_r) / z_r)[:, None]], axis=1)
        res[r] = np.where(ok[:, None], r_all, 0.0)
        valid[r] = ok
        if jacobian:
            # the chain of the residual; derivatives are (3, N, 6): component, pixel, (phi, delta). The
            # world point moves by phi x (P - t) + delta; its pixel in r with it; the depth read there
            # with the pixel; the surface point with both; the way back into the current camera with
            # the pose itself
            d_world = np.zeros((3, n, 6))
            _add_cross(d_world, points_world - t, -1.0)
            d_world[0, :, 3] = d_world[1, :, 4] = d_world[2, :, 5] = 1.0
            d_in_r = _rotate(R_r.T, d_world)
            du_r, dv_r = _projection_slopes(d_in_r, in_r, k_r)
            d_depth = slope[0][:, 0:1] * du_r + slope[0][:, 1:2] * dv_r  # (N, 6)
            d_surface = np.stack(
                [
                    (d_r[:, None] * du_r + (u_r[:, 0] - k_r.cx)[:, None] * d_depth) / k_r.fx,
                    (d_r[:, None] * dv_r + (u_r[:, 1] - k_r.cy)[:, None] * d_depth) / k_r.fy,
                    d_depth,
                ]
            )
            d_back_w = _rotate(R_r, d_surface)  # the surface point in the world, then seen from the
            _add_cross(d_back_w, surface_w - t, 1.0)  # current camera turning: (W - t) x phi
            d_back_w[0, :, 3] -= 1.0  # and moving
            d_back_w[1, :, 4] -= 1.0
            d_back_w[2, :, 5] -= 1.0
            du_back, dv_back = _projection_slopes(_rotate(R.T, d_back_w), back, intrinsics)
            d_depth_px = intrinsics.fx * (d_depth - (d_r / z_r)[:, None] * d_in_r[2]) / z_r[:, None]
            jac[r] = np.where(ok[:, None, None], np.stack([du_back, dv_back, d_depth_px], axis=1), 0.0)
    return (res, valid, jac) if jacobian else (res, valid)


def fit_loop_pose(
    T_world_init: np.ndarray,
    pixels: np.ndarray,
    depths: np.ndarray,
    intrinsics: Intrinsics,
    views: list[DepthView],
    loss_scale_px: float = 1.0,
    min_scale_px: float = 0.05,
    rounds: int = 3,
    max_evaluations: int = 100,
    ftol: float = 1e-6,
    xtol: float = 1e-4,
) -> PoseFit:
    """Minimise the loop objective over the current keyframe's pose, from ``T_world_init`` (the
    geometric check's estimate), for ``(N, 2)`` pixels with ``(N,)`` depths.

    Robust, coarse to fine: a Cauchy loss (its pull vanishes for large residuals: occluded pixels and
    depth edges, a few percent of the pairs, do not bias the pose, as a bounded pull such as soft-L1's
    would) of scale ``loss_scale_px`` first, then ``rounds - 1`` times of
    scale twice the residuals' robust spread (1.4826 x median absolute residual) at the last pose,
    clipped to [``min_scale_px``, ``loss_scale_px``]: exact synthetic depth ends at the floor, real
    depth at its own noise level.

    Each round stops when a step changes the robust cost by less than ``ftol`` (relative) or moves the
    6-vector by less than ``xtol`` of its length (about a micrometre for a centimetre correction).
    scipy's defaults (1e-8 both) ask for nanometres, about twice the evaluations for poses that differ by
    hundredths of a millimetre, where a fit is accepted up to 2 px RMS (``loop.max_fit_rms_px``).

    The Jacobian is analytic (:func:`reprojection_residuals` with ``jacobian``, chained with the rotation
    vector's :func:`~neb_slam_core.geometry.se3.so3_left_jacobian`): one pass over the pixels where forward
    differences took seven poses' worth.
    """
    lookups = [_Interpolator(v.depth_m) for v in views]
    R0, t0 = T_world_init[:3, :3], T_world_init[:3, 3]

    def pose(x: np.ndarray) -> np.ndarray:  # R = exp(x[:3]) R0, t = t0 + x[3:]
        out = np.eye(4)
        out[:3, :3] = Rotation.from_rotvec(x[:3]).as_matrix() @ R0
        out[:3, 3] = t0 + x[3:]
        return out

    def residuals(x: np.ndarray) -> np.ndarray:
        return reprojection_residuals(pose(x), pixels, depths, intrinsics, views, lookups)[0].ravel()

    def jacobian(x: np.ndarray) -> np.ndarray:
        J = reprojection_residuals(pose(x), pixels, depths, intrinsics, views, lookups, jacobian=True)[2].reshape(-1, 6)
        J[:, :3] = J[:, :3] @ so3_left_jacobian(x[:3])  # exp(x + d) = exp(J_l d) exp(x): phi = J_l d
        return J

    def rms(T: np.ndarray) -> tuple[float, int, np.ndarray]:
        r, ok = reprojection_residuals(T, pixels, depths, intrinsics, views, lookups)
        n = int(ok.sum())
        return (float(np.sqrt((r[ok][:, :2] ** 2).sum(axis=1).mean())) if n else float("inf")), n, r[ok]

    rms_start, _, _ = rms(T_world_init)
    x, scale = np.zeros(6), loss_scale_px
    for round_ in range(rounds):
        if round_ > 0:
            _, n, r = rms(pose(x))
            spread = 1.4826 * float(np.median(np.abs(r))) if n else loss_scale_px
            scale = float(np.clip(2.0 * spread, min_scale_px, loss_scale_px))
        x = least_squares(
            residuals,
            x,
            jac=jacobian,
            loss="cauchy",
            f_scale=scale,
            max_nfev=max_evaluations,
            x_scale=np.full(6, 1e-2),
            ftol=ftol,
            xtol=xtol,
        ).x
    T = pose(x)
    rms_end, n_valid, _ = rms(T)
    return PoseFit(T, rms_start, rms_end, n_valid, len(pixels))


#: rotation errors count as the arc length they sweep at this distance (metres per radian)
_ROTATION_ARM_M = 1.0
#: an edge's variance is the path length it spans plus this (metres): no edge is free to absorb it all
_MIN_EDGE_M = 0.01


def _shared_correction(poses: np.ndarray, start_id: int, end_id: int, T_end_new: np.ndarray) -> np.ndarray:
    """The correction spread by path length, rotation about the current keyframe: the pose graph's start."""
    delta = T_end_new @ invert(poses[end_id])
    pivot = poses[end_id][:3, 3].copy()
    steps = np.linalg.norm(np.diff(poses[start_id : end_id + 1, :3, 3], axis=0), axis=1)
    travelled = np.concatenate([[0.0], np.cumsum(steps)])
    shares = travelled / travelled[-1] if travelled[-1] > 0 else np.linspace(0.0, 1.0, len(travelled))
    out = poses[start_id : end_id + 1].copy()
    for k, w in enumerate(shares[1:], start=1):
        out[k] = interpolate_correction(delta, pivot, float(w)) @ out[k]
    return out


def _edge_errors(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``(n, 6)`` errors of ``inv(A_i) B_i`` (rotation vector times the arm, translation), batched."""
    E_R = np.einsum("nji,njk->nik", A[:, :3, :3], B[:, :3, :3])
    E_t = np.einsum("nji,nj->ni", A[:, :3, :3], B[:, :3, 3] - A[:, :3, 3])
    return np.concatenate([_ROTATION_ARM_M * Rotation.from_matrix(E_R).as_rotvec(), E_t], axis=1)


def _edge_weight(Z: np.ndarray) -> np.ndarray:
    """``(n,)`` weights of relative poses ``(n, 4, 4)``: 1 / sqrt(the path length they span + 1 cm)."""
    return 1.0 / np.sqrt(np.linalg.norm(Z[:, :3, 3], axis=1) + _MIN_EDGE_M)


def propagate_correction(
    poses: np.ndarray,
    start_id: int,
    end_id: int,
    T_end_new: np.ndarray,
    registrations: Mapping[tuple[int, int], np.ndarray] | None = None,
) -> np.ndarray:
    """Keyframe poses ``(K, 4, 4)`` after moving keyframe ``end_id`` to ``T_end_new``, the loop's older
    end ``start_id`` and every keyframe before it held (the pose graph of the module docstring).

    ``registrations`` maps keyframe pairs ``(i, j)`` to a measured relative pose ``inv(T_i) T_j``
    (``(4, 4)``, e.g. a depth registration of ``j`` against ``i``); those with both ends in
    ``start_id .. end_id`` join the graph as edges beside the tracked ones, weighted the same way."""
    from scipy.sparse import lil_matrix

    poses = np.array(poses, dtype=np.float64)
    T_end_new = np.array(T_end_new, dtype=np.float64)
    if not 0 <= start_id < end_id < len(poses):
        raise ValueError(f"propagate_correction: need 0 <= start_id ({start_id}) < end_id ({end_id}) < {len(poses)}")
    chain = poses[start_id : end_id + 1]
    n = end_id - start_id  # nodes 0 (held) and n (the fitted pose) are fixed
    # edges: the tracked consecutive ones, Z_i = inv(T_i) T_i+1, then the registrations inside the chain
    first, second = list(range(n)), list(range(1, n + 1))
    measured = [np.einsum("nij,njk->nik", np.linalg.inv(chain[:-1]), chain[1:])]
    for (i, j), Z in sorted((registrations or {}).items()):
        if start_id <= i < j <= end_id:
            first.append(i - start_id)
            second.append(j - start_id)
            measured.append(np.asarray(Z, dtype=np.float64)[None])
    first_a, second_a, measured_a = np.array(first), np.array(second), np.concatenate(measured)
    weights = _edge_weight(measured_a)
    fixed = chain.copy()
    fixed[-1] = T_end_new

    def nodes(x: np.ndarray) -> np.ndarray:
        x = x.reshape(n - 1, 6)
        out = fixed.copy()
        out[1:-1, :3, :3] = Rotation.from_rotvec(x[:, :3]).as_matrix() @ chain[1:-1, :3, :3]
        out[1:-1, :3, 3] = chain[1:-1, :3, 3] + x[:, 3:]
        return out

    def residuals(x: np.ndarray) -> np.ndarray:
        T = nodes(x)
        relative = np.einsum("nij,njk->nik", np.linalg.inv(T[first_a]), T[second_a])
        return (_edge_errors(measured_a, relative) * weights[:, None]).ravel()

    start = _shared_correction(poses, start_id, end_id, T_end_new)
    x = np.zeros(0)
    if n > 1:
        # edge e joins nodes first[e] and second[e]; free node k (1..n-1) is x[k-1]
        sparsity = lil_matrix((6 * len(first), 6 * (n - 1)), dtype=int)
        for e, ends in enumerate(zip(first, second)):
            for k in ends:
                if 1 <= k <= n - 1:
                    sparsity[6 * e : 6 * e + 6, 6 * (k - 1) : 6 * k] = 1
        R0 = start[1:-1, :3, :3] @ np.transpose(chain[1:-1, :3, :3], (0, 2, 1))
        x0 = np.concatenate([Rotation.from_matrix(R0).as_rotvec(), start[1:-1, :3, 3] - chain[1:-1, :3, 3]], axis=1)
        x = least_squares(residuals, x0.ravel(), jac_sparsity=sparsity, method="trf", x_scale=1e-2, max_nfev=100).x
    out = poses.copy()
    out[start_id : end_id + 1] = nodes(x)
    out[end_id + 1 :] = T_end_new @ invert(poses[end_id]) @ poses[end_id + 1 :]
    return out


def correction_size(T_old: np.ndarray, T_new: np.ndarray) -> tuple[float, float]:
    """Translation (cm) and rotation (degrees) between two poses of one camera."""
    E = invert(T_old) @ T_new
    return float(np.linalg.norm(E[:3, 3]) * 100.0), float(np.degrees(Rotation.from_matrix(E[:3, :3]).magnitude()))


def merge_correction(poses: np.ndarray, first_id: int, corrected: np.ndarray) -> np.ndarray:
    """Keyframe poses ``(K, 4, 4)`` with keyframes ``first_id .. first_id + n - 1`` replaced by the ``(n, 4, 4)``
    ``corrected`` ones (a loop correction computed elsewhere, e.g. by another process) and the keyframes
    after them, which that computation did not know, moved rigidly with the last of them."""
    poses = np.array(poses, dtype=np.float64)
    corrected = np.asarray(corrected, dtype=np.float64).reshape(-1, 4, 4)
    end = first_id + len(corrected) - 1
    if len(corrected) == 0 or not 0 < first_id <= end < len(poses):
        raise ValueError(f"merge_correction: keyframes {first_id}..{end} are not after the first of {len(poses)}")
    delta = corrected[-1] @ invert(poses[end])
    out = poses.copy()
    out[first_id : end + 1] = corrected
    out[end + 1 :] = delta @ poses[end + 1 :]
    return out
