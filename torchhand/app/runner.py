"""The runner: tracks sequence folders (datasets/README.md layout) and writes the results.

Reading sequence folders, batching same-scene sequences, and writing theta, keypoints,
MOTION files, logs and overlays live here; the tracker itself takes depth frames and
returns results (:mod:`torchhand.tracking.tracker`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable, Dict, Iterator, List, Optional, Sequence

import cv2
import numpy as np
import torch
from tqdm import tqdm

from torchhand.app.drawing import (GT_COLOR, OBJECT_COLOR, depth_range, depth_to_color, draw_chain, draw_colorbar,
                                   draw_hull, draw_legend, draw_mask_outline, draw_skeleton, write_video)
from torchhand.data.layout import (Poses, SequenceError, SequenceInfo, camera_dir, frame_name, read_depth,
                                   read_init_pose, read_poses, read_sequence_info, write_depth, write_poses)
from torchhand.io.assets import THESIS_MODEL_NAMES
from torchhand.io.output_dir import prepare_output_dir
from torchhand.io.thesis import write_motion
from torchhand.model.motion import theta_to_motion
from torchhand.model.scene import Scene, SceneOutput
from torchhand.scoring.metrics import fit_quality
from torchhand.tracking.energies import EnergyTerm
from torchhand.tracking.initialization import InitResult, initialize_hands
from torchhand.tracking.segmentation import SegmentConfig, SegmentationError, segment_hands
from torchhand.tracking.tracker import FrameResult, Tracker, TrackerConfig

__all__ = ["track_sequences", "automatic_init"]


def track_sequences(roots: Sequence, out, config: TrackerConfig = TrackerConfig(), device: str = "cpu",
                    viz: bool = False, force: bool = False, progress: bool = True,
                    make_terms: Optional[Callable[[], List[EnergyTerm]]] = None,
                    segment: Optional[SegmentConfig] = None, write_render: bool = False) -> List[dict]:
    """Track sequence folders and write their results.

    Sequences with the same models are solved as one batch, frame by frame; the
    tracking never reads ``gt/``. For every sequence ``<out>/<name>/`` receives the
    ``gt/`` layout (theta.npy, keypoints_3d.npy, keypoints_2d.npy, meta.json with
    per-frame ``valid`` flags), ``motion/<Model>.MOTION`` per model (thesis format: row
    0 is the rigging pose, row k+1 is frame k), ``track_log.json``, and with ``viz``
    overlay PNGs and an MP4 (drawn after the sequence is tracked; where the sequence
    folder has ``gt/``, its skeletons are drawn beside the tracked ones).
    ``make_terms`` builds custom energy terms per batch (default: from ``config.energy``).
    ``segment``: the hand segmentation of every frame (:mod:`torchhand.tracking.segmentation`;
    only the hands' pixels reach the tracker); None: what each ``sequence.json`` says
    (``torchhand import`` stores it), else none. A frame without a hand-sized blob keeps
    the previous pose and is flagged, like a missing frame.
    Every frame's fit quality, measured without ground truth (:func:`~torchhand.scoring.
    metrics.fit_quality`: the silhouette IoU of the rendered fitted models and the data
    the tracker saw, and the median |model - data| depth on their overlap), goes into
    ``track_log.json`` (``iou``, ``depth_residual_mm``) and the summary; with
    ``write_render`` the rendered model depth of each frame is written to
    ``render/NNNNNN.png`` (16-bit mm) so the fit can be checked independently.

    A sequence whose first depth frame cannot be read (missing, not 16-bit, values
    that look like metres), or of which no frame could be tracked, fails: nothing is
    written for it and its summary says why; the others are tracked.

    Returns:
        one dict per sequence, in the order of ``roots``: ``sequence``, ``status``
        ("ok" or "failed"), ``error`` (failed), ``frames``, ``out``,
        ``seconds_per_frame``, ``flagged_frames``.
    """
    roots = [Path(r) for r in roots]
    infos = [read_sequence_info(r) for r in roots]
    names = [i.name for i in infos]
    if len(set(names)) != len(names):
        names = [f"{i.name}_{k}" for k, i in enumerate(infos)]
    out = Path(out)
    targets = [out / n for n in names]
    for t in targets:
        if t.exists() and any(t.iterdir()) and not force:
            raise FileExistsError(f"{t} is not empty; choose another --out or pass --force")
    summaries: Dict[int, dict] = {}
    groups: Dict[tuple, List[int]] = {}
    for k, info in enumerate(infos):
        try:  # a sequence whose first frame is unusable fails before any tracking
            read_depth(camera_dir(roots[k], 0) / "depth" / frame_name(0), info.depth_unit_mm)
        except SequenceError as err:
            summaries[k] = _failed(names[k], f"{err}")
            continue
        groups.setdefault(tuple(info.models), []).append(k)
    for models, members in groups.items():
        scene = Scene.from_names(list(models), device=device)
        tracker = Tracker(scene, config, make_terms() if make_terms is not None else None)
        cams = [infos[k].cameras[0].to(device) for k in members]
        segs = [_segment_of(infos[k], segment) for k in members]
        starts, init_notes = [], []
        for i, k in enumerate(members):
            th, note = _init_pose(roots[k], infos[k], scene, models, tracker, cams[i], segs[i], device)
            starts.append(th)
            init_notes.append(note)
            if note:
                tqdm.write(f"{names[k]}: {note}")
        init = torch.as_tensor(np.stack(starts), dtype=torch.float32, device=device)
        n_frames = max(infos[k].frames for k in members)
        read_errors: List[List[str]] = []
        bar = tqdm(total=n_frames * len(members), desc=f"track {'+'.join(models)}", unit="frame", disable=not progress)
        results: List[FrameResult] = []
        frames = _depth_frames([roots[k] for k in members], [infos[k] for k in members], n_frames, read_errors, segs)
        for f, res in enumerate(tracker.track(frames, cams, init)):
            for i, err in enumerate(read_errors[f]):
                if err:
                    res.notes[i] = f"{err}; previous pose kept"
                elif f == 0 and init_notes[i]:
                    res.notes[i] = init_notes[i]
            for i, note in enumerate(res.notes):
                if note:
                    tqdm.write(f"{names[members[i]]} frame {f}: {note}")
            results.append(res)
            bar.update(len(members))
        bar.close()
        for i, k in enumerate(members):
            summaries[k] = _write_sequence(targets[k], roots[k], infos[k], names[k], scene, cams[i], results, i,
                                           len(members), config, viz, force, segs[i], tracker.renderer, write_render)
    return [summaries[k] for k in range(len(roots))]


def _failed(name: str, error: str) -> dict:
    return {"sequence": name, "status": "failed", "error": error, "frames": 0, "out": None,
            "seconds_per_frame": float("nan"), "flagged_frames": 0}


def _init_pose(root: Path, info: SequenceInfo, scene: Scene, models: tuple, tracker: Tracker, cam,
               segment: Optional[SegmentConfig], device) -> tuple:
    """(theta of frame 0, note): ``init_pose.json`` when the folder has it, else the
    automatic initialisation on frame 0 (:mod:`torchhand.tracking.initialization`)."""
    if (root / "init_pose.json").is_file():
        th = read_init_pose(root)
        if th.shape != (scene.num_dofs,):
            raise ValueError(f"{root / 'init_pose.json'}: theta has {th.size} values, the scene "
                             f"{list(models)} has {scene.num_dofs} DoF")
        return th, ""
    res = automatic_init(root, info, scene, tracker, cam, segment)
    return res.theta.cpu().double().numpy(), (f"no init_pose.json: initialised automatically (depth discrepancy "
                                             f"{res.cost:.2f}, {res.seconds:.1f} s)")


def automatic_init(root: Path, info: SequenceInfo, scene: Scene, tracker: Tracker, cam,
                   segment: Optional[SegmentConfig]) -> InitResult:
    """The automatic initialisation of a sequence's frame 0 (its segmentation, or the
    automatic one with as many hands as the scene has)."""
    if segment is None:
        segment = SegmentConfig(hands=max(1, sum(m.kind == "hand" for m in scene.models)))
    depth, seg = _read_frame(root, info, 0, segment)
    return initialize_hands(tracker, depth, cam, seg)


def _segment_of(info: SequenceInfo, given: Optional[SegmentConfig]) -> Optional[SegmentConfig]:
    """The segmentation of a sequence: the one given, else its ``sequence.json``'s."""
    if given is not None:
        return None if given.mode == "none" else given
    if info.segmentation:
        try:
            return SegmentConfig.from_dict(info.segmentation)
        except (TypeError, ValueError) as err:
            raise SequenceError(f"{info.name}: sequence.json segmentation: {err}") from None
    return None


def _read_frame(root: Path, info: SequenceInfo, f: int, segment: Optional[SegmentConfig]):
    """(depth mm with only the hands' pixels when segmented, segmentation or None)."""
    path = camera_dir(root, 0) / "depth" / frame_name(f)
    depth = read_depth(path, info.depth_unit_mm)
    if segment is None:
        return depth, None
    seg = segment_hands(depth, info.cameras[0], segment, frame=str(path))
    return np.where(seg.mask, depth, 0).astype(np.float32), seg


def _depth_frames(roots: List[Path], infos: List[SequenceInfo], n_frames: int, errors: List[List[str]],
                  segments: List[Optional[SegmentConfig]]) -> Iterator[List[Optional[np.ndarray]]]:
    """Per frame, the depth map of every sequence (None past its end, where unreadable or
    where the segmentation found no hand; the reason is appended to ``errors``, one list
    per frame)."""
    for f in range(n_frames):
        depths, why = [], []
        for root, info, seg in zip(roots, infos, segments):
            depth, err = None, ""
            if f < info.frames:
                try:
                    depth, _ = _read_frame(root, info, f, seg)
                except (SequenceError, SegmentationError) as e:  # the tracker keeps the previous pose
                    err = str(e)
            depths.append(depth)
            why.append(err)
        errors.append(why)
        yield depths


def _write_sequence(target: Path, root: Path, info: SequenceInfo, name: str, scene: Scene, cam, results, i: int,
                    batch: int, config: TrackerConfig, viz: bool, force: bool,
                    segment: Optional[SegmentConfig] = None, renderer=None, write_render: bool = False) -> dict:
    """Write one sequence's outputs from the batch's frame results (problem ``i``)."""
    N = info.frames
    valid = np.array([r.valid[i].item() for r in results[:N]], bool)
    if not valid.any():
        first = next((r.notes[i] for r in results[:N] if r.notes[i]), "no frame could be tracked")
        return _failed(name, f"{root}: no frame of the {N} could be tracked (frame 0: {first})")
    TH = np.stack([r.theta[i].detach().cpu().numpy() for r in results[:N]])
    with torch.no_grad():
        th = torch.as_tensor(TH, device=cam.device)
        posed = scene(th)
        kp3 = cam.to_camera(posed.keypoints).cpu().numpy()[:, None]
        kp2 = cam.project(posed.keypoints).cpu().numpy()[:, None]
    target = prepare_output_dir(target, force)
    write_poses(target, Poses(TH.astype(np.float64), kp3, kp2, list(scene.names), scene.dof_names,
                              scene.keypoint_names, valid))
    (target / "motion").mkdir()
    thesis_name = {v: k for k, v in THESIS_MODEL_NAMES.items()}
    for model_name, model in zip(scene.names, scene.models):
        mot = theta_to_motion(model, th[:, scene.slices[model_name]])
        rest = {b: model.rest_transforms[j].cpu().double().numpy()[None] for j, b in enumerate(model.bone_names)}
        mot = {b: np.concatenate([rest[b], m], 0) for b, m in mot.items()}
        write_motion(target / "motion" / f"{thesis_name.get(model_name, model_name)}.MOTION", mot)
    quality = _fit_quality(target, root, info, posed, cam, segment, renderer, config, write_render)
    log = [{"frame": f, "seconds": r.seconds, "iterations": int(r.iterations[i]),
            "energy": None if not np.isfinite(float(r.energy[i])) else float(r.energy[i]),
            "valid": bool(r.valid[i]), "recovered": bool(r.recovered[i]),
            "correspondences": int(r.correspondences[i]), "iou": _finite(quality[f][0]),
            "depth_residual_mm": _finite(quality[f][1]), "notes": r.notes[i]} for f, r in enumerate(results[:N])]
    (target / "track_log.json").write_text(json.dumps({"sequence": name, "source": str(root),
                                                       "energy": config.energy, "frames": log}))
    if viz:
        _write_overlays(target, root, info, scene, posed, cam, segment)
    ious = [q[0] for q in quality if np.isfinite(q[0])]
    res = [q[1] for q in quality if np.isfinite(q[1])]
    return {"sequence": name, "status": "ok", "frames": N, "out": str(target),
            "seconds_per_frame": float(np.mean([r.seconds for r in results[:N]])) / batch,
            "flagged_frames": int((~valid).sum()), "mean_iou": float(np.mean(ious)) if ious else float("nan"),
            "median_depth_residual_mm": float(np.median(res)) if res else float("nan")}


def _finite(x: float) -> Optional[float]:
    return float(x) if np.isfinite(x) else None


def _fit_quality(target: Path, root: Path, info: SequenceInfo, posed: SceneOutput, cam,
                 segment: Optional[SegmentConfig], renderer, config: TrackerConfig, write_render: bool) -> list:
    """Per frame (IoU, median depth residual mm) of the fitted models against the data the
    tracker saw (segmented, in the working range); renders written with ``write_render``."""
    if write_render:
        (target / "render").mkdir()
    out = []
    pre = config.preprocess
    with torch.no_grad():
        for f in range(info.frames):
            model = renderer(posed.vertices[f : f + 1], cam, normals=False).depth[0].cpu().numpy()
            if write_render:
                write_depth(target / "render" / frame_name(f), model)
            try:
                data, _ = _read_frame(root, info, f, segment)
            except (SequenceError, SegmentationError):
                out.append((float("nan"), float("nan")))
                continue
            data = np.where((data >= pre.near) & (data <= pre.far), data, 0)
            out.append(fit_quality(model, data))
    return out


def _write_overlays(target: Path, root: Path, info: SequenceInfo, scene: Scene, posed: SceneOutput, cam,
                    segment: Optional[SegmentConfig] = None) -> None:
    """Overlays for a person: the input depth in false colour with one mm range for the
    whole sequence (and its colour bar), the frame number, the tracked models (hand
    skeletons, object outlines) and, where ``root/gt`` exists, the ground-truth
    skeletons in white beside them; with a segmentation, the outline of the hands'
    pixels in green and the forearm cut away in red. One PNG per frame and an MP4."""
    (target / "overlays").mkdir()
    gt = _ground_truth_2d(root, scene, info.frames)
    depths, segs = [], []
    for f in range(info.frames):
        try:
            depths.append(read_depth(camera_dir(root, 0) / "depth" / frame_name(f), info.depth_unit_mm))
        except SequenceError:
            depths.append(np.zeros((cam.height, cam.width), np.float32))
        seg = None
        if segment is not None:
            try:
                seg = segment_hands(depths[-1], info.cameras[0], segment)
            except SegmentationError:
                pass
        segs.append(seg)
    near, far = depth_range(depths)
    kinds = [m.kind for m in scene.models]
    legend = [(f"{n}: tracked", None if kind == "hand" else OBJECT_COLOR) for n, kind in zip(scene.names, kinds)]
    legend += [("ground truth", GT_COLOR)] if gt is not None else []
    images = []
    with torch.no_grad():
        for f, depth in enumerate(depths):
            img = depth_to_color(depth, near, far)
            if segs[f] is not None:
                draw_mask_outline(img, segs[f].mask, (0, 220, 0))
                draw_mask_outline(img, segs[f].cut, (0, 0, 220))
            for k, (model, out) in enumerate(zip(scene.models, posed.models)):
                if kinds[k] == "hand":
                    draw_skeleton(img, cam.project(out.keypoints[f : f + 1])[0].cpu().numpy())
                    if gt is not None:  # thin, over the tracked one, so that both show
                        draw_skeleton(img, gt[f, scene.keypoint_slices[scene.names[k]]], color=GT_COLOR, thickness=1)
                elif model.num_bones > 1:
                    draw_chain(img, cam.project(model.joints_from(out.G[f : f + 1]))[0].cpu().numpy())
                else:
                    draw_hull(img, cam.project(out.vertices[f : f + 1, ::16])[0].cpu().numpy())
            draw_colorbar(img, near, far)
            draw_legend(img, f"frame {f}", legend)
            cv2.imwrite(str(target / "overlays" / frame_name(f)), img)
            images.append(img)
    write_video(images, target / "overlays.mp4", fps=info.fps)


def _ground_truth_2d(root: Path, scene: Scene, frames: int) -> Optional[np.ndarray]:
    """(N, P, 2) ground-truth keypoints of camera 0 for the overlays, or None when the
    folder has no readable ``gt/`` of this scene (the tracking itself never reads it)."""
    try:
        gt = read_poses(root / "gt")
    except SequenceError:
        return None
    if gt.keypoint_names != scene.keypoint_names or len(gt.keypoints_2d) != frames:
        return None
    return gt.keypoints_2d[:, 0]
