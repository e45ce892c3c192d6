"""The RGB-D tracker (thesis Ch. 4.2, Algorithm 1), batched over independent sequences.

For every frame, starting from the previous frame's pose, repeat until the joints
move less than 0.2 mm on average or the iteration budget is spent: render the scene at the
current pose, find the correspondences of every energy term, and take a
Levenberg-Marquardt step on the stacked residuals, within a box of the joint limits
grown to hold each sequence's initial pose (``TrackerConfig.limit_slack``). B sequences
of the same scene are tracked as one batch: their frames are independent problems that
share every tensor operation.
"""

from __future__ import annotations

import collections
import itertools
import math
import time
from dataclasses import dataclass, field
from typing import Callable, Iterable, Iterator, List, NamedTuple, Optional, Sequence, Union

import numpy as np
import torch

from torchhand.geometry.camera import Camera
from torchhand.geometry.mesh import is_closed_outward
from torchhand.core.check import skip_checks
from torchhand.geometry.raycast import BACKENDS, _box_of, default_backend
from torchhand.geometry.render import Renderer, RenderResult, window_map
from torchhand.model.scene import Scene, SceneOutput
from torchhand.optim.levenberg_marquardt import levenberg_marquardt
from torchhand.optim.pso import particle_swarm
from torchhand.tracking.energies import EnergyTerm, Prepared, TrackState, parse_energy
from torchhand.tracking.labels import LABELINGS, label_by_proximity, label_data
from torchhand.tracking.preprocess import (ColourConfig, ColourFrame, ColourView, DepthFrame, EmptyFrameError,
                                          PreprocessConfig, preprocess_colour, preprocess_depth)

__all__ = ["TrackerConfig", "FrameResult", "SolveResult", "Tracker", "predicted_start"]

#: a depth map in mm: (H, W) tensor or array, or None for a missing frame
Depth = Union[torch.Tensor, np.ndarray, None]

#: frames whose energies the recovery rule compares a frame with (the median of these)
ENERGY_HISTORY = 30

#: the solvers of a frame: Levenberg-Marquardt (Algorithm 1) or the particle swarm (HOPE)
SOLVERS = ("lm", "pso")

#: the spread of HOPE's particles about the start pose, per DoF: global translation (mm),
#: global rotation and joint angles (rad)
SWARM_SPREAD = (5.0, 0.05, 0.1)
#: the most pixels HOPE renders in one batch (particles x views x the solve's box; at
#: least one particle): one particle of 8 views of 1280x960 ran 1.4x faster than 8 in a
#: batch, and at 640x480 batches of 1 to 4 particles ran alike (docs/results.md)
SWARM_BATCH_PIXELS = 1 << 21


@dataclass
class TrackerConfig:
    """energy: terms (``LO+F``: model-to-data, data-to-model and free space, the best
    combination measured over the shared sequences, the windows and the rope, see
    docs/results.md "Objects, free space and physics"); metric: m2d distance; inner_iterations: LM steps per
    correspondence update (1 = the thesis' alternation); max_iterations: per frame (the
    thesis' i_thr); first_frame_iterations: for frame 0 (50 in the thesis);
    min_joint_motion: mm, convergence when the joints of every model move less than
    this on average in an iteration (the thesis' criterion, 0.2 mm);
    step_retries: a rejected LM step is retried with ten times the damping up to this
    many times before the correspondences are renewed (the retries reuse them and
    the Jacobian); a problem whose retries all fail has converged;
    recover_factor: a frame whose energy (per candidate correspondence, those
    without a correspondence charged min(distance, cut-off)^2) exceeds
    this multiple of the median of the previous frames is re-solved from ``recover_tries`` random
    perturbations of the previous pose (the best is kept if it is better); seed: of
    those perturbations in :func:`track_sequences`, so a run is repeatable;
    labels: how data pixels are assigned to models (:mod:`torchhand.tracking.labels`):
    ``"proximity"`` (the default), the model nearest in 3D within ``label_distance`` mm,
    or ``"rendered"``, the nearest rendered model in the image within ``label_radius``
    px (it hands background data beside a model to the model, which hides free space);
    prediction: a frame's solve starts from the previous pose plus
    ``prediction`` times the last step (:func:`predicted_start`, clamped to the joint
    limits): 0 starts from the previous pose as the thesis does, 1 is a
    constant-velocity prediction, None (the default) is 0 for energies with depth
    terms and 1 for colour views only (Ballan's features let the hands drift behind a
    fast motion without it: 4.9 against 1.7 mm on the ball sequence of
    docs/results.md's Table 1); prediction_limiter: per DoF, the smaller of the last
    two steps when they have the same sign and 0 otherwise (minmod), so that
    frame-to-frame jitter is not extrapolated. The temporal regularisation (Eq. 4.18)
    and the recovery keep the previous pose as their reference.
    backend: of the renders (``"warp"``, ``"warp-raycast"`` or ``"open3d"``,
    :mod:`torchhand.geometry.raycast`) and, with it, of the neighbour searches (Warp for
    the Warp backends, the CPU reference for open3d); None: Warp when installed;
    render_margin: px around the projection of a solve's start poses that its renders
    cover (the models move a few mm within a frame: 48 px are about 40 mm at 450 mm; a
    model that leaves the box loses the pixels outside it for that frame); colour: the
    preprocessing of colour views (:class:`~torchhand.tracking.preprocess.ColourConfig`);
    solver: ``"lm"`` (Algorithm 1, Levenberg-Marquardt) or ``"pso"``, the HOPE baseline
    of Ballan et al. (Oikonomidis et al.'s particle swarm over the same energy,
    :meth:`Tracker.swarm_solve`) with ``particles`` particles and ``generations``
    generations (HOPE64: 64 and 40); limit_slack: the solvers keep each sequence's θ in
    a box, the joint limits widened by this many radians and grown to hold the
    sequence's initial pose (:meth:`Tracker.reset`); None: no box, the soft limits of
    E_anatomy (Eq. 4.17) alone. The thesis' own tracked motions leave the limits (by up
    to 0.8 rad): a box at the limits alone held a window of sequence 11, whose first pose
    is outside them, at 4.8 mm; no box at all lets weakly seen joints drift (1.8 against
    1.2 mm on the demo's first frames in 8 colour views); see docs/results.md "Joint
    limits"."""

    energy: str = "LO+F"
    metric: str = "point-to-plane"
    inner_iterations: int = 1
    max_iterations: int = 50
    first_frame_iterations: int = 50
    min_joint_motion: float = 0.2
    step_retries: int = 4
    recover_factor: float = 4.0
    recover_tries: int = 4
    perturbation: float = 0.15
    seed: int = 0
    labels: str = "proximity"
    label_distance: float = 30.0
    label_radius: float = 40.0
    prediction: Optional[float] = None
    prediction_limiter: bool = True
    preprocess: PreprocessConfig = field(default_factory=PreprocessConfig)
    colour: ColourConfig = field(default_factory=ColourConfig)
    backend: Optional[str] = None
    render_margin: int = 48
    solver: str = "lm"
    particles: int = 64
    generations: int = 40
    limit_slack: Optional[float] = 0.0

    def __post_init__(self) -> None:
        if self.prediction is not None and (isinstance(self.prediction, bool)
                                            or not isinstance(self.prediction, (int, float))
                                            or not math.isfinite(self.prediction) or self.prediction < 0):
            raise ValueError(f"prediction must be a finite number >= 0 or None, got {self.prediction!r}")
        if not isinstance(self.prediction_limiter, bool):
            raise ValueError(f"prediction_limiter must be True or False, got {self.prediction_limiter!r}")
        if self.labels not in LABELINGS:
            raise ValueError(f"labels must be one of {LABELINGS}, got {self.labels!r}")
        if not self.label_distance > 0:
            raise ValueError(f"label_distance must be > 0 (mm), got {self.label_distance!r}")
        if self.solver not in SOLVERS:
            raise ValueError(f"solver must be one of {SOLVERS}, got {self.solver!r}")
        if not (isinstance(self.particles, int) and self.particles >= 2 and isinstance(self.generations, int)
                and self.generations >= 0):
            raise ValueError(f"need particles >= 2 and generations >= 0, got {self.particles!r}, {self.generations!r}")
        if self.backend is not None and self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS} or None, got {self.backend!r}")
        if self.limit_slack is not None and (isinstance(self.limit_slack, bool)
                                             or not isinstance(self.limit_slack, (int, float))
                                             or not 0 <= self.limit_slack < math.inf):
            raise ValueError(f"limit_slack must be a finite number >= 0 (radians) or None (no box), "
                             f"got {self.limit_slack!r}")

    @property
    def motion_prediction(self) -> float:
        """The prediction a run uses: ``prediction``, or when None, 1 (constant velocity)
        for an energy of colour views only (no ``LO``) and 0 (the thesis) otherwise."""
        if self.prediction is not None:
            return float(self.prediction)
        return 0.0 if "LO" in self.energy.replace(" ", "").split("+") else 1.0

    @property
    def render_backend(self) -> str:
        """The backend the renders use (``backend``, or Warp when installed)."""
        return default_backend() if self.backend is None else self.backend

    @property
    def neighbor_backend(self) -> str:
        """``"warp"`` with a Warp render backend, else scipy on the CPU (``"cpu"``)."""
        return "warp" if self.render_backend.startswith("warp") else "cpu"


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


class SolveResult(NamedTuple):
    """theta: (B, D); iterations: (B,) outer iterations; energy: (B,) per candidate
    correspondence; correspondences: (B,) int64 C_all at the last outer iteration."""

    theta: torch.Tensor
    iterations: torch.Tensor
    energy: torch.Tensor
    correspondences: torch.Tensor


def _same_camera(a: Camera, b: Camera) -> bool:
    return a is b or (a.width == b.width and a.height == b.height and torch.equal(a.K, b.K)
                      and torch.equal(a.T_cw, b.T_cw))


class Objective:
    """The stacked residuals of prepared terms, as the solver calls them:
    ``objective(theta, jacobian) -> (r (B, m), J (B, m, D) or None)``.

    It poses the scene once per theta it is called with and follows the solver's
    accepted steps (:meth:`accept`), so that :attr:`current` is the scene posed at the
    solver's theta without posing it again, and without comparing tensors (a host sync).
    The solver's first call is at its start clamped to the bounds: ``theta`` (with its
    ``posed`` scene) must lie within them, so that this call reuses ``posed``.
    """

    def __init__(self, scene: Scene, terms: Sequence[EnergyTerm], theta: torch.Tensor, posed: SceneOutput,
                 views: int = 1):
        self.scene, self.terms, self.views = scene, list(terms), int(views)
        self.current = posed  # the scene at the solver's current theta
        self._first, self._last = True, (theta, posed)  # the latest theta evaluated and its pose
        self._rep = None if self.views == 1 else torch.arange(theta.shape[0], device=theta.device).repeat_interleave(self.views)

    def __call__(self, theta: torch.Tensor, jacobian: bool):
        if self._first:  # the start (clamping a theta within the bounds changes no value)
            self._first, posed = False, self.current
        elif theta is self._last[0]:
            posed = self._last[1]
        else:
            posed = self.scene(theta, validate=False)
            self._last = (theta, posed)
        if self._rep is None:
            parts = [t.residuals(theta, posed, jacobian) for t in self.terms]
        else:  # the terms that read images see the B x V view problems: stack each problem's views
            B, D = theta.shape
            per_view = [t for t in self.terms if t.needs is not None]
            th_v, posed_v = (theta[self._rep], posed.select(self._rep)) if per_view else (None, None)
            parts = []
            for t in self.terms:
                if t.needs is None:
                    parts.append(t.residuals(theta, posed, jacobian))
                    continue
                res = t.residuals(th_v, posed_v, jacobian)
                parts.append(res._replace(r=res.r.reshape(B, -1),
                                          J=None if res.J is None else res.J.reshape(B, -1, D)))
        r = torch.cat([p.r for p in parts], 1)
        J = torch.cat([p.J for p in parts], 1) if jacobian else None
        return r, J

    def accept(self, mask: torch.Tensor) -> None:
        """The solver took the latest candidate for the problems of ``mask`` (B,) bool."""
        cand = self._last[1]
        self.current = SceneOutput(*(_where(mask, a, b) for a, b in zip(cand[:2], self.current[:2])),
                                   [type(mc)(*(_where(mask, a, b) for a, b in zip(mc, mo)))
                                    for mc, mo in zip(cand.models, self.current.models)])


def _where(mask: torch.Tensor, a, b):
    if not isinstance(a, torch.Tensor):
        return a
    return torch.where(mask.view(-1, *([1] * (a.dim() - 1))), a, b)


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

    def __init__(self, scene: Scene, config: TrackerConfig = TrackerConfig(),
                 terms: Optional[List[EnergyTerm]] = None):
        self.scene, self.config = scene, config
        self.terms = (list(terms) if terms is not None
                      else parse_energy(config.energy, config.metric, backend=config.neighbor_backend))
        for k, t in enumerate(self.terms):
            if not isinstance(t, EnergyTerm):
                raise TypeError(f"terms[{k}] must be an EnergyTerm, got {type(t).__name__}")
        if not any(not t.prior for t in self.terms):
            raise ValueError("terms need at least one data term (a term that is not a prior)")
        self._energy_history: collections.deque = collections.deque(maxlen=ENERGY_HISTORY)
        self._last_gray: dict = {}  # view problem -> (grey image, ignored pixels) of its previous frame (flow)
        # back faces can be left out of the renders when every mesh is closed and outward
        cull = all(is_closed_outward(m.vertices_rest, m.faces) for m in scene.models)
        self.renderer = Renderer(scene.faces, scene.face_model_id, scene.face_bone_id, backend=config.render_backend,
                                 cull_back_faces=cull)
        # the solvers' box: the joint limits widened by limit_slack (the limits themselves
        # are the soft ones of E_anatomy, Eq. 4.17), and per sequence grown to hold its
        # initial pose (reset)
        self._slack = math.inf if config.limit_slack is None else float(config.limit_slack)
        self._grown: Optional[tuple] = None

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
        self._last_gray.clear()
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

    # ------------------------------------------------------------------ frames
    def _render(self, vertices: torch.Tensor, cameras: Sequence[Camera], slots: torch.Tensor,
                shared: bool, box: Optional[tuple]) -> RenderResult:
        """One render call for the batch: one camera for all (``shared``), or one per problem."""
        with skip_checks():  # the library's own posed vertices
            # the terms read the pixels near the models: maps of the box only (RenderResult.origin)
            if shared:
                return self.renderer(vertices, cameras[0], normals=False, slots=slots, box=box, crop=True)
            r = self.renderer(vertices, list(cameras), normals=False, per_problem=True, slots=slots, box=box,
                              crop=True)
        return r.maps(lambda x: x[:, 0])

    def _box(self, vertices: torch.Tensor, cameras: Sequence[Camera], shared: bool) -> tuple:
        """The pixel box the solve renders in: the projections of its start poses, widened
        by ``config.render_margin`` px for the motion within the frame (one host sync per
        solve)."""
        cams = [cameras[0]] if shared else list(cameras)
        views = self.renderer._views(cams, not shared, vertices.shape[0], vertices.device)
        b = _box_of(vertices.detach().to(torch.float32), views)
        m, H, W = self.config.render_margin, views.height, views.width
        lo, hi = b.amin(0).tolist(), b.amax(0).tolist()
        return (max(lo[0] - m, 0), min(hi[1] + m, H), max(lo[2] - m, 0), min(hi[3] + m, W))

    def _state(self, theta, previous, frames, cameras, **kwargs) -> TrackState:
        """The state of the first outer iteration of one view per problem (the terms' tests)."""
        return self._states(theta, previous, frames, cameras, **kwargs)[0]

    def _states(self, theta, previous, frames, cameras, problems=None, frame_data=None, posed=None,
                labels=None, shared=None, box=None, colours=None, views: int = 1):
        """The states of one outer iteration: (view state, pose state) (``TrackState``);
        one object with one view. ``frames``, ``cameras``, ``colours`` and ``problems``
        are per view problem; ``theta``, ``previous`` and ``posed`` per problem."""
        V, nb = views, theta.shape[0]
        problems = torch.arange(nb * V, device=theta.device) if problems is None else problems
        frame_data = {} if frame_data is None else frame_data
        shared = all(_same_camera(c, cameras[0]) for c in cameras) if shared is None else shared
        posed = posed if posed is not None else self.scene(theta, validate=False)
        if V == 1:
            th_v, prev_v, posed_v = theta, previous, posed
        else:
            rep = torch.arange(nb, device=theta.device).repeat_interleave(V)
            th_v, prev_v, posed_v = theta[rep], previous[rep], posed.select(rep)
        rend = self._render(posed_v.vertices.detach(), cameras, problems, shared, box)
        if labels is None:  # once per frame, at its start pose
            H, W = cameras[0].height, cameras[0].width
            if all(f is None for f in frames):  # colour views: no data pixels to label (a 1 x 1 map each)
                labels = torch.full((len(frames), 1, 1), -1, dtype=torch.int64, device=rend.model_id.device)
            elif self.config.labels == "proximity":
                labels = label_by_proximity(frames, cameras, posed_v.vertices, self.scene.vertex_model_id,
                                            self.config.label_distance, self.config.neighbor_backend)
            else:  # OpenCV on the CPU, on whole images
                ids = window_map(rend.model_id, rend.origin, (0, H, 0, W), -1)
                labels = torch.stack([label_data(f, ids[b], self.config.label_radius) for b, f in enumerate(frames)])
        view = TrackState(self.scene, th_v, prev_v, posed_v, frames, cameras, rend, labels, problems=problems,
                          frame_data=frame_data, box=box, colours=colours)
        if V == 1:
            return view, view
        first = slice(0, None, V)  # each problem seen by its first view
        pose = TrackState(self.scene, theta, previous, posed, frames[first], cameras[first],
                          rend.maps(lambda x: x[first]), labels[first],
                          problems=problems[first] // V, frame_data=frame_data, box=box,
                          colours=None if colours is None else colours[first])
        return view, pose

    def _prepare(self, view: TrackState, pose: TrackState, views: int = 1):
        """Prepare every term: the data terms (on the view problems, summed per problem),
        then the priors with C_all known. Returns (C_all (B,), candidates (B,), unmatched
        energy (B,))."""
        nb = pose.theta.shape[0]

        def summed(x):
            return x.view(nb, views).sum(1)

        found = []
        for t in self.terms:
            if t.prior:
                continue
            if views == 1 or t.needs is None:
                found.append(t.prepare(pose))
            else:
                f = t.prepare(view)
                found.append(Prepared(summed(f.correspondences), summed(f.candidates), summed(f.unmatched),
                                      {k: summed(v) for k, v in f.diagnostics.items()}))
        pose.correspondences = sum(f.correspondences for f in found)
        found += [t.prepare(pose) for t in self.terms if t.prior]
        return pose.correspondences, sum(f.candidates for f in found), sum(f.unmatched for f in found)

    def solve(self, start: torch.Tensor, previous: torch.Tensor, frames: List[Optional[DepthFrame]],
              cameras: Sequence[Camera], iterations: int, min_motion: Optional[float] = None,
              colours: Optional[List[ColourFrame]] = None, views: int = 1,
              bounds: Optional[tuple] = None) -> SolveResult:
        """Algorithm 1 for a batch: alternate correspondences and LM steps.

        The data pixels are labelled at the start pose (``config.labels``) and keep
        these labels for the frame (the models move a few mm within a frame);
        visibility, silhouettes
        and correspondences are renewed in every iteration.

        With ``views`` V > 1 (camera rigs), ``frames``, ``cameras`` and ``colours`` hold
        B x V entries, problem-major (view v of problem b at b V + v); ``frames`` entries
        are None for colour views.

        A problem stops when its joints moved less than ``min_motion`` mm (default
        ``config.min_joint_motion``) in an iteration, or when no LM step was accepted.
        ``bounds``: the box (lower, upper), each (D,) or (B, D) (default: the joint
        limits widened by ``config.limit_slack``).

        Returns :class:`SolveResult`: the energy is per candidate correspondence, a
        candidate without a correspondence charged its truncated square
        (:attr:`Prepared.unmatched`).
        """
        bounds = (self.lower, self.upper) if bounds is None else bounds
        theta = self.clamp(start, bounds)  # within the bounds, as the solver keeps it (see Objective)
        B, V = theta.shape[0], int(views)
        if len(frames) != B * V or len(cameras) != B * V or (colours is not None and len(colours) != B * V):
            raise ValueError(f"give B x V = {B} x {V} frames and cameras (and colour frames), got {len(frames)}, "
                             f"{len(cameras)}" + ("" if colours is None else f" and {len(colours)}"))
        lower, upper = (x.to(theta.device) for x in bounds)
        min_motion = self.config.min_joint_motion if min_motion is None else min_motion
        iters = torch.zeros(B, dtype=torch.int64, device=theta.device)
        damping = theta.new_full((B,), 1e-3)
        energy = theta.new_zeros(B)
        counts = torch.zeros(B, dtype=torch.int64, device=theta.device)
        # Only the problems still moving are solved: `sub` lists them (on the host, from
        # the stopping rule's one sync), `idx` is the same on the device. `posed` and
        # `labels` belong to the problems of `idx` of the previous iteration.
        sub = list(range(B))
        idx = torch.arange(B, device=theta.device)
        posed, labels = None, None
        frame_data: dict = {}  # the terms' data side of this solve
        shared = all(_same_camera(c, cameras[0]) for c in cameras)  # once per solve (compares tensors)
        with torch.no_grad():
            posed = self.scene(theta, validate=False)
            box = self._box(posed.vertices if V == 1 else posed.vertices.repeat_interleave(V, 0), cameras, shared)
        for it in range(iterations):
            vsub = [b * V + v for b in sub for v in range(V)]
            with torch.no_grad():
                view, state = self._states(theta[idx], previous[idx], [frames[j] for j in vsub],
                                          [cameras[j] for j in vsub],
                                          idx if V == 1 else torch.tensor(vsub, device=theta.device), frame_data,
                                          posed, labels, shared, box,
                                          None if colours is None else [colours[j] for j in vsub], V)
                labels = view.data_labels  # labelled once per frame, at its start pose
                count, candidates, unmatched = self._prepare(view, state, V)
                counts[idx] = count.to(counts.device)
                objective = Objective(self.scene, self.terms, state.theta, state.posed, V)

                def going(th, steps, objective=objective, state=state):
                    # a problem goes on while its joints move; one whose step was rejected
                    # after every retry moved nothing: its correspondences would not change
                    return (self.scene.joint_motion(state.posed, objective.current) >= min_motion) & (steps > 0)

                lo, hi = _box_rows((lower, upper), idx)
                res = levenberg_marquardt(objective, state.theta, lo, hi,
                                          max_iterations=self.config.inner_iterations, damping=damping[idx],
                                          retries=self.config.step_retries, status=going)
                posed = objective.current
            theta[idx], damping[idx] = res.theta, res.damping
            energy[idx] = (res.cost + unmatched.to(theta)) / candidates.to(theta).clamp_min(1)
            iters[idx] += 1
            # the stopping rule: one host sync per outer iteration, read with the solver's
            # retry check when there is one
            flags = res.status if res.status is not None else going(res.theta, res.iterations).tolist()
            if not any(flags):
                break
            if not all(flags):
                sub = [b for b, g in zip(sub, flags) if g]
                idx = torch.tensor(sub, device=theta.device)
                keep = torch.tensor(flags, device=theta.device)
                labels, posed = labels[keep.repeat_interleave(V) if V > 1 else keep], posed.select(keep)
        return SolveResult(theta, iters, energy, counts)

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
        rigs, V, nested = _rigs(cameras, B)
        self._check_inputs(depths is not None, colours is not None)
        depth_views = _per_view(depths, B, V, "depth", nested) if depths is not None else None
        colour_views = _per_view(colours, B, V, "colour image", nested) if colours is not None else None
        if start is not None:
            start = self.scene.check_theta(start, "start")
            if start.shape[0] != B:
                raise ValueError(f"start must have one row per problem ({B}), got shape {tuple(start.shape)}")
        lower, upper = self._bounds_of(B)
        init = previous if start is None else self.clamp(start, (lower, upper))
        frames, cols, ok, notes = [], [], [], [""] * B
        for b in range(B):
            try:
                fr, co = [None] * V, [None] * V
                if depth_views is not None:
                    if depth_views[b] is None:
                        raise EmptyFrameError("missing depth frame")
                    fr = [preprocess_depth(d, rigs[b][v], cfg.preprocess, device=previous.device, dtype=previous.dtype)
                          for v, d in enumerate(depth_views[b])]
                if colour_views is not None:
                    if colour_views[b] is None:
                        raise EmptyFrameError("missing colour frame")
                    co = [self._colour_frame(c, rigs[b][v], b * V + v, previous) for v, c in enumerate(colour_views[b])]
                frames += fr
                cols += co
                ok.append(b)
            except EmptyFrameError as err:
                notes[b] = f"{err}; previous pose kept"
        theta = previous.clone()
        valid = torch.zeros(B, dtype=torch.bool)
        iters = torch.zeros(B, dtype=torch.int64)
        energy = previous.new_full((B,), float("nan"))
        recovered = torch.zeros(B, dtype=torch.bool)
        counts = torch.zeros(B, dtype=torch.int64)
        if ok:
            idx = torch.tensor(ok)
            cams = [rigs[b][v] for b in ok for v in range(V)]
            cols = cols if colour_views is not None else None
            n_it = cfg.first_frame_iterations if first else cfg.max_iterations
            # the first frame refines a given initial pose: its whole budget is spent
            # unless the solver stops accepting steps (the thesis' 50 iterations)
            box = _box_rows((lower, upper), idx)
            if cfg.solver == "pso":
                sol = self.swarm_solve(init[idx], previous[idx], frames, cams, cols, V, generator, box)
            else:
                sol = self.solve(init[idx], previous[idx], frames, cams, n_it, 0.0 if first else None, cols, V, box)
            th, en = sol.theta, sol.energy
            if cfg.solver == "lm" and not first and cfg.recover_tries > 0 and len(self._energy_history) >= 3:
                th, en, rec = self._recover(th, en, previous[idx], frames, cams, n_it, idx, generator, cols, V, box)
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

    def swarm_solve(self, start: torch.Tensor, previous: torch.Tensor, frames: List[Optional[DepthFrame]],
                    cameras: Sequence[Camera], colours: Optional[List[ColourFrame]] = None, views: int = 1,
                    generator: Optional[torch.Generator] = None, bounds: Optional[tuple] = None) -> SolveResult:
        """HOPE for a batch (Oikonomidis et al. 2011, the baseline of Ballan et al.'s
        Table 1): a particle swarm (:func:`torchhand.optim.pso.particle_swarm`) over the
        energy Levenberg-Marquardt minimises, each particle's correspondences found at its
        own pose (the terms' prepare), its fitness the energy per candidate correspondence
        (:meth:`solve`'s). ``config.particles`` particles are drawn about the start pose
        (:data:`SWARM_SPREAD`; the first is the start itself), ``config.generations``
        generations follow; velocities are limited to twice the spread. Arguments as
        :meth:`solve`; ``generator`` draws the particles and the swarm's coefficients."""
        cfg, V = self.config, int(views)
        bounds = (self.lower, self.upper) if bounds is None else bounds
        theta = self.clamp(start, bounds)
        B, D = theta.shape
        P = cfg.particles
        generator = torch.Generator().manual_seed(cfg.seed) if generator is None else generator
        frame_data: dict = {}
        shared = all(_same_camera(c, cameras[0]) for c in cameras)
        with torch.no_grad():
            posed = self.scene(theta, validate=False)
            box = self._box(posed.vertices if V == 1 else posed.vertices.repeat_interleave(V, 0), cameras, shared)
            view, pose = self._states(theta, previous, frames, cameras, None, frame_data, posed, None, shared, box,
                                      colours, V)
            labels = view.data_labels
            self._prepare(view, pose, V)  # the terms' data side, once for the frame
        spread = torch.full((D,), SWARM_SPREAD[2], dtype=theta.dtype)
        for sl in self.scene.slices.values():
            spread[sl.start : sl.start + 3], spread[sl.start + 3 : sl.start + 6] = SWARM_SPREAD[0], SWARM_SPREAD[1]
        spread = spread.to(theta.device)
        noise = torch.randn(B, P, D, generator=generator, dtype=theta.dtype).to(theta.device) * spread
        noise[:, 0] = 0
        # particles per batch of renders (their data sides are gathered per view problem):
        # as many as keep a batch's maps within SWARM_BATCH_PIXELS, at least one; larger
        # maps are fresh memory on every call (page faults), which costs more than drawing
        pixels = max(1, (box[1] - box[0]) * (box[3] - box[2]) * V)
        chunk = max(1, SWARM_BATCH_PIXELS // pixels)

        def energies(th: torch.Tensor, owner: List[int]) -> tuple:
            """(energy (N,), C_all (N,)) of poses th (N, D) of the problems ``owner``."""
            out, counts = [], []
            for c0 in range(0, len(owner), chunk):
                js = list(range(c0, min(c0 + chunk, len(owner))))
                vsub = [owner[j] * V + v for j in js for v in range(V)]
                prob = torch.tensor([owner[j] for j in js], device=theta.device)
                vidx = torch.tensor(vsub, device=theta.device)
                with torch.no_grad():
                    sv, sp = self._states(th[js], previous[prob], [frames[i] for i in vsub], [cameras[i] for i in vsub],
                                          vidx, frame_data, None, labels[vidx.to(labels.device)], shared, box,
                                          None if colours is None else [colours[i] for i in vsub], V)
                    count, cand, unmatched = self._prepare(sv, sp, V)
                    r, _ = Objective(self.scene, self.terms, sp.theta, sp.posed, V)(sp.theta, False)
                out.append(((r ** 2).sum(1) + unmatched.to(r)) / cand.to(r).clamp_min(1))
                counts.append(count.cpu())
            return torch.cat(out), torch.cat(counts)

        owners = [b for b in range(B) for _ in range(P)]
        res = particle_swarm(lambda pos: energies(pos.reshape(B * P, D), owners)[0].view(B, P), theta[:, None] + noise,
                             bounds[0], bounds[1], cfg.generations, velocity_scale=2 * spread,
                             generator=generator)
        best = self.clamp(res.best, bounds)
        final, n = energies(best, list(range(B)))
        iters = torch.full((B,), cfg.generations, dtype=torch.int64)
        return SolveResult(best, iters, final, n)

    def _check_inputs(self, has_depth: bool, has_colour: bool) -> None:
        """Every term's data is there: a clear error instead of a term without its images."""
        for t in self.terms:
            if t.needs == "depth" and not has_depth:
                raise ValueError(f"energy term {t.name!r} needs depth frames, but only colour images were given "
                                 "(colour terms: E edges, O optical flow)")
            if t.needs == "colour" and not has_colour:
                raise ValueError(f"energy term {t.name!r} needs colour images, but only depth frames were given "
                                 "(depth terms: LO, F, S)")

    def _colour_frame(self, item, camera: Camera, key: int, like: torch.Tensor) -> ColourFrame:
        """A colour view preprocessed, with the previous frame this tracker saw of it."""
        view = ColourView(*item) if isinstance(item, tuple) else ColourView(item)
        prev, prev_ignore = self._last_gray.get(key, (None, None))
        if prev is not None and prev.shape != (camera.height, camera.width):
            prev, prev_ignore = None, None
        frame = preprocess_colour(view.image, camera, self.config.colour, prev, view.ignore, device=like.device,
                                  dtype=like.dtype, salient=view.salient, previous_ignore=prev_ignore)
        self._last_gray[key] = (frame.gray, view.ignore)
        return frame

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
            ``config.motion_prediction``; the recovery perturbations are drawn from a
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
            try:
                frame = None if depth_frames is None else next(depth_frames)
                colour = None if colour_frames is None else next(colour_frames)
            except StopIteration:
                return
            start = predicted_start(list(history), cfg.motion_prediction, cfg.prediction_limiter)
            res = self.track_frame(frame, cameras, theta, first=(f == 0), generator=generator, start=start,
                                   colours=colour)
            if revise is not None:
                res = revise(f, res)
            theta = res.theta
            history.append((theta, res.valid.to(theta.device)))
            yield res

    def _recover(self, theta, energy, previous, frames, cameras, iterations, idx, generator, colours=None, views=1,
                 bounds=None):
        """Re-solve problems whose energy rose sharply, from perturbed previous poses
        (``bounds``: the box of each problem, as :meth:`solve`'s)."""
        hist = torch.stack(list(self._energy_history))[:, idx]
        ref = torch.nanmedian(hist, 0).values
        bad = torch.nonzero(energy > self.config.recover_factor * ref)[:, 0].tolist()
        rec = torch.zeros(len(energy), dtype=torch.bool)
        if not bad:
            return theta, energy, rec
        R, V = self.config.recover_tries, views
        starts, fr, cams, prev, cols = [], [], [], [], []
        # every try perturbs the previous pose (the unperturbed start was just solved):
        # the joints by N(0, perturbation) rad, the global pose by N(0, 4 mm / 0.03 rad)
        scale = torch.full((previous.shape[1],), self.config.perturbation, dtype=previous.dtype)
        for s in self.scene.slices.values():
            scale[s.start : s.start + 3], scale[s.start + 3 : s.start + 6] = 4.0, 0.03
        for b in bad:
            for r in range(R):
                noise = torch.randn(previous.shape[1], generator=generator, dtype=previous.dtype) * scale
                starts.append(previous[b] + noise.to(previous.device))
                fr += frames[b * V : (b + 1) * V]
                cams += cameras[b * V : (b + 1) * V]
                cols += [] if colours is None else colours[b * V : (b + 1) * V]
                prev.append(previous[b])
        bounds = (self.lower, self.upper) if bounds is None else _box_rows(bounds, [b for b in bad for _ in range(R)])
        sol = self.solve(self.clamp(torch.stack(starts), bounds), torch.stack(prev), fr, cams, iterations,
                         colours=None if colours is None else cols, views=V, bounds=bounds)
        th, en = sol.theta, sol.energy
        for i, b in enumerate(bad):
            best = int(torch.argmin(en[i * R : (i + 1) * R]))
            if en[i * R + best] < energy[b]:
                theta[b], energy[b], rec[b] = th[i * R + best], en[i * R + best], True
        return theta, energy, rec


def _box_rows(bounds: tuple, rows) -> tuple:
    """The (lower, upper) of the problems ``rows`` (indices): rows of a per-problem box
    ((B, D) each), a shared (D,) box as it is."""
    lower, upper = bounds
    if lower.dim() == 1:
        return lower, upper
    rows = torch.as_tensor(rows, device=lower.device)
    return lower[rows], upper[rows]


def predicted_start(history: Sequence[tuple], factor: float, limiter: bool = True) -> Optional[torch.Tensor]:
    """The pose to start the next frame from: ``theta_{t-1} + factor * step``.

    Args:
        history: ``(theta (B, D), tracked (B,) bool)`` of the last frames, oldest first;
            the last one is the previous frame.
        factor: the prediction (0: none, 1: constant velocity).
        limiter: the step is, per DoF, the smaller of the last two steps when they have
            the same sign and 0 otherwise (minmod); needs three tracked frames.
            Without it, the step is the last one (two tracked frames).
    Returns:
        (B, D), or None when no problem has the tracked frames it needs (the step is 0
        for the problems that lack them).
    """
    if not factor >= 0:
        raise ValueError(f"factor must be >= 0, got {factor!r}")
    need = 3 if limiter else 2
    if factor == 0 or len(history) < need:
        return None
    poses = [h[0] for h in history[-need:]]
    ok = torch.stack([h[1] for h in history[-need:]]).all(0)
    if not bool(ok.any()):
        return None
    step = poses[-1] - poses[-2]
    if limiter:
        older = poses[-2] - poses[-3]
        same = torch.sign(step) == torch.sign(older)
        step = torch.where(same, torch.sign(step) * torch.minimum(step.abs(), older.abs()), torch.zeros_like(step))
    return poses[-1] + factor * torch.where(ok[:, None], step, torch.zeros_like(step))


def _rigs(cameras: Sequence, B: int) -> tuple:
    """(B rigs as tuples of V cameras, V, nested) of ``track_frame``'s cameras: one camera
    per problem, or (``nested``) one rig per problem with the same number of views and
    one image size."""
    if len(cameras) != B:
        raise ValueError(f"give one camera (or camera rig) per problem: previous has {B} rows, got {len(cameras)}")
    nested = bool(cameras) and not isinstance(cameras[0], Camera)
    if any(isinstance(c, Camera) == nested for c in cameras):
        raise ValueError("give a Camera for every problem, or a camera rig (a sequence of Cameras) for every problem")
    rigs = [tuple(c) if nested else (c,) for c in cameras]
    V = len(rigs[0]) if rigs else 1
    for b, rig in enumerate(rigs):
        if len(rig) != V or V == 0:
            raise ValueError(f"problem {b} has {len(rig)} views, problem 0 has {V}: a batch tracks rigs of one size")
        for v, c in enumerate(rig):
            if not isinstance(c, Camera):
                raise TypeError(f"problem {b}, view {v}: expected a Camera, got {type(c).__name__}")
            if (c.width, c.height) != (rig[0].width, rig[0].height):
                raise ValueError(f"problem {b}: view {v} is {c.width}x{c.height} px, view 0 is {rig[0].width}x"
                                 f"{rig[0].height}: every view of a rig needs the same image size")
    return rigs, V, nested


def _per_view(items: Sequence, B: int, V: int, what: str, nested: bool) -> list:
    """B entries of V items each (None: the problem's frame is missing); with one camera
    per problem (not ``nested`` in rigs) an entry is the item itself. A frame missing in
    some views of a problem only is an error."""
    if len(items) != B:
        raise ValueError(f"give one {what} entry per problem ({B}), got {len(items)}")
    out = []
    for b, item in enumerate(items):
        if item is None:
            out.append(None)
            continue
        views = list(item) if nested else [item]
        if len(views) != V:
            raise ValueError(f"problem {b}: {len(views)} {what}s for a rig of {V} views")
        missing = [v for v, x in enumerate(views) if x is None]
        if missing and len(missing) < V:
            raise ValueError(f"problem {b}: views {missing} have no {what} while the other views have one: "
                             "every view of a rig needs each frame")
        out.append(None if missing else views)
    return out
