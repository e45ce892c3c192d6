"""E_keypoints (energy letter K): the model's 21 standard joints pulled onto the hand
localiser's detections, the thesis' salient term (Eq. 4.14-4.15) generalised from
fingertips to every joint of the hand.

Once per frame the localiser (:mod:`torchhand.salient.localiser`) runs on the frame's
raw depth and finds each hand's 21 joints (image position, confidence) and its side.
Each hand model of the scene takes the located hand of its side (else none). A joint
detected at pixel (u, v) defines the camera ray through it; the residual of the
model's joint X (camera frame) is its offset from that ray at its own depth,

    r = (x - z (u - c_x) / f_x,  y - z (v - c_y) / f_y) * sqrt(c),

the reprojection error expressed in mm at the joint's depth (linear in X, so its
Jacobian is exact), weighted by the square root of the detection's confidence c.
Joints below ``min_confidence`` are left out. Wrapped in a robust loss by the energy
string (Cauchy, ``DEFAULT_LOSS``), so a wrong detection pulls little.

The joints and their Jacobian are :func:`~torchhand.model.joints21.standard_joints`
and :func:`~torchhand.model.joints21.standard_joint_jacobian`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict

import numpy as np
import torch

from torchhand.model.joints21 import is_hand, joint_sources, standard_joint_jacobian, standard_joints
from torchhand.model.scene import Scene
from torchhand.optim.robust_loss import Cauchy
from torchhand.tracking.energies.base import EnergyTerm, Prepared, Residuals, TrackState, counts, no_residuals

__all__ = ["Keypoints", "KeypointRows", "DEFAULT_WEIGHT", "DEFAULT_LOSS"]

#: The term's weight in the energy string's ``K`` (against the depth terms' ~1,500 rows).
DEFAULT_WEIGHT = 2.0
#: Its robust loss: detections farther than ~10 mm from the model's joints pull less.
DEFAULT_LOSS = Cauchy(scale=10.0)


@dataclass(frozen=True, eq=False)
class KeypointRows(Prepared):
    """Prepared data of :class:`Keypoints`: ``scene``; ``hands`` the scene indices of its
    hand models; ``ray`` (B, 21 x hands, 2) the detections' normalised image
    coordinates ((u - c_x) / f_x, (v - c_y) / f_y); ``weight`` (B, 21 x hands) the square
    root of their confidence, 0 for joints not detected; ``R`` (B, 3, 3) and ``t``
    (B, 3) each problem's world-to-camera transform."""

    scene: Scene
    hands: tuple
    ray: torch.Tensor
    weight: torch.Tensor
    R: torch.Tensor
    t: torch.Tensor


class Keypoints(EnergyTerm):
    """E_keypoints (module docstring).

    Args:
        localiser: an object with ``locate(depth (H, W) mm) -> Localisation`` (default:
            the shipped one, loaded once per process).
        min_confidence: joints detected with less confidence are not used.
    """

    name = "keypoints"
    needs = "depth"
    whole_frames = True  # the localiser reads the whole frame

    def __init__(self, localiser=None, min_confidence: float = 0.3):
        self._localiser = localiser
        self.min_confidence = float(min_confidence)
        self._cache: Dict[int, tuple] = {}
        self._sources = {}

    def _located(self, frame):
        key = id(frame)
        if key not in self._cache:
            if self._localiser is None:
                from torchhand.tracking.segmentation import shared_localiser

                self._localiser = shared_localiser()
            depth = frame.raw if frame.raw is not None else frame.depth
            d = torch.nan_to_num(torch.as_tensor(depth).float(), nan=0.0).cpu().numpy()
            if len(self._cache) >= 64:
                self._cache.clear()
            self._cache[key] = (frame, self._localiser.locate(d).hands)  # the frame kept: its id stays unique
        return self._cache[key][1]

    def prepare(self, state: TrackState) -> KeypointRows:
        scene, B = state.scene, state.theta.shape[0]
        dev, dt = state.theta.device, state.theta.dtype
        hands = tuple(k for k, m in enumerate(scene.models) if is_hand(m))
        ray = torch.zeros(B, 21 * len(hands), 2, dtype=dt, device=dev)
        weight = torch.zeros(B, 21 * len(hands), dtype=dt, device=dev)
        R = torch.zeros(B, 3, 3, dtype=dt, device=dev)
        t = torch.zeros(B, 3, dtype=dt, device=dev)
        used = torch.zeros(B, dtype=torch.int64)
        for b in range(B):
            cam = state.cameras[b]
            T = cam.T_cw.to(dev, dt)
            R[b], t[b] = T[:3, :3], T[:3, 3]
            located = self._located(state.frames[b])
            for i, k in enumerate(hands):
                h = next((h for h in located if h.side == scene.models[k].side), None)
                if h is None:
                    continue
                conf = np.asarray(h.confidence, np.float64)
                ok = conf >= self.min_confidence
                a = np.stack([(h.uv[:, 0] - cam.cx) / cam.fx, (h.uv[:, 1] - cam.cy) / cam.fy], 1)
                ray[b, 21 * i:21 * i + 21] = torch.as_tensor(a, dtype=dt, device=dev)
                weight[b, 21 * i:21 * i + 21] = torch.as_tensor(np.where(ok, np.sqrt(conf), 0.0), dtype=dt, device=dev)
                used[b] += int(ok.sum())
        return KeypointRows(counts(B, correspondences=used), scene, hands, ray, weight, R, t)

    def _joints(self, scene: Scene, posed, hands: tuple, jacobian: bool) -> tuple:
        X, J = [], []
        for k in hands:
            m = scene.models[k]
            if m not in self._sources:
                self._sources[m] = joint_sources(m)
            out = posed.models[k]
            X.append(standard_joints(out, m, self._sources[m]))
            if jacobian:
                Jk = standard_joint_jacobian(out, m, self._sources[m])
                full = Jk.new_zeros(*Jk.shape[:3], scene.num_dofs)
                sl = scene.slices[scene.names[k]]
                full[..., sl] = Jk
                J.append(full)
        return torch.cat(X, 1), (torch.cat(J, 1) if jacobian else None)

    def residuals(self, theta, posed, prepared: KeypointRows, jacobian=True):
        p = prepared
        if not p.hands:
            return no_residuals(theta, jacobian, 2)
        B, D = theta.shape
        Xw, Jw = self._joints(p.scene, posed, p.hands, jacobian)
        Xc = Xw @ p.R.transpose(1, 2) + p.t[:, None]  # (B, n, 3)
        w = p.weight[..., None]
        r = (Xc[..., :2] - Xc[..., 2:] * p.ray) * w  # (B, n, 2)
        n = r.shape[1]
        J = None
        if jacobian:
            A = torch.zeros(B, n, 2, 3, dtype=theta.dtype, device=theta.device)
            A[..., 0, 0] = A[..., 1, 1] = 1.0
            A[..., :, 2] = -p.ray
            Jc = torch.einsum("bij,bnjd->bnid", p.R, Jw)  # camera frame
            J = (torch.einsum("bnij,bnjd->bnid", A, Jc) * w[..., None]).reshape(B, 2 * n, D)
        mask = (p.weight > 0).to(theta.dtype)
        return Residuals(r.reshape(B, 2 * n), J, 2, mask)
