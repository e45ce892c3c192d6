"""S on colour views: the salient points of Ballan et al. 2012 (Sec. 4.1, Eq. 3), the
finger nails, matched to detected image points without a fixed association.

Per view and outer iteration: the salient vertices (one per fingertip, the centre of
its nail: :func:`torchhand.model.fingertips.nail_vertices`) that the render shows are
projected, and their distances ``w_st`` in px to the view's detections form the cost of
the paper's bipartite matching with outlier nodes (Eq. 3, solved by
:func:`torchhand.salient.association.associate`, the same integer programme as the
thesis' Eq. 4.14): a vertex and a detection are paired only when ``w_st < 2 lambda``,
cheaper than declaring both outliers; ``gate_px = 2 lambda = 60`` px by default. Each
pair's residual is the vertex's reprojection error to its detection (Eq. 2), in mm at
the vertex's depth (:class:`~torchhand.tracking.energies.base.VertexPixelTerm`).

The detections of a frame are ``ColourFrame.salient``: the simulated detections of
Ballan's protocol (``salient.json`` per camera, ``torchhand synth --protocol ballan``), or
those of a detector run on the image by the caller. A view without detections gives no
pairs.
"""

from __future__ import annotations

import numpy as np
import torch

from torchhand.core.check import check_number
from torchhand.model.fingertips import nail_vertices
from torchhand.optim.robust_loss import Cauchy
from torchhand.salient.association import associate
from torchhand.tracking.energies.base import PixelPairs, TrackState, VertexPixelTerm, counts, pixel_rows, project_views

__all__ = ["Nails", "DEFAULT_WEIGHT", "DEFAULT_LOSS"]

#: the weight of the nail pairs (Ballan weighs every correspondence alike; a few nails
#: against hundreds of edge and flow pairs per view: 3 tracked the Table 1 sequences
#: 1.66 / 2.0 mm against 1.72 / 2.14 with 1, docs/results.md)
DEFAULT_WEIGHT = 3.0

#: the pairs' robust loss: a false detection within the gate of a nail whose own
#: detection was missed is paired with it, up to 60 px off (docs/multicam.md)
DEFAULT_LOSS = Cauchy(scale=5.0)


class Nails(VertexPixelTerm):
    """S_colour (module docstring).

    Args:
        gate_px: 2 lambda of Eq. 3: the farthest pair, in px (Ballan: 60).
    """

    name = "nails"
    needs = "colour"
    detections = "salient"

    def __init__(self, gate_px: float = 60.0):
        check_number(gate_px, "gate_px", low=0, unit="px")
        self.gate_px = float(gate_px)
        self._ids, self._ids_scene = None, None

    def prepare(self, state: TrackState) -> PixelPairs:
        scene, B = state.scene, state.theta.shape[0]
        dev, dt = state.theta.device, state.theta.dtype
        if self._ids_scene is not scene:
            self._ids, self._ids_scene = nail_vertices(scene).to(dev), scene
        if state.colours is None or any(c is None for c in state.colours):
            raise ValueError("the salient-point term on colour views needs a colour frame for every view")
        T = len(self._ids)
        uv, z, K_b, T_b = project_views(state, state.posed.vertices.detach()[:, self._ids])  # (B, T, 2) px
        seen = state.visible_vertices()[:, self._ids].cpu().numpy()
        uv_h = uv.cpu().numpy()
        vertex = self._ids.expand(B, T).clone()
        target = torch.zeros(B, T, 2, dtype=dt, device=dev)
        keep = torch.zeros(B, T, dtype=torch.bool)
        detections = torch.zeros(B, dtype=torch.int64)
        for b, frame in enumerate(state.colours):
            det = frame.salient
            if det is None or len(det) == 0 or not seen[b].any():
                continue
            det = np.asarray(det, np.float64).reshape(-1, 2)
            detections[b] = len(det)
            cost = np.linalg.norm(det[:, None] - uv_h[b][None], axis=-1)  # (S, T) px
            cost[:, ~seen[b]] = np.inf
            a = associate(cost, self.gate_px / 2)
            for s, t in zip(a.detection.tolist(), a.fingertip.tolist()):
                target[b, t] = torch.as_tensor(det[s], dtype=dt)
                keep[b, t] = True
        keep = keep.to(dev)
        found = counts(B, device=dev, correspondences=keep.sum(1), detections=detections.to(dev))
        return PixelPairs(found, scene=scene, rows=pixel_rows(scene, vertex, target, z / K_b[:, 0, 0, None], keep), K=K_b,
                          T_cw=T_b)

    def __repr__(self) -> str:
        return f"Nails(gate_px={self.gate_px:g})"
