"""Error measures: keypoint errors in px and mm, PCK curves and their AUC, the joint
errors of the hand pose literature (MPJPE, PA-MPJPE, root-relative MPJPE) with validity
masks, interpenetration of posed meshes, and the fit check of a tracked frame without
ground truth (:func:`fit_check`: the tracker's own data, and the hand localiser's
independent evidence, which can say that the tracker follows the wrong thing).

The 2D measure is the thesis' (Table 4.6): the mean Euclidean distance in pixels
between projected keypoints and ground truth. The 3D measure is the same in mm in
the camera frame. The curve is the fraction of keypoints within a 3D threshold.

Joint errors take ground truth that may lack joints: a joint is absent when any of its
coordinates is NaN, when all of them are -1 (how several datasets mark a missing joint)
or when the caller's mask says so. Absent joints are left out of every mean, never
scored as zero; a mean over no joints is NaN.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Optional, Sequence

import cv2
import numpy as np

__all__ = ["keypoint_errors", "pck_curve", "auc", "Penetration", "penetration", "max_depth", "model_pair_counts",
           "PCK_THRESHOLDS_MM", "fit_quality", "fit_check", "surrounded", "FitCheck", "FitCheckLimits", "valid_joints", "joint_errors", "similarity_align", "mpjpe",
           "pa_mpjpe", "rr_mpjpe", "JointScores", "joint_scores", "mean_px", "per_joint_mean"]

#: thresholds of the PCK curve, 0..50 mm in 1 mm steps
PCK_THRESHOLDS_MM = np.arange(0.0, 50.0 + 1e-9, 1.0)


def fit_quality(model_depth: np.ndarray, data_depth: np.ndarray) -> tuple:
    """How well a fitted model explains depth data without ground truth.

    model_depth: (H, W) the rendered fitted models' depth in mm (0 = empty); data_depth:
    (H, W) the data the tracker saw (segmented, 0 = none, NaN = unknown: model pixels
    there, such as a wrist over the forearm cut away, are left out). Returns
    (silhouette IoU of the two masks, median |model - data| mm where both have depth);
    (nan, nan) when both are empty, median nan when they do not overlap.
    """
    data_depth = np.asarray(data_depth)
    m, d = (np.asarray(model_depth) > 0) & ~np.isnan(data_depth), data_depth > 0
    union = int((m | d).sum())
    if union == 0:
        return float("nan"), float("nan")
    both = m & d
    if not both.any():
        return 0.0, float("nan")
    diff = np.asarray(model_depth, np.float64)[both] - np.asarray(data_depth, np.float64)[both]
    return float(both.sum()) / union, float(np.median(np.abs(diff)))


@dataclass(frozen=True)
class FitCheckLimits:
    """Where a frame's fit check fails (docs/localiser.md, "The fit check").

    Attributes:
        keypoint_mm: the median distance between the model's projected standard joints
            and the localiser's confident ones, in mm at the joints' depth (px x z / f),
            above which the fit is flagged (the shipped localiser's joints lie ~25 mm
            from the true ones on its test set, a hand on the wrong blob hundreds);
        explained: the share of the localiser's hand pixels under the model's
            silhouette below which it is flagged;
        off_hand: the share of the model's silhouette on measured pixels that the
            localiser calls not hand (3 px of margin) above which it is flagged;
        confidence: joints of the localiser below this confidence are not compared;
        surrounded: the share of a hand's surround (:func:`surrounded`) where the measured
            surface goes on at the hand's depth above which the fit is flagged: a hand
            ends in depth edges except at the wrist and where it holds something (the
            tracked SR305 frames at most 0.24, docs/localiser.md), a model laid on a body
            or a table is surrounded by that surface (0.80-0.96 on the SR305 body). The one measure that needs no
            localiser, so it also checks the blob rules' segmentation; it does not flag a
            hand for which at least ``vouching_joints`` of the localiser's confident
            joints of that hand lie a median half of ``keypoint_mm`` or less from the
            model's (a grasp, a hand on a table).
    """

    keypoint_mm: float = 40.0
    explained: float = 0.6
    off_hand: float = 0.3
    confidence: float = 0.3
    surrounded: float = 0.6
    vouching_joints: int = 10


class FitCheck(NamedTuple):
    """One frame's fit check: the silhouette IoU and median depth residual of
    :func:`fit_quality`, and against the localiser (NaN without it): ``keypoint_px``
    (the median joint distance in px) and ``keypoint_mm`` (the same in mm at the joints'
    depth), ``explained``, ``off_hand``, and from the measured depth alone
    ``surrounded`` (the most surrounded hand, :func:`surrounded`; NaN without it) (see
    :class:`FitCheckLimits`); ``flagged``: a limit is crossed (False without evidence)."""

    iou: float
    residual_mm: float
    keypoint_px: float = float("nan")
    keypoint_mm: float = float("nan")
    explained: float = float("nan")
    off_hand: float = float("nan")
    flagged: bool = False
    surrounded: float = float("nan")


def surrounded(own: np.ndarray, model_depth: np.ndarray, models: np.ndarray, measured: np.ndarray, focal: float,
               band_mm: tuple = (6.0, 20.0), tolerance_mm: float = 25.0) -> float:
    """The share of a hand model's surround where the measured surface goes on at the
    hand's depth: evidence, from the sensor alone, that the model lies on a surface
    (a body, an arm, a table) rather than on a hand, which ends in depth edges.

    Args:
        own: (H, W) bool, the hand model's silhouette; model_depth: (H, W) the rendered
            models' depth (mm, 0 = empty); models: (H, W) bool, every model's silhouette
            (the other hands and objects are not surround).
        measured: (H, W) the depth the frame measured (mm; 0 or NaN = nothing).
        focal: the camera's focal length (px), to turn ``band_mm`` into pixels at the
            hand's depth.
        band_mm: the surround, from this far outside the silhouette (a good fit's few
            pixels of misalignment) to that far.
        tolerance_mm: how far from the depth of the nearest model pixel a measured pixel
            still continues the surface.
    Returns:
        continued pixels / surround pixels (pixels without depth count as not continued:
        a hand before a far background leaves them empty); NaN without the hand.
    """
    own = np.asarray(own, bool)
    if not own.any():
        return float("nan")
    c0, r0, w, h = cv2.boundingRect(np.ascontiguousarray(own).view(np.uint8))
    depth = np.asarray(model_depth, np.float32)
    z = float(np.median(depth[r0:r0 + h, c0:c0 + w][own[r0:r0 + h, c0:c0 + w]]))
    r_in = max(2, int(round(band_mm[0] * focal / z)))
    r_out = max(r_in + 2, int(round(band_mm[1] * focal / z)))
    H, W = own.shape
    m = r_out + r_in + 1  # other models up to r_in beyond the surround count too
    box = (slice(max(0, r0 - m), min(H, r0 + h + m)), slice(max(0, c0 - m), min(W, c0 + w + m)))
    hand = own[box]
    # the distance of every pixel to the hand and the hand pixel it is nearest (labels
    # count the hand's pixels in raster order), and its distance to any model
    dist, nearest = cv2.distanceTransformWithLabels((~hand).astype(np.uint8), cv2.DIST_L2, 5,
                                                    labelType=cv2.DIST_LABEL_PIXEL)
    apart = cv2.distanceTransform((~np.asarray(models, bool)[box]).astype(np.uint8), cv2.DIST_L2, 5)
    ring = (dist > r_in) & (dist <= r_out) & (apart > r_in)
    if not ring.any():
        return float("nan")
    near = depth[box][hand][nearest[ring] - 1]  # the depth of the nearest hand pixel
    d = np.nan_to_num(np.asarray(measured, np.float32)[box][ring], nan=0.0)
    on = (d > 0) & (np.abs(d - near) <= tolerance_mm)
    return float(on.sum()) / float(ring.sum())


def fit_check(model_depth: np.ndarray, data_depth: np.ndarray, hand_mask: Optional[np.ndarray] = None,
              labels: Optional[np.ndarray] = None, model_uv: Optional[np.ndarray] = None,
              located_uv: Optional[np.ndarray] = None, located_confidence: Optional[np.ndarray] = None,
              located_z: Optional[np.ndarray] = None, focal: float = float("nan"),
              limits: FitCheckLimits = FitCheckLimits(), surround: Sequence[float] = ()) -> FitCheck:
    """A fit check that can fail: :func:`fit_quality` against the tracker's own data,
    :func:`surrounded` from the measured depth, and three measures against the hand
    localiser's independent evidence.

    Args:
        model_depth, data_depth: as :func:`fit_quality`.
        hand_mask: (H, W) bool, the localiser's pixels of the hands the scene tracks.
        labels: (H, W) uint8, the localiser's class of every pixel (1, 2: hands; 255:
            nothing measured, so a model pixel there is no evidence either way).
        model_uv, located_uv: (P, 2) the model's projected standard joints and the
            localiser's, in the same order (NaN rows: not compared);
            located_confidence: (P,) the localiser's confidences; located_z: (P,) its
            joints' depth (mm) and ``focal`` the camera's focal length (px), to measure
            the distances in mm.
        surround: the caller's :func:`surrounded` of each hand model (NaN: not in view),
            in the order of the joints' blocks of 21 rows; a hand above the limit is
            vouched for only by its own block's joints.
    """
    iou, residual = fit_quality(model_depth, data_depth)
    shares = np.asarray(surround, np.float64).reshape(-1)
    worst = float(np.nanmax(shares)) if np.isfinite(shares).any() else float("nan")
    on_surface = np.isfinite(shares) & (shares > limits.surrounded)  # per hand
    if hand_mask is None or labels is None:
        return FitCheck(iou, residual, flagged=bool(on_surface.any()), surrounded=worst)
    model = np.asarray(model_depth) > 0
    hand = np.asarray(hand_mask, bool)
    explained = float((model & hand).sum()) / hand.sum() if hand.any() else float("nan")
    any_hand = np.isin(labels, (1, 2)).astype(np.uint8)
    near_hand = cv2.dilate(any_hand, np.ones((7, 7), np.uint8)) > 0
    on_model = model & (np.asarray(labels) != 255)
    off_hand = float((on_model & ~near_hand).sum()) / on_model.sum() if on_model.any() else float("nan")
    kp, kp_mm, mm = float("nan"), float("nan"), None
    if model_uv is not None and located_uv is not None:
        conf = np.ones(len(located_uv)) if located_confidence is None else np.asarray(located_confidence)
        d = np.linalg.norm(np.asarray(model_uv, np.float64) - np.asarray(located_uv, np.float64), axis=-1)
        use = np.isfinite(d) & (conf >= limits.confidence)
        kp = float(np.median(d[use])) if use.any() else float("nan")
        if located_z is not None:
            mm = np.where(use, d * np.asarray(located_z, np.float64) / focal, np.nan)
            kp_mm = float(np.median(mm[use])) if use.any() else float("nan")
    surrounded_alone = any(on and not _vouched(mm, k, limits) for k, on in enumerate(on_surface))
    flagged = bool((np.isfinite(kp_mm) and kp_mm > limits.keypoint_mm) or not hand.any()
                   or (np.isfinite(explained) and explained < limits.explained)
                   or (np.isfinite(off_hand) and off_hand > limits.off_hand) or surrounded_alone)
    return FitCheck(iou, residual, kp, kp_mm, explained, off_hand, flagged, worst)


def _vouched(mm: Optional[np.ndarray], k: int, limits: FitCheckLimits) -> bool:
    """Hand ``k``'s own confident joints (``mm``: each joint's distance in mm, NaN where not
    compared) lie within half the joints' limit of the model's: a grasp or a hand on a
    table may be surrounded, a body is not jointed like a hand."""
    if mm is None or len(mm) < 21 * (k + 1):
        return False
    own = mm[21 * k:21 * k + 21]
    own = own[np.isfinite(own)]
    return len(own) >= limits.vouching_joints and float(np.median(own)) <= limits.keypoint_mm / 2


def keypoint_errors(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Euclidean distances. pred, gt: (..., P, d) -> (..., P)."""
    return np.linalg.norm(np.asarray(pred, np.float64) - np.asarray(gt, np.float64), axis=-1)


def pck_curve(errors: np.ndarray, thresholds: np.ndarray = PCK_THRESHOLDS_MM) -> np.ndarray:
    """Fraction of errors <= each threshold. errors: any shape -> (T,)."""
    e = np.sort(np.asarray(errors, np.float64).ravel())
    if e.size == 0:
        return np.zeros(len(thresholds))
    return np.searchsorted(e, thresholds, side="right") / e.size


def auc(thresholds: np.ndarray, curve: np.ndarray) -> float:
    """Area under a PCK curve, normalised by the threshold range (1 = all within the first)."""
    span = thresholds[-1] - thresholds[0]
    area = np.sum((curve[1:] + curve[:-1]) / 2 * np.diff(thresholds))
    return float(area / span) if span > 0 else float(curve[-1])


class Penetration(NamedTuple):
    """pairs: intersecting triangle pairs between different models; max_depth_mm:
    deepest vertex of one model inside another (0 when none)."""

    pairs: int
    max_depth_mm: float


def penetration(meshes: Sequence[tuple]) -> Penetration:
    """Interpenetration between the meshes of different models of one frame.

    Args:
        meshes: list of (vertices (V, 3) mm, faces (F, 3)) numpy arrays, one per model.
    Returns:
        :class:`Penetration`. The depth is the largest negative signed distance of a
        vertex of one model to another model's surface (open3d; the thesis meshes are
        closed, so inside is well defined). Pairs are counted with
        :func:`torchhand.geometry.intersections.detect_collisions` (the same pairs as python-fcl,
        see tests/test_collision.py).
    """
    import torch

    offsets = np.cumsum([0] + [len(v) for v, _ in meshes])
    vertices = torch.as_tensor(np.concatenate([np.asarray(v, np.float64) for v, _ in meshes]))[None]
    faces = torch.as_tensor(np.concatenate([np.asarray(f, np.int64) + o for (_, f), o in zip(meshes, offsets)]))
    model = torch.cat([torch.full((len(f),), k, dtype=torch.int64) for k, (_, f) in enumerate(meshes)])
    return Penetration(int(model_pair_counts(vertices, faces, model)[0]), max_depth(meshes))


def max_depth(meshes: Sequence[tuple]) -> float:
    """Deepest vertex of one mesh inside another (mm, 0 when none); meshes as in
    :func:`penetration`."""
    import open3d as o3d

    depth = 0.0
    for a, (va, fa) in enumerate(meshes):
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(np.asarray(va, np.float32)), o3d.core.Tensor(np.asarray(fa, np.uint32)))
        lo, hi = va.min(0), va.max(0)
        for b, (vb, _) in enumerate(meshes):
            if a == b:
                continue
            near = np.all((vb >= lo) & (vb <= hi), axis=1)  # only vertices inside a's box can be inside a
            if not near.any():
                continue
            # the sign is a ray-parity test; one ray flips it when it grazes an edge or a
            # vertex (a vertex 19 mm outside was once reported 19 mm deep): 5 rays vote
            sd = scene.compute_signed_distance(o3d.core.Tensor(np.asarray(vb[near], np.float32)),
                                               nsamples=5).numpy()
            depth = max(depth, float(-sd.min()) if sd.min() < 0 else 0.0)
    return depth


def model_pair_counts(vertices, faces, face_model, chunk: int = 16) -> np.ndarray:
    """Intersecting triangle pairs between different models (not within one), per frame.

    vertices: (N, V, 3) tensor, N frames of one scene; faces: (F, 3); face_model: (F,)
    model of each face -> (N,) counts. The hierarchy is built once for all frames.
    """
    import torch

    from torchhand.geometry.intersections import CollisionMesh, detect_collisions

    K = int(face_model.max()) + 1 if len(face_model) else 0
    if K < 2:
        return np.zeros(len(vertices), np.int64)
    mesh = CollisionMesh(faces, face_model, torch.eye(K, dtype=torch.bool), face_model, vertices[0])
    counts = [detect_collisions(vertices[i : i + chunk], mesh).counts(len(vertices[i : i + chunk]))
              for i in range(0, len(vertices), chunk)]
    return torch.cat(counts).cpu().numpy()


def valid_joints(gt: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """(..., P) bool: the joints of ``gt`` (..., P, d) that are present (module docstring),
    and'ed with ``valid`` (..., P) when given."""
    gt = np.asarray(gt, np.float64)
    ok = np.isfinite(gt).all(-1) & ~(gt == -1).all(-1)
    if valid is not None:
        ok &= np.broadcast_to(np.asarray(valid, bool), ok.shape)
    return ok


def joint_errors(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """(..., P) Euclidean distances of pred, gt (..., P, d), NaN where the joint is absent.
    Raises ValueError where a present joint has no finite prediction."""
    ok = valid_joints(gt, valid)
    pred = np.asarray(pred, np.float64)
    if not np.isfinite(pred[ok]).all():
        raise ValueError("pred: a joint present in the ground truth has a non-finite prediction")
    e = np.linalg.norm(pred - np.where(ok[..., None], np.asarray(gt, np.float64), 0.0), axis=-1)
    return np.where(ok, e, np.nan)


def _mean(e: np.ndarray) -> float:
    e = e[~np.isnan(e)]
    return float(e.mean()) if e.size else float("nan")


def per_joint_mean(errors: np.ndarray) -> np.ndarray:
    """(P,) mean of errors (..., P) over everything but the joint axis, absent (NaN) left
    out; NaN for a joint never present."""
    e = np.asarray(errors, np.float64).reshape(-1, np.shape(errors)[-1])
    n = (~np.isnan(e)).sum(0)
    return np.where(n > 0, np.nansum(e, 0) / np.maximum(n, 1), np.nan)


def similarity_align(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """pred (N, P, 3) moved by the similarity (scale, rotation without reflection,
    translation) that best fits its present joints to gt's, per frame (Umeyama 1991).

    Returns (N, P, 3); frames with fewer than 3 present joints are all NaN.
    """
    ok = valid_joints(gt, valid)
    w = ok[..., None].astype(np.float64)  # (N, P, 1)
    x = np.where(ok[..., None], np.asarray(pred, np.float64), 0.0)
    y = np.where(ok[..., None], np.asarray(gt, np.float64), 0.0)
    n = np.maximum(w.sum(1, keepdims=True), 1.0)  # (N, 1, 1)
    mx, my = x.sum(1, keepdims=True) / n, y.sum(1, keepdims=True) / n
    xc, yc = (x - mx) * w, (y - my) * w
    U, S, Vt = np.linalg.svd(np.einsum("npi,npj->nij", yc, xc) / n)  # cov(y, x) = U S Vt
    d = np.ones_like(S)
    d[:, -1] = np.sign(np.linalg.det(U) * np.linalg.det(Vt))  # no reflection
    R = U @ (d[..., None] * Vt)
    var_x = (xc ** 2).sum((1, 2)) / n[:, 0, 0]
    s = (S * d).sum(-1) / np.maximum(var_x, 1e-300)
    aligned = s[:, None, None] * np.einsum("nij,npj->npi", R, np.asarray(pred, np.float64) - mx) + my
    aligned[ok.sum(-1) < 3] = np.nan
    return aligned


def mpjpe(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None = None) -> float:
    """Mean per-joint position error (units of the input) over the present joints of
    pred, gt (..., P, d)."""
    return _mean(joint_errors(pred, gt, valid))


def pa_mpjpe(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None = None) -> float:
    """MPJPE after :func:`similarity_align` per frame; pred, gt (N, P, 3)."""
    return _mean(joint_errors(similarity_align(pred, gt, valid), gt, _aligned(gt, valid)))


def _aligned(gt, valid):
    """Present joints of frames with at least 3 of them (the ones Procrustes can fit)."""
    ok = valid_joints(gt, valid)
    return ok & (ok.sum(-1, keepdims=True) >= 3)


def _root_relative(pred, gt, valid, root: int):
    ok = valid_joints(gt, valid)
    ok = ok & ok[..., root : root + 1]  # a frame without its root is left out
    pred = np.asarray(pred, np.float64)
    gt = np.where(ok[..., None], np.asarray(gt, np.float64), 0.0)
    return pred - pred[..., root : root + 1, :], gt - gt[..., root : root + 1, :], ok


def rr_mpjpe(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None = None, root: int = 0) -> float:
    """MPJPE after moving both root joints (the wrist, joint 0) to the origin; frames whose
    root is absent are left out."""
    return _mean(joint_errors(*_root_relative(pred, gt, valid, root)))


class JointScores(NamedTuple):
    """The 3D joint scores of a set of frames (mm). ``*_mm``: means over present joints;
    ``per_joint_*``: (P,) the same per joint; ``pck``: (T,) the fraction of present joints
    within each of ``thresholds`` (T,) (no alignment); ``auc_0_50``: its area."""

    mpjpe_mm: float
    pa_mpjpe_mm: float
    rr_mpjpe_mm: float
    auc_0_50: float
    thresholds: np.ndarray
    pck: np.ndarray
    per_joint_mm: np.ndarray
    per_joint_pa_mm: np.ndarray
    per_joint_rr_mm: np.ndarray


def joint_scores(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None = None, root: int = 0,
                 thresholds: np.ndarray = PCK_THRESHOLDS_MM) -> JointScores:
    """All 3D joint scores of pred, gt (N, P, 3) mm with ``valid`` (N, P) (module docstring)."""
    e = joint_errors(pred, gt, valid)
    pa = joint_errors(similarity_align(pred, gt, valid), gt, _aligned(gt, valid))
    rr = joint_errors(*_root_relative(pred, gt, valid, root))
    curve = pck_curve(e[~np.isnan(e)], thresholds)
    return JointScores(_mean(e), _mean(pa), _mean(rr), auc(thresholds, curve) if (~np.isnan(e)).any() else float("nan"),
                       thresholds, curve, per_joint_mean(e), per_joint_mean(pa), per_joint_mean(rr))


def mean_px(pred: np.ndarray, gt: np.ndarray, visible: np.ndarray | None = None) -> float:
    """Mean 2D distance (px) of pred, gt (..., P, 2) over the joints present in gt and
    ``visible`` (..., P) (e.g. (N, C, P): per camera; not occluded, inside the image)."""
    return mpjpe(pred, gt, visible)
