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

from dataclasses import dataclass
from typing import Optional

import torch

from torchhand.model.scene import SceneOutput
from torchhand.optim.robust_loss import RobustLoss
from torchhand.tracking.energies.base import EnergyTerm, Prepared, Residuals, TrackState

__all__ = ["Weighted", "Robust", "WeightedPrepared", "RobustPrepared"]


@dataclass(frozen=True, eq=False)
class WeightedPrepared(Prepared):
    """Prepared data of :class:`Weighted`: ``inner`` the wrapped term's (with the
    weight folded in where the term could take it); ``sqrt_w`` the factor of r and J,
    a float, (B, 1) per problem, or None when ``inner`` holds the weight already."""

    inner: Prepared
    sqrt_w: object


@dataclass(frozen=True, eq=False)
class RobustPrepared(Prepared):
    """Prepared data of :class:`Robust`: ``inner`` the wrapped term's (with the row
    weights folded in where the term could take them); ``sqrt_w`` (B, n) the factor of
    each row, fixed for the outer iteration, or None when ``inner`` holds it already."""

    inner: Prepared
    sqrt_w: Optional[torch.Tensor]


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
        self.name, self.needs, self.detections = term.name, term.needs, term.detections
        self.whole_frames = term.whole_frames
        self.prior = term.prior or self.per_correspondence

    def prepare(self, state: TrackState) -> WeightedPrepared:
        inner = self.term.prepare(state)
        if not self.per_correspondence:
            return WeightedPrepared(inner.counts._replace(unmatched=self.weight * inner.counts.unmatched), inner,
                                    self.weight ** 0.5)
        c = state.correspondences
        if c is None:
            raise ValueError(f"{self!r} scales with C_all, but state.correspondences is not set; prepare the data "
                             "terms first (Tracker does)")
        w = (self.weight * c.to(state.theta)).clamp_min(self.min_weight)[:, None]  # (B, 1)
        found = inner.counts._replace(unmatched=w[:, 0].double() * inner.counts.unmatched)
        folded = self.term.fold_weight(inner, w)
        if folded is not None:
            return WeightedPrepared(found, folded, None)
        return WeightedPrepared(found, inner, w.sqrt())

    def residuals(self, theta: torch.Tensor, posed: SceneOutput, prepared: WeightedPrepared,
                  jacobian: bool = True) -> Residuals:
        res = self.term.residuals(theta, posed, prepared.inner, jacobian)
        sw = prepared.sqrt_w
        if sw is None:
            return res
        if isinstance(sw, torch.Tensor):  # (B, 1) per problem
            return res._replace(r=res.r * sw, J=None if res.J is None else res.J * sw[..., None])
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
        self.name, self.prior, self.needs, self.detections = term.name, term.prior, term.needs, term.detections
        self.whole_frames = term.whole_frames

    def prepare(self, state: TrackState) -> RobustPrepared:
        inner = self.term.prepare(state)
        res = self.term.residuals(state.theta, state.posed, inner, jacobian=False)
        B = res.r.shape[0]
        norm = res.r.view(B, -1, res.dim).norm(dim=-1)  # (B, n) row norms
        sqrt_w = self.loss.sqrt_weights(norm, res.mask, res.group, res.groups)
        # a term whose residuals are linear in its stored correspondences takes the
        # weights into them once, instead of scaling r and J at every evaluation
        folded = self.term.fold_row_weights(inner, sqrt_w)
        if folded is not None:
            return RobustPrepared(inner.counts, folded, None)
        return RobustPrepared(inner.counts, inner, sqrt_w)

    def residuals(self, theta: torch.Tensor, posed: SceneOutput, prepared: RobustPrepared,
                  jacobian: bool = True) -> Residuals:
        res = self.term.residuals(theta, posed, prepared.inner, jacobian)
        if prepared.sqrt_w is None:
            return res
        sw = prepared.sqrt_w.repeat_interleave(res.dim, dim=1) if res.dim > 1 else prepared.sqrt_w  # (B, m)
        return res._replace(r=res.r * sw, J=None if res.J is None else res.J * sw[..., None])

    def __repr__(self) -> str:
        return f"Robust({self.term!r}, {self.loss!r})"
