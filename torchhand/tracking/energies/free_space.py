"""F: model surface in free space is pulled back inside its data (not in the thesis).

A rendered pixel of model k is *in free space* when the sensor saw nothing there, or
saw something farther than the model by more than ``margin`` mm (with data in front,
the model is occluded, which is no evidence against it). "Nothing" excludes the small
holes of the data (``DepthFrame.covered``): a structured-light sensor loses the pixels
in the shadow beside an occluding finger, and a held rope seen through such shadows
was pushed along its axis, away from the hands, by 100 mm over 40 frames. The vertex seen at such a
pixel is paired with the nearest data pixel q labelled k within ``radius`` px (an
exact ring search of the data labels at the pairs' pixels only,
:func:`torchhand.geometry.neighbors.nearest_marked_pixel`, on the device; equidistant
pixels are told apart by a pixel hash), and its residual is the image distance from the vertex's projection to q, in mm
at the data's depth there: ``(pi(V) - q') z_q / f`` (2 rows), where q' is q moved
``tolerance`` px towards the free pixel. The model is pulled back to within
``tolerance`` px of its data silhouette along the image, whatever the depth there.
Pixels within ``tolerance`` px of their data are left alone: noisy sensors erode thin
silhouettes by a pixel or two (the Kinect noise model does), and pulling every
boundary pixel of every model inward by that much slid a held rope along its axis by
130 mm over 60 frames.

Why not the distance to q's projection ray, as data-to-model writes its pairs: every
ray meets the camera centre, so a vertex shortens its distance to any ray by moving
towards the camera, and a rope end paired with rays swung 170 mm towards the camera in
one step (data-to-model is kept from this by its 30 mm test on the 3D distance, which a
pair in free space has no data depth for).

Model-to-data (pairs within 10 mm) and data-to-model (data edges to the model's
silhouette) exert no force on surface that left the data: a rope end hanging beyond a
hand, a tube sliding along itself. The 2D silhouette term of Tagliasacchi et al. (2015,
a distance transform of the sensor silhouette) and DART's free-space constraint (Schmidt
et al. 2014: model points seen where the sensor saw farther) are the references; this is
the former's pairing with the latter's test, in the 3D units of the other terms. The
tracker wraps it in :data:`DEFAULT_LOSS` and :data:`DEFAULT_WEIGHT`
(:func:`torchhand.tracking.energies.parse_energy`, ``F``).

Every problem has ``max_pixels`` rows per model (a stride subsample of its free-space
pixels in the solve's render box); no host synchronisation with Warp (the ``"cpu"``
backend's distance transform runs on the host).
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional

import torch

from torchhand.core.check import check_int, check_number
from torchhand.geometry.neighbors import nearest_marked_pixel
from torchhand.geometry.render import window
from torchhand.optim.robust_loss import Cauchy
from torchhand.tracking.energies.base import (PixelPairs, PixelRows, TrackState, VertexPixelTerm, begin, capped,
                                              counts, seen_vertices, stride_subsample)

__all__ = ["FreeSpace", "DEFAULT_WEIGHT", "DEFAULT_LOSS"]

#: The tracker's weight of the term (one free-space pixel counts as a quarter of a
#: data pair, as a data-to-model pair does): docs/results.md, "Free space".
DEFAULT_WEIGHT = 0.25

#: Cauchy weights of each pair's ray distance, scale 5 mm: a pixel a few mm outside its
#: data pulls fully, one whose nearest data is far (a model lost as a whole) does not
#: dominate the frame.
DEFAULT_LOSS = Cauchy(scale=5.0)


class _Data(NamedTuple):
    """The data side of a solve: depth (B, h, w) mm on the render box (h, w pixels from
    (r0, c0) = ``origin``), 0 where nothing was seen, -1 in the data's small holes;
    labels (B, H, W) int64 the data labels of the whole images (the model of each data
    pixel, -1 none); boxes (B x K, 4) int32 the search box of each image and model."""

    depth: torch.Tensor
    labels: torch.Tensor
    boxes: torch.Tensor
    origin: tuple


class FreeSpace(VertexPixelTerm):
    """E_free: unweighted, with the plain sum of squares.

    Args:
        margin: mm, data farther than the model by more than this counts as free space.
        radius: px, the farthest data a free-space pixel is paired with (beyond it the
            pixel has no pair: a model lost as a whole is not dragged across the image).
        tolerance: px, free-space pixels this near their data are not pulled.
        max_pixels: free-space pixels used per model and problem (a stride subsample).
        backend: of the nearest-data-pixel search (``"warp"``, ``"cpu"`` or ``"torch"``;
            None: Warp when installed).
    """

    name = "free"
    needs = "depth"

    def __init__(self, margin: float = 10.0, radius: float = 40.0, tolerance: float = 2.0, max_pixels: int = 400,
                 backend: Optional[str] = None):
        check_number(tolerance, "tolerance", low=0, inclusive=True, unit="px")
        check_number(margin, "margin", low=0, inclusive=True, unit="mm")
        check_number(radius, "radius", low=0, unit="px")
        check_int(max_pixels, "max_pixels", low=1)
        self.margin, self.radius, self.max_pixels = float(margin), float(radius), max_pixels
        self.tolerance = float(tolerance)
        self.backend = backend

    def _build(self, state: TrackState) -> _Data:
        dev = state.theta.device
        H, W = state.frames[0].mask.shape
        box = (0, H, 0, W) if state.box is None else state.box
        r0, r1, c0, c1 = box
        # depth where seen, 0 where nothing was seen, -1 in the data's small holes (unknown);
        # on the box only
        def seen(f):
            mask, covered = f.mask[r0:r1, c0:c1], (f.mask if f.covered is None else f.covered)[r0:r1, c0:c1]
            return torch.where(mask, f.depth[r0:r1, c0:c1], torch.where(covered, -1.0, 0.0).to(f.depth))

        depth = torch.stack([seen(f) for f in state.frames]).to(dev)
        labels = state.data_labels.to(dev)
        K, P = len(state.scene.models), labels.shape[0]
        # every group's search box the whole image: a bound, as the searches need, without a
        # pass over every pixel and group (the rings stop at the radius or the first data)
        boxes = torch.tensor([0, H - 1, 0, W - 1], dtype=torch.int32, device=dev).repeat(P * K, 1)
        return _Data(depth.float(), labels, boxes, (r0, c0))

    def prepare(self, state: TrackState) -> PixelPairs:
        scene, B, dev, dt, data, p = begin(state, self, self._build)
        depth = data.depth[p]  # the pairs' nearest pixels are gathered below, not whole maps copied
        r0, c0 = data.origin
        h, w = depth.shape[1:]
        rend = window(state.render, (r0, r0 + h, c0, c0 + w))  # the data side's box
        ids, z_model = rend.model_id, rend.depth
        free = (ids >= 0) & ((depth == 0) | (depth > z_model + self.margin))  # (B, h, w)
        K, M = len(scene.models), capped(self.max_pixels, state.share)
        # up to M free-space pixels of each model, evenly spaced
        flat, mid = free.reshape(B, -1), ids.reshape(B, -1)
        pos, slot = zip(*(stride_subsample(flat & (mid == k), M) for k in range(K)))
        pos, slot = torch.cat(pos, 1), torch.cat(slot, 1)  # (B, K M) positions in the box
        model = torch.arange(K, device=dev).repeat_interleave(M)[None].expand(B, -1)
        b = torch.arange(B, device=dev)[:, None]
        pr, pc = pos // w, pos % w
        rc = torch.stack([pr + r0, pc + c0], -1)
        R = torch.full_like(pos, int(math.ceil(self.radius)))
        q = nearest_marked_pixel(data.labels, rc, torch.where(slot, model, -1), R, K, self.backend, images=p,
                                 boxes=data.boxes)  # (B, K M, 2) image (row, col), -1 none
        dist = torch.where(q[..., 0] >= 0, (rc - q).to(dt).norm(dim=-1), torch.full_like(pos, 2 ** 20, dtype=dt))
        keep = slot & (dist <= self.radius) & (dist > self.tolerance)
        gap = (rc - q).to(dt)  # (row, col) from the data pixel to the free one
        target = q.to(dt) + gap * (self.tolerance / dist.clamp(min=1e-9))[..., None]  # q', tolerance px out
        vid = seen_vertices(rend, scene.faces, rc)
        qr, qc = (q[..., 0] - r0).clamp(0, h - 1), (q[..., 1] - c0).clamp(0, w - 1)
        z = torch.where(keep, depth[b, qr, qc].to(dt), torch.zeros_like(dist))  # the data depth at q
        K_b = torch.stack([c.K.to(dev, dt) for c in state.cameras])
        T_b = torch.stack([c.T_cw.to(dev, dt) for c in state.cameras])
        # mm per px at the data's depth: the residual's scale, fixed for the outer iteration
        scale = torch.where(keep, z / K_b[:, 0, 0, None], torch.zeros_like(z))
        per_model = []
        for k, name in enumerate(scene.names):
            rows = slice(k * M, (k + 1) * M)
            local = torch.where(keep[:, rows], vid[:, rows] - scene.vertex_slices[name].start, 0)
            per_model.append(PixelRows(local, target[:, rows].flip(-1), scale[:, rows], keep[:, rows].to(dt)))
        found = counts(B, device=dev, pixels=keep.sum(1), free=free.reshape(B, -1).sum(1))
        return PixelPairs(found, scene=scene, rows=tuple(per_model), K=K_b, T_cw=T_b)
