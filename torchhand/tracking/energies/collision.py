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

import torch

from torchhand.geometry.intersections import DEFAULT_SIGMA, CollisionMesh, conic_field, detect_collisions, intruders
from torchhand.geometry.mesh import vertex_normals
from torchhand.tracking.energies.base import EnergyTerm, Prepared, Residuals, TrackState, no_residuals, prepared

__all__ = ["Collision", "DEFAULT_WEIGHT"]

#: gamma_c of the thesis, the tracker's weight of the term
DEFAULT_WEIGHT = 10.0


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
        if metric not in ("point-to-point", "point-to-plane"):
            raise ValueError(f"metric must be 'point-to-point' or 'point-to-plane', got {metric!r}")
        if not sigma > 0:
            raise ValueError(f"sigma must be positive, got {sigma}")
        self.sigma, self.metric, self.self_collisions = float(sigma), metric, self_collisions
        self._mesh, self._mesh_scene = None, None

    def mesh_for(self, scene) -> CollisionMesh:
        """The scene's :class:`CollisionMesh`, built once per scene."""
        if self._mesh_scene is not scene:
            self._mesh, self._mesh_scene = CollisionMesh.from_scene(scene, self.self_collisions), scene
        return self._mesh

    def prepare(self, state: TrackState) -> Prepared:
        scene, B = state.scene, state.theta.shape[0]
        V = state.posed.vertices
        dev = V.device
        pairs = detect_collisions(V, self.mesh_for(scene))
        rows = intruders(pairs, scene.faces)
        counts = torch.bincount(rows.batch, minlength=B)
        m = int(counts.max()) if len(rows.batch) else 0
        start = torch.cumsum(counts, 0) - counts
        pos = torch.arange(len(rows.batch), device=dev) - start[rows.batch]
        # (B, m) padded rows: 4 vertices per row (intruder, then the receiver's three)
        self.vids = torch.zeros(B, m, 4, dtype=torch.int64, device=dev)
        self.vids[rows.batch, pos] = torch.cat([rows.vertex[:, None], scene.faces[rows.face]], 1)
        self.mask = torch.zeros(B, m, dtype=V.dtype, device=dev)
        self.mask[rows.batch, pos] = 1.0
        # the Jacobian is taken once per distinct vertex of a problem: (B, u) ids and
        # for every (row, corner) its column among them
        key = torch.arange(B, device=dev)[:, None] * scene.num_vertices + self.vids.reshape(B, -1)
        uniq, inverse = torch.unique(key, return_inverse=True)
        ub = torch.div(uniq, scene.num_vertices, rounding_mode="floor")
        ucount = torch.bincount(ub, minlength=B)
        upos = torch.arange(len(uniq), device=dev) - (torch.cumsum(ucount, 0) - ucount)[ub]
        self.uids = torch.zeros(B, int(ucount.max()) if len(uniq) else 0, dtype=torch.int64, device=dev)
        self.uids[ub, upos] = uniq - ub * scene.num_vertices
        self.ucol = upos[inverse].view(B, m, 4)
        if self.metric == "point-to-point":
            n = vertex_normals(V, scene.faces)
            self.normal = -n[torch.arange(B, device=dev)[:, None], self.vids[..., 0]]  # push back: -n_v
        self._scene = scene
        # collision rows are not data correspondences (C_all)
        return prepared(B, device=dev, pairs=pairs.counts(B))

    def residuals(self, theta, posed, jacobian=True):
        B, D = theta.shape
        m = self.vids.shape[1]
        dim = 1 if self.metric == "point-to-plane" else 3
        if m == 0:
            return no_residuals(theta, jacobian, dim)
        b = torch.arange(B, device=theta.device)[:, None, None]
        X = posed.vertices.detach()[b, self.vids]  # (B, m, 4, 3)
        if not jacobian:
            psi = conic_field(X[:, :, 0], X[:, :, 1:], self.sigma) * self.mask
            return Residuals(self._shape(psi), None, dim, self.mask)
        with torch.enable_grad():
            X = X.requires_grad_()
            psi = conic_field(X[:, :, 0], X[:, :, 1:], self.sigma) * self.mask
            (g,) = torch.autograd.grad(psi.sum(), X)  # (B, m, 4, 3): rows depend on their own X only
        Ju = self._scene.vertex_jacobian(posed, self.uids)  # (B, u, 3, D)
        J = theta.new_zeros(B, m, D)
        for c in range(4):  # intruder, then the receiver's corners
            Jc = torch.gather(Ju, 1, self.ucol[:, :, c, None, None].expand(-1, -1, 3, D))
            J += torch.einsum("bmk,bmkd->bmd", g[:, :, c], Jc)
        return Residuals(self._shape(psi.detach()), self._shape_jacobian(J), dim, self.mask)

    def _shape(self, psi):
        if self.metric == "point-to-plane":
            return psi
        return (psi[..., None] * self.normal).reshape(psi.shape[0], -1)

    def _shape_jacobian(self, J):
        if self.metric == "point-to-plane":
            return J
        return (self.normal[..., None] * J[:, :, None, :]).reshape(J.shape[0], -1, J.shape[-1])
