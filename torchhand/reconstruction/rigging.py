"""Kinematic topology and skinning of a motion-segmented mesh (thesis Ch. 6.4.2).

From the template mesh, its parts (:mod:`~torchhand.reconstruction.motion_segments`)
and the tracked vertex trajectories, :func:`build_rig` makes a torchhand model
(:class:`~torchhand.io.assets.ModelAssets`) that keeps the template's vertices and
faces in their order:

1. the curve skeleton of the mesh (pygel3d's local-separator skeleton, with the map from
   every vertex to its skeleton node; the thesis uses the mean curvature skeleton, which
   no maintained Python package ships: both contract the surface to a curve inside it);
2. a joint at the centroid of the boundary between every two adjacent parts, snapped to
   the nearest point of the skeleton (so it lies inside the mesh);
3. the parts' tree from the graph centre of the part adjacency (the root part is the one
   fewest joints away from every other, the largest on ties; a cycle of parts keeps the
   breadth-first tree's edges); auxiliary joints without DoF at the skeleton's ends and
   branches, in ``skeleton.json`` and the picture: one bone per part carries all of a
   part's vertices, so the thesis' redundant bones (end to auxiliary joint inside one
   part) never arise;
4. joint axes and limits from the motion: the rotation of every part against its parent
   over the frames (Kabsch of the part's trajectories), its rotation vectors' principal
   directions; an axis is a DoF when its RMS angle is at least ``axis_ratio`` of the main
   axis' (a hinge has one, a rope's links two); the limits are the range seen, widened
   by ``limit_margin_deg``;
5. skinning weights smooth across part boundaries: the part indicators diffused over the
   mesh by one implicit heat step (``skin_width`` mm; the cotangent Laplacian of Eq. 6.5),
   the largest ``skin_bones`` kept and renormalised. The thesis computes Baran and
   Popović's bone heat, which adds a visibility test from every vertex to its bone; for
   parts found by their motion the parts themselves already say which bone a vertex
   follows.

:func:`fit_rig` poses a rig onto tracked vertices (the tracker's first-frame pose).
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from typing import Dict, List, NamedTuple, Optional

import numpy as np
import torch

from torchhand.core.errors import MissingExtra
from torchhand.io.assets import ModelAssets, rigid_assets
from torchhand.model.kinematics import so3_log
from torchhand.optim.levenberg_marquardt import levenberg_marquardt
from torchhand.reconstruction.deformable import cotangent_weights
from torchhand.reconstruction.motion_segments import mesh_edges, mesh_graph
from torchhand.reconstruction.registration import kabsch_batch

__all__ = ["RigConfig", "Rig", "Skeleton", "curve_skeleton", "part_transforms", "build_rig", "fit_rig"]


@dataclass(frozen=True)
class RigConfig:
    """axis_ratio: an axis of a joint's rotation is a DoF when its RMS angle is at least
    this fraction of the main axis'. limit_margin_deg: widening of the seen range.
    skin_width: mm, about the width of the blend across a part boundary. skin_bones:
    weights kept per vertex. joint_search: mm, how far along the skeleton from the
    boundary centroid a joint moves to the point that the two parts' motions agree on
    best (0: the snapped centroid, as the thesis places it). joint_core: mm along the
    mesh; the two parts' motions for that search come from their vertices at least this
    far from their boundary (the deformable tracking bends a part most there)."""

    axis_ratio: float = 0.3
    limit_margin_deg: float = 15.0
    skin_width: float = 5.0
    skin_bones: int = 4
    joint_search: float = 40.0
    joint_core: float = 20.0


class Skeleton(NamedTuple):
    """nodes: (S, 3) mm; edges: (E, 2) node ids; vertex_node: (V,) the node of every vertex."""

    nodes: np.ndarray
    edges: np.ndarray
    vertex_node: np.ndarray

    def degree(self) -> np.ndarray:
        return np.bincount(self.edges.ravel(), minlength=len(self.nodes))


class Rig(NamedTuple):
    """assets: the model; parts: (V,) part per vertex; bone_of_part: (P,) its bone;
    joints: (P-1, 3) the joint positions (rigging pose), in bone order (bone 1..);
    joint_dofs: (P-1,) axes per joint; ends, branches: (n, 3) auxiliary joints;
    skeleton: the curve skeleton; notes: what the construction decided."""

    assets: ModelAssets
    parts: np.ndarray
    bone_of_part: np.ndarray
    joints: np.ndarray
    joint_dofs: np.ndarray
    ends: np.ndarray
    branches: np.ndarray
    skeleton: Skeleton
    notes: List[str]

    def to_json(self) -> dict:
        return {"parts": int(len(self.bone_of_part)), "part_sizes": np.bincount(self.parts).tolist(),
                "bone_of_part": self.bone_of_part.tolist(), "joints_mm": self.joints.round(3).tolist(),
                "joint_dofs": self.joint_dofs.tolist(), "parents": self.assets.parents.tolist(),
                "auxiliary_ends_mm": self.ends.round(3).tolist(),
                "auxiliary_branches_mm": self.branches.round(3).tolist(),
                "skeleton_nodes_mm": self.skeleton.nodes.round(3).tolist(),
                "skeleton_edges": self.skeleton.edges.tolist(), "notes": self.notes}


@contextlib.contextmanager
def _quiet_stdout():
    """pygel3d's C++ prints its progress on file descriptor 1."""
    import sys

    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def curve_skeleton(vertices: np.ndarray, faces: np.ndarray) -> Skeleton:
    """The local-separator curve skeleton of a closed mesh (pygel3d)."""
    try:
        from pygel3d import graph, hmesh
    except ImportError:
        raise MissingExtra("rigging (the curve skeleton)", "pygel3d") from None
    m = hmesh.Manifold.from_triangles(np.asarray(vertices, np.float64), np.asarray(faces, np.int64))
    with _quiet_stdout():
        skel, mapping = graph.LS_skeleton_and_map(graph.from_mesh(m))
    nodes = list(skel.nodes())
    pos = np.asarray(skel.positions())
    index = {n: i for i, n in enumerate(nodes)}
    edges = sorted({tuple(sorted((index[a], index[b]))) for a in nodes for b in skel.neighbors(a) if b in index})
    vertex_node = np.array([index.get(int(k), 0) for k in np.asarray(mapping)], np.int64)
    return Skeleton(pos[nodes], np.asarray(edges, np.int64).reshape(-1, 2), vertex_node)


def _snap(skeleton: Skeleton, q: np.ndarray) -> np.ndarray:
    """The point of the skeleton's edges (or nodes) nearest to q."""
    P = skeleton.nodes
    if len(skeleton.edges) == 0:
        return P[np.argmin(np.linalg.norm(P - q, axis=1))]
    a, b = P[skeleton.edges[:, 0]], P[skeleton.edges[:, 1]]
    ab = b - a
    s = np.clip(((q - a) * ab).sum(1) / np.maximum((ab * ab).sum(1), 1e-12), 0, 1)
    c = a + s[:, None] * ab
    return c[np.argmin(np.linalg.norm(c - q, axis=1))]


def _skeleton_points(skeleton: Skeleton, centre: np.ndarray, radius: float, step: float = 0.5) -> np.ndarray:
    """Points along the skeleton's edges every ``step`` mm within ``radius`` of ``centre``."""
    P = skeleton.nodes
    pts = [P]
    for a, b in skeleton.edges:
        n = int(np.ceil(np.linalg.norm(P[b] - P[a]) / step))
        if n > 1:
            s = np.linspace(0, 1, n + 1)[1:-1, None]
            pts.append(P[a] + s * (P[b] - P[a]))
    pts = np.concatenate(pts)
    near = pts[np.linalg.norm(pts - centre, axis=1) <= radius]
    return near if len(near) else centre[None]


def part_transforms(trajectories: np.ndarray, template: np.ndarray, parts: np.ndarray) -> tuple:
    """Per part and frame the rigid motion rest -> frame: R (T, P, 3, 3), t (T, P, 3)."""
    X = torch.as_tensor(np.asarray(trajectories, np.float64))
    rest = torch.as_tensor(np.asarray(template, np.float64))
    Rs, ts = [], []
    for p in range(int(parts.max()) + 1):
        ids = torch.as_tensor(np.nonzero(parts == p)[0])
        R, t = kabsch_batch(rest[ids], X[:, ids])
        Rs.append(R)
        ts.append(t)
    return torch.stack(Rs, 1).numpy(), torch.stack(ts, 1).numpy()


def _core_motion(trajectories: np.ndarray, template: np.ndarray, parts: np.ndarray, part: int, boundary: np.ndarray,
                 graph, core: float, R: np.ndarray, t: np.ndarray) -> tuple:
    """The rigid motion (T, 3, 3), (T, 3) of the part's vertices at least ``core`` mm
    along the mesh from ``boundary``; the whole part's (R, t) when fewer than 10 are."""
    from scipy.sparse.csgraph import dijkstra

    far = dijkstra(graph, indices=boundary, min_only=True, limit=core) >= core
    ids = np.nonzero((parts == part) & far)[0]
    if len(ids) < 10:
        return R, t
    Rc, tc = kabsch_batch(torch.as_tensor(np.asarray(template, np.float64)[ids]),
                          torch.as_tensor(np.asarray(trajectories, np.float64)[:, ids]))
    return Rc.numpy(), tc.numpy()


def _tree(adjacency: np.ndarray, sizes: np.ndarray) -> tuple:
    """(order, parent) of the parts: breadth first from the graph centre."""
    from scipy.sparse.csgraph import shortest_path

    P = len(sizes)
    hops = shortest_path(adjacency > 0, unweighted=True, directed=False)
    ecc = np.where(np.isfinite(hops), hops, P + 1).max(1)
    root = min(range(P), key=lambda p: (ecc[p], -sizes[p]))
    order, parent = [root], {root: -1}
    k = 0
    while k < len(order):
        p = order[k]
        k += 1
        for c in np.argsort(-adjacency[p], kind="stable"):
            if adjacency[p, c] > 0 and c not in parent:
                parent[int(c)] = p
                order.append(int(c))
    return order, parent


def _frame(x: np.ndarray) -> np.ndarray:
    """A rotation whose first column is the unit vector x."""
    x = x / max(np.linalg.norm(x), 1e-12)
    helper = np.eye(3)[np.argmin(np.abs(x))]
    y = np.cross(x, helper)
    y /= np.linalg.norm(y)
    return np.stack([x, y, np.cross(x, y)], 1)


def skin_weights(vertices: np.ndarray, faces: np.ndarray, bone_of_vertex: np.ndarray, bones: int, width: float,
                 keep: int) -> tuple:
    """(skin_index, skin_weight) (V, K): the bone indicators after one implicit heat step
    of about ``width`` mm over the mesh, the largest ``keep`` renormalised."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    W, A = cotangent_weights(vertices, faces)
    K = sp.diags(np.asarray(W.sum(1)).ravel()) - W
    M = sp.diags(A)
    lu = splu((M + 0.5 * width ** 2 * K).tocsc())
    onehot = np.zeros((len(vertices), bones))
    onehot[np.arange(len(vertices)), bone_of_vertex] = 1.0
    heat = np.clip(lu.solve(M @ onehot), 0, None)
    heat[np.arange(len(vertices)), bone_of_vertex] += 1e-9  # the own bone wins ties
    k = min(keep, bones)
    idx = np.argsort(-heat, axis=1, kind="stable")[:, :k]
    w = np.take_along_axis(heat, idx, 1)
    w[w < 1e-3 * w[:, :1]] = 0
    w /= w.sum(1, keepdims=True)
    idx = np.where(w > 0, idx, 0)
    return idx.astype(np.int64), w


def _part_tree(faces: np.ndarray, parts: np.ndarray, P: int) -> tuple:
    """The mesh's edges ``e`` (E, 2), the parts ``la``, ``lb`` (E,) of their ends, and
    the tree of the P parts (``order``, ``parent`` of :func:`_tree`, over the parts'
    adjacency: the number of edges between them); an error when the parts are not
    connected."""
    e = mesh_edges(faces)
    la, lb = parts[e[:, 0]], parts[e[:, 1]]
    cross = la != lb
    adjacency = np.zeros((P, P))
    np.add.at(adjacency, (la[cross], lb[cross]), 1)
    np.add.at(adjacency, (lb[cross], la[cross]), 1)
    sizes = np.bincount(parts, minlength=P)
    order, parent = _tree(adjacency, sizes)
    if len(order) < P:
        raise ValueError(f"the mesh's parts are not connected: parts {sorted(set(range(P)) - set(order))} share no "
                         "edge with the others (a template of one closed surface is needed)")
    return e, la, lb, order, parent


def _joints(template: np.ndarray, faces: np.ndarray, trajectories: np.ndarray, parts: np.ndarray,
            skeleton: Skeleton, edges: tuple, order: list, parent: dict, R: np.ndarray, tr: np.ndarray,
            config: RigConfig, notes: List[str]) -> Dict[int, np.ndarray]:
    """Each non-root part's joint to its parent (3,): the boundary centroid snapped to
    the skeleton, then moved along it to where the parent's and the child's motions
    (``R``, ``tr`` of :func:`part_transforms`) move the joint alike; a note per joint.
    ``edges``: the mesh's edges and their ends' parts (:func:`_part_tree`)."""
    e, la, lb = edges
    graph = mesh_graph(template, faces) if config.joint_search > 0 and config.joint_core > 0 else None
    joint_of: Dict[int, np.ndarray] = {}
    for p in order[1:]:
        q = parent[p]
        sel = ((la == p) & (lb == q)) | ((la == q) & (lb == p))
        boundary = np.unique(e[sel].ravel())
        snapped = _snap(skeleton, template[boundary].mean(0))
        joint_of[p] = snapped
        if config.joint_search > 0:
            cand = _skeleton_points(skeleton, snapped, config.joint_search)
            Rq, tq, Rp, tp = R[:, q], tr[:, q], R[:, p], tr[:, p]
            if config.joint_core > 0:
                Rq, tq = _core_motion(trajectories, template, parts, q, boundary, graph, config.joint_core, Rq, tq)
                Rp, tp = _core_motion(trajectories, template, parts, p, boundary, graph, config.joint_core, Rp, tp)
            A, b = Rq - Rp, tq - tp  # (T, 3, 3), (T, 3)
            cost = np.linalg.norm(np.einsum("tij,sj->tsi", A, cand) + b[:, None], axis=-1).mean(0)
            joint_of[p] = cand[np.argmin(cost)]
            at_centroid = cost[np.argmin(np.linalg.norm(cand - snapped, axis=1))]
            moved = np.linalg.norm(joint_of[p] - snapped)
            notes.append(f"joint of part {p}: {moved:.1f} mm from the boundary centroid (motion mismatch "
                         f"{cost.min():.2f} mm there, {at_centroid:.2f} mm at the centroid)")
    return joint_of


def _bone_frames(template: np.ndarray, parts: np.ndarray, skeleton: Skeleton, order: list, parent: dict,
                 joint_of: Dict[int, np.ndarray]) -> tuple:
    """Per part its bone frame (P, 4, 4) and length (P,): origin at the joint to the
    parent (the root: its skeleton end farthest from its children's joints), x towards
    the part's farthest skeleton point."""
    P = len(order)
    node_part = np.zeros(len(skeleton.nodes), np.int64)
    for n in range(len(skeleton.nodes)):
        mine = parts[skeleton.vertex_node == n]
        node_part[n] = np.bincount(mine).argmax() if len(mine) else -1
    rest = np.tile(np.eye(4), (P, 1, 1))
    lengths = np.zeros(P)
    for p in order:
        pts = skeleton.nodes[node_part == p]
        if len(pts) == 0:
            pts = template[parts == p]
        if parent[p] < 0:
            kids = [joint_of[c] for c in order if parent[c] == p]
            far = np.min([np.linalg.norm(pts - k, axis=1) for k in kids], 0) if kids else np.zeros(len(pts))
            origin = pts[np.argmax(far)]
            target = kids[0] if kids else template[parts == p].mean(0)
        else:
            origin = joint_of[p]
            target = pts[np.argmax(np.linalg.norm(pts - origin, axis=1))]
        axis = target - origin
        if np.linalg.norm(axis) < 1e-6:
            axis = np.linalg.svd(template[parts == p] - template[parts == p].mean(0))[2][0]
        rest[p, :3, :3] = _frame(axis)
        rest[p, :3, 3] = origin
        lengths[p] = float(np.linalg.norm(target - origin))
    return rest, lengths


def _joint_slots(R: np.ndarray, rest: np.ndarray, order: list, parent: dict, bone_of_part: np.ndarray,
                 config: RigConfig, notes: List[str]) -> tuple:
    """Axes (P, 3, 3), used slots (P, 3) and limits (P, 3, 2) of each bone's joint from
    the parts' relative rotations (``R`` of :func:`part_transforms`): the principal
    directions of the rotation vectors; a note per joint."""
    P = len(order)
    slot_axes = np.zeros((P, 3, 3))
    slot_used = np.zeros((P, 3), bool)
    slot_limits = np.zeros((P, 3, 2))
    margin = np.deg2rad(config.limit_margin_deg)
    for p in order[1:]:
        q = parent[p]
        rel = np.swapaxes(R[:, q], 1, 2) @ R[:, p]  # child in the parent's rest frame
        w = so3_log(torch.as_tensor(rel)).numpy()  # (T, 3)
        _, s, vt = np.linalg.svd(w, full_matrices=False)
        used = max(1, int((s >= config.axis_ratio * s[0]).sum())) if s[0] > 0 else 1
        b = bone_of_part[p]
        for k in range(used):
            a = vt[k]
            ang = w @ a
            if ang.mean() < 0:  # positive angles along the main direction of the motion
                a, ang = -a, -ang
            slot_axes[b, k] = rest[p, :3, :3].T @ a  # in the bone frame
            slot_used[b, k] = True
            lo, hi = float(ang.min()), float(ang.max())
            slot_limits[b, k] = [max(lo - margin, -np.pi), min(hi + margin, np.pi)]
        rms = np.round(np.rad2deg(s / np.sqrt(len(w))), 1).tolist()
        notes.append(f"joint {bone_of_part[q]}->{b}: {used} DoF (RMS angles {rms} deg)")
    return slot_axes, slot_used, slot_limits


def build_rig(template: np.ndarray, faces: np.ndarray, trajectories: np.ndarray, parts: np.ndarray, name: str,
              config: RigConfig = RigConfig(), source: str = "", skeleton: Optional[Skeleton] = None) -> Rig:
    """The rigged model of the template (module docstring). ``trajectories``: (T, V, 3)
    the tracked vertices; ``parts``: (V,) the motion segmentation."""
    template = np.asarray(template, np.float64)
    faces = np.asarray(faces, np.int64)
    parts = np.asarray(parts, np.int64)
    P = int(parts.max()) + 1
    skeleton = curve_skeleton(template, faces) if skeleton is None else skeleton
    deg = skeleton.degree()
    ends, branches = skeleton.nodes[deg == 1], skeleton.nodes[deg >= 3]
    notes: List[str] = []
    if P == 1:
        notes.append("one part: the object did not bend in the sequence; the model is rigid")
        assets = rigid_assets(name, template, faces, source=source)
        return Rig(assets, parts, np.zeros(1, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64), ends, branches,
                   skeleton, notes)

    e, la, lb, order, parent = _part_tree(faces, parts, P)
    bone_of_part = np.empty(P, np.int64)
    bone_of_part[order] = np.arange(P)
    R, tr = part_transforms(trajectories, template, parts)
    joint_of = _joints(template, faces, trajectories, parts, skeleton, (e, la, lb), order, parent, R, tr, config,
                       notes)
    rest, lengths = _bone_frames(template, parts, skeleton, order, parent, joint_of)
    slot_axes, slot_used, slot_limits = _joint_slots(R, rest, order, parent, bone_of_part, config, notes)

    skin_index, skin_weight = skin_weights(template, faces, bone_of_part[parts], P, config.skin_width,
                                           config.skin_bones)
    parents = np.array([-1 if parent[p] < 0 else bone_of_part[parent[p]] for p in order], np.int64)
    assets = ModelAssets(
        name=name, kind="object", side=None, bone_names=[f"part{k}" for k in range(P)], parents=parents,
        rest_transforms=rest[order], bone_lengths=lengths[order], vertices=template, faces=faces,
        skin_index=skin_index, skin_weight=skin_weight, slot_axes=slot_axes, slot_used=slot_used,
        slot_limits=slot_limits, source=source)
    joints = np.stack([joint_of[p] for p in order[1:]])
    dofs = slot_used.sum(1)[1:]
    return Rig(assets, parts, bone_of_part, joints, dofs, ends, branches, skeleton, notes)


def fit_rig(model, vertices: np.ndarray, parts: Optional[np.ndarray] = None, iterations: int = 30,
            samples: int = 2000) -> torch.Tensor:
    """theta (D,) of ``model`` (an :class:`~torchhand.model.articulated.ArticulatedModel`,
    float64) that best poses its vertices onto (V, 3) ``vertices`` (same order): the
    root from a Kabsch fit of the root bone's vertices, then the library's LM on a
    subset of the vertices."""
    target = torch.as_tensor(np.asarray(vertices, np.float64))
    rest = model.vertices_rest.double()
    V = len(rest)
    root_ids = torch.nonzero(model.vertex_bone == 0)[:, 0]
    R, t = kabsch_batch(rest[root_ids], target[root_ids][None])
    th = model.zero_pose(1).double()
    th[0, 3:6] = so3_log(R[0])
    # the root rotates about the rigging-pose origin of bone 0: x' = R (x - o) + o + t_theta
    o = model.rest_transforms[0, :3, 3].double()
    th[0, :3] = t[0] + R[0] @ o - o
    ids = torch.as_tensor(np.linspace(0, V - 1, min(samples, V)).round().astype(np.int64))

    def residuals(theta, with_jacobian):
        out = model(theta, validate=False)
        r = (out.vertices[:, ids] - target[ids]).reshape(theta.shape[0], -1)
        J = model.jacobian(theta, ids).reshape(theta.shape[0], -1, theta.shape[1]) if with_jacobian else None
        return r, J

    res = levenberg_marquardt(residuals, th, model.lower.double(), model.upper.double(), max_iterations=iterations)
    return res.theta[0]
