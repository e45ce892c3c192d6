"""The solvers of a frame: Algorithm 1 (alternating correspondences and
Levenberg-Marquardt steps, thesis Ch. 4.2) and what every solver shares.

A solver is an object with ``solve(tracker, start, previous, frames, cameras, ...) ->
SolveResult`` (the tracker gives it the scene, the terms, the states and the box) and
``recovers``: whether the tracker's recovery re-solve (:mod:`~torchhand.tracking.recovery`)
follows it. :data:`SOLVER_TYPES` maps ``TrackerConfig.solver`` to its class.
"""

from __future__ import annotations

from typing import List, NamedTuple, Optional, Sequence

import torch

from torchhand.core.profiling import stage
from torchhand.geometry.camera import Camera
from torchhand.optim.levenberg_marquardt import levenberg_marquardt
from torchhand.tracking.fused import FusedObjective, supports
from torchhand.tracking.objective import Objective, prepare_terms
from torchhand.tracking.views import same_camera

__all__ = ["SolveResult", "Algorithm1", "box_rows", "check_counts"]


class SolveResult(NamedTuple):
    """theta: (B, D); iterations: (B,) outer iterations; energy: (B,) per candidate
    correspondence (those without a correspondence charged their truncated square,
    :attr:`~torchhand.tracking.energies.Counts.unmatched`); correspondences: (B,) int64
    C_all at the last outer iteration."""

    theta: torch.Tensor
    iterations: torch.Tensor
    energy: torch.Tensor
    correspondences: torch.Tensor


def box_rows(bounds: tuple, rows) -> tuple:
    """The (lower, upper) of the problems ``rows`` (indices): rows of a per-problem box
    ((B, D) each), a shared (D,) box as it is."""
    lower, upper = bounds
    if lower.dim() == 1:
        return lower, upper
    rows = torch.as_tensor(rows, device=lower.device)
    return lower[rows], upper[rows]


def check_counts(B: int, V: int, frames: Sequence, cameras: Sequence, colours: Optional[Sequence]) -> None:
    """B x V frames and cameras (and colour frames), or a clear error."""
    if len(frames) != B * V or len(cameras) != B * V or (colours is not None and len(colours) != B * V):
        raise ValueError(f"give B x V = {B} x {V} frames and cameras (and colour frames), got {len(frames)}, "
                         f"{len(cameras)}" + ("" if colours is None else f" and {len(colours)}"))


class Algorithm1:
    """Algorithm 1 for a batch: alternate correspondences and LM steps.

    The data pixels are labelled at the start pose (``config.labels``) and keep these
    labels for the frame (the models move a few mm within a frame); visibility,
    silhouettes and correspondences are renewed in every outer iteration. A problem
    stops when its joints moved less than ``min_motion`` mm in an iteration, or when no
    LM step was accepted; only the problems still moving are solved further.
    """

    recovers = True

    def solve(self, tracker, start: torch.Tensor, previous: torch.Tensor, frames: List, cameras: Sequence[Camera],
              *, iterations: int, min_motion: float, colours: Optional[List] = None, views: int = 1,
              bounds: tuple, generator: Optional[torch.Generator] = None) -> SolveResult:
        """Arguments as :meth:`Tracker.solve <torchhand.tracking.tracker.Tracker.solve>`;
        ``bounds`` (lower, upper), each (D,) or (B, D); ``generator`` is not used."""
        cfg, scene = tracker.config, tracker.scene
        theta = tracker.clamp(start, bounds)  # within the bounds, as the solver keeps it (see Objective)
        B, V = theta.shape[0], int(views)
        check_counts(B, V, frames, cameras, colours)
        lower, upper = (x.to(theta.device) for x in bounds)
        iters = torch.zeros(B, dtype=torch.int64, device=theta.device)
        damping = theta.new_full((B,), 1e-3)
        energy = theta.new_zeros(B)
        counts = torch.zeros(B, dtype=torch.int64, device=theta.device)
        # Only the problems still moving are solved: `sub` lists them (on the host, from
        # the stopping rule's one sync), `idx` is the same on the device. `posed` and
        # `labels` belong to the problems of `idx` of the previous iteration.
        sub = list(range(B))
        idx = torch.arange(B, device=theta.device)
        frame_data: dict = {}  # the terms' data side of this solve
        shared = all(same_camera(c, cameras[0]) for c in cameras)  # once per solve (compares tensors)
        labels = None
        with torch.no_grad():
            posed = scene(theta, validate=False)
            box = tracker.frame_states.box(posed.vertices.repeat_interleave(V, 0), cameras, shared)
        for _ in range(iterations):
            vsub = [b * V + v for b in sub for v in range(V)]
            with stage("iteration"), torch.no_grad():
                view, state = tracker.frame_states.states(
                    theta[idx], previous[idx], [frames[j] for j in vsub], [cameras[j] for j in vsub], views=V,
                    colours=None if colours is None else [colours[j] for j in vsub],
                    problems=torch.tensor(vsub, device=theta.device), frame_data=frame_data, posed=posed,
                    labels=labels, shared=shared, box=box)
                labels = view.data_labels  # labelled once per frame, at its start pose
                prep = prepare_terms(tracker.terms, view, state, V)
                counts[idx] = prep.correspondences.to(counts.device)
                kind = FusedObjective if cfg.fused and supports(theta, V) else Objective
                objective = kind(scene, tracker.terms, prep.prepared, state.posed, V)

                def going(th, steps, objective=objective, state=state):
                    # a problem goes on while its joints move; one whose step was rejected
                    # after every retry moved nothing: its correspondences would not change
                    return (scene.joint_motion(state.posed, objective.current) >= min_motion) & (steps > 0)

                lo, hi = box_rows((lower, upper), idx)
                with stage("lm"):
                    res = levenberg_marquardt(objective, state.theta, lo, hi, max_iterations=cfg.inner_iterations,
                                              damping=damping[idx], retries=cfg.step_retries, keep_going=going)
                posed = objective.current
                theta[idx], damping[idx] = res.theta, res.damping
                energy[idx] = (res.cost + prep.unmatched.to(theta)) / prep.candidates.to(theta).clamp_min(1)
                iters[idx] += 1
                # the stopping rule: one host sync per outer iteration, read with the solver's
                # retry check when there is one
                with stage("host sync"):
                    flags = res.going if res.going is not None else going(res.theta, res.iterations).tolist()
            if not any(flags):
                break
            if not all(flags):
                sub = [b for b, g in zip(sub, flags) if g]
                idx = torch.tensor(sub, device=theta.device)
                keep = torch.tensor(flags, device=theta.device)
                labels, posed = labels[keep.repeat_interleave(V)], posed.select(keep)
        return SolveResult(theta, iters, energy, counts)
