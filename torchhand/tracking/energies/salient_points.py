"""E_salient: detected fingertips pull the model's fingertips (thesis Eq. 4.14-4.15).

Once per frame, the fingertip detector (:mod:`torchhand.salient`) runs on the raw
depth. Each detection s becomes a small 3D point cloud delta'_s: the valid pixels
of a (2 r + 1)^2 box around it whose depth is within ``depth_band`` mm of the
nearest surface in the box, and its centroid c_s. At every outer iteration:

1. the model fingertips phi_t are the fingertip vertex groups of every hand,
   restricted to the vertices visible in the render; c_t is their centroid;
2. detections and fingertips are associated by Eq. 4.14 with
   w_st = |c_s - c_t| / ``unit_mm`` and lambda (see :func:`associate`);
3. for an assigned pair: nothing when w_st < 10 mm (the detector is not more
   precise); when at least 50 % of phi_t's visible vertices project into the box,
   each of them is paired with its closest point of delta'_s, otherwise all of them
   with c_s (Eq. 4.15, Fig. 4.7).

Residuals are point-to-point, ``V_i - X_i`` (weight 1 in the tracker). The thesis leaves the
unit of w_st open; with centimetres (``unit_mm = 10``) and its lambda = 1.2, a
detection and a fingertip are paired when they are closer than 2 lambda = 24 mm
(with w_s = 1), which is the range a tracker moves between frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Dict, Optional

import numpy as np
import torch
from scipy.spatial import cKDTree

from torchhand.salient.association import associate
from torchhand.model.fingertips import fingertip_faces
from torchhand.model.scene import Scene
from torchhand.tracking.energies.base import EnergyTerm, Prepared, Residuals, TrackState, counts, no_residuals

__all__ = ["Salient", "SalientPairs"]


@dataclass(frozen=True, eq=False)
class SalientPairs(Prepared):
    """Prepared data of :class:`Salient`: ``scene``; ``ids`` (B, n) int64 scene vertex
    ids of the fingertip vertices paired with detections, ``X`` (B, n, 3) their
    targets (world, mm), ``mask`` (B, n) 1 for real rows."""

    scene: Scene
    ids: torch.Tensor
    X: torch.Tensor
    mask: torch.Tensor


class Salient(EnergyTerm):
    """E_salient.

    Args:
        detector: an object with ``detect(depth (H, W) mm) -> Detections`` (default:
            the shipped network, through ONNX Runtime on CPU or torch on CUDA).
        lam: lambda of Eq. 4.14 (1.2).
        min_score: c_thr, the smallest detection score used (the thesis keeps only
            confident detections, c_thr = 3 for its forest; 0.15 for the shipped
            network's scores, Hough value x cell probability squared: on its validation
            frames precision 0.95 at recall 0.81, see docs/results.md).
        confidence_weighted: w_s = c_s / c_thr instead of 1 (the thesis' second option).
        unit_mm: mm per unit of w_st (10: centimetres).
        near_mm: no correspondences for a pair closer than this (10).
        min_inside: fraction of a fingertip's visible vertices that must project into
            the detection box for closest-point pairs (0.5), else centroid pairs.
        box: r, the half size in px of a detection's box (8).
        depth_band: mm behind the nearest point of the box kept in delta'_s (25).
    """

    name = "salient"
    whole_frames = True  # its detector reads the whole frame
    needs = "depth"

    def __init__(self, detector=None, lam: float = 1.2, min_score: float = 0.15, confidence_weighted: bool = False,
                 unit_mm: float = 10.0, near_mm: float = 10.0, min_inside: float = 0.5, box: int = 8,
                 depth_band: float = 25.0):
        if lam < 0 or unit_mm <= 0 or box < 1:
            raise ValueError(f"need lam >= 0, unit_mm > 0 and box >= 1; got {lam}, {unit_mm}, {box}")
        self._detector = detector
        self.lam, self.confidence_weighted, self.unit_mm = float(lam), confidence_weighted, float(unit_mm)
        self.min_score = float(min_score)
        self.near_mm, self.min_inside, self.box, self.depth_band = near_mm, min_inside, int(box), depth_band
        self._cache: Dict[int, tuple] = {}
        self._tips, self._tips_scene = None, None

    # ---------------------------------------------------------------- detections
    def detector_for(self, device: torch.device):
        if self._detector is None:
            from torchhand.salient.detector import SalientDetector

            self._detector = (SalientDetector.load(device=device) if device.type == "cuda"
                              else SalientDetector.load_onnx(threads=max(1, torch.get_num_threads())))
        return self._detector

    def _regions(self, frame, camera) -> tuple:
        """Detections of one frame as (centroids (S, 3) world, clouds [(n_s, 3)], boxes (S, 4), conf (S,)),
        computed once per frame."""
        key = id(frame)
        if key in self._cache:
            return self._cache[key][1]
        depth = frame.raw if frame.raw is not None else frame.depth
        det = self.detector_for(depth.device).detect(depth)
        pts = frame.points.detach()
        valid = frame.mask if frame.raw is None else frame.raw > 0
        H, W = depth.shape
        T_wc = camera.T_wc.to(pts.device, pts.dtype)
        cents, clouds, boxes, conf = [], [], [], []
        for (u, v), c in zip(det.uv.tolist(), det.score.tolist()):
            if c < self.min_score:
                continue
            u0, u1 = max(0, int(round(u)) - self.box), min(W, int(round(u)) + self.box + 1)
            v0, v1 = max(0, int(round(v)) - self.box), min(H, int(round(v)) + self.box + 1)
            z = depth[v0:v1, u0:u1].to(pts.dtype)
            ok = valid[v0:v1, u0:u1] & (z > 0)
            if not bool(ok.any()):
                continue
            ok &= z <= z[ok].min() + self.depth_band
            if frame.raw is not None:  # back-project the raw depth of the box
                vv, uu = torch.meshgrid(torch.arange(v0, v1, device=z.device), torch.arange(u0, u1, device=z.device),
                                        indexing="ij")
                K = camera.K.to(z.device, z.dtype)
                xyz = torch.stack([(uu - K[0, 2]) * z / K[0, 0], (vv - K[1, 2]) * z / K[1, 1], z], -1)[ok]
            else:
                xyz = pts[v0:v1, u0:u1][ok]
            xyz = xyz @ T_wc[:3, :3].T + T_wc[:3, 3]
            cents.append(xyz.mean(0))
            clouds.append(xyz)
            boxes.append((u0 - 0.5, v0 - 0.5, u1 - 0.5, v1 - 0.5))
            conf.append(c)
        out = (torch.stack(cents) if cents else pts.new_zeros(0, 3), clouds,
               np.asarray(boxes, np.float64).reshape(-1, 4), np.asarray(conf, np.float64))
        if len(self._cache) >= 64:  # frames of earlier tracker steps; the cached frame keeps its id unique
            self._cache.clear()
        self._cache[key] = (frame, out)
        return out

    # ------------------------------------------------------------------- prepare
    def prepare(self, state: TrackState) -> SalientPairs:
        scene, B = state.scene, state.theta.shape[0]
        dev, dt = state.theta.device, state.theta.dtype
        if self._tips_scene is not scene:
            self._tips, self._tips_scene = fingertip_faces(scene), scene
        index, mask = self._tips[0].to(dev), self._tips[1].to(dev)
        V = state.posed.vertices.detach()
        rows, count, assigned = [], torch.zeros(B, dtype=torch.int64), torch.zeros(B, dtype=torch.int64)
        for b in range(B):
            cent, clouds, boxes, conf = self._regions(state.frames[b], state.cameras[b])
            vis = state.visible_vertices()[b]
            tip_vis = mask & vis[index]  # (T, G)
            has = tip_vis.any(1)
            if len(cent) == 0 or not bool(has.any()):
                rows.append(None)
                continue
            w = tip_vis.to(dt)
            c_t = (V[b][index] * w[..., None]).sum(1) / w.sum(1, keepdim=True).clamp_min(1)  # (T, 3)
            dist = torch.cdist(cent.to(dt), c_t).cpu().numpy()  # (S, T) mm
            cost = np.where(has.cpu().numpy()[None], dist / self.unit_mm, np.inf)
            ws = conf / max(self.min_score, 1e-9) if self.confidence_weighted else None
            a = associate(cost, self.lam, ws)
            assigned[b] = len(a.detection)
            ids, targets = [], []
            cam = state.cameras[b].to(device=dev, dtype=dt)
            for s, t in zip(a.detection.tolist(), a.fingertip.tolist()):
                if dist[s, t] < self.near_mm:
                    continue
                vids = index[t][tip_vis[t]]
                uv = cam.project(V[b, vids][None])[0].cpu().numpy()
                u0, v0, u1, v1 = boxes[s]
                inside = (uv[:, 0] >= u0) & (uv[:, 0] <= u1) & (uv[:, 1] >= v0) & (uv[:, 1] <= v1)
                if inside.mean() >= self.min_inside:
                    cloud = clouds[s]
                    _, j = cKDTree(cloud.cpu().numpy()).query(V[b, vids].cpu().numpy())
                    X = cloud[torch.as_tensor(j, device=cloud.device)]
                else:
                    X = cent[s].expand(len(vids), 3)
                ids.append(vids)
                targets.append(X.to(dev, dt))
            if ids:
                rows.append((torch.cat(ids), torch.cat(targets)))
                count[b] = len(rows[-1][0])
            else:
                rows.append(None)
        n = int(count.max())
        ids = torch.zeros(B, n, dtype=torch.int64, device=dev)
        X = torch.zeros(B, n, 3, dtype=dt, device=dev)
        mask = torch.zeros(B, n, dtype=dt, device=dev)
        for b, r in enumerate(rows):
            if r is not None:
                k = len(r[0])
                ids[b, :k], X[b, :k], mask[b, :k] = r[0], r[1], 1.0
        return SalientPairs(counts(B, correspondences=count, assigned=assigned), scene, ids, X, mask)

    def residuals(self, theta, posed, prepared: SalientPairs, jacobian=True):
        B, D = theta.shape
        p = prepared
        n = p.ids.shape[1]
        if n == 0:
            return no_residuals(theta, jacobian, 3)
        b = torch.arange(B, device=theta.device)[:, None]
        r = (posed.vertices[b, p.ids] - p.X) * p.mask[..., None]  # (B, n, 3)
        J = None
        if jacobian:
            J = p.scene.vertex_jacobian(posed, p.ids) * p.mask[..., None, None]
            J = J.reshape(B, 3 * n, D)
        return Residuals(r.reshape(B, 3 * n), J, 3, p.mask)


def simulated_detector(lookup: Callable[[torch.Tensor], Optional[np.ndarray]]):
    """A detector for experiments whose detections come from ``lookup(depth)``,
    which returns (N, 3) rows of (u, v, score) for a frame (e.g. perturbed ground
    truth, Ballan's protocol) or None."""
    from torchhand.salient.hough import Detections

    class _Simulated:
        def detect(self, depth):
            rows = lookup(depth)
            rows = np.zeros((0, 3)) if rows is None else np.asarray(rows, np.float64).reshape(-1, 3)
            d = torch.as_tensor(depth)
            uv = torch.as_tensor(rows[:, :2], dtype=torch.float32)
            iu = uv[:, 0].round().long().clamp(0, d.shape[1] - 1)
            iv = uv[:, 1].round().long().clamp(0, d.shape[0] - 1)
            return Detections(uv, torch.as_tensor(rows[:, 2], dtype=torch.float32), d[iv, iu].float())

    return _Simulated()
