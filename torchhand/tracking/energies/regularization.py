"""E_regularization: stay near the previous frame's joint angles (thesis Eq. 4.18).

``E = sum_k (theta_k - theta~_k)^2`` over the revolute joints, weighted by
gamma_r = 0.02 C_all (C_all: the problem's number of data correspondences), so the
previous pose decides only where the data cannot.
"""

from __future__ import annotations

import torch

from torchhand.tracking.energies.base import EnergyTerm, Residuals, TrackState

__all__ = ["Regularization"]


class Regularization(EnergyTerm):
    name = "regularization"

    def __init__(self, gamma_per_correspondence: float = 0.02, root_weight: float = 0.0):
        super().__init__(1.0)
        self.gamma, self.root_weight = gamma_per_correspondence, root_weight

    def prepare(self, state: TrackState, correspondences: torch.Tensor | None = None) -> None:
        lo, hi = state.scene.lower, state.scene.upper
        joint = torch.isfinite(lo) & torch.isfinite(hi)
        c = correspondences if correspondences is not None else torch.ones(state.theta.shape[0])
        g = (self.gamma * c.to(state.theta)).clamp_min(1e-6)[:, None]
        # revolute joints get gamma_r; the global DoF (mm and rad) only root_weight
        self.sqrt_w = torch.where(joint, g, torch.full_like(g, self.root_weight)).sqrt()  # (B, D)
        self.previous = state.previous

    def residuals(self, theta, posed, with_jacobian):
        r = self.sqrt_w * (theta - self.previous)
        J = torch.diag_embed(self.sqrt_w) if with_jacobian else None
        return Residuals(r, J)
