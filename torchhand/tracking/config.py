"""The tracker's settings: one frozen dataclass, each field's meaning in one place.

The measurements behind the defaults are in docs/results.md (the energy, the labels,
the prediction, the joint limits, the solvers' box) and docs/benchmarks.md (speed).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Tuple

from torchhand.core.check import check_choice, check_int, check_number
from torchhand.geometry.raycast import BACKENDS, default_backend
from torchhand.tracking.labels import LABELINGS
from torchhand.tracking.preprocess import ColourConfig, PreprocessConfig

__all__ = ["TrackerConfig", "SOLVERS"]

#: the solvers of a frame: Levenberg-Marquardt (Algorithm 1) or the particle swarm (HOPE)
SOLVERS = ("lm", "pso")


@dataclass(frozen=True)
class TrackerConfig:
    """How the tracker runs (immutable: change a field with ``dataclasses.replace``).

    Attributes:
        energy: the terms (:func:`~torchhand.tracking.energies.parse_energy`); ``LO+F``:
            model-to-data, data-to-model and free space.
        metric: model-to-data distance, ``"point-to-plane"`` or ``"point-to-point"``.
        inner_iterations: LM steps per correspondence update (1: the thesis' alternation).
        max_iterations: outer iterations per frame (the thesis' i_thr).
        first_frame_iterations: for frame 0 (50 in the thesis).
        min_joint_motion: mm; a problem converges when its joints move less than this on
            average in an iteration (the thesis' 0.2 mm).
        step_retries: a rejected LM step is retried with ten times the damping up to
            this many times, reusing the correspondences and the Jacobian.
        recover_factor: a frame whose energy exceeds this multiple of the median of the
            previous frames' is re-solved from ``recover_tries`` perturbations of the
            previous pose (joints by N(0, ``perturbation``) rad).
        seed: of those perturbations and of the swarm, so a run is repeatable.
        labels: how data pixels are assigned to models: ``"proximity"`` (the nearest
            model in 3D within ``label_distance`` mm) or ``"rendered"`` (the nearest
            rendered model within ``label_radius`` px).
        prediction: a frame starts from the previous pose plus this times the last step
            (0: none, 1: constant velocity; None: 1, except 0 for a scene with a chain
            of like bones, the rope, tracked with depth terms: :meth:`motion_prediction`);
            prediction_limiter: the step per DoF is the smaller of the last two when
            they agree in sign, else 0 (minmod).
        preprocess, colour: depth and colour preprocessing.
        backend: of the renders and with it of the neighbour searches (``"warp"``,
            ``"warp-raycast"``, ``"open3d"``; None: Warp when installed).
        render_margin: px around the projection of a solve's start poses that its renders
            cover.
        solver: ``"lm"`` (Algorithm 1) or ``"pso"`` (HOPE: ``particles`` particles over
            ``generations`` generations, drawn about the start with ``swarm_spread``:
            global translation mm, global rotation rad, joint angles rad).
        fused: the LM steps of Algorithm 1 take the depth terms' rows and Jacobians from
            the fused Warp kernels and solve the normal equations they accumulate
            (:mod:`~torchhand.tracking.fused`; float32 and one view per problem, else the
            torch objective); False: the torch objective, the reference.
        crop_views: each view of a camera rig is cut to the box of its hands (the start
            pose's projection widened by ``render_margin`` and ``views.CROP_MARGIN`` px;
            depth views without colour, and no term reading whole frames): the same
            geometry, a fraction of the pixels. False: whole images.
        rig_budget: a camera rig's depth terms pair at most this many single views'
            worth of model vertices and data pixels, spread evenly over its views (each
            view takes ``rig_budget / V`` of every term's cap; more views see the hand
            from more sides, not in more detail); None: every view its whole caps.
        threads: torch intra-op threads of the frame loop (reading a frame, preprocessing,
            solving, the ``revise`` callback; at most torch's own count): 1, because the
            loop's many small operations gain nothing from more and lose much on a busy
            machine (:mod:`torchhand.core.threads`); None: torch's setting.
        limit_slack: rad; the solvers keep each sequence's θ within the joint limits
            widened by this and grown to hold its initial pose; None: no box, only the
            soft limits of E_anatomy (Eq. 4.17).
    """

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
    swarm_spread: Tuple[float, float, float] = (5.0, 0.05, 0.1)
    limit_slack: Optional[float] = 0.0
    fused: bool = False
    crop_views: bool = True
    rig_budget: Optional[float] = 2.0
    threads: Optional[int] = 1

    def __post_init__(self) -> None:
        if not isinstance(self.fused, bool):
            raise ValueError(f"fused must be True or False, got {self.fused!r}")
        if not isinstance(self.crop_views, bool):
            raise ValueError(f"crop_views must be True or False, got {self.crop_views!r}")
        check_number(self.rig_budget, "rig_budget", low=0, unit="views", none=True)
        check_number(self.prediction, "prediction", low=0, inclusive=True, none=True)
        if not isinstance(self.prediction_limiter, bool):
            raise ValueError(f"prediction_limiter must be True or False, got {self.prediction_limiter!r}")
        check_choice(self.labels, "labels", LABELINGS)
        check_number(self.label_distance, "label_distance", low=0, unit="mm")
        check_number(self.label_radius, "label_radius", low=0, unit="px")
        check_choice(self.solver, "solver", SOLVERS)
        check_int(self.particles, "particles", low=2)
        check_int(self.generations, "generations", low=0)
        if len(self.swarm_spread) != 3:
            raise ValueError(f"swarm_spread must be 3 numbers (mm, rad, rad), got {self.swarm_spread!r}")
        for name, x in zip(("translation", "rotation", "joint"), self.swarm_spread):
            check_number(x, f"swarm_spread's {name} spread", low=0, inclusive=True)
        check_choice(self.backend, "backend", BACKENDS + (None,))
        check_number(self.limit_slack, "limit_slack", low=0, inclusive=True, unit="radians; None: no box", none=True)
        for name in ("inner_iterations", "max_iterations", "first_frame_iterations"):
            check_int(getattr(self, name), name, low=1)
        check_int(self.step_retries, "step_retries", low=0)
        check_int(self.recover_tries, "recover_tries", low=0)
        check_int(self.render_margin, "render_margin", low=0)
        if self.threads is not None:
            check_int(self.threads, "threads", low=1)

    def motion_prediction(self, chains: bool = False) -> float:
        """The prediction a run uses: ``prediction``, or when None, 1 (constant velocity),
        except 0 (the thesis' previous pose) where the scene has a chain of like bones
        (``chains``: the rope, :func:`~torchhand.tracking.energies.chain_smoothness.chain_pairs`)
        and the energy has depth terms (``LO``): with the minmod limiter it tracks hands
        and rigid objects closer and in fewer iterations, and loses a rope whose noisy
        estimates do not move smoothly (docs/results.md, "Starting a frame from a
        constant-velocity prediction")."""
        if self.prediction is not None:
            return float(self.prediction)
        return 0.0 if chains and "LO" in self.energy.replace(" ", "").split("+") else 1.0

    @property
    def render_backend(self) -> str:
        """The backend the renders use (``backend``, or Warp when installed)."""
        return default_backend() if self.backend is None else self.backend

    @property
    def neighbor_backend(self) -> str:
        """``"warp"`` with a Warp render backend, else scipy on the CPU (``"cpu"``)."""
        return "warp" if self.render_backend.startswith("warp") else "cpu"
