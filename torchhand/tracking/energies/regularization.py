"""E_regularization: stay near the previous frame's joint angles (thesis Eq. 4.18).

``E = sum_k (theta_k - theta~_k)^2`` over the revolute joints; the tracker weights it by
gamma_r = 0.02 C_all (C_all: the problem's number of data correspondences;
:data:`DEFAULT_WEIGHT`), so the previous pose decides only where the data cannot.
"""

from __future__ import annotations

import torch

from torchhand.tracking.energies.base import EnergyTerm, Prepared, Residuals, TrackState, prepared

__all__ = ["Regularization", "DEFAULT_WEIGHT"]

#: gamma_r per data correspondence (thesis: 0.02)
DEFAULT_WEIGHT = 0.02


class Regularization(EnergyTerm):
    """E_regularization. ``root_weight``: weight of the global DoF (mm and rad)
    relative to the joints' (0: the global pose is free, as in the thesis)."""

    name = "regularization"
    prior = True

    def __init__(self, root_weight: float = 0.0):
        if not root_weight >= 0:
            raise ValueError(f"root_weight must be >= 0, got {root_weight!r}")
        self.root_weight = float(root_weight)

    def prepare(self, state: TrackState) -> Prepared:
        lo, hi = state.scene.lower, state.scene.upper
        joint = torch.isfinite(lo) & torch.isfinite(hi)
        # (D,): revolute joints 1, the global DoF sqrt(root_weight)
        self.scale = torch.where(joint, torch.ones_like(lo), torch.full_like(lo, self.root_weight ** 0.5)).to(state.theta)
        self.previous = state.previous
        return prepared(state.theta.shape[0], device=state.theta.device)

    def residuals(self, theta, posed, jacobian=True):
        r = self.scale * (theta - self.previous)
        J = torch.diag_embed(self.scale.expand_as(theta)) if jacobian else None
        return Residuals(r, J)
