"""E_regularization: stay near the previous frame's joint angles (thesis Eq. 4.18).

``E = sum_k (theta_k - theta~_k)^2`` over the revolute joints; the tracker weights it by
gamma_r = 0.02 C_all (C_all: the problem's number of data correspondences;
:data:`DEFAULT_WEIGHT`), so the previous pose decides only where the data cannot.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchhand.core.check import check_number
from torchhand.tracking.energies.base import EnergyTerm, Prepared, Residuals, TrackState, counts

__all__ = ["Regularization", "RegularizationPrepared", "DEFAULT_WEIGHT"]

#: gamma_r per data correspondence (thesis: 0.02)
DEFAULT_WEIGHT = 0.02


@dataclass(frozen=True, eq=False)
class RegularizationPrepared(Prepared):
    """Prepared data of :class:`Regularization`: ``scale`` (D,) the factor of each DoF
    (1 for revolute joints, sqrt(root_weight) for the global DoF), ``previous`` (B, D)
    the reference pose."""

    scale: torch.Tensor
    previous: torch.Tensor


class Regularization(EnergyTerm):
    """E_regularization. ``root_weight``: weight of the global DoF (mm and rad)
    relative to the joints' (0: the global pose is free, as in the thesis)."""

    name = "regularization"
    prior = True

    def __init__(self, root_weight: float = 0.0):
        check_number(root_weight, "root_weight", low=0, inclusive=True)
        self.root_weight = float(root_weight)

    def prepare(self, state: TrackState) -> RegularizationPrepared:
        lo, hi = state.scene.lower, state.scene.upper
        joint = torch.isfinite(lo) & torch.isfinite(hi)
        # (D,): revolute joints 1, the global DoF sqrt(root_weight)
        scale = torch.where(joint, torch.ones_like(lo), torch.full_like(lo, self.root_weight ** 0.5)).to(state.theta)
        return RegularizationPrepared(counts(state.theta.shape[0], device=state.theta.device), scale, state.previous)

    def residuals(self, theta, posed, prepared: RegularizationPrepared, jacobian=True):
        r = prepared.scale * (theta - prepared.previous)
        J = torch.diag_embed(prepared.scale.expand_as(theta)) if jacobian else None
        return Residuals(r, J)
