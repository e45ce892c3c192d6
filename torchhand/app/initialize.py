"""``torchhand init``: the automatic initialisation of a sequence folder's frame 0
(:mod:`torchhand.tracking.initialization`), written to ``init_pose.json``; and the pose
the runner starts a sequence from (``init_pose.json``, else the same search)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import cv2
import numpy as np
import torch

from torchhand.app.drawing import depth_to_color, draw_mask_outline, draw_skeleton
from torchhand.app.frames import hand_sides, read_frame, segment_for_search, segment_of
from torchhand.data.layout import SequenceInfo, SequenceLayout, read_depth, read_init_pose, read_sequence_info, \
    write_init_pose
from torchhand.model.scene import Scene
from torchhand.scoring.metrics import fit_quality
from torchhand.tracking.initialization import InitConfig, Initializer, InitResult
from torchhand.tracking.segmentation import SegmentConfig, SegmentationError, segment_hands
from torchhand.tracking.tracker import Tracker, TrackerConfig

__all__ = ["initialize_sequence", "automatic_init", "first_pose"]


def first_pose(root: Path, info: SequenceInfo, scene: Scene, initializer: Optional[Initializer], cam,
               segment: Optional[SegmentConfig], frame: int = 0) -> tuple:
    """(theta of ``frame``, note): for frame 0, ``init_pose.json`` when the folder has
    it; else the automatic initialisation on ``frame``
    (:mod:`torchhand.tracking.initialization`; a chunk of a sequence starts there)."""
    seq = SequenceLayout(root)
    if frame == 0 and seq.init_pose.is_file():
        th = read_init_pose(root)
        if th.shape != (scene.num_dofs,):
            raise ValueError(f"{seq.init_pose}: theta has {th.size} values, the scene "
                             f"{list(info.models)} has {scene.num_dofs} DoF")
        return th, ""
    if initializer is None:
        if frame:
            raise ValueError(f"{root}: a chunk starting at frame {frame} needs the automatic initialisation, which "
                             f"places hands only, from depth (the scene {list(info.models)}, {len(info.cameras)} "
                             "view(s), this energy): track this sequence without --chunk")
        raise ValueError(f"{root}: no init_pose.json, and the automatic initialisation places hands only, from "
                         f"depth (the scene {list(info.models)}, {len(info.cameras)} view(s), this energy): "
                         "write init_pose.json")
    res = automatic_init(root, info, initializer, cam, segment, frame)
    why = "a chunk's first frame" if frame else "no init_pose.json"
    return res.theta.cpu().double().numpy(), (f"{why}: initialised automatically (depth discrepancy "
                                             f"{res.cost:.2f}, {res.seconds:.1f} s)")


def automatic_init(root: Path, info: SequenceInfo, initializer: Initializer, cam,
                   segment: Optional[SegmentConfig], frame: int = 0) -> InitResult:
    """The automatic initialisation of a sequence's ``frame`` (its segmentation, or the
    automatic one with as many hands as the scene has). A camera rig is initialised in
    the view where the hands are seen best (the localiser's hand pixels times their
    score; camera 0 with the blob rules); the pose is in world coordinates either way."""
    segment = segment_for_search(segment, initializer.tracker.scene)
    seq = SequenceLayout(root)
    sides = hand_sides(initializer.tracker.scene)
    best, first_error = None, None
    for c in range(len(info.cameras)):
        path = seq.depth(frame, c)
        depth = read_depth(path, info.depth_unit_mm)
        try:
            seg = segment_hands(depth, info.cameras[c], segment, frame=str(path), sides=sides)
        except SegmentationError as err:
            first_error = first_error or err
            continue
        seen = sum(float(h.score) * float(h.mask.sum()) for h in seg.located) if seg.located else float(seg.mask.sum())
        if best is None or (len(seg.blobs), seen) > best[0]:
            best = ((len(seg.blobs), seen), c, depth, seg)
        if not seg.located:  # the blob rules: camera 0 as before
            break
    if best is None:
        raise first_error
    _, c, depth, seg = best
    camera = cam if c == 0 else info.cameras[c].to(cam.device)
    return initializer(depth, camera, seg)


def initialize_sequence(root, force: bool = False, segment: Optional[SegmentConfig] = None,
                        config: InitConfig = InitConfig()) -> dict:
    """``torchhand init``: the automatic initialisation of a sequence folder's frame 0,
    written to ``init_pose.json`` with ``init_overlay.png`` (data outline green, the
    fitted model's red, its skeleton) to check it. An existing ``init_pose.json`` is
    kept unless ``force``. Returns the paths, the fit quality and the time."""
    root = Path(root)
    seq = SequenceLayout(root)
    target, overlay = seq.init_pose, seq.init_overlay
    if target.exists() and not force:
        raise FileExistsError(f"{target} exists; pass --force to replace it")
    info = read_sequence_info(root)
    scene = Scene.from_names(info.models)
    tracker = Tracker(scene, TrackerConfig())
    if any(m.kind != "hand" for m in scene.models):
        raise ValueError(f"{root}: the automatic initialisation places hands only; the scene {info.models} has "
                         "objects: write init_pose.json")
    segment = segment_of(info, segment)
    cam = info.cameras[0]
    res = automatic_init(root, info, Initializer(tracker, config), cam, segment)
    depth, seg = read_frame(root, info, 0, segment_for_search(segment, scene))
    with torch.no_grad():
        posed = scene(res.theta[None])
        model = tracker.renderer(posed.vertices, cam, normals=False).depth[0].cpu().numpy()
    iou, med = fit_quality(model, depth)
    img = depth_to_color(np.nan_to_num(depth))
    draw_mask_outline(img, model > 0, (0, 0, 255))
    draw_mask_outline(img, seg.mask, (0, 220, 0))
    draw_skeleton(img, cam.project(posed.keypoints)[0].cpu().numpy())
    write_init_pose(root, res.theta.cpu().double().numpy())
    cv2.imwrite(str(overlay), img)
    return {"init_pose": str(target), "overlay": str(overlay), "iou": iou, "depth_residual_mm": med,
            "seconds": res.seconds, "cost": res.cost}
