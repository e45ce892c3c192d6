"""LO_d2m: data depth discontinuities to the model's silhouette (thesis Eq. 4.8).

Depth-discontinuity pixels of the data (see preprocess) are matched to the nearest
silhouette pixel of the rendered model with the same label, an exact nearest-pixel
search (:func:`torchhand.geometry.neighbors.nearest_marked_pixel`) bounded by the
distance at which a pair can still pass the 30 mm test; the vertex seen at that
silhouette pixel must lie on the data
pixel's projection ray, written as a Pluecker line (d, m): the residual is
``V x d - m`` (its norm is the vertex's distance to the ray). Pairs whose 3D
distance, with the data depth averaged over 3x3 pixels, exceeds 30 mm are dropped,
and, as for model-to-data, per bone the pairs whose ray distance lies beyond mean + 2
sigma of that bone's pairs (Ballan et al. 2012, Sec. 3). The tracker's default wraps
the term in a Cauchy loss of the ray distance whose scale follows the model's median
misfit and a weight of 0.25 (:func:`torchhand.tracking.energies.parse_energy`), choices
the thesis leaves open; see :data:`DEFAULT_LOSS` and :data:`DEFAULT_WEIGHT`.
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import torch

from torchhand.core.check import check_int, check_number
from torchhand.geometry.camera import pixel_rays, unproject_pixels
from torchhand.geometry.neighbors import marked_boxes, nearest_marked_pixel
from torchhand.geometry.render import window_map
from torchhand.optim.robust_loss import Cauchy
from torchhand.tracking.energies.base import (ModelRows, RayRows, TrackState, VertexRayTerm, begin, bone_inliers,
                                              capped, counts, seen_vertices)

__all__ = ["DataToModel", "DEFAULT_WEIGHT", "DEFAULT_LOSS"]

#: The tracker's weight of the term. The thesis adds E_m2d and E_d2m with weight 1
#: (Eq. 4.5), as sums over every visible vertex and every discontinuity pixel. Here both
#: are subsampled (up to 1,500 vertices and 600 pixels per model), which already doubles
#: d2m's share, and the measured weight is 0.25: on Kinect noise the data silhouette is
#: eroded by about a pixel, which pulls the models away from the camera (docs/results.md,
#: "Data-to-model weight").
DEFAULT_WEIGHT = 0.25

#: The tracker's robust loss of the term: Cauchy weights ``1 / (1 + (r / c)^2)`` of each
#: pair's ray distance r, with c the larger of 3 mm and twice the median ray distance of
#: the model's kept pairs (per model and problem). Why: a data edge whose nearest model
#: silhouette is not its own contour (the other hand, a hidden finger, noise) otherwise
#: pulls with its full distance up to the 30 mm cut-off. At the ground-truth pose of a
#: two-hand frame the ray distances have a median of 1.1 mm and a tail to 21 mm, and over
#: the 231 frames of sequence 01 such pairs turned a hidden thumb 50 degrees away. A
#: fixed c = 3 mm (about 3 pixels at the thesis' working distance) fixed that but slowed
#: the recovery from fast motion, where all of a model's pairs are far: c follows the
#: model's median misfit, so a model that is off as a whole is pulled at full strength
#: and a model that fits is not pulled by its few far pairs (docs/results.md,
#: "Data-to-model outliers").
DEFAULT_LOSS = Cauchy(scale=3.0, relative=2.0)


class _Edges(NamedTuple):
    """The data side of a solve, (B, K, M) slots per problem and model: rc (..., 2) int64
    pixels; X (..., 3) world points; d, m (..., 3) their Pluecker rays; valid bool;
    radius int64 px, the search radius around each pixel."""

    rc: torch.Tensor
    X: torch.Tensor
    d: torch.Tensor
    m: torch.Tensor
    valid: torch.Tensor
    radius: torch.Tensor


class DataToModel(VertexRayTerm):
    """E_data->model, unweighted and with the plain sum of squares (the tracker wraps
    it in :data:`DEFAULT_LOSS` and :data:`DEFAULT_WEIGHT`).

    Args:
        max_distance: mm (30 in the thesis).
        max_pixels: data edge pixels used per model and problem (a stride subsample).
        outlier_sigma: per-bone rejection of pairs whose ray distance exceeds the
            mean + ``outlier_sigma`` std of their bone's pairs (None: off).
    """

    name = "d2m"
    needs = "depth"

    def __init__(self, max_distance=30.0, max_pixels=600, outlier_sigma=2.0, backend: Optional[str] = None):
        check_number(max_distance, "max_distance", low=0, unit="mm")
        check_number(outlier_sigma, "outlier_sigma", low=0, none=True)
        check_int(max_pixels, "max_pixels", low=1)
        self.max_distance, self.max_pixels, self.outlier_sigma = float(max_distance), max_pixels, outlier_sigma
        self.backend = backend
        self._bones = None  # (scene, (V,) scene-level bone of every vertex, number of bones)

    def _build(self, state: TrackState) -> _Edges:
        """The labelled data edge pixels of every problem of the solve (up to
        ``max_pixels`` per model, evenly spaced), their points, Pluecker rays and search
        radii; built at the solve's first outer iteration (host work once per frame)."""
        dev, dt = state.theta.device, state.theta.dtype
        B, K, M = len(state.frames), len(state.scene.models), capped(self.max_pixels, state.share)
        rc = torch.zeros(B, K, M, 2, dtype=torch.int64, device=dev)
        z = torch.zeros(B, K, M, dtype=dt, device=dev)
        valid = torch.zeros(B, K, M, dtype=torch.bool, device=dev)
        for b, frame in enumerate(state.frames):
            if not len(frame.edges):
                continue
            label = state.data_labels[b][frame.edges[:, 0], frame.edges[:, 1]]
            for k in range(K):
                sel = torch.nonzero(label == k)[:, 0]
                if len(sel) > M:  # a stride subsample
                    sel = sel[torch.linspace(0, len(sel) - 1, M, device=sel.device).long()]
                n = len(sel)
                rc[b, k, :n], z[b, k, :n], valid[b, k, :n] = frame.edges[sel], frame.edge_depth[sel].to(dt), True
        K_b = torch.stack([c.K.to(dev, dt) for c in state.cameras])  # (B, 3, 3)
        T_b = torch.stack([c.T_cw.to(dev, dt) for c in state.cameras])
        uv = rc.flip(-1).to(dt).reshape(B, K * M, 2)
        X_cam = unproject_pixels(uv, z.reshape(B, K * M), K_b)
        X = ((X_cam - T_b[:, None, :3, 3]) @ T_b[:, :3, :3]).view(B, K, M, 3)  # to world
        rays = pixel_rays(uv, K_b, T_b)
        # the farthest pixel distance at which a model point can lie within max_distance of
        # the data point: the ball's image at the nearest depth, with room for perspective
        # off the axis and for the vertex seen at a pixel lying a triangle away from it
        f = K_b[:, 0, 0].max()
        near = (z - self.max_distance).clamp(min=1.0)
        radius = torch.ceil(1.5 * f * self.max_distance / near).long().clamp(max=400) + 4
        return _Edges(rc, X, rays.direction.view(B, K, M, 3), rays.moment.view(B, K, M, 3), valid, radius)

    def prepare(self, state: TrackState) -> ModelRows:
        scene, B, dev, dt, data, p = begin(state, self, self._build)
        rc, X, d, m, valid, radius = (x[p] for x in data)
        K, M = valid.shape[1:]
        rend = state.render
        if self._bones is None or self._bones[0] is not scene:
            offsets = torch.tensor([0] + [mdl.num_bones for mdl in scene.models], device=dev).cumsum(0)
            bone = torch.cat([mdl.vertex_bone.to(dev) + offsets[k] for k, mdl in enumerate(scene.models)])
            self._bones = (scene, bone, int(offsets[-1]))
        _, vertex_bone, num_bones = self._bones
        # the nearest silhouette pixel of the data pixel's model (Eq. 4.8's pairs), searched
        # on whole images: the data pixels lie anywhere in them, the render may be a crop
        crop = torch.where(rend.silhouette_edges, rend.model_id, -1).to(torch.int32)
        marks = window_map(crop, rend.origin, (0, state.cameras[0].height, 0, state.cameras[0].width), -1)
        # the marks' boxes from the render's crop (inside the image): the same as from the
        # whole image, without a pass over it per model
        o_r, o_c = rend.origin or (0, 0)
        boxes = marked_boxes(crop, K) + torch.tensor([o_r, o_r, o_c, o_c], dtype=torch.int32, device=dev)
        groups = torch.where(valid, torch.arange(K, device=dev)[None, :, None], -1).reshape(B, K * M)
        px = nearest_marked_pixel(marks, rc.reshape(B, K * M, 2), groups, radius.reshape(B, K * M), K, self.backend,
                                  boxes=boxes)
        found = px[..., 0] >= 0
        b = torch.arange(B, device=dev)[:, None]
        vid = seen_vertices(rend, scene.faces, px)  # (B, K M) the scene vertex seen at the model pixel
        V = state.posed.vertices[b, vid]
        Xf, df, mf = X.reshape(B, K * M, 3), d.reshape(B, K * M, 3), m.reshape(B, K * M, 3)
        within = found & ((V - Xf).norm(dim=-1) <= self.max_distance)
        ray_dist = (torch.cross(V, df, dim=-1) - mf).norm(dim=-1)
        keep = within
        if self.outlier_sigma is not None:
            keep = within & bone_inliers(ray_dist, vertex_bone[vid], within, num_bones, self.outlier_sigma)
        outlier = within & ~keep
        candidates, count = valid.reshape(B, -1).sum(1), keep.sum(1)
        # a pair beyond the cut-off is charged the cut-off squared, an outlier its own
        # squared distance (as model-to-data does)
        unmatched = (self.max_distance ** 2 * (candidates - count - outlier.sum(1)).double()
                     + torch.where(outlier, ray_dist ** 2, torch.zeros_like(ray_dist)).sum(1).double())
        per_model = []
        for k, name in enumerate(scene.names):
            rows = slice(k * M, (k + 1) * M)
            local = torch.where(keep[:, rows], vid[:, rows] - scene.vertex_slices[name].start, 0)
            per_model.append(RayRows(local, df[:, rows], mf[:, rows], keep[:, rows].to(dt)))
        return ModelRows(counts(B, correspondences=count, candidates=candidates, unmatched=unmatched), scene,
                        tuple(per_model))
