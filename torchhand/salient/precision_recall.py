"""Precision-recall and average precision of point detections (PASCAL VOC protocol).

Detections of all frames are sorted by decreasing confidence. Going down that list, a
detection is a true positive if it lies within ``radius`` px of a ground-truth point
of its frame that no earlier (more confident) detection has matched; it then matches
the nearest such point. A detection that matches no free point but lies within
``radius`` of an *ignored* ("difficult") point is skipped (neither true nor false
positive, as VOC does for difficult objects); any other detection is a false positive.

AP is the area under the interpolated precision-recall curve, all-points
interpolation (VOC 2010 onwards): precision at recall r is the maximum precision at any
recall >= r, integrated exactly over the recall steps.
"""

from __future__ import annotations

from typing import NamedTuple, Optional, Sequence

import numpy as np

__all__ = ["PRCurve", "match_detections", "average_precision"]


class PRCurve(NamedTuple):
    """Result of :func:`average_precision`.

    Attributes:
        ap: area under the interpolated precision-recall curve, in [0, 1].
        precision: (K,) precision after each of the K counted detections (sorted).
        recall: (K,) recall after each counted detection.
        scores: (K,) confidence of each counted detection.
        num_gt: number of (non-ignored) ground-truth points.
    """

    ap: float
    precision: np.ndarray
    recall: np.ndarray
    scores: np.ndarray
    num_gt: int


def match_detections(det_uv: np.ndarray, gt_uv: np.ndarray, radius: float, taken: np.ndarray) -> int:
    """Index of the nearest free ground-truth point within ``radius`` of one detection, or -1.

    Args:
        det_uv: (2,) detection pixel coordinates.
        gt_uv: (G, 2) ground-truth pixel coordinates.
        radius: match radius (px).
        taken: (G,) bool, points already matched (not modified).
    """
    if len(gt_uv) == 0:
        return -1
    d = np.linalg.norm(gt_uv - det_uv[None], axis=1)
    d = np.where(taken, np.inf, d)
    k = int(np.argmin(d))
    return k if d[k] <= radius else -1


def average_precision(
    det_uv: Sequence[np.ndarray],
    det_score: Sequence[np.ndarray],
    gt_uv: Sequence[np.ndarray],
    radius: float = 10.0,
    gt_ignore: Optional[Sequence[np.ndarray]] = None,
) -> PRCurve:
    """VOC average precision of point detections over a set of frames.

    Args:
        det_uv: per frame, (N_f, 2) detected pixel coordinates.
        det_score: per frame, (N_f,) confidences.
        gt_uv: per frame, (G_f, 2) ground-truth pixel coordinates.
        radius: a detection within this distance (px) of a free ground-truth point is
            a true positive.
        gt_ignore: per frame, (I_f, 2) points that may be detected but need not be
            (e.g. barely visible fingertips); detections near them are not counted.

    Returns:
        :class:`PRCurve`. With no ground truth at all, AP is 0 (and 1 if there are also
        no counted detections, by convention).
    """
    if not (len(det_uv) == len(det_score) == len(gt_uv)):
        raise ValueError(f"det_uv, det_score and gt_uv must list the same frames, got "
                         f"{len(det_uv)}, {len(det_score)}, {len(gt_uv)}")
    if gt_ignore is not None and len(gt_ignore) != len(gt_uv):
        raise ValueError(f"gt_ignore must list the same frames as gt_uv, got {len(gt_ignore)} vs {len(gt_uv)}")
    frames, uvs, scores = [], [], []
    for f, (u, s) in enumerate(zip(det_uv, det_score)):
        u = np.asarray(u, np.float64).reshape(-1, 2)
        s = np.asarray(s, np.float64).reshape(-1)
        if len(u) != len(s):
            raise ValueError(f"frame {f}: {len(u)} detections but {len(s)} scores")
        frames.append(np.full(len(s), f))
        uvs.append(u)
        scores.append(s)
    frames = np.concatenate(frames) if frames else np.zeros(0, int)
    uvs = np.concatenate(uvs) if uvs else np.zeros((0, 2))
    scores = np.concatenate(scores) if scores else np.zeros(0)
    gts = [np.asarray(g, np.float64).reshape(-1, 2) for g in gt_uv]
    ign = [np.asarray(g, np.float64).reshape(-1, 2) for g in gt_ignore] if gt_ignore is not None else None
    num_gt = int(sum(len(g) for g in gts))
    taken = [np.zeros(len(g), bool) for g in gts]

    order = np.argsort(-scores, kind="stable")
    tp, counted = [], []
    for i in order:
        f = frames[i]
        k = match_detections(uvs[i], gts[f], radius, taken[f])
        if k >= 0:
            taken[f][k] = True
            tp.append(True)
            counted.append(i)
        elif ign is not None and len(ign[f]) and np.linalg.norm(ign[f] - uvs[i][None], axis=1).min() <= radius:
            continue  # near an ignored point: not counted
        else:
            tp.append(False)
            counted.append(i)
    tp = np.asarray(tp, bool)
    ctp = np.cumsum(tp)
    precision = ctp / np.maximum(np.arange(1, len(tp) + 1), 1)
    recall = ctp / num_gt if num_gt > 0 else np.zeros(len(tp))
    if num_gt == 0:
        ap = 1.0 if len(tp) == 0 else 0.0
    else:
        # All-points interpolation (VOC): make precision monotone from the right, then
        # sum precision over the recall steps.
        mrec = np.concatenate([[0.0], recall, [1.0]])
        mpre = np.concatenate([[0.0], precision, [0.0]])
        mpre = np.maximum.accumulate(mpre[::-1])[::-1]
        step = np.nonzero(mrec[1:] != mrec[:-1])[0]
        ap = float(np.sum((mrec[step + 1] - mrec[step]) * mpre[step + 1]))
    return PRCurve(ap, precision, recall, scores[np.asarray(counted, int)], num_gt)
