"""Generalised Chamfer matching of silhouette contours (thesis Ch. 3.4, Eq. 3.4-3.8):
which contour pixel of an image each projected rim point of a model is paired with.

The distances of the thesis (``CHAMFER_KINDS``):

- ``CH`` (3.5): the nearest contour pixel, no orientation;
- ``DCH-Thres`` (3.6): the nearest contour pixel, the pair dropped when the two
  orientations differ by ``tau`` or more (the thesis' variant that removes such pairs
  instead of charging a fixed penalty);
- ``DCH-Quant`` (3.7): the nearest contour pixel of the same orientation bin (one
  distance transform per bin);
- ``DCH-Quant2``: soft binning, a pair in each of the two bins nearest to the point's
  orientation;
- ``DCH-DT3`` (3.8, Liu et al. 2010): the contour pixel minimising
  ``|p - q| + lambda |phi(p) - phi(q)|`` with phi quantised into ``bins`` (the 3D
  distance transform, evaluated as the minimum over the bins' 2D transforms).

Orientations are the directions of the silhouette's outward normal in the image,
``phi`` in [0, 2 pi); the circular distance is signed (``signed=True``, range [0, pi]:
the thesis' "360", its better variant) or unsigned (range [0, pi / 2]: "180"). The
contour of an image (:func:`silhouette_contour`) is approximated by line segments
(Ramer-Douglas-Peucker, OpenCV's ``approxPolyDP``), each pixel taking its segment's
normal, as in Liu et al. and the thesis; the model's rim points take the direction of
their rendered normal in the image plane.

The nearest-pixel searches are :func:`torchhand.geometry.neighbors.nearest_marked_pixel`
(Warp, or torch), batched over problems, with the orientation bin as the mark.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple, Optional

import numpy as np
import torch

from torchhand.geometry.neighbors import default_neighbor_backend, marked_boxes, nearest_marked_pixel

__all__ = ["CHAMFER_KINDS", "ChamferConfig", "silhouette_contour", "contour_marks", "boundary_pixels",
           "circular_distance", "orientation_bin", "match_contour", "mark_groups", "contour_boxes", "ContourMatch"]

CHAMFER_KINDS = ("CH", "DCH-Thres", "DCH-Quant", "DCH-Quant2", "DCH-DT3")
TWO_PI = 2 * math.pi


@dataclass(frozen=True)
class ChamferConfig:
    """kind: one of :data:`CHAMFER_KINDS`; tau_deg: DCH-Thres' threshold (thesis
    Fig. 3.2: 22.5); signed: 360 (True) or 180 (False) circular distance; bins: the
    orientation bins of DCH-Quant, -Quant2 and -DT3 (thesis: 16 for DT3); lam: DT3's
    lambda in px per radian (thesis Fig. 3.3: 25); radius_px: the farthest pair."""

    kind: str = "DCH-Thres"
    tau_deg: float = 22.5
    signed: bool = True
    bins: int = 16
    lam: float = 25.0
    radius_px: int = 60

    def __post_init__(self) -> None:
        if self.kind not in CHAMFER_KINDS:
            raise ValueError(f"unknown Chamfer distance {self.kind!r}; known: {', '.join(CHAMFER_KINDS)}")
        if self.bins < 2 or self.radius_px < 1 or not 0 < self.tau_deg <= 180 or self.lam < 0:
            raise ValueError(f"need bins >= 2, radius_px >= 1, 0 < tau_deg <= 180, lam >= 0; got {self}")


class ContourMatch(NamedTuple):
    """Pairs of rim points and contour pixels: ``source`` (B, m) int64 the index of the
    query each pair comes from, ``pixel`` (B, m, 2) (row, col) int64 the contour pixel,
    ``valid`` (B, m) bool (m = n queries, or 2n for DCH-Quant2)."""

    source: torch.Tensor
    pixel: torch.Tensor
    valid: torch.Tensor


def circular_distance(a: torch.Tensor, b: torch.Tensor, signed: bool = True) -> torch.Tensor:
    """|a - b|_phi of angles in radians: in [0, pi] (signed), or in [0, pi / 2] with
    opposite directions equal (unsigned)."""
    period = TWO_PI if signed else math.pi
    d = torch.remainder(a - b, period)
    return torch.minimum(d, period - d)


def orientation_bin(phi: torch.Tensor, bins: int, signed: bool = True) -> torch.Tensor:
    """(...) int64 bin of each angle: ``bins`` equal bins over [0, 2 pi) (signed) or
    [0, pi) (unsigned), bin k centred at k * period / bins."""
    period = TWO_PI if signed else math.pi
    return torch.remainder(torch.round(torch.remainder(phi, period) / period * bins), bins).long()


def silhouette_contour(mask: np.ndarray, epsilon_px: float = 1.0) -> tuple:
    """The contour pixels of a binary silhouette and their orientation: ((n, 2) int64
    (row, col), (n,) float64 phi in [0, 2 pi), the outward normal of the pixel's line
    segment). Outer boundaries and holes both count; ``epsilon_px``: the segments'
    largest deviation from the contour (Ramer-Douglas-Peucker)."""
    import cv2

    m = np.ascontiguousarray(np.asarray(mask) > 0, dtype=np.uint8)
    if m.ndim != 2:
        raise ValueError(f"silhouette_contour needs an (H, W) mask, got shape {m.shape}")
    H, W = m.shape
    contours, _ = cv2.findContours(m, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    pix, phis = [], []
    for c in contours:
        c = c[:, 0, :]  # (k, 2) x, y
        if len(c) < 3:
            pix.append(c[:, ::-1])
            phis.append(np.zeros(len(c)))
            continue
        poly = cv2.approxPolyDP(c[:, None, :], epsilon_px, closed=True)[:, 0, :]
        # the polygon's vertices are contour points: their indices along the contour
        key = {(int(x), int(y)): i for i, (x, y) in reversed(list(enumerate(c)))}
        idx = sorted({key[(int(x), int(y))] for x, y in poly})
        if len(idx) < 2:
            idx = [0, len(c) // 2]
        seg = np.searchsorted(np.asarray(idx), np.arange(len(c)), side="right") - 1  # segment of each pixel
        seg[seg < 0] = len(idx) - 1  # pixels before the first vertex: the closing segment
        a = c[np.asarray(idx)].astype(np.float64)
        b = np.roll(a, -1, axis=0)
        t = b - a
        n = np.stack([t[:, 1], -t[:, 0]], 1)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        # outward: the side of the segment's middle that is not in the silhouette
        mid = (a + b) / 2
        probe = np.round(mid + 2.0 * n).astype(np.int64)
        inside = m[np.clip(probe[:, 1], 0, H - 1), np.clip(probe[:, 0], 0, W - 1)] > 0
        n[inside] *= -1
        phi = np.remainder(np.arctan2(n[:, 1], n[:, 0]), TWO_PI)  # image x right, y down
        pix.append(c[:, ::-1])
        phis.append(phi[seg])
    if not pix:
        return np.zeros((0, 2), np.int64), np.zeros(0)
    return np.concatenate(pix).astype(np.int64), np.concatenate(phis)


def contour_marks(pixels: np.ndarray, phi: np.ndarray, shape: tuple, config: ChamferConfig) -> tuple:
    """(marks (H, W) int64, phi (H, W) float32) of one image's contour for
    :func:`match_contour`: marks hold the orientation bin of each contour pixel (0 for
    every pixel with CH and DCH-Thres), -1 elsewhere; phi their orientation, NaN
    elsewhere."""
    H, W = shape
    marks = np.full((H, W), -1, np.int64)
    image = np.full((H, W), np.nan, np.float32)
    if len(pixels):
        binned = mark_groups(config) > 1
        b = orientation_bin(torch.as_tensor(phi), config.bins, config.signed).numpy() if binned else 0
        marks[pixels[:, 0], pixels[:, 1]] = b
        image[pixels[:, 0], pixels[:, 1]] = phi
    return marks, image


def boundary_pixels(hit: torch.Tensor) -> torch.Tensor:
    """(B, H, W) bool: the pixels of a rendered silhouette (``hit``) with a 4-neighbour
    outside it, or on the image border."""
    p = torch.nn.functional.pad(hit, (1, 1, 1, 1), value=False)
    inside = p[:, :-2, 1:-1] & p[:, 2:, 1:-1] & p[:, 1:-1, :-2] & p[:, 1:-1, 2:]  # all four neighbours in
    return hit & ~inside


def mark_groups(config: ChamferConfig) -> int:
    """The number of mark values of :func:`contour_marks` under ``config``: the
    orientation bins, or 1 (CH and DCH-Thres mark every contour pixel 0)."""
    return config.bins if config.kind in ("DCH-Quant", "DCH-Quant2", "DCH-DT3") else 1


def contour_boxes(config: ChamferConfig, marks: torch.Tensor, backend: Optional[str] = None) -> Optional[torch.Tensor]:
    """What :func:`match_contour` may be given as ``boxes`` for (I, H, W) ``marks``: the
    boxes of each mark's pixels that the Warp search starts from, or None for the other
    backends (which do not use them). Compute them once when the same contour images
    are matched many times (a tracker's outer iterations, a swarm's particles)."""
    backend = default_neighbor_backend() if backend is None else backend
    return marked_boxes(marks, mark_groups(config)) if backend == "warp" else None


def match_contour(config: ChamferConfig, marks: torch.Tensor, phi_image: torch.Tensor, queries: torch.Tensor,
                  query_phi: torch.Tensor, query_ok: torch.Tensor, backend: Optional[str] = None,
                  images: Optional[torch.Tensor] = None, boxes: Optional[torch.Tensor] = None) -> ContourMatch:
    """Pair each rim point with a contour pixel by the distance ``config.kind``.

    Args:
        marks, phi_image: (B, H, W) of :func:`contour_marks`, one image per problem;
            with ``images``, (I, H, W) images the problems share.
        queries: (B, n, 2) int64 (row, col) rim pixels; query_phi: (B, n) their
            orientations; query_ok: (B, n) bool real queries.
        images: (B,) int64 the image of each problem (None: problem b has image b).
        boxes: :func:`contour_boxes` of ``marks`` (None: computed here, once for the
            call's searches).
    """
    B, n = query_ok.shape
    dev = queries.device
    boxes = contour_boxes(config, marks, backend) if boxes is None else boxes
    radius = torch.full((B, n), int(config.radius_px), dtype=torch.int64, device=dev)
    idx = torch.arange(n, device=dev).expand(B, n)
    bidx = torch.arange(B, device=dev)[:, None] if images is None else images.to(dev)[:, None]

    def search(groups, num_groups):
        g = torch.where(query_ok, groups, torch.full_like(groups, -1))
        hit = nearest_marked_pixel(marks, queries, g, radius, num_groups, backend=backend, images=images, boxes=boxes)
        return hit, (hit[..., 0] >= 0) & query_ok

    def dist(hit):
        return (hit - queries).double().norm(dim=-1)

    if config.kind in ("CH", "DCH-Thres"):
        hit, ok = search(torch.zeros(B, n, dtype=torch.int64, device=dev), 1)
        if config.kind == "DCH-Thres":
            phi_q = phi_image[bidx, hit[..., 0].clamp_min(0), hit[..., 1].clamp_min(0)].double()
            ok &= circular_distance(query_phi.double(), phi_q, config.signed) < math.radians(config.tau_deg)
        return ContourMatch(idx, hit, ok)
    period = TWO_PI if config.signed else math.pi
    width = period / config.bins
    if config.kind == "DCH-Quant":
        hit, ok = search(orientation_bin(query_phi, config.bins, config.signed), config.bins)
        return ContourMatch(idx, hit, ok)
    if config.kind == "DCH-Quant2":  # the two bins nearest to phi: its own and the neighbour on its side
        lo = torch.floor(torch.remainder(query_phi, period) / width).long() % config.bins
        hits = [search(k % config.bins, config.bins) for k in (lo, lo + 1)]
        return ContourMatch(torch.cat([idx, idx], 1), torch.cat([h for h, _ in hits], 1),
                            torch.cat([o for _, o in hits], 1))
    # DCH-DT3: min over bins of |p - q_k| + lambda |phi_p - centre_k|
    best_cost = torch.full((B, n), math.inf, dtype=torch.float64, device=dev)
    best = torch.full((B, n, 2), -1, dtype=torch.int64, device=dev)
    for k in range(config.bins):
        penalty = config.lam * circular_distance(query_phi.double(), torch.tensor(k * width, dtype=torch.float64,
                                                                                   device=dev), config.signed)
        hit, ok = search(torch.full((B, n), k, dtype=torch.int64, device=dev), config.bins)
        cost = torch.where(ok, dist(hit) + penalty, torch.full_like(penalty, math.inf))
        better = cost < best_cost
        best_cost = torch.where(better, cost, best_cost)
        best = torch.where(better[..., None], hit, best)
    return ContourMatch(idx, best, torch.isfinite(best_cost) & query_ok)
