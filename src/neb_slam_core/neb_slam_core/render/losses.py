"""The paper's objective, defined once: each loss is a :class:`Residual` term, and both optimisers read
the same terms.

A term is a tensor of residuals ``r`` (one row per ray, ``K`` entries per row: colour channels, samples
along the ray, neighbour differences), a mask of the entries that count, and the term's weight. Its loss
is the mean (or sum) of ``r^2`` over each row's masked entries, then the mean over the rows that have
at least one: for the SDF and free-space terms that is the paper's "mean over each ray's samples, then
over the rays". The objective is the weighted sum of the terms' losses.

- Adam (mapping, and the paper's tracking) back-propagates through :meth:`Objective.total`.
- Gauss-Newton tracking (:mod:`neb_slam_core.tracking.gauss_newton`) reads each term's residuals, its
  per-entry weights (:meth:`Residual.entry_weights`, which make ``sum(w r^2)`` the weighted loss) and
  what the residual is an affine function of (``source`` and ``slope``): the rendered colour, the
  rendered depth or the samples' SDF. It needs no code of its own for a new term of one of those kinds.

Units follow Co-SLAM, whose weights the paper adopts: the SDF term compares metric signed distances
(``tr * sdf`` against ``d_obs - z``), the free-space term compares the normalised prediction with 1
(the truncation distance).

A new loss: a weight in :class:`~neb_slam_core.config.LossWeights` (and ``configs/base.yaml``), and one
entry in :func:`render_residuals` (or a builder like :func:`smoothness_residual` for a term that is not
rendered along rays).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..config import LossWeights

#: what a term's residuals can be an affine function of: the rays' rendered colour (R, 3) and depth
#: (R,), the samples' predicted SDF (R, S); None: the term does not depend on the camera pose
SOURCES = ("rgb", "depth", "sdf", None)


@dataclass
class Residual:
    """One term of the objective.

    Attributes:
        r: ``(R, K)`` residuals.
        mask: ``(R, K)`` bool, the entries that count.
        weight: the term's weight in the objective.
        source: what ``r`` is an affine function of (one of :data:`SOURCES`), with ``K`` its entries per row.
        slope: ``d r / d source`` (a scalar).
        per_row: ``"mean"`` or ``"sum"`` of each row's masked squared entries.
        active_above: the Gauss-Newton model takes a masked entry into its matrix only where ``|r|``
            exceeds this (0: every masked entry); the cost a step is judged by always has them all.
        row_weight: ``(R,)`` a weight per row, multiplying the row's share of the mean over rows (None:
            1 for every row).
    """

    r: torch.Tensor
    mask: torch.Tensor
    weight: float
    source: str | None
    slope: float = 1.0
    per_row: str = "mean"
    active_above: float = 0.0
    row_weight: torch.Tensor | None = None

    def _counts(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The mask as numbers, each row's count of entries, each row's weight (0 for a row without
        entries) and the number of rows with entries (at least 1: what the mean over rows divides by)."""
        m = self.mask.to(self.r.dtype)
        n = m.sum(dim=-1)
        has_entries = n > 0
        rows = has_entries.to(self.r.dtype)
        if self.row_weight is not None:
            rows = rows * self.row_weight
        return m, n, rows, has_entries.sum().clamp(min=1)

    def value(self) -> torch.Tensor:
        """The term's loss (a scalar, without its weight)."""
        m, n, rows, n_rows = self._counts()
        per_row = (self.r * self.r * m).sum(dim=-1)
        if self.per_row == "mean":
            per_row = per_row / n.clamp(min=1)
        return (per_row * rows).sum() / n_rows

    def entry_weights(self) -> torch.Tensor:
        """``(R, K)`` weights ``w`` with ``sum(w r^2) = weight * value()`` (0 off the mask)."""
        m, n, rows, n_rows = self._counts()
        per_entry = m / (n.clamp(min=1)[:, None] if self.per_row == "mean" else 1.0)
        return (self.weight / n_rows) * rows[:, None] * per_entry


@dataclass
class Objective:
    """The terms of the objective, their losses and the weighted total."""

    terms: dict[str, Residual]
    values: dict[str, torch.Tensor]
    total: torch.Tensor

    def as_floats(self) -> dict[str, float]:
        out = {name: float(v.detach()) for name, v in self.values.items()}
        out["total"] = float(self.total.detach())
        return out


def combine(terms: dict[str, Residual]) -> Objective:
    """The objective of ``terms``: each term's loss and the weighted sum (in the terms' order)."""
    values = {name: term.value() for name, term in terms.items()}
    total = None
    for name, term in terms.items():
        part = term.weight * values[name]
        total = part if total is None else total + part
    if total is None:
        raise ValueError("an objective needs at least one term")
    return Objective(terms, values, total)


#: the axial noise of a Kinect v1 depth measurement, ``sigma(z) = a + b (z - c)^2`` (metres; Nguyen, Izadi
#: and Lovell, "Modeling Kinect sensor noise for improved 3D reconstruction and tracking", 3DIMPVT 2012)
KINECT_DEPTH_NOISE = (0.0012, 0.0019, 0.4)


def depth_noise_weights(depth_obs: torch.Tensor) -> torch.Tensor:
    """``(R,)`` weights of rays with measured depths ``depth_obs`` (0: none): ``1 / sigma(z)^2`` of
    :data:`KINECT_DEPTH_NOISE`, scaled to a mean of 1 over the rays with depth (0 for the others), so
    that the losses keep the paper's scale and only their balance across depths changes. The growth with
    the square of the depth is that of any camera that triangulates depth (structured light, stereo);
    the constants set how fast the weight falls beyond a metre."""
    a, b, c = KINECT_DEPTH_NOISE
    has_depth = depth_obs > 0
    inverse_variance = torch.where(has_depth, 1.0 / (a + b * (depth_obs - c) ** 2) ** 2, torch.zeros_like(depth_obs))
    n = has_depth.sum().clamp(min=1)
    return inverse_variance * (n / inverse_variance.sum().clamp(min=torch.finfo(depth_obs.dtype).tiny))


def render_residuals(
    weights: LossWeights,
    truncation_m: float,
    rgb: torch.Tensor,
    depth_m: torch.Tensor,
    sdf: torch.Tensor,
    z: torch.Tensor,
    sample_valid: torch.Tensor,
    observed: torch.Tensor,
    rgb_obs: torch.Tensor,
    depth_obs: torch.Tensor,
    depth_noise: bool = False,
) -> dict[str, Residual]:
    """The four rendering terms of ``R`` rays with ``S`` samples each.

    Args:
        rgb, depth_m: ``(R, 3)``, ``(R,)`` rendered colour and depth.
        sdf: ``(R, S)`` predicted SDF in truncation units; ``z``: ``(R, S)`` sample depths.
        sample_valid: ``(R, S)`` bool, the sample lies in a consulted block.
        observed: ``(R,)`` bool, the ray counts for colour and depth
            (:func:`~neb_slam_core.render.volume.observed_rays`).
        rgb_obs, depth_obs: ``(R, 3)``, ``(R,)`` measurements (depth 0: invalid, the ray's depth, SDF and
            free-space terms ignore it).
        depth_noise: the depth, SDF and free-space rows weighed by :func:`depth_noise_weights` (the
            config's ``render.depth_noise_weights``).
    Returns:
        ``colour`` (per ray, the mean over channels), ``depth`` (m^2), ``sdf`` (m^2, samples within the
        truncation band of the measured depth) and ``free_space`` (truncation units^2, samples in front of
        the band). Samples behind the band are unconstrained (the surface may hide anything there), as
        in Co-SLAM.
    """
    tr = truncation_m
    has_depth = depth_obs > 0
    obs_sdf = depth_obs[:, None] - z  # metres, positive in front of the surface
    band = sample_valid & has_depth[:, None] & (obs_sdf.abs() <= tr)
    front = sample_valid & has_depth[:, None] & (obs_sdf > tr)
    rows = depth_noise_weights(depth_obs) if depth_noise else None
    return {
        "colour": Residual(rgb - rgb_obs, observed[:, None].expand(-1, 3), weights.colour, "rgb"),
        "depth": Residual(
            (depth_m - depth_obs)[:, None], (observed & has_depth)[:, None], weights.depth, "depth", row_weight=rows
        ),
        "sdf": Residual(sdf * tr - obs_sdf, band, weights.sdf, "sdf", slope=tr, row_weight=rows),
        # a satisfied free-space sample barely moves the pose; of the many in front of the surface, only
        # the violated ones enter the Gauss-Newton matrix
        "free_space": Residual(sdf - 1.0, front, weights.free_space, "sdf", active_above=1e-2, row_weight=rows),
    }


def smoothness_residual(
    weight: float, features: torch.Tensor, neighbours: torch.Tensor, valid: torch.Tensor
) -> Residual:
    """Feature smoothness: ``(G, D)`` features at random points, ``(G, 3, D)`` at the points shifted by one
    step along x, y, z; per point the summed squared differences, then the mean over ``valid`` points.
    Independent of the camera pose."""
    g = features.shape[0]
    diff = (neighbours - features[:, None, :]).reshape(g, -1)
    return Residual(diff, valid[:, None].expand_as(diff), weight, None, per_row="sum")
