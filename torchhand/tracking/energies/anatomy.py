"""E_anatomy: soft joint limits (thesis Eq. 4.17).

``E = sum_k exp(p (l_k - theta_k)) + exp(p (theta_k - u_k))`` over the revolute
joints, p = 10 (angles in radians), weighted by gamma_a = 0.0015 C_all where C_all
is the number of data correspondences of the problem. As a least-squares term the
residual of joint k is sqrt(gamma_a E_k).
"""

from __future__ import annotations

import torch

from torchhand.tracking.energies.base import EnergyTerm, Residuals, TrackState

__all__ = ["Anatomy"]


class Anatomy(EnergyTerm):
    name = "anatomy"

    def __init__(self, gamma_per_correspondence: float = 0.0015, p: float = 10.0):
        super().__init__(1.0)
        self.gamma, self.p = gamma_per_correspondence, p

    def prepare(self, state: TrackState, correspondences: torch.Tensor | None = None) -> None:
        lo, hi = state.scene.lower, state.scene.upper
        self.joints = torch.nonzero(torch.isfinite(lo) & torch.isfinite(hi))[:, 0]
        self.lo, self.hi = lo[self.joints], hi[self.joints]
        c = correspondences if correspondences is not None else torch.ones(state.theta.shape[0])
        self.scale = (self.gamma * c.to(state.theta)).clamp_min(1e-6)[:, None]  # (B, 1)

    def residuals(self, theta, posed, with_jacobian):
        t = theta[:, self.joints]
        a, b = torch.exp(self.p * (self.lo - t)), torch.exp(self.p * (t - self.hi))
        r = (self.scale * (a + b)).sqrt()
        if not with_jacobian:
            return Residuals(r, None)
        dr = self.scale * self.p * (b - a) / (2 * r)
        J = theta.new_zeros(theta.shape[0], len(self.joints), theta.shape[1])
        J[:, torch.arange(len(self.joints)), self.joints] = dr
        return Residuals(r, J)
