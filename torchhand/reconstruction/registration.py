"""Rigid registration of the in-hand object's frames (thesis Sec. 5.4): contact points
of the tracked hand (Sec. 5.4.1) and frame-to-model ICP, combined in one least-squares
problem (Eq. 5.2, 5.6, 5.7) solved by the library's Levenberg-Marquardt.

Conventions: a frame's pose ``X`` (4, 4) maps its camera coordinates into the object
frame (the reconstruction's coordinates); the object's pose in the camera is its
inverse. Points are (n, 3) float64 tensors in mm.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, NamedTuple, Optional

import torch

from torchhand.geometry.neighbors import PointIndex
from torchhand.geometry.rigid import kabsch, kabsch_batch, nearest_rotation  # noqa: F401 (re-exported)
from torchhand.model.kinematics import so3_exp
from torchhand.optim.levenberg_marquardt import levenberg_marquardt

__all__ = ["contact_vertices", "ContactConfig", "RegistrationConfig", "register_frame", "kabsch", "kabsch_batch",
           "nearest_rotation", "Registration"]


@dataclass(frozen=True)
class ContactConfig:
    """Sec. 5.4.1: an end-effector is a contact bone when more than ``min_vertices`` of
    its vertices lie within ``distance`` mm of the object's points; the distance grows
    by ``step`` mm until ``min_bones`` end-effectors are found (at most ``max_distance``)."""

    distance: float = 1.0
    step: float = 0.5
    max_distance: float = 15.0
    min_vertices: int = 40
    min_bones: int = 2


def contact_vertices(hand_vertices: torch.Tensor, effector_vertices: List[torch.Tensor], object_points: torch.Tensor,
                     config: ContactConfig = ContactConfig(), backend: Optional[str] = None) -> torch.Tensor:
    """The contact vertices of one frame (thesis Sec. 5.4.1).

    Args:
        hand_vertices: (V, 3) posed hand vertices (camera frame, mm).
        effector_vertices: per end-effector (the distal bones), its vertex ids (k_e,).
        object_points: (n, 3) the object's data points (hand pixels removed).
    Returns:
        (c,) int64 ids of all vertices of the contact bones (empty when the hand does
        not touch the data within ``max_distance``).
    """
    empty = torch.zeros(0, dtype=torch.int64)
    if len(object_points) == 0:
        return empty
    index = PointIndex(object_points, torch.zeros(len(object_points), dtype=torch.int64),
                       torch.zeros(len(object_points), dtype=torch.int64), 1, 1, config.max_distance, backend)
    ids = torch.cat(effector_vertices)
    owner = torch.cat([torch.full((len(e),), k) for k, e in enumerate(effector_vertices)])
    q = hand_vertices[ids][None]
    nn = index.nearest(q, torch.zeros(1, dtype=torch.int64), torch.zeros_like(q[..., 0], dtype=torch.int64))[0]
    dist = torch.where(nn >= 0, (q[0] - object_points[nn.clamp_min(0)]).norm(dim=1),
                       torch.full_like(q[0, :, 0], float("inf")))
    thr = config.distance
    while True:
        counts = torch.bincount(owner[dist < thr], minlength=len(effector_vertices))
        bones = torch.nonzero(counts > config.min_vertices)[:, 0]
        if len(bones) >= config.min_bones or thr + config.step > config.max_distance:
            break
        thr += config.step
    if len(bones) == 0:
        return empty
    return torch.cat([effector_vertices[int(b)] for b in bones])


@dataclass(frozen=True)
class RegistrationConfig:
    """gamma_t: weight of the contact term against the ICP term (Eq. 5.2; both are sums
    over their correspondences, each contact residual divided by the number of contact
    vertices and multiplied by the number of ICP points, so that gamma_t = 1 gives the
    two terms the same say whatever their counts; the default, 0.05, lets the object's
    shape correct a tracked hand that is off by a few mm while the hand still holds the
    directions ICP cannot see, docs/scanning.md); icp_distance: the largest ICP pair
    distance (5 mm in the thesis); iterations: correspondence updates; lm_iterations:
    LM steps per update."""

    gamma_t: float = 0.05
    icp_distance: float = 5.0
    iterations: int = 10
    lm_iterations: int = 3


class Registration(NamedTuple):
    """X: (4, 4) camera -> object frame; icp_pairs: ICP pairs at the last update;
    rms_mm: their point-to-plane RMS."""

    X: torch.Tensor
    icp_pairs: int
    rms_mm: float


def _skew_jacobian(p: torch.Tensor) -> torch.Tensor:
    """(n, 3) -> (n, 3, 6): d(exp(xi) p)/d xi at xi = 0 for xi = (rotation, translation)."""
    n = len(p)
    J = p.new_zeros(n, 3, 6)
    x, y, z = p.unbind(1)
    J[:, 0, 1], J[:, 0, 2] = z, -y
    J[:, 1, 0], J[:, 1, 2] = -z, x
    J[:, 2, 0], J[:, 2, 1] = y, -x
    J[:, :, 3:] = torch.eye(3, dtype=p.dtype)
    return J


def _apply(xi: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """(6,) increment, (4, 4) -> exp(xi) X."""
    D = torch.eye(4, dtype=X.dtype)
    D[:3, :3] = so3_exp(xi[None, :3])[0]
    D[:3, 3] = xi[3:]
    return D @ X


def register_frame(points: torch.Tensor, X0: torch.Tensor, model: Optional[PointIndex], model_points: torch.Tensor,
                   model_normals: torch.Tensor, contacts_now: torch.Tensor, contacts_model: torch.Tensor,
                   config: RegistrationConfig = RegistrationConfig()) -> Registration:
    """Align one frame to the reconstruction (Eq. 5.2 with the visual term E_icp, Eq. 5.7,
    and the contact term, Eq. 5.6).

    Args:
        points: (n, 3) the frame's object points (camera frame).
        X0: (4, 4) start (camera -> object), e.g. from the hand's motion.
        model: the reconstruction's points indexed for radius queries (None: contacts only).
        model_points, model_normals: (m, 3) the reconstruction (object frame).
        contacts_now: (c, 3) contact vertices of this frame (camera frame).
        contacts_model: (c, 3) the same vertices at the previous frame, in the object frame.
    Returns:
        :class:`Registration`.
    """
    X = X0.clone()
    n_icp = max(len(points), 1)
    w_c = (config.gamma_t * n_icp / max(len(contacts_now), 1)) ** 0.5
    pairs, rms = 0, float("nan")
    zero = torch.zeros(1, dtype=torch.int64)
    for _ in range(config.iterations):
        q = points @ X[:3, :3].T + X[:3, 3]
        if model is not None and len(points):
            nn = model.nearest(q[None], zero, torch.zeros(1, len(q), dtype=torch.int64), config.icp_distance)[0]
            keep = nn >= 0
            src, dst, nrm = points[keep], model_points[nn[keep]], model_normals[nn[keep]]
        else:
            src = dst = nrm = points[:0]
        pairs = len(src)
        if pairs + len(contacts_now) < 3:
            break

        def residuals(xi: torch.Tensor, jacobian: bool, X=X, src=src, dst=dst, nrm=nrm):
            Xi = _apply(xi[0], X)
            p = src @ Xi[:3, :3].T + Xi[:3, 3]
            r_icp = ((p - dst) * nrm).sum(1)
            c = contacts_now @ Xi[:3, :3].T + Xi[:3, 3]
            r_c = w_c * (c - contacts_model).reshape(-1)
            r = torch.cat([r_icp, r_c])[None]
            if not jacobian:
                return r, None
            # d(exp(xi) Xi_0 x)/dxi at the candidate: the left-perturbation Jacobian at p
            Jp = torch.einsum("nk,nkd->nd", nrm, _skew_jacobian(p))
            Jc = w_c * _skew_jacobian(c).reshape(-1, 6)
            return r, torch.cat([Jp, Jc])[None]

        res = levenberg_marquardt(residuals, torch.zeros(1, 6, dtype=X.dtype), max_iterations=config.lm_iterations)
        X = _apply(res.theta[0], X)
        rms = float(((src @ X[:3, :3].T + X[:3, 3] - dst) * nrm).sum(1).pow(2).mean().sqrt()) if pairs else rms
    return Registration(X, pairs, rms)
