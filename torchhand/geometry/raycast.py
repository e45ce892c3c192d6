"""Ray casting backends: the hits of pixel rays against B posed scenes in C views.

A backend returns raw hits (:class:`Hits`: face, ray parameter, barycentrics per pixel,
as pytorch3d's rasteriser returns ``Fragments``); everything derived from them (depth,
ids, normals, visibility, silhouettes) is plain torch in :mod:`torchhand.geometry.render`.

Backends, selected by name:

- ``"warp"`` (the default when NVIDIA Warp is installed): z-buffer rasterisation of the
  triangles of every view in one Warp kernel, then the exact hit of each pixel's ray.
  Sampling the pixel centres of a pinhole camera, it finds what a ray cast through each
  of them finds (the nearest face whose projection covers the centre), on CPU and CUDA
  from one kernel source. On this project's 2-core CPU it is about 6x faster than
  casting the same rays through Warp's BVH (4.7 against 30 ms for two hands and a ball
  at 640x480, docs/benchmarks.md), which is why it is the default.
- ``"warp-raycast"``: the rays cast through a Warp mesh BVH that holds the B problems as
  groups, refitted when the vertices move and rebuilt only when the topology (or the
  number of problem slots) changes (:class:`RayCaster` keeps it between calls).
- ``"open3d"``: open3d's Embree ray casting on the CPU, one BVH built per problem and
  view: the reference the others are tested against.

Every backend recomputes the hit of its face in float64 (Moller-Trumbore on the ray
through the pixel centre), so depth and barycentrics agree across backends to float32
rounding wherever they find the same face; faces differ only where a pixel centre lies
exactly on an edge shared by two faces (a tie).

Conventions: world-frame vertices in mm; rays through integer pixel centres (OpenCV);
ray directions with unit camera-frame z, so the ray parameter ``t`` is the depth.
"""

from __future__ import annotations

from typing import List, NamedTuple, Optional, Sequence

import numpy as np
import torch

from torchhand.core.check import check_index, check_tensor, checks_enabled
from torchhand.geometry.camera import Camera
from torchhand.geometry.image_ops import clamp_box

__all__ = ["Hits", "BACKENDS", "default_backend", "RayCaster", "views_of", "Views", "camera_rays", "projected_boxes"]

#: backend names, fastest first
BACKENDS = ("warp", "warp-raycast", "open3d")


def _warp_available() -> bool:
    try:
        from torchhand.geometry import warp_kernels

        warp_kernels.require_warp()
    except ImportError:
        return False
    return True


def default_backend() -> str:
    """``"warp"`` when NVIDIA Warp is installed, else ``"open3d"``."""
    return "warp" if _warp_available() else "open3d"


class Hits(NamedTuple):
    """Raw per-pixel hits of N = B x C views.

    Attributes:
        face_id: (N, H, W) int64 index of the hit face of the problem's faces, -1 where none.
        t: (N, H, W) float32 ray parameter of the hit: the camera-frame depth in mm; 0 where
            none (every backend guarantees it: the renderer uses t as the depth map).
        barycentric: (N, H, W, 2) float32 ``(u, v)``: the hit is ``(1 - u - v) v0 + u v1 + v v2``
            of the face's vertices; 0 where none.
        normals: (N, H, W, 3) float32 camera-frame unit normals of the hit faces, towards
            the camera, when the backend computed them on the way (``"warp"`` when
            asked), else None (the renderer derives them from the faces).
    """

    face_id: torch.Tensor
    t: torch.Tensor
    barycentric: torch.Tensor
    normals: Optional[torch.Tensor] = None


class Views(NamedTuple):
    """Cameras as tensors for the kernels: R = Rb x C rows (Rb = 1: shared by every
    problem; Rb = B: one set per problem), all of one image size.

    intrinsics: (R, 5) float32 (fx, fy, cx, cy, skew); rotation: (R, 3, 3) and
    translation: (R, 3) float32 world-to-camera; views: C; height, width: px.
    """

    intrinsics: torch.Tensor
    rotation: torch.Tensor
    translation: torch.Tensor
    views: int
    height: int
    width: int


def views_of(cameras: Sequence[Camera], views: int, device) -> Views:
    """:class:`Views` of ``cameras`` (R = Rb x ``views`` of them, problem-major)."""
    if len(cameras) == 0 or len(cameras) % views:
        raise ValueError(f"expected a multiple of {views} cameras, got {len(cameras)}")
    sizes = {(c.height, c.width) for c in cameras}
    if len(sizes) != 1:
        raise ValueError(f"the cameras of one render must share one image size, got {sorted(sizes)}")
    (H, W), = sizes
    K = torch.stack([c.K.detach().to(device, torch.float32) for c in cameras])
    T = torch.stack([c.T_cw.detach().to(device, torch.float32) for c in cameras])
    intr = torch.stack([K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 0, 1]], 1)
    return Views(intr.contiguous(), T[:, :3, :3].contiguous(), T[:, :3, 3].contiguous(), views, H, W)


def camera_rays(views: Views) -> tuple:
    """World-frame rays through the pixel centres: origins (R, 3) and directions
    (R, H, W, 3) float32 with unit camera-frame z (so that t is the depth)."""
    intr, R, t = views.intrinsics, views.rotation, views.translation
    dev = intr.device
    v, u = torch.meshgrid(torch.arange(views.height, dtype=torch.float64, device=dev),
                          torch.arange(views.width, dtype=torch.float64, device=dev), indexing="ij")
    fx, fy, cx, cy, sk = (intr[:, k, None, None].double() for k in range(5))
    yn = (v - cy) / fy
    xn = (u - cx - sk * yn) / fx
    d_cam = torch.stack([xn, yn, torch.ones_like(xn)], -1)  # (R, H, W, 3)
    Rd = R.double()
    d_world = torch.einsum("rji,rhwj->rhwi", Rd, d_cam)  # R^T d
    origin = -(Rd.transpose(1, 2) @ t.double()[..., None])[..., 0]
    return origin.float().contiguous(), d_world.float().contiguous()


def projected_boxes(vertices: torch.Tensor, views: Views) -> torch.Tensor:
    """(B x C, 4) int32 pixel boxes (r0, r1, c0, c1) of the projected vertices, 2 px wider;
    the whole image where a vertex lies at or behind the camera plane. No host sync."""
    B, C = vertices.shape[0], views.views
    Rb = views.intrinsics.shape[0] // C
    idx = (torch.arange(B, device=vertices.device)[:, None] % Rb) * C + torch.arange(C, device=vertices.device)
    idx = idx.reshape(-1)
    R, t, K = views.rotation[idx], views.translation[idx], views.intrinsics[idx]
    pc = torch.einsum("nij,nvj->nvi", R, vertices.repeat_interleave(C, 0)) + t[:, None]  # (N, V, 3)
    z = pc[..., 2]
    behind = (z <= 1e-3).any(1)
    zs = torch.where(z > 1e-3, z, torch.ones_like(z))
    x = (K[:, None, 0] * pc[..., 0] + K[:, None, 4] * pc[..., 1]) / zs + K[:, None, 2]
    y = K[:, None, 1] * pc[..., 1] / zs + K[:, None, 3]
    H, W = views.height, views.width
    box = torch.stack([y.amin(1).floor() - 2, y.amax(1).ceil() + 3, x.amin(1).floor() - 2, x.amax(1).ceil() + 3], 1)
    box = torch.stack([box[:, 0].clamp(0, H), box[:, 1].clamp(0, H), box[:, 2].clamp(0, W), box[:, 3].clamp(0, W)], 1)
    full = torch.tensor([0, H, 0, W], dtype=box.dtype, device=box.device)
    return torch.where(behind[:, None], full, box).to(torch.int32)


class RayCaster:
    """Casts the pixel rays of views against posed copies of one mesh.

    Args:
        faces: (F, 3) integer faces of every problem's mesh.
        backend: one of :data:`BACKENDS` (None: :func:`default_backend`).
        cull_back_faces: with ``"warp"``, skip faces turned away from the camera (exact
            for closed meshes with outward normals, as every shipped model is).

    ``"warp-raycast"`` keeps its BVH between calls: call after call with the same
    topology only refits it. ``"warp"`` keeps nothing but the faces.
    """

    def __init__(self, faces: torch.Tensor, backend: Optional[str] = None, cull_back_faces: bool = False,
                 row_split: Optional[int] = None):
        backend = default_backend() if backend is None else backend
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        if backend.startswith("warp"):
            from torchhand.geometry import warp_kernels

            warp_kernels.require_warp()
        self.backend, self.cull_back_faces = backend, bool(cull_back_faces)
        self.row_split = row_split  # "warp": threads per box row of the pixel kernels (None: by device)
        self.faces = faces
        self._faces32 = None
        self._mesh = None  # warp-raycast: the grouped BVH
        self._rays = None  # cached (views key, origins, directions)

    def to(self, device) -> "RayCaster":
        """Move the faces to ``device`` (in place); the device's BVH is rebuilt on use."""
        device = torch.device(device)
        if device != self.faces.device:
            self.faces = self.faces.to(device)
            self._faces32, self._mesh, self._rays = None, None, None
        return self

    def __call__(self, vertices: torch.Tensor, views: Views, slots: Optional[torch.Tensor] = None,
                 box: Optional[tuple] = None, normals: bool = False, crop: bool = False) -> Hits:
        """Hits of (B, V, 3) world-frame vertices in every view.

        ``slots``: (B,) int64 the problem slot of each row, for ``"warp-raycast"`` (a
        problem keeps its BVH group from call to call; default ``arange(B)``).
        ``box``: (r0, r1, c0, c1) host ints, the pixels that can be hit (a caller that
        knows where its meshes project saves the rest of the image); None: the box of
        the projected vertices, found here (a host synchronisation). ``normals``: ask
        the backend for the hit faces' normals if it computes them on the way. ``crop``:
        return the pixels of ``box`` only (clamped to the image; it must be given), maps
        of its size instead of whole images (``"warp"`` draws only those; the other
        backends cut them out).
        Returns :class:`Hits` with N = B x C, problem-major.
        """
        B, V = vertices.shape[:2]
        if crop and box is None:
            raise ValueError("crop needs the pixel box (r0, r1, c0, c1)")
        if self.backend == "warp" and self.faces.shape[0]:
            return self._rasterize(vertices, views, box, normals, crop)
        if self.faces.shape[0] == 0:
            N = B * views.views
            shape = (N, views.height, views.width)
            dev = vertices.device
            hits = Hits(torch.full(shape, -1, dtype=torch.int64, device=dev), torch.zeros(shape, device=dev),
                        torch.zeros(*shape, 2, device=dev))
        elif self.backend == "warp-raycast":
            hits = self._warp_raycast(vertices, views, slots)
        else:
            hits = self._open3d(vertices, views)
        if not crop:
            return hits
        r0, r1, c0, c1 = clamp_box(box, views.height, views.width)
        return Hits(*(None if x is None else x[:, r0:r1, c0:c1].contiguous() for x in hits))

    # ------------------------------------------------------------------ warp
    def _faces_int32(self, device) -> torch.Tensor:
        if self._faces32 is None or self._faces32.device != torch.device(device):
            self._faces32 = self.faces.to(device=device, dtype=torch.int32).contiguous()
        return self._faces32

    def _rasterize(self, vertices: torch.Tensor, views: Views, box: Optional[tuple], normals: bool,
                   crop: bool = False) -> Hits:
        from torchhand.geometry import warp_kernels

        vertices = vertices.to(torch.float32)
        if box is None:
            b = projected_boxes(vertices, views)
            box = (int(b[:, 0].min()), int(b[:, 1].max()), int(b[:, 2].min()), int(b[:, 3].max()))
        face, t, bary, nrm = warp_kernels.rasterize(vertices, self._faces_int32(vertices.device), views.intrinsics,
                                                    views.rotation, views.translation, views.views, views.height,
                                                    views.width, self.cull_back_faces, box, normals, crop,
                                                    self.row_split)
        return Hits(face, t, bary, nrm)

    def depth(self, vertices: torch.Tensor, views: Views) -> torch.Tensor:
        """(B x C, H, W) float32 depth (mm; 0: none) of (B, V, 3) world-frame vertices in
        every view: with ``"warp"`` the rasteriser's depth test alone (the face's plane
        at the pixel centre, in float32, from :func:`~torchhand.geometry.warp_kernels.
        zbuffer`), else the exact hits' depth."""
        if self.backend != "warp" or self.faces.shape[0] == 0:
            return self(vertices, views).t
        from torchhand.geometry import warp_kernels

        vertices = vertices.to(torch.float32)
        b = projected_boxes(vertices, views)
        r0, r1, c0, c1 = clamp_box((int(b[:, 0].min()), int(b[:, 1].max()), int(b[:, 2].min()), int(b[:, 3].max())),
                                   views.height, views.width)
        depth = vertices.new_zeros(vertices.shape[0] * views.views, views.height, views.width)
        if r1 > r0 and c1 > c0:
            zbuf, _ = warp_kernels.zbuffer(vertices, self._faces_int32(vertices.device), views.intrinsics,
                                           views.rotation, views.translation, views.views, self.cull_back_faces,
                                           (r0, r1, c0, c1))
            z = (zbuf >> 32).to(torch.int32).view(torch.float32)  # a key's high word: the depth's bits
            depth[:, r0:r1, c0:c1] = torch.where(zbuf == warp_kernels.EMPTY_KEY, torch.zeros_like(z), z)
        return depth

    def _warp_raycast(self, vertices: torch.Tensor, views: Views, slots: Optional[torch.Tensor]) -> Hits:
        from torchhand.geometry import warp_kernels

        B, V = vertices.shape[:2]
        slots = torch.arange(B, device=vertices.device) if slots is None else slots.to(vertices.device)
        capacity = max(B, int(slots.max()) + 1) if B else 1
        if self._mesh is None or not self._mesh.matches(self.faces, V, capacity, vertices.device):
            seed = vertices.detach().to(torch.float32)
            if capacity > B:  # slots without vertices yet start as copies of the first problem
                seed = seed[:1].expand(capacity, V, 3).clone()
                seed[slots] = vertices.detach().to(torch.float32)
            self._mesh = warp_kernels.build_grouped_mesh(self.faces, V, seed)
        self._mesh.update(vertices, slots)
        origins, dirs = self._camera_rays(views)
        boxes = projected_boxes(vertices.detach().to(torch.float32), views)
        face, t, u, v = warp_kernels.cast_rays(self._mesh, slots, origins, dirs, boxes, views.views)
        return Hits(face.long(), t, torch.stack([u, v], -1))

    def _camera_rays(self, views: Views) -> tuple:
        key = (views.intrinsics, views.rotation, views.translation)
        if self._rays is not None and all(a.shape == b.shape and torch.equal(a, b) for a, b in zip(self._rays[0], key)):
            return self._rays[1], self._rays[2]
        origins, dirs = camera_rays(views)
        self._rays = (tuple(k.clone() for k in key), origins, dirs)
        return origins, dirs

    # ---------------------------------------------------------------- open3d
    def _open3d(self, vertices: torch.Tensor, views: Views) -> Hits:
        import open3d as o3d

        B, C = vertices.shape[0], views.views
        H, W = views.height, views.width
        origins, dirs = self._camera_rays(views)
        Rb = origins.shape[0] // C
        verts = vertices.detach().to("cpu", torch.float32).numpy()
        faces_np = self.faces.detach().cpu().numpy().astype(np.uint32)
        faces_o3d = o3d.core.Tensor(faces_np)
        o_np, d_np = origins.cpu().numpy(), dirs.cpu().numpy()
        boxes = projected_boxes(vertices.detach().to(torch.float32), views).cpu().numpy()
        invalid = int(o3d.t.geometry.RaycastingScene.INVALID_ID)
        face = np.full((B * C, H, W), -1, np.int64)
        for b in range(B):
            # open3d builds one BVH per scene, so each problem needs its own
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(o3d.core.Tensor(verts[b]), faces_o3d)
            for c in range(C):
                i, r = b * C + c, (b % Rb) * C + c
                r0, r1, c0, c1 = boxes[i]
                if r1 <= r0 or c1 <= c0:
                    continue
                d = d_np[r, r0:r1, c0:c1]
                rays = np.concatenate([np.broadcast_to(o_np[r], d.shape), d], -1)
                hit = scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays, dtype=np.float32)))
                ids = hit["primitive_ids"].numpy().astype(np.int64)
                face[i, r0:r1, c0:c1] = np.where(ids == invalid, -1, ids)
        face_t = torch.from_numpy(face).to(vertices.device)
        t, bary = exact_hits(vertices, self.faces, face_t, views)
        return Hits(face_t, t, bary)


def exact_hits(vertices: torch.Tensor, faces: torch.Tensor, face_id: torch.Tensor, views: Views) -> tuple:
    """The hit of each pixel's ray with its face, in float64: (N, H, W) depth t and
    (N, H, W, 2) barycentrics, 0 where ``face_id`` (N, H, W) is -1. The reference
    computation the Warp kernels do in-kernel (slow: it gathers per hit pixel)."""
    N, H, W = face_id.shape
    C = views.views
    Rb = views.intrinsics.shape[0] // C
    t = torch.zeros(N, H, W, dtype=torch.float32, device=face_id.device)
    bary = torch.zeros(N, H, W, 2, dtype=torch.float32, device=face_id.device)
    i, r, c = torch.nonzero(face_id >= 0, as_tuple=True)
    if len(i) == 0:
        return t, bary
    b = torch.div(i, C, rounding_mode="floor")
    cam = (b % Rb) * C + (i - b * C)
    R, tr, K = views.rotation[cam].double(), views.translation[cam].double(), views.intrinsics[cam].double()
    f = faces.to(face_id.device)[face_id[i, r, c]]  # (n, 3)
    P = vertices.detach().double()[b[:, None], f]  # (n, 3, 3) world
    P = torch.einsum("nij,nkj->nki", R, P) + tr[:, None]  # camera frame
    yn = (r.double() - K[:, 3]) / K[:, 1]
    xn = (c.double() - K[:, 2] - K[:, 4] * yn) / K[:, 0]
    d = torch.stack([xn, yn, torch.ones_like(xn)], -1)
    e1, e2 = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]
    pvec = torch.linalg.cross(d, e2)
    det = (e1 * pvec).sum(-1)
    tvec = -P[:, 0]
    qvec = torch.linalg.cross(tvec, e1)
    ok = det != 0
    det = torch.where(ok, det, torch.ones_like(det))
    t[i, r, c] = torch.where(ok, (e2 * qvec).sum(-1) / det, 0.0).float()
    bary[i, r, c] = torch.where(ok[:, None], torch.stack([(tvec * pvec).sum(-1), (d * qvec).sum(-1)], -1) / det[:, None],
                                0.0).float()
    return t, bary


def check_vertices_faces(vertices: torch.Tensor, faces: torch.Tensor) -> tuple:
    """Validate (B, V, 3) or (V, 3) vertices and (F, 3) faces for a render; returns
    (vertices (B, V, 3) detached, faces int64). Raises naming the argument."""
    check_tensor(vertices, "vertices", ("...", None, 3), spec="(B, V, 3) or (V, 3)", floating=True)
    if vertices.ndim == 2:
        vertices = vertices[None]
    elif vertices.ndim != 3:
        raise ValueError(f"vertices must have shape (B, V, 3) or (V, 3), got {tuple(vertices.shape)}")
    check_tensor(faces, "faces", (None, 3), spec="(F, 3)", integer=True)
    if faces.device != vertices.device:
        raise ValueError(f"faces is on {faces.device} but vertices is on {vertices.device}; they must match")
    vertices, faces = vertices.detach(), faces.detach().long()
    if vertices.shape[0] == 0:
        raise ValueError("vertices has no problems (B = 0): nothing to render")
    if checks_enabled():  # reads every value: skipped inside the tracker's iterations
        if not bool(torch.isfinite(vertices).all()):
            bad = torch.nonzero(~torch.isfinite(vertices).all(-1))[:3].tolist()
            raise ValueError(f"vertices must be finite, got NaN or inf values (first at [problem, vertex] {bad})")
        check_index(faces, "faces", vertices.shape[1], "vertices")
    return vertices, faces


def _listify(cameras) -> List[Camera]:
    if isinstance(cameras, Camera):
        return [cameras]
    cams = list(cameras)
    for k, c in enumerate(cams):
        if not isinstance(c, Camera):
            raise TypeError(f"cameras[{k}] must be a torchhand.geometry.camera.Camera, got {type(c).__name__}")
    return cams
