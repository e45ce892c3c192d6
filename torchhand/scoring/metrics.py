"""Error measures: keypoint errors in px and mm, PCK curves and their AUC, and
interpenetration of posed meshes.

The 2D measure is the thesis' (Table 4.6): the mean Euclidean distance in pixels
between projected keypoints and ground truth. The 3D measure is the same in mm in
the camera frame. The curve is the fraction of keypoints within a 3D threshold.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

__all__ = ["keypoint_errors", "pck_curve", "auc", "Penetration", "penetration", "max_depth", "model_pair_counts",
           "PCK_THRESHOLDS_MM", "fit_quality"]

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
