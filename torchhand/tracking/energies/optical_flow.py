"""O: visible vertices follow the optical flow between consecutive colour frames
(Ballan et al. 2012, Eq. 2; the flow correspondences of their reference [28]).

Once per frame and view, the dense flow from the previous grey image to the current
one (OpenCV's DIS, ``preset``) predicts where each model point moved: a vertex seen at
the start of the frame's solve projects, at the previous frame's pose, to p; its
correspondence is ``p + flow(p)``, and its residual the reprojection error to it, in
mm at the vertex's depth (:class:`~torchhand.tracking.energies.base.VertexPixelTerm`).
Pixels ignored in the frame or the previous one (``ColourFrame.ignore``,
``previous_ignore``: the occluders of Ballan's protocol, whose flow the paper leaves
out), and ``margin_px`` around them (DIS estimates the flow of 8 px patches), give no
pairs, nor do vertices whose flow
is longer than ``max_flow_px``. At every outer iteration, pairs farther than the mean
plus ``sigma`` standard deviations of their bone's pairs are dropped (Ballan Sec. 3).

The visible vertices are those of the render at the solve's first outer iteration, at
its start pose: the previous frame's pose unless the tracker predicts the motion.
The first frame of a sequence has no flow: the term is empty there.
"""

from __future__ import annotations

from typing import Dict, NamedTuple

import cv2
import numpy as np
import torch

from torchhand.core.check import check_choice, check_int, check_number
from torchhand.optim.robust_loss import Cauchy
from torchhand.tracking.energies.base import (PixelPairs, TrackState, VertexPixelTerm, begin, bone_inliers, counts,
                                              pixel_rows, project_views, stride_subsample)

__all__ = ["OpticalFlow", "dense_flow", "DEFAULT_LOSS", "DEFAULT_WEIGHT"]

#: the pairs' robust loss, as the edges' (flow is wrong at occlusions and in textureless skin)
DEFAULT_LOSS = Cauchy(scale=3.0)
#: the term's weight against the edges' 1 (Ballan et al. do not give theirs). Table 1's
#: run at 640x480 (eval/exp_multicam.py --image-scale 1, docs/results.md), LO+ECO /
#: LO+ECOS joint error: weight 1 2.22 / 1.93 mm, 0.5 1.92 / 1.78 mm, 0.25 1.83 / 2.44 mm
#: (a finger lost on the crossing fingers: the flow no longer holds it where the edges
#: are ambiguous)
DEFAULT_WEIGHT = 0.5

PRESETS = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
           "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}


def dense_flow(previous: np.ndarray, current: np.ndarray, preset: str = "medium") -> np.ndarray:
    """(H, W, 2) float32 (du, dv) px: OpenCV DIS flow from ``previous`` to ``current``
    ((H, W) uint8 grey images)."""
    check_choice(preset, "preset", sorted(PRESETS))
    return cv2.DISOpticalFlow_create(PRESETS[preset]).calc(previous, current, None)


class _Data(NamedTuple):
    vertex: torch.Tensor  # (P, n) int64 scene vertex ids
    target: torch.Tensor  # (P, n, 2) (u, v) px, where the flow moved them
    keep: torch.Tensor  # (P, n) bool


class OpticalFlow(VertexPixelTerm):
    """E_flow (module docstring).

    Args:
        max_points: vertices with a flow correspondence per view (a stride subsample).
        max_flow_px: longer flow vectors are taken as wrong.
        sigma: per-bone outlier cut in standard deviations (Ballan: 2); None keeps all.
        preset: DIS preset (``"ultrafast"``, ``"fast"``, ``"medium"``).
        margin_px: px around ignored pixels whose flow is not used either.
    """

    name = "flow"
    needs = "colour"

    def __init__(self, max_points: int = 300, max_flow_px: float = 60.0, sigma=2.0, preset: str = "medium",
                 margin_px: int = 8):
        check_int(margin_px, "margin_px", low=0)
        self.margin_px = margin_px
        check_int(max_points, "max_points", low=1)
        check_number(max_flow_px, "max_flow_px", low=0, unit="px")
        check_number(sigma, "sigma", low=0, none=True)
        check_choice(preset, "preset", sorted(PRESETS))
        self.max_points, self.max_flow_px, self.sigma, self.preset = max_points, float(max_flow_px), sigma, preset
        self._flows: Dict[int, tuple] = {}

    def _flow(self, frame) -> tuple:
        """(flow (H, W, 2), unusable (H, W) bool or None) of the frame from its previous
        image, computed once per frame."""
        key = id(frame)
        if key not in self._flows:
            if len(self._flows) >= 64:
                self._flows.clear()
            masks = [np.asarray(m, bool) for m in (frame.ignore, frame.previous_ignore) if m is not None]
            bad = None
            if masks:
                k = 2 * self.margin_px + 1
                bad = cv2.dilate(np.logical_or.reduce(masks).astype(np.uint8), np.ones((k, k), np.uint8)) > 0
            self._flows[key] = (frame, (dense_flow(frame.previous, frame.gray, self.preset), bad))
        return self._flows[key][1]

    def _build(self, state: TrackState) -> _Data:
        if state.colours is None or any(c is None for c in state.colours):
            raise ValueError("the optical-flow term needs a colour frame for every view")
        scene, P = state.scene, state.theta.shape[0]
        dev, dt = state.theta.device, state.theta.dtype
        n = self.max_points
        vis = state.visible_vertices()  # (P, V) at the start pose
        index, slot = stride_subsample(vis, n)
        earlier = scene(state.previous, validate=False).vertices.detach()  # (P, V, 3)
        b = torch.arange(P, device=dev)[:, None]
        uv_all, _, _, _ = project_views(state, earlier[b, index])  # (P, n, 2) at the previous pose
        target = torch.zeros(P, n, 2, dtype=dt, device=dev)
        keep = torch.zeros(P, n, dtype=torch.bool, device=dev)
        for j, frame in enumerate(state.colours):
            if frame.previous is None:
                continue
            flow, bad = self._flow(frame)
            flow = torch.as_tensor(flow, device=dev, dtype=dt)
            H, W = flow.shape[:2]
            uv = uv_all[j]
            iu, iv = uv[:, 0].round().long(), uv[:, 1].round().long()
            inside = slot[j] & (iu >= 0) & (iu < W) & (iv >= 0) & (iv < H)
            iu, iv = iu.clamp(0, W - 1), iv.clamp(0, H - 1)
            f = flow[iv, iu]
            ok = inside & (f.norm(dim=-1) <= self.max_flow_px)
            if bad is not None:
                ok &= ~torch.as_tensor(bad, device=dev)[iv, iu]
            target[j], keep[j] = uv + f, ok
        return _Data(index, target, keep)

    def prepare(self, state: TrackState) -> PixelPairs:
        scene, B, dev, _, data, p = begin(state, self, self._build)
        vertex, target, keep = data.vertex[p], data.target[p], data.keep[p]
        b = torch.arange(B, device=dev)[:, None]
        uv, z, K_b, T_b = project_views(state, state.posed.vertices.detach()[b, vertex])
        if self.sigma is not None:
            keep = keep & bone_inliers((uv - target).norm(dim=-1), scene.vertex_bone_id[vertex], keep, scene.num_bones,
                                       self.sigma)
        scale = z / K_b[:, 0, 0, None]
        return PixelPairs(counts(B, device=dev, correspondences=keep.sum(1)), scene=scene,
                          rows=pixel_rows(scene, vertex, target, scale, keep), K=K_b, T_cw=T_b)

    def __repr__(self) -> str:
        return f"OpticalFlow(max_points={self.max_points}, sigma={self.sigma}, preset={self.preset!r})"
