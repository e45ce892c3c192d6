"""Mesh topology helpers: vertex one-rings and area-weighted vertex normals."""

from __future__ import annotations

from typing import Optional

import torch

__all__ = ["face_corners", "face_normals", "vertex_faces", "vertex_normals", "is_closed_outward"]


def face_corners(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(B, F, 3, 3): the corners of every face, from (B, V, 3) vertices and (F, 3) faces.

    One ``index_select`` on the flattened faces; on CPU it is about 4x faster than
    ``vertices[:, faces]`` (advanced indexing), with the same result. ``faces`` must hold
    integer (int64) indices in [0, V); they are moved to the vertices' device.
    """
    return vertices.index_select(1, faces.reshape(-1).to(vertices.device)).view(vertices.shape[0], faces.shape[0], 3, 3)


def face_normals(corners: torch.Tensor) -> torch.Tensor:
    """(..., F, 3): unnormalised face normals (twice the area, counter-clockwise side)
    from (..., F, 3, 3) face corners (:func:`face_corners`)."""
    return torch.linalg.cross(corners[..., 1, :] - corners[..., 0, :], corners[..., 2, :] - corners[..., 0, :], dim=-1)


def vertex_faces(faces: torch.Tensor, num_vertices: int) -> torch.Tensor:
    """The faces around every vertex: (V, R) int64, padded with F (one past the last face).

    faces: (F, 3) int64 vertex indices; R is the largest vertex degree.
    """
    F = faces.shape[0]
    vid = faces.reshape(-1)
    fid = torch.arange(F, device=faces.device).repeat_interleave(3)
    order = torch.argsort(vid, stable=True)
    vid, fid = vid[order], fid[order]
    degree = torch.bincount(vid, minlength=num_vertices)
    start = torch.cumsum(degree, 0) - degree
    slot = torch.arange(len(vid), device=faces.device) - start[vid]
    ring = torch.full((num_vertices, int(degree.max()) if F else 0), F, dtype=torch.int64, device=faces.device)
    ring[vid, slot] = fid
    return ring


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor, ids: Optional[torch.Tensor] = None,
                   ring: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Area-weighted unit vertex normals (the sum of the adjacent faces' cross products).

    Args:
        vertices: (B, V, 3); faces: (F, 3) int64.
        ids: optional (N,) or (B, N) int64 indices of the vertices to compute the normals
            of (all by default).
        ring: :func:`vertex_faces` of ``faces``; needed with ``ids``.
    Returns:
        (B, V, 3), or (B, N, 3) with ``ids``.
    """
    if ids is not None and ring is None:
        raise ValueError("vertex_normals with ids needs ring=vertex_faces(faces, V)")
    B, F = vertices.shape[0], faces.shape[0]
    if ids is not None and ids.shape[-1] * ring.shape[1] < F:
        # few vertices: the normals of their own faces only (the same products, summed in
        # the same order), not of every face
        r = ring.index_select(0, ids.reshape(-1))  # (n, R), padded with F
        corners_of = torch.cat([faces, faces[:1]]).index_select(0, r.reshape(-1))  # (n R, 3)
        if ids.dim() == 1:  # index_select: see face_corners
            tri = vertices.index_select(1, corners_of.reshape(-1)).view(B, *r.shape, 3, 3)
        else:
            flat = corners_of.view(B, -1)
            tri = vertices.gather(1, flat[..., None].expand(-1, -1, 3)).view(B, *ids.shape[1:], r.shape[1], 3, 3)
        fn = face_normals(tri) * (r < F).view(*ids.shape, r.shape[1], 1).to(vertices.dtype)  # the pad face: zero
        n = fn.sum(-2)
        return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    fn = face_normals(face_corners(vertices, faces))  # twice the area
    if ids is None:
        n = torch.zeros_like(vertices)
        for i in range(3):
            n.index_add_(1, faces[:, i], fn)
    else:
        fn = torch.cat([fn, fn.new_zeros(fn.shape[0], 1, 3)], 1)  # the ring's pad face: zero
        if ids.dim() == 1:  # index_select: see face_corners
            r = ring.index_select(0, ids)  # (N, R)
            n = fn.index_select(1, r.reshape(-1)).view(fn.shape[0], *r.shape, 3).sum(-2)
        else:  # one index_select on the flattened problems (as above; faster than fn[b, r])
            r = ring.index_select(0, ids.reshape(-1)).view(*ids.shape, ring.shape[1])  # (B, N, R)
            r = r + (torch.arange(B, device=fn.device) * fn.shape[1]).view(B, 1, 1)
            n = fn.reshape(-1, 3).index_select(0, r.reshape(-1)).view(*r.shape, 3).sum(-2)
    return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def is_closed_outward(vertices: torch.Tensor, faces: torch.Tensor) -> bool:
    """True when the mesh is closed with consistent winding and outward normals: every
    directed edge occurs once and its reverse once, and the signed volume is positive.

    vertices: (V, 3); faces: (F, 3) int64.
    """
    if faces.shape[0] == 0:
        return False
    e = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).cpu()
    V = int(vertices.shape[0])
    key, rev = e[:, 0] * V + e[:, 1], e[:, 1] * V + e[:, 0]
    unique, counts = torch.unique(key, return_counts=True)
    if bool((counts != 1).any()) or not bool(torch.isin(rev, unique).all()):
        return False
    v = vertices.detach().double().cpu()[faces.cpu()]
    return float(torch.linalg.cross(v[:, 0], v[:, 1], dim=-1).mul(v[:, 2]).sum()) > 0
