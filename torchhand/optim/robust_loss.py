"""Robust losses for least squares, applied by iteratively reweighted least squares.

A robust loss replaces a correspondence's squared residual norm ``s = |r|^2`` by
``rho(s)``. Gauss-Newton on ``sum rho(s_i)`` takes, at the current residuals, the
step of the weighted problem ``sum w_i |r_i|^2`` with ``w_i = rho'(s_i)`` (the IRLS
weights; Triggs et al., "Bundle adjustment - a modern synthesis", Sec. 4.3; theseus'
``RobustCostFunction`` rescales r and J by ``sqrt(rho')`` the same way). Every loss
here has ``rho(0) = 0``, ``rho'(0) = 1`` and a scale ``c`` (in the residual's units) at
which it departs from the plain square. What a least-squares solver multiplies rows by
is ``sqrt(w_i)``: :meth:`RobustLoss.sqrt_weights` gives it from the row norms ``|r_i|``.

The scale can follow the data (:attr:`RobustLoss.relative`): per group of
correspondences (e.g. one model of one problem) ``c = max(scale, relative x median
|r|)``, so a group whose residuals are large as a whole (fast motion) keeps its
pull while the far outliers of a group that fits are damped. Groups and padding are
given by the caller: ``mask`` (B, n) marks real rows, ``group`` (B, n) their group.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch

__all__ = ["RobustLoss", "Squared", "Cauchy", "Huber", "GemanMcClure", "Truncated", "LOSSES", "robust_loss"]


@dataclass(frozen=True)
class RobustLoss:
    """Base class. ``scale``: c, in the residual's units; ``relative``: None for a fixed
    c, else c = max(scale, relative x median |r|) per group (module docstring)."""

    scale: float = 1.0
    relative: Optional[float] = None

    def __post_init__(self) -> None:
        if not (isinstance(self.scale, (int, float)) and math.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"{type(self).__name__}: scale must be a finite number > 0, got {self.scale!r}")
        if self.relative is not None and not (isinstance(self.relative, (int, float)) and self.relative > 0):
            raise ValueError(f"{type(self).__name__}: relative must be > 0 or None, got {self.relative!r}")

    # s: squared norms, c2: squared scales (broadcasting)
    def rho(self, s: torch.Tensor, c2: torch.Tensor) -> torch.Tensor:  # pragma: no cover - interface
        """The loss of squared norms ``s`` at squared scale ``c2``."""
        raise NotImplementedError

    def weight(self, s: torch.Tensor, c2: torch.Tensor) -> torch.Tensor:  # pragma: no cover - interface
        """``rho'(s)``, the IRLS weight of a correspondence."""
        raise NotImplementedError

    def sqrt_weight(self, norm: torch.Tensor, c: torch.Tensor) -> torch.Tensor:  # pragma: no cover - interface
        """``sqrt(rho'(|r|^2))`` from row norms ``|r|`` at scale ``c``."""
        raise NotImplementedError

    def scales(self, norm: torch.Tensor, mask: Optional[torch.Tensor] = None,
               group: Optional[torch.Tensor] = None, groups: int = 1) -> torch.Tensor:
        """c for every row: (B, n) from the row norms ``norm`` (B, n), the real rows
        ``mask`` (B, n) (None: all) and their ``group`` (B, n) int64 in ``[0, groups)``
        (None: one group). No host sync."""
        c = norm.new_full(norm.shape, float(self.scale))
        if self.relative is None or norm.numel() == 0:
            return c
        real = torch.ones_like(norm, dtype=torch.bool) if mask is None else mask.bool()
        g = torch.zeros_like(norm, dtype=torch.int64) if group is None else group
        G = max(int(groups), 1)  # groups are model indices: a handful
        # (B, G, n) with NaN outside the group: nanmedian is the lower median of the
        # group's real rows, as torch.median is; a group without rows gets c = scale
        member = (g[:, None, :] == torch.arange(G, device=norm.device)[None, :, None]) & real[:, None, :]
        med = torch.nanmedian(torch.where(member, norm[:, None, :], norm.new_tensor(float("nan"))), dim=-1).values
        c_group = torch.fmax(med * float(self.relative), med.new_tensor(float(self.scale)))  # fmax ignores NaN
        return torch.gather(c_group, 1, g)

    def sqrt_weights(self, norm: torch.Tensor, mask: Optional[torch.Tensor] = None,
                     group: Optional[torch.Tensor] = None, groups: int = 1) -> torch.Tensor:
        """(B, n) ``sqrt(w_i)`` of rows with norms ``norm`` (B, n); 0 on padding rows."""
        sw = self.sqrt_weight(norm, self.scales(norm, mask, group, groups))
        return sw if mask is None else sw * mask.to(sw.dtype)


@dataclass(frozen=True)
class Squared(RobustLoss):
    """``rho(s) = s``: the plain sum of squares (weights 1)."""

    def rho(self, s, c2):
        return s

    def weight(self, s, c2):
        return torch.ones_like(s)

    def sqrt_weight(self, norm, c):
        return torch.ones_like(norm)


@dataclass(frozen=True)
class Cauchy(RobustLoss):
    """``rho(s) = c^2 log(1 + s / c^2)``, ``w = 1 / (1 + s / c^2)``."""

    def rho(self, s, c2):
        return c2 * torch.log1p(s / c2)

    def weight(self, s, c2):
        return 1.0 / (1.0 + s / c2)

    def sqrt_weight(self, norm, c):
        return (1 + (norm / c) ** 2).rsqrt()


@dataclass(frozen=True)
class Huber(RobustLoss):
    """``rho(s) = s`` for ``s <= c^2``, else ``2 c sqrt(s) - c^2``; ``w = min(1, c / sqrt(s))``."""

    def rho(self, s, c2):
        return torch.where(s <= c2, s, 2 * (c2 * s).sqrt() - c2)

    def weight(self, s, c2):
        return torch.where(s <= c2, torch.ones_like(s), (c2 / s.clamp_min(torch.finfo(s.dtype).tiny)).sqrt())

    def sqrt_weight(self, norm, c):
        return torch.where(norm <= c, torch.ones_like(norm), (c / norm.clamp_min(torch.finfo(norm.dtype).tiny)).sqrt())


@dataclass(frozen=True)
class GemanMcClure(RobustLoss):
    """``rho(s) = c^2 s / (c^2 + s)``, ``w = c^4 / (c^2 + s)^2``: redescending."""

    def rho(self, s, c2):
        return c2 * s / (c2 + s)

    def weight(self, s, c2):
        return (c2 / (c2 + s)) ** 2

    def sqrt_weight(self, norm, c):
        return 1 / (1 + (norm / c) ** 2)


@dataclass(frozen=True)
class Truncated(RobustLoss):
    """``rho(s) = min(s, c^2)``, ``w = 1`` for ``s <= c^2``, else 0: a hard cut."""

    def rho(self, s, c2):
        return torch.minimum(s, c2)

    def weight(self, s, c2):
        return (s <= c2).to(s.dtype)

    def sqrt_weight(self, norm, c):
        return (norm <= c).to(norm.dtype)


#: name -> class, for configuration files and the command line
LOSSES = {"squared": Squared, "cauchy": Cauchy, "huber": Huber, "geman-mcclure": GemanMcClure,
          "truncated": Truncated}


def robust_loss(name: str, scale: float = 1.0, relative: Optional[float] = None) -> RobustLoss:
    """A loss by name (:data:`LOSSES`)."""
    if name not in LOSSES:
        raise ValueError(f"unknown robust loss {name!r}; known: {sorted(LOSSES)}")
    return LOSSES[name](scale, relative)
