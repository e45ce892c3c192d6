"""The fused iteration: the depth terms' rows and Jacobian rows in Warp kernels, and
the normal equations the LM step solves (``TrackerConfig.fused``).

The torch objective (:class:`~torchhand.tracking.objective.Objective`) builds each
term's residuals from many small tensor operations: gathers of the pairs' vertices, the
skinning Jacobian of every pair (:func:`~torchhand.model.skinning.lbs_jacobian`), the
term's projection of it, the scatter into the scene's columns, the stacking of terms.
:class:`FusedObjective` computes the rows of model-to-data (point-to-plane, Eq. 4.7),
data-to-model (Pluecker lines, Eq. 4.8) and free space with one kernel launch per term
(one thread per pair, one code for CPU and CUDA): the thread skins its vertex from the
bone motions G and its skinning weights (Eq. 4.1) and adds, per influence and per DoF
that moves the influence's bone, ``w_k (omega_d x G_k v0 + u_d)`` projected on the
term's rows into its Jacobian rows (the twist form of
:func:`~torchhand.model.skinning.lbs_jacobian`; only the DoFs of its bones' chains).
The LM step then receives J^T J and J^T r per problem
(:class:`~torchhand.optim.levenberg_marquardt.NormalEquations`), one product each; the
priors (a few rows per DoF) keep their torch residuals and add their own products.

Weights and robust losses stay wrappers: :func:`fusable` unwraps ``Weighted`` and
``Robust`` around a term into per-row factors, so the kernels see the same rows the torch
terms give. Terms without a kernel (collisions, salient points, colour terms,
point-to-point model-to-data) are evaluated by torch in the same objective. The fused
path needs float32 and one view per problem; elsewhere the tracker uses the torch
objective. Tests: tests/test_fused.py (rows, Jacobians and tracked θ against the torch
path).
"""

from __future__ import annotations

import functools
from typing import List, NamedTuple, Optional, Sequence

import torch

from torchhand.core.profiling import stage
from torchhand.geometry.warp_kernels import on_torch_stream, require_warp, wp_device
from torchhand.model.scene import Scene, SceneOutput
from torchhand.optim.levenberg_marquardt import NormalEquations, normal_equations
from torchhand.tracking.energies import DataToModel, EnergyTerm, FreeSpace, ModelToData, Prepared, Robust, Weighted
from torchhand.tracking.energies.wrappers import RobustPrepared, WeightedPrepared
from torchhand.tracking.objective import Objective

__all__ = ["FusedObjective", "FusedRows", "fusable", "fused_rows", "supports"]

#: rows per pair of each kernel kind
ROWS = {"plane": 1, "ray": 3, "pixel": 2}


class FusedRows(NamedTuple):
    """One term's pairs as its kernel reads them (B problems, n pairs each).

    Attributes:
        kind: ``"plane"`` (model-to-data), ``"ray"`` (data-to-model) or ``"pixel"``
            (free space).
        vertex: (B, n) int32 scene vertex of each pair.
        a: (B, n, 3) the data point X (plane), the line direction d (ray), (u, v, 0) of
            the image target q (pixel).
        b: (B, n, 3) the model normal (plane), the line moment m (ray), unused (pixel).
        weight: (B, n) the factor of the pair's rows: the mask, robust and term weights
            (and the mm-per-px scale of a pixel pair).
        camera: (B, 4) fx, fy, cx, cy (pixel; zeros otherwise); R (B, 3, 3), t (B, 3):
            world to camera (pixel).
    """

    kind: str
    vertex: torch.Tensor
    a: torch.Tensor
    b: torch.Tensor
    weight: torch.Tensor
    camera: torch.Tensor
    R: torch.Tensor
    t: torch.Tensor


def supports(theta: torch.Tensor, views: int) -> bool:
    """Whether the fused path runs for these problems: float32 and one view each."""
    return theta.dtype == torch.float32 and int(views) == 1


def fusable(term: EnergyTerm, prepared: Prepared, scene: Scene) -> Optional[FusedRows]:
    """The term's prepared pairs as :class:`FusedRows` when a kernel computes its rows
    (model-to-data point-to-plane, data-to-model, free space, each possibly wrapped in
    ``Weighted`` and ``Robust``), else None."""
    factor = 1.0  # (B, 1) or a float: Weighted's sqrt(w); (B, n): Robust's unfolded row weights
    while isinstance(term, (Weighted, Robust)):
        if isinstance(prepared, WeightedPrepared):
            factor = factor * (1.0 if prepared.sqrt_w is None else prepared.sqrt_w)
        elif isinstance(prepared, RobustPrepared):
            if prepared.sqrt_w is not None:
                factor = factor * prepared.sqrt_w
        else:
            return None
        term, prepared = term.term, prepared.inner
    kind = _KINDS.get(type(term))
    if kind is None or (kind == "plane" and term.metric != "point-to-plane"):
        return None
    rows = prepared.rows
    starts = [scene.vertex_slices[n].start for n in scene.names]
    vertex = torch.cat([r[0] + s for r, s in zip(rows, starts)], 1).to(torch.int32)
    B, n = vertex.shape
    mask = torch.cat([r[-1] for r in rows], 1)
    camera, R, t = mask.new_zeros(B, 4), mask.new_zeros(B, 3, 3), mask.new_zeros(B, 3)  # read by pixel pairs only
    if kind == "plane":
        a, b, w = torch.cat([r.X for r in rows], 1), torch.cat([r.normal for r in rows], 1), mask
    elif kind == "ray":
        a, b, w = torch.cat([r.d for r in rows], 1), torch.cat([r.m for r in rows], 1), mask
    else:
        q = torch.cat([r.q for r in rows], 1)
        a, b = torch.cat([q, q.new_zeros(B, n, 1)], -1), mask.new_zeros(B, n, 3)
        w = torch.cat([r.scale for r in rows], 1) * mask
        K = prepared.K
        camera = torch.stack([K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2]], -1)
        R, t = prepared.T_cw[:, :3, :3], prepared.T_cw[:, :3, 3]
    w = w * factor
    c = lambda x: x.to(torch.float32).contiguous()  # noqa: E731
    return FusedRows(kind, vertex.contiguous(), c(a), c(b), c(w), c(camera), c(R), c(t))


_KINDS = {ModelToData: "plane", DataToModel: "ray", FreeSpace: "pixel"}


class _Skin(NamedTuple):
    """A scene's skinning as the kernels read it (Warp arrays, built once per scene and
    device): rest vertices, influences (scene bone ids, weights), and per scene bone the
    scene DoFs that move it (CSR: ``bone_start`` (J + 1,), ``bone_dofs``)."""

    rest: object
    index: object
    weight: object
    bone_start: object
    bone_dofs: object
    tensors: tuple  # the torch tensors behind the arrays (kept alive)


@functools.lru_cache(maxsize=8)
def _skin(scene: Scene, device: torch.device) -> _Skin:
    wp = require_warp()
    rest, index, weight, starts, dofs = [], [], [], [0], []
    K = max(m.skin_index.shape[1] for m in scene.models)
    bone0, dof0 = 0, 0
    for m in scene.models:
        n, k = m.skin_index.shape
        rest.append(m.vertices_rest.float())
        index.append(torch.nn.functional.pad(m.skin_index + bone0, (0, K - k)))
        weight.append(torch.nn.functional.pad(m.skin_weight.float(), (0, K - k)))
        moves = m.descendants[:, m.dof_bone]  # (J, D): DoF d moves bone j ("A" of lbs_jacobian)
        for j in range(m.num_bones):
            d = torch.nonzero(moves[j])[:, 0] + dof0
            dofs.append(d)
            starts.append(starts[-1] + len(d))
        bone0, dof0 = bone0 + m.num_bones, dof0 + m.num_dofs
    t = (torch.cat(rest).contiguous(), torch.cat(index).to(torch.int32).contiguous(),
         torch.cat(weight).contiguous(), torch.tensor(starts, dtype=torch.int32),
         torch.cat(dofs).to(torch.int32).contiguous())
    t = tuple(x.to(device) for x in t)
    return _Skin(wp.from_torch(t[0], dtype=wp.vec3), wp.from_torch(t[1]), wp.from_torch(t[2]), wp.from_torch(t[3]),
                 wp.from_torch(t[4]), t)


@functools.lru_cache(maxsize=1)
def _funcs() -> dict:
    """The kernel's Warp functions: skinning a vertex, the motion of a point by a DoF,
    the rows of a pixel pair, the Jacobian rows of a pair."""
    wp = require_warp()

    @wp.func
    def skin_point(G: wp.array2d(dtype=wp.mat44), b: int, p0: wp.vec3, index: wp.array2d(dtype=wp.int32),
                   weight: wp.array2d(dtype=wp.float32), v: int):
        p = wp.vec3(0.0)
        for k in range(index.shape[1]):
            w = weight[v, k]
            if w != 0.0:
                p = p + w * wp.transform_point(G[b, index[v, k]], p0)
        return p

    @wp.func
    def dof_motion(tw: wp.array3d(dtype=wp.float32), b: int, d: int, x: wp.vec3):
        # d x / d theta_d = omega_d x x + u_d (kinematics.FKResult)
        u = wp.vec3(tw[b, d, 0], tw[b, d, 1], tw[b, d, 2])
        om = wp.vec3(tw[b, d, 3], tw[b, d, 4], tw[b, d, 5])
        return wp.cross(om, x) + u

    @wp.func
    def pixel_rows(b: int, p: wp.vec3, q: wp.vec3, s: float, camera: wp.array2d(dtype=wp.float32),
                   R: wp.array3d(dtype=wp.float32), t: wp.array2d(dtype=wp.float32), base: int,
                   r: wp.array2d(dtype=wp.float32)):
        # (pi(V) - q) s in mm; returns the rows' map of a vertex motion (s Jp R, 2 rows)
        Rm = wp.mat33(R[b, 0, 0], R[b, 0, 1], R[b, 0, 2], R[b, 1, 0], R[b, 1, 1], R[b, 1, 2],
                      R[b, 2, 0], R[b, 2, 1], R[b, 2, 2])
        xc = Rm @ p + wp.vec3(t[b, 0], t[b, 1], t[b, 2])
        z = wp.max(xc[2], 1.0)
        fx = camera[b, 0]
        fy = camera[b, 1]
        r[b, base] = s * (fx * xc[0] / z + camera[b, 2] - q[0])
        r[b, base + 1] = s * (fy * xc[1] / z + camera[b, 3] - q[1])
        jp0 = wp.vec3(fx / z, 0.0, -fx * xc[0] / (z * z))
        jp1 = wp.vec3(0.0, fy / z, -fy * xc[1] / (z * z))
        e0 = s * (wp.transpose(Rm) @ jp0)
        e1 = s * (wp.transpose(Rm) @ jp1)
        return wp.mat33(e0[0], e0[1], e0[2], e1[0], e1[1], e1[2], 0.0, 0.0, 0.0)

    @wp.func
    def jacobian_rows(G: wp.array2d(dtype=wp.mat44), tw: wp.array3d(dtype=wp.float32), b: int, p0: wp.vec3,
                      index: wp.array2d(dtype=wp.int32), weight: wp.array2d(dtype=wp.float32), v: int,
                      bone_start: wp.array(dtype=wp.int32), bone_dofs: wp.array(dtype=wp.int32), E: wp.mat33,
                      rows: int, base: int, J: wp.array3d(dtype=wp.float32)):
        # per influence k and DoF d moving its bone: w_k (omega_d x G_k v0 + u_d), mapped by E
        e0, e1, e2 = E[0], E[1], E[2]
        for k in range(index.shape[1]):
            w = weight[v, k]
            if w == 0.0:
                continue
            j = index[v, k]
            x = wp.transform_point(G[b, j], p0)
            for e in range(bone_start[j], bone_start[j + 1]):
                dof = bone_dofs[e]
                dv = w * dof_motion(tw, b, dof, x)
                J[b, base, dof] = J[b, base, dof] + wp.dot(e0, dv)
                if rows > 1:
                    J[b, base + 1, dof] = J[b, base + 1, dof] + wp.dot(e1, dv)
                if rows > 2:
                    J[b, base + 2, dof] = J[b, base + 2, dof] + wp.dot(e2, dv)

    return {"skin_point": skin_point, "pixel_rows": pixel_rows, "jacobian_rows": jacobian_rows}


@functools.lru_cache(maxsize=1)
def _kernels() -> dict:
    wp = require_warp()
    f = _funcs()
    skin_point, pixel_rows, jacobian_rows = f["skin_point"], f["pixel_rows"], f["jacobian_rows"]

    @wp.kernel(enable_backward=False)
    def rows_kernel(G: wp.array2d(dtype=wp.mat44), tw: wp.array3d(dtype=wp.float32),
                    rest: wp.array(dtype=wp.vec3), index: wp.array2d(dtype=wp.int32),
                    weight: wp.array2d(dtype=wp.float32), bone_start: wp.array(dtype=wp.int32),
                    bone_dofs: wp.array(dtype=wp.int32), kinds: wp.array(dtype=wp.int32),
                    first: wp.array(dtype=wp.int32), vertex: wp.array2d(dtype=wp.int32),
                    a: wp.array2d(dtype=wp.vec3), bb: wp.array2d(dtype=wp.vec3), pw: wp.array2d(dtype=wp.float32),
                    camera: wp.array2d(dtype=wp.float32), R: wp.array3d(dtype=wp.float32),
                    t: wp.array2d(dtype=wp.float32), jacobian: int,
                    r: wp.array2d(dtype=wp.float32), J: wp.array3d(dtype=wp.float32)):
        b, i = wp.tid()
        kind = kinds[i]
        base = first[i]  # the pair's first row
        v = vertex[b, i]
        s = pw[b, i]
        p0 = rest[v]
        p = skin_point(G, b, p0, index, weight, v)
        E = wp.mat33(0.0)  # the rows' linear map of a vertex motion
        rows = 1
        if kind == 0:  # point-to-plane: n^T (V - X)   (Eq. 4.7)
            n = bb[b, i]
            r[b, base] = s * wp.dot(n, p - a[b, i])
            E = wp.mat33(s * n[0], s * n[1], s * n[2], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        elif kind == 1:  # Pluecker line: V x d - m   (Eq. 4.8); d(V x d) = dV x d = -[d]x dV
            d = a[b, i]
            c = wp.cross(p, d) - bb[b, i]
            r[b, base] = s * c[0]
            r[b, base + 1] = s * c[1]
            r[b, base + 2] = s * c[2]
            E = s * wp.mat33(0.0, d[2], -d[1], -d[2], 0.0, d[0], d[1], -d[0], 0.0)
            rows = 3
        else:  # a pixel pair (free space)
            E = pixel_rows(b, p, a[b, i], s, camera, R, t, base, r)
            rows = 2
        if jacobian != 0 and s != 0.0:
            jacobian_rows(G, tw, b, p0, index, weight, v, bone_start, bone_dofs, E, rows, base, J)

    return {"rows": rows_kernel}


_KIND_IDS = {"plane": 0, "ray": 1, "pixel": 2}


class _Launch:
    """The pairs of several terms as one launch of the rows kernel: their arrays
    concatenated along the pairs (each pair's kind and first row kept), converted to Warp
    arrays once, for every evaluation of an LM step."""

    def __init__(self, scene: Scene, terms: Sequence[FusedRows]):
        self.scene, self.rows = scene, sum(ROWS[f.kind] * f.vertex.shape[1] for f in terms)
        self.pairs = sum(f.vertex.shape[1] for f in terms)
        if not self.pairs:
            return
        wp = require_warp()
        dev = terms[0].vertex.device
        kind = torch.cat([torch.full((f.vertex.shape[1],), _KIND_IDS[f.kind], dtype=torch.int32) for f in terms])
        starts = [0]
        for f in terms:
            starts.append(starts[-1] + ROWS[f.kind] * f.vertex.shape[1])
        first = torch.cat([s + ROWS[f.kind] * torch.arange(f.vertex.shape[1], dtype=torch.int32)
                           for s, f in zip(starts, terms)])
        pixel = [f for f in terms if f.kind == "pixel"] or terms[:1]  # the cameras: the problems' own, one per term
        cat = lambda name: torch.cat([getattr(f, name) for f in terms], 1).contiguous()  # noqa: E731
        self._keep = (kind.to(dev), first.to(dev), cat("vertex"), cat("a"), cat("b"), cat("weight"),
                      pixel[0].camera, pixel[0].R.contiguous(), pixel[0].t)
        k = self._keep
        self.skin = _skin(scene, dev)
        self.static = [wp.from_torch(x, dtype=wp.vec3) if i in (3, 4) else wp.from_torch(x) for i, x in enumerate(k)]
        self.device = dev

    def __call__(self, posed: SceneOutput, jacobian: bool) -> tuple:
        """(r (B, m) float32, J (B, m, D) float32 or None) at the pose of ``posed``."""
        G = torch.cat([o.G for o in posed.models], 1).to(torch.float32).contiguous()
        B, dev = G.shape[0], G.device
        r = torch.zeros(B, self.rows, dtype=torch.float32, device=dev)
        J = torch.zeros(B, self.rows, self.scene.num_dofs, dtype=torch.float32, device=dev) if jacobian else None
        if not self.pairs:
            return r, J
        wp = require_warp()
        tw = torch.cat([o.twists for o in posed.models], 1).to(torch.float32).contiguous()
        sk = self.skin
        with on_torch_stream(dev):
            wp.launch(_kernels()["rows"], dim=(B, self.pairs), device=wp_device(dev),
                      inputs=[wp.from_torch(G, dtype=wp.mat44), wp.from_torch(tw), sk.rest, sk.index, sk.weight,
                              sk.bone_start, sk.bone_dofs, *self.static, int(jacobian), wp.from_torch(r),
                              wp.from_torch(J if jacobian else r.new_zeros(1, 1, 1))])
        return r, J


def fused_rows(scene: Scene, posed: SceneOutput, terms: Sequence[FusedRows], jacobian: bool) -> tuple:
    """The rows of ``terms`` at the pose of ``posed`` (its bone motions and twists): (r
    (B, m) float32, J (B, m, D) float32 or None), the terms' rows stacked in order."""
    return _Launch(scene, terms)(posed, jacobian)


class FusedObjective(Objective):
    """:class:`~torchhand.tracking.objective.Objective` whose depth terms' rows come from
    the fused kernels and whose :meth:`linearize` gives the LM step the normal equations
    (arguments as ``Objective``; float32, one view per problem: :func:`supports`)."""

    def __init__(self, scene: Scene, terms: Sequence[EnergyTerm], prepared: Sequence[Prepared], posed: SceneOutput,
                 views: int = 1):
        super().__init__(scene, terms, prepared, posed, views)
        if int(views) != 1:
            raise ValueError(f"the fused objective takes one view per problem, got {views} (use Objective)")
        rows = [fusable(t, p, scene) for t, p in zip(self.terms, self.prepared)]
        self.fused: List[FusedRows] = [f for f in rows if f is not None]
        self.rest = [(t, p) for t, p, f in zip(self.terms, self.prepared, rows) if f is None]
        self._launch = _Launch(scene, self.fused)

    def _torch_rows(self, theta: torch.Tensor, posed: SceneOutput, jacobian: bool) -> tuple:
        parts = []
        for t, p in self.rest:
            with stage(f"{'rows+J' if jacobian else 'rows'}:{t.name}"):
                parts.append(t.residuals(theta, posed, p, jacobian))
        r = torch.cat([x.r for x in parts], 1) if parts else theta.new_zeros(theta.shape[0], 0)
        J = (torch.cat([x.J for x in parts], 1) if parts else theta.new_zeros(theta.shape[0], 0, theta.shape[1])) \
            if jacobian else None
        return r, J

    def linearize(self, theta: torch.Tensor) -> NormalEquations:
        with stage("rows+J:fused"):
            r, J = self._launch(self.current, True)
        rt, Jt = self._torch_rows(theta, self.current, True)
        with stage("normal equations"):
            a, b = normal_equations(r.to(theta.dtype), J.to(theta.dtype)), normal_equations(rt, Jt)
            return NormalEquations(a.H + b.H, a.g + b.g, a.cost + b.cost)

    def evaluate(self, theta: torch.Tensor) -> torch.Tensor:
        with stage("pose"):
            self.candidate = self.scene(theta, validate=False)
        with stage("rows:fused"):
            r, _ = self._launch(self.candidate, False)
        return torch.cat([r.to(theta.dtype), self._torch_rows(theta, self.candidate, False)[0]], 1)
