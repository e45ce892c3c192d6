"""The tracking objective (thesis Eq. 4.5): prepared energy terms stacked into the
least-squares problem the solvers minimise.

:func:`prepare_terms` prepares every term at the pose of an outer iteration (the data
terms on the view problems, then the priors with C_all known); :class:`Objective` holds
the terms with what they prepared and gives the solver residuals and Jacobians at any
theta (:class:`~torchhand.optim.levenberg_marquardt.LeastSquaresProblem`).
"""

from __future__ import annotations

from typing import List, NamedTuple, Sequence

import torch

from torchhand.core.profiling import stage
from torchhand.model.scene import Scene, SceneOutput
from torchhand.optim.levenberg_marquardt import LeastSquaresProblem
from torchhand.tracking.energies import EnergyTerm, Prepared, TrackState

__all__ = ["Objective", "PreparedTerms", "prepare_terms"]


class PreparedTerms(NamedTuple):
    """What :func:`prepare_terms` returns: ``prepared``, one :class:`Prepared` per term
    (in the terms' order); per problem (B,): ``correspondences`` C_all (int64),
    ``candidates`` (int64) and ``unmatched`` energy (float64) summed over the terms."""

    prepared: List[Prepared]
    correspondences: torch.Tensor
    candidates: torch.Tensor
    unmatched: torch.Tensor


def prepare_terms(terms: Sequence[EnergyTerm], view: TrackState, pose: TrackState, views: int) -> PreparedTerms:
    """Prepare every term for one outer iteration: the terms that read images on the
    B x V view problems of ``view`` (their counts summed per problem), the others on the
    B problems of ``pose``, then the priors with ``pose.correspondences`` = C_all set."""
    nb = pose.theta.shape[0]

    def summed(x):
        return x.view(nb, views).sum(1)

    prepared: List[Prepared] = [None] * len(terms)  # type: ignore[list-item]
    for k, t in enumerate(terms):
        if t.prior:
            continue
        if t.needs is None:
            with stage(f"prepare:{t.name}"):
                prepared[k] = t.prepare(pose)
        else:
            with stage(f"prepare:{t.name}", work=lambda: _prepare_work(prepared[k])):
                p = prepared[k] = t.prepare(view)
            c = p.counts
            prepared[k] = p.recounted(correspondences=summed(c.correspondences), candidates=summed(c.candidates),
                                      unmatched=summed(c.unmatched),
                                      diagnostics={n: summed(v) for n, v in c.diagnostics.items()})
    data = [p.counts for p in prepared if p is not None]
    pose.correspondences = sum(c.correspondences for c in data)
    for k, t in enumerate(terms):
        if t.prior:
            with stage(f"prepare:{t.name}"):
                prepared[k] = t.prepare(pose)
    found = [p.counts for p in prepared]
    return PreparedTerms(prepared, pose.correspondences, sum(c.candidates for c in found),
                         sum(c.unmatched for c in found))


class Objective(LeastSquaresProblem):
    """The stacked residuals of prepared terms, for B problems of V views each.

    Args:
        scene: the scene the terms were prepared for.
        terms: the energy terms; prepared: what each returned from ``prepare``.
        posed: the scene posed at the solver's start (the pose the terms were prepared
            at, within the solver's box).
        views: V; the terms that read images see the B x V view problems (problem-major),
            whose rows are stacked per problem.

    It follows the solver (:class:`~torchhand.optim.levenberg_marquardt.LeastSquaresProblem`):
    :attr:`current` is the scene posed at the solver's iterate, :attr:`candidate` at the
    last candidate it evaluated; :meth:`accept` moves the accepted problems' rows of the
    candidate into :attr:`current`, so no theta is posed twice.
    """

    def __init__(self, scene: Scene, terms: Sequence[EnergyTerm], prepared: Sequence[Prepared], posed: SceneOutput,
                 views: int = 1):
        if len(terms) != len(prepared):
            raise ValueError(f"give one prepared data per term: {len(terms)} terms, {len(prepared)} prepared")
        self.scene, self.terms, self.prepared, self.views = scene, list(terms), list(prepared), int(views)
        self.current = posed  # the scene at the solver's iterate
        self.candidate: SceneOutput = posed  # the scene at the last candidate
        B = posed.vertices.shape[0]
        self._rep = torch.arange(B, device=posed.vertices.device).repeat_interleave(self.views)

    def residuals(self, theta: torch.Tensor, posed: SceneOutput, jacobian: bool) -> tuple:
        """(r (B, m), J (B, m, D) or None) at ``theta`` (B, D), with ``posed`` the scene
        posed there."""
        B, D = theta.shape
        per_view = any(t.needs is not None for t in self.terms)
        th_v, posed_v = (theta[self._rep], posed.select(self._rep)) if per_view else (None, None)
        parts = []
        for t, p in zip(self.terms, self.prepared):
            with stage(f"{'rows+J' if jacobian else 'rows'}:{t.name}",
                       work=lambda: _rows_work(parts[-1], self.scene, jacobian)):
                if t.needs is None:
                    parts.append(t.residuals(theta, posed, p, jacobian))
                    continue
                res = t.residuals(th_v, posed_v, p, jacobian)  # the view problems' rows, stacked per problem
                parts.append(res._replace(r=res.r.reshape(B, -1),
                                          J=None if res.J is None else res.J.reshape(B, -1, D)))
        r = torch.cat([p.r for p in parts], 1)
        J = torch.cat([p.J for p in parts], 1) if jacobian else None
        return r, J

    def linearize(self, theta: torch.Tensor) -> tuple:
        return self.residuals(theta, self.current, True)

    def evaluate(self, theta: torch.Tensor) -> torch.Tensor:
        with stage("pose", work=lambda: _pose_work(self.scene, theta.shape[0])):
            self.candidate = self.scene(theta, validate=False)
        return self.residuals(theta, self.candidate, False)[0]

    def accept(self, mask: torch.Tensor) -> None:
        cand, cur = self.candidate, self.current
        self.current = SceneOutput(*(_where(mask, a, b) for a, b in zip(cand[:2], cur[:2])),
                                   [type(mc)(*(_where(mask, a, b) for a, b in zip(mc, mo)))
                                    for mc, mo in zip(cand.models, cur.models)])


def _where(mask: torch.Tensor, a, b):
    if not isinstance(a, torch.Tensor):
        return a
    return torch.where(mask.view(-1, *([1] * (a.dim() - 1))), a, b)


# Floors of the stages (core.profiling): what the work cannot avoid, in flops and bytes.
# K = 4 skinning influences per vertex: the thesis hands' vertices have 9 non-zero weights
# on average but 3.5 above 0.01; a floor counts what a lean skinning would need.
_K = 4


def _prepare_work(prepared: Prepared) -> tuple:
    """A data term's preparation: per candidate a neighbour query of ~27 points (~250
    flops), the normal or ray of the pair (~100 flops), 64 bytes read and written."""
    n = float(prepared.counts.candidates.sum())
    return 350.0 * n, 64.0 * n


def _rows_work(res, scene: Scene, jacobian: bool) -> tuple:
    """A term's residual rows (at ``dim`` rows per pair): per pair its vertex skinned
    (K x 24 flops, K x 8 + 12 bytes of skinning data read) and 28 bytes of pair data;
    with the Jacobian, per DoF of the pair's model (~D / models of the scene) the
    DoF's motion of the vertex (24 flops) and its projection on the rows (6 x dim);
    the Jacobian's normal equations are counted in the solve."""
    m = res.r.shape[0] * res.r.shape[1]
    pairs = m / max(res.dim, 1)
    D = scene.num_dofs / max(len(scene.models), 1)
    flops = pairs * _K * 24 + (pairs * D * (24 + 6 * res.dim) if jacobian else 0.0)
    return flops, pairs * (_K * 8 + 12 + 28) + 4.0 * m


def _pose_work(scene: Scene, B: int) -> tuple:
    """Posing the scene: forward kinematics (~200 flops per bone) and every vertex
    skinned from its K influences (K x 24 flops; rest vertex, K ids and weights read,
    the posed vertex written)."""
    V = scene.num_vertices
    bones = sum(m.num_bones for m in scene.models)
    return B * (200.0 * bones + _K * 24.0 * V), B * V * (12.0 + _K * 8 + 12)
