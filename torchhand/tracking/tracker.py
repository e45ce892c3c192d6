"""The RGB-D tracker (thesis Ch. 4.2, Algorithm 1), batched over independent sequences.

For every frame, starting from the previous frame's pose (or a motion prediction,
:mod:`~torchhand.tracking.prediction`), the frame's solver
(:class:`~torchhand.tracking.solve.Algorithm1`, or HOPE's swarm,
:class:`~torchhand.tracking.swarm.Swarm`) minimises the energy of the tracker's terms
(:mod:`~torchhand.tracking.objective`) within a box of the joint limits grown to hold each
sequence's initial pose (``TrackerConfig.limit_slack``); a frame whose energy rose
sharply is re-solved (:mod:`~torchhand.tracking.recovery`). B sequences of the same scene
are tracked as one batch: their frames are independent problems that share every tensor
operation. Every problem has a rig of V >= 1 cameras (:mod:`~torchhand.tracking.views`).
"""

from __future__ import annotations

import collections
import itertools
import math
import time
from typing import Callable, Iterable, Iterator, List, NamedTuple, Optional, Sequence, Union

import numpy as np
import torch

from torchhand.core.profiling import stage
from torchhand.core.threads import intra_op_threads
from torchhand.geometry.camera import Camera
from torchhand.geometry.mesh import is_closed_outward
from torchhand.geometry.raycast import RayCaster
from torchhand.geometry.render import Renderer
from torchhand.model.scene import Scene
from torchhand.tracking.config import TrackerConfig
from torchhand.tracking.energies import EnergyTerm, parse_energy
from torchhand.tracking.energies.chain_smoothness import chain_pairs
from torchhand.tracking.prediction import predicted_start
from torchhand.tracking.preprocess import ColourFrame, DepthFrame, EmptyFrameError, preprocess_depth
from torchhand.tracking.recovery import recover
from torchhand.tracking.solve import Algorithm1, SolveResult, box_rows
from torchhand.tracking.swarm import Swarm
from torchhand.tracking.views import (CROP_MARGIN, ColourHistory, FrameStates, StateBuilder, crop_views, per_view,
                                      rigs_of)

__all__ = ["TrackerConfig", "FrameResult", "SolveResult", "Tracker", "predicted_start", "SOLVER_TYPES"]

#: a depth map in mm: (H, W) tensor or array, or None for a missing frame
Depth = Union[torch.Tensor, np.ndarray, None]

#: frames whose energies the recovery rule compares a frame with (the median of these)
ENERGY_HISTORY = 30

#: the solver object of each ``TrackerConfig.solver``
SOLVER_TYPES = {"lm": Algorithm1, "pso": Swarm}


class FrameResult(NamedTuple):
    """One tracked frame of B sequences: what the runner writes.

    Attributes:
        theta: (B, D) poses.
        valid: (B,) bool, False where a frame could not be used (the previous pose is kept).
        iterations: (B,) outer iterations spent.
        energy: (B,) final energy per candidate correspondence (see :meth:`Tracker.solve`);
            NaN where the frame was not used.
        recovered: (B,) bool, True where the recovery re-solve replaced the estimate.
        correspondences: (B,) int64 data correspondences (C_all) at the last outer iteration.
        notes: B strings, why a frame was flagged ("" when fine).
        seconds: wall time of the whole batch's frame.
    """

    theta: torch.Tensor
    valid: torch.Tensor
    iterations: torch.Tensor
    energy: torch.Tensor
    recovered: torch.Tensor
    correspondences: torch.Tensor
    notes: List[str]
    seconds: float


class Tracker:
    """Tracks a scene through depth frames.

    Args:
        scene: the models, in the order of their slices in theta.
        config: :class:`TrackerConfig`.
        terms: energy terms (default: ``parse_energy(config.energy, config.metric)``).
            Priors (``term.prior``) are prepared after the other terms, with the
            state's C_all known.

    The tracker keeps the energies of the last :data:`ENERGY_HISTORY` frames of the
    sequences it tracks, for the recovery rule; :meth:`reset` forgets them (a new set
    of sequences), as :meth:`track` does when it starts.
    """

    def __init__(self, scene: Scene, config: Optional[TrackerConfig] = None,
                 terms: Optional[List[EnergyTerm]] = None):
        config = TrackerConfig() if config is None else config
        if not isinstance(config, TrackerConfig):
            raise TypeError(f"config must be a TrackerConfig, got {type(config).__name__}")
        self.scene, self.config = scene, config
        self.terms = (list(terms) if terms is not None
                      else parse_energy(config.energy, config.metric, backend=config.neighbor_backend))
        for k, t in enumerate(self.terms):
            if not isinstance(t, EnergyTerm):
                raise TypeError(f"terms[{k}] must be an EnergyTerm, got {type(t).__name__}")
        if not any(not t.prior for t in self.terms):
            raise ValueError("terms need at least one data term (a term that is not a prior)")
        self._energy_history: collections.deque = collections.deque(maxlen=ENERGY_HISTORY)
        self.colour_history = ColourHistory(config.colour)  # the views' previous frames (optical flow)
        # back faces can be left out of the renders when every mesh is closed and outward
        cull = all(is_closed_outward(m.vertices_rest, m.faces) for m in scene.models)
        caster = RayCaster(scene.faces, config.render_backend, cull_back_faces=cull)
        self.renderer = Renderer(scene.faces, scene.face_model_id, scene.face_bone_id, caster=caster)
        self.frame_states = StateBuilder(scene, self.renderer, config.labels, config.label_distance,
                                         config.label_radius, config.neighbor_backend, config.render_margin,
                                         config.rig_budget)
        self.solver = SOLVER_TYPES[config.solver]()
        # the solvers' box: the joint limits widened by limit_slack (the limits themselves
        # are the soft ones of E_anatomy, Eq. 4.17), and per sequence grown to hold its
        # initial pose (reset)
        self._slack = math.inf if config.limit_slack is None else float(config.limit_slack)
        self._grown: Optional[tuple] = None
        #: whether the scene has a chain of like bones (the rope): the default motion
        #: prediction is off for it (TrackerConfig.motion_prediction)
        self.has_chains = len(chain_pairs(scene)) > 0

    @property
    def lower(self) -> torch.Tensor:
        """(D,) the joint limits widened by ``config.limit_slack`` (lower side)."""
        return self.scene.lower - self._slack

    @property
    def upper(self) -> torch.Tensor:
        """(D,) the joint limits widened by ``config.limit_slack`` (upper side)."""
        return self.scene.upper + self._slack

    @property
    def bounds(self) -> tuple:
        """The solvers' box (lower, upper): (B, D) rows grown to hold the initial poses
        of the last :meth:`reset`, or the (D,) widened limits."""
        return (self.lower, self.upper) if self._grown is None else self._grown

    def clamp(self, theta: torch.Tensor, bounds: Optional[tuple] = None) -> torch.Tensor:
        """Project theta into ``bounds`` ((lower, upper), each (D,) or (B, D); default
        :attr:`bounds`, the solvers' box)."""
        lower, upper = self.bounds if bounds is None else bounds
        return torch.maximum(torch.minimum(theta, upper), lower)

    def reset(self, init: Optional[torch.Tensor] = None) -> None:
        """Forget the energies and colour images of earlier frames (before tracking other
        sequences). ``init``: (B, D) initial poses of the sequences to track next; the
        solvers' box of each (:attr:`bounds`, (B, D) rows) is the joint limits widened by
        ``config.limit_slack`` and grown to hold its initial pose, so that a given pose
        outside the limits (the thesis' own motions leave them) is not pulled into them.
        Without ``init`` the box is the same for every problem."""
        self._energy_history.clear()
        self.colour_history.clear()
        self._grown = None
        if init is not None:
            init = init.detach()
            self._grown = (torch.minimum(self.lower.to(init), init), torch.maximum(self.upper.to(init), init))

    def _bounds_of(self, B: int) -> tuple:
        """The box of the B problems of a frame: :attr:`bounds`, whose rows (when it has
        them) must be the B sequences of the last :meth:`reset`."""
        lower, upper = self.bounds
        if lower.dim() == 2 and lower.shape[0] != B:
            raise ValueError(f"the tracker was reset with the initial poses of {lower.shape[0]} sequences, this frame "
                             f"has {B} problems: call reset(init) with this batch's initial poses (or reset())")
        return lower, upper

    def states(self, theta: torch.Tensor, frames: List[Optional[DepthFrame]], cameras: Sequence[Camera], *,
               previous: Optional[torch.Tensor] = None, colours: Optional[List[ColourFrame]] = None,
               views: int = 1) -> FrameStates:
        """What the terms see at the first outer iteration of a frame, at ``theta``
        (B, D): the scene rendered, the data labelled
        (:meth:`StateBuilder.states <torchhand.tracking.views.StateBuilder.states>`);
        ``frames``, ``cameras`` and ``colours`` per view problem (B x V); ``previous``
        (B, D): the previous frame's poses (default ``theta``). For preparing terms by
        hand (tests, learning pipelines)."""
        return self.frame_states.states(theta, theta if previous is None else previous, list(frames), list(cameras),
                                        views=views, colours=colours)

    def solve(self, start: torch.Tensor, previous: torch.Tensor, frames: List[Optional[DepthFrame]],
              cameras: Sequence[Camera], iterations: int, min_motion: Optional[float] = None,
              colours: Optional[List[ColourFrame]] = None, views: int = 1,
              bounds: Optional[tuple] = None) -> SolveResult:
        """Algorithm 1 for a batch (:class:`~torchhand.tracking.solve.Algorithm1`).

        With ``views`` V > 1 (camera rigs), ``frames``, ``cameras`` and ``colours`` hold
        B x V entries, problem-major (view v of problem b at b V + v); ``frames`` entries
        are None for colour views. A problem stops when its joints moved less than
        ``min_motion`` mm (default ``config.min_joint_motion``) in an iteration, or when
        no LM step was accepted. ``bounds``: the box (lower, upper), each (D,) or (B, D)
        (default: the joint limits widened by ``config.limit_slack``).
        """
        return Algorithm1().solve(self, start, previous, frames, cameras, iterations=iterations,
                                  min_motion=self.config.min_joint_motion if min_motion is None else min_motion,
                                  colours=colours, views=views,
                                  bounds=(self.lower, self.upper) if bounds is None else bounds)

    def swarm_solve(self, start: torch.Tensor, previous: torch.Tensor, frames: List[Optional[DepthFrame]],
                    cameras: Sequence[Camera], colours: Optional[List[ColourFrame]] = None, views: int = 1,
                    generator: Optional[torch.Generator] = None, bounds: Optional[tuple] = None) -> SolveResult:
        """HOPE for a batch (:class:`~torchhand.tracking.swarm.Swarm`); arguments as
        :meth:`solve`; ``generator`` draws the particles and the swarm's coefficients."""
        return Swarm().solve(self, start, previous, frames, cameras, iterations=0, min_motion=0.0, colours=colours,
                             views=views, bounds=(self.lower, self.upper) if bounds is None else bounds,
                             generator=generator)

    def track_frame(self, depths: Optional[Sequence], cameras: Sequence, previous: torch.Tensor,
                    first: bool = False, generator: Optional[torch.Generator] = None,
                    start: Optional[torch.Tensor] = None, colours: Optional[Sequence] = None) -> FrameResult:
        """Track one frame of each of B sequences.

        Args:
            depths: B depth maps (H, W) in mm (tensors or arrays), or None where a frame is
                missing; for camera rigs, B sequences of V depth maps. None: no depth
                (colour views only).
            cameras: B cameras, or B camera rigs (sequences of V cameras, the same V for
                every problem and one image size for every view).
            previous: (B, D) poses of the previous frame (or the initial poses).
            first: use the first-frame iteration budget.
            generator: draws the recovery perturbations (torch's global generator if None).
            start: (B, D) poses to start the solve from (default: ``previous``), e.g. a
                motion prediction; ``previous`` stays the reference of the temporal
                regularisation and the recovery.
            colours: None, or B colour images (H, W, 3) uint8 RGB (B sequences of V for
                rigs), or None where a frame is missing; an image may come as a
                :class:`~torchhand.tracking.preprocess.ColourView` (or ``(image, ignore,
                salient)`` tuple) with an (H, W) bool mask of pixels whose features are
                not used and the frame's salient point detections.
                The optical flow of a view is computed against the previous frame this
                tracker saw of it (:meth:`reset` forgets them).
        Returns:
            :class:`FrameResult`; problems without usable data keep ``previous``
            and are flagged invalid.
        Raises:
            ValueError: inputs of the wrong count, rigs of different sizes, a frame
            missing in some views of a problem but not in others, or terms that need
            depth (colour) without depth (colour) data.
        """
        t0 = time.perf_counter()
        cfg, B = self.config, previous.shape[0]
        rigs, V, nested = rigs_of(cameras, B)
        self._check_inputs(depths is not None, colours is not None)
        depth_views = per_view(depths, B, V, "depth", nested) if depths is not None else None
        colour_views = per_view(colours, B, V, "colour image", nested) if colours is not None else None
        if start is not None:
            start = self.scene.check_theta(start, "start")
            if start.shape[0] != B:
                raise ValueError(f"start must have one row per problem ({B}), got shape {tuple(start.shape)}")
        lower, upper = self._bounds_of(B)
        init = previous if start is None else self.clamp(start, (lower, upper))
        depth_views, rigs = self._cut_views(depth_views, colour_views, rigs, init)
        frames, cols, ok, notes = self._preprocess(depth_views, colour_views, rigs, previous)
        theta = previous.clone()
        valid, recovered = torch.zeros(B, dtype=torch.bool), torch.zeros(B, dtype=torch.bool)
        iters, counts = torch.zeros(B, dtype=torch.int64), torch.zeros(B, dtype=torch.int64)
        energy = previous.new_full((B,), float("nan"))
        if ok:
            idx = torch.tensor(ok)
            cams = [rigs[b][v] for b in ok for v in range(V)]
            cols = cols if colour_views is not None else None
            n_it = cfg.first_frame_iterations if first else cfg.max_iterations
            # the first frame refines a given initial pose: its whole budget is spent
            # unless the solver stops accepting steps (the thesis' 50 iterations)
            box = box_rows((lower, upper), idx)
            sol = self.solver.solve(self, init[idx], previous[idx], frames, cams, iterations=n_it,
                                    min_motion=0.0 if first else cfg.min_joint_motion, colours=cols, views=V,
                                    bounds=box, generator=generator)
            th, en = sol.theta, sol.energy
            if self.solver.recovers and not first and cfg.recover_tries > 0 and len(self._energy_history) >= 3:
                history = torch.stack(list(self._energy_history))[:, idx]
                th, en, rec = recover(self, th, en, previous[idx], frames, cams, iterations=n_it, history=history,
                                      generator=generator, colours=cols, views=V, bounds=box)
                recovered[idx] = rec.cpu()
            # never return NaN: a diverged problem keeps its previous pose and is flagged
            finite = torch.isfinite(th).all(1) & torch.isfinite(en)
            th = torch.where(finite[:, None], th, previous[idx])
            theta[idx], valid[idx], iters[idx], energy[idx] = th, finite.cpu(), sol.iterations.cpu(), en
            counts[idx] = sol.correspondences.cpu()
            for k, b in enumerate(ok):
                if not finite[k]:
                    notes[b] = "the solver diverged; previous pose kept"
                elif sol.correspondences[k] == 0:
                    notes[b] = "no correspondences (models out of view or far from the data)"
        self._energy_history.append(energy)
        return FrameResult(theta, valid, iters, energy, recovered, counts, notes, time.perf_counter() - t0)

    def _cut_views(self, depth_views, colour_views, rigs, start: torch.Tensor) -> tuple:
        """(depth views, rigs): a depth rig's views cut to the hands at ``start``
        (``TrackerConfig.crop_views``; not for colour views or terms reading whole
        frames), else as given."""
        cfg = self.config
        if (len(rigs[0]) == 1 or not cfg.crop_views or depth_views is None or colour_views is not None
                or any(t.whole_frames for t in self.terms)):
            return depth_views, rigs
        with torch.no_grad():
            vertices = self.scene(start, validate=False).vertices
        return crop_views(depth_views, rigs, vertices, self.renderer, cfg.render_margin + CROP_MARGIN)

    def _preprocess(self, depth_views, colour_views, rigs, previous: torch.Tensor) -> tuple:
        """The frames of the problems that have them, preprocessed: (depth frames and
        colour frames per view problem of the usable problems, their indices, B notes
        naming the problems without a frame)."""
        cfg, B = self.config, previous.shape[0]
        V = len(rigs[0])
        frames, cols, ok, notes = [], [], [], [""] * B
        for b in range(B):
            try:
                fr, co = [None] * V, [None] * V
                if depth_views is not None:
                    if depth_views[b] is None:
                        raise EmptyFrameError("missing depth frame")
                    with stage("preprocess", work=lambda: _preprocess_work(depth_views[b])):
                        fr = [preprocess_depth(d, rigs[b][v], cfg.preprocess, device=previous.device,
                                               dtype=previous.dtype) for v, d in enumerate(depth_views[b])]
                if colour_views is not None:
                    if colour_views[b] is None:
                        raise EmptyFrameError("missing colour frame")
                    co = [self.colour_history.frame(c, rigs[b][v], b * V + v, previous)
                          for v, c in enumerate(colour_views[b])]
                frames += fr
                cols += co
                ok.append(b)
            except EmptyFrameError as err:
                notes[b] = f"{err}; previous pose kept"
        return frames, cols, ok, notes

    def _check_inputs(self, has_depth: bool, has_colour: bool) -> None:
        """Every term's data is there: a clear error instead of a term without its images."""
        for t in self.terms:
            if t.needs == "depth" and not has_depth:
                raise ValueError(f"energy term {t.name!r} needs depth frames, but only colour images were given "
                                 "(colour terms: E edges, O optical flow)")
            if t.needs == "colour" and not has_colour:
                raise ValueError(f"energy term {t.name!r} needs colour images, but only depth frames were given "
                                 "(depth terms: LO, F, S)")

    def track(self, depths: Optional[Iterable[Sequence[Depth]]], cameras: Sequence, init: torch.Tensor,
              revise: Optional[Callable[[int, FrameResult], FrameResult]] = None,
              colours: Optional[Iterable[Sequence]] = None) -> Iterator[FrameResult]:
        """Track B sequences frame by frame from their initial poses.

        Args:
            depths: per frame, B depth maps (H, W) in mm or None (a sequence that has
                ended or lacks the frame keeps its pose and is flagged); for camera rigs,
                B sequences of V. None: colour views only.
            cameras: B cameras, or B camera rigs (:meth:`track_frame`).
            colours: per frame, the colour images of :meth:`track_frame`, or None
                (depth only); read in step with ``depths``.
            init: (B, D) initial poses (the first frame refines them with the
                first-frame budget).
            revise: called with (frame index, result) after each frame; what it returns
                is yielded and the next frame starts from its ``theta`` (the runner's
                re-initialisation of badly fitting frames).
        Yields:
            one :class:`FrameResult` per frame. The starts follow
            ``config.motion_prediction`` (of :attr:`has_chains`; no velocity is taken
            across a pose that ``revise`` replaced); the recovery perturbations are drawn from a
            generator seeded with ``config.seed``, so a run is repeatable.
        """
        cfg = self.config
        theta = self.scene.check_theta(init, "init")
        self.reset(theta)
        generator = torch.Generator().manual_seed(cfg.seed)
        history: collections.deque = collections.deque(maxlen=3)  # (theta, tracked) of the last frames
        if depths is None and colours is None:
            raise ValueError("give depth frames, colour frames or both")
        depth_frames = None if depths is None else iter(depths)
        colour_frames = None if colours is None else iter(colours)
        for f in itertools.count():
            with intra_op_threads(cfg.threads):  # restored before yielding to the caller
                try:
                    frame = None if depth_frames is None else next(depth_frames)
                    colour = None if colour_frames is None else next(colour_frames)
                except StopIteration:
                    return
                start = predicted_start(list(history), cfg.motion_prediction(self.has_chains), cfg.prediction_limiter)
                with stage("frame"):
                    res = self.track_frame(frame, cameras, theta, first=(f == 0), generator=generator, start=start,
                                           colours=colour)
                if revise is not None:
                    revised = revise(f, res)
                    # a pose the caller replaced (a re-initialisation) starts a new motion:
                    # the frames before it give it no velocity
                    same = (revised.theta == res.theta) | (revised.theta.isnan() & res.theta.isnan())
                    replaced = (~same).any(1).to(theta.device)
                    history = collections.deque([(th, ok & ~replaced) for th, ok in history], maxlen=3)
                    res = revised
            theta = res.theta
            history.append((theta, res.valid.to(theta.device)))
            yield res


def _preprocess_work(depths) -> tuple:
    """(flops, bytes) floor of preprocessing depth maps: every pixel read once; on the
    valid pixels the 5 x 5 bilateral filter, the Sobel normals and the edge test (about
    150 flops) and the points, normals and mask written (28 bytes)."""
    valid = sum(int((torch.as_tensor(np.asarray(d)) > 0).sum()) for d in depths)
    pixels = sum(int(np.prod(np.shape(d))) for d in depths)
    return 150.0 * valid, 4.0 * pixels + 28.0 * valid
