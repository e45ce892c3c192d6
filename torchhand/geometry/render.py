"""Depth, id, normal and silhouette rendering of posed triangle meshes, in two layers.

1. A backend (:mod:`torchhand.geometry.raycast`: Warp rasterisation, Warp BVH ray
   casting, or open3d's Embree as the reference) returns raw :class:`Hits`: the face,
   depth and barycentrics of the ray through every pixel centre.
2. Everything else is derived from the hits here, on the vertices' device, once, for
   every consumer (as pytorch3d derives shading from ``Fragments``): depth, model and
   bone ids, pixel normals, silhouette edges and, on demand, the visible vertices. In
   plain torch, except that the Warp backends take the ids and edges in one Warp pass
   (the same maps; the torch passes over the pixels cost more than the drawing for the
   swarm's many views).

:class:`Renderer` keeps what can be kept between calls (the faces on the device, the
BVH of ``"warp-raycast"``); :func:`render` is the one-off call. Rendering is not
differentiable (inputs are detached). Units are millimetres; the camera frame is x
right, y down, z forward; one ray per integer pixel centre (OpenCV convention).
"""

from __future__ import annotations

from typing import NamedTuple, Optional, Sequence, Union

import numpy as np
import torch
import torch.nn.functional as F

from torchhand.core.check import check_index, check_tensor, checks_enabled
from torchhand.geometry.camera import Camera
from torchhand.geometry.image_ops import clamp_box, max_filter_3x3
from torchhand.geometry.mesh import face_corners, face_normals
from torchhand.geometry.raycast import (BACKENDS, Hits, RayCaster, Views, projected_boxes, _listify, check_vertices_faces,
                                       views_of)

__all__ = ["RenderResult", "Renderer", "render", "window", "window_map", "silhouette_edges", "visible_vertices",
           "model_masks", "DEFAULT_EDGE_THRESHOLD_MM", "BACKENDS"]

#: Depth jump (mm) between neighbouring pixels that counts as a silhouette edge.
DEFAULT_EDGE_THRESHOLD_MM = 10.0

Cameras = Union[Camera, Sequence[Camera]]


class RenderResult(NamedTuple):
    """Per-pixel render outputs, all on the device of the rendered vertices.

    Shapes are (B, H, W) for one camera and (B, C, H, W) for C cameras (the leading
    dims written ``(...)`` below).

    Attributes:
        depth: (..., H, W) float32 camera-frame z in mm; 0 where nothing is hit.
        face_id: (..., H, W) int64 index of the hit triangle; -1 where empty.
        model_id: (..., H, W) int64 ``face_model_id`` of the hit triangle; -1 where empty.
        bone_id: (..., H, W) int64 ``face_bone_id`` of the hit triangle; -1 where empty.
        normals: (..., H, W, 3) float32 camera-frame unit normals of the hit triangle,
            oriented towards the camera; 0 where empty. None when rendered with
            ``normals=False``.
        silhouette_edges: (..., H, W) bool, see :func:`silhouette_edges`.
        barycentric: (..., H, W, 2) float32 ``(u, v)`` of the hit, i.e. the hit point is
            ``(1 - u - v) * v0 + u * v1 + v * v2`` of the face's vertices; 0 where empty.
        origin: None for whole images; for a render cropped to a pixel box
            (``Renderer(..., crop=True)``, :func:`window`), the image pixel (row, col)
            of the maps' (0, 0): H x W is then the box's size, and image pixel (r, c)
            is map pixel (r - row, c - col). :func:`window` cuts or pads either kind to
            any box.
    """

    depth: torch.Tensor
    face_id: torch.Tensor
    model_id: torch.Tensor
    bone_id: torch.Tensor
    normals: Optional[torch.Tensor]
    silhouette_edges: torch.Tensor
    barycentric: torch.Tensor
    origin: Optional[tuple] = None

    def maps(self, fn) -> "RenderResult":
        """The same render with ``fn`` applied to every map (None stays None)."""
        return RenderResult(*(None if x is None else fn(x) for x in self[:7]), self.origin)


#: the value of each map where nothing is hit
_EMPTY = {"depth": 0, "face_id": -1, "model_id": -1, "bone_id": -1, "normals": 0, "silhouette_edges": False,
          "barycentric": 0}
#: the maps with a channel dim after the pixel dims
_CHANNELS = ("normals", "barycentric")


def window(result: RenderResult, box: tuple) -> RenderResult:
    """The maps of a render over the image pixels ``box`` (r0, r1, c0, c1), empty where
    the render did not cover them (a cropped render's box, or outside the image): a
    render cropped at ``origin`` (r0, c0), e.g. whole images again with (0, H, 0, W).
    Shapes (..., H, W) as in :class:`RenderResult`; the render itself where it already
    is that box."""
    r0, r1, c0, c1 = (int(x) for x in box)
    h, w = result.depth.shape[-2:]
    if (r0, c0) == (result.origin or (0, 0)) and (r1 - r0, c1 - c0) == (h, w):
        return result
    out = [None if x is None else window_map(x, result.origin, box, _EMPTY[name], 1 if name in _CHANNELS else 0)
           for name, x in zip(RenderResult._fields[:7], result[:7])]
    return RenderResult(*out, (r0, c0))


def window_map(x: torch.Tensor, origin: Optional[tuple], box: tuple, fill, channels: int = 0) -> torch.Tensor:
    """One map of a render, (..., h, w) with image pixel ``origin`` (row, col) at its
    (0, 0) (None: (0, 0)), over the image pixels ``box`` (r0, r1, c0, c1), ``fill``
    where it has no pixel; ``channels``: trailing dims after the pixel dims (1 for
    normals and barycentrics)."""
    r0, r1, c0, c1 = (int(v) for v in box)
    o_r, o_c = origin or (0, 0)
    h, w = x.shape[x.dim() - 2 - channels : x.dim() - channels]
    lead, trail = x.shape[: x.dim() - 2 - channels], x.shape[x.dim() - channels :]
    y = x.new_full((*lead, r1 - r0, c1 - c0, *trail), fill)
    # the overlap of the two boxes, in each one's pixels
    a0, a1, b0, b1 = max(r0, o_r), min(r1, o_r + h), max(c0, o_c), min(c1, o_c + w)
    if a1 > a0 and b1 > b0:
        tail = (slice(None),) * channels
        y[(Ellipsis, slice(a0 - r0, a1 - r0), slice(b0 - c0, b1 - c0)) + tail] = \
            x[(Ellipsis, slice(a0 - o_r, a1 - o_r), slice(b0 - o_c, b1 - o_c)) + tail]
    return y


def silhouette_edges(depth: torch.Tensor, threshold: float = DEFAULT_EDGE_THRESHOLD_MM) -> torch.Tensor:
    """Occluding-contour pixels of a depth map.

    A pixel is an edge if it is foreground (depth > 0) and one of its 8 neighbours is
    background or farther away by more than ``threshold``; i.e. only the near
    (occluding) side of a discontinuity is marked. Implemented as a torch morphological
    comparison: a flat 3x3 grey-scale dilation of the depth map with background set to
    +inf. Pixels outside the image do not count as background.

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
    return foreground & (max_filter_3x3(far) - depth > threshold)


def _check_ids(name: str, ids: Optional[torch.Tensor], num_faces: int, like: torch.Tensor) -> torch.Tensor:
    if ids is None:
        return like.new_zeros(num_faces, dtype=torch.int64)
    check_tensor(ids, name, (num_faces,), spec=f"(F,) with F={num_faces}", integer=True)
    if ids.device != like.device:
        raise ValueError(f"{name} is on {ids.device} but vertices is on {like.device}; they must match")
    return ids.long()


class Renderer:
    """Renders posed copies of one mesh (a scene's concatenated models).

    Args:
        faces: (F, 3) int64 vertex indices; F may be 0.
        face_model_id: (F,) int64 model index per face; zeros if None.
        face_bone_id: (F,) int64 bone index per face; zeros if None.
        backend: ``"warp"`` (rasterisation), ``"warp-raycast"`` (Warp BVH) or ``"open3d"``
            (:mod:`torchhand.geometry.raycast`); None: Warp when installed. Ignored when
            ``caster`` is given.
        edge_threshold: depth jump (mm) for :func:`silhouette_edges`.
        cull_back_faces: leave faces turned away from the camera out (``"warp"``); exact
            for closed meshes with outward normals seen from outside, as every shipped
            model is: a ray enters a closed mesh through a front face first.
        caster: the :class:`~torchhand.geometry.raycast.RayCaster` that finds the hits
            (as pytorch3d's ``MeshRenderer`` takes its rasteriser); None: one is made
            of ``faces``, ``backend`` and ``cull_back_faces``. Its faces must be ``faces``.

    The buffers stay where they were made: :meth:`to` moves them, and vertices on
    another device are an error naming both.
    """

    def __init__(self, faces: torch.Tensor, face_model_id: Optional[torch.Tensor] = None,
                 face_bone_id: Optional[torch.Tensor] = None, backend: Optional[str] = None,
                 edge_threshold: float = DEFAULT_EDGE_THRESHOLD_MM, cull_back_faces: bool = False,
                 caster: Optional[RayCaster] = None):
        check_tensor(faces, "faces", (None, 3), spec="(F, 3)", integer=True)
        faces = faces.detach().long()
        if faces.shape[0] and bool((faces.min(1).values < 0).any()):
            raise ValueError(f"faces must hold vertex indices >= 0, got {int(faces.min())}")
        repeated = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])
        if bool(repeated.any()):
            rows = torch.nonzero(repeated)[:5, 0].tolist()
            raise ValueError(f"faces has degenerate triangles (a vertex index repeated) at rows {rows}")
        self.faces = faces
        self.model_ids = _check_ids("face_model_id", face_model_id, faces.shape[0], faces)
        self.bone_ids = _check_ids("face_bone_id", face_bone_id, faces.shape[0], faces)
        self.edge_threshold = float(edge_threshold)
        if caster is None:
            caster = RayCaster(faces, backend, cull_back_faces)
        elif not isinstance(caster, RayCaster):
            raise TypeError(f"caster must be a torchhand.geometry.raycast.RayCaster, got {type(caster).__name__}")
        elif caster.faces.shape != faces.shape or not torch.equal(caster.faces.to(faces.device), faces):
            raise ValueError("caster was made for other faces than the renderer's")
        self.caster = caster
        self._views_cache = None

    @property
    def backend(self) -> str:
        return self.caster.backend

    @property
    def device(self) -> torch.device:
        """Where the renderer's buffers (faces, ids) are; vertices must be there too."""
        return self.faces.device

    def to(self, device) -> "Renderer":
        """Move the buffers to ``device`` (in place, as ``nn.Module.to``); returns self."""
        device = torch.device(device)
        if device != self.faces.device:
            self.faces, self.model_ids, self.bone_ids = (x.to(device) for x in
                                                        (self.faces, self.model_ids, self.bone_ids))
            self.caster.to(device)
            self._views_cache = None
        return self

    def _check_device(self, vertices: torch.Tensor) -> None:
        if vertices.device != self.faces.device:
            raise ValueError(f"vertices are on {vertices.device} but the renderer's faces are on {self.faces.device}: "
                             f"move one of them (Renderer.to({str(vertices.device)!r}))")

    def pixel_boxes(self, vertices: torch.Tensor, cameras: Cameras, per_problem: bool = False) -> torch.Tensor:
        """(B x C, 4) int32 pixel boxes (r0, r1, c0, c1) of the projections of each
        problem's (B, V, 3) ``vertices`` in each of its views (cameras as in
        :meth:`__call__`), 2 px wider; the whole image where a vertex lies at or behind
        the camera plane. No host sync."""
        self._check_device(vertices)
        cams = _listify(cameras)
        return projected_boxes(vertices.to(torch.float32), self._views(cams, per_problem, vertices.shape[0],
                                                                       vertices.device))

    def _views(self, cams, per_problem: bool, B: int, device) -> Views:
        """The cameras as tensors, kept while the same camera objects come back."""
        key = (tuple(id(c) for c in cams), per_problem, B if per_problem else 0, str(device))
        if self._views_cache is None or self._views_cache[0] != key:
            views = views_of(cams, len(cams) // B if per_problem else len(cams), device)
            self._views_cache = (key, views, cams)  # holding the cameras keeps their ids unique
        return self._views_cache[1]

    def hits(self, vertices: torch.Tensor, cameras: Cameras, per_problem: bool = False,
             slots: Optional[torch.Tensor] = None, box: Optional[tuple] = None) -> Hits:
        """The backend's raw :class:`Hits` (N = B x C views); see :meth:`__call__`."""
        vertices, _ = check_vertices_faces(vertices, self.faces)
        self._check_device(vertices)
        return self._hits(vertices, _listify(cameras), per_problem, slots, box)

    def _hits(self, vertices, cams, per_problem, slots, box) -> Hits:
        B = vertices.shape[0]
        if per_problem and len(cams) % B:
            raise ValueError(f"per_problem needs a multiple of B = {B} cameras (problem-major), got {len(cams)}")
        return self.caster(vertices, self._views(cams, per_problem, B, vertices.device), slots, box)

    def depth(self, vertices: torch.Tensor, cameras: Cameras, per_problem: bool = False) -> torch.Tensor:
        """The depth map alone of (B, V, 3) world-frame vertices in mm (0: nothing),
        shaped as :meth:`__call__`'s: for searches that compare many poses by depth
        (:mod:`torchhand.tracking.initialization`). With the ``"warp"`` backend it is
        the rasteriser's depth test (the nearest face's plane at each pixel centre, in
        float32: within about 2e-5 relative of the exact hit) without the exact hits,
        ids, barycentrics and contours of :meth:`__call__`."""
        vertices, _ = check_vertices_faces(vertices, self.faces)
        self._check_device(vertices)
        single = isinstance(cameras, Camera)
        cams = _listify(cameras)
        B = vertices.shape[0]
        depth = self.caster.depth(vertices, self._views(cams, per_problem, B, vertices.device))
        return depth if single else depth.view(B, depth.shape[0] // B, *depth.shape[1:])

    def __call__(self, vertices: torch.Tensor, cameras: Cameras, *, normals: bool = True, per_problem: bool = False,
                 slots: Optional[torch.Tensor] = None, box: Optional[tuple] = None,
                 crop: bool = False) -> RenderResult:
        """Render (B, V, 3) (or (V, 3)) world-frame vertices in mm.

        Args:
            cameras: one camera (results (B, H, W)), or C cameras seen by every problem
                (results (B, C, H, W)); with ``per_problem``, B x C cameras, problem-major
                (problem b sees cameras b*C .. b*C + C - 1).
            normals: compute the pixel normals (the tracker does not need them).
            slots: with ``"warp-raycast"``, the BVH group of each problem (see
                :class:`~torchhand.geometry.raycast.RayCaster`).
            box: (r0, r1, c0, c1) host ints: the pixels that can be hit, with at least a
                2 px empty border around the meshes' projections (the derived maps are
                computed there only; the rest of the image is empty). None: the box of
                the projected vertices (found with a host synchronisation).
            crop: return the maps of the box only (``RenderResult.origin`` says where
                they lie): a caller that reads the pixels near the meshes saves whole-image
                buffers, which dominate the cost of large images.
        """
        vertices, faces = check_vertices_faces(vertices, self.faces)
        self._check_device(vertices)
        single = isinstance(cameras, Camera)
        cams = _listify(cameras)
        B = vertices.shape[0]
        views = self._views(cams, per_problem, B, vertices.device)
        if box is None:
            b = projected_boxes(vertices.to(torch.float32), views)
            box = (int(b[:, 0].min()), int(b[:, 1].max()), int(b[:, 2].min()), int(b[:, 3].max()))
        box = clamp_box(box, views.height, views.width)
        if crop and (box[1] == box[0] or box[3] == box[2]):
            box = (0, 1, 0, 1)  # the meshes miss the image: one empty pixel keeps the maps non-empty
        hits = self.caster(vertices, views, slots, box, normals, crop)
        C = hits.face_id.shape[0] // B
        res = derive(hits, vertices, self.faces, self.model_ids, self.bone_ids, C, cams, self.edge_threshold,
                     normals, box, crop, warp=self.backend.startswith("warp"), row_split=self.caster.row_split)
        if single:
            return res
        return res.maps(lambda x: x.view(B, C, *x.shape[1:]))


def derive(hits: Hits, vertices: torch.Tensor, faces: torch.Tensor, model_ids: torch.Tensor, bone_ids: torch.Tensor,
           views: int, cameras, edge_threshold: float, normals: bool, box: tuple,
           cropped: bool = False, warp: bool = False, row_split: Optional[int] = None) -> RenderResult:
    """Depth, ids, normals and silhouettes of (N, H, W) hits, N = B x ``views``, computed
    inside ``box`` (r0, r1, c0, c1) and empty outside it; ``cropped``: the hits are the
    box's pixels only, and so are the maps. ``warp``: the ids and contours in one Warp
    kernel (:func:`~torchhand.geometry.warp_kernels.derive_maps`, the same maps; a
    Warp backend has Warp loaded) instead of torch's passes over the box."""
    r0, r1, c0, c1 = box
    face_id, depth, bary = hits.face_id, hits.t, hits.barycentric  # -1 / 0 where nothing is hit (every backend)
    H, W = face_id.shape[-2:]

    def whole(x, fill, channels=0):
        """A map of the box as the hits are: itself when cropped, else pasted into whole images."""
        return x if cropped else window_map(x, (r0, c0), (0, H, 0, W), fill, channels)

    box_face = face_id if cropped else face_id[:, r0:r1, c0:c1]
    hit = box_face >= 0
    if warp and faces.shape[0] and face_id.device.type in ("cpu", "cuda"):
        from torchhand.geometry import warp_kernels

        model_id, bone_id, edges = warp_kernels.derive_maps(face_id, depth, model_ids, bone_ids,
                                                            (0, H, 0, W) if cropped else box, edge_threshold,
                                                            row_split)
    else:
        safe = box_face.clamp(min=0)

        def ids(per_face):  # take: a flat gather
            return torch.where(hit, per_face.take(safe), -1) if faces.shape[0] else torch.full_like(box_face, -1)

        model_id, bone_id = whole(ids(model_ids), -1), whole(ids(bone_ids), -1)
        # the box keeps an empty border, so its edges are the image's
        edges = whole(silhouette_edges(depth if cropped else depth[:, r0:r1, c0:c1], edge_threshold), False)
    pixel_normals = None
    if normals and hits.normals is not None:  # the backend computed them on the way
        pixel_normals = hits.normals
    elif normals:
        pixel_normals = whole(_pixel_normals(vertices, faces, box_face, hit, views, cameras), 0, 1)
    return RenderResult(depth, face_id, model_id, bone_id, pixel_normals, edges, bary, (r0, c0) if cropped else None)


def _pixel_normals(vertices, faces, face_id, hit, views, cameras) -> torch.Tensor:
    """(N, H, W, 3) float32 camera-frame face normals facing the camera, 0 where empty."""
    B = vertices.shape[0]
    cams = list(cameras)
    T = torch.stack([c.T_cw.to(vertices) for c in cams])  # (R, 4, 4), R = Rb x views
    idx = torch.arange(B * views, device=vertices.device)
    b = torch.div(idx, views, rounding_mode="floor")
    cam = (b % (len(cams) // views)) * views + (idx - b * views)  # the camera of view (b, c)
    R, t = T[cam, :3, :3], T[cam, :3, 3]
    v_cam = torch.einsum("nij,nvj->nvi", R, vertices[b]) + t[:, None]  # (N, V, 3)
    tri = face_corners(v_cam, faces)
    n = face_normals(tri)
    facing = (n * tri[:, :, 0]).sum(-1)  # the camera is the origin: front side iff n . v0 <= 0
    n = F.normalize(torch.where(facing[..., None] > 0, -n, n), dim=-1).float()
    N, Fn = n.shape[:2]
    if Fn == 0:
        return n.new_zeros(*face_id.shape, 3)
    rows = (torch.arange(N, device=n.device)[:, None, None] * Fn + face_id.clamp(min=0)).reshape(-1)
    out = n.reshape(-1, 3).index_select(0, rows).view(*face_id.shape, 3)
    return out * hit[..., None]


def render(vertices: torch.Tensor, faces: torch.Tensor, camera: Cameras, face_model_id: Optional[torch.Tensor] = None,
           face_bone_id: Optional[torch.Tensor] = None, *, edge_threshold: float = DEFAULT_EDGE_THRESHOLD_MM,
           normals: bool = True, cull_back_faces: bool = False, backend: Optional[str] = None) -> RenderResult:
    """Render depth, ids, normals and silhouette edges of a posed mesh (one call).

    Args:
        vertices: (B, V, 3) or (V, 3) world-frame vertices in mm (float).
        faces: (F, 3) integer (int64) vertex indices; F may be 0.
        camera: the camera (results (B, H, W)) or C cameras (results (B, C, H, W)).
        face_model_id: (F,) int64 model index per face; zeros if None.
        face_bone_id: (F,) int64 bone index per face; zeros if None.
        edge_threshold: depth jump (mm) for :func:`silhouette_edges`.
        normals: compute the pixel normals.
        cull_back_faces: see :class:`Renderer`.
        backend: ``"warp"``, ``"warp-raycast"`` or ``"open3d"`` (None: Warp when installed).

    Returns:
        :class:`RenderResult` on ``vertices.device``. For many frames of one mesh keep a
        :class:`Renderer` instead (it keeps the faces and the BVH between calls).
    """
    if isinstance(faces, torch.Tensor) and isinstance(vertices, torch.Tensor) and faces.device != vertices.device:
        raise ValueError(f"faces is on {faces.device} but vertices is on {vertices.device}; they must match")
    if not isinstance(camera, Camera) and not (isinstance(camera, (list, tuple)) and camera):
        raise TypeError(f"camera must be a torchhand.geometry.camera.Camera (or a list of them), "
                        f"got {type(camera).__name__}")
    return Renderer(faces, face_model_id, face_bone_id, backend, edge_threshold, cull_back_faces)(
        vertices, camera, normals=normals)


def visible_vertices(render_result: RenderResult, faces: torch.Tensor, num_vertices: int,
                     box: Optional[tuple] = None) -> torch.Tensor:
    """Vertices of triangles hit by at least one pixel (batched, no host sync).

    Args:
        render_result: output of :func:`render`; only ``face_id`` (B, H, W) is used.
        faces: (F, 3) int64 faces that were rendered.
        num_vertices: V, the number of rendered vertices.
        box: (r0, r1, c0, c1) the pixels the render covered (None: all; a cropped
            render covers its maps, and the box is not needed).

    Returns:
        (B, V) bool visibility mask on the device of ``render_result.face_id``.
    """
    face_id = render_result.face_id
    check_tensor(face_id, "render_result.face_id", (None, None, None), spec="(B, H, W)", integer=True)
    check_tensor(faces, "faces", (None, 3), spec="(F, 3)", integer=True)
    if isinstance(num_vertices, bool) or not isinstance(num_vertices, int) or num_vertices < 0:
        raise ValueError(f"num_vertices must be a non-negative int, got {num_vertices!r}")
    B, num_faces = face_id.shape[0], faces.shape[0]
    check_index(faces, "faces", num_vertices, "vertices")  # host syncs, skipped under skip_checks()
    check_index(face_id[face_id >= 0] if checks_enabled() else face_id[:0], "render_result.face_id", num_faces, "faces")
    faces = faces.long().to(face_id.device)
    if box is not None and render_result.origin is None:  # clamped: a negative start would slice from the end
        face_id = face_id[:, max(box[0], 0) : max(box[1], 0), max(box[2], 0) : max(box[3], 0)]
    flat = face_id.reshape(B, -1).long()
    # one extra column collects the empty pixels (-1)
    hit_faces = torch.zeros(B, num_faces + 1, dtype=torch.uint8, device=face_id.device)
    hit_faces.scatter_(1, torch.where(flat >= 0, flat, num_faces), 1)
    hit_faces = hit_faces[:, :num_faces]
    visible = torch.zeros(B, num_vertices, dtype=torch.uint8, device=face_id.device)
    for c in range(3):  # the three corners of every face
        visible.scatter_reduce_(1, faces[:, c].expand(B, num_faces), hit_faces, "amax")
    return visible.bool()


def model_masks(renderer: "Renderer", vertices: torch.Tensor, camera: Camera, dilation: int = 0,
                batch: int = 16) -> np.ndarray:
    """(N, H, W) bool: where the (N, V, 3) posed vertices cover each frame's image,
    grown by ``dilation`` px (OpenCV), rendered ``batch`` frames at a time; what a
    caller removes from the depth when it takes tracked models out of the data."""
    import cv2

    kernel = np.ones((2 * dilation + 1, 2 * dilation + 1), np.uint8)
    masks = []
    for s in range(0, len(vertices), batch):
        res = renderer(vertices[s:s + batch], camera, normals=False)
        for m in (res.model_id >= 0).cpu().numpy():
            masks.append(cv2.dilate(m.astype(np.uint8), kernel) > 0 if dilation else m)
    return np.stack(masks) if masks else np.zeros((0, camera.height, camera.width), bool)

