"""E_chain: the joints of a chain of like bones (the rope) bend alike.

``E = sum_(j, k) (theta_j - theta_k)^2`` over the pairs of a bone's DoF and the same DoF
of its only child, where both turn about the same axis of their own frames, in runs of
at least :data:`MIN_JOINTS` such joints (the rope's 35 joints about y and z); hands are
left out (their finger joints do not bend alike), and so are rigid objects, the pipe's
single joint, a mechanism's few hinges (a rigged or generated chain of links) and any
joint whose neighbour turns about another axis. The tracker weights it by 0.2 per data
correspondence (:data:`DEFAULT_WEIGHT`), like the temporal term.

Not in the thesis, which tracks the rope with the generic terms. Why: a tube is thin
under the sensor's noise and uniform along its length, so nothing in the data stops one
joint under a hand from folding while its neighbours stay straight, and the rest of the
rope then slides along its own axis (docs/results.md, "Two hands and the rope": the
rope in the pipe's place, 400 frames, 6.5 mm on average and 101 frames above 10 mm
without the term, 2.5 mm and one frame above 10 mm with it). A real rope or cable resists such kinks: its bending
stiffness spreads a bend over its length.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchhand.model.scene import Scene
from torchhand.tracking.energies.base import EnergyTerm, Prepared, Residuals, TrackState, counts

__all__ = ["ChainSmoothness", "ChainPrepared", "DEFAULT_WEIGHT", "MIN_JOINTS", "chain_pairs"]

#: weight per data correspondence (the rope in the pipe's place, docs/results.md)
DEFAULT_WEIGHT = 0.2

#: the shortest run of like joints that counts as a chain (the rope has 35)
MIN_JOINTS = 8

_SLOTS = {"x": 0, "y": 1, "z": 2}


def chain_pairs(scene: Scene) -> torch.Tensor:
    """(P, 2) int64 scene DoF indices (parent's, child's) of the pairs of E_chain: runs of
    at least :data:`MIN_JOINTS` like joints (a mechanism's few hinges are left alone)."""
    pairs = []
    for name, model in zip(scene.names, scene.models):
        if model.kind == "hand":
            continue
        start = scene.slices[name].start
        parents = [int(p) for p in model.parents]
        children = {b: [c for c, p in enumerate(parents) if p == b] for b in range(len(parents))}
        slots = {}
        for k, dof in enumerate(model.dof_names):
            bone, _, axis = dof.partition(":")
            if bone != "root" and axis in _SLOTS:
                slots[(int(model.dof_bone[k]), _SLOTS[axis])] = start + k
        link = {}  # (bone, slot) -> (its only child, slot) turning about the same axis
        for (bone, slot) in slots:
            kids = children[bone]
            if len(kids) == 1 and (kids[0], slot) in slots and torch.allclose(
                    model.slot_axes[bone, slot], model.slot_axes[kids[0], slot], atol=1e-6):
                link[(bone, slot)] = (kids[0], slot)
        for head in set(link) - set(link.values()):  # each run from its first joint
            run = [head]
            while run[-1] in link:
                run.append(link[run[-1]])
            if len(run) >= MIN_JOINTS:
                pairs += [(slots[a], slots[b]) for a, b in zip(run, run[1:])]
    return torch.tensor(sorted(pairs), dtype=torch.int64).reshape(-1, 2)


@dataclass(frozen=True, eq=False)
class ChainPrepared(Prepared):
    """Prepared data of :class:`ChainSmoothness`: ``pairs`` (P, 2) int64 the scene DoF
    of each pair (:func:`chain_pairs`)."""

    pairs: torch.Tensor


class ChainSmoothness(EnergyTerm):
    """E_chain (module docstring). A scene without such chains has no residuals."""

    name = "chain_smoothness"
    prior = True

    def __init__(self):
        self._pairs = None  # (scene, pairs): chain_pairs memoised per scene

    def prepare(self, state: TrackState) -> ChainPrepared:
        if self._pairs is None or self._pairs[0] is not state.scene:
            self._pairs = (state.scene, chain_pairs(state.scene))
        return ChainPrepared(counts(state.theta.shape[0], device=state.theta.device),
                             self._pairs[1].to(state.theta.device))

    def residuals(self, theta, posed, prepared: ChainPrepared, jacobian=True):
        a, b = prepared.pairs[:, 0], prepared.pairs[:, 1]
        r = theta[:, a] - theta[:, b]
        J = None
        if jacobian:
            J = theta.new_zeros(theta.shape[0], len(a), theta.shape[1])
            rows = torch.arange(len(a), device=theta.device)
            J[:, rows, a] = 1.0
            J[:, rows, b] = -1.0
        return Residuals(r, J)
