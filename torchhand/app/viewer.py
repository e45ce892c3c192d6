"""3D viewing of a tracked sequence with rerun (``torchhand view``; the ``viz`` extra,
``pip install 'torchhand[viz]'``): a recording written to an ``.rrd`` file, or sent to a
viewer it spawns.

The recording has one timeline, ``frame`` (the sequence's frame index), and these
entities; world coordinates are the sequence's (camera 0's for every reader and for
synthesis: x right, y down, z forward), in mm:

- ``world``: the view coordinates (static);
- ``world/cam<k>``: camera k of the rig, its pose (camera to world) and pinhole
  intrinsics (static), and under it ``world/cam<k>/depth``, per frame, its depth map
  back-projected (every ``stride``-th pixel in each direction; coloured by its colour
  image where the sequence has one) in camera k's frame;
- ``world/models/<name>``: per frame, each tracked model's posed mesh;
- ``world/joints21/tracked`` and, with ground truth, ``world/joints21/ground_truth``: per
  frame the standard 21 joints of each hand (points), and ``.../bones`` the five finger
  chains from the wrist (line strips); absent ground-truth joints are left out;
- ``metrics/mpjpe_mm`` (with ground truth): each frame's mean 21-joint error, camera 0;
  ``metrics/<key>``: the fit check of ``track_log.json`` as time series, for each of
  :data:`FIT_KEYS` that the log holds (the silhouette IoU of models and data, the median
  depth residual, the surround, the measures against the hand localiser, and
  ``fit_flagged`` as 0 / 1).

The ``.rrd`` is written to a hidden file beside ``FILE`` and renamed when complete.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Dict, List, NamedTuple, Optional

import numpy as np
import torch

from torchhand.core.errors import MissingExtra, UsageError
from torchhand.data.layout import (OutputLayout, SequenceInfo, SequenceLayout, read_depth, read_joints21,
                                   read_joints21_valid, read_poses, read_rgb, read_sequence_info)
from torchhand.geometry.camera import unproject_pixels

__all__ = ["view_sequence", "ViewSources", "view_sources", "FINGER_CHAINS", "ENTITY_ROOTS", "FIT_KEYS"]

#: the five finger chains of the standard 21 joints, each from the wrist to the tip
FINGER_CHAINS = [[0, 1 + 4 * f, 2 + 4 * f, 3 + 4 * f, 4 + 4 * f] for f in range(5)]
#: the entity trees of a recording (module docstring)
ENTITY_ROOTS = ("world", "metrics")
#: the fit check's per-frame keys of ``track_log.json`` that the recording plots
FIT_KEYS = ("iou", "depth_residual_mm", "surrounded", "keypoint_mm", "hand_explained", "off_hand", "fit_flagged")


class ViewSources(NamedTuple):
    """What a view reads: the output folder, the sequence folder (depth, cameras) and
    whether its ground truth is drawn."""

    out: OutputLayout
    seq: SequenceLayout
    info: SequenceInfo
    with_gt: bool


def _rerun():
    try:
        import rerun
    except ImportError:
        raise MissingExtra("torchhand view", "rerun-sdk", "viz") from None
    return rerun


def view_sources(out_dir, gt: Optional[Path] = None) -> ViewSources:
    """The folders a view reads (module docstring); ``gt`` the sequence folder, else the
    one ``track_log.json`` names (then without ground truth)."""
    out = OutputLayout(Path(out_dir))
    if not out.meta.is_file():
        raise UsageError(f"{out.meta}: not found ({out.root} is not a tracked sequence's output folder, "
                         "OUT/<sequence> of torchhand track)")
    if gt is None:
        try:
            gt = Path(json.loads(out.track_log.read_text())["source"])
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise UsageError(f"{out.track_log}: cannot read the sequence folder it names ({err}); give it with "
                             "--gt SEQ") from None
        with_gt = False
    else:
        with_gt = SequenceLayout(gt).gt.keypoints21_3d.is_file()
    seq = SequenceLayout(Path(gt))
    return ViewSources(out, seq, read_sequence_info(seq.root), with_gt)


def _to_world(info: SequenceInfo, points_cam0: np.ndarray) -> np.ndarray:
    """(..., 3) points of camera 0's frame -> world, mm."""
    T = np.linalg.inv(info.cameras[0].T_cw.double().numpy())
    return points_cam0 @ T[:3, :3].T + T[:3, 3]


def _log_rig(rr, rec, info: SequenceInfo) -> None:
    rec.log("world", rr.ViewCoordinates.RDF, static=True)
    for k, cam in enumerate(info.cameras):
        T = np.linalg.inv(cam.T_cw.double().numpy())  # camera -> world
        rec.log(f"world/cam{k}", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]), static=True)
        rec.log(f"world/cam{k}", rr.Pinhole(image_from_camera=cam.K.double().numpy(),
                                            resolution=[cam.width, cam.height], camera_xyz=rr.ViewCoordinates.RDF),
                static=True)


def _depth_points(src: ViewSources, frame: int, camera: int, stride: int):
    """(points (P, 3) mm in the camera's frame, colours (P, 3) uint8 or None) of one depth map."""
    cam = src.info.cameras[camera]
    depth = read_depth(src.seq.depth(frame, camera), src.info.depth_unit_mm)[::stride, ::stride]
    v, u = np.nonzero(depth > 0)
    if not len(u):
        return np.zeros((0, 3)), None
    pixels = torch.from_numpy(np.stack([u, v], 1) * float(stride))
    pts = unproject_pixels(pixels, torch.from_numpy(depth[v, u].astype(np.float64)), cam.K.double()).numpy()
    colours = None
    rgb_path = src.seq.rgb(frame, camera)
    if src.info.has_rgb and rgb_path.is_file():
        colours = read_rgb(rgb_path)[::stride, ::stride][v, u]
    return pts, colours


def _log_joints(rr, rec, path: str, joints: np.ndarray, colour) -> None:
    """joints (21 x hands, 3) world mm, NaN where absent: points and the finger chains."""
    ok = np.isfinite(joints).all(-1)
    rec.log(path, rr.Points3D(joints[ok], colors=colour, radii=3.0))
    strips = [joints[h * 21 + np.array(c)] for h in range(len(joints) // 21) for c in FINGER_CHAINS]
    strips = [s[np.isfinite(s).all(-1)] for s in strips]
    rec.log(f"{path}/bones", rr.LineStrips3D([s for s in strips if len(s) > 1], colors=colour, radii=1.5))


def _fit_check(out: OutputLayout, frames: int) -> Dict[str, List[Optional[float]]]:
    """Per frame each of :data:`FIT_KEYS` of ``track_log.json`` (None where absent or
    not a number; ``fit_flagged`` as 0 / 1); keys that no frame has are left out."""
    try:
        log = json.loads(out.track_log.read_text())["frames"]
    except (OSError, ValueError, KeyError, TypeError):
        return {}

    def value(f: int, key: str) -> Optional[float]:
        v = log[f].get(key) if f < len(log) and isinstance(log[f], dict) else None
        return float(v) if isinstance(v, (int, float)) else None  # bool is an int: flagged 0 / 1

    series = {key: [value(f, key) for f in range(frames)] for key in FIT_KEYS}
    return {key: v for key, v in series.items() if any(x is not None for x in v)}


def _per_frame_error(src: ViewSources, pred21) -> Optional[np.ndarray]:
    """(N,) mean 21-joint error of each frame in camera 0 (NaN where none), or None."""
    from torchhand.scoring.metrics import joint_errors

    if not src.with_gt or pred21 is None:
        return None
    gt3, _ = read_joints21(src.seq.gt.root)
    if gt3.shape != pred21[0].shape:
        raise UsageError(f"{src.seq.gt.keypoints21_3d}: {gt3.shape}, but {src.out.keypoints21_3d} is "
                         f"{pred21[0].shape}; --gt must be the sequence that was tracked")
    e = joint_errors(np.nan_to_num(pred21[0][:, 0]), gt3[:, 0], read_joints21_valid(src.seq.gt.root))
    return np.array([np.nanmean(r) if np.isfinite(r).any() else np.nan for r in e])


def _posed_meshes(models: List[str], theta: np.ndarray):
    """(scene, world vertices (N, V, 3)) of the tracked poses."""
    from torchhand.model.scene import Scene

    scene = Scene.from_names(models, dtype=torch.float64)
    with torch.no_grad():
        return scene, scene(torch.as_tensor(theta, dtype=torch.float64)).vertices.numpy()


def _log_frames(rr, rec, src: ViewSources, stride: int, progress: bool) -> int:
    """Log every frame (module docstring); returns the number of frames."""
    from tqdm import tqdm

    poses = read_poses(src.out.root)
    pred21 = read_joints21(src.out.root)
    gt21 = read_joints21(src.seq.gt.root) if src.with_gt else None
    gt_valid = read_joints21_valid(src.seq.gt.root) if src.with_gt else None
    scene, vertices = _posed_meshes(poses.models, poses.theta)
    errors, fit = _per_frame_error(src, pred21), _fit_check(src.out, len(poses.theta))
    views = range(len(src.info.cameras)) if src.info.has_depth else range(0)
    for f in tqdm(range(len(poses.theta)), desc="view", unit="frame", disable=not progress):
        rec.set_time("frame", sequence=f)
        for k in views if f < src.info.frames else ():
            pts, colours = _depth_points(src, f, k, stride)
            rec.log(f"world/cam{k}/depth", rr.Points3D(pts, colors=colours, radii=1.0))
        for name, model in zip(scene.names, scene.models):
            rec.log(f"world/models/{name}", rr.Mesh3D(vertex_positions=vertices[f, scene.vertex_slices[name]],
                                                      triangle_indices=model.faces.numpy()))
        if pred21 is not None:
            _log_joints(rr, rec, "world/joints21/tracked", _to_world(src.info, pred21[0][f, 0]), (40, 200, 255))
        if gt21 is not None and f < len(gt21[0]):
            j = gt21[0][f, 0].copy()
            if gt_valid is not None:
                j[~gt_valid[f]] = np.nan
            _log_joints(rr, rec, "world/joints21/ground_truth", _to_world(src.info, j), (255, 120, 40))
        if errors is not None and np.isfinite(errors[f]):
            rec.log("metrics/mpjpe_mm", rr.Scalars(float(errors[f])))
        for key, values in fit.items():
            if values[f] is not None:
                rec.log(f"metrics/{key}", rr.Scalars(float(values[f])))
    return len(poses.theta)


def view_sequence(out_dir, rrd: Optional[Path] = None, gt: Optional[Path] = None, spawn: bool = False,
                  stride: int = 4, force: bool = False, progress: bool = True) -> Dict:
    """Record a tracked sequence for rerun (module docstring).

    Args:
        out_dir: a tracked sequence's output folder (``OUT/<sequence>`` of ``torchhand track``).
        rrd: the ``.rrd`` file to write (must not exist unless ``force``).
        gt: the sequence folder (its depth, cameras and ``gt/`` joints); default: the one
            ``track_log.json`` names, drawn without ground truth.
        spawn: also (or instead of ``rrd``) send the recording to a viewer it starts.
        stride: every ``stride``-th depth pixel in each direction becomes a point.
    Returns:
        ``{"frames", "cameras", "rrd", "ground_truth"}``.
    """
    if rrd is None and not spawn:
        raise UsageError("give --rrd FILE (a recording to open with rerun) or --spawn (a viewer, where a display exists)")
    if not (isinstance(stride, int) and stride >= 1):
        raise UsageError(f"--stride must be an integer >= 1, got {stride!r}")
    rrd = None if rrd is None else Path(rrd)
    if rrd is not None and rrd.exists() and not force:
        raise FileExistsError(f"{rrd} exists; choose a new file or pass --force to replace it")
    src = view_sources(out_dir, gt)
    rr = _rerun()
    rec = rr.RecordingStream(application_id="torchhand", recording_id=src.out.root.name)
    partial = None if rrd is None else rrd.parent / f".{rrd.name}.partial"
    if partial is not None:
        rrd.parent.mkdir(parents=True, exist_ok=True)
    if spawn and partial is not None:  # both: the file and a viewer
        rec.spawn(connect=False)
        rec.set_sinks(rr.FileSink(str(partial)), rr.GrpcSink())
    elif spawn:
        rec.spawn()
    else:
        rec.save(str(partial))
    try:
        _log_rig(rr, rec, src.info)
        frames = _log_frames(rr, rec, src, stride, progress)
        rec.flush()
        rec.disconnect()
    except BaseException:
        if partial is not None:
            partial.unlink(missing_ok=True)
        raise
    if partial is not None:
        os.replace(partial, rrd)
    return {"frames": frames, "cameras": len(src.info.cameras), "rrd": None if rrd is None else str(rrd),
            "ground_truth": src.with_gt}
