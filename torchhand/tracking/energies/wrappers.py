"""Weights and robust losses as wrappers around any energy term.

``Weighted(term, w)`` multiplies the term's residuals and Jacobian by ``sqrt(w)``, so its
share of the energy is ``w`` times its sum of squares; with ``per_correspondence=True``
the weight is ``w x C_all`` per problem (the thesis' gamma_a and gamma_r, Eq.
4.17-4.18), which makes it a prior. ``Robust(term, loss)`` applies a robust loss
(:mod:`torchhand.optim.robust_loss`) to each correspondence row by iteratively
reweighted least squares: at ``prepare`` the weights ``rho'(|r_i|^2)`` are computed
from the residuals at the current pose and then kept while the solver tries poses, as
the correspondences are. Robust losses act in the term's own units, so ``Robust``
goes inside ``Weighted``::

    Weighted(Robust(DataToModel(), Cauchy(3.0, relative=2.0)), 0.25)   # the default d2m
"""

from __future__ import annotations

from typing import Optional

import torch

from torchhand.model.scene import SceneOutput
from torchhand.optim.robust_loss import RobustLoss
from torchhand.tracking.energies.base import EnergyTerm, Prepared, Residuals, TrackState

__all__ = ["Weighted", "Robust"]


class Weighted(EnergyTerm):
    """A term times a weight.

    Args:
        term: the wrapped term.
        weight: w >= 0.
        per_correspondence: the weight is ``w x C_all`` of each problem (``C_all``:
            ``state.correspondences``); such a term is prepared after the data terms.
        min_weight: with ``per_correspondence``, the least weight (a frame without
            correspondences keeps a faint prior instead of none).
    """

    def __init__(self, term: EnergyTerm, weight: float, per_correspondence: bool = False, min_weight: float = 1e-6):
        if not isinstance(term, EnergyTerm):
            raise TypeError(f"term must be an EnergyTerm, got {type(term).__name__}")
        if not (isinstance(weight, (int, float)) and weight >= 0):
            raise ValueError(f"weight must be a number >= 0, got {weight!r}")
        self.term, self.weight = term, float(weight)
        self.per_correspondence, self.min_weight = bool(per_correspondence), float(min_weight)
        self.name, self.needs = term.name, term.needs
        self.prior = term.prior or self.per_correspondence
        self._sqrt_w: Optional[torch.Tensor] = None  # (B, 1) with per_correspondence
        self._folded = False

    def prepare(self, state: TrackState) -> Prepared:
        found = self.term.prepare(state)
        if not self.per_correspondence:
            return found._replace(unmatched=self.weight * found.unmatched)
        c = state.correspondences
        if c is None:
            raise ValueError(f"{self!r} scales with C_all, but state.correspondences is not set; prepare the data "
                             "terms first (Tracker does)")
        w = (self.weight * c.to(state.theta)).clamp_min(self.min_weight)[:, None]  # (B, 1)
        self._sqrt_w = w.sqrt()
        self._folded = self.term.fold_weight(w)
        return found._replace(unmatched=w[:, 0].double() * found.unmatched)

    def residuals(self, theta: torch.Tensor, posed: SceneOutput, jacobian: bool = True) -> Residuals:
        res = self.term.residuals(theta, posed, jacobian)
        if self._folded:
            return res
        if self.per_correspondence:
            sw = self._sqrt_w
            return res._replace(r=res.r * sw, J=None if res.J is None else res.J * sw[..., None])
        sw = self.weight ** 0.5
        return res._replace(r=res.r * sw, J=None if res.J is None else res.J * sw)

    def __repr__(self) -> str:
        extra = ", per_correspondence=True" if self.per_correspondence else ""
        return f"Weighted({self.term!r}, {self.weight:g}{extra})"


class Robust(EnergyTerm):
    """A term whose correspondence rows are weighted by a robust loss (IRLS).

    Args:
        term: the wrapped term (its :class:`Residuals` give rows, mask and groups).
        loss: a :class:`torchhand.optim.robust_loss.RobustLoss`.
    """

    def __init__(self, term: EnergyTerm, loss: RobustLoss):
        if not isinstance(term, EnergyTerm):
            raise TypeError(f"term must be an EnergyTerm, got {type(term).__name__}")
        if not isinstance(loss, RobustLoss):
            raise TypeError(f"loss must be a torchhand.optim.robust_loss.RobustLoss, got {type(loss).__name__}")
        self.term, self.loss = term, loss
        self.name, self.prior, self.needs = term.name, term.prior, term.needs
        self._sqrt_w: Optional[torch.Tensor] = None  # (B, n) per row, fixed for the outer iteration
        self._folded = False

    def prepare(self, state: TrackState) -> Prepared:
        found = self.term.prepare(state)
        res = self.term.residuals(state.theta, state.posed, jacobian=False)
        B = res.r.shape[0]
        norm = res.r.view(B, -1, res.dim).norm(dim=-1)  # (B, n) row norms
        self._sqrt_w = self.loss.sqrt_weights(norm, res.mask, res.group, res.groups)
        # a term whose residuals are linear in its stored correspondences takes the
        # weights into them once, instead of scaling r and J at every evaluation
        self._folded = self.term.fold_row_weights(self._sqrt_w)
        return found

    def residuals(self, theta: torch.Tensor, posed: SceneOutput, jacobian: bool = True) -> Residuals:
        res = self.term.residuals(theta, posed, jacobian)
        if self._folded:
            return res
        sw = self._sqrt_w.repeat_interleave(res.dim, dim=1) if res.dim > 1 else self._sqrt_w  # (B, m)
        return res._replace(r=res.r * sw, J=None if res.J is None else res.J * sw[..., None])

    def __repr__(self) -> str:
        return f"Robust({self.term!r}, {self.loss!r})"
