"""E_collision: conic distance fields around intersecting triangles (thesis Eq. 4.9-4.13).

At every outer iteration the intersecting triangle pairs C of the posed scene are
found (:func:`torchhand.geometry.intersections.detect_collisions`: hand-hand, hand-object and,
within a model, parts that are not neighbours); while the solver tries poses the
pairs stay fixed and each vertex of one triangle is penalised by the other's conic
field Psi. The residual of an (intruder, receiver) row is ``Psi`` (Eq. 4.13,
point-to-plane), or the 3-vector ``Psi n`` along the intruder's vertex normal, fixed at
the pose where the pair was found (Eq. 4.12, point-to-point); the tracker weights the
term by gamma_c = 10 as the thesis does (:data:`DEFAULT_WEIGHT`). Both give the same energy; with the
normal fixed they also give the same Gauss-Newton step, so Eq. 4.13 is the default.

The Jacobian chains dPsi/d(intruder, receiver vertices), taken by autograd on the
few rows, with the analytic LBS Jacobians of those four vertices. Collision rows do
not count as data correspondences (C_all of the anatomy and regularisation weights).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from torchhand.core.check import check_choice, check_number
from torchhand.geometry.intersections import DEFAULT_SIGMA, CollisionMesh, conic_field, detect_collisions, intruders
from torchhand.geometry.mesh import vertex_normals
from torchhand.model.scene import Scene
from torchhand.tracking.energies.base import EnergyTerm, Prepared, Residuals, TrackState, counts, no_residuals

__all__ = ["Collision", "CollisionRows", "DEFAULT_WEIGHT"]

#: gamma_c of the thesis, the tracker's weight of the term
DEFAULT_WEIGHT = 10.0


@dataclass(frozen=True, eq=False)
class CollisionRows(Prepared):
    """Prepared data of :class:`Collision`, m rows per problem (padded):

    Attributes:
        scene: the scene the ids index.
        vids: (B, m, 4) int64 scene vertex ids of each row: the intruder, then the
            receiving triangle's three corners.
        mask: (B, m) 1 for real rows.
        uids: (B, u) int64 the distinct vertices of each problem's rows (their
            Jacobians are taken once).
        ucol: (B, m, 4) int64 the column in ``uids`` of each (row, corner).
        normal: (B, m, 3) the push-back direction of each row (minus the intruder's
            vertex normal at the pose where the pair was found) for the point-to-point
            metric, else None.
    """

    scene: Scene
    vids: torch.Tensor
    mask: torch.Tensor
    uids: torch.Tensor
    ucol: torch.Tensor
    normal: Optional[torch.Tensor]


class Collision(EnergyTerm):
    """E_collision.

    Args:
        sigma: sigma of Eq. 4.10-4.11 in the scene's units (0.5).
        metric: "point-to-plane" (Eq. 4.13, one residual per row) or
            "point-to-point" (Eq. 4.12, three).
        self_collisions: also test non-neighbouring parts of one model (fingers
            against each other and the palm).
    """

    name = "collision"

    def __init__(self, sigma: float = DEFAULT_SIGMA, metric: str = "point-to-plane", self_collisions: bool = True):
        check_choice(metric, "metric", ("point-to-point", "point-to-plane"))
        check_number(sigma, "sigma", low=0, unit="mm")
        self.sigma, self.metric, self.self_collisions = float(sigma), metric, self_collisions
        self._mesh, self._mesh_scene = None, None

    def mesh_for(self, scene) -> CollisionMesh:
        """The scene's :class:`CollisionMesh`, built once per scene."""
        if self._mesh_scene is not scene:
            self._mesh, self._mesh_scene = CollisionMesh.from_scene(scene, self.self_collisions), scene
        return self._mesh

    def prepare(self, state: TrackState) -> CollisionRows:
        scene, B = state.scene, state.theta.shape[0]
        V = state.posed.vertices
        dev = V.device
        pairs = detect_collisions(V, self.mesh_for(scene))
        rows = intruders(pairs, scene.faces)
        n_rows = torch.bincount(rows.batch, minlength=B)
        m = int(n_rows.max()) if len(rows.batch) else 0
        start = torch.cumsum(n_rows, 0) - n_rows
        pos = torch.arange(len(rows.batch), device=dev) - start[rows.batch]
        # (B, m) padded rows: 4 vertices per row (intruder, then the receiver's three)
        vids = torch.zeros(B, m, 4, dtype=torch.int64, device=dev)
        vids[rows.batch, pos] = torch.cat([rows.vertex[:, None], scene.faces[rows.face]], 1)
        mask = torch.zeros(B, m, dtype=V.dtype, device=dev)
        mask[rows.batch, pos] = 1.0
        # the Jacobian is taken once per distinct vertex of a problem: (B, u) ids and
        # for every (row, corner) its column among them
        key = torch.arange(B, device=dev)[:, None] * scene.num_vertices + vids.reshape(B, -1)
        uniq, inverse = torch.unique(key, return_inverse=True)
        ub = torch.div(uniq, scene.num_vertices, rounding_mode="floor")
        ucount = torch.bincount(ub, minlength=B)
        upos = torch.arange(len(uniq), device=dev) - (torch.cumsum(ucount, 0) - ucount)[ub]
        uids = torch.zeros(B, int(ucount.max()) if len(uniq) else 0, dtype=torch.int64, device=dev)
        uids[ub, upos] = uniq - ub * scene.num_vertices
        normal = None
        if self.metric == "point-to-point":
            n = vertex_normals(V, scene.faces)
            normal = -n[torch.arange(B, device=dev)[:, None], vids[..., 0]]  # push back: -n_v
        # collision rows are not data correspondences (C_all)
        return CollisionRows(counts(B, device=dev, pairs=pairs.counts(B)), scene, vids, mask, uids,
                             upos[inverse].view(B, m, 4), normal)

    def residuals(self, theta, posed, prepared: CollisionRows, jacobian=True):
        B, D = theta.shape
        p = prepared
        m = p.vids.shape[1]
        dim = 1 if self.metric == "point-to-plane" else 3
        if m == 0:
            return no_residuals(theta, jacobian, dim)
        b = torch.arange(B, device=theta.device)[:, None, None]
        X = posed.vertices.detach()[b, p.vids]  # (B, m, 4, 3)
        if not jacobian:
            psi = conic_field(X[:, :, 0], X[:, :, 1:], self.sigma) * p.mask
            return Residuals(_shape(psi, p.normal), None, dim, p.mask)
        with torch.enable_grad():
            X = X.requires_grad_()
            psi = conic_field(X[:, :, 0], X[:, :, 1:], self.sigma) * p.mask
            (g,) = torch.autograd.grad(psi.sum(), X)  # (B, m, 4, 3): rows depend on their own X only
        Ju = p.scene.vertex_jacobian(posed, p.uids)  # (B, u, 3, D)
        J = theta.new_zeros(B, m, D)
        for c in range(4):  # intruder, then the receiver's corners
            Jc = torch.gather(Ju, 1, p.ucol[:, :, c, None, None].expand(-1, -1, 3, D))
            J += torch.einsum("bmk,bmkd->bmd", g[:, :, c], Jc)
        return Residuals(_shape(psi.detach(), p.normal), _shape_jacobian(J, p.normal), dim, p.mask)


def _shape(psi, normal):
    """Rows of Eq. 4.13 (``normal`` None) or Eq. 4.12 (along the fixed ``normal``)."""
    if normal is None:
        return psi
    return (psi[..., None] * normal).reshape(psi.shape[0], -1)


def _shape_jacobian(J, normal):
    if normal is None:
        return J
    return (normal[..., None] * J[:, :, None, :]).reshape(J.shape[0], -1, J.shape[-1])
