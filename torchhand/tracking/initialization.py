"""Automatic initialisation of the hands' pose: a global search, then the tracker's LM.

Used when a sequence has no ``init_pose.json`` (``torchhand track``) and by
``torchhand init``. Per hand blob of the segmentation (:mod:`torchhand.tracking.segmentation`):

1. seeds: where the localiser found the hand's 21 joints (``segment auto``), first the
   pose whose standard joints best fit them (:func:`keypoint_pose`: the palm by a rigid
   fit of the wrist and knuckles, then every DoF by LM on all 21 joints weighted by
   their confidence, then again with the joints left far off down-weighted), so
   half-closed hands and fists start curled; and always the
   blob's seeds: the model's palm centre on the blob's palm centre (12 mm behind the seen
   surface), the hand's length axis on the blob's first principal axis (pointing away
   from the forearm where one was seen; else towards the fingertips that the shipped
   detector finds on the blob, when at least two lie 20 mm or more along the axis from
   the blob's centroid and at least three times as many on that side as on the other
   (the thumb may lie aside); both signs otherwise), its palm normal on the blob's third
   axis (both signs), fingers at the rest pose;
2. particle swarm optimisation (:func:`~torchhand.optim.pso.particle_swarm`, 64
   particles x 40 generations by default, as FORTH's tracker and HOPE64) around the
   seeds over FORTH's depth-discrepancy objective: the rendered depth of each particle
   against the segmented data at a low resolution (the blob's box at ``resolution`` px),
   ``mean over the union of both silhouettes of min(|d_model - d_data|, clamp) / clamp``
   (a pixel in one silhouette only costs 1). All particles are rendered as one batch,
   depth only (:meth:`~torchhand.geometry.render.Renderer.depth`: the rasteriser's depth
   test, without the exact hits and maps the tracker needs);
3. the best ``refine`` distinct particles are refined by the tracker's own objective
   (Algorithm 1, ``refine_iterations`` iterations, one batch) and the one with the
   lowest discrepancy at full resolution is kept, unless it is more than
   :data:`REFINE_SLACK` worse than the best unrefined pick (a refinement that left the
   data), which is kept then.
4. step 2 runs ``restarts`` times (2 by default) from independently seeded swarms
   (seeds ``seed * restarts + r``), and step 3 refines their best picks (``refine`` in
   all, shared among the swarms) as one batch: a
   swarm that settles a finger beside the truth scores clearly worse at full
   resolution than one that does not (0.148-0.219 against 0.084-0.088 on the thesis
   renders of sequences 08 and 11, docs/results.md), so a second swarm makes such a
   start rarer.

The particles are rendered with a coarse proxy of each hand (:func:`~torchhand.model.
proxy.coarse_model`, ``proxy_faces`` triangles: the same skeleton on a decimated mesh),
which at the search's resolution renders the same depth for a tenth of the work; the
refinement and the final choice use the full models. An :class:`Initializer` builds the
proxies once, for the frames of a whole run (re-initialisation); ``initialize_hands``
is the one-frame shortcut.

The thesis initialises from a given pose; FORTH's objective is used for the search
because it needs no correspondences, so a particle far from the data still has a
meaningful cost. Only hands are initialised: a scene with objects needs init_pose.json.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import NamedTuple, Optional

import numpy as np
import torch

from torchhand.core.check import skip_checks
from torchhand.geometry.camera import Camera
from torchhand.geometry.mesh import is_closed_outward
from torchhand.geometry.render import Renderer
from torchhand.geometry.rigid import kabsch
from torchhand.model.joints21 import joint_sources, standard_joint_jacobian, standard_joints
from torchhand.optim.levenberg_marquardt import levenberg_marquardt
from torchhand.model.kinematics import so3_log
from torchhand.model.proxy import coarse_model
from torchhand.model.scene import Scene
from torchhand.optim.pso import particle_swarm
from torchhand.tracking.preprocess import preprocess_depth
from torchhand.tracking.segmentation import Segmentation

__all__ = ["InitConfig", "InitResult", "Initializer", "initialize_hands", "depth_discrepancy", "crop_camera",
           "search_box", "keypoint_pose", "KEYPOINT_SEED_CONFIDENCE"]

#: A located hand seeds the search from its joints when their mean confidence reaches this
#: (the shipped localiser's peaks average 0.1-0.3 and do not track the joints' error;
#: docs/localiser.md).
KEYPOINT_SEED_CONFIDENCE = 0.1
#: A seed from the joints is dropped when its mesh centre lies farther than this (mm)
#: from the segmentation's palm point (a fit thrown off by misplaced joints).
KEYPOINT_SEED_REACH = 150.0
#: A refined pose is kept unless its depth discrepancy exceeds the best unrefined swarm
#: pick's by more than this (0 .. 1: a diverged refinement scores ~1).
REFINE_SLACK = 0.05
#: Scale (mm) of the robust weights of :func:`keypoint_pose`'s second fit.
ROBUST_JOINT_MM = 20.0
#: The palm's joints among the standard 21 (wrist, thumb CMC, the four knuckles).
_PALM_JOINTS = [0, 1, 5, 9, 13, 17]


#: Fingertip detections scoring below this are not used (as the salient-point term).
TIP_SCORE = 0.15


@dataclass(frozen=True)
class InitConfig:
    particles: int = 64
    generations: int = 40
    resolution: int = 64
    clamp_mm: float = 40.0
    rotation_spread: float = 0.35
    translation_spread: float = 15.0
    finger_spread: float = 0.25
    refine: int = 4
    refine_iterations: int = 15
    proxy_faces: int = 2000
    fingertips: bool = True
    seed: int = 0
    restarts: int = 2

    def __post_init__(self) -> None:
        for name in ("particles", "generations", "resolution", "refine", "refine_iterations", "proxy_faces",
                     "restarts"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"InitConfig.{name} must be an integer >= 1, got {v!r}")


class InitResult(NamedTuple):
    """theta: (D,) the pose found; cost: its depth discrepancy at full resolution (0 best,
    1 no overlap); search_cost: the swarm's best cost; seconds: wall time."""

    theta: torch.Tensor
    cost: float
    search_cost: float
    seconds: float


def _hand_frame(model) -> tuple:
    """(palm centre (3,), length axis (3,), palm normal (3,)) of the rest pose, world."""
    with torch.no_grad():
        k = model(model.zero_pose(1)).keypoints[0]
    k = k.double()
    wrist, mid, index, little = k[0], k[9], k[5], k[17]
    centre = (wrist + mid) / 2
    axis = (mid - wrist) / torch.linalg.norm(mid - wrist)
    side = index - little
    normal = torch.linalg.cross(axis, side)
    normal = normal / torch.linalg.norm(normal)
    return centre, axis, normal


def crop_camera(camera: Camera, box: tuple, resolution: int) -> tuple:
    """A camera seeing the pixel box (r0, r1, c0, c1) at ``resolution`` px on its long side,
    and the full-resolution pixel of each of its pixels."""
    r0, r1, c0, c1 = box
    s = resolution / max(r1 - r0, c1 - c0)
    h, w = max(int(round((r1 - r0) * s)), 1), max(int(round((c1 - c0) * s)), 1)
    fx, fy = camera.fx * s, camera.fy * s
    cx, cy = (camera.cx - c0 + 0.5) * s - 0.5, (camera.cy - r0 + 0.5) * s - 0.5
    small = Camera.from_intrinsics(fx, fy, cx, cy, w, h, T_cw=camera.T_cw, dtype=camera.dtype, device=camera.device)
    rows = np.clip(np.round((np.arange(h) + 0.5) / s - 0.5).astype(int) + r0, 0, camera.height - 1)
    cols = np.clip(np.round((np.arange(w) + 0.5) / s - 0.5).astype(int) + c0, 0, camera.width - 1)
    return small, rows, cols


def search_box(mask: np.ndarray) -> tuple:
    """(r0, r1, c0, c1): the box of a mask's pixels widened by 30 % of its size (+4 px)."""
    rows, cols = np.nonzero(mask)
    pad = int(0.3 * max(rows.max() - rows.min(), cols.max() - cols.min())) + 4
    H, W = mask.shape
    return (max(rows.min() - pad, 0), min(rows.max() + 1 + pad, H), max(cols.min() - pad, 0),
            min(cols.max() + 1 + pad, W))


def depth_discrepancy(model_depth: torch.Tensor, data: torch.Tensor, clamp: float) -> torch.Tensor:
    """(N, h, w) rendered depth vs (h, w) data (NaN: unknown, left out) -> (N,) FORTH's
    clamped depth discrepancy."""
    m, d = (model_depth > 0) & ~torch.isnan(data)[None], (data > 0)[None]
    both = m & d
    cost = torch.where(both, ((model_depth - data).abs() / clamp).clamp(max=1.0), (m | d).to(model_depth.dtype))
    union = (m | d).sum((1, 2)).clamp(min=1)
    return cost.sum((1, 2)) / union


class Initializer:
    """The automatic initialisation of a tracker's hands, for any number of frames.

    Args:
        tracker: a :class:`~torchhand.tracking.tracker.Tracker` of the scene (its
            renderer, objective and LM refine the search); its energy history is not
            touched, so a run can re-initialise mid-sequence.
        config: :class:`InitConfig`.
    """

    def __init__(self, tracker, config: InitConfig = InitConfig()):
        scene = tracker.scene
        if any(m.kind != "hand" for m in scene.models):
            raise ValueError(f"the automatic initialisation places hands only; the scene {list(scene.names)} has "
                             "objects: give init_pose.json")
        self.tracker, self.config = tracker, config
        self.coarse = Scene([coarse_model(m, config.proxy_faces) for m in scene.models], names=list(scene.names))
        cull = all(is_closed_outward(m.vertices_rest, m.faces) for m in self.coarse.models)
        self.renderer = Renderer(self.coarse.faces, self.coarse.face_model_id, self.coarse.face_bone_id,
                                 backend=tracker.config.render_backend, cull_back_faces=cull)
        self._detector = None

    def fingertips(self, data: np.ndarray, blob: np.ndarray, camera: Camera) -> np.ndarray:
        """(n, 3) camera-frame points of the fingertips the shipped detector finds on one
        blob of a segmented frame (score >= ``TIP_SCORE``; each at the median depth of its
        5x5 pixels in the blob)."""
        if self._detector is None:
            from torchhand.salient.detector import SalientDetector

            self._detector = SalientDetector.load_onnx(threads=1)
        det = self._detector.detect(np.nan_to_num(data, nan=0.0).astype(np.float32))
        H, W = blob.shape
        out = []
        for u, v in det.uv.numpy()[det.score.numpy() >= TIP_SCORE].round().astype(int):
            v0, v1, u0, u1 = max(v - 2, 0), min(v + 3, H), max(u - 2, 0), min(u + 3, W)
            z = data[v0:v1, u0:u1][blob[v0:v1, u0:u1]]
            z = z[np.isfinite(z) & (z > 0)]
            if len(z):
                zm = float(np.median(z))
                out.append(((u - camera.cx) * zm / camera.fx, (v - camera.cy) * zm / camera.fy, zm))
        return np.asarray(out, np.float64).reshape(-1, 3)

    def _seed_poses(self, model, k: int, segmentation: Segmentation, data_full: np.ndarray,
                    camera: Camera) -> list:
        located = segmentation.located[k] if k < len(segmentation.located) else None
        if located is not None and float(np.mean(located.confidence)) >= KEYPOINT_SEED_CONFIDENCE:
            joints = np.stack([(located.uv[:, 0] - camera.cx) * located.z / camera.fx,
                               (located.uv[:, 1] - camera.cy) * located.z / camera.fy, located.z], 1)
            # the joints' pose first; the blob's seeds stay hypotheses of their own swarms
            # (the swarm keeps what fits the depth best: a few misplaced joints cannot trap it)
            blob = self._blob_seeds(model, k, segmentation, data_full, camera)
            seed = keypoint_pose(model, joints, located.confidence, camera)
            # a fit thrown off by misplaced joints (its palm far from the hand's) is no seed
            with torch.no_grad():
                palm = model(seed[None].to(model.vertices_rest.dtype)).vertices[0].double().mean(0).cpu().numpy()
            T_cw = camera.T_cw.double().cpu().numpy()
            seen = T_cw[:3, :3] @ palm + T_cw[:3, 3]
            return ([seed] if np.linalg.norm(seen - segmentation.palms[k]) < KEYPOINT_SEED_REACH else []) + blob
        return self._blob_seeds(model, k, segmentation, data_full, camera)

    def _blob_seeds(self, model, k: int, segmentation: Segmentation, data_full: np.ndarray,
                    camera: Camera) -> list:
        """The seed hypotheses (D_m,) float64 of one hand ``model`` from its blob ``k``:
        the palm at the blob's palm point, the hand's length along the blob's main axis
        (pointing away from the forearm, or towards the fingertips seen, else both ways)
        and the palm's normal along the blob's least axis (both ways)."""
        config = self.config
        v, u = np.nonzero(segmentation.blobs[k])
        z = data_full[v, u]
        pts = np.stack([(u - camera.cx) * z / camera.fx, (v - camera.cy) * z / camera.fy, z], 1)
        palm = segmentation.palms[k] + 12.0 * segmentation.palms[k] / np.linalg.norm(segmentation.palms[k])
        c = pts - pts.mean(0)
        _, _, vt = np.linalg.svd(c, full_matrices=False)
        a1, a3 = vt[0], vt[2]
        arm = segmentation.forearm[k]
        signs_axis = [1.0, -1.0]
        if np.any(arm):
            signs_axis = [-1.0 if a1 @ arm > 0 else 1.0]
        elif config.fingertips:
            along = (self.fingertips(data_full, segmentation.blobs[k], camera) - pts.mean(0)) @ a1
            pos, neg = int((along >= 20.0).sum()), int((along <= -20.0).sum())
            if max(pos, neg) >= 2 and max(pos, neg) >= 3 * min(pos, neg):  # the thumb may lie aside
                signs_axis = [1.0 if pos > neg else -1.0]
        centre, axis, normal = (x.numpy() for x in _hand_frame(model))
        T_wc = camera.T_wc.double().cpu().numpy()
        palm_w = T_wc[:3, :3] @ palm + T_wc[:3, 3]
        rc = model.rest_transforms[0][:3, 3].double().cpu()
        options = []
        for sa in signs_axis:
            for sn in (1.0, -1.0):
                A = sa * (T_wc[:3, :3] @ a1)
                N = sn * (T_wc[:3, :3] @ a3)
                N = N - (N @ A) * A
                N /= np.linalg.norm(N)
                tgt = np.stack([A, N, np.cross(A, N)], 1)
                src = np.stack([axis, normal, np.cross(axis, normal)], 1)
                R = tgt @ src.T
                rot = so3_log(torch.as_tensor(R, dtype=torch.float64)[None])[0]
                Rt = torch.as_tensor(R)
                t = torch.as_tensor(palm_w) - rc - Rt @ (torch.as_tensor(centre) - rc)
                th = torch.zeros(model.num_dofs, dtype=torch.float64)
                th[:3], th[3:6] = t, rot
                options.append(th)
        return options

    def __call__(self, depth: np.ndarray, camera: Camera, segmentation: Segmentation,
                 around: Optional[torch.Tensor] = None) -> InitResult:
        """Find the pose of the scene's hands in one segmented depth frame.

        Args:
            depth: (H, W) mm, the frame (the segmentation is applied here).
            camera: its camera.
            segmentation: the frame's hands (one blob per hand model, left to right).
            around: (D,) a pose to search around as well (re-initialisation).
        """
        t0 = time.perf_counter()
        tracker, config = self.tracker, self.config
        scene = tracker.scene
        if len(segmentation.blobs) != len(scene.models):
            raise ValueError(f"{len(scene.models)} hands in the scene, {len(segmentation.blobs)} segmented")
        dev, dt = camera.device, torch.float32
        data_full = segmentation.apply(depth)
        P, D = config.particles, scene.num_dofs
        # the two hands: the right hand is on the image's left for a camera facing the person
        order = np.argsort([0 if m.side == "right" else 1 for m in scene.models], kind="stable")
        hyp = [self._seed_poses(model, int(np.where(order == mi)[0][0]), segmentation, data_full, camera)
               for mi, model in enumerate(scene.models)]
        # particles: spread around every combination of the hands' seed hypotheses
        combos = [[]]
        for options in hyp:
            combos = [c + [o] for c in combos for o in options]
        bases = [torch.cat(c) for c in combos]
        if around is not None:
            bases.append(around.detach().double().cpu())
        lo, hi = scene.lower.double().cpu(), scene.upper.double().cpu()
        spread = _spread(scene, config)
        small, rr, cc = crop_camera(camera, search_box(segmentation.mask), config.resolution)
        data_small = torch.as_tensor(data_full[np.ix_(rr, cc)], device=dev)
        frame = preprocess_depth(data_full, camera, tracker.config.preprocess, device=dev, dtype=dt)
        data_t = torch.as_tensor(data_full, device=dev)

        def cost(pos: torch.Tensor, cam=small, data=data_small, models=self.coarse, renderer=self.renderer
                 ) -> torch.Tensor:
            th = scene.clamp(pos.reshape(-1, D).to(dev, dt))
            with torch.no_grad(), skip_checks():
                depth = renderer.depth(models(th, validate=False).vertices, cam)  # the depth test's depth alone
            return depth_discrepancy(depth, data, config.clamp_mm).double().cpu().reshape(pos.shape[:2])

        picks, swarm_costs = [], []
        for r in range(config.restarts):  # independent swarms, their picks refined together
            gen = torch.Generator().manual_seed(config.seed * config.restarts + r)
            x = torch.maximum(torch.minimum(_particles(bases, P, spread, gen), hi), lo)
            res = particle_swarm(cost, x, lo, hi, config.generations, velocity_scale=spread * 0.5, generator=gen)
            # the best of every swarm, then the best distinct particles: ``refine`` in all
            share = -(-config.refine // config.restarts)
            picks.append(res.particles.reshape(-1, D)[_refine_picks(res, share)])
            swarm_costs.append(float(res.cost.min()))
        # refined with the tracker's objective, as one batch
        starts = scene.clamp(torch.cat(picks).to(dev, dt))
        n = len(starts)
        refined = tracker.solve(starts, starts, [frame] * n, [camera] * n, config.refine_iterations, 0.0).theta
        # the swarms' picks stay candidates: a refinement that went off the data (a
        # diverged LM) is not taken, though one that fits a little worse by this coarse
        # measure is (LM's own objective is the finer one)
        cands = torch.cat([refined.detach(), starts])
        final = cost(cands[None].double(), camera, data_t, scene, tracker.renderer)[0]
        k = int(torch.argmin(final[:n]))
        if final[k] > final[n:].min() + REFINE_SLACK:
            k = n + int(torch.argmin(final[n:]))
        return InitResult(cands[k], float(final[k]), min(swarm_costs), time.perf_counter() - t0)


def keypoint_pose(model, joints: np.ndarray, confidence: np.ndarray, camera: Camera, iterations: int = 15
                  ) -> torch.Tensor:
    """(D,) float64 the pose of hand ``model`` whose standard 21 joints
    (:mod:`torchhand.model.joints21`) best fit ``joints`` (21, 3) mm in ``camera``'s
    frame, weighted by ``confidence`` (21,): the global pose by a rigid fit of the palm's
    joints (wrist, thumb base, knuckles), then every DoF within its limits by LM on all
    21 joints (``iterations``, the joints' analytic Jacobian), then once more with the
    joints that fit leaves far off down-weighted (:data:`ROBUST_JOINT_MM`)."""
    m = model
    dt = m.vertices_rest.dtype
    src = joint_sources(m)
    T_wc = camera.T_wc.to(dt).cpu()
    target = torch.as_tensor(joints, dtype=dt) @ T_wc[:3, :3].T + T_wc[:3, 3]  # world frame
    w = torch.as_tensor(np.clip(confidence, 0.05, 1.0), dtype=dt).sqrt()
    with torch.no_grad():
        rest = standard_joints(m(m.zero_pose(1).to(dt)), m, src)[0]
    T = kabsch(rest[_PALM_JOINTS].double(), target[_PALM_JOINTS].double()).to(dt)
    rc = m.rest_transforms[0][:3, 3]
    theta0 = torch.zeros(1, m.num_dofs, dtype=dt)
    theta0[0, 3:6] = so3_log(T[None, :3, :3])[0]
    theta0[0, :3] = T[:3, 3] + T[:3, :3] @ rc - rc

    def residuals(theta: torch.Tensor, with_jacobian: bool) -> tuple:
        with torch.no_grad(), skip_checks():
            posed = m(theta, validate=False)
            r = ((standard_joints(posed, m, src) - target) * w[:, None]).reshape(len(theta), -1)
            if not with_jacobian:
                return r, None
            J = (standard_joint_jacobian(posed, m, src) * w[:, None, None]).reshape(len(theta), r.shape[1], -1)
        return r, J

    res = levenberg_marquardt(residuals, theta0, m.lower, m.upper, max_iterations=iterations)
    # then robustly: joints the fit leaves far off (misplaced detections) are down-weighted
    # (Cauchy weights, scale ROBUST_JOINT_MM) and the fit is run again from there
    with torch.no_grad(), skip_checks():
        off = (standard_joints(m(res.theta, validate=False), m, src)[0] - target).norm(dim=-1)
    w = w * (1.0 + (off / ROBUST_JOINT_MM) ** 2).rsqrt()
    res = levenberg_marquardt(residuals, res.theta, m.lower, m.upper, max_iterations=iterations)
    return res.theta[0].detach().double()


def _spread(scene, config: InitConfig) -> torch.Tensor:
    """(D,) float64 the particles' spread: ``config.translation_spread`` and
    ``rotation_spread`` on each model's global DoF, ``finger_spread`` elsewhere."""
    spread = torch.full((scene.num_dofs,), config.finger_spread, dtype=torch.float64)
    for sl in scene.slices.values():
        spread[sl.start : sl.start + 3] = config.translation_spread
        spread[sl.start + 3 : sl.start + 6] = config.rotation_spread
    return spread


def _particles(bases: list, P: int, spread: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """(S, n, D) float64 start particles around the seed poses ``bases`` (D,) each:
    one independent swarm per seed hypothesis (a shared best would pull every particle
    into the first basin found: a hand flipped about its length axis has a similar
    silhouette), unless there are too many for a useful swarm each (S = 1); every
    seed itself, the others drawn about it with ``spread`` (D,) from ``gen``."""
    D = spread.shape[0]
    S = len(bases) if len(bases) * 8 <= P else 1
    n = P // S
    x = torch.zeros(S, n, D, dtype=torch.float64)
    for k in range(S * n):
        sw, p = (k % S, k // S) if S > 1 else (0, k)
        base = bases[sw] if S > 1 else bases[k % len(bases)]
        first = p == 0 if S > 1 else k < len(bases)
        x[sw, p] = base + (0 if first else torch.randn(D, generator=gen, dtype=torch.float64) * spread)
    return x


def _refine_picks(res, refine: int) -> list:
    """The particles of the swarms ``res`` (S swarms of n) that the tracker refines:
    the best of every swarm, then the best particles distinct from those picked
    (5 mm apart, or 0.3 rad in a DoF), ``refine`` in all (at least S); flat indices."""
    S, n, D = res.particles.shape
    own, oc = res.particles.reshape(-1, D), res.particle_cost.reshape(-1)
    pick = [int(torch.argmin(res.particle_cost[sw])) + sw * n for sw in range(S)][: max(refine, S)]
    for i in torch.argsort(oc).tolist():
        if len(pick) >= refine:
            break
        if all(torch.linalg.norm(own[i, :3] - own[j, :3]) > 5 or (own[i] - own[j]).abs().max() > 0.3 for j in pick):
            pick.append(i)
    return pick


def initialize_hands(tracker, depth: np.ndarray, camera: Camera, segmentation: Segmentation,
                     config: InitConfig = InitConfig(), around: Optional[torch.Tensor] = None) -> InitResult:
    """One frame's :class:`Initializer` (builds the proxies each call: for many frames,
    keep an :class:`Initializer`)."""
    return Initializer(tracker, config)(depth, camera, segmentation, around)
