"""Collision detection between the triangles of posed meshes, and the conic distance
fields that penalise it (thesis Ch. 4.2.2.4, Eq. 4.9-4.13; Ballan et al. 2012, Sec. 4.2).

Detection is batched over B posed copies of one mesh (the scene's triangles):

1. Broad phase: a bounding-volume hierarchy per batch element. Triangles are sorted
   by the Morton code of their centroid and grouped into leaves of ``leaf_size``;
   the tree is the complete binary tree over the sorted leaves, so every level is
   one ``amin``/``amax`` over pairs of the level below (no pointers). The tree is
   traversed against itself one level at a time: the frontier of overlapping node
   pairs is a tensor, expanded to the children pairs whose boxes overlap.
2. Part pruning: every triangle belongs to a part (a bone of one model). Each node
   carries the bit set of its parts and of the parts they may collide with, so node
   pairs that can only hold excluded part pairs (the same bone, a bone and its
   parent) are dropped as early as box-disjoint ones.
3. Narrow phase: the exact triangle-triangle test by separating axes (the two face
   normals, the nine edge-edge cross products and the six in-plane edge normals,
   as in PQP/FCL), vectorised over all candidate pairs. Touching counts as
   intersecting. Triangles of one model that share a vertex are never reported.

The penalty (Eq. 4.9-4.11): for a colliding pair (f_s, f_t) the vertices of f_t
are intruders in the conic distance field of the receiver f_s, and vice versa.
The cone's axis is the receiver's normal through its circumcentre o, its radius
at the triangle is the circumradius r, and its apex lies sigma in front of the
triangle. ``Phi`` is the distance of a vertex from the axis in units of the cone's
radius at the vertex's height, ``Upsilon`` grows linearly with the depth behind
the triangle, and ``Psi = ((1 - Phi) Upsilon)^2`` inside the cone, 0 outside.
Eq. 4.13 (used by the tracker) sums ``Psi^2`` over the intruders of every pair;
Eq. 4.12 gives the same energy as 3-vectors ``Psi n_v`` along the vertex normal.

Distances are in the scene's units (mm for the shipped models), so sigma = 0.5
is 0.5 mm: the thesis does not state the unit; in mm, a vertex starts to be
pushed back half a millimetre before it reaches the receiving triangle.
"""

from __future__ import annotations

import copy
from typing import List, NamedTuple, Optional, Sequence

import torch

from torchhand.core.check import check_tensor

__all__ = [
    "CollisionMesh",
    "CollisionPairs",
    "IntruderSet",
    "detect_collisions",
    "triangles_intersect",
    "conic_field",
    "intruders",
    "collision_energy",
    "collision_loss",
    "pair_sets",
]

#: sigma of Eq. 4.10-4.11 (thesis: 0.5)
DEFAULT_SIGMA = 0.5
_WORD_BITS = 62  # part bits per int64 word (the sign bit stays clear)


class CollisionPairs(NamedTuple):
    """Intersecting triangle pairs of a batch.

    batch: (N,) int64 batch element; face_s, face_t: (N,) int64 face indices into the
    mesh's faces with ``face_s < face_t``; sorted by batch element.
    """

    batch: torch.Tensor
    face_s: torch.Tensor
    face_t: torch.Tensor

    def __len__(self) -> int:
        return int(self.batch.shape[0])

    def counts(self, batch_size: int) -> torch.Tensor:
        """(B,) number of pairs per batch element."""
        return torch.bincount(self.batch, minlength=batch_size)


class CollisionMesh:
    """The static part of collision detection: faces, their parts and which part
    pairs are never tested.

    Args:
        faces: (F, 3) int64 vertex indices.
        face_part: (F,) int64 part of each face, in [0, P).
        excluded: (P, P) bool, True where two parts are not tested against each
            other (symmetric; the diagonal is the self-collision of a rigid part).
        face_model: (F,) int64 model of each face (default: all one model); faces of
            the same model that share a vertex are never reported.
    """

    def __init__(self, faces: torch.Tensor, face_part: torch.Tensor, excluded: torch.Tensor,
                 face_model: Optional[torch.Tensor] = None, rest_vertices: Optional[torch.Tensor] = None,
                 leaf_size: int = 2):
        check_tensor(faces, "faces", ("F", 3), finite=True)
        F = faces.shape[0]
        check_tensor(face_part, "face_part", (F,), finite=True)
        P = int(face_part.max()) + 1 if F else 0
        check_tensor(excluded, "excluded", (P, P), finite=True)
        if excluded.dtype != torch.bool:
            raise TypeError(f"excluded must be a bool tensor, got {excluded.dtype}")
        if not bool((excluded == excluded.T).all()):
            raise ValueError("excluded must be symmetric")
        self.faces = faces.long()
        self.face_part = face_part.long()
        self.face_model = torch.zeros_like(self.face_part) if face_model is None else face_model.long()
        self.excluded = excluded
        self.num_parts = P
        self.num_vertices_needed = int(self.faces.max()) + 1 if F else 0
        # bit sets: the part of each face, and the parts it may collide with
        words = max(1, -(-P // _WORD_BITS))
        bit = torch.arange(P, device=faces.device)
        onehot = torch.zeros(P, words, dtype=torch.int64, device=faces.device)
        onehot[bit, bit // _WORD_BITS] = torch.bitwise_left_shift(torch.ones_like(bit), bit % _WORD_BITS)
        allowed = (~excluded).long()[:, :, None] * onehot[None]  # (P, P, words)
        allowed_bits = _or_reduce(allowed, dim=1)  # (P, words)
        self.face_bits = onehot[self.face_part]  # (F, words)
        self.face_allowed = allowed_bits[self.face_part]
        # The hierarchy's topology is fixed: faces sorted by part, then by the Morton
        # code of their rest-pose centroid. A part moves (nearly) rigidly, so this
        # order keeps its locality at every pose and each pose only refits the boxes
        # (the approach for deformable meshes of Teschner et al. 2004); grouping by
        # part also makes the part bit sets of the nodes small.
        if leaf_size < 1 or leaf_size & (leaf_size - 1):
            raise ValueError(f"leaf_size must be a power of two, got {leaf_size}")
        self.leaf_size = leaf_size
        key = self.face_part * (1 << 31)
        if rest_vertices is not None:
            check_tensor(rest_vertices, "rest_vertices", ("V", 3), finite=True)
            cent = rest_vertices.detach()[self.faces].mean(1)[None]
            key = key + _morton_codes(cent, torch.ones(cent.shape[:2], dtype=torch.bool, device=cent.device))[0]
        order = torch.argsort(key * F + torch.arange(F, device=key.device))
        n_leaves = max(1, -(-F // leaf_size))
        pad = n_leaves * leaf_size - F
        self.slot_face = torch.cat([order, order.new_full((pad,), -1)])  # -1: empty slot
        # faces of zero area on the rest mesh have no normal and no cone: never tested
        degenerate = torch.zeros(F, dtype=torch.bool, device=faces.device)
        if rest_vertices is not None:
            t = rest_vertices.detach()[self.faces]
            area2 = torch.linalg.vector_norm(torch.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0], dim=-1), dim=-1)
            degenerate = area2 <= 1e-10 * (t.amax(1) - t.amin(1)).amax(-1).square()
        self.slot_empty = torch.cat([degenerate[order], degenerate.new_ones(pad)])
        # The tree over the leaves: level sizes halve (rounding up; an odd level gets
        # one empty node), node k of a level has children 2k and 2k + 1 below.
        sizes = [n_leaves]
        while sizes[-1] > 1:
            sizes.append(-(-sizes[-1] // 2))
        self.level_sizes = sizes[::-1]  # root first
        # part bit sets of every node (static), root level first
        gather = torch.where(self.slot_face >= 0, self.slot_face, F)  # empty slots read a zero row
        zero = self.face_bits.new_zeros(1, words)
        bits = _or_reduce(torch.cat([self.face_bits, zero])[gather].view(n_leaves, leaf_size, words), 1)
        allow = _or_reduce(torch.cat([self.face_allowed, zero])[gather].view(n_leaves, leaf_size, words), 1)
        self.node_bits = _levels(bits, lambda x, y: x | y, 0)
        self.node_allowed = _levels(allow, lambda x, y: x | y, 0)
        self._copies = {faces.device: self}

    _TENSORS = ("faces", "face_part", "face_model", "excluded", "face_bits", "face_allowed", "slot_face",
                "slot_empty")

    def to(self, device) -> "CollisionMesh":
        """This mesh with its tensors on ``device`` (copies are cached per device)."""
        device = torch.device(device)
        for d, m in self._copies.items():
            if d.type == device.type and (device.index is None or d.index == device.index):
                return m
        other = copy.copy(self)
        for name in self._TENSORS:
            setattr(other, name, getattr(self, name).to(device))
        other.node_bits = [x.to(device) for x in self.node_bits]
        other.node_allowed = [x.to(device) for x in self.node_allowed]
        self._copies[device] = other
        return other

    @classmethod
    def from_scene(cls, scene, self_collisions: bool = True, models: Optional[Sequence[str]] = None,
                   leaf_size: int = 2) -> "CollisionMesh":
        """Collision mesh of a :class:`~torchhand.model.scene.Scene`.

        Parts are the bones of every model (a face belongs to the bone of its first
        vertex, as in rendering). Within a model, a bone is not tested against
        itself, its parent, or a bone whose skin touches its own on the rest mesh
        (the faces of both share a vertex: the palm's metacarpals, the webbing
        between neighbouring fingers): there the skin is continuous, and at every
        pose the two surfaces meet along a seam that would be reported as a
        collision. Fingers are tested against the palm and each other from the
        middle phalanx on. With ``self_collisions=False`` no two bones of one model
        are tested. Models are always tested against each other; ``models``
        restricts detection to some of them (faces keep their scene indices).
        """
        offsets, parents, model_of_part = [], [], []
        start = 0
        for k, m in enumerate(scene.models):
            offsets.append(start)
            parents.append(torch.where(m.parents >= 0, m.parents + start, -1).cpu())
            model_of_part.append(torch.full((m.num_bones,), k, dtype=torch.int64))
            start += m.num_bones
        parents_all = torch.cat(parents)
        model_of_part = torch.cat(model_of_part)
        P = start
        faces = scene.faces.cpu()
        face_part = (scene.face_bone_id + torch.tensor(offsets, device=scene.faces.device)[scene.face_model_id]).cpu()
        if self_collisions:
            excluded = torch.eye(P, dtype=torch.bool)
            child = torch.nonzero(parents_all >= 0)[:, 0]
            excluded[child, parents_all[child]] = True
            excluded[parents_all[child], child] = True
            touching = torch.zeros(scene.num_vertices, P)  # vertex x part incidence on the rest mesh
            for k in range(3):
                touching[faces[:, k], face_part] = 1.0
            excluded |= (touching.T @ touching) > 0
        else:
            excluded = model_of_part[:, None] == model_of_part[None, :]
        if models is not None:
            unknown = [n for n in models if n not in scene.names]
            if unknown:
                raise KeyError(f"scene has no models {unknown}; models: {scene.names}")
            keep = torch.tensor([n in models for n in scene.names])[model_of_part]
            excluded |= ~(keep[:, None] & keep[None, :])
        dev = scene.faces.device
        with torch.no_grad():
            rest = scene(scene.zero_pose().to(scene.lower.dtype), validate=False).vertices[0]
        return cls(scene.faces, face_part.to(dev), excluded.to(dev), scene.face_model_id, rest, leaf_size)


def _or_reduce(x: torch.Tensor, dim: int) -> torch.Tensor:
    """Bitwise OR over one dimension (torch has no OR reduction): pairwise halving."""
    x = x.movedim(dim, 0)
    if x.shape[0] == 0:
        return torch.zeros_like(x).sum(0)
    while x.shape[0] > 1:
        if x.shape[0] % 2:
            x = torch.cat([x, torch.zeros_like(x[:1])])
        x = x[0::2] | x[1::2]
    return x[0]


def _levels(leaves: torch.Tensor, combine, empty, dim: int = 0) -> List[torch.Tensor]:
    """Node values of every tree level, root first, from the leaves' values along
    ``dim``: parents combine child pairs; an odd level is padded with ``empty``."""
    out = [leaves]
    x = leaves.movedim(dim, 0)
    while x.shape[0] > 1:
        if x.shape[0] % 2:
            x = torch.cat([x, torch.full_like(x[:1], empty)])
        x = combine(x[0::2], x[1::2])
        out.append(x.movedim(0, dim))
    return out[::-1]


def _morton_codes(points: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """30-bit Morton codes of points (B, F, 3) quantised in each batch element's box."""
    big = torch.finfo(points.dtype).max
    lo = torch.where(valid[..., None], points, big).amin(1, keepdim=True)
    hi = torch.where(valid[..., None], points, -big).amax(1, keepdim=True)
    q = ((points - lo) / (hi - lo).clamp_min(1e-12) * 1023).clamp(0, 1023).nan_to_num(0).long()

    def spread(v):  # 10 bits -> every third bit
        v = (v | (v << 16)) & 0x030000FF
        v = (v | (v << 8)) & 0x0300F00F
        v = (v | (v << 4)) & 0x030C30C3
        return (v | (v << 2)) & 0x09249249

    code = (spread(q[..., 0]) << 2) | (spread(q[..., 1]) << 1) | spread(q[..., 2])
    return torch.where(valid, code, 1 << 31)  # degenerate faces sort last


def _box_rows(lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """(N, 6) rows of (lo xyz, hi xyz) from (3, N) bounds."""
    return torch.cat([lo, hi]).T.contiguous()


def _boxes_overlap(boxes: torch.Tensor, i: torch.Tensor, j: torch.Tensor) -> torch.Tensor:
    """Whether boxes i and j (M,) of :func:`_box_rows` overlap."""
    a, b = boxes.index_select(0, i), boxes.index_select(0, j)
    return ((a[:, :3] <= b[:, 3:]) & (b[:, :3] <= a[:, 3:])).all(-1)


def _bits_meet(allowed: torch.Tensor, bits: torch.Tensor) -> torch.Tensor:
    return ((allowed & bits) != 0).any(-1)


def detect_collisions(vertices: torch.Tensor, mesh: CollisionMesh) -> CollisionPairs:
    """All intersecting triangle pairs of each posed mesh, except excluded part pairs.

    Args:
        vertices: (B, V, 3) posed vertices (finite).
        mesh: :class:`CollisionMesh` with faces indexing V.
    Returns:
        :class:`CollisionPairs`. Faces of zero area on the rest mesh are never tested
        (they have no normal and no cone); a face that degenerates at some pose is
        still tested, and as a receiver adds no penalty (:func:`conic_field`).
    """
    check_tensor(vertices, "vertices", ("B", "V", 3), finite=True)
    if mesh.num_vertices_needed > vertices.shape[1]:
        raise ValueError(f"faces index vertex {mesh.num_vertices_needed - 1} but vertices has {vertices.shape[1]}")
    B, F, dev = vertices.shape[0], mesh.faces.shape[0], vertices.device
    empty = torch.zeros(0, dtype=torch.int64, device=dev)
    if F < 2 or B == 0:
        return CollisionPairs(empty, empty, empty)
    mesh = mesh.to(dev)
    leaf_size, sizes = mesh.leaf_size, mesh.level_sizes
    n_leaves = sizes[-1]
    with torch.no_grad():
        slo, shi = _slot_boxes(vertices, mesh)
        # box levels of the tree, root first, flattened over the batch: node k of
        # element b on a level of n nodes is row b * n + k of the level's box rows
        # (single-index gathers are much faster than (b, k) indexing)
        lo_leaf = slo.view(3, B, n_leaves, leaf_size).amin(-1)
        hi_leaf = shi.view(3, B, n_leaves, leaf_size).amax(-1)
        boxes = [_box_rows(lo.reshape(3, -1), hi.reshape(3, -1))
                 for lo, hi in zip(_levels(lo_leaf, torch.minimum, float("inf"), dim=2),
                                   _levels(hi_leaf, torch.maximum, float("-inf"), dim=2))]
        i, j = _overlapping_leaves(mesh, boxes, B)
        return _intersecting_faces(vertices, mesh, i, j, slo, shi)


def _slot_boxes(vertices: torch.Tensor, mesh: CollisionMesh) -> tuple[torch.Tensor, torch.Tensor]:
    """The refit of :func:`detect_collisions`: (3, B, slots) lower and upper corners of
    the boxes of the faces in the static slot order, coordinates first; empty slots (and
    degenerate faces) get empty boxes (+inf, -inf)."""
    B, slot_face = vertices.shape[0], mesh.slot_face
    slots = slot_face.shape[0]
    corners = mesh.faces.index_select(0, slot_face.clamp_min(0)).T.reshape(-1)  # (3 * slots,) corner-major
    base = (torch.arange(B, device=vertices.device) * vertices.shape[1])[:, None]
    rows = vertices.detach().reshape(-1, 3).index_select(0, (base + corners).reshape(-1))  # row gathers are fast
    xyz = rows.view(B, 3, slots, 3).permute(3, 0, 1, 2)  # (xyz, B, corner, slot)
    slo = torch.minimum(torch.minimum(xyz[:, :, 0], xyz[:, :, 1]), xyz[:, :, 2])
    shi = torch.maximum(torch.maximum(xyz[:, :, 0], xyz[:, :, 1]), xyz[:, :, 2])
    empty_slot = mesh.slot_empty
    slo = slo.masked_fill(empty_slot, float("inf"))
    shi = shi.masked_fill(empty_slot, float("-inf"))
    return slo, shi


def _overlapping_leaves(mesh: CollisionMesh, boxes: list, B: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Simultaneous traversal of the tree against itself, one level at a time, from the
    deepest level of at most 64 nodes (all its pairs are tested); part bit sets prune
    first (static, cheap), boxes second. ``boxes``: the box rows of each level, root
    first. Returns the pairs (i, j) of leaves (flat rows b * n_leaves + k, i <= j)
    whose boxes overlap."""
    sizes, dev = mesh.level_sizes, mesh.faces.device
    start = max(k for k, n in enumerate(sizes) if n <= 64)
    n0 = sizes[start]
    ti, tj = torch.triu_indices(n0, n0, device=dev)
    off = (torch.arange(B, device=dev) * n0)[:, None]
    i, j = (off + ti).reshape(-1), (off + tj).reshape(-1)
    ci = torch.tensor([0, 0, 1, 1], device=dev)
    cj = torch.tensor([0, 1, 0, 1], device=dev)
    for level in range(start, len(sizes)):
        n = sizes[level]
        allow, bits = mesh.node_allowed[level], mesh.node_bits[level]
        keep = _bits_meet(allow.index_select(0, i % n), bits.index_select(0, j % n))
        keep &= _boxes_overlap(boxes[level], i, j)
        sel = torch.nonzero(keep)[:, 0]
        i, j = i.index_select(0, sel), j.index_select(0, sel)
        if level + 1 < len(sizes):  # node (b, k) has children (b, 2k), (b, 2k + 1) below
            m = sizes[level + 1]
            bi = torch.div(i, n, rounding_mode="floor")
            ki = (2 * (i - bi * n))[:, None] + ci
            kj = (2 * (j - bi * n))[:, None] + cj
            # self pairs (i == j) keep each child pair once; the last node of an
            # odd level has one child
            ok = (ki <= kj) & (kj < m)
            sel = torch.nonzero(ok.reshape(-1))[:, 0]
            base = (bi * m)[:, None].expand(-1, 4).reshape(-1).index_select(0, sel)
            i = base + ki.reshape(-1).index_select(0, sel)
            j = base + kj.reshape(-1).index_select(0, sel)
    return i, j


def _intersecting_faces(vertices: torch.Tensor, mesh: CollisionMesh, i: torch.Tensor, j: torch.Tensor,
                        slo: torch.Tensor, shi: torch.Tensor) -> CollisionPairs:
    """The face pairs of the leaf pairs (i, j) whose boxes (``slo``, ``shi`` of
    :func:`_slot_boxes`) overlap, less the excluded part pairs and the faces sharing a
    vertex, whose triangles intersect; sorted by (b, s, t)."""
    faces, leaf_size, slot_face = mesh.faces, mesh.leaf_size, mesh.slot_face
    slots, F, dev = slot_face.shape[0], faces.shape[0], vertices.device
    # leaf pairs -> pairs of slots (flat columns b * slots + s)
    a = torch.arange(leaf_size, device=dev)
    si = (i[:, None, None] * leaf_size + a[None, :, None]).expand(-1, leaf_size, leaf_size).reshape(-1)
    sj = (j[:, None, None] * leaf_size + a[None, None, :]).expand(-1, leaf_size, leaf_size).reshape(-1)
    slot_boxes = _box_rows(slo.reshape(3, -1), shi.reshape(3, -1))
    keep = (si < sj) & _boxes_overlap(slot_boxes, si, sj)
    sel = torch.nonzero(keep)[:, 0]
    si, sj = si.index_select(0, sel), sj.index_select(0, sel)
    b = torch.div(si, slots, rounding_mode="floor")
    fs, ft = slot_face.index_select(0, si - b * slots), slot_face.index_select(0, sj - b * slots)
    part = mesh.face_part
    pa, pb = part.index_select(0, fs), part.index_select(0, ft)
    keep = ~mesh.excluded.reshape(-1).index_select(0, pa * mesh.num_parts + pb)
    fm = mesh.face_model
    va, vb = faces.index_select(0, fs), faces.index_select(0, ft)
    share = (va[:, :, None] == vb[:, None, :]).any(-1).any(-1) & (fm.index_select(0, fs) == fm.index_select(0, ft))
    sel = torch.nonzero(keep & ~share)[:, 0]
    b, fs, ft = b.index_select(0, sel), fs.index_select(0, sel), ft.index_select(0, sel)
    V = vertices.detach().reshape(-1, 3)
    base = (b * vertices.shape[1])[:, None]
    tri_s = V.index_select(0, (faces.index_select(0, fs) + base).reshape(-1)).view(-1, 3, 3)
    tri_t = V.index_select(0, (faces.index_select(0, ft) + base).reshape(-1)).view(-1, 3, 3)
    hit = triangles_intersect(tri_s, tri_t)
    b, fs, ft = b[hit], fs[hit], ft[hit]
    s, t = torch.minimum(fs, ft), torch.maximum(fs, ft)
    key = (b * F + s) * F + t
    key, perm = torch.sort(key)
    return CollisionPairs(b[perm], s[perm], t[perm])


def triangles_intersect(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Exact test whether closed triangles intersect, by separating axes.

    p, q: (N, 3, 3) triangles (vertex, xyz) -> (N,) bool. The 17 candidate axes are
    both normals, the 9 cross products of their edges and the 6 in-plane normals of
    the edges (which separate coplanar triangles); the triangles are disjoint iff
    the projections on one axis do not overlap. Touching triangles intersect.
    """
    ep = p.roll(-1, 1) - p  # (N, 3, 3) edges
    eq = q.roll(-1, 1) - q
    np_, nq = torch.cross(ep[:, 0], ep[:, 1], dim=-1), torch.cross(eq[:, 0], eq[:, 1], dim=-1)
    cross = torch.cross(ep[:, :, None].expand(-1, 3, 3, 3), eq[:, None].expand(-1, 3, 3, 3), dim=-1).reshape(-1, 9, 3)
    inplane_p = torch.cross(np_[:, None].expand(-1, 3, 3), ep, dim=-1)
    inplane_q = torch.cross(nq[:, None].expand(-1, 3, 3), eq, dim=-1)
    axes = torch.cat([np_[:, None], nq[:, None], cross, inplane_p, inplane_q], 1)  # (N, 17, 3)
    # project relative to p's first vertex, so magnitudes stay small
    o = p[:, :1]
    pp = torch.einsum("nak,nvk->nav", axes, p - o)  # (N, 17, 3)
    qq = torch.einsum("nak,nvk->nav", axes, q - o)
    separated = (pp.amax(-1) < qq.amin(-1)) | (qq.amax(-1) < pp.amin(-1))
    return ~separated.any(-1)


# --------------------------------------------------------------------- penalty
def conic_field(points: torch.Tensor, triangles: torch.Tensor, sigma: float = DEFAULT_SIGMA) -> torch.Tensor:
    """Psi of Eq. 4.9: the conic distance field of each receiving triangle at a point.

    points: (..., 3) intruding vertices; triangles: (..., 3, 3) receivers with
    outward counter-clockwise winding -> (...,) Psi >= 0. Differentiable in both;
    the gradient is finite everywhere (0 outside the cone and on its axis' kink).
    """
    a, b, c = triangles.unbind(-2)
    u, w = b - a, c - a
    m = torch.cross(u, w, dim=-1)
    mm = (m * m).sum(-1, keepdim=True)
    ok = mm > 0  # degenerate receivers have no cone (and must not give NaN gradients)
    mm = torch.where(ok, mm, torch.ones_like(mm))
    # circumcentre o = a + ((|u|^2 w - |w|^2 u) x m) / (2 |m|^2)  (u x w = m)
    rel = torch.cross((u * u).sum(-1, keepdim=True) * w - (w * w).sum(-1, keepdim=True) * u, m, dim=-1) / (2 * mm)
    o = a + rel
    r = _safe_norm(rel)
    n = m / mm.sqrt()
    d = points - o
    x = (n * d).sum(-1)  # height above the triangle's plane
    lateral = _safe_norm(d - x[..., None] * n)
    inside_height = (x < sigma) & ok[..., 0] & (r > 0)
    radius = torch.where(inside_height, r * (1 - x / sigma), torch.ones_like(r))  # > 0 below the apex
    phi = lateral / radius
    upsilon = _upsilon(x, sigma)
    psi = ((1 - phi) * upsilon).square()
    return torch.where(inside_height & (phi < 1), psi, torch.zeros_like(psi))


def _safe_norm(x: torch.Tensor) -> torch.Tensor:
    """Euclidean norm over the last dim with a zero (not NaN) gradient at 0."""
    sq = (x * x).sum(-1)
    pos = sq > 0
    return torch.where(pos, torch.where(pos, sq, torch.ones_like(sq)).sqrt(), torch.zeros_like(sq))


def _upsilon(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Upsilon of Eq. 4.11: linear behind -sigma, quadratic on (-sigma, sigma), 0 beyond."""
    quad = -(1 - 2 * sigma) / (4 * sigma**2) * x.square() - x / (2 * sigma) + (3 - 2 * sigma) / 4
    lin = -x + 1 - sigma
    return torch.where(x <= -sigma, lin, torch.where(x < sigma, quad, torch.zeros_like(x)))


class IntruderSet(NamedTuple):
    """The (intruder vertex, receiving face) rows of a set of collisions: six per pair
    (the three vertices of f_t in the field of f_s, and of f_s in the field of f_t).

    batch: (M,) batch element; vertex: (M,) intruding vertex; face: (M,) receiving face.
    """

    batch: torch.Tensor
    vertex: torch.Tensor
    face: torch.Tensor


def intruders(pairs: CollisionPairs, faces: torch.Tensor) -> IntruderSet:
    """Rows of Eq. 4.12/4.13 for colliding pairs; faces: (F, 3) -> :class:`IntruderSet`."""
    b = pairs.batch.repeat_interleave(6)
    recv = torch.stack([pairs.face_s, pairs.face_t], 1).repeat_interleave(3, 1).reshape(-1)
    intr = torch.cat([faces[pairs.face_t], faces[pairs.face_s]], 1).reshape(-1)
    return IntruderSet(b, intr, recv)


def collision_energy(vertices: torch.Tensor, faces: torch.Tensor, pairs: CollisionPairs,
                     sigma: float = DEFAULT_SIGMA) -> torch.Tensor:
    """E_collision of Eq. 4.13 per batch element, differentiable in ``vertices``.

    vertices: (B, V, 3); faces: (F, 3); pairs: found at (any) pose -> (B,) energy
    ``sum Psi^2`` over the intruders of every pair (Eq. 4.12 has the same value).
    """
    faces = faces.to(vertices.device)
    rows = intruders(pairs, faces)
    psi = conic_field(vertices[rows.batch, rows.vertex], vertices[rows.batch[:, None], faces[rows.face]], sigma)
    return vertices.new_zeros(vertices.shape[0]).index_add(0, rows.batch, psi.square())


def collision_loss(vertices: torch.Tensor, mesh: CollisionMesh, sigma: float = DEFAULT_SIGMA) -> torch.Tensor:
    """Detect collisions at ``vertices`` and return their Eq. 4.13 energy (B,).

    A plain differentiable loss (e.g. for training a pose network): detection runs
    without gradients, the penalty has them, so ``loss.sum().backward()`` pushes the
    intruding vertices out of the receivers' cones. vertices: (B, V, 3).

    The pair set C depends on the pose, so the loss is piecewise smooth: a step can
    bring new triangles into contact and raise it, as in the thesis, where C is
    found again at every iteration.
    """
    pairs = detect_collisions(vertices, mesh)
    return collision_energy(vertices, mesh.faces, pairs, sigma)


def pair_sets(pairs: CollisionPairs, batch_size: int) -> List[set]:
    """Per batch element, the set of (face_s, face_t) tuples (for tests and reports)."""
    out: List[set] = [set() for _ in range(batch_size)]
    for b, s, t in zip(pairs.batch.tolist(), pairs.face_s.tolist(), pairs.face_t.tolist()):
        out[b].add((s, t))
    return out
