"""LO_m2d: model vertices to their closest data points (thesis Eq. 4.6 and 4.7).

For each visible vertex (visibility from the renderer) the closest data point of the
same model (data pixels are labelled by the rendered model ids) is found with a
KD-tree (scipy), built once per frame and model while the labels stay the same. Pairs farther than 10 mm or whose normals differ by more than 45
degrees are discarded, and, per bone, pairs beyond mean + 2 sigma of that bone's
distances (Ballan et al. 2012, Sec. 3). Point-to-point gives 3 residuals per pair;
point-to-plane gives 1, ``n^T (V - X)`` with the model normal fixed at the pose
where the pair was found (thesis Eq. 4.7; the normal's own derivative is dropped,
as is usual for point-to-plane ICP).
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import numpy as np
import torch
from scipy.spatial import cKDTree

from torchhand.geometry.mesh import vertex_normals
from torchhand.tracking.energies.base import (EnergyTerm, Prepared, Residuals, TrackState, bone_inliers, prepared,
                                              scatter_columns, stack_rows)

__all__ = ["ModelToData"]


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
    """

    name = "m2d"

    def __init__(self, metric="point-to-plane", max_distance=10.0, max_angle=45.0, max_vertices=1500,
                 outlier_sigma=2.0):
        if not max_distance > 0:
            raise ValueError(f"max_distance must be > 0 (mm), got {max_distance!r}")
        if metric not in ("point-to-point", "point-to-plane"):
            raise ValueError(f"metric must be 'point-to-point' or 'point-to-plane', got {metric!r}")
        self.metric, self.max_distance, self.cos_max = metric, max_distance, float(np.cos(np.radians(max_angle)))
        self.max_vertices, self.outlier_sigma = max_vertices, outlier_sigma

    def prepare(self, state: TrackState) -> Prepared:
        scene, B = state.scene, state.theta.shape[0]
        self._scene = scene
        dev, dt = state.theta.device, state.theta.dtype
        self.per_model = []
        count = torch.zeros(B, dtype=torch.int64)
        candidates = torch.zeros(B, dtype=torch.int64)
        unmatched = torch.zeros(B, dtype=torch.float64)
        tau2 = self.max_distance ** 2
        visible = state.visible_vertices()
        # the data side (points of a model's label, in the world frame, and their KD-tree)
        # is kept while the frame and the label mask stay the same (most outer iterations)
        self._data = {key: v for key, v in getattr(self, "_data", {}).items()
                      if any(v.frame is f for f in state.frames)}
        # visible vertices (a stride subsample) of every model and problem, and their
        # normals, one call per problem
        vis, nrm = [[None] * B for _ in scene.models], [[None] * B for _ in scene.models]
        for b in range(B):
            for k, name in enumerate(scene.names):
                vs = scene.vertex_slices[name]
                ids = torch.nonzero(visible[b][vs])[:, 0] + vs.start
                if len(ids) > self.max_vertices:
                    ids = ids[torch.linspace(0, len(ids) - 1, self.max_vertices, device=ids.device).long()]
                vis[k][b] = ids
            n = vertex_normals(state.posed.vertices[b : b + 1], scene.faces, torch.cat([v[b] for v in vis]),
                               scene.vertex_faces)[0]
            for k, part in enumerate(n.split([len(v[b]) for v in vis])):
                nrm[k][b] = part
        for k, (name, model) in enumerate(zip(scene.names, scene.models)):
            vs = scene.vertex_slices[name]
            rows = []
            for b in range(B):
                data = self._data_points(state, b, k)
                candidates[b] += len(vis[k][b])
                if len(vis[k][b]) == 0 or data is None:
                    unmatched[b] += tau2 * len(vis[k][b])
                    rows.append(None)
                    continue
                pts_w, nrm_w, tree = data
                V = state.posed.vertices[b, vis[k][b]]
                # the search stops just past the cut-off (scipy's bound is exclusive):
                # pairs beyond it are rejected anyway; scipy returns d = inf and
                # j = the number of points for them, here d = 2 x cut-off (rejected below)
                bound = float(np.nextafter(self.max_distance, np.inf))
                dist, j = tree.query(V.detach().cpu().numpy(), k=1, distance_upper_bound=bound)
                far = ~np.isfinite(dist)
                dist[far], j[far] = 2 * self.max_distance, 0
                j = torch.as_tensor(j, device=dev)
                X, nX = pts_w[j], nrm_w[j]
                nV = nrm[k][b]
                d = torch.as_tensor(dist, device=dev, dtype=dt)
                keep = (d <= self.max_distance) & ((nV * nX).sum(-1) >= self.cos_max)
                local = vis[k][b] - vs.start
                keep = keep & bone_inliers(d, model.vertex_bone[local], keep, model.num_bones, self.outlier_sigma)
                rows.append((local[keep], X[keep], nV[keep]))
                count[b] += int(keep.sum())
                unmatched[b] += float(d[~keep].clamp(max=self.max_distance).square().sum())
            self.per_model.append(_pad_rows(rows, B, dev, dt))
        return prepared(B, correspondences=count, candidates=candidates, unmatched=unmatched)

    def _data_points(self, state: TrackState, b: int, k: int):
        """(points, normals, KD-tree) of the data pixels labelled k in problem b, world
        frame; None when there are none. Reused while frame and labels are unchanged."""
        frame, camera, labels = state.frames[b], state.cameras[b], state.data_labels
        hit = self._data.get((id(frame), k))
        same = hit is not None and hit.frame is frame and hit.camera is camera
        if same and hit.labels is labels and hit.b == b:  # the same label map: no comparison needed
            return hit.data
        sel = labels[b] == k
        if same and torch.equal(hit.sel, sel):
            self._data[(id(frame), k)] = hit._replace(labels=labels, b=b)
            return hit.data
        data = None
        if bool(sel.any()):
            T_wc = camera.T_wc.to(state.theta)
            pts_w = frame.points[sel] @ T_wc[:3, :3].T + T_wc[:3, 3]
            nrm_w = frame.normals[sel] @ T_wc[:3, :3].T
            # an unbalanced tree builds in about two thirds of the time and queries as fast
            data = (pts_w, nrm_w, cKDTree(pts_w.detach().cpu().numpy(), balanced_tree=False))
        self._data[(id(frame), k)] = _DataEntry(frame, camera, sel, data, labels, b)
        return data

    def residuals(self, theta, posed, jacobian=True):
        B, D = theta.shape
        dim = 3 if self.metric == "point-to-point" else 1
        parts = []
        b = torch.arange(B, device=theta.device)[:, None]
        for k, (ids, X, nV, mask) in enumerate(self.per_model):
            if ids is None:
                continue
            out = posed.models[k]
            diff = (out.vertices[b, ids] - X) * mask[..., None]  # (B, n, 3)
            r = diff if self.metric == "point-to-point" else (nV * diff).sum(-1, keepdim=True)
            J = None
            if jacobian:
                model = self._scene.models[k]
                Jv = model.jacobian(None, ids, fk=(out.G, out.twists)) * mask[..., None, None]
                if self.metric == "point-to-plane":
                    Jv = (nV[..., None] * Jv).sum(-2, keepdim=True)
                cols = self._scene.slices[self._scene.names[k]]
                J = scatter_columns(Jv.reshape(B, -1, Jv.shape[-1]), cols, D)
            parts.append(Residuals(r.reshape(B, -1), J, dim, mask, torch.full_like(ids, k)))
        return stack_rows(parts, theta, jacobian, dim, len(self.per_model))


class _DataEntry(NamedTuple):
    """A cached data side: valid for ``frame`` and ``camera`` while the pixels labelled
    k are ``sel`` (known without comparing when the label map is the tensor ``labels``
    of problem ``b``); ``data`` is (points, normals, KD-tree) or None."""

    frame: object
    camera: object
    sel: torch.Tensor
    data: Optional[tuple]
    labels: torch.Tensor
    b: int


def _pad_rows(rows, B, dev, dt):
    """Per-problem (ids, A, C) rows (ids (n,), A and C (n, 3)) -> padded (B, n) ids,
    (B, n, 3) A and C, and a (B, n) mask; four Nones when no problem has a row."""
    n = max((len(r[0]) for r in rows if r is not None), default=0)
    if n == 0:
        return None, None, None, None
    ids = torch.zeros(B, n, dtype=torch.int64, device=dev)
    X = torch.zeros(B, n, 3, dtype=dt, device=dev)
    N = torch.zeros(B, n, 3, dtype=dt, device=dev)
    mask = torch.zeros(B, n, dtype=dt, device=dev)
    for b, r in enumerate(rows):
        if r is None:
            continue
        c = len(r[0])
        ids[b, :c], X[b, :c], N[b, :c], mask[b, :c] = r[0], r[1], r[2], 1
    return ids, X, N, mask
