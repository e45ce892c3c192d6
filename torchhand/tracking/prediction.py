"""Motion prediction: the pose a frame's solve starts from."""

from __future__ import annotations

from typing import Optional, Sequence

import torch

__all__ = ["predicted_start"]


def predicted_start(history: Sequence[tuple], factor: float, limiter: bool = True) -> Optional[torch.Tensor]:
    """The pose to start the next frame from: ``theta_{t-1} + factor * step``.

    Args:
        history: ``(theta (B, D), tracked (B,) bool)`` of the last frames, oldest first;
            the last one is the previous frame.
        factor: the prediction (0: none, 1: constant velocity).
        limiter: the step is, per DoF, the smaller of the last two steps when they have
            the same sign and 0 otherwise (minmod); needs three tracked frames.
            Without it, the step is the last one (two tracked frames).
    Returns:
        (B, D), or None when no problem has the tracked frames it needs (the step is 0
        for the problems that lack them).
    """
    if not factor >= 0:
        raise ValueError(f"factor must be >= 0, got {factor!r}")
    need = 3 if limiter else 2
    if factor == 0 or len(history) < need:
        return None
    poses = [h[0] for h in history[-need:]]
    ok = torch.stack([h[1] for h in history[-need:]]).all(0)
    if not bool(ok.any()):
        return None
    step = poses[-1] - poses[-2]
    if limiter:
        older = poses[-2] - poses[-3]
        same = torch.sign(step) == torch.sign(older)
        step = torch.where(same, torch.sign(step) * torch.minimum(step.abs(), older.abs()), torch.zeros_like(step))
    return poses[-1] + factor * torch.where(ok[:, None], step, torch.zeros_like(step))
