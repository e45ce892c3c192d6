"""Hough voting and peak picking of the salient point detector.

Every cell of :class:`~torchhand.salient.detector.SalientNet`'s score map votes for the
position of a fingertip (or nail) centre; :func:`hough_votes` accumulates the votes
into a Hough map (part of the network's ``forward`` and of its ONNX graph), and
:func:`detect_peaks` turns Hough maps into :class:`Detections` (post-processing outside
``forward``): max-pool non-maximum suppression, threshold, top-k, sub-cell refinement
and the confidence of each peak (thesis Ch. 4.2; Ballan et al. 2012, Sec. 4).

Pixel coordinates follow :mod:`torchhand.geometry.camera`: pixel centres at integer
coordinates, ``u`` = column (x), ``v`` = row (y).
"""

from __future__ import annotations

from typing import List, NamedTuple, Optional

import torch
import torch.nn.functional as F

__all__ = ["Detections", "hough_votes", "detect_peaks", "STRIDE", "HOUGH_STRIDE", "DEFAULT_THRESHOLD",
           "DEFAULT_MAX_DETECTIONS", "DEFAULT_NMS_RADIUS"]

#: Peak picking defaults: a low threshold and many candidates, so that a precision-recall
#: curve (and a consumer such as the tracker, which applies its own confidence
#: threshold) sees every plausible fingertip; NMS over 3x3 Hough cells (6 px). The
#: threshold 0.02 gave the highest AP on the training run's validation frames (0.05: -0.004).
DEFAULT_THRESHOLD = 0.02
DEFAULT_MAX_DETECTIONS = 40
DEFAULT_NMS_RADIUS = 1

#: Encoder stride: the score/offset maps are (H/4, W/4); inputs must be multiples of it.
STRIDE = 4
#: Stride of the Hough map, (H/2, W/2).
HOUGH_STRIDE = 2


class Detections(NamedTuple):
    """Salient point detections of one frame, sorted by decreasing score.

    Attributes:
        uv: (N, 2) float pixel coordinates in the input image (u = column, v = row).
        score: (N,) confidence, higher is surer: the Hough-map value at the peak (about
            the number of cells voting for it times their mean score) times the squared
            score probability of the cell under it, as the detectors report it; the Hough
            value alone from :func:`detect_peaks` without ``logits``.
        depth: (N,) input depth (mm) at the rounded pixel; 0 where invalid, and 0 for
            colour frames.
    """

    uv: torch.Tensor
    score: torch.Tensor
    depth: torch.Tensor


def hough_votes(scores: torch.Tensor, offsets: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Accumulate weighted votes into a Hough map by bilinear splatting (scatter-add).

    Cell (i, j) of the score map votes at pixel ``(4 j + 1.5 + du, 4 i + 1.5 + dv)``
    with weight ``scores[b, 0, i, j]``; the vote is spread bilinearly over the four
    nearest Hough cells (Hough cell (r, c) is centred on pixel ``(2 c + 0.5, 2 r + 0.5)``).
    Votes that land outside the map are dropped. Differentiable in both inputs.

    Args:
        scores: (B, 1, h, w) non-negative vote weights.
        offsets: (B, 2, h, w) vote offsets (du, dv) in pixels.
        height, width: size (Hh, Wh) of the Hough map.

    Returns:
        (B, 1, Hh, Wh) accumulated votes.
    """
    B, _, h, w = scores.shape
    jj = torch.arange(w, device=scores.device).to(scores.dtype)
    ii = torch.arange(h, device=scores.device).to(scores.dtype)
    # Vote position in Hough cells, (pixel - 0.5) / 2, clamped to [-1, size]: a vote off
    # the map then lands (with its full weight) on a one-cell border that is cropped
    # away, which drops it exactly as the map's edge requires without a mask per corner.
    hx = ((jj[None, None, :] * STRIDE + 1.0 + offsets[:, 0]) / HOUGH_STRIDE).clamp(-1, width)  # (B, h, w)
    hy = ((ii[None, :, None] * STRIDE + 1.0 + offsets[:, 1]) / HOUGH_STRIDE).clamp(-1, height)
    x0 = torch.floor(hx)
    y0 = torch.floor(hy)
    fx = hx - x0
    fy = hy - y0
    # bordered map: rows and columns -1 .. size + 1 (the "+ 1" takes the zero-weight
    # corner of a vote clamped to the far edge)
    Wb = width + 3
    corner = ((y0 + 1) * Wb + (x0 + 1)).long().reshape(B, -1)
    idx = torch.cat([corner, corner + 1, corner + Wb, corner + (Wb + 1)], 1)
    weight = scores[:, 0]
    wy = weight * (1 - fy)
    wy1 = weight * fy
    val = torch.cat([(wy * (1 - fx)).reshape(B, -1), (wy * fx).reshape(B, -1),
                     (wy1 * (1 - fx)).reshape(B, -1), (wy1 * fx).reshape(B, -1)], 1)
    hough = scores.new_zeros(B, (height + 3) * Wb).scatter_add(1, idx, val)
    return hough.reshape(B, 1, height + 3, Wb)[:, :, 1:height + 1, 1:width + 1]


def detect_peaks(
    hough: torch.Tensor,
    threshold: float = DEFAULT_THRESHOLD,
    max_detections: int = DEFAULT_MAX_DETECTIONS,
    nms_radius: int = DEFAULT_NMS_RADIUS,
    image_size: Optional[tuple] = None,
    logits: Optional[torch.Tensor] = None,
) -> List[Detections]:
    """Fingertip detections from Hough maps: local maxima above a threshold, top-k.

    A Hough cell is a peak if it equals the maximum of its ``(2 r + 1)^2`` neighbourhood
    (max-pool NMS, r = ``nms_radius`` cells = 2 r px) and exceeds ``threshold``; of a
    plateau of equal maxima only the first (row-major) cell is kept. Its
    position is refined to the vote-weighted centroid of its 3x3 neighbourhood and
    mapped to input pixels, ``u = 2 c + 0.5``. ``depth`` of the detections is 0 (use
    :class:`SalientDetector` to get it filled in).

    The score of a detection is its Hough value (about the number of cells voting for
    it) or, with ``logits``, the Hough value times ``sigmoid(logit)^2`` of the score cell
    nearest to the detection: a peak that many cells vote for but whose own cell the
    network does not call a fingertip (the ball, folded knuckles, noise blobs) is ranked
    lower. Chosen on the training run's validation frames (AP 0.904 -> 0.928; powers 1,
    3 and 4 gave 0.924, 0.929 and 0.930, the 3x3 to 7x7 cell maxima less); see
    docs/salient.md.

    Args:
        hough: (B, 1, Hh, Wh) Hough maps (:attr:`SalientOutput.hough`).
        threshold: smallest peak (Hough) value kept.
        max_detections: at most this many per image (the highest Hough values).
        nms_radius: NMS neighbourhood radius in Hough cells.
        image_size: optional (H, W) of the unpadded input; peaks outside are dropped.
        logits: optional (B, 1, Hh / 2, Wh / 2) score logits (:attr:`SalientOutput.logits`)
            of the same forward pass; they rescore the detections as above.

    Returns:
        one :class:`Detections` per batch element, sorted by decreasing score.
    """
    _check_peak_inputs(hough, logits)
    B, _, Hh, Wh = hough.shape
    k = 2 * nms_radius + 1
    # separable max-pool (rows, then columns): the (2 r + 1)^2 neighbourhood maximum
    local_max = F.max_pool2d(F.max_pool2d(hough, (1, k), 1, (0, nms_radius)), (k, 1), 1, (nms_radius, 0))
    peak = (hough == local_max) & (hough > threshold)
    ramp = hough.new_tensor([-1.0, 0.0, 1.0])
    padded = F.pad(hough, (1, 1, 1, 1))
    three = torch.arange(3, device=hough.device)
    flat = torch.where(peak, hough, hough.new_zeros(())).flatten(1)
    # candidates: a few more than needed, as plateaus of equal maxima give several
    n = min(4 * max_detections, flat.shape[1])
    score, idx = flat.topk(n, dim=1)
    out = []
    for b in range(B):
        keep = score[b] > 0
        s, i = _first_of_plateaus(score[b][keep], idx[b][keep], Wh, nms_radius)
        s, order = torch.sort(s, descending=True, stable=True)
        s, i = s[:max_detections], i[order][:max_detections]
        r = torch.div(i, Wh, rounding_mode="floor")
        c = i - r * Wh
        uv = _centroids(padded[b, 0], r, c, ramp, three)
        if image_size is not None:
            inside = (uv[:, 0] <= image_size[1] - 0.5) & (uv[:, 1] <= image_size[0] - 0.5)
            uv, s = uv[inside], s[inside]
        if logits is not None:
            uv, s = _rescored(uv, s, logits[b, 0])
        out.append(Detections(uv, s, s.new_zeros(s.shape)))
    return out


def _check_peak_inputs(hough, logits) -> None:
    """The checks of :func:`detect_peaks`: a (B, 1, Hh, Wh) Hough map and, if given,
    floating-point (B, 1, Hh / 2, Wh / 2) logits on its device."""
    if not isinstance(hough, torch.Tensor) or hough.ndim != 4 or hough.shape[1] != 1:
        shape = tuple(hough.shape) if isinstance(hough, torch.Tensor) else type(hough).__name__
        raise ValueError(f"hough must be a tensor of shape (B, 1, Hh, Wh), got {shape}")
    B, _, Hh, Wh = hough.shape
    ratio = STRIDE // HOUGH_STRIDE
    if logits is not None and (not isinstance(logits, torch.Tensor) or logits.ndim != 4
                               or tuple(logits.shape) != (B, 1, Hh // ratio, Wh // ratio)):
        shape = tuple(logits.shape) if isinstance(logits, torch.Tensor) else type(logits).__name__
        raise ValueError(f"logits must be a tensor of shape {(B, 1, Hh // ratio, Wh // ratio)} for a Hough map of "
                         f"shape {tuple(hough.shape)}, got {shape}")
    if logits is not None and (logits.device != hough.device or not logits.is_floating_point()):
        raise ValueError(f"logits must be a floating-point tensor on the Hough map's device ({hough.device}), "
                         f"got {logits.dtype} on {logits.device}")


def _first_of_plateaus(s: torch.Tensor, i: torch.Tensor, Wh: int, nms_radius: int):
    """Of a plateau (equal peaks within ``nms_radius`` cells) keep the first in
    row-major order. ``s``, ``i``: (n,) peak values and flat cell indices of a map
    ``Wh`` cells wide; returns the kept ones, in row-major order."""
    i, order = torch.sort(i)
    s = s[order]
    rr, cc = torch.div(i, Wh, rounding_mode="floor"), i % Wh
    near = ((rr[:, None] - rr[None]).abs() <= nms_radius) & ((cc[:, None] - cc[None]).abs() <= nms_radius)
    earlier = torch.ones_like(near).tril(-1)
    dup = (near & earlier & (s[:, None] == s[None])).any(1)
    return s[~dup], i[~dup]


def _centroids(padded: torch.Tensor, r: torch.Tensor, c: torch.Tensor, ramp: torch.Tensor,
               three: torch.Tensor) -> torch.Tensor:
    """(n, 2) sub-cell pixel positions (u, v) of the peaks at Hough cells (``r``, ``c``):
    the vote-weighted centroid of each peak's 3x3 neighbourhood in ``padded``, the
    (Hh + 2, Wh + 2) Hough map with a zero border; ``ramp`` is (-1, 0, 1) and ``three``
    (0, 1, 2)."""
    patch = padded[(r[:, None, None] + three[None, :, None]), (c[:, None, None] + three[None, None, :])]
    total = patch.sum((1, 2)).clamp_min(torch.finfo(padded.dtype).tiny)
    u = (c.to(padded.dtype) + (patch * ramp).sum((1, 2)) / total) * HOUGH_STRIDE + 0.5
    v = (r.to(padded.dtype) + (patch * ramp[:, None]).sum((1, 2)) / total) * HOUGH_STRIDE + 0.5
    return torch.stack([u, v], 1)


def _rescored(uv: torch.Tensor, s: torch.Tensor, logits: torch.Tensor):
    """Detections (``uv`` (n, 2), ``s`` (n,)) with each score times ``sigmoid(logit)^2``
    of the score cell nearest to it (centres ``4 j + 1.5``) in ``logits`` (Hs, Ws),
    sorted again by decreasing score."""
    Hs, Ws = logits.shape
    j = ((uv[:, 0] - 1.5) / STRIDE).round().long().clamp(0, Ws - 1)
    i = ((uv[:, 1] - 1.5) / STRIDE).round().long().clamp(0, Hs - 1)
    s = s * torch.sigmoid(logits[i, j].to(s.dtype)).square()
    s, order = torch.sort(s, descending=True, stable=True)
    return uv[order], s
