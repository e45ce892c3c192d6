"""LO_d2m: data depth discontinuities to the model's silhouette (thesis Eq. 4.8).

Depth-discontinuity pixels of the data (see preprocess) are matched to the nearest
silhouette pixel of the rendered model with the same label by a 2D distance
transform (OpenCV); the vertex seen at that silhouette pixel must lie on the data
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

import cv2
import numpy as np
import torch

from torchhand.geometry.camera import pixel_rays, unproject_pixels
from torchhand.model.kinematics import skew
from torchhand.optim.robust_loss import Cauchy
from torchhand.tracking.energies.base import (EnergyTerm, Prepared, Residuals, TrackState, bone_inliers, prepared,
                                              scatter_columns, stack_rows)
from torchhand.tracking.energies.model_to_data import _pad_rows

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


class DataToModel(EnergyTerm):
    """E_data->model, unweighted and with the plain sum of squares (the tracker wraps
    it in :data:`DEFAULT_LOSS` and :data:`DEFAULT_WEIGHT`).

    Args:
        max_distance: mm (30 in the thesis).
        max_pixels: data edge pixels used per model and problem (a stride subsample).
        outlier_sigma: per-bone rejection of pairs whose ray distance exceeds the
            mean + ``outlier_sigma`` std of their bone's pairs (None: off).
    """

    name = "d2m"

    def __init__(self, max_distance=30.0, max_pixels=600, outlier_sigma=2.0):
        if not max_distance > 0:
            raise ValueError(f"max_distance must be > 0 (mm), got {max_distance!r}")
        if outlier_sigma is not None and not outlier_sigma > 0:
            raise ValueError(f"outlier_sigma must be > 0 or None, got {outlier_sigma!r}")
        self.max_distance, self.max_pixels, self.outlier_sigma = max_distance, max_pixels, outlier_sigma

    def prepare(self, state: TrackState) -> Prepared:
        scene, B = state.scene, state.theta.shape[0]
        self._scene = scene
        dev, dt = state.theta.device, state.theta.dtype
        rend = state.render
        count = torch.zeros(B, dtype=torch.int64)
        candidates = torch.zeros(B, dtype=torch.int64)
        outliers = torch.zeros(B, dtype=torch.int64)
        rejected = torch.zeros(B, dtype=torch.float64)  # summed squared ray distances of outliers
        self.per_model = []
        # silhouette pixels (row, col) of every problem and the model each belongs to
        sil = [torch.nonzero(rend.silhouette_edges[b]).cpu().numpy() for b in range(B)]
        sil_model = [rend.model_id[b][rend.silhouette_edges[b]].cpu().numpy() for b in range(B)]
        for k, (name, model) in enumerate(zip(scene.names, scene.models)):
            vs = scene.vertex_slices[name]
            rows = []
            for b in range(B):
                frame, cam = state.frames[b], state.cameras[b]
                zero_rc = sil[b][sil_model[b] == k]  # row-major, as nonzero returns them
                sel = torch.zeros(0, dtype=torch.int64)
                if len(frame.edges):
                    sel = torch.nonzero(state.data_labels[b][frame.edges[:, 0], frame.edges[:, 1]] == k)[:, 0]
                if len(sel) > self.max_pixels:
                    sel = sel[torch.linspace(0, len(sel) - 1, self.max_pixels, device=sel.device).long()]
                candidates[b] += len(sel)
                if len(zero_rc) == 0 or len(sel) == 0:
                    rows.append(None)
                    continue
                rc = frame.edges[sel]
                # Nearest model silhouette pixel of every data edge pixel, by a distance
                # transform on the box around both pixel sets, which holds every nearest
                # pixel (its labels index the zero pixels in row-major order).
                rcn = rc.cpu().numpy()
                lo = np.minimum(zero_rc.min(0), rcn.min(0))
                hi = np.maximum(zero_rc.max(0), rcn.max(0)) + 1
                src = np.full(hi - lo, 255, np.uint8)
                src[zero_rc[:, 0] - lo[0], zero_rc[:, 1] - lo[1]] = 0
                _, labels = cv2.distanceTransformWithLabels(src, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
                p = torch.as_tensor(zero_rc[labels[rcn[:, 0] - lo[0], rcn[:, 1] - lo[1]] - 1], device=dev)
                fid = rend.face_id[b][p[:, 0], p[:, 1]]
                bary = rend.barycentric[b][p[:, 0], p[:, 1]].to(dt)
                w = torch.cat([1 - bary.sum(-1, keepdim=True), bary], -1)
                vid = scene.faces[fid, w.argmax(-1)]  # global vertex seen at the model pixel
                z = frame.edge_depth[sel].to(dt)
                uv = rc.flip(-1).to(dt)
                K, T_cw = cam.K.to(dev, dt), cam.T_cw.to(dev, dt)
                X_cam = unproject_pixels(uv, z, K)
                X = (X_cam - T_cw[:3, 3]) @ T_cw[:3, :3]  # to world
                V = state.posed.vertices[b, vid]
                within = (V - X).norm(dim=-1) <= self.max_distance
                rays = pixel_rays(uv, K, T_cw)
                ray_dist = (torch.cross(V, rays.direction, dim=-1) - rays.moment).norm(dim=-1)
                keep = within
                if self.outlier_sigma is not None:
                    keep = within & bone_inliers(ray_dist, model.vertex_bone[vid - vs.start], within,
                                                 model.num_bones, self.outlier_sigma)
                    rejected[b] += float(ray_dist[within & ~keep].square().sum())
                rows.append((vid[keep] - vs.start, rays.direction[keep], rays.moment[keep]))
                count[b] += int(keep.sum())
                outliers[b] += int((within & ~keep).sum())
            self.per_model.append(_pad_rows(rows, B, dev, dt))
        # a pair beyond the cut-off is charged the cut-off squared, an outlier its own
        # squared distance (as model-to-data does)
        unmatched = self.max_distance ** 2 * (candidates - count - outliers).double() + rejected
        return prepared(B, correspondences=count, candidates=candidates, unmatched=unmatched)

    def fold_row_weights(self, sqrt_w):
        # V x d - m is linear in the line (d, m): scaling both by sqrt(w) weights the
        # pair's squared residual, and its Jacobian, by w
        start = 0
        for k, (ids, d, m, mask) in enumerate(self.per_model):
            if ids is None:
                continue
            sw = sqrt_w[:, start : start + ids.shape[1], None]
            self.per_model[k] = (ids, d * sw, m * sw, mask)
            start += ids.shape[1]
        return True

    def residuals(self, theta, posed, jacobian=True):
        B, D = theta.shape
        parts = []
        b = torch.arange(B, device=theta.device)[:, None]
        for k, (ids, d, m, mask) in enumerate(self.per_model):
            if ids is None:
                continue
            out = posed.models[k]
            V = out.vertices[b, ids]
            r = (torch.cross(V, d, dim=-1) - m) * mask[..., None]  # Eq. 4.8
            J = None
            if jacobian:
                model = self._scene.models[k]
                Jv = model.jacobian(None, ids, fk=(out.G, out.twists))
                Jr = -(skew(d) @ Jv) * mask[..., None, None]  # d(V x d) = -[d]x dV
                cols = self._scene.slices[self._scene.names[k]]
                J = scatter_columns(Jr.reshape(B, -1, Jr.shape[-1]), cols, D)
            parts.append(Residuals(r.reshape(B, -1), J, 3, mask, torch.full_like(ids, k)))
        return stack_rows(parts, theta, jacobian, 3, len(self.per_model))
