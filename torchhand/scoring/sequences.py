"""Scoring tracker output against ground truth, for one sequence or many in parallel.

Both sides use the ``gt/`` layout (datasets/README.md): ``theta.npy``,
``keypoints_3d.npy`` (N, C, P, 3), ``keypoints_2d.npy`` (N, C, P, 2), ``meta.json``.
"""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Dict, List, Sequence, Tuple

import numpy as np

from torchhand.data.layout import Poses, SequenceError, read_poses
from torchhand.scoring.metrics import PCK_THRESHOLDS_MM, auc, keypoint_errors, max_depth, model_pair_counts, pck_curve

__all__ = ["EvaluationError", "evaluate_sequence", "evaluate_many", "summarize"]


class EvaluationError(ValueError):
    """Prediction and ground truth cannot be compared; the message says why."""


def _resolve(folder) -> Path:
    """Accept a gt/-layout folder or a sequence folder holding gt/."""
    folder = Path(folder)
    if not (folder / "meta.json").is_file() and (folder / "gt" / "meta.json").is_file():
        return folder / "gt"
    return folder


def _check_pair(pred: Poses, gt: Poses, pred_dir: Path, gt_dir: Path) -> None:
    if len(pred.theta) != len(gt.theta):
        raise EvaluationError(f"{pred_dir} has {len(pred.theta)} frames but {gt_dir} has {len(gt.theta)}")
    if pred.keypoint_names != gt.keypoint_names:
        raise EvaluationError(f"keypoint names of {pred_dir} differ from {gt_dir}")
    if pred.keypoints_3d.shape != gt.keypoints_3d.shape or pred.keypoints_2d.shape != gt.keypoints_2d.shape:
        raise EvaluationError(f"keypoint arrays of {pred_dir} {pred.keypoints_3d.shape} do not match "
                              f"{gt_dir} {gt.keypoints_3d.shape}")
    for name, arr in (("keypoints_3d", pred.keypoints_3d), ("keypoints_2d", pred.keypoints_2d), ("theta", pred.theta)):
        bad = ~np.isfinite(arr).reshape(len(arr), -1).all(1)
        if bad.any():
            raise EvaluationError(f"{pred_dir / (name + '.npy')}: NaN or inf in frames {np.nonzero(bad)[0][:10].tolist()}")


def evaluate_sequence(pred_dir, gt_dir, with_penetration: bool = True) -> Dict:
    """Score one prediction folder against one ground-truth folder.

    Returns a JSON-ready dict with ``frames``, ``mean_px``, ``median_px``,
    ``mean_mm``, ``median_mm``, ``auc_0_50mm``, ``pck`` (thresholds and fractions),
    ``per_keypoint`` and ``per_frame`` errors, and ``penetration`` when the scene has
    several models (mean intersecting triangle pairs per frame, max depth in mm).
    """
    pred_dir, gt_dir = _resolve(pred_dir), _resolve(gt_dir)
    try:
        pred, gt = read_poses(pred_dir), read_poses(gt_dir)
    except SequenceError as err:
        raise EvaluationError(str(err)) from None
    _check_pair(pred, gt, pred_dir, gt_dir)
    e2 = keypoint_errors(pred.keypoints_2d, gt.keypoints_2d)  # (N, C, P)
    e3 = keypoint_errors(pred.keypoints_3d, gt.keypoints_3d)
    result = _scores(e2, e3)
    result.update(
        keypoint_errors=int(e2.size),
        sequence=gt_dir.parent.name if gt_dir.name == "gt" else gt_dir.name,
        prediction=str(pred_dir),
        per_keypoint={n: {"px": float(e2[..., p].mean()), "mm": float(e3[..., p].mean())}
                      for p, n in enumerate(gt.keypoint_names)},
        per_frame={"px": e2.mean(axis=(1, 2)).tolist(), "mm": e3.mean(axis=(1, 2)).tolist()},
        flagged_frames=int((~np.asarray(pred.valid, bool)).sum()),
    )
    if with_penetration and len(gt.models) > 1:
        result["penetration"] = _penetration(pred)
    return result


def _scores(e2: np.ndarray, e3: np.ndarray) -> Dict:
    curve = pck_curve(e3, PCK_THRESHOLDS_MM)
    return {
        "frames": int(e2.shape[0]),
        "mean_px": float(e2.mean()) if e2.size else float("nan"),
        "median_px": float(np.median(e2)) if e2.size else float("nan"),
        "mean_mm": float(e3.mean()) if e3.size else float("nan"),
        "median_mm": float(np.median(e3)) if e3.size else float("nan"),
        "auc_0_50mm": auc(PCK_THRESHOLDS_MM, curve),
        "pck": {"thresholds_mm": PCK_THRESHOLDS_MM.tolist(), "fraction": curve.tolist()},
    }


def _penetration(poses: Poses) -> Dict:
    import torch

    from torchhand.model.scene import Scene

    scene = Scene.from_names(poses.models, dtype=torch.float64)
    with torch.no_grad():
        out = scene(torch.as_tensor(poses.theta, dtype=torch.float64))
    faces = [m.faces.numpy() for m in scene.models]
    pairs = model_pair_counts(out.vertices, scene.faces, scene.face_model_id)
    depth = max(max_depth([(o.vertices[k].numpy(), f) for o, f in zip(out.models, faces)])
                for k in range(len(poses.theta)))
    return {"pairs_per_frame": float(np.mean(pairs)), "max_pairs": int(max(pairs)), "max_depth_mm": depth}


def _evaluate_star(args):
    return evaluate_sequence(*args)


def evaluate_many(pairs: Sequence[Tuple[Path, Path]], workers: int = 1, with_penetration: bool = True,
                  progress: bool = True) -> Dict:
    """Score several (prediction, ground truth) pairs, in parallel processes.

    Returns ``{"sequences": [per-sequence dicts], ...overall scores}`` where the
    overall scores pool all keypoints of all frames of all sequences.
    """
    from tqdm import tqdm

    jobs = [(Path(p), Path(g), with_penetration) for p, g in pairs]
    if workers > 1 and len(jobs) > 1:
        with ProcessPoolExecutor(max_workers=workers) as ex:
            results = list(tqdm(ex.map(_evaluate_star, jobs), total=len(jobs), desc="eval", unit="seq",
                                disable=not progress))
    else:
        results = [evaluate_sequence(*j) for j in tqdm(jobs, desc="eval", unit="seq", disable=not progress)]
    return summarize(results)


def summarize(results: List[Dict]) -> Dict:
    """Pool per-sequence results over all keypoints of all frames: means and the AUC
    are weighted by each sequence's number of keypoint errors (exact pooling, since
    both are linear in the errors' distribution); medians are taken over the
    per-frame mean errors."""
    frames = sum(r["frames"] for r in results)
    w = np.array([r["keypoint_errors"] for r in results], float)
    pooled = {
        "frames": frames,
        "mean_px": float(np.average([r["mean_px"] for r in results], weights=w)),
        "mean_mm": float(np.average([r["mean_mm"] for r in results], weights=w)),
        "median_px": float(np.median(np.concatenate([r["per_frame"]["px"] for r in results]))),
        "median_mm": float(np.median(np.concatenate([r["per_frame"]["mm"] for r in results]))),
        "auc_0_50mm": float(np.average([r["auc_0_50mm"] for r in results], weights=w)),
        "keypoint_errors": int(w.sum()),
    }
    if len(results) == 1:
        return results[0]
    pooled["note"] = "median_px/median_mm pooled over per-frame mean errors of all sequences"
    pooled["sequences"] = results
    return pooled
