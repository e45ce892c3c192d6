"""HOPE (Oikonomidis et al. 2011), the baseline of Ballan et al.'s Table 1: a particle
swarm (:func:`torchhand.optim.pso.particle_swarm`, the one PSO the initialisation and
the calibration use too) over the energy Algorithm 1 minimises, each particle's
correspondences found at its own pose (the terms' prepare), its fitness the energy per
candidate correspondence.
"""

from __future__ import annotations

from typing import List, Optional, Sequence

import torch

from torchhand.geometry.camera import Camera
from torchhand.optim.pso import particle_swarm
from torchhand.tracking.objective import Objective, prepare_terms
from torchhand.tracking.solve import SolveResult, check_counts
from torchhand.tracking.views import same_camera

__all__ = ["Swarm", "SWARM_BATCH_PIXELS"]

#: the most pixels HOPE renders in one batch (particles x views x the solve's box; at
#: least one particle); larger maps are fresh memory on every call (page faults), which
#: costs more than drawing (the trial: docs/results.md)
SWARM_BATCH_PIXELS = 1 << 21


class Swarm:
    """HOPE for a batch: ``config.particles`` particles drawn about the start pose
    (``config.swarm_spread``; the first is the start itself), ``config.generations``
    generations; velocities are limited to twice the spread. No recovery re-solve
    follows it."""

    recovers = False

    def solve(self, tracker, start: torch.Tensor, previous: torch.Tensor, frames: List, cameras: Sequence[Camera],
              *, iterations: int, min_motion: float, colours: Optional[List] = None, views: int = 1,
              bounds: tuple, generator: Optional[torch.Generator] = None) -> SolveResult:
        """Arguments as :meth:`Algorithm1.solve <torchhand.tracking.solve.Algorithm1.solve>`
        (``iterations`` and ``min_motion`` are not used: the swarm runs its generations);
        ``generator`` draws the particles and the swarm's coefficients (default: seeded
        with ``config.seed``)."""
        cfg, scene, V = tracker.config, tracker.scene, int(views)
        theta = tracker.clamp(start, bounds)
        B, D = theta.shape
        check_counts(B, V, frames, cameras, colours)
        P = cfg.particles
        generator = torch.Generator().manual_seed(cfg.seed) if generator is None else generator
        frame_data: dict = {}
        shared = all(same_camera(c, cameras[0]) for c in cameras)
        with torch.no_grad():
            posed = scene(theta, validate=False)
            box = tracker.frame_states.box(posed.vertices.repeat_interleave(V, 0), cameras, shared)
            view, pose = tracker.frame_states.states(theta, previous, frames, cameras, views=V, colours=colours,
                                                     frame_data=frame_data, posed=posed, shared=shared, box=box)
            labels = view.data_labels
            prepare_terms(tracker.terms, view, pose, V)  # the terms' data side, once for the frame
        spread = _spread(scene, D, cfg.swarm_spread, theta)
        noise = torch.randn(B, P, D, generator=generator, dtype=theta.dtype).to(theta.device) * spread
        noise[:, 0] = 0
        # particles per batch of renders (their data sides are gathered per view problem)
        pixels = max(1, (box[1] - box[0]) * (box[3] - box[2]) * V)
        chunk = max(1, SWARM_BATCH_PIXELS // pixels)

        def energies(th: torch.Tensor, owner: List[int]) -> tuple:
            """(energy (N,), C_all (N,)) of poses th (N, D) of the problems ``owner``."""
            out, found = [], []
            for c0 in range(0, len(owner), chunk):
                js = list(range(c0, min(c0 + chunk, len(owner))))
                vsub = [owner[j] * V + v for j in js for v in range(V)]
                prob = torch.tensor([owner[j] for j in js], device=theta.device)
                vidx = torch.tensor(vsub, device=theta.device)
                with torch.no_grad():
                    sv, sp = tracker.frame_states.states(
                        th[js], previous[prob], [frames[i] for i in vsub], [cameras[i] for i in vsub], views=V,
                        colours=None if colours is None else [colours[i] for i in vsub], problems=vidx,
                        frame_data=frame_data, labels=labels[vidx.to(labels.device)], shared=shared, box=box)
                    prep = prepare_terms(tracker.terms, sv, sp, V)
                    r, _ = Objective(scene, tracker.terms, prep.prepared, sp.posed, V).residuals(sp.theta, sp.posed,
                                                                                                 False)
                out.append(((r ** 2).sum(1) + prep.unmatched.to(r)) / prep.candidates.to(r).clamp_min(1))
                found.append(prep.correspondences.cpu())
            return torch.cat(out), torch.cat(found)

        owners = [b for b in range(B) for _ in range(P)]
        res = particle_swarm(lambda pos: energies(pos.reshape(B * P, D), owners)[0].view(B, P), theta[:, None] + noise,
                             bounds[0], bounds[1], cfg.generations, velocity_scale=2 * spread, generator=generator)
        best = tracker.clamp(res.best, bounds)
        final, n = energies(best, list(range(B)))
        iters = torch.full((B,), cfg.generations, dtype=torch.int64)
        return SolveResult(best, iters, final, n)


def _spread(scene, D: int, spread: tuple, like: torch.Tensor) -> torch.Tensor:
    """(D,) the particles' spread per DoF: (global translation mm, global rotation rad,
    joint angles rad) of ``spread`` placed in each model's slice."""
    out = torch.full((D,), spread[2], dtype=like.dtype)
    for sl in scene.slices.values():
        out[sl.start : sl.start + 3], out[sl.start + 3 : sl.start + 6] = spread[0], spread[1]
    return out.to(like.device)
