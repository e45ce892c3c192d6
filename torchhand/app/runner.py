"""The runner: tracks sequence folders (datasets/README.md layout) and writes the results.

Reading sequence folders (:mod:`torchhand.app.frames`), batching same-scene sequences,
re-initialising badly fitting frames, and writing theta, keypoints, MOTION files, logs
and overlays (:mod:`torchhand.app.outputs`) live here; the tracker itself takes depth
frames and returns results (:mod:`torchhand.tracking.tracker`). The options of a run are
one :class:`~torchhand.app.options.TrackOptions`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence

import numpy as np
import torch
from tqdm import tqdm

from torchhand.app.frames import FrameReader, hand_sides, pose_fit, segment_for_search, segment_of
from torchhand.app.initialize import first_pose
from torchhand.app.options import NAIL_DETECTIONS, NAIL_SCORE, NAIL_SOURCES, REINIT_IOU, TrackOptions
from torchhand.app.outputs import TrackedSequence, failed, write_sequence
from torchhand.data.layout import SequenceError, SequenceInfo, SequenceLayout, read_depth, read_rgb, read_sequence_info
from torchhand.model.scene import Scene
from torchhand.scoring.metrics import FitCheck
from torchhand.tracking.energies import EnergyTerm, parse_energy
from torchhand.tracking.initialization import Initializer
from torchhand.tracking.segmentation import SegmentConfig, SegmentationError, segment_hands
from torchhand.tracking.tracker import FrameResult, Tracker, TrackerConfig

__all__ = ["track_sequences", "TrackOptions", "output_names", "energy_needs", "REINIT_IOU", "NAIL_SCORE",
           "NAIL_DETECTIONS", "NAIL_SOURCES"]

#: What a term reads besides its images (``EnergyTerm.needs``), by the term's type: the
#: nail term reads the colour views' nail detections (``salient.json`` or the shipped
#: detector, which the runner provides: ``"salient"``).
def track_sequences(roots: Sequence, out, options: TrackOptions = TrackOptions(), *,
                    names: Optional[Sequence[str]] = None, init_poses: Optional[Sequence] = None,
                    make_terms: Optional[Callable[[], List[EnergyTerm]]] = None, force: bool = False,
                    progress: bool = True, on_frames: Optional[Callable[[int], None]] = None) -> List[dict]:
    """Track sequence folders with ``options`` and write their results.

    Sequences with the same models are solved as one batch, frame by frame; the
    tracking never reads ``gt/``. Every sequence's ``<out>/<name>/`` receives the
    :class:`~torchhand.data.layout.OutputLayout`: the ``gt/`` layout (per-frame ``valid``
    flags in meta.json), ``motion/<Model>.MOTION`` per model, ``track_log.json`` with
    every frame's fit quality measured without ground truth (``iou``: the silhouette IoU
    of the rendered fitted models and the data the tracker saw; ``depth_residual_mm``:
    the median |model - data| on their overlap) and the run's settings
    (:meth:`TrackOptions.settings`, against which ``--resume`` checks a finished
    folder), and what the options add (overlays, renders, vertices). The outputs go to a
    hidden ``<out>/.<name>.partial-*`` folder renamed when complete.

    Re-initialisation: a frame (after the first) whose silhouette IoU is below
    ``options.reinit_iou`` gets the automatic initialisation's global search (seeded
    from the frame's segmented blobs and around the pose just tracked, as Ballan et al.
    re-initialise by sampling around the previous pose); its pose replaces the tracked
    one when it fits the frame better, the tracking goes on from it, and the frame is
    flagged (``reinitialized`` and a note in ``track_log.json``, the count in the
    summary). Scenes with objects are not re-initialised (the search places hands).

    A sequence whose first frame cannot be read (missing, not 16-bit, values that look
    like metres), or of which no frame could be tracked, fails: nothing is written for
    it and its summary says why; the others are tracked.

    ``names``: the output folder names (default: each ``sequence.json``'s name, made
    unique). ``init_poses``: one theta of frame 0 per sequence (the scene's DoF) instead
    of ``init_pose.json`` (a caller that found the first pose itself, e.g. ``torchhand
    rig``). ``make_terms`` builds custom energy terms per batch (default: from
    ``options.config.energy``). ``force``: replace non-empty output folders.
    ``on_frames(n)`` is called as frames are tracked (progress of a caller that runs many
    calls, :mod:`torchhand.app.scaleout`).

    Returns:
        one dict per sequence, in the order of ``roots``: ``sequence``, ``status``
        ("ok" or "failed"), ``error`` (failed), ``frames``, ``out``,
        ``seconds_per_frame``, ``flagged_frames``, ``reinitialized_frames``, ``mean_iou``,
        ``median_depth_residual_mm``.
    """
    terms = _terms(options.config, make_terms)  # the first batch's; the terms declare what the run reads
    run = _Run.of(roots, out, options, names, init_poses, make_terms, force, progress, on_frames, energy_needs(terms))
    summaries, groups = run.check()
    for (models, V), members in groups.items():
        summaries.update(_track_batch(run, list(models), V, members, terms))
        terms = None
    return [summaries[k] for k in range(len(run.roots))]


def _terms(config: TrackerConfig, make_terms: Optional[Callable[[], List[EnergyTerm]]]) -> List[EnergyTerm]:
    """A batch's energy terms: ``make_terms()``, else the tracker's own of ``config``."""
    if make_terms is not None:
        return make_terms()
    return parse_energy(config.energy, config.metric, backend=config.neighbor_backend)


def energy_needs(terms: Sequence[EnergyTerm]) -> set:
    """What energy terms read: a subset of ``{"depth", "colour", "salient"}``, each
    term's declared ``needs`` and ``detections`` (salient: the nail detections of colour
    views; the wrappers declare their term's)."""
    return {x for t in terms for x in (t.needs, t.detections) if x is not None}


@dataclass(frozen=True)
class _Run:
    """One call of :func:`track_sequences`: its sequences and what it was asked."""

    roots: List[Path]
    infos: List[SequenceInfo]
    names: List[str]
    targets: List[Path]
    options: TrackOptions
    settings: dict
    init_poses: Optional[Sequence]
    make_terms: Optional[Callable[[], List[EnergyTerm]]]
    force: bool
    progress: bool
    on_frames: Optional[Callable[[int], None]]
    needs: frozenset

    @classmethod
    def of(cls, roots, out, options: TrackOptions, names, init_poses, make_terms, force, progress, on_frames,
           needs: set) -> "_Run":
        roots = [Path(r) for r in roots]
        infos = [read_sequence_info(r) for r in roots]
        if options.models is not None:
            infos = [dataclasses.replace(i, models=list(options.models)) for i in infos]
        names = list(names) if names is not None else output_names(infos)
        if init_poses is not None and len(init_poses) != len(roots):
            raise ValueError(f"init_poses: one theta per sequence, got {len(init_poses)} for {len(roots)} sequences")
        if len(names) != len(roots) or len(set(names)) != len(names):
            raise ValueError(f"names: one distinct output name per sequence, got {names} for {len(roots)} sequences")
        targets = [Path(out) / n for n in names]
        for t in targets:
            if t.exists() and any(t.iterdir()) and not force:
                raise FileExistsError(f"{t} is not empty; choose another --out or pass --force")
        return cls(roots, infos, names, targets, options, options.settings(), init_poses, make_terms, force,
                   progress, on_frames, frozenset(needs))

    def check(self) -> tuple:
        """({sequence: failed summary}, {(models, views): sequences}) of the sequences
        that cannot be tracked with this energy and the batches of the others; a
        sequence whose first frame is unusable fails before any tracking."""
        needs = self.needs
        summaries: Dict[int, dict] = {}
        groups: Dict[tuple, List[int]] = {}
        for k, info in enumerate(self.infos):
            why = _unusable(self.roots[k], info, needs, self.options.segment)
            if not why:
                try:
                    seq = SequenceLayout(self.roots[k])
                    for c in range(len(info.cameras)):
                        if "depth" in needs:
                            read_depth(seq.depth(0, c), info.depth_unit_mm)
                        if "colour" in needs:
                            read_rgb(seq.rgb(0, c))
                except SequenceError as err:
                    why = f"{err}"
            if why:
                summaries[k] = failed(self.names[k], why)
            else:
                groups.setdefault((tuple(info.models), len(info.cameras)), []).append(k)
        return summaries, groups


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
    return ""


def output_names(infos: Sequence[SequenceInfo]) -> List[str]:
    """The output folder name of each sequence: its ``sequence.json`` name, with the
    sequence's index appended to every name when two are equal."""
    names = [i.name for i in infos]
    if len(set(names)) != len(names):
        names = [f"{i.name}_{k}" for k, i in enumerate(infos)]
    return names


def _track_batch(run: _Run, models: list, V: int, members: List[int],
                 terms: Optional[List[EnergyTerm]]) -> Dict[int, dict]:
    """Track one batch of same-scene sequences (``members``) and write them."""
    opt, needs = run.options, run.needs
    scene = Scene.from_names(models, device=opt.device)
    if terms is None and run.make_terms is not None:
        terms = run.make_terms()
    tracker = Tracker(scene, opt.config, terms)  # terms None: the tracker's own of the config
    cams = [run.infos[k].cameras[0].to(opt.device) for k in members]
    rigs = [[c.to(opt.device) for c in run.infos[k].cameras] for k in members] if V > 1 else None
    segs = [segment_of(run.infos[k], opt.segment) for k in members]
    hands_only = all(m.kind == "hand" for m in scene.models)
    # the automatic initialisation reads the depth view that sees the hands best, the
    # re-initialisation and the fit check camera 0's
    initializer = Initializer(tracker, opt.init_config) if hands_only and "depth" in needs else None
    init, init_notes = _starts(run, members, scene, initializer, cams, segs)
    n_frames = max(run.infos[k].frames for k in members)
    frames = FrameReader([run.roots[k] for k in members], [run.infos[k] for k in members], n_frames, segs,
                         keep_masks=opt.viz, views=V, depth="depth" in needs, colour="colour" in needs,
                         nails=opt.nails if "salient" in needs else None)
    refit = _Refit(tracker, scene, cams, frames, initializer if opt.reinit_iou > 0 else None, opt.reinit_iou,
                   [segment_for_search(segs[i], scene) for i in range(len(members))])
    bar = tqdm(total=n_frames * len(members), desc=f"track {'+'.join(models)}", unit="frame",
               disable=not run.progress)
    results: List[FrameResult] = []
    tracked = tracker.track(frames.depth_frames() if "depth" in needs else None, rigs or cams, init, revise=refit,
                            colours=frames.colour_frames() if "colour" in needs else None)
    for f, res in enumerate(tracked):
        for i, err in enumerate(frames.record(f).errors):
            if err:
                res.notes[i] = f"{err}; previous pose kept"
            elif f == 0 and init_notes[i]:
                res.notes[i] = init_notes[i]
        for i, note in enumerate(res.notes):
            if note:
                tqdm.write(f"{run.names[members[i]]} frame {f}: {note}")
        results.append(res)
        bar.update(len(members))
        if run.on_frames is not None:
            run.on_frames(sum(f < run.infos[k].frames for k in members))
    bar.close()
    written = {}
    for i, k in enumerate(members):
        N = run.infos[k].frames
        seq = TrackedSequence(run.names[k], run.roots[k], run.infos[k], rigs[i] if rigs else [cams[i]], i,
                              len(members), results, [refit.quality[f][i] for f in range(N)],
                              [refit.reinitialized[f][i] for f in range(N)], partial(frames.masks_of, i),
                              "depth" in needs)
        written[k] = write_sequence(run.targets[k], seq=seq, scene=scene, renderer=tracker.renderer, options=opt,
                                    settings=run.settings, force=run.force)
    return written


def _starts(run: _Run, members: List[int], scene: Scene, initializer: Optional[Initializer], cams: list,
            segs: list) -> tuple:
    """((B, D) theta of frame 0 of each sequence of a batch, the notes of their first frame)."""
    starts, notes = [], []
    for i, k in enumerate(members):
        if run.init_poses is not None:
            th, note = np.asarray(run.init_poses[k], np.float64), ""
            if th.shape != (scene.num_dofs,):
                raise ValueError(f"init_poses[{k}]: {th.size} values, the scene {list(run.infos[k].models)} has "
                                 f"{scene.num_dofs} DoF")
        else:
            th, note = first_pose(run.roots[k], run.infos[k], scene, initializer, cams[i], segs[i])
        starts.append(th)
        notes.append(note)
        if note:
            tqdm.write(f"{run.names[k]}: {note}")
    return torch.as_tensor(np.stack(starts), dtype=torch.float32, device=run.options.device), notes


class _Refit:
    """After each frame: every sequence's fit quality (``quality[f][i]``: silhouette IoU,
    median depth residual) and, below ``reinit_iou``, its re-initialisation
    (``reinitialized[f][i]``); see :func:`track_sequences`. The frame's depth maps and
    segmentations are the reader's record of the frame."""

    def __init__(self, tracker: Tracker, scene: Scene, cams: list, frames: FrameReader,
                 initializer: Optional[Initializer], reinit_iou: float, search: List[SegmentConfig]):
        self.tracker, self.scene, self.cams, self.frames = tracker, scene, cams, frames
        self.initializer, self.reinit_iou, self.search = initializer, reinit_iou, search
        pre = tracker.config.preprocess
        self.near, self.far = pre.near, pre.far
        self.quality: List[List[tuple]] = []
        self.reinitialized: List[List[bool]] = []

    def fit(self, theta: torch.Tensor, i: int, data: np.ndarray, seg=None) -> FitCheck:
        return pose_fit(self.scene, self.tracker.renderer, theta, self.cams[i], data, seg)

    def __call__(self, f: int, res: FrameResult) -> FrameResult:
        record = self.frames.record(f)
        theta, notes = res.theta.clone(), list(res.notes)
        quality, flags = [], []
        for i, depth in enumerate(record.depths):
            if depth is None or not bool(res.valid[i]):
                quality.append(FitCheck(float("nan"), float("nan")))
                flags.append(False)
                continue
            seg = record.segmentations[i]
            if seg is not None and seg.note and not notes[i]:
                notes[i] = seg.note
            data = np.where(np.isnan(depth) | ((depth >= self.near) & (depth <= self.far)), depth, 0)
            q, flag = self.fit(theta[i], i, data, seg), False
            if self.initializer is not None and f > 0 and (q.iou < self.reinit_iou or q.flagged):
                q, flag = self._reinitialise(i, depth, seg, data, theta, q, notes)
            quality.append(q)
            flags.append(flag)
        self.quality.append(quality)
        self.reinitialized.append(flags)
        return res._replace(theta=theta, notes=notes)

    def _reinitialise(self, i: int, depth: np.ndarray, seg, data: np.ndarray, theta: torch.Tensor, q: FitCheck,
                      notes: list) -> tuple:
        """The search around problem ``i``'s pose (seeded from the localiser's joints where
        it found them); its pose replaces ``theta[i]`` when it fits better: for a failed
        fit check, one that passes it or explains more of the localiser's hand and lies
        less off it; else a higher silhouette IoU.
        Returns (fit check, re-initialised)."""
        why = (f"fit check (keypoints {q.keypoint_mm:.0f} mm from the localiser's, {q.explained:.2f} of its hand "
               f"explained, {q.off_hand:.2f} off it)" if q.flagged else f"silhouette IoU {q.iou:.2f}")
        try:
            if seg is None:
                seg = segment_hands(depth, self.cams[i], self.search[i], sides=hand_sides(self.scene))
            new = self.initializer(depth, self.cams[i], seg, around=theta[i])
        except (SegmentationError, ValueError) as err:
            notes[i] = f"{why}; no re-initialisation: {err}"
            return q, False
        q2 = self.fit(new.theta.to(theta), i, data, seg)
        by_check = q.flagged and np.isfinite(q.explained) and np.isfinite(q2.explained)
        better = ((not q2.flagged, q2.explained - q2.off_hand) > (False, q.explained - q.off_hand) if by_check
                  else q2.iou > q.iou)
        if better:
            what = (f"hand explained {q.explained:.2f} -> {q2.explained:.2f}, off it {q.off_hand:.2f} -> "
                    f"{q2.off_hand:.2f}" if by_check else f"silhouette IoU {q.iou:.2f} -> {q2.iou:.2f}")
            notes[i] = f"re-initialised ({why}): {what} ({new.seconds:.1f} s)"
            theta[i] = new.theta.to(theta)
            return q2, True
        return q, False
