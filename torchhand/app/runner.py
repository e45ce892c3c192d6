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
from typing import Callable, Dict, List, NamedTuple, Optional, Sequence, Tuple

import numpy as np
import torch
from tqdm import tqdm

from torchhand.app.frames import (FrameReader, hand_hints, hand_sides, pose_fit, render_pose, segment_for_search,
                                  segment_of, unpack_masks)
from torchhand.app.initialize import first_pose
from torchhand.app.options import NAIL_DETECTIONS, NAIL_SCORE, NAIL_SOURCES, REINIT_IOU, TrackOptions
from torchhand.app.outputs import TrackedSequence, failed, write_sequence
from torchhand.core.check import skip_checks
from torchhand.data.layout import SequenceError, SequenceInfo, SequenceLayout, read_depth, read_rgb, read_sequence_info
from torchhand.model.scene import Scene
from torchhand.scoring.metrics import FitCheck, FitCheckLimits
from torchhand.tracking.energies import EnergyTerm, parse_energy
from torchhand.tracking.initialization import Initializer
from torchhand.tracking.segmentation import SegmentConfig, SegmentationError, segment_hands
from torchhand.tracking.tracker import FrameResult, Tracker, TrackerConfig

__all__ = ["track_sequences", "track_chunk", "write_chunks", "TrackedChunk", "TrackOptions", "output_names",
           "energy_needs", "REINIT_IOU", "NAIL_SCORE", "NAIL_DETECTIONS", "NAIL_SOURCES"]

#: A frame's fit gives the next frame's localiser hints (``_Refit``) when it passes its
#: fit check with at least this silhouette IoU.
HINT_MIN_IOU = 0.5


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
        targets = [] if out is None else [Path(out) / n for n in names]  # None: a chunk, written by its caller
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


class _Tracked(NamedTuple):
    """What :func:`_track_frames` tracked: the batch's scene, tracker and cameras, the
    frame results and the fit checks and re-initialisations (``refit``) of each frame,
    and the frame reader (its masks)."""

    scene: Scene
    tracker: Tracker
    cams: list
    rigs: Optional[list]
    results: List[FrameResult]
    refit: "_Refit"
    frames: FrameReader


def _track_frames(run: _Run, models: list, V: int, members: List[int], terms: Optional[List[EnergyTerm]],
                  window: Optional[Tuple[int, int]] = None) -> _Tracked:
    """Track one batch of same-scene sequences (``members``): all their frames, or the
    frames ``window`` = [start, stop) of a single sequence (frame ``start``
    initialised automatically unless it is 0)."""
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
    first = 0 if window is None else window[0]
    init, init_notes = _starts(run, members, scene, initializer, cams, segs, first)
    n_frames = max(run.infos[k].frames for k in members) if window is None else window[1] - first
    frames = FrameReader([run.roots[k] for k in members], [run.infos[k] for k in members], n_frames, segs,
                         keep_masks=opt.viz, views=V, depth="depth" in needs, colour="colour" in needs,
                         nails=opt.nails if "salient" in needs else None, first=first)
    refit = _Refit(tracker, scene, cams, frames, initializer if opt.reinit_iou > 0 else None, opt.reinit_iou,
                   [segment_for_search(segs[i], scene) for i in range(len(members))], rigs)
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
                tqdm.write(f"{run.names[members[i]]} frame {first + f}: {note}")
        results.append(res)
        bar.update(len(members))
        if run.on_frames is not None:
            run.on_frames(sum(first + f < run.infos[k].frames for k in members))
    bar.close()
    return _Tracked(scene, tracker, cams, rigs, results, refit, frames)


def _track_batch(run: _Run, models: list, V: int, members: List[int],
                 terms: Optional[List[EnergyTerm]]) -> Dict[int, dict]:
    """Track one batch of same-scene sequences (``members``) and write them."""
    t = _track_frames(run, models, V, members, terms)
    written = {}
    for i, k in enumerate(members):
        N = run.infos[k].frames
        seq = TrackedSequence(run.names[k], run.roots[k], run.infos[k], t.rigs[i] if t.rigs else [t.cams[i]], i,
                              len(members), t.results, [t.refit.quality[f][i] for f in range(N)],
                              [t.refit.reinitialized[f][i] for f in range(N)], partial(t.frames.masks_of, i),
                              "depth" in run.needs)
        written[k] = write_sequence(run.targets[k], seq=seq, scene=t.scene, renderer=t.tracker.renderer,
                                    options=run.options, settings=run.settings, force=run.force)
    return written


class TrackedChunk(NamedTuple):
    """Frames ``first``..``first + len(results) - 1`` of one sequence, tracked by one task
    of a chunked run (:func:`track_chunk`; picklable): per frame its result (a batch of
    one), fit check and re-initialisation flag, and its packed masks (overlays only)."""

    first: int
    results: List[FrameResult]
    quality: List[tuple]
    reinitialized: List[bool]
    masks: Dict[int, Optional[tuple]]


def track_chunk(root, options: TrackOptions, start: int, stop: int, keep: int, *,
                on_frames: Optional[Callable[[int], None]] = None) -> TrackedChunk:
    """Track frames [``start``, ``stop``) of one sequence folder from the automatic
    initialisation of frame ``start`` (``init_pose.json`` where ``start`` is 0) and
    return frames [``keep``, ``stop``): the frames before ``keep`` are the overlap with
    the previous chunk, tracked only to reach ``keep`` with a settled pose. Nothing is
    written (:func:`write_chunks` writes the sequence). Raises ``ValueError`` naming the
    folder when the sequence cannot be tracked with these options."""
    if not 0 <= start <= keep < stop:
        raise ValueError(f"track_chunk: expected 0 <= start <= keep < stop, got {start}, {keep}, {stop}")
    terms = _terms(options.config, None)
    run = _Run.of([root], None, options, None, None, None, False, False, on_frames, energy_needs(terms))
    summaries, groups = run.check()
    if summaries:
        raise ValueError(summaries[0]["error"])
    if stop > run.infos[0].frames:
        raise ValueError(f"{root}: frames [{start}, {stop}) asked, sequence.json has {run.infos[0].frames}")
    (models, V), = groups
    t = _track_frames(run, list(models), V, [0], terms, window=(start, stop))
    k = keep - start
    results = t.results[k:]
    if start > 0:  # the chunk's start, said on its first kept frame (the overlap's frames are not written)
        r = results[0]
        said = f"first frame of a chunk tracked from frame {start} ({t.results[0].notes[0]})"
        results[0] = r._replace(notes=[f"{said}; {r.notes[0]}" if r.notes[0] else said])
    return TrackedChunk(keep, results, [t.refit.quality[f][0] for f in range(k, stop - start)],
                        [t.refit.reinitialized[f][0] for f in range(k, stop - start)],
                        {start + f: m for f, m in t.frames.masks[0].items() if f >= k})


def write_chunks(root, target, options: TrackOptions, chunks: Sequence[TrackedChunk], settings: dict,
                 force: bool = False, name: Optional[str] = None) -> dict:
    """Write a sequence tracked in chunks (:func:`track_chunk`, which together cover
    every frame once, in order) into ``target`` as :func:`track_sequences` writes a
    sequence tracked in one pass; returns its summary."""
    root = Path(root)
    info = read_sequence_info(root)
    if options.models is not None:
        info = dataclasses.replace(info, models=list(options.models))
    chunks = sorted(chunks, key=lambda c: c.first)
    covered = [c.first + j for c in chunks for j in range(len(c.results))]
    if covered != list(range(info.frames)):
        raise ValueError(f"{root}: the chunks cover frames {covered[:3]}...{covered[-3:]}, not 0..{info.frames - 1} "
                         "once each")
    scene = Scene.from_names(info.models, device=options.device)
    renderer = Tracker(scene, options.config).renderer if options.write_render else None  # renders only
    cams = [c.to(options.device) for c in info.cameras]
    masks = {f: m for c in chunks for f, m in c.masks.items()}
    seq = TrackedSequence(name or info.name, root, info, cams if len(cams) > 1 else cams[:1], 0, 1,
                          [r for c in chunks for r in c.results], [q for c in chunks for q in c.quality],
                          [x for c in chunks for x in c.reinitialized],
                          lambda f, shape: unpack_masks(masks.get(f), shape),
                          "depth" in energy_needs(_terms(options.config, None)))
    return write_sequence(Path(target), seq=seq, scene=scene, renderer=renderer, options=options, settings=settings,
                          force=force)


def _starts(run: _Run, members: List[int], scene: Scene, initializer: Optional[Initializer], cams: list,
            segs: list, first: int = 0) -> tuple:
    """((B, D) theta of frame ``first`` of each sequence of a batch, the notes of that frame)."""
    starts, notes = [], []
    for i, k in enumerate(members):
        if run.init_poses is not None and first == 0:
            th, note = np.asarray(run.init_poses[k], np.float64), ""
            if th.shape != (scene.num_dofs,):
                raise ValueError(f"init_poses[{k}]: {th.size} values, the scene {list(run.infos[k].models)} has "
                                 f"{scene.num_dofs} DoF")
        else:
            th, note = first_pose(run.roots[k], run.infos[k], scene, initializer, cams[i], segs[i], frame=first)
        starts.append(th)
        notes.append(note)
        if note:
            tqdm.write(f"{run.names[k]}: {note}")
    return torch.as_tensor(np.stack(starts), dtype=torch.float32, device=run.options.device), notes


def _failed(q: FitCheck, limits: FitCheckLimits = FitCheckLimits()) -> str:
    """What a flagged fit check crossed, in words (only the measures past their limit)."""
    parts = []
    if np.isfinite(q.surrounded) and q.surrounded > limits.surrounded:
        parts.append(f"{q.surrounded:.2f} of a hand's surround is measured surface at its depth")
    if np.isfinite(q.keypoint_mm) and q.keypoint_mm > limits.keypoint_mm:
        parts.append(f"joints {q.keypoint_mm:.0f} mm from the localiser's")
    if np.isfinite(q.explained) and q.explained < limits.explained:
        parts.append(f"{q.explained:.2f} of the localiser's hand explained")
    if np.isfinite(q.off_hand) and q.off_hand > limits.off_hand:
        parts.append(f"{q.off_hand:.2f} of the model off its hand")
    return ", ".join(parts) or "the localiser found none of the tracked hands' pixels"


class _Refit:
    """After each frame: every sequence's fit quality (``quality[f][i]``: silhouette IoU,
    median depth residual) and, below ``reinit_iou``, its re-initialisation
    (``reinitialized[f][i]``); see :func:`track_sequences`. The frame's depth maps and
    segmentations are the reader's record of the frame. A fit that passes its check
    (and has a silhouette IoU of :data:`HINT_MIN_IOU` or more) gives the localiser of
    the next frame its hands as hints, in every view of a rig (``rigs``;
    :func:`~torchhand.app.frames.hand_hints`); a failed one takes them back, so a wrong
    track does not hold the localiser to it."""

    def __init__(self, tracker: Tracker, scene: Scene, cams: list, frames: FrameReader,
                 initializer: Optional[Initializer], reinit_iou: float, search: List[SegmentConfig],
                 rigs: Optional[list] = None):
        self.tracker, self.scene, self.cams, self.frames, self.rigs = tracker, scene, cams, frames, rigs
        self.initializer, self.reinit_iou, self.search = initializer, reinit_iou, search
        pre = tracker.config.preprocess
        self.near, self.far = pre.near, pre.far
        self.quality: List[List[tuple]] = []
        self.reinitialized: List[List[bool]] = []

    def _hints(self, i: int, rendered: tuple) -> list:
        """Problem ``i``'s hints for the next frame, one tuple per camera, from the fit's
        (posed scene, camera 0's render): the rig's other views' from a render of their
        hands' box."""
        posed, render = rendered
        cam0 = self.cams[i]
        hints = [hand_hints(self.scene, render, (cam0.height, cam0.width))]
        if self.rigs is not None:
            with torch.no_grad(), skip_checks():
                for cam in self.rigs[i][1:]:
                    view = self.tracker.renderer(posed.vertices, cam, normals=False, crop=True)
                    hints.append(hand_hints(self.scene, view, (cam.height, cam.width)))
        return hints

    def fit(self, theta: torch.Tensor, i: int, data: np.ndarray, seg=None) -> tuple:
        """(fit check, (posed scene, render)) of problem ``i``'s pose."""
        rendered = render_pose(self.scene, self.tracker.renderer, theta, self.cams[i])
        return pose_fit(self.scene, self.tracker.renderer, theta, self.cams[i], data, seg, rendered), rendered

    def __call__(self, f: int, res: FrameResult) -> FrameResult:
        record = self.frames.record(f)
        theta, notes = res.theta.clone(), list(res.notes)
        quality, flags = [], []
        for i, depth in enumerate(record.depths):
            if depth is None or not bool(res.valid[i]):
                quality.append(FitCheck(float("nan"), float("nan")))
                flags.append(False)
                self.frames.hints[i] = []  # no fit, no hint: a hand that left is not looked for there
                continue
            seg = record.segmentations[i]
            if seg is not None and seg.note and not notes[i]:
                notes[i] = seg.note
            data = np.where(np.isnan(depth) | ((depth >= self.near) & (depth <= self.far)), depth, 0)
            (q, rendered), flag = self.fit(theta[i], i, data, seg), False
            if self.initializer is not None and f > 0 and (q.iou < self.reinit_iou or q.flagged):
                q, flag, rendered = self._reinitialise(i, depth, seg, data, theta, q, rendered, notes)
            good = seg is not None and seg.labels is not None and not q.flagged and q.iou >= HINT_MIN_IOU
            self.frames.hints[i] = self._hints(i, rendered) if good else []
            quality.append(q)
            flags.append(flag)
        self.quality.append(quality)
        self.reinitialized.append(flags)
        return res._replace(theta=theta, notes=notes)

    def _reinitialise(self, i: int, depth: np.ndarray, seg, data: np.ndarray, theta: torch.Tensor, q: FitCheck,
                      rendered, notes: list) -> tuple:
        """The search around problem ``i``'s pose (seeded from the localiser's joints where
        it found them); its pose replaces ``theta[i]`` when it fits better than the
        current pose judged on the same evidence (a frame without a segmentation is
        segmented for the search, and the current pose scored again with it): for a failed
        fit check, one that passes it or explains more of the localiser's hand and lies
        less off it (with the localiser's evidence), else one that passes it with a
        silhouette IoU of :data:`HINT_MIN_IOU` or the current one's; for a low IoU, a
        higher silhouette IoU.
        Returns (fit check, re-initialised, render of the pose kept)."""
        why = f"fit check: {_failed(q)}" if q.flagged else f"silhouette IoU {q.iou:.2f}"
        try:
            now = q
            if seg is None:
                seg = segment_hands(depth, self.cams[i], self.search[i], sides=hand_sides(self.scene))
                now = self.fit(theta[i], i, data, seg)[0]
            new = self.initializer(depth, self.cams[i], seg, around=theta[i])
        except (SegmentationError, ValueError) as err:
            notes[i] = f"{why}; no re-initialisation: {err}"
            return q, False, rendered
        q2, rendered2 = self.fit(new.theta.to(theta), i, data, seg)
        by_check = q.flagged and np.isfinite(now.explained) and np.isfinite(q2.explained)
        if by_check:
            better = (not q2.flagged, q2.explained - q2.off_hand) > (not now.flagged, now.explained - now.off_hand)
        elif q.flagged:  # no localiser evidence to compare (the surround flagged it): a pose that passes and fits
            better = not q2.flagged and (now.flagged or q2.iou > now.iou) and q2.iou >= min(now.iou, HINT_MIN_IOU)
        else:
            better = q2.iou > now.iou
        if better:
            what = (f"hand explained {now.explained:.2f} -> {q2.explained:.2f}, off it {now.off_hand:.2f} -> "
                    f"{q2.off_hand:.2f}" if by_check else f"silhouette IoU {now.iou:.2f} -> {q2.iou:.2f}"
                    + (", passes the fit check" if q.flagged else ""))
            notes[i] = f"re-initialised ({why}): {what} ({new.seconds:.1f} s)"
            theta[i] = new.theta.to(theta)
            return q2, True, rendered2
        return q, False, rendered
