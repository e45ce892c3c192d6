"""LO_m2d: model vertices to their closest data points (thesis Eq. 4.6 and 4.7).

For each visible vertex (visibility from the renderer, up to ``max_vertices`` per model
and problem, evenly spaced) the closest data point of the same model (data pixels are
labelled by the rendered model ids) is found within 10 mm through a
:class:`~torchhand.geometry.neighbors.PointIndex` (a grouped Warp hash grid), built once
per frame: the labels stay the same for the frame. Pairs farther than 10 mm or whose
normals differ by more than 45 degrees are discarded, and, per bone, pairs beyond mean +
2 sigma of that bone's distances (Ballan et al. 2012, Sec. 3). Point-to-point gives 3
residuals per pair; point-to-plane gives 1, ``n^T (V - X)`` with the model normal fixed
at the pose where the pair was found (thesis Eq. 4.7; the normal's own derivative is
dropped, as is usual for point-to-plane ICP).

Every problem of a batch has ``max_vertices`` rows per model; rows without a pair are
masked. Preparing an outer iteration makes no host synchronisation.
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import numpy as np
import torch

from torchhand.core.check import check_choice, check_int, check_number
from torchhand.geometry.mesh import vertex_normals
from torchhand.geometry.neighbors import PointIndex
from torchhand.tracking.energies.base import (EnergyTerm, ModelRows, Residuals, TrackState, begin, bone_inliers, capped,
                                              counts, scatter_columns, stack_rows, stride_subsample)

__all__ = ["ModelToData", "SurfaceRows"]


class SurfaceRows(NamedTuple):
    """One model's (vertex, data point) pairs: ids (B, n) int64 vertex ids local to the
    model; X (B, n, 3) the data points (world, mm); normal (B, n, 3) the model normals
    at the pose where the pairs were found; mask (B, n) 1 for kept pairs."""

    ids: torch.Tensor
    X: torch.Tensor
    normal: torch.Tensor
    mask: torch.Tensor




class _Data(NamedTuple):
    """The data side of a solve: labelled data points and normals (world) and their index."""

    points: torch.Tensor
    normals: torch.Tensor
    index: Optional[PointIndex]


class ModelToData(EnergyTerm):
    """E_model->data.

    The term's residuals are unweighted (the thesis' weight is 1); wrap it in
    :class:`~torchhand.tracking.energies.wrappers.Weighted` or
    :class:`~torchhand.tracking.energies.wrappers.Robust` for another weight or loss.

    Args:
        metric: "point-to-plane" (Eq. 4.7, the default, as the tracker uses) or
            "point-to-point" (Eq. 4.6).
        max_distance: mm (10 in the thesis); max_angle: degrees (45).
        max_vertices: visible vertices used per model and problem (a stride subsample).
        outlier_sigma: the per-bone rejection (Ballan et al. 2012, Sec. 3).
        backend: of the neighbour search, ``"warp"`` or ``"torch"`` (None: Warp when
            installed).
    """

    name = "m2d"
    needs = "depth"

    def __init__(self, metric="point-to-plane", max_distance=10.0, max_angle=45.0, max_vertices=1500,
                 outlier_sigma=2.0, backend: Optional[str] = None):
        check_number(max_distance, "max_distance", low=0, unit="mm")
        check_choice(metric, "metric", ("point-to-point", "point-to-plane"))
        check_int(max_vertices, "max_vertices", low=1)
        self.metric, self.max_distance, self.cos_max = metric, float(max_distance), float(np.cos(np.radians(max_angle)))
        self.max_vertices, self.outlier_sigma, self.backend = max_vertices, outlier_sigma, backend

    def _build(self, state: TrackState) -> _Data:
        """The labelled data points of every problem of the solve, built at its first
        outer iteration (host syncs: once per frame)."""
        dev, dt = state.theta.device, state.theta.dtype
        pts, nrm, prob, lab = [], [], [], []
        for b, (frame, camera) in enumerate(zip(state.frames, state.cameras)):
            labels = state.data_labels[b].reshape(-1)
            sel = torch.nonzero(labels >= 0)[:, 0]  # index_select: 2x faster than a boolean mask here
            T_wc = camera.T_wc.to(dev, dt)
            pts.append(frame.points.reshape(-1, 3).index_select(0, sel) @ T_wc[:3, :3].T + T_wc[:3, 3])
            nrm.append(frame.normals.reshape(-1, 3).index_select(0, sel) @ T_wc[:3, :3].T)
            prob.append(torch.full((pts[-1].shape[0],), b, dtype=torch.int64, device=dev))
            lab.append(labels.index_select(0, sel))
        points, normals = torch.cat(pts), torch.cat(nrm)
        index = None
        if len(points):
            # cells of half the distance: a vertex with no data within it (a pose far off,
            # as the initialisation's refinements start) then scans 5^3 cells at the full
            # distance instead of 9^3 with quarter cells, and a tracked one, found within
            # the first ring, is no slower (docs/benchmarks.md); the pairs are the same
            index = PointIndex(points, torch.cat(prob), torch.cat(lab), len(state.frames), len(state.scene.models),
                               self.max_distance, self.backend, cell=self.max_distance / 2)
        return _Data(points, normals, index)

    def prepare(self, state: TrackState) -> ModelRows:
        scene, B, dev, dt, data, problems = begin(state, self, self._build)
        visible = state.visible_vertices()
        V = state.posed.vertices
        batch = torch.arange(B, device=dev)[:, None]
        cut = self.max_distance
        # every model's candidates first, then their normals and their nearest data points
        # in one pass each for all models (the same values as model by model: each
        # vertex's normal and each query's answer do not depend on the others)
        picks = [stride_subsample(visible[:, scene.vertex_slices[name]], capped(self.max_vertices, state.share))
                 for name in scene.names]  # (local (B, M), slot (B, M)) per model
        ids = torch.cat([local + scene.vertex_slices[name].start for name, (local, _) in zip(scene.names, picks)], 1)
        groups = torch.cat([torch.where(slot, torch.full_like(local, k), -1) for k, (local, slot) in enumerate(picks)], 1)
        Vq = V[batch, ids]  # (B, sum M, 3)
        normals = vertex_normals(V, scene.faces, ids, scene.vertex_faces)
        if data.index is None:  # no labelled data (e.g. every model far from it)
            nearest = torch.full_like(ids, -1)
        else:
            nearest = data.index.nearest(Vq, problems, groups, cut)
        sizes = [local.shape[1] for local, _ in picks]
        count = torch.zeros(B, dtype=torch.int64, device=dev)
        candidates = torch.zeros(B, dtype=torch.int64, device=dev)
        unmatched = torch.zeros(B, dtype=torch.float64, device=dev)
        rows = []
        for model, (local, slot), Vk, nV, j in zip(scene.models, picks, Vq.split(sizes, 1), normals.split(sizes, 1),
                                                   nearest.split(sizes, 1)):  # models: a handful, static
            found = j >= 0
            if data.index is None:
                X, nX = torch.zeros_like(Vk), torch.zeros_like(Vk)
            else:
                X, nX = data.points[j.clamp(min=0)], data.normals[j.clamp(min=0)]
            d = torch.where(found, (Vk - X).norm(dim=-1), torch.full_like(Vk[..., 0], 2 * cut))
            keep = slot & found & (d <= cut) & ((nV * nX).sum(-1) >= self.cos_max)
            keep = keep & bone_inliers(d, model.vertex_bone[local], keep, model.num_bones, self.outlier_sigma)
            candidates += slot.sum(1)
            count += keep.sum(1)
            # a candidate without a pair is charged min(distance, cut-off)^2
            unmatched += torch.where(slot & ~keep, d.clamp(max=cut) ** 2, torch.zeros_like(d)).sum(1).double()
            rows.append(SurfaceRows(local, X.to(dt), nV.contiguous(), keep.to(dt)))
        return ModelRows(counts(B, correspondences=count, candidates=candidates, unmatched=unmatched), scene,
                            tuple(rows))

    def residuals(self, theta, posed, prepared: ModelRows, jacobian=True):
        B, D = theta.shape
        dim = 3 if self.metric == "point-to-point" else 1
        parts = []
        b = torch.arange(B, device=theta.device)[:, None]
        scene = prepared.scene
        for k, (ids, X, nV, mask) in enumerate(prepared.rows):
            out = posed.models[k]
            diff = (out.vertices[b, ids] - X) * mask[..., None]  # (B, n, 3)
            r = diff if self.metric == "point-to-point" else (nV * diff).sum(-1, keepdim=True)
            J = None
            if jacobian:
                Jv = scene.models[k].jacobian(None, ids, fk=(out.G, out.twists)) * mask[..., None, None]
                if self.metric == "point-to-plane":
                    Jv = (nV[..., None] * Jv).sum(-2, keepdim=True)
                cols = scene.slices[scene.names[k]]
                J = scatter_columns(Jv.reshape(B, -1, Jv.shape[-1]), cols, D)
            parts.append(Residuals(r.reshape(B, -1), J, dim, mask, torch.full_like(ids, k)))
        return stack_rows(parts, theta, jacobian, dim, len(prepared.rows))
