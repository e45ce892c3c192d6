"""F: model surface in free space is pulled back inside its data (not in the thesis).

A rendered pixel of model k is *in free space* when the sensor saw nothing there, or
saw something farther than the model by more than ``margin`` mm (with data in front,
the model is occluded, which is no evidence against it). "Nothing" excludes the small
holes of the data (``DepthFrame.covered``): a structured-light sensor loses the pixels
in the shadow beside an occluding finger, and a held rope seen through such shadows
was pushed along its axis, away from the hands, by 100 mm over 40 frames. The vertex seen at such a
pixel is paired with the nearest data pixel q labelled k within ``radius`` px (an
exact Euclidean feature transform of the data labels,
:func:`torchhand.geometry.neighbors.marked_pixel_transform`, computed once per frame
on the CPU, since the labels stay for the frame; each outer iteration then reads it on
the device), and its residual is the image distance from the vertex's projection to q, in mm
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
pixels in the solve's render box); no host synchronisation after the frame's transform.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from torchhand.core.check import check_int, check_number
from torchhand.geometry.neighbors import marked_pixel_transform
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
    """The data side of a solve, on the render box (h, w pixels from (r0, c0)): depth
    (B, h, w) mm, 0 where nothing was seen, -1 in the data's small holes; nearest (B, K, h, w, 2) int64 the nearest
    data pixel labelled k (row, col in the image); distance (B, K, h, w) px to it."""

    depth: torch.Tensor
    nearest: torch.Tensor
    distance: torch.Tensor
    origin: tuple


class FreeSpace(VertexPixelTerm):
    """E_free: unweighted, with the plain sum of squares.

    Args:
        margin: mm, data farther than the model by more than this counts as free space.
        radius: px, the farthest data a free-space pixel is paired with (beyond it the
            pixel has no pair: a model lost as a whole is not dragged across the image).
        tolerance: px, free-space pixels this near their data are not pulled.
        max_pixels: free-space pixels used per model and problem (a stride subsample).
    """

    name = "free"
    needs = "depth"

    def __init__(self, margin: float = 10.0, radius: float = 40.0, tolerance: float = 2.0, max_pixels: int = 400):
        check_number(tolerance, "tolerance", low=0, inclusive=True, unit="px")
        check_number(margin, "margin", low=0, inclusive=True, unit="mm")
        check_number(radius, "radius", low=0, unit="px")
        check_int(max_pixels, "max_pixels", low=1)
        self.margin, self.radius, self.max_pixels = float(margin), float(radius), max_pixels
        self.tolerance = float(tolerance)

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
        nearest, distance = marked_pixel_transform(state.data_labels, len(state.scene.models), box)
        return _Data(depth.float(), nearest, distance, (r0, c0))

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
        q = data.nearest[p[:, None], model, pr, pc]  # (B, K M, 2) image (row, col)
        dist = data.distance[p[:, None], model, pr, pc].to(dt)
        rc = torch.stack([pr + r0, pc + c0], -1)
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
