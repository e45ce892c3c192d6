"""Hand-size calibration: a global scale and five finger length factors fitted to frames.

The shipped hands belong to one person; another person's hand is larger or smaller, and
its fingers are longer or shorter relative to the palm. The tracker cannot absorb that
with its pose parameters: its fingertips end short of (or beyond) the data, and the free
space and silhouette terms fight over the difference. The thesis personalises its hand
models by scanning; here the shipped model is resized (:mod:`torchhand.model.shape`:
the skeleton's topology, axes and limits kept, each finger's bones and surface scaled
about their joints) to fit a few frames of the user's own recording.

The fit alternates, for ``rounds`` rounds:

1. the size, with the frames' poses fixed: particle swarm optimisation
   (:func:`~torchhand.optim.pso.particle_swarm`) over the global scale and the finger
   factors, within ``scale_range`` and ``finger_range``, of FORTH's depth discrepancy
   (:func:`~torchhand.tracking.initialization.depth_discrepancy`) summed over the
   frames, each frame rendered in its hand's box at ``resolution`` px. Every particle's
   resized hand is posed exactly from the model's own bone motions
   (:func:`~torchhand.model.shape.pose_resized`), so all particles of a frame are one
   batch. The current size is one of the particles, so a round never gets worse;
2. the poses, with the size fixed: the tracker's objective (Algorithm 1,
   ``iterations``) on every frame, from the poses of the previous round.

The frames' first poses come from the caller (the automatic initialisation). The
factors are estimated from the silhouette and depth of the hand: a finger that stays
bent in every frame has a poorly observed length, so use frames with the fingers
spread where one can.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, NamedTuple, Sequence

import numpy as np
import torch

from torchhand.core.check import skip_checks
from torchhand.geometry.camera import Camera
from torchhand.io.assets import ModelAssets
from torchhand.model.articulated import ArticulatedModel
from torchhand.model.scene import Scene
from torchhand.model.shape import FINGERS, bone_scales, pose_resized, resize_hand
from torchhand.optim.pso import particle_swarm
from torchhand.tracking.initialization import crop_camera, depth_discrepancy, search_box
from torchhand.tracking.preprocess import preprocess_depth
from torchhand.tracking.tracker import Tracker

__all__ = ["CalibrationConfig", "CalibrationResult", "calibrate_hand"]


@dataclass(frozen=True)
class CalibrationConfig:
    rounds: int = 5
    particles: int = 24
    generations: int = 12
    scale_range: tuple = (0.8, 1.25)
    finger_range: tuple = (0.85, 1.18)
    resolution: int = 96
    clamp_mm: float = 40.0
    iterations: int = 30
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("rounds", "particles", "generations", "resolution", "iterations"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"CalibrationConfig.{name} must be an integer >= 1, got {v!r}")
        for name in ("scale_range", "finger_range"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= 1 <= hi:
                raise ValueError(f"CalibrationConfig.{name} must hold 1 within (low > 0, high), got {(lo, hi)}")


class CalibrationResult(NamedTuple):
    """assets: the resized hand; scale, fingers: its factors; theta: (K, D) the frames'
    final poses; before, after: (K,) each frame's depth discrepancy at full resolution
    with the given model at the given poses and with the resized one at the final poses."""

    assets: ModelAssets
    scale: float
    fingers: Dict[str, float]
    theta: torch.Tensor
    before: np.ndarray
    after: np.ndarray


def calibrate_hand(tracker, depths: Sequence[np.ndarray], cameras: Sequence[Camera], theta: torch.Tensor,
                   config: CalibrationConfig = CalibrationConfig(), name: str | None = None) -> CalibrationResult:
    """Fit the size of a one-hand tracker's hand to K frames.

    Args:
        tracker: a :class:`~torchhand.tracking.tracker.Tracker` of a scene of one hand
            (its configuration and energy are used for the pose rounds).
        depths: K depth maps in mm as the tracker sees them (segmented: 0 = nothing,
            NaN = unknown, :meth:`~torchhand.tracking.segmentation.Segmentation.apply`).
        cameras: their cameras.
        theta: (K, D) the frames' starting poses.
        name: of the resized model (default: the hand's).
    """
    scene = tracker.scene
    if len(scene.models) != 1 or scene.models[0].kind != "hand":
        raise ValueError(f"calibration fits one hand; the scene is {list(scene.names)}")
    K = len(depths)
    if K == 0 or len(cameras) != K or theta.shape[0] != K:
        raise ValueError(f"give one camera and one pose per frame: {K} frames, {len(cameras)} cameras, "
                         f"theta {tuple(theta.shape)}")
    model: ArticulatedModel = scene.models[0]
    dev, dt = theta.device, theta.dtype
    gen = torch.Generator().manual_seed(config.seed)
    data_full = [torch.as_tensor(np.asarray(d, np.float32), device=dev) for d in depths]
    crops = []
    for d, cam in zip(depths, cameras):
        small, rr, cc = crop_camera(cam, search_box(np.asarray(d) > 0), config.resolution)
        crops.append((small, torch.as_tensor(np.asarray(d, np.float32)[np.ix_(rr, cc)], device=dev)))
    frames = [preprocess_depth(d, cam, tracker.config.preprocess, device=dev, dtype=dt)
              for d, cam in zip(depths, cameras)]

    def discrepancy(tr, th, full: bool) -> np.ndarray:
        with torch.no_grad(), skip_checks():
            verts = tr.scene(th, validate=False).vertices
            out = []
            for k in range(K):
                cam, data = (cameras[k], data_full[k]) if full else crops[k]
                out.append(depth_discrepancy(tr.renderer(verts[k : k + 1], cam, normals=False).depth, data,
                                             config.clamp_mm))
        return torch.cat(out).cpu().numpy()

    before = discrepancy(tracker, theta, True)
    lo = torch.tensor([config.scale_range[0]] + [config.finger_range[0]] * 5, dtype=torch.float64)
    hi = torch.tensor([config.scale_range[1]] + [config.finger_range[1]] * 5, dtype=torch.float64)
    x = torch.ones(6, dtype=torch.float64)
    th = theta.clone()
    sized_tracker = tracker
    for _ in range(config.rounds):
        with torch.no_grad():
            G = model(th).G  # (K, J, 4, 4): every resized copy is posed from these

        def cost(pos: torch.Tensor) -> torch.Tensor:
            p = pos[0].to(dev, dt)  # (P, 6)
            s = bone_scales(model, p[:, 0], p[:, 1:])
            total = torch.zeros(p.shape[0], dtype=torch.float64)
            with torch.no_grad(), skip_checks():
                for k in range(K):
                    verts, _, _ = pose_resized(model, G[k : k + 1].expand(p.shape[0], -1, -1, -1), s)
                    cam, data = crops[k]
                    depth = tracker.renderer(verts, cam, normals=False).depth
                    total += depth_discrepancy(depth, data, config.clamp_mm).double().cpu()
            return (total / K)[None]

        P = config.particles
        init = x + torch.randn(P, 6, generator=gen, dtype=torch.float64) * 0.06
        init[0] = x
        init = torch.maximum(torch.minimum(init, hi), lo)
        res = particle_swarm(cost, init[None], lo, hi, config.generations,
                             velocity_scale=torch.full((6,), 0.04, dtype=torch.float64), generator=gen)
        x = res.best[0]
        assets = _resized(model, x, name)
        sized = Scene([ArticulatedModel(assets, dtype=dt).to(dev)], names=list(scene.names))
        sized_tracker = Tracker(sized, tracker.config)
        th = sized_tracker.solve(th, th, frames, list(cameras), config.iterations, 0.0).theta
    after = discrepancy(sized_tracker, th, True)
    return CalibrationResult(assets, float(x[0]), {f: float(v) for f, v in zip(FINGERS, x[1:])}, th.detach(),
                             before, after)


def _resized(model: ArticulatedModel, x: torch.Tensor, name) -> ModelAssets:
    return resize_hand(model.assets, float(x[0]), {f: float(v) for f, v in zip(FINGERS, x[1:])}, name=name)
