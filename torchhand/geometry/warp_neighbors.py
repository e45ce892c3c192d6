"""The neighbour queries' Warp side: a grouped hash grid and the launches of their kernels.

- :func:`nearest_in_grid`: the nearest point of the same group within a radius, through a
  grouped hash grid (:class:`Grid`).
- :func:`nearest_marked_pixel`: the nearest pixel of an image carrying a given mark, by an
  exact ring search bounded by a per-query radius.

The kernels are compiled once, with the geometry core's others, in
:mod:`torchhand.geometry.warp_kernels`; tensors are exchanged with torch zero-copy
(``wp.from_torch``) on the tensors' own device. Used by :mod:`torchhand.geometry.neighbors`.
"""

from __future__ import annotations

from typing import Optional

import torch

from torchhand.geometry.warp_kernels import _kernels, on_torch_stream, require_warp, wp_device

__all__ = ["Grid", "build_grid", "nearest_in_grid", "nearest_marked_pixel"]


class Grid:
    """A grouped Warp hash grid over (N, 3) float32 points."""

    def __init__(self, points: torch.Tensor, groups: torch.Tensor, radius: float, dims: int = 64):
        wp = require_warp()
        self.cell = float(radius)  # the cells' size, the first radius of a query
        self.device = points.device
        self.points = points.detach().to(torch.float32).contiguous()
        self.groups = groups.to(torch.int32).contiguous()
        self.radius = float(radius)
        self.grid = wp.HashGrid(dims, dims, dims, device=wp_device(self.device))
        self._wp_points = wp.from_torch(self.points, dtype=wp.vec3)
        if len(self.points):
            with on_torch_stream(self.device):
                self.grid.build(self._wp_points, self.radius, groups=wp.from_torch(self.groups))


def build_grid(points: torch.Tensor, groups: torch.Tensor, radius: float) -> Grid:
    """A grouped hash grid with cells of ``radius`` (build once, query many times)."""
    return Grid(points, groups, radius)


def nearest_in_grid(grid: Grid, queries: torch.Tensor, groups: torch.Tensor, radius: float,
                    any_point: bool = False) -> torch.Tensor:
    """(B, n) int64 index of the nearest grid point of the query's group within
    ``radius`` (<= radius, ties to the smaller index), -1 where none or ``groups < 0``;
    with ``any_point``, of the first point found within ``radius``.

    queries: (B, n, 3); groups: (B, n) int.
    """
    wp = require_warp()
    kernel = _kernels()[1]
    B, n = groups.shape
    out = torch.empty(B, n, dtype=torch.int32, device=queries.device)
    if B * n == 0 or len(grid.points) == 0:
        return out.fill_(-1).long()
    if radius > grid.radius + 1e-6:
        raise ValueError(f"radius {radius} exceeds the grid's cell size {grid.radius}")
    with on_torch_stream(queries.device):
        wp.launch(kernel, dim=(B, n),
                  inputs=[grid.grid.id, grid._wp_points,
                          wp.from_torch(queries.detach().to(torch.float32).contiguous(), dtype=wp.vec3),
                          wp.from_torch(groups.to(torch.int32).contiguous()), float(radius),
                          _first_radius(grid.cell, float(radius)), int(bool(any_point))],
                  outputs=[wp.from_torch(out)], device=wp_device(queries.device))
    return out.long()


def _first_radius(cell: float, radius: float) -> float:
    """The first radius of a query up to ``radius`` on a grid of ``cell`` mm: ``radius``
    halved while it stays at least a cell, so that the radii double up to ``radius``."""
    first = radius
    while first / 2 >= cell * (1 - 1e-6):
        first /= 2
    return first


def nearest_marked_pixel(marks: torch.Tensor, boxes: torch.Tensor, queries: torch.Tensor, groups: torch.Tensor,
                         radius: torch.Tensor, images: Optional[torch.Tensor] = None) -> torch.Tensor:
    """(B, n, 2) int64 (row, col) of the nearest pixel with ``marks == group`` within the
    query's radius (Euclidean, ties to the smaller pixel hash), -1 where none.

    marks: (I, H, W) int group of each pixel (-1 none); boxes: (I x G, 4) int (r_min,
    r_max, c_min, c_max) of each group's pixels (r_min > r_max when empty); queries:
    (B, n, 2) int (row, col); groups: (B, n) int in [0, G) or -1; radius: (B, n) int px;
    images: (B,) int, the marks image of each query row (None: row b searches image b,
    I = B).
    """
    wp = require_warp()
    kernel = _kernels()[2]
    B, n = groups.shape
    out = torch.empty(B, n, 2, dtype=torch.int32, device=marks.device)
    if B * n == 0:
        return out.long()
    images = torch.arange(B, device=marks.device) if images is None else images
    with on_torch_stream(marks.device):
        wp.launch(kernel, dim=(B, n),
                  inputs=[wp.from_torch(marks.to(torch.int32).contiguous()), wp.from_torch(boxes.to(torch.int32).contiguous()),
                          wp.from_torch(images.to(torch.int32).contiguous()),
                          wp.from_torch(queries.to(torch.int32).contiguous()), wp.from_torch(groups.to(torch.int32).contiguous()),
                          wp.from_torch(radius.to(torch.int32).contiguous())],
                  outputs=[wp.from_torch(out)], device=wp_device(marks.device))
    return out.long()
