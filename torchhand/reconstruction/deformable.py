"""Deformable mesh tracking of an object being bent (thesis Ch. 6.3.2, Eq. 6.1-6.5).

A static template mesh follows the depth data frame by frame. Each frame minimises

    E = E_smooth + gamma_def (E_model->data + E_data->model)                 (6.1)

- E_model->data (6.2): the visible vertices (rendered, :class:`~torchhand.geometry.
  render.Renderer`) against their nearest data point (:class:`~torchhand.geometry.
  neighbors.PointIndex`), pairs beyond 10 mm or with normals more than 45 degrees apart
  discarded;
- E_data->model (6.3): each depth discontinuity (the Canny edges of
  :func:`~torchhand.tracking.preprocess.preprocess_depth`) against the nearest projected
  visible vertex, the distance of that vertex to the pixel's Plücker ray;
- E_smooth (6.4): |L V - L V_{t-1}|^2 with the cotangent Laplacian of Eq. 6.5
  (:func:`cotangent_laplacian`), which keeps the surface's curvature where the single
  camera sees nothing.

Choices the thesis leaves open, made here:

- E_data->model is linearised at the current estimate: the vertex is pulled to its
  foot point on the ray. The line distance |V x d - m| and the distance to the foot
  point have the same gradient at the current estimate (both are the component of V -
  foot normal to d), so the iterations reach the same fixed points; the point form
  keeps the three coordinates apart, so one factorisation of a V x V matrix serves x, y
  and z (the thesis' sparse Cholesky; here SuperLU of scipy).
- A data discontinuity pairs with a visible vertex whose projection lies within
  ``edge_radius_px``; beyond that the pair is an outlier (another object's outline).
- ``eps`` |V - V_{t-1}|^2 (1e-6 of the data weight) keeps the system regular when a
  frame has no data (the Laplacian does not see translations).
- Correspondences are searched again ``iterations`` times per frame (ICP), each time
  followed by an exact solve of the quadratic problem.
- Two terms the thesis does not have keep a tube seen from one side in shape
  (docs/rigging.md has the measurements): ``rigidity`` |V - R T|^2 over the cotangent-
  weighted edges, as rigid as possible against the template T (Sorkine and Alexa's
  local rotations R), and ``stretch``, each edge at its template length along its
  current direction. The Laplacian does not see a tube stretching or sliding along
  itself (a linear stretch is harmonic); the edge-length term does, and leaves bending
  free. Both are linearised at the current estimate and share the ARAP system matrix.

Everything is in world coordinates (mm); several depth cameras add their
correspondences to the same system (multi-view depth).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable, List, NamedTuple, Optional, Sequence

import numpy as np
import torch
from tqdm import tqdm

from torchhand.geometry.camera import Camera, unproject_pixels
from torchhand.geometry.mesh import vertex_normals
from torchhand.geometry.neighbors import PointIndex, nearest_marked_pixel
from torchhand.geometry.render import Renderer, RenderResult, visible_vertices
from torchhand.reconstruction.registration import nearest_rotation
from torchhand.tracking.preprocess import DepthFrame

__all__ = ["DeformConfig", "DeformResult", "Embedding", "cotangent_laplacian", "cotangent_weights", "embed",
           "track_deformable", "deform_frame"]


@dataclass(frozen=True)
class DeformConfig:
    """gamma_def: the data terms' weight in Eq. 6.1 (thesis: 0.005 for triangles under
    10 mm^2, 0.05 above). max_distance (mm), max_normal_angle (degrees): the thesis'
    model-to-data gates. edge_radius_px: the data-to-model gate. iterations: searches
    and solves per frame. eps: the regularising weight relative to gamma_def.
    max_vertices: a larger template is tracked as a decimated copy that carries it.
    point_to_plane: the model-to-data term along the data normal instead of Eq. 6.2's
    point-to-point. predict: each frame's search starts from the constant-velocity
    prediction. rigidity: weight of the as-rigid-as-possible term against the template
    (0: the thesis' objective). stretch: weight of the edge-length term, every edge at
    its template length along its current direction (bending free; 0: off)."""

    gamma_def: float = 0.005
    max_distance: float = 10.0
    max_normal_angle: float = 45.0
    edge_radius_px: float = 15.0
    iterations: int = 4
    eps: float = 1e-6
    max_vertices: int = 2500
    point_to_plane: bool = False
    predict: bool = True
    rigidity: float = 0.005
    stretch: float = 0.05


class DeformResult(NamedTuple):
    """vertices: (T, V, 3) float32 world mm, the tracked template per frame;
    model_to_data, data_to_model: (T,) correspondences of the last iteration;
    seconds: (T,) per frame."""

    vertices: np.ndarray
    model_to_data: np.ndarray
    data_to_model: np.ndarray
    seconds: np.ndarray


def cotangent_weights(vertices: np.ndarray, faces: np.ndarray) -> tuple:
    """(W, A): the symmetric (V, V) CSR matrix of ``cot alpha_ij + cot beta_ij`` per mesh
    edge and (V,) the thesis' Voronoi area, half the summed area of the triangles
    around each vertex."""
    import scipy.sparse as sp

    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    V = len(v)
    cot = np.zeros((len(f), 3))
    for k in range(3):  # the angle at corner k is opposite the edge (k+1, k+2)
        a, b, c = f[:, k], f[:, (k + 1) % 3], f[:, (k + 2) % 3]
        e1, e2 = v[b] - v[a], v[c] - v[a]
        cot[:, k] = (e1 * e2).sum(1) / np.maximum(np.linalg.norm(np.cross(e1, e2), axis=1), 1e-12)
    rows = np.concatenate([f[:, 1], f[:, 2], f[:, 2], f[:, 0], f[:, 0], f[:, 1]])
    cols = np.concatenate([f[:, 2], f[:, 1], f[:, 0], f[:, 2], f[:, 1], f[:, 0]])
    vals = np.concatenate([cot[:, 0], cot[:, 0], cot[:, 1], cot[:, 1], cot[:, 2], cot[:, 2]])
    W = sp.coo_matrix((vals, (rows, cols)), shape=(V, V)).tocsr()
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    A = 0.5 * np.bincount(f.ravel(), np.repeat(area, 3), minlength=V)
    if (A <= 0).any():
        raise ValueError(f"{int((A <= 0).sum())} vertices belong to no triangle of positive area")
    return W, A


def cotangent_laplacian(vertices: np.ndarray, faces: np.ndarray):
    """The cotangent Laplacian of Eq. 6.5 as a scipy CSR matrix (V, V).

    ``L_ij = -w_ij`` for one-ring neighbours, ``L_ii = sum_k w_ik``, with ``w_ij =
    (cot alpha_ij + cot beta_ij) / (2 |A_i|)`` and the Voronoi area ``|A_i|``
    approximated, as the thesis does, by half the summed area of the triangles around
    vertex i.
    """
    import scipy.sparse as sp

    W, A = cotangent_weights(vertices, faces)
    Wn = sp.diags(1.0 / (2.0 * A)) @ W
    return (sp.diags(np.asarray(Wn.sum(1)).ravel()) - Wn).tocsr()


def _gates(config: DeformConfig) -> None:
    if not config.gamma_def > 0:
        raise ValueError(f"gamma_def must be > 0, got {config.gamma_def}")
    if config.iterations < 1:
        raise ValueError(f"iterations must be >= 1, got {config.iterations}")
    if config.max_vertices < 100:
        raise ValueError(f"max_vertices must be >= 100, got {config.max_vertices}")
    for name in ("rigidity", "stretch"):
        if not getattr(config, name) >= 0:
            raise ValueError(f"{name} must be >= 0 (0: off), got {getattr(config, name)}")


class Embedding(NamedTuple):
    """Vertices of a fine mesh carried by a coarse one: the coarse triangle of each fine
    vertex, its barycentric coordinates there and its offset along the triangle's normal."""

    coarse_vertices: np.ndarray
    coarse_faces: np.ndarray
    triangle: np.ndarray
    barycentric: np.ndarray
    offset: np.ndarray

    def apply(self, coarse: np.ndarray) -> np.ndarray:
        """(..., Vc, 3) coarse vertices -> (..., V, 3) the fine vertices they carry."""
        tri = coarse[..., self.coarse_faces[self.triangle], :]  # (..., V, 3, 3)
        n = np.cross(tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :])
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
        return (self.barycentric[..., None] * tri).sum(-2) + self.offset[:, None] * n


def embed(vertices: np.ndarray, faces: np.ndarray, max_vertices: int) -> Embedding:
    """A simplified copy of the mesh with about ``max_vertices`` vertices (open3d) and
    the embedding of the original vertices in it (open3d's closest points)."""
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(vertices, np.float64)),
                                     o3d.utility.Vector3iVector(np.asarray(faces, np.int32)))
    # vertex clustering on a uniform grid keeps vertices everywhere (quadric decimation
    # empties flat and ruled regions, a cylinder's length, which then cannot bend);
    # quadric decimation where clustering does not leave a closed manifold
    voxel = float(np.sqrt(mesh.get_surface_area() / max_vertices))
    coarse = mesh.simplify_vertex_clustering(voxel_size=voxel,
                                             contraction=o3d.geometry.SimplificationContraction.Average)
    for clean in ("remove_degenerate_triangles", "remove_duplicated_triangles", "remove_non_manifold_edges",
                  "remove_unreferenced_vertices"):
        getattr(coarse, clean)()
    if not (coarse.is_watertight() and coarse.is_orientable() and len(coarse.vertices) >= 100):
        coarse = mesh.simplify_quadric_decimation(target_number_of_triangles=2 * max_vertices - 4)
        coarse.remove_unreferenced_vertices()
    cv, cf = np.asarray(coarse.vertices), np.asarray(coarse.triangles, np.int64)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(cv.astype(np.float32)), o3d.core.Tensor(cf.astype(np.uint32)))
    found = scene.compute_closest_points(o3d.core.Tensor(np.asarray(vertices, np.float32)))
    tri = found["primitive_ids"].numpy().astype(np.int64)
    uv = found["primitive_uvs"].numpy().astype(np.float64)
    bary = np.stack([1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], 1)
    corners = cv[cf[tri]]
    closest = (bary[..., None] * corners).sum(1)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    offset = ((np.asarray(vertices) - closest) * normal).sum(1)
    return Embedding(cv, cf, tri, bary, offset)


class _Problem:
    """The constant parts of one sequence's problem: the Laplacian and its normal matrix."""

    def __init__(self, template: np.ndarray, faces: np.ndarray, config: DeformConfig):
        import scipy.sparse as sp

        self.L = cotangent_laplacian(template, faces)
        self.LtL3 = sp.kron((self.L.T @ self.L).tocsr(), sp.eye(3)).tocsr()  # unknowns x0 y0 z0 x1 ...
        # as-rigid-as-possible against the template (``rigidity``): cotangent edge weights
        W, _ = cotangent_weights(template, faces)
        W = W.tocoo()
        keep = W.row != W.col
        self.arap_i, self.arap_j = W.row[keep], W.col[keep]
        self.arap_w = np.clip(0.5 * W.data[keep], 1e-3, None)  # clipped: obtuse triangles give negative weights
        Wc = sp.coo_matrix((self.arap_w, (self.arap_i, self.arap_j)), shape=W.shape).tocsr()
        self.K3 = sp.kron(sp.diags(np.asarray(Wc.sum(1)).ravel()) - Wc, sp.eye(3)).tocsr()
        self.template = torch.as_tensor(np.asarray(template, np.float64))
        self.faces = torch.as_tensor(np.asarray(faces, np.int64))
        self.renderer = Renderer(self.faces, cull_back_faces=True)
        self.config = config


def _pair_blocks(V: int, ids: np.ndarray, weights: np.ndarray, H: np.ndarray):
    """sum over pairs of w_k w_l H at the (ids_k, ids_l) vertex blocks: ids (n, c) the
    vertices of each pair, weights (n, c) their coefficients, H (n, 3, 3) -> (3V, 3V)."""
    import scipy.sparse as sp

    blk = weights[:, :, None, None, None] * weights[:, None, :, None, None] * H[:, None, None]  # (n, c, c, 3, 3)
    r = 3 * ids[:, :, None, None, None] + np.arange(3)[None, None, None, :, None]
    q = 3 * ids[:, None, :, None, None] + np.arange(3)[None, None, None, None, :]
    r, q = np.broadcast_to(r, blk.shape), np.broadcast_to(q, blk.shape)
    return sp.coo_matrix((blk.ravel(), (r.ravel(), q.ravel())), shape=(3 * V, 3 * V)).tocsr()


def _arap_rhs(problem: _Problem, current: torch.Tensor) -> np.ndarray:
    """The right-hand side of the as-rigid-as-possible term at the rotations that best
    map each vertex's template edges onto its current ones (the local step, batched SVD)."""
    i, j, w = problem.arap_i, problem.arap_j, torch.as_tensor(problem.arap_w)
    T, X = problem.template, current
    e0, e1 = T[i] - T[j], X[i] - X[j]
    S = torch.zeros(len(T), 3, 3, dtype=T.dtype)
    S.index_add_(0, torch.as_tensor(i), w[:, None, None] * e0[:, :, None] * e1[:, None, :])
    R = nearest_rotation(S)  # (V, 3, 3) template -> current
    rhs = torch.zeros_like(T)
    rhs.index_add_(0, torch.as_tensor(i), (w[:, None, None] * 0.5 * (R[i] + R[j]) @ e0[..., None])[..., 0])
    return rhs.numpy()


def _stretch_rhs(problem: _Problem, current: torch.Tensor) -> np.ndarray:
    """The right-hand side of the edge-length term: every edge at its template length
    along its current direction (each edge turns freely: bending costs nothing)."""
    i, j, w = problem.arap_i, problem.arap_j, torch.as_tensor(problem.arap_w)
    T, X = problem.template, current
    l0 = (T[i] - T[j]).norm(dim=-1)
    e1 = X[i] - X[j]
    u = e1 / e1.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    rhs = torch.zeros_like(T)
    rhs.index_add_(0, torch.as_tensor(i), (w * l0)[:, None] * u)
    return rhs.numpy()


def _data_points(frame: DepthFrame, camd: Camera) -> tuple:
    """The frame's valid points and normals in world coordinates."""
    R_wc, t_wc = camd.T_wc[:3, :3], camd.T_wc[:3, 3]
    pts = frame.points[frame.mask].double() @ R_wc.T + t_wc
    return pts, frame.normals[frame.mask].double() @ R_wc.T


def deform_frame(problem: _Problem, previous: torch.Tensor, frames: Sequence[DepthFrame],
                 cameras: Sequence[Camera], start: Optional[torch.Tensor] = None) -> tuple:
    """One frame of Eq. 6.1 from the previous frame's vertices (V, 3) float64 world
    (``start``: where the correspondence search begins, default ``previous``).
    Returns (vertices (V, 3), model-to-data pairs, data-to-model pairs)."""
    cfg = problem.config
    V = previous.shape[0]
    faces = problem.faces
    prev = previous.numpy().reshape(-1)
    rhs_smooth = problem.LtL3 @ prev
    current = (previous if start is None else start).clone()
    m2d = d2m = 0
    data = [_data_points(f, c.to(dtype=torch.float64)) for f, c in zip(frames, cameras)]
    indexes = [PointIndex(p, torch.zeros(len(p), dtype=torch.int64), torch.zeros(len(p), dtype=torch.int64), 1, 1,
                          cfg.max_distance, backend="cpu") if len(p) else None for p, _ in data]
    for _ in range(cfg.iterations):
        mats, rhs = [], np.zeros((V, 3))
        m2d = d2m = 0
        normals = vertex_normals(current[None], faces)[0]
        for frame, cam, (pts, nrm), index in zip(frames, cameras, data, indexes):
            camd = cam.to(dtype=torch.float64)
            rend = problem.renderer(current[None], camd, normals=False)
            vis = torch.nonzero(visible_vertices(rend, faces, V)[0])[:, 0]
            if len(vis) == 0:
                continue
            if index is not None:
                m2d += _model_to_data(mats, rhs, current, normals, vis, pts, nrm, index, cfg)
            if len(frame.edges):
                d2m += _data_to_model(mats, rhs, current, faces, frame, rend, camd, cfg)
        current = _solve_frame(problem, mats, rhs, rhs_smooth, prev, current)
    return current, m2d, d2m


def _model_to_data(mats: list, rhs: np.ndarray, current: torch.Tensor, normals: torch.Tensor, vis: torch.Tensor,
                   pts: torch.Tensor, nrm: torch.Tensor, index: PointIndex, cfg: DeformConfig) -> int:
    """Model to data (Eq. 6.2): each visible vertex ``vis`` and its nearest data point
    (``pts``, ``nrm``: (N, 3) world, in ``index``), within the normal angle gate, added
    to the normal equations (``mats``, ``rhs`` (V, 3)); returns the number of pairs."""
    V = current.shape[0]
    cos_gate = math.cos(math.radians(cfg.max_normal_angle))
    near = index.nearest(current[vis][None], torch.zeros(1, dtype=torch.int64),
                         torch.zeros(1, len(vis), dtype=torch.int64))[0]
    ok = near >= 0
    ok[ok.clone()] &= (normals[vis[ok]] * nrm[near[ok]]).sum(-1) > cos_gate
    ids = vis[ok].numpy()
    X = pts[near[ok]].numpy()
    if cfg.point_to_plane:
        n = nrm[near[ok]].numpy()
        Hm = n[:, :, None] * n[:, None, :]
    else:
        Hm = np.broadcast_to(np.eye(3), (len(ids), 3, 3))
    mats.append(_pair_blocks(V, ids[:, None], np.ones((len(ids), 1)), Hm))
    np.add.at(rhs, ids, (Hm @ X[..., None])[..., 0])
    return len(ids)


def _data_to_model(mats: list, rhs: np.ndarray, current: torch.Tensor, faces: torch.Tensor, frame: DepthFrame,
                   rend: RenderResult, camd: Camera, cfg: DeformConfig) -> int:
    """Data to model (Eq. 6.3): each depth discontinuity of ``frame`` and the model's
    silhouette point nearest to it in the image of ``rend`` (the hit point of that
    pixel, a barycentric combination of its face's vertices), ``|P x d - m|^2``, added
    to the normal equations (``mats``, ``rhs`` (V, 3)); returns the number of pairs."""
    V = current.shape[0]
    marks = torch.where(rend.silhouette_edges, 0, -1)
    E = len(frame.edges)
    px = nearest_marked_pixel(marks, frame.edges[None], torch.zeros(1, E, dtype=torch.int64),
                              torch.full((1, E), int(math.ceil(cfg.edge_radius_px)), dtype=torch.int64),
                              1)[0]
    ok = px[:, 0] >= 0
    if not ok.any():
        return 0
    px, edges = px[ok], frame.edges[ok]
    f_id = rend.face_id[0, px[:, 0], px[:, 1]]
    uv = rend.barycentric[0, px[:, 0], px[:, 1]].double()
    w = torch.stack([1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], 1)
    corner = faces[f_id]
    P = (w[..., None] * current[corner]).sum(1)
    pix = edges.flip(-1).double()[None]  # (row, col) -> (u, v)
    z = frame.edge_depth[ok].double()[None]
    Xe = camd.T_wc[:3, :3] @ unproject_pixels(pix, z, camd.K)[0].T
    Xe = Xe.T + camd.T_wc[:3, 3]
    keep = ((P - Xe).norm(dim=-1) <= cfg.max_distance).numpy()
    rays = camd.rays(pix)
    d, m = rays.direction[0].numpy()[keep], rays.moment[0].numpy()[keep]
    ids, w = corner.numpy()[keep], w.numpy()[keep]
    Hd = np.eye(3) - d[:, :, None] * d[:, None, :]
    mats.append(_pair_blocks(V, ids, w, Hd))
    np.add.at(rhs, ids, w[..., None] * np.cross(d, m)[:, None])
    return int(keep.sum())


def _solve_frame(problem: _Problem, mats: list, rhs: np.ndarray, rhs_smooth: np.ndarray, prev: np.ndarray,
                 current: torch.Tensor) -> torch.Tensor:
    """The vertices (V, 3) minimising Eq. 6.1 for this iteration's pairs (``mats``,
    ``rhs``): the Laplacian's smoothness about ``prev`` (3V,), the data terms, and the
    as-rigid-as-possible and edge-length terms at ``current``; one sparse solve."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    cfg = problem.config
    V = current.shape[0]
    g = cfg.gamma_def
    e = cfg.eps * g
    A = problem.LtL3 + sp.eye(3 * V) * e
    for M in mats:
        A = A + g * M
    b = rhs_smooth + g * rhs.reshape(-1) + e * prev
    if cfg.rigidity > 0:
        A = A + cfg.rigidity * problem.K3
        b = b + cfg.rigidity * _arap_rhs(problem, current).reshape(-1)
    if cfg.stretch > 0:
        A = A + cfg.stretch * problem.K3
        b = b + cfg.stretch * _stretch_rhs(problem, current).reshape(-1)
    return torch.as_tensor(splu(A.tocsc(), permc_spec="COLAMD").solve(b).reshape(V, 3))


def track_deformable(template: np.ndarray, faces: np.ndarray, frames: Iterable[Sequence[DepthFrame]],
                     cameras: Sequence[Camera], config: DeformConfig = DeformConfig(), num_frames: Optional[int] = None,
                     progress: bool = True, desc: str = "deformable tracking") -> DeformResult:
    """Track the template (V, 3) world mm, placed on frame 0, through ``frames`` (per
    frame one :class:`DepthFrame` per camera of ``cameras``, the object's data only).
    Each frame starts from the previous one's result."""
    _gates(config)
    template = np.asarray(template, np.float64)
    emb = embed(template, faces, config.max_vertices) if len(template) > config.max_vertices else None
    problem = _Problem(emb.coarse_vertices, emb.coarse_faces, config) if emb else _Problem(template, faces, config)
    current = torch.as_tensor(emb.coarse_vertices if emb else template)
    out: List[np.ndarray] = []
    m2d, d2m, secs = [], [], []
    import time

    before = None
    bar = tqdm(total=num_frames, desc=desc, unit="frame", disable=not progress)
    for frame in frames:
        t0 = time.perf_counter()
        start = current + (current - before) if config.predict and before is not None else None
        before = current
        current, a, b = deform_frame(problem, current, frame, cameras, start)
        out.append((emb.apply(current.numpy()) if emb else current.numpy()).astype(np.float32))
        m2d.append(a)
        d2m.append(b)
        secs.append(time.perf_counter() - t0)
        bar.update(1)
    bar.close()
    return DeformResult(np.stack(out), np.asarray(m2d), np.asarray(d2m), np.asarray(secs))
