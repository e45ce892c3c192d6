"""In-hand scanning (thesis Ch. 5): the object's motion from its data and the tracked
hand, its depth fused into one closed surface.

Per frame (:func:`scan`), given the object's depth (the tracked hand's pixels removed)
and the tracked hand's vertices:

1. contacts (Sec. 5.4.1, :func:`~torchhand.reconstruction.registration.contact_vertices`);
2. the start pose: the frame moves as the contact vertices moved since the previous
   frame (their rigid fit, the minimiser of Eq. 5.6 alone), so the grasp carries the
   object across the frames where its own shape says nothing (a sphere, a cylinder);
   where no end-effector touches the object's *visible* points (the fingers often hold
   it on the side the camera does not see, and the hand's dilated silhouette is cut
   from the data), the whole hand's vertices stand in for the contacts: the object
   moves with the hand (its palm is the part the tracker sees best); a frame where the
   hand hides the object moves it with the whole hand;
3. refinement against the reconstruction so far (frame-to-model ICP, point-to-plane,
   pairs within 5 mm, Eq. 5.7) together with the contact term (Eq. 5.6, weight
   ``gamma_t``), one least-squares problem, from three starts: the grasp's motion,
   the previous pose and a constant-velocity prediction; the result with the lowest
   objective (truncated point-to-plane cost plus ``gamma_t`` times the contact cost) is
   kept, so a jump of the tracked hand does not throw the object off where its shape
   holds it, and where its shape says nothing (a turn about a symmetry axis) the
   hand decides; The thesis refines by ICP alone after a
   pairwise sparse alignment (SIFT and ISS/CSHOT features and contacts, Eq. 5.3-5.5);
   keeping the contact term in the refinement holds a symmetric object where ICP has
   no say, and the feature terms are left out: the objects to scan here are textureless
   and smooth, where those features find nothing to match (thesis Fig. 5.4);
4. the frame's points join the reconstruction's point cloud (voxel-downsampled) and its
   depth the TSDF (:mod:`torchhand.reconstruction.fusion`).

Without hand vertices (the KinectFusion-style baseline), every frame starts from the
previous pose and is aligned by ICP alone.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import time
from typing import Iterable, List, NamedTuple, Optional

import numpy as np
import torch
from tqdm import tqdm

from torchhand.geometry.camera import depth_to_points_and_normals
from torchhand.geometry.neighbors import PointIndex
from torchhand.reconstruction.fusion import TSDF, FusionConfig, SurfaceMesh
from torchhand.reconstruction.registration import (ContactConfig, RegistrationConfig, contact_vertices, kabsch,
                                                   register_frame)

__all__ = ["ScanConfig", "ScanResult", "ScanError", "scan"]


class ScanError(ValueError):
    """The sequence cannot be scanned (the object is never seen, or leaves the view);
    the message names the frame."""


@dataclass(frozen=True)
class ScanConfig:
    """points: the most object points per frame used for registration (a random
    subset); model_voxel: mm, the reconstruction's point spacing; min_points: a frame
    with fewer object points is not registered nor fused (the hand covers the object);
    lost_frames: that many such frames in a row end the scan with an error;
    refine_passes: passes that align every fused frame again to the reconstruction of
    all frames (ICP alone, from its pose) before the depth is fused (0: fuse as the
    frames come)."""

    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    contacts: ContactConfig = field(default_factory=ContactConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    points: int = 3000
    model_voxel: float = 1.5
    min_points: int = 150
    lost_frames: int = 30
    refine_passes: int = 1


class ScanResult(NamedTuple):
    """mesh: the closed surface in the object frame; poses: (N, 4, 4) object ->
    camera per frame (the object frame is frame 0's camera frame moved to the
    centroid of frame 0's object points); fused: (N,) bool the frames fused;
    contacts: (N,) contact vertices per frame; icp_pairs: (N,); seconds: (N,) per frame
    (registration and fusion)."""

    mesh: SurfaceMesh
    poses: np.ndarray
    fused: np.ndarray
    contacts: np.ndarray
    icp_pairs: np.ndarray
    seconds: np.ndarray


def _points(depth: np.ndarray, K: torch.Tensor):
    d = torch.as_tensor(np.nan_to_num(np.asarray(depth, np.float64), nan=0.0))[None]
    p, n = depth_to_points_and_normals(d, K.double())
    keep = (d[0] > 0) & (n[0].norm(dim=-1) > 0.5)
    return p[0][keep], n[0][keep]


def _voxel_merge(points: torch.Tensor, normals: torch.Tensor, voxel: float):
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.numpy()))
    pc.normals = o3d.utility.Vector3dVector(normals.numpy())
    pc = pc.voxel_down_sample(voxel)
    n = torch.as_tensor(np.asarray(pc.normals))
    return torch.as_tensor(np.asarray(pc.points)), n / n.norm(dim=1, keepdim=True).clamp_min(1e-9)


def _fit_cost(points, X, index, model_p, model_n, radius) -> float:
    """The truncated point-to-plane cost of a frame at pose X: mean of min(d, radius)^2
    over its points, unpaired points charged radius^2 (the robust fit measure that
    chooses between registration starts)."""
    q = points @ X[:3, :3].T + X[:3, 3]
    nn = index.nearest(q[None], torch.zeros(1, dtype=torch.int64), torch.zeros(1, len(q), dtype=torch.int64))[0]
    d = ((q - model_p[nn.clamp_min(0)]) * model_n[nn.clamp_min(0)]).sum(1).abs().clamp_max(radius)
    d = torch.where(nn >= 0, d, torch.full_like(d, radius))
    return float(d.pow(2).mean())


def _refine(kept: dict, Xs: dict, model_p, model_n, K, width: int, height: int, config: "ScanConfig"):
    """One refinement pass: every fused frame aligned again, by ICP alone from its pose,
    to the reconstruction of all frames (no longer only the frames before it), and
    fused into a new TSDF. Returns the new poses and the TSDF."""
    index = PointIndex(model_p, torch.zeros(len(model_p), dtype=torch.int64),
                       torch.zeros(len(model_p), dtype=torch.int64), 1, 1, config.registration.icp_distance)
    tsdf = TSDF(K.numpy(), width, height, config.fusion)
    out = {}
    none = model_p[:0]
    for f, (ps, flat, vals) in kept.items():
        reg = register_frame(ps, Xs[f], index, model_p, model_n, none, none, config.registration)
        out[f] = reg.X
        d = np.zeros(height * width, np.float32)
        d[flat] = vals
        tsdf.integrate(d.reshape(height, width), torch.linalg.inv(reg.X).numpy())
    return out, tsdf


def _contact_cost(X, contacts_now, contacts_model) -> float:
    """Mean squared distance of the contact vertices moved by X to where the grasp puts
    them (the contact term per vertex; 0 without contacts)."""
    if len(contacts_now) == 0:
        return 0.0
    return float((contacts_now @ X[:3, :3].T + X[:3, 3] - contacts_model).pow(2).sum(1).mean())


def _next_hand(hands_it, f: int, bar) -> torch.Tensor:
    """Frame ``f``'s hand vertices (V, 3) float64 on the CPU from ``hands_it``; an error
    naming the frame (the progress ``bar`` closed) when they end or are not finite."""
    hand = next(hands_it, None)
    if hand is None:
        bar.close()
        raise ValueError(f"frame {f}: the hand vertices end before the depth frames")
    hand = hand.detach().double().cpu()
    if not torch.isfinite(hand).all():
        bar.close()
        raise ValueError(f"frame {f}: the hand vertices contain NaN or inf")
    return hand


def _subset(p: torch.Tensor, n: torch.Tensor, count: int, g: torch.Generator):
    """At most ``count`` of the points ``p`` and normals ``n`` (N, 3), a random subset
    (drawn from ``g``) when there are more."""
    if len(p) > count:
        pick = torch.randperm(len(p), generator=g)[:count]
        return p[pick], n[pick]
    return p, n


def _check_lost(f: int, missing: int, started: bool, lost_frames: int, bar) -> None:
    """:class:`ScanError` naming frame ``f`` (the progress ``bar`` closed) when the
    object has been missing for ``lost_frames`` frames in a row, before the
    reconstruction ``started`` or after."""
    if not started and missing >= lost_frames:
        bar.close()
        raise ScanError(f"frame {f}: the object is not seen apart from the hand in the first {missing} "
                        "frames (it never leaves the hand's silhouette, or the depth range cuts it)")
    if missing >= lost_frames:
        bar.close()
        raise ScanError(f"frame {f}: the object has not been seen for {missing} frames in a row "
                        "(it left the view or the hand covers it)")


def _register_next(ps: torch.Tensor, hand, prev_hand, contacts: torch.Tensor, X: torch.Tensor, X_before,
                   model_p: torch.Tensor, model_n: torch.Tensor, config: ScanConfig):
    """The registration of a frame's points ``ps`` (n, 3) to the reconstruction
    (``model_p``, ``model_n``) from three starts, the grasp's motion (the hand's
    ``contacts`` from ``prev_hand`` to ``hand``), the previous pose ``X`` and constant
    velocity (from ``X_before``): the one that fits best (Eq. 5.2)."""
    start, ids = X, contacts[:0]
    if hand is not None and prev_hand is not None:
        # the contact vertices, or the whole hand's when none touches the data
        # seen (the fingers hold the object where the camera does not see it)
        ids = contacts if len(contacts) >= 3 else torch.arange(len(hand))
        # x_prev = A x_now for those vertices: the grasp's motion
        start = X @ kabsch(hand[ids], prev_hand[ids])
    c_now = hand[ids] if len(ids) else ps[:0]
    c_model = (prev_hand[ids] @ X[:3, :3].T + X[:3, 3]) if len(ids) else ps[:0]
    index = PointIndex(model_p, torch.zeros(len(model_p), dtype=torch.int64),
                       torch.zeros(len(model_p), dtype=torch.int64), 1, 1, config.registration.icp_distance)
    starts = [start, X] if start is not X else [X]
    if X_before is not None:  # constant velocity
        starts.append(X @ torch.linalg.inv(X_before) @ X)
    regs = [register_frame(ps, s0, index, model_p, model_n, c_now, c_model, config.registration)
            for s0 in starts]
    costs = [_fit_cost(ps, r.X, index, model_p, model_n, config.registration.icp_distance)
             + config.registration.gamma_t * _contact_cost(r.X, c_now, c_model) for r in regs]
    return regs[int(np.nanargmin(costs))] if np.isfinite(costs).any() else regs[0]


def _grown(model_p: torch.Tensor, model_n: torch.Tensor, p: torch.Tensor, n: torch.Tensor, X: torch.Tensor,
           voxel: float):
    """The reconstruction's points and normals with a frame's ``p``, ``n`` (N, 3)
    moved by its pose ``X`` (camera -> object) added, merged per voxel."""
    R = X[:3, :3]
    return _voxel_merge(torch.cat([model_p, p @ R.T + X[:3, 3]]), torch.cat([model_n, n @ R.T]), voxel)


def _kept_frame(ps: torch.Tensor, depth: np.ndarray) -> tuple:
    """What the refinement keeps of a fused frame: its point subset ``ps``, the flat
    indices of its depth pixels and their depths."""
    flat = np.flatnonzero(np.nan_to_num(np.asarray(depth, np.float32)) > 0)
    return ps, flat, np.asarray(depth, np.float32).ravel()[flat]


def _refine_passes(kept: dict, kept_normals: dict, Xs: dict, model_p, model_n, K, width: int, height: int,
                   config: ScanConfig):
    """``config.refine_passes`` passes of :func:`_refine`, each after the first aligning
    to the reconstruction rebuilt from the refined poses. Returns the poses and the TSDF."""
    for k in range(config.refine_passes):
        if k:  # a further pass aligns to the reconstruction rebuilt from the refined poses
            model_p, model_n = _voxel_merge(torch.cat([ps @ Xs[f][:3, :3].T + Xs[f][:3, 3] for f, (ps, _, _) in kept.items()]),
                                            torch.cat([ns @ Xs[f][:3, :3].T for f, ns in kept_normals.items()]),
                                            config.model_voxel)
        Xs, tsdf = _refine(kept, Xs, model_p, model_n, K, width, height, config)
    return Xs, tsdf


def scan(depths: Iterable[np.ndarray], K, width: int, height: int, hands: Optional[Iterable[torch.Tensor]] = None,
         effectors: Optional[List[torch.Tensor]] = None, config: ScanConfig = ScanConfig(), frames: Optional[int] = None,
         seed: int = 0, progress: bool = True, desc: str = "scan") -> ScanResult:
    """Reconstruct the object seen in ``depths``.

    Args:
        depths: per frame, the object's depth (H, W) mm (0 or NaN where not the object).
        K: (3, 3) intrinsics; width, height: of the depth maps.
        hands: per frame, the tracked hand's (V, 3) vertices in the camera frame (None:
            the baseline without the hand).
        effectors: vertex ids (k_e,) of each end-effector (distal bone) of the hand.
        frames: the number of frames (for the progress bar).
    Returns:
        :class:`ScanResult`. Raises :class:`ScanError` when the object is never seen
        apart from the hand, or is lost for ``config.lost_frames`` frames in a row.
    """
    K = torch.as_tensor(np.asarray(K, np.float64))
    g = torch.Generator().manual_seed(seed)
    tsdf = TSDF(K.numpy(), width, height, config.fusion)
    hands_it = iter(hands) if hands is not None else None
    poses, fused, n_contacts, n_pairs, secs = [], [], [], [], []
    X = X_before = None  # camera -> object of the last registered frame, and of the one before it
    model_p = model_n = prev_hand = None
    missing = 0
    kept, Xs, kept_normals = {}, {}, {}  # per fused frame: (points, depth pixels, depth values); its pose
    bar = tqdm(total=frames, desc=desc, unit="frame", disable=not progress)
    for f, depth in enumerate(depths):
        t0 = time.perf_counter()
        hand = _next_hand(hands_it, f, bar) if hands_it is not None else None
        p, n = _points(depth, K)
        ps, ns = _subset(p, n, config.points, g)
        ok = len(p) >= config.min_points
        contacts = torch.zeros(0, dtype=torch.int64)
        if ok and hand is not None and effectors is not None:
            contacts = contact_vertices(hand, effectors, p, config.contacts)
        pairs = 0
        if not ok:
            missing += 1
            _check_lost(f, missing, X is not None, config.lost_frames, bar)
            if X is not None and hand is not None and prev_hand is not None:
                # unseen (the hand covers it): the object moves with the whole hand
                X_before, X = X, X @ kabsch(hand, prev_hand)
        elif X is None:  # frame 0 of the reconstruction: the object frame
            X = torch.eye(4, dtype=torch.float64)
            X[:3, 3] = -p.mean(0)
            model_p, model_n = _voxel_merge(p + X[:3, 3], n, config.model_voxel)
            missing = 0
        else:
            reg = _register_next(ps, hand, prev_hand, contacts, X, X_before, model_p, model_n, config)
            X_before, X, pairs = X, reg.X, reg.icp_pairs
            model_p, model_n = _grown(model_p, model_n, p, n, X, config.model_voxel)
            missing = 0
        if ok and X is not None:
            if config.refine_passes:  # kept for the refinement: the subset and the depth's pixels
                kept[f], kept_normals[f] = _kept_frame(ps, depth), ns
            else:
                tsdf.integrate(depth, torch.linalg.inv(X).numpy())
            Xs[f] = X
        if hand is not None:
            prev_hand = hand
        poses.append(torch.linalg.inv(X).numpy() if X is not None else np.full((4, 4), np.nan))
        fused.append(bool(ok and X is not None))
        n_contacts.append(len(contacts))
        n_pairs.append(pairs)
        secs.append(time.perf_counter() - t0)
        bar.update(1)
    bar.close()
    if X is None:
        raise ScanError("no frame shows the object apart from the hand")
    t0 = time.perf_counter()
    if config.refine_passes:
        Xs, tsdf = _refine_passes(kept, kept_normals, Xs, model_p, model_n, K, width, height, config)
        for f, X_f in Xs.items():
            poses[f] = torch.linalg.inv(X_f).numpy()
    mesh = tsdf.surface()
    secs[-1] += time.perf_counter() - t0
    # frames before the first registered one keep NaN poses
    return ScanResult(mesh, np.stack(poses), np.array(fused), np.array(n_contacts), np.array(n_pairs),
                      np.array(secs))
