"""Rigid alignment of point sets: the nearest rotation to a covariance and Kabsch's
least-squares rigid transform (Umeyama without scale), batched.

Used by the initialisation from detected joints (:mod:`torchhand.tracking.initialization`),
the in-hand scan's registration and the rigging (:mod:`torchhand.reconstruction`).
"""

from __future__ import annotations

import torch

__all__ = ["nearest_rotation", "kabsch_batch", "kabsch"]


def nearest_rotation(H: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) covariances sum source target^T -> (..., 3, 3) the rotations R that
    maximise trace(R H) (Kabsch's SVD with the reflection removed), batched."""
    U, _, Vt = torch.linalg.svd(H)
    d = torch.sign(torch.linalg.det(Vt.transpose(-1, -2) @ U.transpose(-1, -2)))
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    return Vt.transpose(-1, -2) @ D @ U.transpose(-1, -2)


def kabsch_batch(source: torch.Tensor, targets: torch.Tensor) -> tuple:
    """(n, 3) source, (T, n, 3) targets -> R (T, 3, 3), t (T, 3) minimising
    sum |R source + t - target|^2 per target."""
    ms, mt = source.mean(0), targets.mean(1)
    R = nearest_rotation((source - ms).T[None] @ (targets - mt[:, None]))
    return R, mt - (R @ ms[:, None])[..., 0]


def kabsch(source: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(n, 3), (n, 3) -> (4, 4) the rigid transform minimising sum |T source - target|^2
    (Umeyama without scale); the identity for fewer than 3 points."""
    T = torch.eye(4, dtype=source.dtype)
    if len(source) < 3:
        return T
    R, t = kabsch_batch(source, target[None])
    T[:3, :3], T[:3, 3] = R[0], t[0]
    return T
