"""The recovery re-solve: a frame whose energy rose sharply against the previous
frames' is solved again from random perturbations of the previous pose, and the best
is kept if it is better."""

from __future__ import annotations

from typing import List, Optional, Sequence

import torch

from torchhand.tracking.solve import box_rows

__all__ = ["recover"]


def recover(tracker, theta: torch.Tensor, energy: torch.Tensor, previous: torch.Tensor, frames: List,
            cameras: Sequence, *, iterations: int, history: torch.Tensor, generator: Optional[torch.Generator],
            colours: Optional[List] = None, views: int = 1, bounds: tuple) -> tuple:
    """Re-solve the problems whose energy exceeds ``config.recover_factor`` times the
    median of ``history`` (F, B) (their earlier frames' energies), each from
    ``config.recover_tries`` perturbations of its previous pose (the joints by
    N(0, ``config.perturbation``) rad, the global pose by N(0, 4 mm / 0.03 rad)).

    Args:
        theta, energy: (B, D), (B,) the frame's solution (changed in place where a try
            is better); previous: (B, D); frames, cameras, colours: B x V per view
            problem; bounds: the box of each problem, as the solvers'.
    Returns:
        (theta, energy, recovered (B,) bool).
    """
    cfg = tracker.config
    ref = torch.nanmedian(history, 0).values
    bad = torch.nonzero(energy > cfg.recover_factor * ref)[:, 0].tolist()
    rec = torch.zeros(len(energy), dtype=torch.bool)
    if not bad:
        return theta, energy, rec
    R, V = cfg.recover_tries, views
    starts, fr, cams, prev, cols = [], [], [], [], []
    scale = torch.full((previous.shape[1],), cfg.perturbation, dtype=previous.dtype)
    for s in tracker.scene.slices.values():
        scale[s.start : s.start + 3], scale[s.start + 3 : s.start + 6] = 4.0, 0.03
    for b in bad:  # every try perturbs the previous pose (the unperturbed start was just solved)
        for _ in range(R):
            noise = torch.randn(previous.shape[1], generator=generator, dtype=previous.dtype) * scale
            starts.append(previous[b] + noise.to(previous.device))
            fr += frames[b * V : (b + 1) * V]
            cams += cameras[b * V : (b + 1) * V]
            cols += [] if colours is None else colours[b * V : (b + 1) * V]
            prev.append(previous[b])
    rows = box_rows(bounds, [b for b in bad for _ in range(R)])
    sol = tracker.solve(tracker.clamp(torch.stack(starts), rows), torch.stack(prev), fr, cams, iterations,
                        colours=None if colours is None else cols, views=V, bounds=rows)
    th, en = sol.theta, sol.energy
    for i, b in enumerate(bad):
        best = int(torch.argmin(en[i * R : (i + 1) * R]))
        if en[i * R + best] < energy[b]:
            theta[b], energy[b], rec[b] = th[i * R + best], en[i * R + best], True
    return theta, energy, rec
