"""Depth and id rendering of posed triangle soups by ray casting.

Ray casting uses open3d's Embree-backed :class:`open3d.t.geometry.RaycastingScene` on
the CPU: inputs on other devices are copied to the CPU for the cast and the results
are returned on the input device. Rendering is not differentiable (inputs are detached).

Units are millimetres; the camera frame is x right, y down, z forward; there is one
ray per pixel centre (integer pixel coordinates, OpenCV convention).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np
import open3d as o3d
import torch
import torch.nn.functional as F

from torchhand.core.check import check_tensor, fmt_shape
from torchhand.geometry.camera import Camera, project_points, transform_points
from torchhand.geometry.image_ops import max_filter_3x3
from torchhand.geometry.mesh import face_corners, face_normals

__all__ = ["RenderResult", "render", "silhouette_edges", "visible_vertices", "DEFAULT_EDGE_THRESHOLD_MM"]

#: Depth jump (mm) between neighbouring pixels that counts as a silhouette edge.
DEFAULT_EDGE_THRESHOLD_MM = 10.0

_INVALID_ID = int(o3d.t.geometry.RaycastingScene.INVALID_ID)


class RenderResult(NamedTuple):
    """Per-pixel render outputs, all on the device of the rendered vertices.

    Attributes:
        depth: (B, H, W) float32 camera-frame z in mm; 0 where nothing is hit.
        face_id: (B, H, W) int64 index of the hit triangle; -1 where empty.
        model_id: (B, H, W) int64 ``face_model_id`` of the hit triangle; -1 where empty.
        bone_id: (B, H, W) int64 ``face_bone_id`` of the hit triangle; -1 where empty.
        normals: (B, H, W, 3) float32 camera-frame unit normals of the hit triangle,
            oriented towards the camera; 0 where empty. None when rendered with
            ``normals=False``.
        silhouette_edges: (B, H, W) bool, see :func:`silhouette_edges`.
        barycentric: (B, H, W, 2) float32 ``(u, v)`` of the hit, i.e. the hit point is
            ``(1 - u - v) * v0 + u * v1 + v * v2`` of the face's vertices; 0 where empty.
    """

    depth: torch.Tensor
    face_id: torch.Tensor
    model_id: torch.Tensor
    bone_id: torch.Tensor
    normals: torch.Tensor
    silhouette_edges: torch.Tensor
    barycentric: torch.Tensor


def silhouette_edges(depth: torch.Tensor, threshold: float = DEFAULT_EDGE_THRESHOLD_MM) -> torch.Tensor:
    """Occluding-contour pixels of a depth map.

    A pixel is an edge if it is foreground (depth > 0) and one of its 8 neighbours is
    background or farther away by more than ``threshold``; i.e. only the near
    (occluding) side of a discontinuity is marked. Implemented as a torch morphological
    comparison: a flat 3x3 grey-scale dilation of the depth map with
    background set to +inf. Pixels outside the image do not count as background.

    Args:
        depth: (B, H, W) depth in mm, 0 (or negative) where empty.
        threshold: depth jump in mm that counts as a discontinuity.

    Returns:
        (B, H, W) bool edge mask.
    """
    check_tensor(depth, "depth", (None, None, None), spec="(B, H, W)", floating=True)
    foreground = depth > 0
    far = torch.where(foreground, depth, torch.full_like(depth, float("inf")))
    # the filter pads with -inf, so the image border is not mistaken for background.
    neighbour_max = max_filter_3x3(far)
    return foreground & (neighbour_max - depth > threshold)


@functools.lru_cache(maxsize=8)  # ~7 MB per 640x480 camera
def _camera_rays(key: tuple) -> np.ndarray:
    """World-frame rays (H, W, 6) through pixel centres, cached per camera.

    Directions are scaled to unit camera-frame z so open3d's ``t_hit`` (in units of the
    direction length) equals the z depth directly.
    """
    K_flat, T_flat, width, height = key
    K = np.asarray(K_flat, dtype=np.float64).reshape(3, 3)
    T = np.asarray(T_flat, dtype=np.float64).reshape(4, 4)
    v, u = np.meshgrid(np.arange(height, dtype=np.float64), np.arange(width, dtype=np.float64), indexing="ij")
    yn = (v - K[1, 2]) / K[1, 1]
    xn = (u - K[0, 2] - K[0, 1] * yn) / K[0, 0]
    d_cam = np.stack([xn, yn, np.ones_like(xn)], axis=-1)
    R, t = T[:3, :3], T[:3, 3]
    d_world = d_cam @ R  # row-vector form of R^T d
    origin = np.broadcast_to(-R.T @ t, d_world.shape)
    return np.ascontiguousarray(np.concatenate([origin, d_world], axis=-1).astype(np.float32))


def _rays_for(camera: Camera) -> np.ndarray:
    key = (
        tuple(camera.K.detach().cpu().double().flatten().tolist()),
        tuple(camera.T_cw.detach().cpu().double().flatten().tolist()),
        camera.width,
        camera.height,
    )
    return _camera_rays(key)


def _regions_of_interest(pc: torch.Tensor, camera: Camera) -> list:
    """Per batch element, the pixel box (r0, r1, c0, c1) that can contain hits.

    ``pc``: (B, V, 3) camera-frame vertices. The bounding box of their projections,
    widened by 2 px; the whole image when some vertex lies at or behind the camera
    plane (its projection is unbounded).
    """
    z = pc[..., 2]
    safe = torch.where((z > 1e-3)[..., None], pc, pc.new_tensor([0.0, 0.0, 1.0]))
    uv = project_points(safe, camera.K.to(pc))
    lo = (uv.amin(1).floor() - 2).cpu().numpy()
    hi = (uv.amax(1).ceil() + 3).cpu().numpy()
    behind = (z.amin(1) <= 1e-3).cpu().numpy()
    out = []
    for b in range(pc.shape[0]):
        if behind[b]:
            out.append((0, camera.height, 0, camera.width))
            continue
        c0, r0 = (int(np.clip(x, 0, m)) for x, m in zip(lo[b], (camera.width, camera.height)))
        c1, r1 = (int(np.clip(x, 0, m)) for x, m in zip(hi[b], (camera.width, camera.height)))
        out.append((r0, r1, c0, c1))
    return out


def _check_ids(name: str, ids: torch.Tensor | None, num_faces: int, like: torch.Tensor) -> torch.Tensor:
    if ids is None:
        return like.new_zeros(num_faces, dtype=torch.int64)
    check_tensor(ids, name, (num_faces,), spec=f"(F,) with F={num_faces}")
    if ids.dtype in (torch.bool,) or ids.is_floating_point() or ids.is_complex():
        raise TypeError(f"{name} must have an integer dtype (int64), got {ids.dtype}")
    if ids.device != like.device:
        raise ValueError(f"{name} is on {ids.device} but vertices is on {like.device}; they must match")
    return ids.long()


def render(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    camera: Camera,
    face_model_id: torch.Tensor | None = None,
    face_bone_id: torch.Tensor | None = None,
    *,
    edge_threshold: float = DEFAULT_EDGE_THRESHOLD_MM,
    normals: bool = True,
    cull_back_faces: bool = False,
) -> RenderResult:
    """Ray-cast depth, ids, normals and silhouette edges of a posed triangle soup.

    Args:
        vertices: (B, V, 3) or (V, 3) world-frame vertices in mm (float).
        faces: (F, 3) integer (int64) vertex indices; F may be 0.
        camera: the camera to render from (its size gives H, W).
        face_model_id: (F,) int64 model index per face; zeros if None.
        face_bone_id: (F,) int64 bone index per face; zeros if None.
        edge_threshold: depth jump (mm) for :func:`silhouette_edges`.
        normals: compute the pixel normals (the tracker does not need them).
        cull_back_faces: leave the faces turned away from the camera out of the ray
            caster's BVH (about half of them, so it builds twice as fast). Exact for
            closed meshes with outward normals seen from outside, as every shipped
            model is: a ray enters a closed mesh through a front face first.

    Returns:
        RenderResult with (B, H, W) maps on ``vertices.device``.
    """
    if not isinstance(camera, Camera):
        raise TypeError(f"camera must be a torchhand.geometry.camera.Camera, got {type(camera).__name__}")
    check_tensor(vertices, "vertices", ("...", None, 3), spec="(B, V, 3) or (V, 3)", floating=True)
    if vertices.ndim == 2:
        vertices = vertices[None]
    elif vertices.ndim != 3:
        raise ValueError(f"vertices must have shape (B, V, 3) or (V, 3), got {fmt_shape(vertices.shape)}")
    check_tensor(faces, "faces", (None, 3), spec="(F, 3)")
    if faces.dtype == torch.bool or faces.is_floating_point() or faces.is_complex():
        raise TypeError(f"faces must have an integer dtype (int64), got {faces.dtype}")
    if faces.device != vertices.device:
        raise ValueError(f"faces is on {faces.device} but vertices is on {vertices.device}; they must match")
    vertices = vertices.detach()
    faces = faces.detach().long()
    B, V = vertices.shape[:2]
    num_faces = faces.shape[0]
    if not bool(torch.isfinite(vertices).all()):
        raise ValueError("vertices must be finite, got NaN or inf values")
    if num_faces > 0 and (int(faces.min()) < 0 or int(faces.max()) >= V):
        raise ValueError(f"faces must index vertices in [0, {V}), got range [{int(faces.min())}, {int(faces.max())}]")
    model_ids = _check_ids("face_model_id", face_model_id, num_faces, faces)
    bone_ids = _check_ids("face_bone_id", face_bone_id, num_faces, faces)

    H, W = camera.height, camera.width
    device = vertices.device
    v_cam = transform_points(camera.T_cw.to(vertices), vertices)  # (B, V, 3); the camera is the origin
    per_problem = _regions_of_interest(v_cam, camera) if num_faces > 0 else [(0, 0, 0, 0)] * B
    rois = [r for r in per_problem if r[1] > r[0] and r[3] > r[2]]  # empty: nothing projects into the image
    # Every per-pixel output is computed on the union of the regions of interest (all
    # pixels outside it are empty) and pasted into the full image at the end.
    r0, r1 = min((r[0] for r in rois), default=0), max((r[1] for r in rois), default=0)
    c0, c1 = min((r[2] for r in rois), default=0), max((r[3] for r in rois), default=0)
    h, w = r1 - r0, c1 - c0
    t_hit = np.full((B, h, w), np.inf, dtype=np.float32)
    prim = np.full((B, h, w), _INVALID_ID, dtype=np.uint32)
    uvs = np.zeros((B, h, w, 2), dtype=np.float32)
    # face normals and their orientation, for the culling and the pixel normals alike
    n_cam, facing = _face_orientation(v_cam, faces) if rois and (cull_back_faces or normals) else (None, None)
    if rois:
        rays = _rays_for(camera)
        verts_np = np.ascontiguousarray(vertices.to("cpu", torch.float32).numpy())
        faces_np = faces.cpu().numpy().astype(np.uint32)
        faces_o3d = o3d.core.Tensor(faces_np)
        front = (facing <= 0).cpu().numpy() if cull_back_faces else None
        # open3d builds one BVH per scene, so each batch element needs its own scene.
        for b, (b0, b1, d0, d1) in enumerate(per_problem):
            if b1 <= b0 or d1 <= d0:
                continue
            kept = None if front is None else np.flatnonzero(front[b])
            if kept is not None and len(kept) == 0:
                continue  # every face turned away: nothing can be hit
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(o3d.core.Tensor(verts_np[b]),
                                faces_o3d if kept is None else o3d.core.Tensor(faces_np[kept]))
            # Only pixels inside the projected bounding box can be hit.
            hit = scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays[b0:b1, d0:d1])))
            box = (b, slice(b0 - r0, b1 - r0), slice(d0 - c0, d1 - c0))
            t_hit[box] = hit["t_hit"].numpy()
            ids = hit["primitive_ids"].numpy()
            if kept is not None:  # back to indices of all faces
                ids = np.where(ids == _INVALID_ID, _INVALID_ID, kept[np.minimum(ids, len(kept) - 1)]).astype(np.uint32)
            prim[box] = ids
            uvs[box] = hit["primitive_uvs"].numpy()

    t_hit_t = torch.from_numpy(t_hit).to(device)
    hit_mask = torch.isfinite(t_hit_t)
    # Rays have unit camera-frame z, so t_hit already is the z depth.
    depth = torch.where(hit_mask, t_hit_t, 0.0)
    empty = torch.tensor(-1, dtype=torch.int64, device=device)
    face_id = torch.where(hit_mask, torch.from_numpy(prim.astype(np.int64)).to(device), empty)
    if rois:
        safe_id = face_id.clamp(min=0)
        model_id = torch.where(hit_mask, model_ids.take(safe_id), empty)  # take: a flat gather, faster than [ ]
        bone_id = torch.where(hit_mask, bone_ids.take(safe_id), empty)
        pixel_normals = _pixel_normals(n_cam, facing, face_id, hit_mask) if normals else None
    else:
        model_id = torch.full_like(face_id, -1)
        bone_id = torch.full_like(face_id, -1)
        pixel_normals = depth.new_zeros(B, h, w, 3) if normals else None
    barycentric = torch.from_numpy(uvs).to(device) * hit_mask[..., None]
    # The regions keep a 2 px empty border inside the image, so the crop's edges are
    # those of the whole image.
    edges = silhouette_edges(depth, edge_threshold) if rois else hit_mask
    box = (slice(r0, r1), slice(c0, c1))
    return RenderResult(_paste(depth, box, H, W, 0), _paste(face_id, box, H, W, -1), _paste(model_id, box, H, W, -1),
                        _paste(bone_id, box, H, W, -1),
                        None if pixel_normals is None else _paste(pixel_normals, box, H, W, 0), _paste(edges, box, H, W, False),
                        _paste(barycentric, box, H, W, 0))


def _face_orientation(v_cam: torch.Tensor, faces: torch.Tensor) -> tuple:
    """Unnormalised camera-frame face normals (B, F, 3) and ``n . v0`` (B, F), from
    camera-frame vertices. The camera sits at the origin, so a face's front
    (counter-clockwise) side, or its edge, faces the camera iff ``n . v0 <= 0``."""
    tri = face_corners(v_cam, faces)
    n = face_normals(tri)
    return n, (n * tri[:, :, 0]).sum(-1)


def _paste(crop: torch.Tensor, box: tuple, H: int, W: int, fill) -> torch.Tensor:
    """A (B, h, w, ...) crop placed at ``box`` (row and column slices) of a (B, H, W, ...) map."""
    out = torch.full((crop.shape[0], H, W, *crop.shape[3:]), fill, dtype=crop.dtype, device=crop.device)
    out[:, box[0], box[1]] = crop
    return out


def _pixel_normals(n_cam: torch.Tensor, facing: torch.Tensor, face_id: torch.Tensor, hit_mask: torch.Tensor) -> torch.Tensor:
    """(B, H, W, 3) float32 camera-frame face normals facing the camera, 0 where empty,
    from :func:`_face_orientation`'s normals and orientation."""
    n = F.normalize(torch.where(facing[..., None] > 0, -n_cam, n_cam), dim=-1).float()
    B, num_faces = n.shape[:2]
    # Gather only at hit pixels: usually a small part of the image.
    pixel = hit_mask.flatten().nonzero()[:, 0]
    batch = torch.div(pixel, hit_mask.shape[1] * hit_mask.shape[2], rounding_mode="floor")
    rows = batch * num_faces + face_id.flatten().index_select(0, pixel)
    out = n.new_zeros(hit_mask.numel(), 3)
    out.index_copy_(0, pixel, n.reshape(-1, 3).index_select(0, rows))
    return out.view(*hit_mask.shape, 3)


def visible_vertices(render_result: RenderResult, faces: torch.Tensor, num_vertices: int) -> torch.Tensor:
    """Vertices of triangles hit by at least one pixel.

    Args:
        render_result: output of :func:`render`; only ``face_id`` (B, H, W) is used.
        faces: (F, 3) int64 faces that were rendered.
        num_vertices: V, the number of rendered vertices.

    Returns:
        (B, V) bool visibility mask on the device of ``render_result.face_id``.
    """
    face_id = render_result.face_id
    check_tensor(face_id, "render_result.face_id", (None, None, None), spec="(B, H, W)")
    check_tensor(faces, "faces", (None, 3), spec="(F, 3)")
    if isinstance(num_vertices, bool) or not isinstance(num_vertices, int) or num_vertices < 0:
        raise ValueError(f"num_vertices must be a non-negative int, got {num_vertices!r}")
    B, num_faces = face_id.shape[0], faces.shape[0]
    if num_faces > 0 and int(faces.max()) >= num_vertices:
        raise ValueError(f"faces index vertex {int(faces.max())} but num_vertices is {num_vertices}")
    if face_id.numel() > 0 and int(face_id.max()) >= num_faces:
        raise ValueError(f"render_result.face_id references face {int(face_id.max())} but faces has {num_faces} rows")
    faces = faces.long().to(face_id.device)
    face_id = face_id.long()
    # the faces hit by a pixel, then their corners
    hit_faces = face_id.new_zeros(B, num_faces, dtype=torch.bool)
    visible = face_id.new_zeros(B, num_vertices, dtype=torch.bool)
    for b in range(B):
        hit_faces[b].index_fill_(0, face_id[b].masked_select(face_id[b] >= 0), True)
        visible[b, faces[hit_faces[b]].reshape(-1)] = True
    return visible
