"""Neighbour queries of the correspondence search, batched over problems.

- :class:`PointIndex`: points of several problems, each carrying a group (e.g. the model
  a data pixel was labelled with); the nearest point of the same problem and group
  within a radius, for many queries at once (model-to-data, thesis Eq. 4.6-4.7).
- :func:`nearest_marked_pixel`: for pixels of B images, the nearest pixel carrying a
  given mark within a radius (data-to-model, Eq. 4.8: the model silhouette pixel nearest
  to a data edge pixel).

Backends:

- ``"warp"``: a grouped Warp hash grid; an exact ring search in a Warp kernel; CPU and
  CUDA, no host synchronisation.
- ``"cpu"``: scipy's KD-tree and exact Euclidean distance transform (with the nearest
  pixel's index), per problem and group on the CPU: the fallback without Warp, as fast
  as the CPU makes it.
- ``"torch"``: brute force, the slow, obviously correct reference the others are tested
  against.

All return the exact nearest neighbour. Ties go to the smaller index (points) or, for
``"warp"`` and ``"torch"``, to the smaller :func:`pixel_hash` (pixels); scipy breaks
pixel ties its own way.

Why an exact search and not a distance transform for the pixels: the term needs the
nearest pixel's *position* (it reads the face seen there), which kornia's
``distance_transform`` (an approximation by repeated convolution that returns distances
only) does not give; and the ~600 data edge pixels per model are few enough to search
exactly around, bounded by the radius within which a pair can pass the 30 mm test.
"""

from __future__ import annotations

from typing import Optional

import torch

from torchhand.core.check import check_tensor

__all__ = ["PointIndex", "nearest_marked_pixel", "marked_boxes", "NEIGHBOR_BACKENDS",
           "default_neighbor_backend"]

NEIGHBOR_BACKENDS = ("warp", "cpu", "torch")


def default_neighbor_backend() -> str:
    """``"warp"`` when NVIDIA Warp is installed, else ``"cpu"``."""
    from torchhand.geometry.raycast import default_backend

    return "warp" if default_backend().startswith("warp") else "cpu"


def _check_backend(backend: Optional[str]) -> str:
    backend = default_neighbor_backend() if backend is None else backend
    if backend not in NEIGHBOR_BACKENDS:
        raise ValueError(f"neighbour backend must be one of {NEIGHBOR_BACKENDS}, got {backend!r}")
    if backend == "warp":
        from torchhand.geometry import warp_kernels

        warp_kernels.require_warp()
    return backend


class PointIndex:
    """Points of ``num_problems`` problems in ``num_groups`` groups, for radius queries.

    Args:
        points: (N, 3) float points.
        problem: (N,) int64 the problem of each point, in [0, num_problems).
        group: (N,) int64 its group in [0, num_groups).
        radius: the largest query radius (the hash grid's cell size).
        backend: ``"warp"`` or ``"torch"`` (None: Warp when installed).
        cell: mm, the Warp grid's cells and the first radius of a query (default: a
            quarter of ``radius``); any value gives the same, exact nearest points.

    Build it once for a set of points (a frame's labelled data) and query it many times.
    """

    def __init__(self, points: torch.Tensor, problem: torch.Tensor, group: torch.Tensor, num_problems: int,
                 num_groups: int, radius: float, backend: Optional[str] = None, cell: Optional[float] = None):
        check_tensor(points, "points", (None, 3), floating=True)
        check_tensor(problem, "problem", (points.shape[0],), integer=True)
        check_tensor(group, "group", (points.shape[0],), integer=True)
        if not radius > 0:
            raise ValueError(f"radius must be > 0, got {radius!r}")
        self.backend = _check_backend(backend)
        self.points, self.radius = points.detach(), float(radius)
        self.num_problems, self.num_groups = int(num_problems), int(num_groups)
        self.key = problem.long() * self.num_groups + group.long()  # (N,) the grid group of each point
        if self.backend == "warp":
            from torchhand.geometry import warp_neighbors

            # cells of a quarter of the radius (or ``cell``): the queries start at a radius of
            # about a cell and double it (exact at every size; small cells suit queries that
            # mostly lie near their nearest point)
            self._grid = warp_neighbors.build_grid(self.points, self.key, self.radius / 4 if cell is None else cell)
            self._grid.radius = self.radius
        elif self.backend == "cpu":
            from scipy.spatial import cKDTree

            keys = self.key.cpu()
            order = torch.argsort(keys, stable=True)
            uniq, counts = torch.unique_consecutive(keys[order], return_counts=True)
            pts = self.points.detach().cpu().double().numpy()
            self._trees = {}
            for k, idx in zip(uniq.tolist(), torch.split(order, counts.tolist())):
                # an unbalanced tree builds in about two thirds of the time and queries as fast
                self._trees[k] = (cKDTree(pts[idx.numpy()], balanced_tree=False), idx)

    def nearest(self, queries: torch.Tensor, problems: torch.Tensor, groups: torch.Tensor,
                radius: Optional[float] = None, any_point: bool = False) -> torch.Tensor:
        """The nearest point of the same problem and group within ``radius`` (inclusive).

        Args:
            queries: (B, n, 3) query points.
            problems: (B,) int64 the problem of each row of queries.
            groups: (B, n) int64 the group of each query; -1 skips it.
            radius: at most the index's radius (default: it).
            any_point: any point within ``radius`` will do (whether there is one, not
                which: the Warp search stops at the first it finds; the others give the
                nearest).
        Returns:
            (B, n) int64 index into ``points``, -1 where none.
        """
        radius = self.radius if radius is None else float(radius)
        if radius > self.radius:
            raise ValueError(f"radius {radius} exceeds the index's radius {self.radius}")
        key = torch.where(groups >= 0, problems[:, None].long() * self.num_groups + groups.long(),
                          torch.full_like(groups, -1, dtype=torch.int64))
        if self.backend == "warp":
            from torchhand.geometry import warp_neighbors

            return warp_neighbors.nearest_in_grid(self._grid, queries, key, radius, any_point)
        if self.backend == "cpu":
            return self._nearest_kdtree(queries, key, radius)
        return _nearest_brute_force(self.points, self.key, queries, key, radius)

    def _nearest_kdtree(self, queries, key, radius) -> torch.Tensor:
        import numpy as np

        flat_k = key.reshape(-1).cpu()
        flat_q = queries.detach().reshape(-1, 3).cpu().double().numpy()
        out = torch.full((flat_k.shape[0],), -1, dtype=torch.int64)
        bound = float(np.nextafter(radius, np.inf))  # scipy's bound is exclusive; ours inclusive
        for k in torch.unique(flat_k[flat_k >= 0]).tolist():
            if k not in self._trees:
                continue
            tree, idx = self._trees[k]
            qi = torch.nonzero(flat_k == k)[:, 0]
            d, j = tree.query(flat_q[qi.numpy()], k=1, distance_upper_bound=bound)
            ok = torch.as_tensor(np.isfinite(d))
            j = torch.as_tensor(np.where(np.isfinite(d), j, 0))
            out[qi] = torch.where(ok, idx[j], torch.full_like(j, -1))
        return out.view(key.shape).to(queries.device)


def _nearest_brute_force(points, point_key, queries, key, radius, chunk: int = 4096) -> torch.Tensor:
    """Reference: exact nearest by distances to every point of the same key."""
    B, n = key.shape
    out = torch.full((B, n), -1, dtype=torch.int64, device=queries.device)
    flat_q, flat_k = queries.reshape(-1, 3), key.reshape(-1)
    flat_out = out.view(-1)
    for k in torch.unique(flat_k[flat_k >= 0]).tolist():
        qi = torch.nonzero(flat_k == k)[:, 0]
        pi = torch.nonzero(point_key == k)[:, 0]
        if len(pi) == 0:
            continue
        P = points[pi].double()
        for s in range(0, len(qi), chunk):
            q = qi[s : s + chunk]
            d2 = ((flat_q[q].double()[:, None] - P[None]) ** 2).sum(-1)
            best = d2.argmin(1)  # the first of equal minima: the smaller index
            ok = d2.gather(1, best[:, None])[:, 0] <= radius * radius
            flat_out[q] = torch.where(ok, pi[best], torch.full_like(best, -1))
    return out


def nearest_marked_pixel(marks: torch.Tensor, queries: torch.Tensor, groups: torch.Tensor, radius: torch.Tensor,
                         num_groups: int, backend: Optional[str] = None,
                         images: Optional[torch.Tensor] = None, boxes: Optional[torch.Tensor] = None) -> torch.Tensor:
    """For each query pixel, the nearest pixel of its image marked with its group.

    Args:
        marks: (B, H, W) int64 group of each pixel in [0, num_groups), -1 unmarked; with
            ``images``, (I, H, W) images that the B query rows share.
        queries: (B, n, 2) int64 (row, col) query pixels.
        groups: (B, n) int64 the group each query looks for, -1 skips it.
        radius: (B, n) int64 px, the largest Euclidean distance searched (inclusive).
        num_groups: G.
        backend: ``"warp"`` or ``"torch"`` (None: Warp when installed).
        images: (B,) int64 the image of ``marks`` each query row searches (None: row b
            searches image b); many rows on few images need no copies of them.
        boxes: :func:`marked_boxes` of ``marks`` and ``num_groups``, which the Warp
            search starts from (None: computed here). Pass them when the same marks are
            searched many times: they cost a pass over every pixel and group.
    Returns:
        (B, n, 2) int64 (row, col) of the nearest marked pixel, -1 where none within the
        radius; ties go to the smaller :func:`pixel_hash`.
    """
    backend = _check_backend(backend)
    I, H, W = marks.shape
    if max(H, W) >= 32768:
        raise ValueError(f"marks must be smaller than 32768 px per side, got {H}x{W}")
    B = queries.shape[0]
    if images is not None and images.shape != (B,):
        raise ValueError(f"images must hold one marks image per query row, shape ({B},), got {tuple(images.shape)}")
    if images is None and I != B:
        raise ValueError(f"marks must hold one image per query row ({B}), got {I}")
    if backend == "warp":
        from torchhand.geometry import warp_neighbors

        G = max(int(num_groups), 1)
        if boxes is None:
            boxes = marked_boxes(marks, num_groups)
        elif boxes.shape != (I * G, 4):
            raise ValueError(f"boxes must be marked_boxes(marks, {num_groups}), shape ({I * G}, 4), "
                             f"got {tuple(boxes.shape)}")
        return warp_neighbors.nearest_marked_pixel(marks, boxes, queries, groups, radius, images)
    if images is not None:
        marks = marks[images]
    if backend == "cpu":
        return _nearest_pixel_edt(marks, queries, groups, radius)
    out = torch.full((B, queries.shape[1], 2), -1, dtype=torch.int64, device=marks.device)
    for b in range(B):
        for g in torch.unique(groups[b][groups[b] >= 0]).tolist():
            qi = torch.nonzero(groups[b] == g)[:, 0]
            pix = torch.nonzero(marks[b] == g)  # (m, 2)
            if len(pix) == 0:
                continue
            d2 = ((queries[b, qi][:, None] - pix[None]) ** 2).sum(-1)
            best = (d2 * 2 ** 31 + pixel_hash(pix[:, 0], pix[:, 1])[None]).argmin(1)  # ties: the smaller hash
            ok = d2.gather(1, best[:, None])[:, 0] <= radius[b, qi] ** 2
            out[b, qi] = torch.where(ok[:, None], pix[best], torch.full_like(pix[best], -1))
    return out


def pixel_hash(row: torch.Tensor, col: torch.Tensor) -> torch.Tensor:
    """A 31-bit hash of pixel coordinates that breaks ties between equidistant pixels.

    Ties are common on a pixel grid (8 pixels lie at distance sqrt(5)); breaking them by
    row and column would pull every tied data-to-model pair the same way (along a rope's
    axis, say), a hash has no preferred direction and is the same on every device."""
    return ((row.long() * 40503) ^ (col.long() * 31337)) & 2147483647  # int32-safe below 32768 px, as in Warp


def _feature_transform(pix, lo, hi) -> tuple:
    """scipy's exact Euclidean distance transform with indices of the marked pixels ``pix``
    (n, 2) on the box [lo, hi): (distance (h, w), nearest (h, w, 2) image (row, col))."""
    import numpy as np
    from scipy.ndimage import distance_transform_edt

    feature = np.ones(hi - lo, bool)
    feature[pix[:, 0] - lo[0], pix[:, 1] - lo[1]] = False  # zeros: the marked pixels
    dist, (ri, ci) = distance_transform_edt(feature, return_indices=True)
    return dist, np.stack([ri + lo[0], ci + lo[1]], -1)


def _nearest_pixel_edt(marks, queries, groups, radius) -> torch.Tensor:
    """The ``"cpu"`` backend: scipy's exact Euclidean distance transform with indices, on
    the box holding a group's pixels and its queries."""
    import numpy as np

    B = marks.shape[0]
    m, q, g, rad = marks.cpu().numpy(), queries.cpu().numpy(), groups.cpu().numpy(), radius.cpu().numpy()
    out = np.full(q.shape, -1, np.int64)
    for b in range(B):
        for k in np.unique(g[b][g[b] >= 0]):
            qi = np.nonzero(g[b] == k)[0]
            pix = np.argwhere(m[b] == k)
            if len(pix) == 0:
                continue
            lo = np.minimum(pix.min(0), q[b, qi].min(0))
            _, nearest = _feature_transform(pix, lo, np.maximum(pix.max(0), q[b, qi].max(0)) + 1)
            near = nearest[q[b, qi, 0] - lo[0], q[b, qi, 1] - lo[1]]
            ok = ((near - q[b, qi]) ** 2).sum(-1) <= rad[b, qi] ** 2
            out[b, qi] = np.where(ok[:, None], near, -1)
    return torch.as_tensor(out, device=marks.device)


def marked_boxes(marks: torch.Tensor, num_groups: int) -> torch.Tensor:
    """(B x G, 4) int32 (r_min, r_max, c_min, c_max) of the pixels of each group of (B, H,
    W) ``marks`` (G = ``num_groups``, at least 1); r_min > r_max for an empty group.
    Fixed shapes, no host sync."""
    B, H, W = marks.shape
    G = max(int(num_groups), 1)
    member = marks[:, None] == torch.arange(G, device=marks.device)[None, :, None, None]  # (B, G, H, W)
    rows = member.any(3)  # (B, G, H)
    cols = member.any(2)  # (B, G, W)
    ar, ac = torch.arange(H, device=marks.device), torch.arange(W, device=marks.device)
    big = max(H, W) + 1
    r_min = torch.where(rows, ar, big).amin(-1)
    r_max = torch.where(rows, ar, -big).amax(-1)
    c_min = torch.where(cols, ac, big).amin(-1)
    c_max = torch.where(cols, ac, -big).amax(-1)
    return torch.stack([r_min, r_max, c_min, c_max], -1).reshape(B * G, 4).to(torch.int32)
