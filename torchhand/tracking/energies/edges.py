"""E: the model's rendered edges pulled onto the edges of colour images (Ballan et al.
2012, Sec. 3; the edge distance chosen by the thesis' Ch. 3 benchmark).

Per view and outer iteration:

1. *model edges*: the occluding contours of the rendered depth map
   (:func:`torchhand.geometry.render.silhouette_edges`: the silhouette and the depth
   discontinuities inside it, where a finger passes in front of the palm; Ballan's
   "thresholding the gradient of the rendered depth maps"), at most ``max_points`` of
   them per view (a stride subsample), each with its orientation: the image direction
   of the hit face's normal;
2. each is matched with an image edge pixel (Canny,
   :func:`torchhand.tracking.preprocess.preprocess_colour`) by the Chamfer distance
   ``config`` (:mod:`torchhand.geometry.chamfer`): by default DCH-Thres, the nearest
   edge pixel within ``radius_px`` whose orientation differs by less than 22.5 degrees,
   tied for best with DCH-DT3 in the frame-pair benchmark over 80 pairs and 3.7 times
   cheaper (``eval/exp_frame_pairs.py``, docs/results.md). Image edges have no sign
   (the hand may be brighter or darker than what is behind it), so orientations are
   compared modulo 180 degrees; the thesis' signed variant needs silhouettes, which
   colour images do not give;
3. per-bone outlier rejection (Ballan Sec. 3): a pair farther than the mean plus
   ``sigma`` standard deviations of its bone's pairs in the view is dropped;
4. the vertex seen at the model edge pixel is pulled so that it projects onto its image
   edge pixel: Ballan's reprojection error ``pi_c(v_k) - p`` (Eq. 2), in mm at the
   vertex's depth (:class:`~torchhand.tracking.energies.base.VertexPixelTerm`), so that
   the term combines with depth terms and collisions in an RGB-D rig without a weight
   per camera. (A distance to the edge pixel's ray would let a vertex shorten every
   pair by moving towards the camera, the reason the free-space term projects too.)

The term is prepared once per view (``needs = "colour"``): a rig of V cameras gives each
problem the pairs of all its views.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional

import torch

from torchhand.core.check import check_choice, check_int, check_number
from torchhand.geometry.chamfer import ChamferConfig, boundary_pixels, contour_boxes, contour_marks, match_contour
from torchhand.geometry.mesh import vertex_normals
from torchhand.optim.robust_loss import Cauchy
from torchhand.tracking.energies.base import (PixelPairs, TrackState, VertexPixelTerm, begin, bone_inliers, counts,
                                              pixel_rows, project_views, stride_subsample)

__all__ = ["Edges", "DEFAULT_CHAMFER", "DEFAULT_LOSS", "rim_vertices"]

#: the pairs' robust loss: image edges beside the hand (a textured background, shading)
#: are found for model edges that have no image edge of their own (a finger in front of
#: the palm, of the same colour), and least squares with the per-bone cut alone let them
#: pull the hands 8-10 mm off on the first frame of the demo seen from 4 cameras (2 mm
#: with this loss; docs/multicam.md)
DEFAULT_LOSS = Cauchy(scale=3.0)

#: the edge distance: DCH-Thres, tau = 22.5 deg, unsigned (image edges have no sign)
DEFAULT_CHAMFER = ChamferConfig(kind="DCH-Thres", tau_deg=22.5, signed=False, radius_px=40)


class _Data(NamedTuple):
    marks: torch.Tensor  # (P, H, W) int64 orientation bin of each image edge pixel, -1 elsewhere
    phi: torch.Tensor  # (P, H, W) float32 their orientation, NaN elsewhere
    boxes: Optional[torch.Tensor]  # chamfer.contour_boxes of marks: once per frame, not per iteration or particle


def rim_vertices(state: TrackState, max_points: int, contours: str = "occluding") -> tuple:
    """The visible vertices lying on the rendered edges of each view (Ballan: "each mesh
    vertex lying on an edge of these maps"): those whose projection falls on, or next
    to, a pixel of ``render.silhouette_edges`` (``contours="occluding"``: the
    silhouette and the depth discontinuities inside it) or of the silhouette's boundary
    alone (``"silhouette"``), at most ``max_points`` per view (a stride subsample).

    Returns (ids (B, n) int64 scene vertex ids, pixels (B, n, 2) int64 (row, col) of
    their projections, phi (B, n) the image direction in [0, 2 pi) of their normals,
    ok (B, n) bool real entries, z (B, n) their depth in mm)."""
    B = state.theta.shape[0]
    rend = state.render
    h, w = rend.model_id.shape[-2:]  # the render's maps: the image, or the box it was cropped to
    o_r, o_c = rend.origin or (0, 0)
    V = state.posed.vertices.detach()
    uv, z, _, T = project_views(state, V)  # every vertex, (B, V, 2)
    iu, iv = uv[..., 0].round().long(), uv[..., 1].round().long()
    ju, jv = iu - o_c, iv - o_r  # in the maps' pixels
    inside = (ju >= 0) & (ju < w) & (jv >= 0) & (jv < h)
    # on an edge pixel or one of its 8 neighbours (looked up at the vertices, not over the image)
    rim = rend.silhouette_edges if contours == "occluding" else boundary_pixels(rend.model_id >= 0)
    edges = rim.reshape(B, -1)
    on = torch.zeros_like(inside)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            at = (jv + dr).clamp(0, h - 1) * w + (ju + dc).clamp(0, w - 1)
            on |= edges.gather(1, at)
    on &= state.visible_vertices() & inside
    ids, ok = stride_subsample(on, max_points)
    pixels = torch.stack([iv.gather(1, ids).clamp(o_r, o_r + h - 1), iu.gather(1, ids).clamp(o_c, o_c + w - 1)], -1)
    n = vertex_normals(V, state.scene.faces, ids, state.scene.vertex_faces) @ T[:, :3, :3].transpose(1, 2)
    phi = torch.remainder(torch.atan2(n[..., 1], n[..., 0]), 2 * math.pi)
    return ids, pixels, phi, ok, z.gather(1, ids)


class Edges(VertexPixelTerm):
    """E_edges (module docstring).

    Args:
        config: the Chamfer distance of the pairs (:class:`ChamferConfig`;
            ``radius_px``: the farthest pair).
        max_points: model edge pixels used per view.
        sigma: the per-bone outlier cut in standard deviations (Ballan: 2); None keeps
            every pair.
        backend: of the nearest-pixel searches (``"warp"``, ``"torch"``; None: Warp when
            installed).
        contours: the model edges: ``"occluding"`` (silhouette and inner depth
            discontinuities, for image edges) or ``"silhouette"`` (its boundary alone,
            for silhouette images: the thesis' Ch. 3 benchmark).
    """

    name = "edges"
    needs = "colour"

    def __init__(self, config: ChamferConfig = DEFAULT_CHAMFER, max_points: int = 400, sigma=2.0, backend=None,
                 contours: str = "occluding"):
        check_choice(contours, "contours", ("occluding", "silhouette"))
        self.contours = contours
        if not isinstance(config, ChamferConfig):
            raise TypeError(f"config must be a ChamferConfig, got {type(config).__name__}")
        check_int(max_points, "max_points", low=1)
        check_number(sigma, "sigma", low=0, none=True)
        self.config, self.max_points, self.sigma, self.backend = config, max_points, sigma, backend

    def _build(self, state: TrackState) -> _Data:
        if state.colours is None or any(c is None for c in state.colours):
            raise ValueError("the edge term needs a colour frame for every view")
        H, W = state.cameras[0].height, state.cameras[0].width
        marks, phis = [], []
        for c in state.colours:
            m, phi = contour_marks(c.edges.cpu().numpy(), c.edge_phi.double().cpu().numpy(), (H, W), self.config)
            marks.append(torch.as_tensor(m))
            phis.append(torch.as_tensor(phi))
        dev = state.theta.device
        marks = torch.stack(marks).to(dev)
        return _Data(marks, torch.stack(phis).to(dev), contour_boxes(self.config, marks, self.backend))

    def prepare(self, state: TrackState) -> PixelPairs:
        scene, B, dev, dt, data, p = begin(state, self, self._build)
        ids, q, phi, ok, z = rim_vertices(state, self.max_points, self.contours)
        match = match_contour(self.config, data.marks, data.phi, q, phi, ok, backend=self.backend, images=p,
                              boxes=data.boxes)
        vid = ids.gather(1, match.source)
        src = q.gather(1, match.source[..., None].expand(-1, -1, 2))  # the model pixel of each pair
        valid = match.valid
        if self.sigma is not None:
            dist = (match.pixel - src).to(dt).norm(dim=-1)
            valid = valid & bone_inliers(dist, scene.vertex_bone_id[vid], valid, scene.num_bones, self.sigma)
        K_b = torch.stack([c.K.to(dev, dt) for c in state.cameras])
        scale = z.gather(1, match.source) / K_b[:, 0, 0, None]  # mm per px at the model's depth
        T_b = torch.stack([c.T_cw.to(dev, dt) for c in state.cameras])
        rows = pixel_rows(scene, vid, match.pixel.flip(-1).to(dt), scale, valid)
        # a model edge pixel without an image edge pixel is charged the cut-off, radius_px at its depth
        matched = torch.zeros_like(ok, dtype=torch.int64).scatter_reduce(1, match.source, valid.long(), "amax") > 0
        cut = (self.config.radius_px * z / K_b[:, 0, 0, None]) ** 2
        unmatched = torch.where(ok & ~matched, cut, torch.zeros_like(cut)).sum(1).double()
        found = counts(B, device=dev, correspondences=valid.sum(1), candidates=torch.maximum(ok.sum(1), valid.sum(1)),
                       unmatched=unmatched, edges=ok.sum(1))
        return PixelPairs(found, scene=scene, rows=rows, K=K_b, T_cw=T_b)

    def __repr__(self) -> str:
        return f"Edges({self.config.kind}, max_points={self.max_points}, sigma={self.sigma})"
