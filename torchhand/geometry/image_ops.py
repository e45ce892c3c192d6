"""Small image operations on (B, H, W) maps shared by the renderer and the depth
back-projection: plain torch, any device; and the clamping of pixel boxes."""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["max_filter_3x3", "clamp_box"]


def max_filter_3x3(x: torch.Tensor) -> torch.Tensor:
    """Flat 3x3 grey-scale dilation of a (B, H, W) float map; the outside counts as -inf.

    Equal to ``F.max_pool2d(x[:, None], 3, 1, 1)[:, 0]``, as a row and a column pass of
    elementwise maxima: on CPU about 15x faster than max_pool2d at 250x350, on any device.
    """
    p = F.pad(x[:, None], (1, 1, 1, 1), value=float("-inf"))[:, 0]
    rows = torch.maximum(torch.maximum(p[:, :, :-2], p[:, :, 1:-1]), p[:, :, 2:])
    return torch.maximum(torch.maximum(rows[:, :-2], rows[:, 1:-1]), rows[:, 2:])


def clamp_box(box: tuple, height: int, width: int) -> tuple:
    """(r0, r1, c0, c1) host ints within an image of ``height`` x ``width`` (empty boxes
    keep r1 >= r0 and c1 >= c0)."""
    r0, r1, c0, c1 = (int(x) for x in box)
    r0, c0 = min(max(r0, 0), height), min(max(c0, 0), width)
    return r0, max(min(r1, height), r0), c0, max(min(c1, width), c0)
