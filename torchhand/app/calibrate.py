"""``torchhand calibrate``: a hand's size (global scale, finger lengths) fitted to a few
frames of a sequence folder (:mod:`torchhand.tracking.calibration`), written as a model
file that ``--models`` accepts, with a report."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from tqdm import tqdm

from torchhand.app.frames import pose_fit, read_frame, segment_for_search, segment_of
from torchhand.data.layout import SequenceError, read_sequence_info
from torchhand.io.assets import save_assets
from torchhand.model.articulated import ArticulatedModel, load_model
from torchhand.model.scene import Scene
from torchhand.tracking.calibration import CalibrationConfig, calibrate_hand
from torchhand.tracking.initialization import Initializer
from torchhand.tracking.segmentation import SegmentConfig, SegmentationError
from torchhand.tracking.tracker import Tracker, TrackerConfig

__all__ = ["calibrate_sequence"]


def calibrate_sequence(root, model: str, out, frames: int = 5, force: bool = False,
                       segment: Optional[SegmentConfig] = None, config: CalibrationConfig = CalibrationConfig(),
                       progress: bool = True) -> dict:
    """``torchhand calibrate``: fit the size of ``model`` (a shipped hand or a model file)
    to ``frames`` frames of a sequence, evenly spread over it (frames without a
    segmented hand are skipped), each initialised automatically
    (:mod:`torchhand.tracking.calibration`). Writes the resized model to ``out`` (an
    ``.npz`` that ``--models`` accepts) and the report beside it (``out`` with
    ``.json``: the factors and each frame's fit before and after); neither is
    overwritten unless ``force``. Returns the report."""
    root, out = Path(root), Path(out)
    report_path = out.with_suffix(".json")
    if out.suffix != ".npz":
        raise ValueError(f"--out {out}: the model is written as an .npz file")
    for p in (out, report_path):
        if p.exists() and not force:
            raise FileExistsError(f"{p} exists; choose another --out or pass --force")
    if frames < 1:
        raise ValueError(f"--frames must be >= 1, got {frames}")
    info = read_sequence_info(root)
    scene = Scene([load_model(model)], names=[Path(model).stem])
    if scene.models[0].kind != "hand":
        raise ValueError(f"--model {model}: calibration resizes a hand, this model is an object")
    tracker = Tracker(scene, TrackerConfig())
    cam = info.cameras[0]
    picks = sorted(set(np.linspace(0, info.frames - 1, min(frames, info.frames)).round().astype(int).tolist()))
    used, depths, thetas, skipped = _initialised_frames(root, info, scene, Initializer(tracker), segment, picks,
                                                        progress)
    theta = torch.stack(thetas)
    res = calibrate_hand(tracker, depths, [cam] * len(used), theta, config, name=out.stem)
    before = [pose_fit(scene, tracker.renderer, theta[k], cam, depths[k]) for k in range(len(used))]
    sized = Scene([ArticulatedModel(res.assets)], names=scene.names)
    after = [pose_fit(sized, tracker.renderer, res.theta[k], cam, depths[k]) for k in range(len(used))]
    report = {"model": str(out), "base_model": model, "sequence": str(root), "scale": res.scale,
              "fingers": res.fingers, "skipped_frames": skipped,
              "frames": [{"frame": f, "iou_before": b[0], "iou_after": a[0], "depth_residual_mm_before": b[1],
                          "depth_residual_mm_after": a[1]} for f, b, a in zip(used, before, after)],
              "mean_iou_before": float(np.mean([b[0] for b in before])),
              "mean_iou_after": float(np.mean([a[0] for a in after]))}
    out.parent.mkdir(parents=True, exist_ok=True)
    save_assets(res.assets, out, overwrite=force)
    report_path.write_text(json.dumps(report, indent=2))
    report["report"] = str(report_path)
    return report


def _initialised_frames(root: Path, info, scene: Scene, initializer: Initializer, segment: Optional[SegmentConfig],
                        picks: list, progress: bool) -> tuple:
    """(frames used, their depths, their initialised poses, {skipped frame: why}) of the
    picked frames, each segmented for one hand and initialised automatically."""
    search = dataclasses.replace(segment_for_search(segment_of(info, segment), scene), hands=1)
    depths, thetas, used, skipped = [], [], [], {}
    for f in tqdm(picks, desc="calibrate: initialise", unit="frame", disable=not progress):
        try:
            depth, seg = read_frame(root, info, f, search)
        except (SequenceError, SegmentationError) as err:
            skipped[f] = str(err)
            continue
        depths.append(depth)
        thetas.append(initializer(depth, info.cameras[0], seg).theta)
        used.append(f)
    if not used:
        raise ValueError(f"{root}: no frame of {picks} has a segmented hand: {skipped}")
    return used, depths, thetas, skipped
