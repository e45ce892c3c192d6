"""E_anatomy: soft joint limits (thesis Eq. 4.17).

``E = sum_k exp(p (l_k - theta_k)) + exp(p (theta_k - u_k))`` over the revolute
joints, p = 10 (angles in radians). As a least-squares term the residual of joint k is
``sqrt(E_k)``; the tracker weights it by gamma_a = 0.0015 C_all, where C_all is the
number of data correspondences of the problem (:data:`DEFAULT_WEIGHT`, a
per-correspondence :class:`~torchhand.tracking.energies.wrappers.Weighted`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from torchhand.tracking.energies.base import EnergyTerm, Prepared, Residuals, TrackState, counts

__all__ = ["Anatomy", "AnatomyPrepared", "DEFAULT_WEIGHT"]

#: gamma_a per data correspondence (thesis: 0.0015)
DEFAULT_WEIGHT = 0.0015


@dataclass(frozen=True, eq=False)
class AnatomyPrepared(Prepared):
    """Prepared data of :class:`Anatomy`: ``joints`` (J,) int64 the limited DoF,
    ``lower``/``upper`` (J,) their limits, ``scale`` the weight folded into the energy
    (1.0, or (B, 1) per problem)."""

    joints: torch.Tensor
    lower: torch.Tensor
    upper: torch.Tensor
    scale: object = 1.0


class Anatomy(EnergyTerm):
    """E_anatomy. ``p``: the steepness of the soft limits (10 per radian)."""

    name = "anatomy"
    prior = True

    def __init__(self, p: float = 10.0):
        self.p = float(p)
        self._limits = None  # (scene, joints, lower, upper): the limited DoF, found once per scene (a host sync)

    def prepare(self, state: TrackState) -> AnatomyPrepared:
        if self._limits is None or self._limits[0] is not state.scene:
            lo, hi = state.scene.lower, state.scene.upper
            joints = torch.nonzero(torch.isfinite(lo) & torch.isfinite(hi))[:, 0]
            self._limits = (state.scene, joints, lo[joints], hi[joints])
        return AnatomyPrepared(counts(state.theta.shape[0], device=state.theta.device), *self._limits[1:])

    def fold_weight(self, prepared: AnatomyPrepared, weight):
        return replace(prepared, scale=weight)  # r = sqrt(w E_k): one square root of the weighted energy

    def residuals(self, theta, posed, prepared: AnatomyPrepared, jacobian=True):
        p = prepared
        t = theta[:, p.joints]
        a, b = torch.exp(self.p * (p.lower - t)), torch.exp(self.p * (t - p.upper))
        r = (p.scale * (a + b)).sqrt()
        if not jacobian:
            return Residuals(r, None)
        dr = p.scale * self.p * (b - a) / (2 * r)
        J = theta.new_zeros(theta.shape[0], len(p.joints), theta.shape[1])
        J[:, torch.arange(len(p.joints)), p.joints] = dr
        return Residuals(r, J)
