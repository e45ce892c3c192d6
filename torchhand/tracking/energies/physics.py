"""P: physical plausibility of a grasp (thesis Eq. 4.16), with Bullet (pybullet).

At the start pose of each frame, every rigid object of the scene is tested for
stability in a simulation with the hands static
(:class:`torchhand.tracking.simulation.GraspSimulation`: 35 steps of 0.1 s, stable when
its centroid moves less than 3 mm). For an unstable object, the combination of two to
four finger parts within 10 mm of it that, moved onto it, holds it best is chosen, and
the term pulls those parts onto the object::

    E_physics = sum_i |V_i(theta) - X_i(theta)|^2                       (Eq. 4.16)

V_i is the vertex of part i nearest to the object and X_i the object vertex nearest to
V_i, both found at the frame's start pose and kept for the frame (the thesis finds the
correspondences of P with the others in Algorithm 1; re-running up to 50 simulations
per outer iteration would cost ~0.2 s each time for the same answer, as the pose moves
a few mm within a frame). Both move with theta: the fingers are pulled to the object and
the object to the fingers. The tracker weights the term by gamma_ph = 10
(:data:`DEFAULT_WEIGHT`).

The simulation runs on the CPU, once per frame and problem.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Dict, List, NamedTuple, Optional, Tuple

import numpy as np
import torch

from torchhand.model.scene import Scene
from torchhand.tracking.energies.base import (EnergyTerm, Prepared, Residuals, TrackState, counts, scatter_columns,
                                              stack_rows)

__all__ = ["Physics", "PhysicsPairs", "DEFAULT_WEIGHT"]

#: gamma_ph of the thesis (Sec. 4.3.2: equal to the collision weight gamma_c)
DEFAULT_WEIGHT = 10.0


class _Pairs(NamedTuple):
    """Per (hand, object) block: hand vertex ids, object vertex ids (B, n) local to their
    models, mask (B, n); and per problem the simulation's outcome for the diagnostics."""

    blocks: Dict[Tuple[int, int], Tuple[torch.Tensor, torch.Tensor, torch.Tensor]]
    unstable: torch.Tensor
    supported: torch.Tensor


@dataclass(frozen=True, eq=False)
class PhysicsPairs(Prepared):
    """Prepared data of :class:`Physics`: ``scene`` and per (hand, object) block
    ``(hand model k, object model o, hand vertex ids (B, n), object vertex ids (B, n),
    mask (B, n))``, the ids local to their models (``blocks``)."""

    scene: Scene
    blocks: Tuple[tuple, ...]


class Physics(EnergyTerm):
    """E_physics, unweighted (the tracker weights it by :data:`DEFAULT_WEIGHT`).

    Args:
        **simulation: keyword arguments of
            :class:`~torchhand.tracking.simulation.GraspSimulation` (friction, steps,
            dt, substeps, stable_mm, contact_mm, max_candidates, gravity).
    """

    name = "physics"

    def __init__(self, **simulation):
        from torchhand.tracking.simulation import require_pybullet

        require_pybullet()
        self.simulation_args = simulation
        self._sim = None  # (scene, GraspSimulation)
        self._warned = False

    def _simulation(self, scene):
        from torchhand.tracking.simulation import GraspSimulation

        if self._sim is None or self._sim[0] is not scene:
            self._sim = (scene, GraspSimulation(scene, **self.simulation_args))
            if not self._sim[1].objects and not self._warned:
                warnings.warn("the physics term does nothing: the scene has no rigid object "
                              f"(models: {', '.join(scene.names)})", stacklevel=3)
                self._warned = True
        return self._sim[1]

    def _build(self, state: TrackState) -> _Pairs:
        from scipy.spatial import cKDTree

        sim = self._simulation(state.scene)
        B, dev = len(state.frames), state.theta.device
        found: List[List[Tuple[int, int, int, int]]] = []  # per problem: (hand, vertex, object, vertex)
        unstable = torch.zeros(B, dtype=torch.int64)
        supported = torch.zeros(B, dtype=torch.int64)
        for b in range(B):
            pairs = []
            if sim.objects and sim.fingers:
                verts = {k: o.vertices[b].detach().double().cpu().numpy() for k, o in enumerate(state.posed.models)}
                for o, support in sim.best_support(verts).items():
                    unstable[b] += int(not support.stable)
                    supported[b] += len(support.parts)
                    if not support.parts:
                        continue
                    tree = cKDTree(verts[o])
                    for k, j in support.parts:
                        ids = sim.parts[k][j]
                        d, x = tree.query(verts[k][ids])
                        i = int(np.argmin(d))
                        pairs.append((k, int(ids[i]), o, int(x[i])))
            found.append(pairs)
        blocks = {}
        for key in sorted({(k, o) for pairs in found for k, _, o, _ in pairs}):
            n = max(sum(1 for k, _, o, _ in pairs if (k, o) == key) for pairs in found)
            vh = torch.zeros(B, n, dtype=torch.int64)
            vo = torch.zeros(B, n, dtype=torch.int64)
            mask = torch.zeros(B, n, dtype=state.theta.dtype)
            for b, pairs in enumerate(found):
                sel = [(v, x) for k, v, o, x in pairs if (k, o) == key]
                for i, (v, x) in enumerate(sel):
                    vh[b, i], vo[b, i], mask[b, i] = v, x, 1.0
            blocks[key] = (vh.to(dev), vo.to(dev), mask.to(dev))
        return _Pairs(blocks, unstable.to(dev), supported.to(dev))

    def prepare(self, state: TrackState) -> PhysicsPairs:
        data = state.data_side(self, self._build)
        p = state.problem_index()
        blocks = tuple((k, o, vh[p], vo[p], mask[p]) for (k, o), (vh, vo, mask) in data.blocks.items())
        B = state.theta.shape[0]
        found = counts(B, device=state.theta.device, unstable=data.unstable[p], contact_parts=data.supported[p])
        return PhysicsPairs(found, state.scene, blocks)

    def residuals(self, theta: torch.Tensor, posed, prepared: PhysicsPairs, jacobian: bool = True) -> Residuals:
        B, D = theta.shape
        b = torch.arange(B, device=theta.device)[:, None]
        parts = []
        scene = prepared.scene
        for k, o, vh, vo, mask in prepared.blocks:
            hk, ok = posed.models[k], posed.models[o]
            r = (hk.vertices[b, vh] - ok.vertices[b, vo]) * mask[..., None]  # (B, n, 3)
            J: Optional[torch.Tensor] = None
            if jacobian:
                names, models = scene.names, scene.models
                Jh = models[k].jacobian(None, vh, fk=(hk.G, hk.twists)) * mask[..., None, None]
                Jo = models[o].jacobian(None, vo, fk=(ok.G, ok.twists)) * mask[..., None, None]
                J = (scatter_columns(Jh.reshape(B, -1, Jh.shape[-1]), scene.slices[names[k]], D)
                     - scatter_columns(Jo.reshape(B, -1, Jo.shape[-1]), scene.slices[names[o]], D))
            parts.append(Residuals(r.reshape(B, -1), J, 3, mask, torch.full_like(vh, k)))
        return stack_rows(parts, theta, jacobian, 3, len(scene.models))
