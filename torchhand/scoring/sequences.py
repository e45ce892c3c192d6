"""Scoring tracker output against ground truth, for one sequence or many in parallel.

Both sides use the ``gt/`` layout (datasets/README.md): ``theta.npy``,
``keypoints_3d.npy`` (N, C, P, 3), ``keypoints_2d.npy`` (N, C, P, 2), ``meta.json``.

Every model is scored per frame (``models`` in the result), in mm in the world frame:

- hands: the mean 3D error of their keypoints (as the px/mm/AUC figures, which are
  over the hand keypoints of all cameras);
- rigid objects: ADD, the mean distance between corresponding vertices of the two
  posed meshes; for an object whose model declares a symmetry (ball, cube, pipe), the
  score is ADD-S, the mean distance from each true vertex to the nearest tracked one
  (Hinterstoisser et al. 2012), since poses that differ by the symmetry look the same;
- articulated objects (more than one bone): the mean distance between true and tracked
  bone origins (a tube's are on its axis, so its symmetry costs nothing), with the mean
  vertex error beside it.

A frame is *lost* when any model's error exceeds :data:`LOST_MM`.

When both sides hold the standard 21 joints of their hands (``keypoints21_3d.npy``,
``keypoints21_2d.npy``; docs/model.md), they give the result's top-level keys, the
figures papers print: ``mpjpe_mm``, ``pa_mpjpe_mm`` (after a similarity Procrustes per
hand and frame), ``rr_mpjpe_mm`` (wrist-relative), ``auc_0_50`` (PCK over 0-50 mm),
``mean_px`` (2D, over the joints the ground truth has in each camera); the ``joints21``
block repeats them with ``scored_joints``, ``per_camera_px``, ``per_joint``, ``pck`` and
``per_frame_mm`` (each frame's mean 3D error, NaN where it has no joint). Joints absent
from the ground truth (NaN, all -1, or False in its ``keypoints21_valid.npy``) are left
out. 3D errors are taken in camera 0's frame (distances do not depend on the camera).

The thesis keypoints' figures keep their keys (``thesis_mean_px``, ``median_px``,
``mean_mm``, ``median_mm``, ``auc_0_50mm``, ``pck``, ``per_keypoint``, ``per_frame``);
only their mean 2D error was renamed from ``mean_px`` to ``thesis_mean_px`` when the
21 joints took that key.

Ground truth that holds the 21 joints alone (a public dataset's ``gt/``: no ``theta.npy``,
no ``meta.json``) is scored on them alone: the result has the five keys, ``joints21``,
``frames``, ``flagged_frames`` and ``lost_frames`` (frames whose mean 21-joint error
exceeds :data:`LOST_MM`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Dict, List, Sequence, Tuple

import numpy as np

from torchhand.core.errors import UsageError
from torchhand.data.layout import (OutputLayout, Poses, PosesLayout, SequenceError, SequenceLayout, read_joints21,
                                   read_joints21_valid, read_poses)
from torchhand.model.joints21 import STANDARD_JOINT_NAMES
from torchhand.scoring.metrics import (PCK_THRESHOLDS_MM, auc, joint_errors, joint_scores, keypoint_errors, max_depth,
                                       mean_px, model_pair_counts, pck_curve, per_joint_mean,
                                       valid_joints)

__all__ = ["EvaluationError", "evaluate_sequence", "evaluate_many", "summarize", "model_errors", "fit_report",
           "LOST_MM", "GOOD_IOU", "JOINT_KEYS"]

#: a frame whose fitted models overlap their data with a silhouette IoU below this is
#: counted as poorly fitted by :func:`fit_report`
GOOD_IOU = 0.8

#: mm, a frame in which some model is farther off than this is lost
LOST_MM = 20.0


class EvaluationError(UsageError):
    """Prediction and ground truth cannot be compared; the message says why (a
    ``ValueError``)."""


#: the five 21-joint figures, top-level keys of every result that has them
JOINT_KEYS = ("mpjpe_mm", "pa_mpjpe_mm", "rr_mpjpe_mm", "auc_0_50", "mean_px")


def _has_poses(folder: Path) -> bool:
    f = PosesLayout(folder)
    return f.meta.is_file() or f.keypoints21_3d.is_file()


def _resolve(folder) -> Path:
    """Accept a gt/-layout folder or a sequence folder holding gt/."""
    folder = Path(folder)
    gt = SequenceLayout(folder).gt
    if not _has_poses(folder) and _has_poses(gt.root):
        return gt.root
    return folder


def _check_pair(pred: Poses, gt: Poses, pred_dir: Path, gt_dir: Path) -> None:
    if len(pred.theta) != len(gt.theta):
        raise EvaluationError(f"{pred_dir} has {len(pred.theta)} frames but {gt_dir} has {len(gt.theta)}")
    if list(pred.models) != list(gt.models):
        raise EvaluationError(f"{pred_dir} holds the models {list(pred.models)} but {gt_dir} {list(gt.models)}")
    if pred.theta.shape != gt.theta.shape:
        raise EvaluationError(f"{pred_dir / 'theta.npy'} is {pred.theta.shape} but {gt_dir / 'theta.npy'} "
                              f"{gt.theta.shape}")
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

    Returns a JSON-ready dict with ``frames``, the thesis keypoints' ``thesis_mean_px``,
    ``median_px``, ``mean_mm``, ``median_mm``, ``auc_0_50mm``, ``pck`` (thresholds and
    fractions), ``per_keypoint`` and ``per_frame`` errors, ``penetration`` when the scene
    has several models (mean intersecting triangle pairs per frame, max depth in mm), and
    the 21 joints' :data:`JOINT_KEYS` and ``joints21`` when both sides have them. Ground
    truth of 21 joints alone is scored on them alone (module docstring).
    """
    pred_dir, gt_dir = _resolve(pred_dir), _resolve(gt_dir)
    if not PosesLayout(gt_dir).meta.is_file() and PosesLayout(gt_dir).keypoints21_3d.is_file():
        return _evaluate_joints_only(pred_dir, gt_dir)
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
        per_frame={"px": _frame_means(e2), "mm": _frame_means(e3)},  # NaN for a scene without keypoints
        flagged_frames=int((~np.asarray(pred.valid, bool)).sum()),
    )
    per_model = model_errors(pred, gt)
    result["models"] = {name: _model_summary(m) for name, m in per_model.items()}
    lost = np.zeros(len(gt.theta), bool)
    for m in per_model.values():
        lost |= m["per_frame"] > LOST_MM
    result["lost_frames"] = int(lost.sum())
    result["lost_frame_ids"] = np.nonzero(lost)[0].tolist()
    if with_penetration and len(gt.models) > 1:
        result["penetration"] = _penetration(pred)
    joints21 = _joints21(pred_dir, gt_dir)
    if joints21 is not None:
        result.update({k: joints21[k] for k in JOINT_KEYS}, joints21=joints21)
    return result


def _evaluate_joints_only(pred_dir: Path, gt_dir: Path) -> Dict:
    """Score a prediction against ground truth that holds the 21 joints alone (module docstring)."""
    joints21 = _joints21(pred_dir, gt_dir)
    if joints21 is None:
        raise EvaluationError(f"{gt_dir} holds the standard 21 joints only, but {pred_dir} has none "
                              f"(keypoints21_3d.npy and keypoints21_2d.npy, which torchhand track writes for hands)")
    try:
        flagged = int((~np.asarray(json.loads(PosesLayout(pred_dir).meta.read_text()).get("valid", []), bool)).sum())
    except (OSError, ValueError):
        flagged = 0
    per_frame = np.asarray(joints21["per_frame_mm"], float)
    lost = np.nan_to_num(per_frame, nan=0.0) > LOST_MM
    return {"frames": len(per_frame), "sequence": gt_dir.parent.name if gt_dir.name == "gt" else gt_dir.name,
            "prediction": str(pred_dir), "ground_truth": "the standard 21 joints only",
            **{k: joints21[k] for k in JOINT_KEYS}, "joints21": joints21, "flagged_frames": flagged,
            "lost_frames": int(lost.sum()), "lost_frame_ids": np.nonzero(lost)[0].tolist()}


def _read_joints21(pred_dir: Path, gt_dir: Path):
    """((pred 3D, 2D), (gt 3D, 2D), gt validity (N, P) or None), or None when a side has no 21 joints."""
    try:
        pred, gt = read_joints21(pred_dir), read_joints21(gt_dir)
        valid = read_joints21_valid(gt_dir) if gt is not None else None
    except SequenceError as err:
        raise EvaluationError(str(err)) from None
    if pred is None or gt is None:
        return None
    if pred[0].shape != gt[0].shape or pred[1].shape != gt[1].shape:
        raise EvaluationError(f"21-joint arrays of {pred_dir} {pred[0].shape} do not match {gt_dir} {gt[0].shape} "
                              "(frames, cameras, joints)")
    if valid is not None and valid.shape != (gt[0].shape[0], gt[0].shape[2]):
        raise EvaluationError(f"{PosesLayout(gt_dir).keypoints21_valid}: {valid.shape}, expected (N, 21 x hands) "
                              f"{(gt[0].shape[0], gt[0].shape[2])}")
    return pred, gt, valid


def _joints21(pred_dir: Path, gt_dir: Path):
    """The ``joints21`` block of the module docstring, or None when a side has no 21 joints."""
    read = _read_joints21(pred_dir, gt_dir)
    if read is None:
        return None
    pred, gt, valid = read
    N, C, P, _ = gt[0].shape
    ok3 = valid_joints(gt[0][:, 0], valid)  # (N, P) present in 3D
    ok2 = valid_joints(gt[1], None if valid is None else valid[:, None])  # (N, C, P) present in each camera
    hands = lambda a: a.reshape(N * (P // 21), 21, a.shape[-1])  # noqa: E731  one row per hand and frame
    try:
        s = joint_scores(hands(pred[0][:, 0]), hands(gt[0][:, 0]), hands(ok3[..., None])[..., 0])
        e3 = joint_errors(pred[0][:, 0], gt[0][:, 0], ok3)  # (N, P) mm
        e2 = joint_errors(pred[1], gt[1], ok2)  # (N, C, P) px, NaN where the ground truth has no joint
    except ValueError as err:
        raise EvaluationError(f"{pred_dir}: 21 joints: {err}") from None
    per_joint = zip(STANDARD_JOINT_NAMES, s.per_joint_mm, s.per_joint_pa_mm, s.per_joint_rr_mm)
    per_frame = [float(np.nanmean(row)) if np.isfinite(row).any() else float("nan") for row in e3]
    return {"mpjpe_mm": s.mpjpe_mm, "pa_mpjpe_mm": s.pa_mpjpe_mm, "rr_mpjpe_mm": s.rr_mpjpe_mm,
            "auc_0_50": s.auc_0_50, "mean_px": mean_px(pred[1], gt[1], ok2),
            "scored_joints": int(ok3.sum()), "scored_px": int((~np.isnan(e2)).sum()),
            "per_camera_px": per_joint_mean(np.moveaxis(e2, 1, -1)).tolist(),
            "per_joint": {n: {"mm": float(a), "pa_mm": float(b), "rr_mm": float(c)} for n, a, b, c in per_joint},
            "pck": {"thresholds_mm": s.thresholds.tolist(), "fraction": s.pck.tolist()},
            "per_frame_mm": per_frame}


def _frame_means(e: np.ndarray) -> list:
    if len(e) == 0 or e[0].size == 0:
        return [float("nan")] * len(e)
    return e.mean(axis=(1, 2)).tolist()


def model_errors(pred: Poses, gt: Poses, chunk: int = 32) -> Dict[str, Dict]:
    """Per model and frame, the error of :mod:`this module's docstring <torchhand.scoring.sequences>`.

    Returns ``{name: {"kind", "metric", "per_frame" (N,) mm, and extra (N,) arrays:
    "add" / "add_s" for rigid objects, "bone_origins" / "vertices" for articulated
    ones}}``.
    """
    import torch
    from scipy.spatial import cKDTree

    from torchhand.model.scene import Scene

    scene = Scene.from_names(gt.models, dtype=torch.float64)
    N = len(gt.theta)
    out: Dict[str, Dict] = {}
    hands = [k for k, m in enumerate(scene.models) if m.kind == "hand"]
    for k in hands:
        name = scene.names[k]
        cols = [i for i, n in enumerate(gt.keypoint_names) if n.startswith(name + "/")]
        e = keypoint_errors(pred.keypoints_3d[:, :, cols], gt.keypoints_3d[:, :, cols])  # (N, C, P)
        out[name] = {"kind": "hand", "metric": "keypoints", "per_frame": e.reshape(N, -1).mean(1)}
    objects = [k for k in range(len(scene.models)) if k not in hands]
    if not objects:
        return out
    rows = {scene.names[k]: {"a": [], "b": []} for k in objects}
    with torch.no_grad():
        for i in range(0, N, chunk):
            th_p = torch.as_tensor(pred.theta[i : i + chunk], dtype=torch.float64)
            th_g = torch.as_tensor(gt.theta[i : i + chunk], dtype=torch.float64)
            sp, sg = scene(th_p), scene(th_g)
            for k in objects:
                model, name = scene.models[k], scene.names[k]
                Vp, Vg = sp.models[k].vertices, sg.models[k].vertices
                vert = (Vp - Vg).norm(dim=-1).mean(1).numpy()
                if model.num_bones > 1:
                    bones = (model.joints_from(sp.models[k].G) - model.joints_from(sg.models[k].G)).norm(dim=-1)
                    rows[name]["a"].append(bones.mean(1).numpy())
                    rows[name]["b"].append(vert)
                else:
                    rows[name]["a"].append(vert)
                    if model.symmetry is not None:  # ADD-S: true vertices to the nearest tracked one
                        rows[name]["b"].append(np.array([cKDTree(p.numpy()).query(g.numpy())[0].mean()
                                                         for p, g in zip(Vp, Vg)]))
    for k in objects:
        model, name = scene.models[k], scene.names[k]
        a = np.concatenate(rows[name]["a"])
        b = np.concatenate(rows[name]["b"]) if rows[name]["b"] else None
        if model.num_bones > 1:
            out[name] = {"kind": "articulated", "metric": "bone origins", "per_frame": a, "bone_origins": a,
                         "vertices": b}
        elif b is not None:
            out[name] = {"kind": "rigid", "metric": f"ADD-S ({model.symmetry})", "per_frame": b, "add": a, "add_s": b}
        else:
            out[name] = {"kind": "rigid", "metric": "ADD", "per_frame": a, "add": a}
    return out


def _model_summary(m: Dict) -> Dict:
    e = m["per_frame"]
    summary = {"kind": m["kind"], "metric": m["metric"], "mean_mm": float(e.mean()), "median_mm": float(np.median(e)),
               "worst_frame_mm": float(e.max()), "worst_frame": int(e.argmax()),
               "frames_over_20mm": int((e > LOST_MM).sum()), "per_frame_mm": e.tolist()}
    for key in ("add", "add_s", "vertices"):
        if m.get(key) is not None:
            summary[f"{key}_mean_mm"] = float(np.mean(m[key]))
    return summary


def _scores(e2: np.ndarray, e3: np.ndarray) -> Dict:
    curve = pck_curve(e3, PCK_THRESHOLDS_MM)
    return {
        "frames": int(e2.shape[0]),
        "thesis_mean_px": float(e2.mean()) if e2.size else float("nan"),
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


def evaluate_many(pairs: Sequence[Tuple[Path, Path]], with_penetration: bool = True, progress: bool = True) -> Dict:
    """Score several (prediction, ground truth) pairs in this process (over processes
    or a Ray cluster: :func:`torchhand.app.scaleout.evaluate_pairs`).

    Returns ``{"sequences": [per-sequence dicts], ...overall scores}`` where the
    overall scores pool all keypoints of all frames of all sequences.
    """
    from tqdm import tqdm

    return summarize([evaluate_sequence(Path(p), Path(g), with_penetration)
                      for p, g in tqdm(pairs, desc="eval", unit="seq", disable=not progress)])


def summarize(results: List[Dict]) -> Dict:
    """Pool per-sequence results over all keypoints of all frames: means and the AUC
    are weighted by each sequence's number of keypoint errors (exact pooling, since
    both are linear in the errors' distribution); medians are taken over the
    per-frame mean errors. The thesis keypoints' figures pool the results that have
    them; the 21 joints' (:data:`JOINT_KEYS`, top level and ``joints21``) are given when
    every result has them."""
    if len(results) == 1:
        return results[0]
    pooled = {"frames": sum(r["frames"] for r in results)}
    thesis = [r for r in results if "keypoint_errors" in r]
    if thesis:
        pooled.update(_pool_thesis(thesis))
    pooled["lost_frames"] = sum(r["lost_frames"] for r in results)
    if all("joints21" in r for r in results):
        pooled["joints21"] = _pool_joints21([r["joints21"] for r in results])
        pooled.update({k: pooled["joints21"][k] for k in JOINT_KEYS})
    pooled["note"] = "median_px/median_mm pooled over per-frame mean errors of all sequences"
    pooled["sequences"] = results
    return pooled


def _pool_thesis(results: List[Dict]) -> Dict:
    """The thesis keypoints' figures and every model's of several sequences."""
    w = np.array([r["keypoint_errors"] for r in results], float)
    pooled = {
        "thesis_mean_px": float(np.average([r["thesis_mean_px"] for r in results], weights=w)),
        "mean_mm": float(np.average([r["mean_mm"] for r in results], weights=w)),
        "median_px": float(np.median(np.concatenate([r["per_frame"]["px"] for r in results]))),
        "median_mm": float(np.median(np.concatenate([r["per_frame"]["mm"] for r in results]))),
        "auc_0_50mm": float(np.average([r["auc_0_50mm"] for r in results], weights=w)),
        "keypoint_errors": int(w.sum()),
    }
    models: Dict[str, Dict] = {}
    for r in results:
        for name, m in r["models"].items():
            models.setdefault(name, {"metric": m["metric"], "per_frame_mm": []})["per_frame_mm"] += m["per_frame_mm"]
    pooled["models"] = {}
    for name, m in models.items():
        e = np.asarray(m["per_frame_mm"])
        pooled["models"][name] = {"metric": m["metric"], "mean_mm": float(e.mean()), "median_mm": float(np.median(e)),
                                  "worst_frame_mm": float(e.max()), "frames_over_20mm": int((e > LOST_MM).sum()),
                                  "frames": int(len(e))}
    return pooled


def _pool_joints21(blocks: List[Dict]) -> Dict:
    """The five 21-joint means of several sequences, weighted by their scored joints
    (the 2D mean by the scored 2D joints)."""
    pooled = {"scored_joints": int(sum(b["scored_joints"] for b in blocks)),
              "scored_px": int(sum(b.get("scored_px", b["scored_joints"]) for b in blocks))}
    for key in JOINT_KEYS:
        w = np.array([b.get("scored_px", b["scored_joints"]) if key == "mean_px" else b["scored_joints"]
                      for b in blocks], float)
        v = np.array([b[key] for b in blocks], float)
        ok = np.isfinite(v) & (w > 0)
        pooled[key] = float(np.average(v[ok], weights=w[ok])) if ok.any() else float("nan")
    return pooled


def fit_report(pred_dirs: Sequence) -> Dict:
    """The fit quality of tracked sequences without ground truth, from each output's
    ``track_log.json`` (the silhouette IoU of the fitted models and the data, and the
    median depth residual on their overlap, per frame; :func:`torchhand.scoring.
    metrics.fit_quality`). Returns ``{"sequences": [...], "frames", "mean_iou",
    "min_iou", "median_depth_residual_mm", "frames_below_iou", "iou_threshold"}``,
    per sequence the same plus ``worst_frame``, ``reinitialized_frames``,
    ``flagged_frames`` and ``fit_flagged_frames`` (frames whose fit check against the hand
    localiser failed, docs/localiser.md); ``fit_flagged_frames`` overall too."""
    rows = []
    for d in pred_dirs:
        path = OutputLayout(d).track_log
        try:
            log = json.loads(path.read_text())
            frames = log["frames"]
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise EvaluationError(f"{path}: cannot read the track log ({err}); without --gt, eval reads the fit "
                                  "quality that torchhand track writes there") from None
        iou = np.array([np.nan if f.get("iou") is None else f["iou"] for f in frames], float)
        res = np.array([np.nan if f.get("depth_residual_mm") is None else f["depth_residual_mm"] for f in frames],
                       float)
        ok = np.isfinite(iou)
        rows.append({"sequence": log.get("sequence", Path(d).name), "frames": len(frames),
                     "scored_frames": int(ok.sum()),
                     "mean_iou": float(np.mean(iou[ok])) if ok.any() else float("nan"),
                     "min_iou": float(np.min(iou[ok])) if ok.any() else float("nan"),
                     "worst_frame": int(np.nanargmin(iou)) if ok.any() else None,
                     "median_depth_residual_mm": float(np.nanmedian(res)) if np.isfinite(res).any() else float("nan"),
                     "frames_below_iou": int((iou[ok] < GOOD_IOU).sum()),
                     "reinitialized_frames": int(sum(bool(f.get("reinitialized")) for f in frames)),
                     "flagged_frames": int(sum(not f.get("valid", True) for f in frames)),
                     "fit_flagged_frames": int(sum(bool(f.get("fit_flagged")) for f in frames)),
                     "per_frame": [{"frame": k, "iou": None if not ok[k] else float(iou[k]),
                                    "depth_residual_mm": None if not np.isfinite(res[k]) else float(res[k]),
                                    "keypoint_px": frames[k].get("keypoint_px"),
                                    "fit_flagged": bool(frames[k].get("fit_flagged"))}
                                   for k in range(len(frames))]})
    all_iou = np.concatenate([[f["iou"] for f in r["per_frame"] if f["iou"] is not None] for r in rows] or [[]])
    all_res = np.concatenate([[f["depth_residual_mm"] for f in r["per_frame"] if f["depth_residual_mm"] is not None]
                              for r in rows] or [[]])
    return {"sequences": rows, "frames": int(sum(r["frames"] for r in rows)), "iou_threshold": GOOD_IOU,
            "mean_iou": float(np.mean(all_iou)) if all_iou.size else float("nan"),
            "min_iou": float(np.min(all_iou)) if all_iou.size else float("nan"),
            "median_depth_residual_mm": float(np.median(all_res)) if all_res.size else float("nan"),
            "fit_flagged_frames": int(sum(r["fit_flagged_frames"] for r in rows)),
            "frames_below_iou": int(sum(r["frames_below_iou"] for r in rows))}
