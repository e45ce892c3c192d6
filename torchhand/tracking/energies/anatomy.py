"""E_anatomy: soft joint limits (thesis Eq. 4.17).

``E = sum_k exp(p (l_k - theta_k)) + exp(p (theta_k - u_k))`` over the revolute
joints, p = 10 (angles in radians). As a least-squares term the residual of joint k is
``sqrt(E_k)``; the tracker weights it by gamma_a = 0.0015 C_all, where C_all is the
number of data correspondences of the problem (:data:`DEFAULT_WEIGHT`, a
per-correspondence :class:`~torchhand.tracking.energies.wrappers.Weighted`).
"""

from __future__ import annotations

import torch

from torchhand.tracking.energies.base import EnergyTerm, Prepared, Residuals, TrackState, prepared

__all__ = ["Anatomy", "DEFAULT_WEIGHT"]

#: gamma_a per data correspondence (thesis: 0.0015)
DEFAULT_WEIGHT = 0.0015


class Anatomy(EnergyTerm):
    """E_anatomy. ``p``: the steepness of the soft limits (10 per radian)."""

    name = "anatomy"
    prior = True

    def __init__(self, p: float = 10.0):
        self.p = float(p)
        self.scale = 1.0  # the folded weight (B, 1), see fold_weight

    def prepare(self, state: TrackState) -> Prepared:
        if getattr(self, "_scene", None) is not state.scene:  # the limited joints, once per scene
            lo, hi = state.scene.lower, state.scene.upper
            self.joints = torch.nonzero(torch.isfinite(lo) & torch.isfinite(hi))[:, 0]
            self.lo, self.hi, self._scene = lo[self.joints], hi[self.joints], state.scene
        self.scale = 1.0
        return prepared(state.theta.shape[0], device=state.theta.device)

    def fold_weight(self, weight):
        self.scale = weight  # r = sqrt(w E_k): one square root of the weighted energy
        return True

    def residuals(self, theta, posed, jacobian=True):
        t = theta[:, self.joints]
        a, b = torch.exp(self.p * (self.lo - t)), torch.exp(self.p * (t - self.hi))
        r = (self.scale * (a + b)).sqrt()
        if not jacobian:
            return Residuals(r, None)
        dr = self.scale * self.p * (b - a) / (2 * r)
        J = theta.new_zeros(theta.shape[0], len(self.joints), theta.shape[1])
        J[:, torch.arange(len(self.joints)), self.joints] = dr
        return Residuals(r, J)
