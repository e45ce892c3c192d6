"""The interface every energy term of the objective (thesis Eq. 4.5) implements.

A term is prepared once per outer iteration of Algorithm 1 (it finds its
correspondences at the current pose) and then evaluated, with the
correspondences fixed, at any theta the solver tries::

    term.prepare(state)                       # correspondences at the current pose
    r, J = term.residuals(theta, posed, True) # r: (B, m), J: (B, m, D)

Residuals come out multiplied by ``sqrt(weight)``, so the stacked sum of squares of
all terms is the weighted energy. ``count`` tells how many correspondences a term
contributes (C_all of the thesis scales the anatomy and regularisation weights).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, NamedTuple, Optional

import torch

from torchhand.geometry.camera import Camera
from torchhand.tracking.preprocess import DepthFrame
from torchhand.geometry.render import RenderResult, visible_vertices
from torchhand.model.scene import Scene, SceneOutput

__all__ = ["Residuals", "TrackState", "EnergyTerm", "scatter_columns", "no_residuals", "bone_inliers"]


class Residuals(NamedTuple):
    """r: (B, m) weighted residuals; J: (B, m, D) their Jacobian, or None."""

    r: torch.Tensor
    J: Optional[torch.Tensor]


@dataclass
class TrackState:
    """What the terms see at the start of an outer iteration, for B problems.

    scene: the shared scene; theta: (B, D) current pose; previous: (B, D) the pose
    of the previous frame; posed: scene output at theta; frames: one preprocessed
    frame per problem (points and normals in the camera frame); cameras: one camera
    per problem; render: the scene rendered at theta from each problem's camera;
    data_labels: (B, H, W) int64 model id assigned to each data pixel (-1 none).
    """

    scene: Scene
    theta: torch.Tensor
    previous: torch.Tensor
    posed: SceneOutput
    frames: List[DepthFrame]
    cameras: List[Camera]
    render: RenderResult
    data_labels: torch.Tensor
    _visible: Optional[torch.Tensor] = field(default=None, repr=False)

    def visible_vertices(self) -> torch.Tensor:
        """(B, V) bool: the vertices of the faces hit in ``render`` (found once per state,
        shared by the terms that need visibility)."""
        if self._visible is None:
            self._visible = visible_vertices(self.render, self.scene.faces, self.scene.num_vertices)
        return self._visible


class EnergyTerm:
    """Base class: a named, weighted term with the prepare/residuals interface."""

    name: str = "term"

    def __init__(self, weight: float = 1.0):
        self.weight = float(weight)
        self.count = None  # (B,) correspondences found by the last prepare()
        # (B,) candidates the last prepare() considered, count of them kept; None when
        # every candidate is a correspondence
        self.candidates = None
        # (B,) energy charged for the candidates left without a correspondence (each
        # weight x min(distance, cut-off)^2, a truncated square), so that poses are
        # compared fairly however many correspondences each finds; None = nothing
        self.unmatched = None

    def unmatched_energy(self) -> torch.Tensor:
        """(B,) energy of the candidates that found no correspondence (zeros if none)."""
        if self.unmatched is None:
            return torch.zeros(self.count.shape, dtype=torch.float64)
        return self.unmatched

    def prepare(self, state: TrackState) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def residuals(self, theta: torch.Tensor, posed: SceneOutput, with_jacobian: bool) -> Residuals:
        raise NotImplementedError  # pragma: no cover - interface


def scatter_columns(J_model: torch.Tensor, cols: slice, D: int) -> torch.Tensor:
    """Place a model's Jacobian (B, m, D_k) into the scene's columns (B, m, D)."""
    J = J_model.new_zeros(J_model.shape[0], J_model.shape[1], D)
    J[:, :, cols] = J_model
    return J


def no_residuals(theta: torch.Tensor, with_jacobian: bool) -> Residuals:
    """The residuals of a term without correspondences: (B, 0) and (B, 0, D)."""
    B, D = theta.shape
    return Residuals(theta.new_zeros(B, 0), theta.new_zeros(B, 0, D) if with_jacobian else None)


def bone_inliers(d: torch.Tensor, bone: torch.Tensor, keep: torch.Tensor, num_bones: int,
                 sigma: float) -> torch.Tensor:
    """Per-bone outlier rejection (Ballan et al. 2012, Sec. 3).

    Args:
        d: (n,) correspondence distances; bone: (n,) the bone of each model point;
        keep: (n,) bool, the pairs the statistics are taken over; sigma: the cut.
    Returns:
        (n,) bool: d <= mean + sigma * std of the kept distances of the same bone.
    """
    w = keep.to(d.dtype)
    n = torch.zeros(num_bones, dtype=d.dtype, device=d.device).index_add_(0, bone, w).clamp_min(1)
    mean = torch.zeros_like(n).index_add_(0, bone, d * w) / n
    std = (torch.zeros_like(n).index_add_(0, bone, (d - mean[bone]) ** 2 * w) / n).sqrt()
    return d <= mean[bone] + sigma * std[bone] + 1e-6
