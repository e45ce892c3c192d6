"""NVIDIA Warp kernels of the geometry core: one kernel source for CPU and CUDA.

Imported only when a Warp backend is used (``warp-lang`` is a dependency of torchhand;
where it is missing or cannot load, :func:`require_warp` says how to install it). Tensors are exchanged with
torch zero-copy (``wp.from_torch``), never through numpy, on the tensors' own device.

- :func:`rasterize`: the same hits for pinhole views by z-buffer rasterisation of the
  triangles (one thread per view and triangle, one 64-bit atomic min of depth and face
  per covered pixel centre), then the exact hit of each pixel's ray in float64: what
  casting a ray through every pixel centre finds, several times faster on a CPU.
- :func:`derive_maps`: the maps a render derives from its hits, in one pass over the
  pixel box: the model and bone id of each hit face, and the occluding-contour pixels
  of the depth map (:func:`torchhand.geometry.render.silhouette_edges`, the same
  comparisons in float32, so the same pixels).
- :func:`cast_rays`: closest hits of rays against a *grouped* mesh (one BVH holding the
  B problems of a batch as B groups, refitted when the vertices move): face, distance
  and barycentrics per pixel of B x C views, only inside each view's pixel box; the hit
  is recomputed in float64 from the hit face, so that depth and barycentrics do not
  depend on the BVH's float32 traversal.
- the kernels of the neighbour queries (the nearest point of the same group within a
  radius, through a grouped hash grid; the nearest pixel of an image carrying a given
  mark), launched from :mod:`torchhand.geometry.warp_neighbors`.
"""

from __future__ import annotations

import contextlib
import functools
from typing import Optional

import torch

from torchhand.geometry.image_ops import clamp_box

__all__ = ["require_warp", "wp_device", "rasterize", "derive_maps", "cast_rays", "build_grouped_mesh"]

#: an empty z-buffer entry (above every depth-and-face key)
EMPTY_KEY = 2 ** 63 - 1

WARP_MISSING = ("NVIDIA Warp is not installed: `pip install warp-lang` (a dependency of torchhand), "
                "or choose backend='open3d'")


@functools.lru_cache(maxsize=1)
def _warp():
    try:
        import warp as wp
    except ImportError as err:  # pragma: no cover - exercised by monkeypatching in the tests
        raise ImportError(WARP_MISSING) from err
    # no banner; Warp's own warnings still show (its native layer prints one line when a
    # CUDA toolkit is installed without a driver)
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    return wp


def require_warp():
    """The ``warp`` module, initialised quietly; ImportError naming the package when missing."""
    return _warp()


@contextlib.contextmanager
def on_torch_stream(device: torch.device):
    """Run the enclosed Warp work on torch's current stream of ``device`` (CUDA), so that
    it is ordered with the torch operations around it without a synchronisation."""
    device = torch.device(device)
    if device.type != "cuda":
        yield
        return
    wp = _warp()
    with wp.ScopedStream(wp.stream_from_torch(torch.cuda.current_stream(device))):
        yield


def wp_device(device: torch.device) -> str:
    """Warp's name of a torch device (``cpu``, ``cuda:0``)."""
    device = torch.device(device)
    if device.type == "cpu":
        return "cpu"
    if device.type == "cuda":
        return f"cuda:{device.index if device.index is not None else torch.cuda.current_device()}"
    raise ValueError(f"Warp kernels run on cpu or cuda devices, got {device}")


#: triangles with a vertex nearer than this (mm) to the camera plane are not rasterised
NEAR_MM = 1.0


@functools.lru_cache(maxsize=1)
def _kernels():
    wp = _warp()
    NEAR = wp.constant(NEAR_MM)
    EMPTY = wp.constant(wp.int64(EMPTY_KEY))

    @wp.kernel(enable_backward=False)
    def cast_kernel(mesh: wp.uint64, slots: wp.array(dtype=wp.int32), roots: wp.array(dtype=wp.int32),
                    points: wp.array(dtype=wp.vec3),
                    indices: wp.array(dtype=wp.int32), origins: wp.array(dtype=wp.vec3),
                    dirs: wp.array3d(dtype=wp.vec3), boxes: wp.array2d(dtype=wp.int32), views: int,
                    ray_batch: int, faces_per_problem: int, face_out: wp.array3d(dtype=wp.int32),
                    t_out: wp.array3d(dtype=wp.float32), u_out: wp.array3d(dtype=wp.float32),
                    v_out: wp.array3d(dtype=wp.float32)):
        i, r, c = wp.tid()  # i = b * views + view
        face_out[i, r, c] = -1
        t_out[i, r, c] = 0.0
        u_out[i, r, c] = 0.0
        v_out[i, r, c] = 0.0
        if r < boxes[i, 0] or r >= boxes[i, 1] or c < boxes[i, 2] or c >= boxes[i, 3]:
            return
        b = i // views
        ray = (b % ray_batch) * views + (i - b * views)
        o = origins[ray]
        d = dirs[ray, r, c]
        slot = slots[b]
        q = wp.mesh_query_ray(mesh, o, d, 1.0e9, roots[slot])
        if not q.result:
            return
        f = q.face
        # Moller-Trumbore in float64 on the hit face: exact to double precision, the same
        # for every backend that finds the same face
        p0 = wp.vec3d(points[indices[3 * f]])
        e1 = wp.vec3d(points[indices[3 * f + 1]]) - p0
        e2 = wp.vec3d(points[indices[3 * f + 2]]) - p0
        dd = wp.vec3d(d)
        pvec = wp.cross(dd, e2)
        det = wp.dot(e1, pvec)
        if det == wp.float64(0.0):
            return
        tvec = wp.vec3d(o) - p0
        u = wp.dot(tvec, pvec) / det
        qvec = wp.cross(tvec, e1)
        v = wp.dot(dd, qvec) / det
        face_out[i, r, c] = f - slot * faces_per_problem
        t_out[i, r, c] = wp.float32(wp.dot(e2, qvec) / det)
        u_out[i, r, c] = wp.float32(u)
        v_out[i, r, c] = wp.float32(v)

    @wp.kernel(enable_backward=False)
    def nearest_grid_kernel(grid: wp.uint64, points: wp.array(dtype=wp.vec3), queries: wp.array2d(dtype=wp.vec3),
                            groups: wp.array2d(dtype=wp.int32), radius: float, first: float, any_point: int,
                            index_out: wp.array2d(dtype=wp.int32)):
        b, k = wp.tid()
        index_out[b, k] = -1
        g = groups[b, k]
        if g < 0:
            return
        x = queries[b, k]
        best = int(-1)
        # growing radii, first, 2 first, ... up to radius: every point within rho lies in
        # the cells the query at rho visits, so a point found within rho is the exact
        # nearest; most queries (vertices near their data) stop at the first, cheap radius
        # (any_point: the first point found within radius, wherever it lies)
        rho = first
        while best < 0 and rho <= radius * 1.0001:
            best_d2 = rho * rho
            query = wp.hash_grid_query(grid, x, rho, g)
            j = int(0)
            while wp.hash_grid_query_next(query, j):
                d2 = wp.length_sq(points[j] - x)
                if any_point != 0 and d2 <= radius * radius:
                    best = j
                    break
                if d2 < best_d2 or (d2 == best_d2 and (best < 0 or j < best)):
                    best_d2 = d2
                    best = j
            rho = rho * 2.0
        index_out[b, k] = best

    @wp.func
    def pixel_hash(r: int, c: int) -> int:
        # ties between equidistant pixels go to the smaller hash: deterministic on every
        # device and without a preferred direction (see neighbors.pixel_hash)
        return ((r * 40503) ^ (c * 31337)) & 2147483647  # no int32 overflow below 32768 px

    @wp.kernel(enable_backward=False)
    def nearest_pixel_kernel(marks: wp.array3d(dtype=wp.int32), boxes: wp.array2d(dtype=wp.int32),
                             images: wp.array(dtype=wp.int32), queries: wp.array3d(dtype=wp.int32),
                             groups: wp.array2d(dtype=wp.int32), radius: wp.array2d(dtype=wp.int32),
                             out: wp.array3d(dtype=wp.int32)):
        b, k = wp.tid()
        out[b, k, 0] = -1
        out[b, k, 1] = -1
        g = groups[b, k]
        if g < 0:
            return
        m = images[b]  # the marks image of query row b
        H = marks.shape[1]
        W = marks.shape[2]
        r0 = queries[b, k, 0]
        c0 = queries[b, k, 1]
        R = radius[b, k]
        # the group's pixels lie in boxes[m * G + g] = (r_min, r_max, c_min, c_max); skip
        # the search when that box is farther than R
        G = boxes.shape[0] // marks.shape[0]
        bi = m * G + g
        if boxes[bi, 0] > boxes[bi, 1]:
            return
        dr_box = wp.max(wp.max(boxes[bi, 0] - r0, r0 - boxes[bi, 1]), 0)
        dc_box = wp.max(wp.max(boxes[bi, 2] - c0, c0 - boxes[bi, 3]), 0)
        if dr_box * dr_box + dc_box * dc_box > R * R:
            return
        best_d2 = R * R + 1
        best_r = int(-1)
        best_c = int(-1)
        best_h = int(2147483647)
        ring = int(0)
        # ring s holds the pixels at Chebyshev distance s; their Euclidean distance is >= s,
        # so once s^2 exceeds the best squared distance no further ring can improve it
        while ring <= R and ring * ring <= best_d2:
            for dr in range(-ring, ring + 1):
                rr = r0 + dr
                if rr >= 0 and rr < H:
                    step = 1
                    if dr != -ring and dr != ring:
                        step = 2 * ring
                    dc = -ring
                    while dc <= ring:
                        cc = c0 + dc
                        if cc >= 0 and cc < W and marks[m, rr, cc] == g:
                            d2 = dr * dr + dc * dc
                            h = pixel_hash(rr, cc)
                            if d2 <= R * R and (d2 < best_d2 or (d2 == best_d2 and h < best_h)):
                                best_d2 = d2
                                best_h = h
                                best_r = rr
                                best_c = cc
                        dc += step
            ring += 1
        out[b, k, 0] = best_r
        out[b, k, 1] = best_c

    @wp.kernel(enable_backward=False)
    def raster_kernel(verts: wp.array2d(dtype=wp.vec3), faces: wp.array2d(dtype=wp.int32),
                      intr: wp.array2d(dtype=wp.float32), rot: wp.array(dtype=wp.mat33), trans: wp.array(dtype=wp.vec3),
                      views: int, cam_batch: int, cull: int, r_lo: int, r_hi: int, c_lo: int, c_hi: int,
                      zbuf: wp.array3d(dtype=wp.int64)):
        i, f = wp.tid()  # i = b * views + view
        b = i // views
        cam = (b % cam_batch) * views + (i - b * views)
        Rm = rot[cam]
        tr = trans[cam]
        p0 = Rm * verts[b, faces[f, 0]] + tr
        p1 = Rm * verts[b, faces[f, 1]] + tr
        p2 = Rm * verts[b, faces[f, 2]] + tr
        if p0[2] <= NEAR or p1[2] <= NEAR or p2[2] <= NEAR:
            return
        n = wp.cross(p1 - p0, p2 - p0)
        nd = wp.dot(n, p0)
        if cull != 0 and nd > 0.0:
            return  # turned away from the camera (at the origin of its frame)
        fx = intr[cam, 0]
        fy = intr[cam, 1]
        cx = intr[cam, 2]
        cy = intr[cam, 3]
        sk = intr[cam, 4]
        x0 = (fx * p0[0] + sk * p0[1]) / p0[2] + cx
        y0 = fy * p0[1] / p0[2] + cy
        x1 = (fx * p1[0] + sk * p1[1]) / p1[2] + cx
        y1 = fy * p1[1] / p1[2] + cy
        x2 = (fx * p2[0] + sk * p2[1]) / p2[2] + cx
        y2 = fy * p2[1] / p2[2] + cy
        # the pixel centres the face covers, within the box [r_lo, r_hi) x [c_lo, c_hi)
        c0 = wp.max(int(wp.ceil(wp.min(wp.min(x0, x1), x2))), c_lo)
        c1 = wp.min(int(wp.floor(wp.max(wp.max(x0, x1), x2))), c_hi - 1)
        r0 = wp.max(int(wp.ceil(wp.min(wp.min(y0, y1), y2))), r_lo)
        r1 = wp.min(int(wp.floor(wp.max(wp.max(y0, y1), y2))), r_hi - 1)
        for r in range(r0, r1 + 1):
            py = float(r)
            for c in range(c0, c1 + 1):
                px = float(c)
                # edge functions; pixel centres on an edge belong to both faces (no cracks),
                # the depth test below decides
                w0 = (x1 - px) * (y2 - py) - (x2 - px) * (y1 - py)
                w1 = (x2 - px) * (y0 - py) - (x0 - px) * (y2 - py)
                w2 = (x0 - px) * (y1 - py) - (x1 - px) * (y0 - py)
                if (w0 >= 0.0 and w1 >= 0.0 and w2 >= 0.0) or (w0 <= 0.0 and w1 <= 0.0 and w2 <= 0.0):
                    yn = (py - cy) / fy
                    xn = (px - cx - sk * yn) / fx
                    den = n[0] * xn + n[1] * yn + n[2]
                    if den != 0.0:
                        z = nd / den  # the ray through the pixel centre meets the face's plane at depth z
                        if z > 0.0:
                            # the nearest depth wins, then the smaller face id: positive float bits
                            # order as integers, so one 64-bit atomic min resolves both
                            key = (wp.int64(wp.cast(z, wp.int32)) << wp.int64(32)) | wp.int64(f)
                            wp.atomic_min(zbuf, i, r - r_lo, c - c_lo, key)

    @wp.kernel(enable_backward=False)
    def resolve_kernel(zbuf: wp.array3d(dtype=wp.int64), verts: wp.array2d(dtype=wp.vec3),
                       faces: wp.array2d(dtype=wp.int32), intr: wp.array2d(dtype=wp.float32),
                       rot: wp.array(dtype=wp.mat33), trans: wp.array(dtype=wp.vec3), views: int, cam_batch: int,
                       r_lo: int, c_lo: int, out_r: int, out_c: int, with_normals: int, split: int,
                       face_out: wp.array3d(dtype=wp.int64),
                       t_out: wp.array3d(dtype=wp.float32), bary_out: wp.array4d(dtype=wp.float32),
                       normal_out: wp.array4d(dtype=wp.float32)):
        # thread (i, rb, s) takes the columns s, s + S, ... of box row rb (S = the launch's
        # last dim: a whole row per thread on a CPU, where most of a row is empty and a
        # thread per pixel costs more than the hits; a pixel per thread on a GPU); the
        # outputs come filled with "empty" (-1 and 0); box pixel (rb, cb) is written at
        # (rb + out_r, cb + out_c): the image's pixel, or the box's own
        i, rb, s = wp.tid()
        b = i // views
        cam = (b % cam_batch) * views + (i - b * views)
        Rm = rot[cam]
        tr = trans[cam]
        r = rb + r_lo
        fy = wp.float64(intr[cam, 1])
        yn = (wp.float64(r) - wp.float64(intr[cam, 3])) / fy
        ro = rb + out_r
        for cb in range(s, zbuf.shape[2], split):
            key = zbuf[i, rb, cb]
            if key == EMPTY:
                continue
            c = cb + c_lo
            f = int(key & wp.int64(0xFFFFFFFF))
            # the exact hit of the pixel's ray in the camera frame, in float64
            # (Moller-Trumbore): t is the depth (the direction has unit z), (u, v) the
            # weights of vertices 1 and 2
            p0 = wp.vec3d(Rm * verts[b, faces[f, 0]] + tr)
            e1 = wp.vec3d(Rm * verts[b, faces[f, 1]] + tr) - p0
            e2 = wp.vec3d(Rm * verts[b, faces[f, 2]] + tr) - p0
            xn = (wp.float64(c) - wp.float64(intr[cam, 2]) - wp.float64(intr[cam, 4]) * yn) / wp.float64(intr[cam, 0])
            dd = wp.vec3d(xn, yn, wp.float64(1.0))
            pvec = wp.cross(dd, e2)
            det = wp.dot(e1, pvec)
            if det == wp.float64(0.0):
                continue
            tvec = -p0
            qvec = wp.cross(tvec, e1)
            co = cb + out_c
            face_out[i, ro, co] = wp.int64(f)
            t_out[i, ro, co] = wp.float32(wp.dot(e2, qvec) / det)
            bary_out[i, ro, co, 0] = wp.float32(wp.dot(tvec, pvec) / det)
            bary_out[i, ro, co, 1] = wp.float32(wp.dot(dd, qvec) / det)
            if with_normals != 0:
                n = wp.normalize(wp.cross(e1, e2))
                if wp.dot(n, p0) > wp.float64(0.0):  # turn it towards the camera (the origin)
                    n = -n
                normal_out[i, ro, co, 0] = wp.float32(n[0])
                normal_out[i, ro, co, 1] = wp.float32(n[1])
                normal_out[i, ro, co, 2] = wp.float32(n[2])

    @wp.kernel(enable_backward=False)
    def derive_kernel(face: wp.array3d(dtype=wp.int64), depth: wp.array3d(dtype=wp.float32),
                      model_ids: wp.array(dtype=wp.int64), bone_ids: wp.array(dtype=wp.int64),
                      r_lo: int, r_hi: int, c_lo: int, c_hi: int, threshold: float, split: int,
                      model_out: wp.array3d(dtype=wp.int64), bone_out: wp.array3d(dtype=wp.int64),
                      edge_out: wp.array3d(dtype=wp.bool)):
        # thread (i, rb, s): the columns s, s + S, ... of box row rb, as the resolve kernel;
        # the outputs come filled with "empty" (-1, False)
        i, rb, s = wp.tid()
        r = rb + r_lo
        for c in range(c_lo + s, c_hi, split):
            f = face[i, r, c]
            if f >= wp.int64(0):
                model_out[i, r, c] = model_ids[int(f)]
                bone_out[i, r, c] = bone_ids[int(f)]
            d = depth[i, r, c]
            if d > 0.0:
                # a foreground pixel with a background neighbour, or one farther by more
                # than the threshold (neighbours outside the box do not count)
                edge = False
                for dr in range(-1, 2):
                    rr = r + dr
                    if rr >= r_lo and rr < r_hi:
                        for dc in range(-1, 2):
                            cc = c + dc
                            if cc >= c_lo and cc < c_hi:
                                dn = depth[i, rr, cc]
                                if dn <= 0.0 or dn - d > threshold:
                                    edge = True
                edge_out[i, r, c] = edge

    return cast_kernel, nearest_grid_kernel, nearest_pixel_kernel, raster_kernel, resolve_kernel, derive_kernel


class GroupedMesh:
    """A Warp mesh holding ``capacity`` copies of one topology as groups (one per
    problem slot), with its points in a torch buffer that the casts refit from.

    The BVH is built from the first vertices it is given (a tree built for other
    positions would refit into a slow one) and then only refitted; :meth:`rebuild`
    builds it anew for the current points.

    Attributes:
        faces: (F, 3) int64 the topology; capacity: the problem slots; device.
    """

    def __init__(self, faces: torch.Tensor, num_vertices: int, vertices: torch.Tensor):
        wp = _warp()
        self.device = vertices.device
        self.faces = faces.detach().to(self.device)
        self.capacity, self.num_vertices, F = vertices.shape[0], int(num_vertices), faces.shape[0]
        self.points = vertices.detach().to(torch.float32).reshape(-1, 3).contiguous().clone()
        offsets = torch.arange(self.capacity, device=self.device, dtype=torch.int64)[:, None, None] * self.num_vertices
        self.indices = (self.faces[None] + offsets).reshape(-1).to(torch.int32).contiguous()
        self._groups = torch.arange(self.capacity, device=self.device, dtype=torch.int32).repeat_interleave(F)
        self._wp_points = wp.from_torch(self.points, dtype=wp.vec3)
        self._wp_indices = wp.from_torch(self.indices, dtype=wp.int32)
        self.roots = torch.zeros(self.capacity, dtype=torch.int32, device=self.device)
        self.rebuild()

    def rebuild(self) -> None:
        """Build the BVH for the current points (and find every group's root)."""
        wp = _warp()
        # the groups array stays referenced by the BVH for its lifetime
        with on_torch_stream(self.device):
            self.mesh = wp.Mesh(points=self._wp_points, indices=self._wp_indices, groups=wp.from_torch(self._groups))
            self.refits = 0
            wp.launch(_roots_kernel(), dim=self.capacity, inputs=[self.mesh.id], outputs=[wp.from_torch(self.roots)],
                      device=wp_device(self.device))

    def matches(self, faces: torch.Tensor, num_vertices: int, capacity: int, device: torch.device) -> bool:
        """True when this mesh can serve ``capacity`` problem slots of this topology."""
        return (self.device == torch.device(device) and self.num_vertices == num_vertices
                and capacity <= self.capacity and self.faces.shape == faces.shape
                and (self.faces is faces or torch.equal(self.faces, faces.to(self.device))))

    def update(self, vertices: torch.Tensor, slots: torch.Tensor) -> None:
        """Write (b, V, 3) vertices into the problem slots ``slots`` (b,) int64 and refit."""
        self.points.view(self.capacity, self.num_vertices, 3)[slots] = vertices.detach().to(torch.float32)
        with on_torch_stream(self.device):
            self.mesh.refit()
        self.refits += 1


@functools.lru_cache(maxsize=1)
def _roots_kernel():
    wp = _warp()

    @wp.kernel(enable_backward=False)
    def roots_kernel(mesh: wp.uint64, out: wp.array(dtype=wp.int32)):
        g = wp.tid()
        out[g] = wp.mesh_get_group_root(mesh, g)

    return roots_kernel


def build_grouped_mesh(faces: torch.Tensor, num_vertices: int, vertices: torch.Tensor) -> GroupedMesh:
    """A :class:`GroupedMesh` with one problem slot per row of ``vertices`` (B, V, 3),
    its BVH built for them."""
    return GroupedMesh(faces, num_vertices, vertices)


def cast_rays(gm: GroupedMesh, slots: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor, boxes: torch.Tensor,
              views: int) -> tuple:
    """Closest hits of the rays of ``views`` cameras against the problem slots ``slots``.

    Args:
        gm: the grouped mesh, already updated with the batch's vertices.
        slots: (batch,) int64 the slot of each problem.
        origins: (R, 3) float32 ray origins, R = Rb x views with Rb 1 (shared) or ``batch``.
        dirs: (R, H, W, 3) float32 directions.
        boxes: (batch x views, 4) int32 pixel boxes (r0, r1, c0, c1) outside which nothing is cast.
    Returns:
        face (batch x views, H, W) int32 local face ids (-1: no hit); t, u, v (same
        shape) float32: ray parameter and barycentrics (hit = (1 - u - v) v0 + u v1 + v v2).
    """
    wp = _warp()
    cast_kernel = _kernels()[0]
    batch = slots.shape[0]
    N, H, W = batch * views, dirs.shape[1], dirs.shape[2]
    dev = gm.device
    face = torch.empty(N, H, W, dtype=torch.int32, device=dev)
    t, u, v = (torch.empty(N, H, W, dtype=torch.float32, device=dev) for _ in range(3))
    ray_batch = origins.shape[0] // views
    with on_torch_stream(dev):
        wp.launch(cast_kernel, dim=(N, H, W),
                  inputs=[gm.mesh.id, wp.from_torch(slots.to(torch.int32).contiguous()), wp.from_torch(gm.roots),
                          gm._wp_points, gm._wp_indices,
                          wp.from_torch(origins.contiguous(), dtype=wp.vec3), wp.from_torch(dirs.contiguous(), dtype=wp.vec3),
                          wp.from_torch(boxes.contiguous()), views, ray_batch, gm.faces.shape[0]],
                  outputs=[wp.from_torch(face), wp.from_torch(t), wp.from_torch(u), wp.from_torch(v)],
                  device=wp_device(dev))
    return face, t, u, v


def rasterize(vertices: torch.Tensor, faces: torch.Tensor, intrinsics: torch.Tensor, rotations: torch.Tensor,
              translations: torch.Tensor, views: int, height: int, width: int, cull_back_faces: bool,
              box: tuple, normals: bool = False, crop: bool = False, row_split: Optional[int] = None) -> tuple:
    """Hits of the pixel centres of B x ``views`` pinhole views, inside a pixel box.

    Args:
        vertices: (B, V, 3) float32 world-frame vertices.
        faces: (F, 3) int32.
        intrinsics: (R, 5) float32 (fx, fy, cx, cy, skew) per camera, R = Rb x views with
            Rb 1 (cameras shared by the problems) or B.
        rotations, translations: (R, 3, 3) and (R, 3) float32 world-to-camera.
        cull_back_faces: skip faces turned away from the camera (exact for closed meshes
            with outward normals seen from outside).
        box: (r0, r1, c0, c1) the pixels drawn; the others stay empty.
        normals: also return the camera-frame unit normals of the hit faces, turned
            towards the camera.
        crop: return the box's pixels only (maps of h x w = r1 - r0 x c1 - c0, after
            clamping the box to the image) instead of whole images.
        row_split: threads per box row (:func:`row_split`; None: by device).
    Returns:
        face (B x views, H, W) int64 (-1: none), t (depth, mm; 0: none), barycentric
        (B x views, H, W, 2) float32 (0: none), as :func:`cast_rays`; normals
        (B x views, H, W, 3) float32 (0: none) or None. H x W is h x w with ``crop``.
    """
    wp = _warp()
    resolve_kernel = _kernels()[4]
    N = vertices.shape[0] * views
    dev = vertices.device
    r0, r1, c0, c1 = clamp_box(box, height, width)
    h, w = r1 - r0, c1 - c0
    H, W = (h, w) if crop else (height, width)
    face = torch.full((N, H, W), -1, dtype=torch.int64, device=dev)
    t = torch.zeros(N, H, W, dtype=torch.float32, device=dev)
    bary = torch.zeros(N, H, W, 2, dtype=torch.float32, device=dev)
    nrm = torch.zeros(N, H, W, 3, dtype=torch.float32, device=dev) if normals else None
    if h == 0 or w == 0 or faces.shape[0] == 0:
        return face, t, bary, nrm
    zbuf, args = zbuffer(vertices, faces, intrinsics, rotations, translations, views, cull_back_faces,
                          (r0, r1, c0, c1))
    out_r, out_c = (0, 0) if crop else (r0, c0)
    with on_torch_stream(dev):
        split = row_split_of(dev, w, row_split)
        wp.launch(resolve_kernel, dim=(N, h, split),
                  inputs=[wp.from_torch(zbuf)] + args + [r0, c0, out_r, out_c, int(normals), split],
                  outputs=[wp.from_torch(face), wp.from_torch(t), wp.from_torch(bary),
                           wp.from_torch(nrm if normals else bary.new_zeros(1, 1, 1, 3))], device=wp_device(dev))
    return face, t, bary, nrm


def zbuffer(vertices, faces, intrinsics, rotations, translations, views: int, cull_back_faces: bool,
            box: tuple) -> tuple:
    """The depth test of :func:`rasterize` (its arguments) over the clamped, non-empty
    ``box``: the (N, h, w) int64 z-buffer of keys, each the float32 bits of the nearest
    face's depth at the pixel centre in its high word and the face in its low word
    (``EMPTY_KEY``: none), and the Warp arguments the kernels share."""
    wp = _warp()
    r0, r1, c0, c1 = box
    N, dev = vertices.shape[0] * views, vertices.device
    zbuf = torch.full((N, r1 - r0, c1 - c0), EMPTY_KEY, dtype=torch.int64, device=dev)
    args = [wp.from_torch(vertices.to(torch.float32).contiguous(), dtype=wp.vec3), wp.from_torch(faces.contiguous()),
            wp.from_torch(intrinsics.contiguous()), wp.from_torch(rotations.contiguous(), dtype=wp.mat33),
            wp.from_torch(translations.contiguous(), dtype=wp.vec3), views, intrinsics.shape[0] // views]
    with on_torch_stream(dev):
        wp.launch(_kernels()[3], dim=(N, faces.shape[0]), inputs=args + [int(cull_back_faces), r0, r1, c0, c1],
                  outputs=[wp.from_torch(zbuf)], device=wp_device(dev))
    return zbuf, args


def row_split_of(device: torch.device, width: int, split: Optional[int] = None) -> int:
    """Threads per box row of the pixel kernels: ``split`` (clamped to [1, width]), or
    when None, one on a CPU (a loop over the row) and one per pixel on a GPU. Every
    split gives the same maps."""
    if split is not None:
        return max(1, min(int(split), width))
    return max(1, width) if torch.device(device).type == "cuda" else 1


def derive_maps(face: torch.Tensor, depth: torch.Tensor, model_ids: torch.Tensor, bone_ids: torch.Tensor,
                box: tuple, threshold: float, row_split: Optional[int] = None) -> tuple:
    """Model ids, bone ids and occluding contours of (N, H, W) hits, inside ``box``.

    Args:
        face: (N, H, W) int64 hit face (-1: none); depth: (N, H, W) float32 (0: none).
        model_ids, bone_ids: (F,) int64 per face.
        box: (r0, r1, c0, c1) the maps' pixels to derive (within H x W); the others stay
            empty, and do not count as neighbours of the box's edge pixels.
        threshold: the depth jump (mm) of a contour.
        row_split: threads per box row (:func:`row_split_of`; None: by device).
    Returns:
        model_id, bone_id (N, H, W) int64 (-1: none) and edges (N, H, W) bool, as
        :func:`torchhand.geometry.render.silhouette_edges` of the box's depth.
    """
    wp = _warp()
    derive_kernel = _kernels()[5]
    dev = face.device
    N, H, W = face.shape
    r0, r1, c0, c1 = clamp_box(box, H, W)
    model = torch.full((N, H, W), -1, dtype=torch.int64, device=dev)
    bone = torch.full((N, H, W), -1, dtype=torch.int64, device=dev)
    edges = torch.zeros((N, H, W), dtype=torch.bool, device=dev)
    if N == 0 or r1 == r0 or c1 == c0:
        return model, bone, edges
    with on_torch_stream(dev):
        split = row_split_of(dev, c1 - c0, row_split)
        wp.launch(derive_kernel, dim=(N, r1 - r0, split),
                  inputs=[wp.from_torch(face.contiguous()), wp.from_torch(depth.to(torch.float32).contiguous()),
                          wp.from_torch(model_ids.to(dev, torch.int64).contiguous()),
                          wp.from_torch(bone_ids.to(dev, torch.int64).contiguous()), r0, r1, c0, c1, float(threshold),
                          split],
                  outputs=[wp.from_torch(model), wp.from_torch(bone), wp.from_torch(edges)], device=wp_device(dev))
    return model, bone, edges
