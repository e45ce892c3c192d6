"""What the runner writes for a tracked sequence (:class:`~torchhand.data.layout.OutputLayout`):
theta, keypoints and the hands' standard 21 joints in the ``gt/`` layout, the thesis'
MOTION files, ``track_log.json``, and on request renders, vertices and overlays for a
person; into a hidden partial folder renamed when complete (:mod:`torchhand.io.output_dir`)."""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, List, Optional

import cv2
import numpy as np
import torch

from torchhand.app.drawing import (GT_COLOR, OBJECT_COLOR, depth_range, depth_to_color, draw_colorbar, draw_legend,
                                   draw_mask_outline, draw_models, mosaic, write_video)
from torchhand.app.options import TrackOptions
from torchhand.data.layout import (OutputLayout, Poses, SequenceError, SequenceInfo, SequenceLayout, read_depth,
                                   read_poses, read_rgb, write_depth, write_joints21, write_poses)
from torchhand.io.assets import THESIS_MODEL_NAMES
from torchhand.io.output_dir import commit_dir, partial_dir
from torchhand.io.thesis import write_motion
from torchhand.model.joints21 import scene_standard_joints
from torchhand.model.motion import theta_to_motion
from torchhand.model.scene import Scene, SceneOutput
from torchhand.tracking.tracker import FrameResult

__all__ = ["TrackedSequence", "write_sequence", "write_view_overlays", "failed"]


@dataclass(frozen=True)
class TrackedSequence:
    """One sequence of a tracked batch, as it is written.

    index: its problem in the batch (of ``batch`` problems); results: the batch's frame
    results (at least ``info.frames``); rig: the cameras tracked (keypoints are written
    in each, renders and vertices in camera 0's); quality: per frame (silhouette IoU,
    median depth residual mm), NaN where not measured; reinitialized: per frame;
    masks: ``masks(f, shape)``, the frame's (hands' mask, forearm cut) or None;
    depth_read: the run read the depth frames (its energy has depth terms).
    """

    name: str
    root: Path
    info: SequenceInfo
    rig: list
    index: int
    batch: int
    results: List[FrameResult]
    quality: List[tuple]
    reinitialized: List[bool]
    masks: Callable[[int, tuple], Optional[tuple]]
    depth_read: bool


def failed(name: str, error: str) -> dict:
    """The summary of a sequence for which nothing was written."""
    return {"sequence": name, "status": "failed", "error": error, "frames": 0, "out": None,
            "seconds_per_frame": float("nan"), "flagged_frames": 0, "reinitialized_frames": 0, "fit_flagged_frames": 0}


def write_sequence(final: Path, *, seq: TrackedSequence, scene: Scene, renderer, options: TrackOptions,
                   settings: dict, force: bool) -> dict:
    """Write one sequence's outputs into a partial folder renamed to ``final`` when
    complete; returns its summary (:func:`~torchhand.app.runner.track_sequences`)."""
    N, i, cam = seq.info.frames, seq.index, seq.rig[0]
    valid = np.array([r.valid[i].item() for r in seq.results[:N]], bool)
    if not valid.any():
        first = next((r.notes[i] for r in seq.results[:N] if r.notes[i]), "no frame could be tracked")
        return failed(seq.name, f"{seq.root}: no frame of the {N} could be tracked (frame 0: {first})")
    TH = np.stack([r.theta[i].detach().cpu().numpy() for r in seq.results[:N]])
    with torch.no_grad():
        th = torch.as_tensor(TH, device=cam.device)
        posed = scene(th)
        kp3, kp2 = _in_cameras(posed.keypoints, seq.rig)
        joints21 = _in_cameras(scene_standard_joints(scene, posed), seq.rig)
    out = OutputLayout(partial_dir(final))
    try:
        write_poses(out, Poses(TH.astype(np.float64), kp3, kp2, list(scene.names), scene.dof_names,
                               scene.keypoint_names, valid))
        if joints21[0].shape[2]:
            write_joints21(out, *joints21)
        _write_motion(out, scene, th)
        if options.write_render:
            _write_renders(out, posed, cam, renderer, N)
        _write_log(out, seq, settings)
        if options.viz and len(seq.rig) == 1 and seq.depth_read:
            _write_overlays(out, seq, scene, posed)
        elif options.viz:
            write_view_overlays(out.root, seq.root, seq.info, scene, posed, seq.rig)
        if options.write_vertices:
            _write_vertices(out, scene, posed, cam)
    except BaseException:
        shutil.rmtree(out.root, ignore_errors=True)
        raise
    commit_dir(out.root, final, force)
    return _summary(seq, valid, str(final))


def _in_cameras(points: torch.Tensor, rig: list) -> tuple:
    """World points (N, P, 3) -> ((N, C, P, 3) mm in each camera's frame, (N, C, P, 2) px)."""
    return (np.stack([c.to_camera(points).cpu().numpy() for c in rig], 1),
            np.stack([c.project(points).cpu().numpy() for c in rig], 1))


def _summary(seq: TrackedSequence, valid: np.ndarray, out: str) -> dict:
    N = seq.info.frames
    ious = [q[0] for q in seq.quality if np.isfinite(q[0])]
    res = [q[1] for q in seq.quality if np.isfinite(q[1])]
    return {"sequence": seq.name, "status": "ok", "frames": N, "out": out,
            "seconds_per_frame": float(np.mean([r.seconds for r in seq.results[:N]])) / seq.batch,
            "flagged_frames": int((~valid).sum()), "reinitialized_frames": int(sum(seq.reinitialized)),
            "fit_flagged_frames": int(sum(bool(getattr(q, "flagged", False)) for q in seq.quality)),
            "mean_iou": float(np.mean(ious)) if ious else float("nan"),
            "median_depth_residual_mm": float(np.median(res)) if res else float("nan")}


def _write_motion(out: OutputLayout, scene: Scene, th: torch.Tensor) -> None:
    """``motion/<Model>.MOTION`` per model (thesis format: row 0 is the rigging pose, row
    k+1 is frame k)."""
    out.motion_dir.mkdir()
    thesis_name = {v: k for k, v in THESIS_MODEL_NAMES.items()}
    for model_name, model in zip(scene.names, scene.models):
        mot = theta_to_motion(model, th[:, scene.slices[model_name]])
        rest = {b: model.rest_transforms[j].cpu().double().numpy()[None] for j, b in enumerate(model.bone_names)}
        mot = {b: np.concatenate([rest[b], m], 0) for b, m in mot.items()}
        write_motion(out.motion(thesis_name.get(model_name, model_name)), mot)


def _check_fields(q) -> dict:
    """The fit check of a frame beyond IoU and residual (:class:`~torchhand.scoring.metrics.FitCheck`)."""
    return {"keypoint_px": _finite(getattr(q, "keypoint_px", float("nan"))),
            "keypoint_mm": _finite(getattr(q, "keypoint_mm", float("nan"))),
            "hand_explained": _finite(getattr(q, "explained", float("nan"))),
            "off_hand": _finite(getattr(q, "off_hand", float("nan"))),
            "surrounded": _finite(getattr(q, "surrounded", float("nan"))),
            "fit_flagged": bool(getattr(q, "flagged", False))}


def _write_log(out: OutputLayout, seq: TrackedSequence, settings: dict) -> None:
    i = seq.index
    log = [{"frame": f, "seconds": r.seconds, "iterations": int(r.iterations[i]),
            "energy": None if not np.isfinite(float(r.energy[i])) else float(r.energy[i]),
            "valid": bool(r.valid[i]), "recovered": bool(r.recovered[i]),
            "correspondences": int(r.correspondences[i]), "iou": _finite(seq.quality[f][0]),
            "depth_residual_mm": _finite(seq.quality[f][1]), **_check_fields(seq.quality[f]),
            "reinitialized": seq.reinitialized[f], "notes": r.notes[i]}
           for f, r in enumerate(seq.results[:seq.info.frames])]
    out.track_log.write_text(json.dumps({"sequence": seq.name, "source": str(seq.root),
                                         "energy": settings["tracker"]["energy"], "settings": settings,
                                         "frames": log}))


def _write_vertices(out: OutputLayout, scene: Scene, posed: SceneOutput, cam) -> None:
    out.vertices_dir.mkdir()
    with torch.no_grad():
        verts = cam.to_camera(posed.vertices)
    for model_name in scene.names:
        np.save(out.vertices(model_name), verts[:, scene.vertex_slices[model_name]].cpu().numpy().astype(np.float32))


def _finite(x: float) -> Optional[float]:
    return float(x) if np.isfinite(x) else None


def _write_renders(out: OutputLayout, posed: SceneOutput, cam, renderer, frames: int) -> None:
    """The rendered depth of the fitted models, ``render/NNNNNN.png`` (16-bit mm, 0 = none)."""
    out.render_dir.mkdir()
    with torch.no_grad():
        for f in range(frames):
            write_depth(out.render(f), renderer(posed.vertices[f : f + 1], cam, normals=False).depth[0].cpu().numpy())


def _legend(scene: Scene, gt: Optional[np.ndarray]) -> list:
    kinds = [m.kind for m in scene.models]
    legend = [(f"{n}: tracked", None if kind == "hand" else OBJECT_COLOR) for n, kind in zip(scene.names, kinds)]
    return legend + ([("ground truth", GT_COLOR)] if gt is not None else [])


def _write_overlays(out: OutputLayout, seq: TrackedSequence, scene: Scene, posed: SceneOutput) -> None:
    """Overlays for a person: the input depth in false colour with one mm range for the
    whole sequence (and its colour bar), the frame number, the tracked models (hand
    skeletons, object outlines) and, where ``root/gt`` exists, the ground-truth
    skeletons in white beside them; with a segmentation, the outline of the hands'
    pixels in green and the forearm cut away in red; a frame whose fit check failed
    (``fit_flagged``) framed in red and labelled. One PNG per frame and an MP4."""
    info, cam = seq.info, seq.rig[0]
    out.overlays_dir.mkdir()
    gt = _ground_truth_2d(seq.root, scene, info.frames)
    depths, segs = [], []
    for f in range(info.frames):
        try:
            depths.append(read_depth(SequenceLayout(seq.root).depth(f), info.depth_unit_mm))
        except SequenceError:
            depths.append(np.zeros((cam.height, cam.width), np.float32))
        segs.append(seq.masks(f, depths[-1].shape))
    near, far = depth_range(depths)
    legend = _legend(scene, gt)
    images = []
    with torch.no_grad():
        for f, depth in enumerate(depths):
            img = depth_to_color(depth, near, far)
            if segs[f] is not None:
                draw_mask_outline(img, segs[f][0], (0, 220, 0))
                draw_mask_outline(img, segs[f][1], (0, 0, 220))
            draw_models(img, scene, posed, f, cam, None if gt is None else gt[f, 0])
            draw_colorbar(img, near, far)
            q = seq.quality[f]
            flagged = bool(getattr(q, "flagged", False))
            draw_legend(img, f"frame {f}" + (" FIT CHECK FAILED" if flagged else ""), legend)
            if flagged:  # a red frame around a fit the localiser contradicts
                cv2.rectangle(img, (0, 0), (img.shape[1] - 1, img.shape[0] - 1), (0, 0, 255), 4)
            cv2.imwrite(str(out.overlay(f)), img)
            images.append(img)
    write_video(images, out.overlays_video, fps=info.fps)


def write_view_overlays(target: Path, root: Path, info: SequenceInfo, scene: Scene, posed: SceneOutput,
                        rig: list) -> None:
    """Overlays of a camera rig (or of colour views): ``overlays/cam<k>/NNNNNN.png`` per
    view, the view's colour image (its depth in false colour where it has none) with
    the tracked models and, where ``root/gt`` exists, the ground-truth skeletons; and
    ``overlays.mp4``, every view of a frame in one picture."""
    out, seq = OutputLayout(target), SequenceLayout(root)
    gt = _ground_truth_2d(root, scene, info.frames)
    legend = _legend(scene, gt)
    for c in range(len(rig)):
        out.overlay_dir(c).mkdir(parents=True)
    pictures = []
    with torch.no_grad():
        for f in range(info.frames):
            views = []
            for c, cam in enumerate(rig):
                try:
                    if info.has_rgb:
                        img = cv2.cvtColor(read_rgb(seq.rgb(f, c)), cv2.COLOR_RGB2BGR)
                    else:
                        img = depth_to_color(read_depth(seq.depth(f, c), info.depth_unit_mm))
                except SequenceError:
                    img = np.zeros((cam.height, cam.width, 3), np.uint8)
                has_gt = gt is not None and gt.shape[1] == len(rig)
                draw_models(img, scene, posed, f, cam, gt[f, c] if has_gt else None)
                draw_legend(img, f"frame {f}, camera {c}", legend)
                cv2.imwrite(str(out.overlay(f, c)), img)
                views.append(img)
            pictures.append(mosaic(views))
    write_video(pictures, out.overlays_video, fps=info.fps)


def _ground_truth_2d(root: Path, scene: Scene, frames: int) -> Optional[np.ndarray]:
    """(N, C, P, 2) ground-truth keypoints of every camera for the overlays, or None when
    the folder has no readable ``gt/`` of this scene (the tracking itself never reads it)."""
    try:
        gt = read_poses(SequenceLayout(root).gt)
    except SequenceError:
        return None
    if gt.keypoint_names != scene.keypoint_names or len(gt.keypoints_2d) != frames:
        return None
    return gt.keypoints_2d
