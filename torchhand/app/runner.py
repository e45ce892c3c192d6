"""The runner: tracks sequence folders (datasets/README.md layout) and writes the results.

Reading sequence folders, batching same-scene sequences, and writing theta, keypoints,
MOTION files, logs and overlays live here; the tracker itself takes depth frames and
returns results (:mod:`torchhand.tracking.tracker`).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path
from typing import Callable, Dict, Iterator, List, Optional, Sequence

import cv2
import numpy as np
import torch
from tqdm import tqdm

from torchhand.app.drawing import (GT_COLOR, OBJECT_COLOR, depth_range, depth_to_color, draw_colorbar, draw_legend,
                                   draw_mask_outline, draw_models, draw_skeleton, mosaic, write_video)
from torchhand.data.layout import (Poses, SequenceError, SequenceInfo, camera_dir, frame_name, read_depth,
                                   read_init_pose, read_poses, read_rgb, read_sequence_info, write_depth, write_poses)
from torchhand.io.assets import THESIS_MODEL_NAMES, save_assets
from torchhand.io.output_dir import commit_dir, partial_dir
from torchhand.io.thesis import write_motion
from torchhand.model.motion import theta_to_motion
from torchhand.model.articulated import ArticulatedModel, load_model
from torchhand.model.scene import Scene, SceneOutput
from torchhand.salient import SalientDetector
from torchhand.scoring.metrics import fit_quality
from torchhand.tracking.calibration import CalibrationConfig, calibrate_hand
from torchhand.tracking.energies import EnergyTerm, parse_energy
from torchhand.tracking.initialization import InitConfig, Initializer, InitResult
from torchhand.tracking.preprocess import ColourView
from torchhand.tracking.segmentation import Segmentation, SegmentConfig, SegmentationError, segment_hands
from torchhand.tracking.tracker import FrameResult, Tracker, TrackerConfig

__all__ = ["track_sequences", "track_settings", "output_names", "automatic_init", "initialize_sequence",
           "calibrate_sequence", "REINIT_IOU", "NAIL_SCORE", "NAIL_DETECTIONS", "NAIL_SOURCES"]

#: A frame whose fitted hands overlap their data with a silhouette IoU below this is
#: re-initialised (0.5: a tracked hand scores 0.8-0.95 on renders and 0.7-0.9 on the real
#: frames; a hand that was lost, or that came back into view elsewhere, scores below 0.3).
REINIT_IOU = 0.5

#: Nail detections of a colour view without ``salient.json``: the shipped colour
#: detector's peaks above this confidence, at most ten per view (two hands' nails).
#: 0.07 is its precision-0.95 point on held-out renders (recall 0.87; at 0.2: precision
#: 0.99, recall 0.75; ``eval/eval_salient.py --modality colour``, docs/salient.md).
NAIL_SCORE = 0.07
NAIL_DETECTIONS = 10
#: Where the nail detections of colour views come from: ``"auto"``, a camera's
#: ``salient.json`` where it has one and the shipped detector elsewhere; ``"detector"``,
#: the shipped detector everywhere.
NAIL_SOURCES = ("auto", "detector")


def track_sequences(roots: Sequence, out, config: TrackerConfig = TrackerConfig(), device: str = "cpu",
                    viz: bool = False, force: bool = False, progress: bool = True,
                    make_terms: Optional[Callable[[], List[EnergyTerm]]] = None,
                    segment: Optional[SegmentConfig] = None, write_render: bool = False,
                    reinit_iou: float = REINIT_IOU, init_config: InitConfig = InitConfig(),
                    models: Optional[Sequence[str]] = None, names: Optional[Sequence[str]] = None,
                    on_frames: Optional[Callable[[int], None]] = None, init_poses: Optional[Sequence] = None,
                    write_vertices: bool = False, nails: str = "auto") -> List[dict]:
    """Track sequence folders and write their results.

    Sequences with the same models are solved as one batch, frame by frame; the
    tracking never reads ``gt/``. For every sequence ``<out>/<name>/`` receives the
    ``gt/`` layout (theta.npy, keypoints_3d.npy, keypoints_2d.npy, meta.json with
    per-frame ``valid`` flags), ``motion/<Model>.MOTION`` per model (thesis format: row
    0 is the rigging pose, row k+1 is frame k), ``track_log.json``, and with ``viz``
    overlay PNGs and an MP4 (drawn after the sequence is tracked; where the sequence
    folder has ``gt/``, its skeletons are drawn beside the tracked ones).
    ``make_terms`` builds custom energy terms per batch (default: from ``config.energy``).
    ``models``: the scene of every sequence instead of its ``sequence.json``'s (shipped
    names or model files, e.g. a hand resized by ``torchhand calibrate``; the same
    number of models of the same kinds, so that ``init_pose.json`` still fits).
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

    Re-initialisation: a frame (after the first) whose silhouette IoU is below
    ``reinit_iou`` (0 disables it) gets the automatic initialisation's global search
    (:class:`~torchhand.tracking.initialization.Initializer`, seeded from the frame's
    segmented blobs and around the pose just tracked, as Ballan et al. re-initialise
    by sampling around the previous pose when the fit is bad); its pose replaces the
    tracked one when it fits the frame better, the tracking goes on from it, and the
    frame is flagged (``reinitialized`` and a note in ``track_log.json``, the count in
    the summary). Scenes with objects are not re-initialised (the search places hands).

    A sequence whose first depth frame cannot be read (missing, not 16-bit, values
    that look like metres), or of which no frame could be tracked, fails: nothing is
    written for it and its summary says why; the others are tracked.

    Each sequence's outputs are written to a hidden ``<out>/.<name>.partial-*`` folder
    and renamed to ``<out>/<name>`` when complete, so a crash never leaves a folder
    that looks finished; ``track_log.json`` records the settings of the run
    (:func:`track_settings`), against which ``--resume`` checks a finished folder.
    ``names``: the output folder names (default: each ``sequence.json``'s name, made
    unique); ``on_frames(n)`` is called as frames are tracked (progress of a caller
    that runs many calls, :mod:`torchhand.app.scaleout`). ``init_poses``: one theta of
    frame 0 per sequence (the scene's DoF) instead of ``init_pose.json`` (a caller that
    found the first pose itself, e.g. ``torchhand rig`` with a model it just built).
    ``write_vertices``: also ``vertices/<model>.npy`` per model, its posed vertices per
    frame in camera 0's coordinates ((N, V, 3) float32 mm), for scoring any model against
    ground-truth vertices. ``nails``: the source of the colour views' nail detections
    (:data:`NAIL_SOURCES`).

    Returns:
        one dict per sequence, in the order of ``roots``: ``sequence``, ``status``
        ("ok" or "failed"), ``error`` (failed), ``frames``, ``out``,
        ``seconds_per_frame``, ``flagged_frames``, ``reinitialized_frames``, ``mean_iou``,
        ``median_depth_residual_mm``.
    """
    roots = [Path(r) for r in roots]
    infos = [read_sequence_info(r) for r in roots]
    if models is not None:
        infos = [dataclasses.replace(i, models=list(models)) for i in infos]
    names = list(names) if names is not None else output_names(infos)
    if init_poses is not None and len(init_poses) != len(roots):
        raise ValueError(f"init_poses: one theta per sequence, got {len(init_poses)} for {len(roots)} sequences")
    if len(names) != len(roots) or len(set(names)) != len(names):
        raise ValueError(f"names: one distinct output name per sequence, got {names} for {len(roots)} sequences")
    if nails not in NAIL_SOURCES:
        raise ValueError(f"nails must be one of {NAIL_SOURCES}, got {nails!r}")
    settings = track_settings(config, segment, reinit_iou, init_config, models, device, nails)
    out = Path(out)
    targets = [out / n for n in names]
    for t in targets:
        if t.exists() and any(t.iterdir()) and not force:
            raise FileExistsError(f"{t} is not empty; choose another --out or pass --force")
    summaries: Dict[int, dict] = {}
    groups: Dict[tuple, List[int]] = {}
    needs = energy_needs(config, make_terms)
    for k, info in enumerate(infos):
        V = len(info.cameras)
        why = _unusable(roots[k], info, needs, segment)
        if why:
            summaries[k] = _failed(names[k], why)
            continue
        try:  # a sequence whose first frame is unusable fails before any tracking
            for c in range(V):
                if "depth" in needs:
                    read_depth(camera_dir(roots[k], c) / "depth" / frame_name(0), info.depth_unit_mm)
                if "colour" in needs:
                    read_rgb(camera_dir(roots[k], c) / "rgb" / frame_name(0))
        except SequenceError as err:
            summaries[k] = _failed(names[k], f"{err}")
            continue
        groups.setdefault((tuple(info.models), V), []).append(k)
    for (models, V), members in groups.items():
        scene = Scene.from_names(list(models), device=device)
        tracker = Tracker(scene, config, make_terms() if make_terms is not None else None)
        cams = [infos[k].cameras[0].to(device) for k in members]
        rigs = [[c.to(device) for c in infos[k].cameras] for k in members] if V > 1 else None
        segs = [_segment_of(infos[k], segment) if V == 1 else None for k in members]
        hands_only = all(m.kind == "hand" for m in scene.models)
        # the automatic initialisation and re-initialisation read one depth view
        initializer = Initializer(tracker, init_config) if hands_only and V == 1 and "depth" in needs else None
        starts, init_notes = [], []
        for i, k in enumerate(members):
            if init_poses is not None:
                th, note = np.asarray(init_poses[k], np.float64), ""
                if th.shape != (scene.num_dofs,):
                    raise ValueError(f"init_poses[{k}]: {th.size} values, the scene {list(models)} has "
                                     f"{scene.num_dofs} DoF")
            else:
                th, note = _init_pose(roots[k], infos[k], scene, models, initializer, cams[i], segs[i])
            starts.append(th)
            init_notes.append(note)
            if note:
                tqdm.write(f"{names[k]}: {note}")
        init = torch.as_tensor(np.stack(starts), dtype=torch.float32, device=device)
        n_frames = max(infos[k].frames for k in members)
        bar = tqdm(total=n_frames * len(members), desc=f"track {'+'.join(models)}", unit="frame", disable=not progress)
        results: List[FrameResult] = []
        frames = _Frames([roots[k] for k in members], [infos[k] for k in members], n_frames, segs, keep_masks=viz,
                         views=V, depth="depth" in needs, colour="colour" in needs,
                         nails=nails if "salient" in needs else None)
        refit = _Refit(tracker, scene, cams, frames, initializer if reinit_iou > 0 else None, reinit_iou,
                       [_segment_for_search(segs[i], scene) for i in range(len(members))])
        read_errors = frames.errors
        tracked = tracker.track(frames.depth_frames() if "depth" in needs else None, rigs or cams, init, revise=refit,
                                colours=frames.colour_frames() if "colour" in needs else None)
        for f, res in enumerate(tracked):
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
            if on_frames is not None:
                on_frames(sum(f < infos[k].frames for k in members))
        bar.close()
        for i, k in enumerate(members):
            summaries[k] = _write_sequence(targets[k], roots[k], infos[k], names[k], scene,
                                           rigs[i] if rigs else [cams[i]], results, i, len(members), settings, viz,
                                           force, frames, refit, tracker.renderer, write_render, write_vertices)
    return [summaries[k] for k in range(len(roots))]


def energy_needs(config: TrackerConfig, make_terms: Optional[Callable[[], List[EnergyTerm]]] = None) -> set:
    """What the run's energy terms read: a subset of ``{"depth", "colour", "salient"}``
    (salient: the nail detections of colour views, ``salient.json``)."""
    terms = make_terms() if make_terms is not None else parse_energy(config.energy, config.metric)
    return {t.needs for t in terms if t.needs is not None} | {"salient" for t in terms if t.name == "nails"}


def _unusable(root: Path, info: SequenceInfo, needs: set, segment: Optional[SegmentConfig]) -> str:
    """Why a sequence cannot be tracked with this energy ("" when it can)."""
    if "depth" in needs and not info.has_depth:
        return (f"{root}: colour views only (sequence.json has_depth false, no depth/), but the energy's terms "
                f"read depth: track colour views with the colour terms (--energy E+C+O), or synthesise the views "
                f"with --depth for an RGB-D rig")
    if "colour" in needs and not info.has_rgb:
        return f"{root}: the energy's colour terms (E, O) read rgb/ images, and sequence.json says it has none"
    sizes = [(c.width, c.height) for c in info.cameras]
    if len(set(sizes)) > 1:
        k = next(k for k, size in enumerate(sizes) if size != sizes[0])
        return (f"{root}: sequence.json camera {k} is {sizes[k][0]}x{sizes[k][1]} px, camera 0 is {sizes[0][0]}x"
                f"{sizes[0][1]}: every view of a rig needs the same image size")
    if len(info.cameras) > 1 and (segment is not None or info.segmentation is not None):
        return (f"{root}: a segmentation (--segment or sequence.json) reads one depth view; a camera rig "
                f"({len(info.cameras)} views) is tracked unsegmented")
    return ""


def output_names(infos: Sequence[SequenceInfo]) -> List[str]:
    """The output folder name of each sequence: its ``sequence.json`` name, with the
    sequence's index appended to every name when two are equal."""
    names = [i.name for i in infos]
    if len(set(names)) != len(names):
        names = [f"{i.name}_{k}" for k, i in enumerate(infos)]
    return names


def track_settings(config: TrackerConfig, segment: Optional[SegmentConfig], reinit_iou: float,
                   init_config: InitConfig, models: Optional[Sequence[str]], device: str = "cpu",
                   nails: str = "auto") -> dict:
    """Everything of a run that changes its tracked poses, as JSON (``track_log.json``
    ``settings``; ``--resume`` refuses a folder tracked with other settings)."""
    return json.loads(json.dumps({
        "command": "track", "tracker": dataclasses.asdict(config),
        "segment": None if segment is None else dataclasses.asdict(segment), "reinit_iou": reinit_iou,
        "init": dataclasses.asdict(init_config), "models": None if models is None else list(models),
        "device": str(device), "nails": nails}))


def _failed(name: str, error: str) -> dict:
    return {"sequence": name, "status": "failed", "error": error, "frames": 0, "out": None,
            "seconds_per_frame": float("nan"), "flagged_frames": 0, "reinitialized_frames": 0}


def _init_pose(root: Path, info: SequenceInfo, scene: Scene, models: tuple, initializer: Optional[Initializer],
               cam, segment: Optional[SegmentConfig]) -> tuple:
    """(theta of frame 0, note): ``init_pose.json`` when the folder has it, else the
    automatic initialisation on frame 0 (:mod:`torchhand.tracking.initialization`)."""
    if (root / "init_pose.json").is_file():
        th = read_init_pose(root)
        if th.shape != (scene.num_dofs,):
            raise ValueError(f"{root / 'init_pose.json'}: theta has {th.size} values, the scene "
                             f"{list(models)} has {scene.num_dofs} DoF")
        return th, ""
    if initializer is None:
        raise ValueError(f"{root}: no init_pose.json, and the automatic initialisation places hands only, in one "
                         f"depth view (the scene {list(models)}, {len(info.cameras)} view(s), this energy): write "
                         "init_pose.json")
    res = automatic_init(root, info, initializer, cam, segment)
    return res.theta.cpu().double().numpy(), (f"no init_pose.json: initialised automatically (depth discrepancy "
                                             f"{res.cost:.2f}, {res.seconds:.1f} s)")


def automatic_init(root: Path, info: SequenceInfo, initializer: Initializer, cam,
                   segment: Optional[SegmentConfig]) -> InitResult:
    """The automatic initialisation of a sequence's frame 0 (its segmentation, or the
    automatic one with as many hands as the scene has)."""
    segment = _segment_for_search(segment, initializer.tracker.scene)
    depth = read_depth(camera_dir(root, 0) / "depth" / frame_name(0), info.depth_unit_mm)
    seg = segment_hands(depth, info.cameras[0], segment, frame=str(camera_dir(root, 0) / "depth" / frame_name(0)))
    return initializer(depth, cam, seg)


def initialize_sequence(root, force: bool = False, segment: Optional[SegmentConfig] = None,
                        config: InitConfig = InitConfig()) -> dict:
    """``torchhand init``: the automatic initialisation of a sequence folder's frame 0,
    written to ``init_pose.json`` with ``init_overlay.png`` (data outline green, the
    fitted model's red, its skeleton) to check it. An existing ``init_pose.json`` is
    kept unless ``force``. Returns the paths, the fit quality and the time."""
    root = Path(root)
    target, overlay = root / "init_pose.json", root / "init_overlay.png"
    if target.exists() and not force:
        raise FileExistsError(f"{target} exists; pass --force to replace it")
    info = read_sequence_info(root)
    scene = Scene.from_names(info.models)
    tracker = Tracker(scene, TrackerConfig())
    if any(m.kind != "hand" for m in scene.models):
        raise ValueError(f"{root}: the automatic initialisation places hands only; the scene {info.models} has "
                         "objects: write init_pose.json")
    segment = _segment_of(info, segment)
    cam = info.cameras[0]
    res = automatic_init(root, info, Initializer(tracker, config), cam, segment)
    depth, seg = _read_frame(root, info, 0, _segment_for_search(segment, scene))
    with torch.no_grad():
        posed = scene(res.theta[None])
        model = tracker.renderer(posed.vertices, cam, normals=False).depth[0].cpu().numpy()
    iou, med = fit_quality(model, depth)
    img = depth_to_color(np.nan_to_num(depth))
    draw_mask_outline(img, model > 0, (0, 0, 255))
    draw_mask_outline(img, seg.mask, (0, 220, 0))
    draw_skeleton(img, cam.project(posed.keypoints)[0].cpu().numpy())
    target.write_text(json.dumps({"theta": [float(x) for x in res.theta.cpu().double().numpy()]}))
    cv2.imwrite(str(overlay), img)
    return {"init_pose": str(target), "overlay": str(overlay), "iou": iou, "depth_residual_mm": med,
            "seconds": res.seconds, "cost": res.cost}


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
    initializer = Initializer(tracker)
    search = _segment_for_search(_segment_of(info, segment), scene)
    search = dataclasses.replace(search, hands=1)
    cam = info.cameras[0]
    picks = sorted(set(np.linspace(0, info.frames - 1, min(frames, info.frames)).round().astype(int).tolist()))
    depths, thetas, used, skipped = [], [], [], {}
    for f in tqdm(picks, desc="calibrate: initialise", unit="frame", disable=not progress):
        try:
            depth, seg = _read_frame(root, info, f, search)
        except (SequenceError, SegmentationError) as err:
            skipped[f] = str(err)
            continue
        depths.append(depth)
        thetas.append(initializer(depth, cam, seg).theta)
        used.append(f)
    if not used:
        raise ValueError(f"{root}: no frame of {picks} has a segmented hand: {skipped}")
    theta = torch.stack(thetas)
    res = calibrate_hand(tracker, depths, [cam] * len(used), theta, config, name=out.stem)
    before = [_fit(scene, tracker.renderer, theta[k], cam, depths[k]) for k in range(len(used))]
    sized = Scene([ArticulatedModel(res.assets)], names=scene.names)
    after = [_fit(sized, tracker.renderer, res.theta[k], cam, depths[k]) for k in range(len(used))]
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


def _fit(scene: Scene, renderer, theta: torch.Tensor, cam, data: np.ndarray) -> tuple:
    """(silhouette IoU, median depth residual) of a scene at one pose against data."""
    with torch.no_grad():
        model = renderer(scene(theta[None]).vertices, cam, normals=False).depth[0].cpu().numpy()
    return fit_quality(model, data)


def _segment_for_search(segment: Optional[SegmentConfig], scene: Scene) -> SegmentConfig:
    """The segmentation that seeds a search: the sequence's, else the automatic one with
    as many hands as the scene has."""
    if segment is not None:
        return segment
    return SegmentConfig(hands=max(1, sum(m.kind == "hand" for m in scene.models)))


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
    rgb_path = camera_dir(root, 0) / "rgb" / frame_name(f)
    rgb = read_rgb(rgb_path) if segment.mode == "skin" and rgb_path.is_file() else None
    seg = segment_hands(depth, info.cameras[0], segment, frame=str(path), rgb=rgb)
    return seg.apply(depth), seg


class _Frames:
    """The frames of a batch of sequences, each read and segmented once.

    :meth:`depth_frames` and :meth:`colour_frames` yield, per frame, what the tracker
    sees of every sequence, read in step (a frame is read once for both): a depth map
    (with one camera) or the depth maps of every view (a rig of ``views``), and the
    colour images (with the protocol's occluders, ``occluders/``, as pixels whose
    features are ignored); None past a sequence's end, where unreadable or where the
    segmentation found no hand (the reason goes to ``errors``, one list per frame).
    ``depths`` and ``segmentations`` hold the current frame's (camera 0's depth); with
    ``keep_masks`` every frame's segmentation masks are kept (packed) for the overlays."""

    def __init__(self, roots: List[Path], infos: List[SequenceInfo], n_frames: int,
                 segments: List[Optional[SegmentConfig]], keep_masks: bool = False, views: int = 1,
                 depth: bool = True, colour: bool = False, nails: Optional[str] = None):
        self.roots, self.infos, self.n_frames, self.segments = roots, infos, n_frames, segments
        self.keep_masks, self.views, self.depth, self.colour = keep_masks, views, depth, colour
        self.nails, self._nail_detector = nails, None  # a NAIL_SOURCES entry; None: no nails read
        self.errors: List[List[str]] = []
        self.depths: List[Optional[np.ndarray]] = []
        self.segmentations: List[Optional[Segmentation]] = []
        self.masks: List[List[Optional[tuple]]] = [[] for _ in roots]  # per sequence, per frame
        self._frame, self._views, self._colours = -1, [], []
        self._detections: Dict[tuple, Optional[list]] = {}

    def _load(self, f: int) -> None:
        if f == self._frame:
            return
        depths, views, colours, segs, why = [], [], [], [], []
        for i, (root, info, seg) in enumerate(zip(self.roots, self.infos, self.segments)):
            depth, view, colour, s, err = None, None, None, None, ""
            if f < info.frames:
                try:
                    if self.depth and self.views == 1:
                        depth, s = _read_frame(root, info, f, seg)
                        view = depth
                    elif self.depth:
                        view = [read_depth(camera_dir(root, c) / "depth" / frame_name(f), info.depth_unit_mm)
                                for c in range(self.views)]
                        depth = view[0]
                    if self.colour:
                        colour = [self._colour_view(i, c, f) for c in range(self.views)]
                        colour = colour[0] if self.views == 1 else colour
                except (SequenceError, SegmentationError) as e:  # the tracker keeps the previous pose
                    depth, view, colour, err = None, None, None, str(e)
                if self.keep_masks:
                    self.masks[i].append(None if s is None else (np.packbits(s.mask), np.packbits(s.cut)))
            depths.append(depth)
            views.append(view)
            colours.append(colour)
            segs.append(s)
            why.append(err)
        self.errors.append(why)
        self.depths, self.segmentations, self._views, self._colours = depths, segs, views, colours
        self._frame = f

    def _colour_view(self, i: int, camera: int, f: int) -> ColourView:
        """Frame ``f`` of a colour view, with its nail detections when the energy reads
        them (``nails``): the camera's ``salient.json`` where it has one (``"auto"``),
        else the shipped colour nail detector's (:data:`NAIL_SCORE`, at most
        :data:`NAIL_DETECTIONS`)."""
        detections = self._salient(i, camera) if self.nails == "auto" else None
        view = _read_colour(self.roots[i], camera, f, detections)
        if self.nails is not None and detections is None:
            if self._nail_detector is None:  # loaded once, where a view first needs it
                self._nail_detector = SalientDetector.load_onnx(modality="colour", threshold=NAIL_SCORE,
                                                                max_detections=NAIL_DETECTIONS)
            found = self._nail_detector.detect(view.image)
            view = view._replace(salient=found.uv.numpy().astype(np.float64))
        return view

    def _salient(self, i: int, camera: int) -> Optional[list]:
        """The salient point detections of sequence ``i``'s camera (``salient.json``: per
        frame a list of (u, v) px), read once; None without the file."""
        key = (i, camera)
        if key not in self._detections:
            path = camera_dir(self.roots[i], camera) / "salient.json"
            frames = None
            if path.is_file():
                try:
                    frames = json.loads(path.read_text())["frames"]
                    if len(frames) != self.infos[i].frames:
                        raise ValueError(f"{len(frames)} frames, sequence.json has {self.infos[i].frames}")
                except (ValueError, KeyError, TypeError) as err:
                    raise SequenceError(f"{path}: expected {{'frames': [[[u, v], ...] per frame]}} ({err})") from None
            self._detections[key] = frames
        return self._detections[key]

    def depth_frames(self) -> Iterator[list]:
        for f in range(self.n_frames):
            self._load(f)
            yield self._views

    def colour_frames(self) -> Iterator[list]:
        for f in range(self.n_frames):
            self._load(f)
            yield self._colours

    def masks_of(self, i: int, f: int, shape: tuple) -> Optional[tuple]:
        """(hands' mask, forearm cut) of sequence ``i``'s frame ``f``, or None."""
        packed = self.masks[i][f] if f < len(self.masks[i]) else None
        if packed is None:
            return None
        n = shape[0] * shape[1]
        return tuple(np.unpackbits(p, count=n).reshape(shape).astype(bool) for p in packed)


def _read_colour(root: Path, camera: int, f: int, detections: Optional[list] = None) -> ColourView:
    """A colour view as the tracker takes it: the image, the protocol's ``occluders/``
    mask of the frame where the folder has one (ignored pixels), and the frame's salient
    point detections."""
    image = read_rgb(camera_dir(root, camera) / "rgb" / frame_name(f))
    occluders = camera_dir(root, camera) / "occluders" / frame_name(f)
    mask = None
    if occluders.is_file():
        mask = cv2.imread(str(occluders), cv2.IMREAD_GRAYSCALE)
        if mask is None or mask.shape != image.shape[:2]:
            raise SequenceError(f"{occluders}: expected an 8-bit mask of the image's size {image.shape[:2]}")
        mask = mask > 0
    salient = None
    if detections is not None:
        salient = np.asarray(detections[f], np.float64).reshape(-1, 2) if len(detections[f]) else np.zeros((0, 2))
    return ColourView(image, mask, salient)


class _Refit:
    """After each frame: every sequence's fit quality (``quality[f][i]``: silhouette IoU,
    median depth residual) and, below ``reinit_iou``, its re-initialisation
    (``reinitialized[f][i]``); see :func:`track_sequences`."""

    def __init__(self, tracker: Tracker, scene: Scene, cams: list, frames: _Frames,
                 initializer: Optional[Initializer], reinit_iou: float, search: List[SegmentConfig]):
        self.tracker, self.scene, self.cams, self.frames = tracker, scene, cams, frames
        self.initializer, self.reinit_iou, self.search = initializer, reinit_iou, search
        pre = tracker.config.preprocess
        self.near, self.far = pre.near, pre.far
        self.quality: List[List[tuple]] = []
        self.reinitialized: List[List[bool]] = []

    def fit(self, theta: torch.Tensor, i: int, data: np.ndarray) -> tuple:
        return _fit(self.scene, self.tracker.renderer, theta, self.cams[i], data)

    def __call__(self, f: int, res: FrameResult) -> FrameResult:
        theta, notes = res.theta.clone(), list(res.notes)
        quality, flags = [], []
        for i, depth in enumerate(self.frames.depths):
            if depth is None or not bool(res.valid[i]):
                quality.append((float("nan"), float("nan")))
                flags.append(False)
                continue
            data = np.where(np.isnan(depth) | ((depth >= self.near) & (depth <= self.far)), depth, 0)
            q, flag = self.fit(theta[i], i, data), False
            if self.initializer is not None and f > 0 and q[0] < self.reinit_iou:
                seg = self.frames.segmentations[i]
                try:
                    if seg is None:
                        seg = segment_hands(depth, self.cams[i], self.search[i])
                    new = self.initializer(depth, self.cams[i], seg, around=theta[i])
                except (SegmentationError, ValueError) as err:
                    notes[i] = f"silhouette IoU {q[0]:.2f}; no re-initialisation: {err}"
                else:
                    q2 = self.fit(new.theta.to(theta), i, data)
                    if q2[0] > q[0]:
                        notes[i] = (f"re-initialised: silhouette IoU {q[0]:.2f} -> {q2[0]:.2f} "
                                    f"({new.seconds:.1f} s)")
                        theta[i], q, flag = new.theta.to(theta), q2, True
            quality.append(q)
            flags.append(flag)
        self.quality.append(quality)
        self.reinitialized.append(flags)
        return res._replace(theta=theta, notes=notes)


def _write_sequence(final: Path, root: Path, info: SequenceInfo, name: str, scene: Scene, rig: list, results,
                    i: int, batch: int, settings: dict, viz: bool, force: bool, frames: _Frames, refit: _Refit,
                    renderer=None, write_render: bool = False, write_vertices: bool = False) -> dict:
    """Write one sequence's outputs from the batch's frame results (problem ``i``), into
    a partial folder renamed to ``final`` when complete; ``rig``: the cameras tracked
    (keypoints are written in each, renders and vertices in camera 0's)."""
    cam = rig[0]
    N = info.frames
    valid = np.array([r.valid[i].item() for r in results[:N]], bool)
    if not valid.any():
        first = next((r.notes[i] for r in results[:N] if r.notes[i]), "no frame could be tracked")
        return _failed(name, f"{root}: no frame of the {N} could be tracked (frame 0: {first})")
    TH = np.stack([r.theta[i].detach().cpu().numpy() for r in results[:N]])
    with torch.no_grad():
        th = torch.as_tensor(TH, device=cam.device)
        posed = scene(th)
        kp3 = np.stack([c.to_camera(posed.keypoints).cpu().numpy() for c in rig], 1)
        kp2 = np.stack([c.project(posed.keypoints).cpu().numpy() for c in rig], 1)
    target = partial_dir(final)
    try:
        summary = _write_outputs(target, root, info, name, scene, rig, results, i, batch, settings, viz, frames,
                                 refit, renderer, write_render, TH, th, posed, kp3, kp2, valid)
        if write_vertices:
            (target / "vertices").mkdir()
            with torch.no_grad():
                verts = cam.to_camera(posed.vertices)
            for model_name in scene.names:
                np.save(target / "vertices" / f"{model_name}.npy",
                        verts[:, scene.vertex_slices[model_name]].cpu().numpy().astype(np.float32))
    except BaseException:
        shutil.rmtree(target, ignore_errors=True)
        raise
    commit_dir(target, final, force)
    summary["out"] = str(final)
    return summary


def _write_outputs(target: Path, root: Path, info: SequenceInfo, name: str, scene: Scene, rig: list, results,
                   i: int, batch: int, settings: dict, viz: bool, frames: _Frames, refit: _Refit, renderer,
                   write_render: bool, TH, th, posed, kp3, kp2, valid) -> dict:
    N, cam = info.frames, rig[0]
    write_poses(target, Poses(TH.astype(np.float64), kp3, kp2, list(scene.names), scene.dof_names,
                              scene.keypoint_names, valid))
    (target / "motion").mkdir()
    thesis_name = {v: k for k, v in THESIS_MODEL_NAMES.items()}
    for model_name, model in zip(scene.names, scene.models):
        mot = theta_to_motion(model, th[:, scene.slices[model_name]])
        rest = {b: model.rest_transforms[j].cpu().double().numpy()[None] for j, b in enumerate(model.bone_names)}
        mot = {b: np.concatenate([rest[b], m], 0) for b, m in mot.items()}
        write_motion(target / "motion" / f"{thesis_name.get(model_name, model_name)}.MOTION", mot)
    if write_render:
        _write_renders(target, posed, cam, renderer, N)
    quality = [refit.quality[f][i] for f in range(N)]
    reinit = [refit.reinitialized[f][i] for f in range(N)]
    log = [{"frame": f, "seconds": r.seconds, "iterations": int(r.iterations[i]),
            "energy": None if not np.isfinite(float(r.energy[i])) else float(r.energy[i]),
            "valid": bool(r.valid[i]), "recovered": bool(r.recovered[i]),
            "correspondences": int(r.correspondences[i]), "iou": _finite(quality[f][0]),
            "depth_residual_mm": _finite(quality[f][1]), "reinitialized": reinit[f], "notes": r.notes[i]}
           for f, r in enumerate(results[:N])]
    (target / "track_log.json").write_text(json.dumps({"sequence": name, "source": str(root),
                                                       "energy": settings["tracker"]["energy"],
                                                       "settings": settings, "frames": log}))
    if viz and len(rig) == 1 and frames.depth:
        _write_overlays(target, root, info, scene, posed, cam, frames, i)
    elif viz:
        write_view_overlays(target, root, info, scene, posed, rig)
    ious = [q[0] for q in quality if np.isfinite(q[0])]
    res = [q[1] for q in quality if np.isfinite(q[1])]
    return {"sequence": name, "status": "ok", "frames": N, "out": str(target),
            "seconds_per_frame": float(np.mean([r.seconds for r in results[:N]])) / batch,
            "flagged_frames": int((~valid).sum()), "reinitialized_frames": int(sum(reinit)), "mean_iou": float(np.mean(ious)) if ious else float("nan"),
            "median_depth_residual_mm": float(np.median(res)) if res else float("nan")}


def _finite(x: float) -> Optional[float]:
    return float(x) if np.isfinite(x) else None


def _write_renders(target: Path, posed: SceneOutput, cam, renderer, frames: int) -> None:
    """The rendered depth of the fitted models, ``render/NNNNNN.png`` (16-bit mm, 0 = none)."""
    (target / "render").mkdir()
    with torch.no_grad():
        for f in range(frames):
            write_depth(target / "render" / frame_name(f),
                        renderer(posed.vertices[f : f + 1], cam, normals=False).depth[0].cpu().numpy())


def _write_overlays(target: Path, root: Path, info: SequenceInfo, scene: Scene, posed: SceneOutput, cam,
                    frames: _Frames, i: int) -> None:
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
        segs.append(frames.masks_of(i, f, depths[-1].shape))
    near, far = depth_range(depths)
    kinds = [m.kind for m in scene.models]
    legend = [(f"{n}: tracked", None if kind == "hand" else OBJECT_COLOR) for n, kind in zip(scene.names, kinds)]
    legend += [("ground truth", GT_COLOR)] if gt is not None else []
    images = []
    with torch.no_grad():
        for f, depth in enumerate(depths):
            img = depth_to_color(depth, near, far)
            if segs[f] is not None:
                draw_mask_outline(img, segs[f][0], (0, 220, 0))
                draw_mask_outline(img, segs[f][1], (0, 0, 220))
            draw_models(img, scene, posed, f, cam, None if gt is None else gt[f, 0])
            draw_colorbar(img, near, far)
            draw_legend(img, f"frame {f}", legend)
            cv2.imwrite(str(target / "overlays" / frame_name(f)), img)
            images.append(img)
    write_video(images, target / "overlays.mp4", fps=info.fps)


def write_view_overlays(target: Path, root: Path, info: SequenceInfo, scene: Scene, posed: SceneOutput,
                        rig: list) -> None:
    """Overlays of a camera rig (or of colour views): ``overlays/cam<k>/NNNNNN.png`` per
    view, the view's colour image (its depth in false colour where it has none) with
    the tracked models and, where ``root/gt`` exists, the ground-truth skeletons; and
    ``overlays.mp4``, every view of a frame in one picture."""
    gt = _ground_truth_2d(root, scene, info.frames)
    kinds = [m.kind for m in scene.models]
    legend = [(f"{n}: tracked", None if kind == "hand" else OBJECT_COLOR) for n, kind in zip(scene.names, kinds)]
    legend += [("ground truth", GT_COLOR)] if gt is not None else []
    for c in range(len(rig)):
        (target / "overlays" / f"cam{c}").mkdir(parents=True)
    pictures = []
    with torch.no_grad():
        for f in range(info.frames):
            views = []
            for c, cam in enumerate(rig):
                try:
                    if info.has_rgb:
                        img = cv2.cvtColor(read_rgb(camera_dir(root, c) / "rgb" / frame_name(f)), cv2.COLOR_RGB2BGR)
                    else:
                        img = depth_to_color(read_depth(camera_dir(root, c) / "depth" / frame_name(f),
                                                        info.depth_unit_mm))
                except SequenceError:
                    img = np.zeros((cam.height, cam.width, 3), np.uint8)
                has_gt = gt is not None and gt.shape[1] == len(rig)
                draw_models(img, scene, posed, f, cam, gt[f, c] if has_gt else None)
                draw_legend(img, f"frame {f}, camera {c}", legend)
                cv2.imwrite(str(target / "overlays" / f"cam{c}" / frame_name(f)), img)
                views.append(img)
            pictures.append(mosaic(views))
    write_video(pictures, target / "overlays.mp4", fps=info.fps)


def _ground_truth_2d(root: Path, scene: Scene, frames: int) -> Optional[np.ndarray]:
    """(N, C, P, 2) ground-truth keypoints of every camera for the overlays, or None when
    the folder has no readable ``gt/`` of this scene (the tracking itself never reads it)."""
    try:
        gt = read_poses(root / "gt")
    except SequenceError:
        return None
    if gt.keypoint_names != scene.keypoint_names or len(gt.keypoints_2d) != frames:
        return None
    return gt.keypoints_2d
