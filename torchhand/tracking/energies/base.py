"""The one interface every energy term of the objective (thesis Eq. 4.5) implements.

A term is prepared once per outer iteration of Algorithm 1 (it finds its
correspondences at the current pose) and then evaluated, with the correspondences
fixed, at any theta the solver tries::

    prep = term.prepare(state)                     # the term's Prepared data (immutable)
    prep.counts.correspondences                    # (B,) what it found
    res = term.residuals(theta, posed, prep, jacobian=True)
    res.r  # (B, m) residuals        res.J  # (B, m, D) their Jacobian

A term keeps no state between the two calls: ``prepare`` returns a frozen dataclass
of its own (a subclass of :class:`Prepared`, its fields and shapes documented there),
and ``residuals`` reads only its arguments. A term may memoise what depends only on
the scene (index tables built once per scene); that never changes a result.

Terms return their own, unweighted residuals. Weights and robust losses are wrappers
around any term (:mod:`torchhand.tracking.energies.wrappers`), as theseus separates
``CostFunction``, ``CostWeight`` and ``RobustCostFunction``; they return new prepared
data (:meth:`EnergyTerm.fold_weight`, :meth:`EnergyTerm.fold_row_weights`), never
change a term's. The stacked sum of squares of all (wrapped) terms is the energy the
solver minimises.

A *prior* (anatomy, regularisation) is prepared after every other term, when
``state.correspondences`` holds C_all, the number of data correspondences of each
problem, which scales the priors' weights (Eq. 4.17-4.18).

A new term subclasses :class:`EnergyTerm` and its prepared data :class:`Prepared`
(a frozen dataclass with the term's fields); docs/architecture.md ("A new term, from the
interface alone") writes one in 30 lines, and tests/test_energy_interface.py runs it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Dict, List, NamedTuple, Optional, Sequence, Tuple

import torch

from torchhand.core.check import skip_checks
from torchhand.geometry.camera import Camera, project_points, transform_points
from torchhand.geometry.render import RenderResult, visible_vertices
from torchhand.model.kinematics import skew
from torchhand.model.scene import Scene, SceneOutput
from torchhand.tracking.preprocess import DepthFrame

__all__ = ["Residuals", "Counts", "Prepared", "TrackState", "EnergyTerm", "VertexRayTerm", "VertexPixelTerm", "capped",
           "ModelRows", "RayRows", "PixelRows", "PixelPairs", "Setup", "begin", "pixel_rows", "project_views",
           "scatter_columns", "no_residuals", "bone_inliers", "counts", "stack_rows", "stride_subsample",
           "seen_vertices"]


class Residuals(NamedTuple):
    """A term's residuals at one theta.

    Attributes:
        r: (B, m) residuals, m = n x ``dim``.
        J: (B, m, D) their Jacobian with respect to theta, or None.
        dim: residual components per correspondence row (3 for point-to-point and
            Pluecker-line residuals, 1 for point-to-plane and scalar penalties); robust
            losses act on the squared norm of each row.
        mask: (B, n) 1 for real rows and 0 for padding (every problem of a batch has
            as many rows as the one with most), or None when every row is real.
        group: (B, n) int64 group of each row in ``[0, groups)`` (the model the row
            belongs to), for losses whose scale is taken per group; None: one group.
        groups: the number of groups.
    """

    r: torch.Tensor
    J: Optional[torch.Tensor]
    dim: int = 1
    mask: Optional[torch.Tensor] = None
    group: Optional[torch.Tensor] = None
    groups: int = 1


class Counts(NamedTuple):
    """What a term's ``prepare`` found, per problem.

    Attributes:
        correspondences: (B,) int64 data correspondences, counted into C_all (0 for
            collisions and priors).
        candidates: (B,) int64 candidates considered (>= correspondences): visible
            vertices, data edge pixels, ...
        unmatched: (B,) float64 energy charged for the candidates left without a
            correspondence (each its truncated square, min(distance, cut-off)^2), so
            that poses are compared fairly however many correspondences each finds.
        diagnostics: named (B,) tensors a term reports (e.g. ``pairs`` for collisions,
            ``assigned`` detections for salient points).
    """

    correspondences: torch.Tensor
    candidates: torch.Tensor
    unmatched: torch.Tensor
    diagnostics: Dict[str, torch.Tensor] = {}


def counts(batch: int, device=None, correspondences: Optional[torch.Tensor] = None,
           candidates: Optional[torch.Tensor] = None, unmatched: Optional[torch.Tensor] = None,
           **diagnostics: torch.Tensor) -> Counts:
    """:class:`Counts` with zeros for what is not given (candidates default to the
    correspondences)."""
    zeros = torch.zeros(batch, dtype=torch.int64, device=device)
    c = zeros if correspondences is None else correspondences
    return Counts(c, c if candidates is None else candidates,
                  torch.zeros(batch, dtype=torch.float64, device=device) if unmatched is None else unmatched,
                  dict(diagnostics))


@dataclass(frozen=True, eq=False)
class Prepared:
    """The base of every term's prepared data: what ``prepare`` found at the pose of
    an outer iteration, read by ``residuals`` at any theta the solver tries. Each term
    subclasses it with the fields it needs (frozen: a wrapper that reweights rows
    returns a new object, :func:`dataclasses.replace`).

    Attributes:
        counts: :class:`Counts`, per problem.
    """

    counts: Counts

    def recounted(self, **changes) -> "Prepared":
        """A copy whose :attr:`counts` has ``changes`` (e.g. ``unmatched=...``)."""
        return replace(self, counts=self.counts._replace(**changes))


@dataclass
class TrackState:
    """What the terms see at the start of an outer iteration, for B problems.

    scene: the shared scene; theta: (B, D) current pose; previous: (B, D) the pose
    of the previous frame (the reference of Eq. 4.18); posed: scene output at theta;
    frames: one preprocessed frame per problem (points and normals in the camera
    frame); cameras: one camera per problem; render: the scene rendered at theta from
    each problem's camera (the tracker's are cropped to ``box``: ``render.origin`` is
    the image pixel of their (0, 0), :func:`~torchhand.geometry.render.window` gives
    any other box); data_labels: (B, H, W) int64 model id assigned to each data pixel
    (-1 none; (B, 1, 1) where the problems have colour images only); correspondences:
    (B,) C_all, the data correspondences of the terms prepared so far (set by the
    tracker before the priors are prepared);
    problems: (B,) int64 the index of each problem in the solve it belongs to (problems
    that converged leave the batch: the others keep their index); frame_data: what terms
    derive once per solve from the frames and labels (their data side), keyed by term,
    made by the tracker per solve and shared by its outer iterations; a term builds its
    entry at the first iteration, when every problem of the solve is present; box: the
    pixel box (r0, r1, c0, c1) the renders of the solve cover (None: the whole image);
    colours: one preprocessed colour frame per problem (``ColourFrame``), or None for
    depth-only data; share: the part of its caps (the most model vertices, data or
    free-space pixels it pairs per problem) that a term takes on each problem, below 1
    for the views of a camera rig (``TrackerConfig.rig_budget``; :func:`capped`).

    With several views per problem (a camera rig), the tracker gives the terms that read
    images (``EnergyTerm.needs``) a state of B x V *view problems*, problem-major (view v
    of problem b at row b V + v), each with its own frame, camera and render, and the
    pose terms a state of the B problems seen by their first view; it stacks the view
    problems' residuals of each problem into that problem's rows.
    """

    scene: Scene
    theta: torch.Tensor
    previous: torch.Tensor
    posed: SceneOutput
    frames: List[DepthFrame]
    cameras: List[Camera]
    render: RenderResult
    data_labels: torch.Tensor
    correspondences: Optional[torch.Tensor] = None
    problems: Optional[torch.Tensor] = None
    frame_data: Dict = field(default_factory=dict, repr=False)
    box: Optional[tuple] = None
    colours: Optional[List] = None
    share: float = 1.0
    _visible: Optional[torch.Tensor] = field(default=None, repr=False)

    def visible_vertices(self) -> torch.Tensor:
        """(B, V) bool: the vertices of the faces hit in ``render`` (found once per state,
        shared by the terms that need visibility)."""
        if self._visible is None:
            with skip_checks():  # the render's own ids: no range checks (host syncs) needed
                self._visible = visible_vertices(self.render, self.scene.faces, self.scene.num_vertices, self.box)
        return self._visible

    def data_side(self, term: "EnergyTerm", build) -> object:
        """A term's data side of this solve: ``build(state)`` at the solve's first outer
        iteration, when every problem is present (host work once per frame), then kept."""
        key = (type(term).__name__, id(term))
        data = self.frame_data.get(key)
        if data is None:
            if self.problems is not None and self.problems.shape[0] != len(self.frames):
                raise RuntimeError(f"{type(term).__name__} builds its data side at a solve's first iteration, with "
                                   f"every problem present ({self.problems.shape[0]} of {len(self.frames)} here)")
            data = self.frame_data[key] = build(self)
        return data

    def problem_index(self) -> torch.Tensor:
        """(B,) int64 ``problems``, or ``arange(B)`` when not set."""
        if self.problems is None:
            return torch.arange(self.theta.shape[0], device=self.theta.device)
        return self.problems


class EnergyTerm:
    """Base class of the terms: ``prepare(state) -> Prepared`` and
    ``residuals(theta, posed, prepared, jacobian=True) -> Residuals``.

    ``name`` names the term in logs; ``prior`` marks terms prepared after the others,
    with ``state.correspondences`` known (module docstring); ``needs`` is what the term
    reads of the images: ``"depth"`` (depth frames, ``state.frames``), ``"colour"``
    (colour frames, ``state.colours``), or None for a term of the pose alone
    (collisions, physics, priors). A term that reads images is prepared once per view
    of a camera rig (``TrackState``). ``detections``: ``"salient"`` for a term that
    reads each colour view's salient point detections (``ColourFrame.salient``: the
    nails), which the runner provides (a camera's ``salient.json``, or the shipped
    nail detector); None otherwise. ``whole_frames``: the term reads more of a view
    than the pixels near the models (it runs a detector on the whole frame), so the
    tracker does not crop a rig's views to the hands for it.
    """

    name: str = "term"
    prior: bool = False
    needs: Optional[str] = None
    detections: Optional[str] = None
    whole_frames: bool = False

    def prepare(self, state: TrackState) -> Prepared:  # pragma: no cover - interface
        """The term's data at ``state``'s pose: correspondences, their counts."""
        raise NotImplementedError

    def residuals(self, theta: torch.Tensor, posed: SceneOutput, prepared: Prepared,
                  jacobian: bool = True) -> Residuals:  # pragma: no cover - interface
        """The residuals at ``theta`` (B, D), ``posed`` = the scene at theta, with the
        correspondences of ``prepared`` (what :meth:`prepare` returned)."""
        raise NotImplementedError

    def fold_weight(self, prepared: Prepared, weight: torch.Tensor) -> Optional[Prepared]:
        """``prepared`` with a fixed per-problem weight taken in, if the term can.

        ``weight``: (B, 1) energy weights (``Weighted`` with ``per_correspondence``). A
        term whose residual is the square root of an energy (anatomy) computes
        ``sqrt(w E)`` in one root, as the thesis writes the weighted term, and returns
        the new prepared data. The default returns None: the caller scales r and J by
        ``sqrt(w)``.
        """
        return None

    def fold_row_weights(self, prepared: Prepared, sqrt_w: torch.Tensor) -> Optional[Prepared]:
        """``prepared`` with fixed row weights taken into its correspondences, if the
        term can.

        ``sqrt_w``: (B, n) factors for the rows of :meth:`residuals`. A term whose
        residuals are linear in stored per-row data (data-to-model's Pluecker lines)
        scales that data once, which is cheaper than scaling r and J at every
        evaluation; it returns the new prepared data. The default returns None: the
        caller (``Robust``) scales r and J.
        """
        return None

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


class Setup(NamedTuple):
    """What a term's ``prepare`` starts from (:func:`begin`): the scene, the number of
    (view) problems B, the state's device and dtype, the term's data side of the solve
    and ``problems`` (B,) int64, each problem's row in that data side."""

    scene: Scene
    batch: int
    device: torch.device
    dtype: torch.dtype
    data: object
    problems: torch.Tensor


def begin(state: "TrackState", term: EnergyTerm, build) -> Setup:
    """The common start of a data term's ``prepare``: its data side of the solve
    (``build(state)`` at the solve's first outer iteration, :meth:`TrackState.data_side`)
    and the state's sizes."""
    return Setup(state.scene, state.theta.shape[0], state.theta.device, state.theta.dtype,
                 state.data_side(term, build), state.problem_index())


@dataclass(frozen=True, eq=False)
class ModelRows(Prepared):
    """Prepared data of a term with a block of pairs per model: ``scene`` and ``rows``,
    one NamedTuple of (B, n) tensors per model (:class:`RayRows` of a
    :class:`VertexRayTerm`, :class:`PixelRows`, model-to-data's ``SurfaceRows``)."""

    scene: Scene
    rows: tuple


class RayRows(NamedTuple):
    """One model's (vertex, ray) pairs: ids (B, n) int64 vertex ids local to the model,
    d (B, n, 3) and m (B, n, 3) the ray's Pluecker line (direction, moment), mask (B, n)
    1 for real rows (rows with mask 0 have d = m = 0 or are zeroed)."""

    ids: torch.Tensor
    d: torch.Tensor
    m: torch.Tensor
    mask: torch.Tensor


class VertexRayTerm(EnergyTerm):
    """A term whose pairs are (model vertex, world ray): the residual ``V x d - m`` of
    the vertex V and the ray's Pluecker line (d, m), whose norm is V's distance to the
    ray (data-to-model, Eq. 4.8). ``prepare`` returns :class:`ModelRows` of
    :class:`RayRows`."""

    def fold_row_weights(self, prepared: ModelRows, sqrt_w):
        # V x d - m is linear in the line (d, m): scaling both by sqrt(w) weights the
        # pair's squared residual, and its Jacobian, by w
        rows, start = [], 0
        for ids, d, m, mask in prepared.rows:
            sw = sqrt_w[:, start : start + ids.shape[1], None]
            rows.append(RayRows(ids, d * sw, m * sw, mask))
            start += ids.shape[1]
        return replace(prepared, rows=tuple(rows))

    def residuals(self, theta, posed, prepared: ModelRows, jacobian=True):
        B, D = theta.shape
        scene = prepared.scene
        parts = []
        b = torch.arange(B, device=theta.device)[:, None]
        for k, (ids, d, m, mask) in enumerate(prepared.rows):
            out = posed.models[k]
            V = out.vertices[b, ids]
            r = (torch.cross(V, d, dim=-1) - m) * mask[..., None]
            J = None
            if jacobian:
                Jv = scene.models[k].jacobian(None, ids, fk=(out.G, out.twists))
                Jr = -(skew(d) @ Jv) * mask[..., None, None]  # d(V x d) = -[d]x dV
                J = scatter_columns(Jr.reshape(B, -1, Jr.shape[-1]), scene.slices[scene.names[k]], D)
            parts.append(Residuals(r.reshape(B, -1), J, 3, mask, torch.full_like(ids, k)))
        return stack_rows(parts, theta, jacobian, 3, len(prepared.rows))


class PixelRows(NamedTuple):
    """One model's (vertex, image point) pairs: ids (B, n) int64 vertex ids local to the
    model, q (B, n, 2) (u, v) px, scale (B, n) mm per px, mask (B, n)."""

    ids: torch.Tensor
    q: torch.Tensor
    scale: torch.Tensor
    mask: torch.Tensor


@dataclass(frozen=True, eq=False)
class PixelPairs(ModelRows):
    """Prepared data of a :class:`VertexPixelTerm`: ``scene``, one :class:`PixelRows` per
    model (``rows``, :func:`pixel_rows` builds them from pairs of any models) and each
    problem's camera (``K`` (B, 3, 3), ``T_cw`` (B, 4, 4))."""

    K: torch.Tensor
    T_cw: torch.Tensor


class VertexPixelTerm(EnergyTerm):
    """A term whose pairs are (model vertex, image point): the residual is the vertex's
    projection minus the point, ``(pi(V) - q) s`` (2 rows), in mm through a per-pair
    scale s (mm per px, fixed for the outer iteration): Ballan et al.'s reprojection
    error (Eq. 2) in the units of the depth terms (free space, edges, optical flow).
    ``prepare`` returns :class:`PixelPairs`."""

    def fold_row_weights(self, prepared: PixelPairs, sqrt_w):
        # the residual is linear in the stored scale: scaling it weights the pair by w
        rows, start = [], 0
        for ids, q, scale, mask in prepared.rows:
            rows.append(PixelRows(ids, q, scale * sqrt_w[:, start : start + ids.shape[1]], mask))
            start += ids.shape[1]
        return replace(prepared, rows=tuple(rows))

    def residuals(self, theta, posed, prepared: PixelPairs, jacobian=True):
        B, D = theta.shape
        scene = prepared.scene
        R, t = prepared.T_cw[:, None, :3, :3], prepared.T_cw[:, None, :3, 3]
        K_b = prepared.K
        fx, fy = K_b[:, 0, 0, None], K_b[:, 1, 1, None]
        cx, cy = K_b[:, 0, 2, None], K_b[:, 1, 2, None]
        parts = []
        b = torch.arange(B, device=theta.device)[:, None]
        for k, (ids, q, scale, mask) in enumerate(prepared.rows):
            out = posed.models[k]
            V = out.vertices[b, ids]  # (B, n, 3) world
            Xc = (R @ V[..., None])[..., 0] + t
            Z = Xc[..., 2].clamp(min=1.0)
            u = torch.stack([fx * Xc[..., 0] / Z + cx, fy * Xc[..., 1] / Z + cy], -1)
            r = (u - q) * scale[..., None]  # (B, n, 2) mm at the data depth
            J = None
            if jacobian:
                Jv = scene.models[k].jacobian(None, ids, fk=(out.G, out.twists))  # (B, n, 3, D_k)
                zeros = torch.zeros_like(Z)
                Jp = torch.stack([torch.stack([fx / Z, zeros, -fx * Xc[..., 0] / Z ** 2], -1),
                                  torch.stack([zeros, fy / Z, -fy * Xc[..., 1] / Z ** 2], -1)], -2)  # (B, n, 2, 3)
                Jr = (Jp @ R) @ Jv * scale[..., None, None]
                J = scatter_columns(Jr.reshape(B, -1, Jr.shape[-1]), scene.slices[scene.names[k]], D)
            parts.append(Residuals(r.reshape(B, -1), J, 2, mask, torch.full_like(ids, k)))
        return stack_rows(parts, theta, jacobian, 2, len(prepared.rows))


def project_views(state: TrackState, points: torch.Tensor) -> tuple:
    """World points (B, n, 3) seen by each problem's camera: (uv (B, n, 2) px
    (:func:`~torchhand.geometry.camera.project_points`), z (B, n) mm (at least 1), K
    (B, 3, 3), T_cw (B, 4, 4)) in the state's dtype and device."""
    dev, dt = state.theta.device, state.theta.dtype
    K = torch.stack([c.K.to(dev, dt) for c in state.cameras])
    T = torch.stack([c.T_cw.to(dev, dt) for c in state.cameras])
    Xc = transform_points(T, points.to(dt))
    return project_points(Xc, K), Xc[..., 2].clamp_min(1.0), K, T


def pixel_rows(scene: Scene, vertex: torch.Tensor, target: torch.Tensor, scale: torch.Tensor,
               keep: torch.Tensor) -> Tuple[PixelRows, ...]:
    """:attr:`PixelPairs.rows` from pairs of any models: vertex (B, n) int64 scene
    vertex ids, target (B, n, 2) (u, v) px, scale (B, n) mm per px, keep (B, n) bool.
    Each model's rows are its kept pairs, packed to the most any problem has (one host
    sync)."""
    out = []
    for name in scene.names:
        sl = scene.vertex_slices[name]
        sel = keep & (vertex >= sl.start) & (vertex < sl.stop)
        count = int(sel.sum(1).max()) if sel.numel() else 0
        pos, ok = stride_subsample(sel, max(count, 1)) if count else (sel.new_zeros(sel.shape[0], 0, dtype=torch.int64),
                                                                       sel.new_zeros(sel.shape[0], 0))
        local = torch.where(ok, vertex.gather(1, pos) - sl.start, torch.zeros_like(pos))
        q = target.gather(1, pos[..., None].expand(-1, -1, 2))
        out.append(PixelRows(local, q, scale.gather(1, pos) * ok, ok.to(target.dtype)))
    return tuple(out)


def seen_vertices(render: RenderResult, faces: torch.Tensor, pixels: torch.Tensor) -> torch.Tensor:
    """The scene vertex seen at each pixel: the corner of the hit face with the largest
    barycentric weight. render: (B, H, W) maps (cropped or not); pixels: (B, n, 2)
    int64 image (row, col), any value where the caller masks the result -> (B, n)
    int64."""
    b = torch.arange(pixels.shape[0], device=pixels.device)[:, None]
    o_r, o_c = render.origin or (0, 0)  # a cropped render's maps start there
    H, W = render.face_id.shape[-2:]
    r, c = (pixels[..., 0] - o_r).clamp(0, H - 1), (pixels[..., 1] - o_c).clamp(0, W - 1)
    fid = render.face_id[b, r, c].clamp(min=0)
    bary = render.barycentric[b, r, c]
    w = torch.cat([1 - bary.sum(-1, keepdim=True), bary], -1)
    return faces[fid, w.argmax(-1)]


def scatter_columns(J_model: torch.Tensor, cols: slice, D: int) -> torch.Tensor:
    """Place a model's Jacobian (B, m, D_k) into the scene's columns (B, m, D)."""
    J = J_model.new_zeros(J_model.shape[0], J_model.shape[1], D)
    J[:, :, cols] = J_model
    return J


def no_residuals(theta: torch.Tensor, jacobian: bool, dim: int = 1) -> Residuals:
    """The residuals of a term without correspondences: (B, 0) and (B, 0, D)."""
    B, D = theta.shape
    return Residuals(theta.new_zeros(B, 0), theta.new_zeros(B, 0, D) if jacobian else None, dim,
                     theta.new_zeros(B, 0), torch.zeros(B, 0, dtype=torch.int64, device=theta.device))


def stack_rows(parts: Sequence[Residuals], theta: torch.Tensor, jacobian: bool, dim: int, groups: int) -> Residuals:
    """Concatenate the row blocks of one term (e.g. one per model) into its Residuals."""
    if not parts:
        return no_residuals(theta, jacobian, dim)._replace(groups=groups)
    B = theta.shape[0]
    masks = [p.mask if p.mask is not None else theta.new_ones(B, p.r.shape[1] // dim) for p in parts]
    group = [p.group if p.group is not None else torch.zeros(m.shape, dtype=torch.int64, device=theta.device)
             for p, m in zip(parts, masks)]
    return Residuals(torch.cat([p.r for p in parts], 1), torch.cat([p.J for p in parts], 1) if jacobian else None,
                     dim, torch.cat(masks, 1), torch.cat(group, 1), groups)


def bone_inliers(d: torch.Tensor, bone: torch.Tensor, keep: torch.Tensor, num_bones: int,
                 sigma: float) -> torch.Tensor:
    """Per-bone outlier rejection (Ballan et al. 2012, Sec. 3), batched over problems.

    Args:
        d: (..., n) correspondence distances; bone: (..., n) int64 the bone of each model
            point, in [0, num_bones); keep: (..., n) bool, the pairs the statistics are
            taken over (per leading index: one problem); sigma: the cut.
    Returns:
        (..., n) bool: d <= mean + sigma * std of the kept distances of the same bone and
        problem. No host sync.
    """
    lead = d.shape[:-1]
    P = math.prod(lead)
    offset = (torch.arange(P, device=d.device) * num_bones).view(*lead, 1) if lead else 0
    key = (bone + offset).reshape(-1)
    dd, w = d.reshape(-1), keep.reshape(-1).to(d.dtype)
    n = torch.zeros(P * num_bones, dtype=d.dtype, device=d.device).index_add_(0, key, w).clamp_min(1)
    mean = torch.zeros_like(n).index_add_(0, key, dd * w) / n
    std = (torch.zeros_like(n).index_add_(0, key, (dd - mean[key]) ** 2 * w) / n).sqrt()
    return (dd <= mean[key] + sigma * std[key] + 1e-6).view(d.shape)


def capped(count: int, share: float) -> int:
    """A term's cap ``count`` on a problem of ``TrackState.share`` (at least 1)."""
    return max(1, int(round(count * share)))


def stride_subsample(mask: torch.Tensor, count: int) -> tuple:
    """Up to ``count`` of the True entries of each row, evenly spaced (a stride subsample:
    entry ``floor(j (n - 1) / (count - 1))`` of the n True entries, all of them when
    n <= count), with fixed shapes and no host sync.

    Args:
        mask: (B, L) bool.
    Returns:
        (index (B, count) int64 positions in the row, ok (B, count) bool: real slots).
    """
    B, L = mask.shape
    n = mask.sum(1)  # (B,)
    j = torch.arange(count, device=mask.device)
    over = n > count
    spread = torch.floor(j.double() * (n[:, None] - 1).double() / max(count - 1, 1)).long()
    rank = torch.where(over[:, None], spread, j.expand(B, count))
    ok = over[:, None] | (j[None] < n[:, None])
    csum = torch.cumsum(mask.long(), 1)
    index = torch.searchsorted(csum, rank + 1).clamp(max=max(L - 1, 0))  # the first position holding that rank
    return torch.where(ok, index, torch.zeros_like(index)), ok
