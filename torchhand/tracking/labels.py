"""Which model each data pixel belongs to: the labels the data terms pair by.

Model-to-data pairs a model's vertices only with data of its own label, data-to-model
pairs a data edge only with its own model's silhouette. Two labellings:

- :func:`label_by_proximity` (the tracker's default, ``TrackerConfig.labels =
  "proximity"``): a data point belongs to the model whose posed surface is nearest in 3D,
  within ``label_distance`` mm. A rope held between two hands is its own wherever it is
  nearer to the rope than to a hand, even where its pixels border the hands' images.
- :func:`label_data` (``"rendered"``): the id of the rendered model at the pixel, or of
  the nearest rendered pixel within a radius in the image (2D). Data of an object whose
  model slid off it goes to whatever model is rendered nearest in the image: the hands
  claimed the arch of a rope between them this way (docs/results.md, "Two hands and the
  rope").

The thesis does not say how data is assigned to models; the rendered ids are the
visibility and stay so whatever the labelling.
"""

from __future__ import annotations

from typing import List, Optional, Sequence

import cv2
import numpy as np
import torch

from torchhand.geometry.camera import Camera
from torchhand.geometry.neighbors import PointIndex
from torchhand.tracking.preprocess import DepthFrame

__all__ = ["LABELINGS", "label_data", "label_by_proximity"]

#: the names of the labellings (``TrackerConfig.labels``)
LABELINGS = ("proximity", "rendered")


def label_data(frame: DepthFrame, model_id: torch.Tensor, radius: float) -> torch.Tensor:
    """Assign every valid data pixel the id of the rendered model at it, or of the
    nearest rendered pixel within ``radius`` px (2D distance transform); -1 otherwise.

    frame: preprocessed data; model_id: (H, W) rendered ids (-1 empty) -> (H, W) int64.
    """
    ids = model_id.cpu().numpy()
    valid = frame.mask.cpu().numpy()
    labels = np.full(ids.shape, -1, np.int64)
    rendered = ids >= 0
    rows, cols = np.nonzero(rendered.any(1))[0], np.nonzero(rendered.any(0))[0]
    if len(rows):
        # only pixels within `radius` of the rendered pixels' box can get a label
        r = int(np.ceil(radius))
        r0, r1 = max(rows[0] - r, 0), min(rows[-1] + 1 + r, ids.shape[0])
        c0, c1 = max(cols[0] - r, 0), min(cols[-1] + 1 + r, ids.shape[1])
        crop, hit = ids[r0:r1, c0:c1], rendered[r0:r1, c0:c1]
        dist, lab = cv2.distanceTransformWithLabels(np.where(hit, 0, 255).astype(np.uint8), cv2.DIST_L2, 5,
                                                    labelType=cv2.DIST_LABEL_PIXEL)
        nearest = crop[hit][lab - 1]  # labels enumerate the zero (rendered) pixels row-major
        labels[r0:r1, c0:c1] = np.where((dist <= radius) & valid[r0:r1, c0:c1], nearest, -1)
    return torch.as_tensor(labels, device=model_id.device)


def _model_boxes_holding(queries: torch.Tensor, vertices: torch.Tensor, vertex_model: torch.Tensor,
                         distance: float) -> torch.Tensor:
    """(B, n) int64 how many models' vertex boxes, widened by ``distance``, hold each
    query (vertices (B, V, 3) of the B problems; vertex_model (V,)). A query held by one
    box can have vertices of that model only within the distance. The boxes are widened
    by 1e-3 mm more, so that the float32 search's rounding cannot leave out a model."""
    M = int(vertex_model.max()) + 1
    model = vertex_model.to(vertices.device)[None, :, None].expand_as(vertices)
    big = torch.finfo(vertices.dtype).max
    lo = vertices.new_full((vertices.shape[0], M, 3), big).scatter_reduce(1, model, vertices, "amin")
    hi = vertices.new_full((vertices.shape[0], M, 3), -big).scatter_reduce(1, model, vertices, "amax")
    count = torch.zeros(queries.shape[:2], dtype=torch.int64, device=queries.device)
    for m in range(M):  # a few models: 3x faster than one broadcast over (B, n, M, 3)
        count += torch.maximum(lo[:, m, None] - queries, queries - hi[:, m, None]).amax(-1) <= distance + 1e-3
    return count


def _nearest_in_steps(coarse: PointIndex, fine: PointIndex, queries: torch.Tensor, problems: torch.Tensor,
                      groups: torch.Tensor, distance: float, found: torch.Tensor) -> torch.Tensor:
    """The nearest vertex within ``distance`` of the queries whose ``found`` (a vertex
    within the distance, from ``coarse``'s first-found search) is >= 0, -1 for the rest,
    in two more steps that give the same answer as one search at any cell size (each is
    exact within its radius): the nearest within a quarter of the distance in
    ``fine``'s eighth-distance cells (a pixel on a model's surface ends there, where a
    half-distance cell holds hundreds of vertices); the rest, the nearest within the
    distance in ``coarse``."""
    near = fine.nearest(queries, problems, torch.where(found >= 0, groups, -1), distance / 4)
    rest = torch.where((found >= 0) & (near < 0), groups, -1)
    return torch.where(near >= 0, near, coarse.nearest(queries, problems, rest, distance))


def label_by_proximity(frames: Sequence[DepthFrame], cameras: Sequence[Camera], vertices: torch.Tensor,
                       vertex_model: torch.Tensor, distance: float, backend: Optional[str] = None) -> torch.Tensor:
    """Label every valid data pixel with the model of the nearest posed vertex in 3D
    within ``distance`` mm; -1 where no model is that near.

    Args:
        frames: B preprocessed frames (points in the camera frame).
        cameras: their B cameras.
        vertices: (B, V, 3) posed scene vertices (world).
        vertex_model: (V,) int64 model of each vertex.
        distance: the cut-off, mm.
        backend: of the neighbour search (:class:`~torchhand.geometry.neighbors.PointIndex`).
    Returns:
        (B, H, W) int64 labels on the frames' device.

    The vertices stand for the surface: the thesis meshes have a vertex every 2-5 mm,
    so the nearest vertex's model is the nearest surface's except within a few mm of
    where two models touch. One batched query for all problems, no host sync but the
    frames' pixel counts. With Warp and several models, the nearest vertex is searched
    only for the pixels that two models' widened vertex boxes hold; elsewhere the first
    vertex found within the distance gives the label (the same model).
    """
    B, V = vertices.shape[:2]
    dev, dt = vertices.device, vertices.dtype
    flat_v, problem_v = vertices.detach().reshape(-1, 3), torch.arange(B, device=dev).repeat_interleave(V)
    zero_v = torch.zeros(B * V, dtype=torch.int64, device=dev)
    # cells of half the distance: a pixel far from every model (a wall behind the hands)
    # scans 5^3 cells at the full distance, one near a model stops at the first vertex
    index = PointIndex(flat_v, problem_v, zero_v, B, 1, distance, backend, cell=distance / 2)
    H, W = frames[0].mask.shape
    labels = torch.full((B, H, W), -1, dtype=torch.int64, device=dev)
    pts: List[torch.Tensor] = []
    sel = []
    for frame, camera in zip(frames, cameras):
        T_wc = camera.T_wc.to(dev, dt)
        s = torch.nonzero(frame.mask.reshape(-1).to(dev))[:, 0]
        sel.append(s)
        pts.append(frame.points.reshape(-1, 3).to(dev, dt)[s] @ T_wc[:3, :3].T + T_wc[:3, 3])
    n = max((len(p) for p in pts), default=0)
    if n == 0:
        return labels
    queries = vertices.new_zeros(B, n, 3)
    groups = torch.full((B, n), -1, dtype=torch.int64, device=dev)
    for b, p in enumerate(pts):
        queries[b, :len(p)], groups[b, :len(p)] = p, 0
    problems = torch.arange(B, device=dev)
    one_model = bool((vertex_model == vertex_model[0]).all())
    if one_model or index.backend != "warp":  # any vertex gives the label / the KD-tree's nearest is exact
        nearest = index.nearest(queries, problems, groups, distance, any_point=one_model)  # into B*V
    else:
        # whether any vertex lies within the distance (stopping at the first found); where
        # one model's widened box alone holds the query, that vertex's model is the label
        found = index.nearest(queries, problems, groups, distance, any_point=True)
        several = _model_boxes_holding(queries, vertices.detach(), vertex_model, distance) >= 2
        fine = PointIndex(flat_v, problem_v, zero_v, B, 1, distance, backend, cell=distance / 8)
        nearest = torch.where(several, _nearest_in_steps(index, fine, queries, problems, groups, distance,
                                                         torch.where(several, found, -1)), found)
    model = torch.where(nearest >= 0, vertex_model.to(dev)[(nearest % V).clamp(min=0)], -1)
    flat = labels.view(B, -1)
    for b, s in enumerate(sel):
        flat[b, s] = model[b, :len(s)]
    return labels
