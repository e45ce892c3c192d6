"""Particle swarm optimisation, batched: B independent swarms of P particles in D dims.

The global search of the automatic (re-)initialisation (:mod:`torchhand.tracking.initialization`)
and the HOPE baseline: Oikonomidis et al.'s tracker (FORTH) and the HOPE64/128 runs of
Ballan et al. search the pose with it. This is the canonical PSO with Clerc's
constriction coefficients (w = 0.7298, c1 = c2 = 1.49618), each particle attracted to
its own best and the swarm's best; nothing here knows about hands or images.

The cost is called once per generation with all B x P particles, so a cost that
renders them does so as one batch.
"""

from __future__ import annotations

from typing import Callable, NamedTuple, Optional

import torch

__all__ = ["PSOResult", "particle_swarm"]

#: Clerc and Kennedy's constriction: inertia and the two acceleration coefficients
INERTIA, COGNITIVE, SOCIAL = 0.7298, 1.49618, 1.49618


class PSOResult(NamedTuple):
    """best: (B, D) the best position found per swarm; cost: (B,) its cost;
    particles: (B, P, D) every particle's own best; particle_cost: (B, P) their costs;
    history: (G + 1,) the mean over swarms of the best cost after each generation
    (entry 0: the initial particles); evaluations: cost calls made (G + 1)."""

    best: torch.Tensor
    cost: torch.Tensor
    particles: torch.Tensor
    particle_cost: torch.Tensor
    history: torch.Tensor
    evaluations: int


def particle_swarm(cost: Callable[[torch.Tensor], torch.Tensor], init: torch.Tensor, lower: torch.Tensor,
                   upper: torch.Tensor, generations: int = 40, velocity_scale: Optional[torch.Tensor] = None,
                   generator: Optional[torch.Generator] = None) -> PSOResult:
    """Minimise ``cost`` from the particles ``init``.

    Args:
        cost: maps (B, P, D) positions to (B, P) costs (lower is better; non-finite
            costs count as +inf).
        init: (B, P, D) initial positions (clamped into the bounds).
        lower, upper: (D,) or (B, D) bounds; +-inf where a dimension is free.
        generations: G, the number of velocity updates after the initial evaluation
            (G + 1 cost calls in all).
        velocity_scale: (D,) or (B, D), the largest speed of a dimension per generation
            (velocities are clamped to it; None: unbounded, which needs finite bounds to
            keep the swarm in place). The initial velocities are zero.
        generator: of the random coefficients (CPU generator; torch's default if None).
    Returns:
        :class:`PSOResult`.
    """
    if init.dim() != 3:
        raise ValueError(f"init must be (B, P, D) particles, got shape {tuple(init.shape)}")
    if generations < 0:
        raise ValueError(f"generations must be >= 0, got {generations}")
    B, P, D = init.shape
    dev, dt = init.device, init.dtype
    lo = torch.as_tensor(lower, dtype=dt, device=dev).expand(B, D)[:, None]
    hi = torch.as_tensor(upper, dtype=dt, device=dev).expand(B, D)[:, None]
    vmax = None if velocity_scale is None else torch.as_tensor(velocity_scale, dtype=dt, device=dev).expand(B, D)[:, None]
    x = torch.maximum(torch.minimum(init, hi), lo)
    v = torch.zeros_like(x)

    def evaluate(pos: torch.Tensor) -> torch.Tensor:
        c = cost(pos)
        if c.shape != (B, P):
            raise ValueError(f"cost must return (B, P) = ({B}, {P}) values, got shape {tuple(c.shape)}")
        return torch.where(torch.isfinite(c), c, torch.full_like(c, float("inf")))

    own, own_cost = x.clone(), evaluate(x)
    history = [own_cost.min(1).values.mean()]
    for _ in range(generations):
        k = own_cost.argmin(1)
        swarm = own[torch.arange(B, device=dev), k][:, None]  # (B, 1, D)
        r1 = torch.rand(B, P, D, generator=generator, dtype=dt).to(dev)
        r2 = torch.rand(B, P, D, generator=generator, dtype=dt).to(dev)
        v = INERTIA * v + COGNITIVE * r1 * (own - x) + SOCIAL * r2 * (swarm - x)
        if vmax is not None:
            v = torch.maximum(torch.minimum(v, vmax), -vmax)
        x = torch.maximum(torch.minimum(x + v, hi), lo)
        c = evaluate(x)
        better = c < own_cost
        own = torch.where(better[..., None], x, own)
        own_cost = torch.where(better, c, own_cost)
        history.append(own_cost.min(1).values.mean())
    k = own_cost.argmin(1)
    idx = torch.arange(B, device=dev)
    return PSOResult(own[idx, k], own_cost[idx, k], own, own_cost, torch.stack(history), generations + 1)
