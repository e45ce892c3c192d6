"""The frames of sequence folders as the tracker takes them: read, segmented and (for
colour views) given their nail detections, once per frame, for a batch of sequences;
and the helpers the runner, ``torchhand init`` and ``torchhand calibrate`` share (one
frame read and segmented, the segmentation of a sequence, the fit of a pose)."""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path
from typing import Dict, Iterator, List, NamedTuple, Optional, Sequence

import cv2
import numpy as np
import torch

from torchhand.app.options import NAIL_DETECTIONS, NAIL_SCORE
from torchhand.data.layout import SequenceError, SequenceInfo, SequenceLayout, read_depth, read_rgb
from torchhand.geometry.camera import project_points
from torchhand.geometry.render import RenderResult, window_map
from torchhand.model.joints21 import is_hand, scene_standard_joints
from torchhand.model.scene import Scene
from torchhand.salient import SalientDetector
from torchhand.scoring.metrics import FitCheck, fit_check, surrounded
from torchhand.tracking.preprocess import ColourView
from torchhand.tracking.segmentation import Segmentation, SegmentConfig, SegmentationError, segment_hands

__all__ = ["FrameRecord", "FrameReader", "unpack_masks", "read_frame", "read_rig_frame", "read_colour", "segment_of",
           "segment_for_search", "pose_fit", "render_pose", "whole_maps", "hand_hints", "hand_sides", "model_sides"]


class FrameRecord(NamedTuple):
    """One frame of a batch of sequences, one entry per sequence.

    index: the frame. views: what the tracker's depth frames hold per problem, a depth
    map (H, W) mm (one camera) or the list of every view's (a rig); None past a
    sequence's end, where unreadable or where the segmentation found no hand.
    depths: camera 0's depth map (H, W) mm or None. colours: the colour views
    (:class:`ColourView`, a list of them on a rig) or None. segmentations: camera 0's
    segmentation or None. errors: why a sequence has no frame ("" when it has one).
    """

    index: int
    views: list
    depths: List[Optional[np.ndarray]]
    colours: list
    segmentations: List[Optional[Segmentation]]
    errors: List[str]


class FrameReader:
    """The frames of a batch of sequences, each read and segmented once.

    :meth:`record` reads frame ``f`` of every sequence (depth maps of ``views`` cameras
    when ``depth``, colour views when ``colour``, with the protocol's occluders,
    ``occluders/``, as pixels whose features are ignored) and keeps the last frame read,
    so that the tracker's depth and colour iterators (:meth:`depth_frames`,
    :meth:`colour_frames`), the re-initialisation and the runner each ask for the frame
    they are at and read it once. ``nails``: the source of colour views' nail detections
    (:data:`~torchhand.app.options.NAIL_SOURCES`; None: none read). With ``keep_masks``
    every frame's segmentation masks are kept (packed) for the overlays (:meth:`masks_of`).
    ``first``: frame ``f`` of the reader is frame ``first + f`` of the sequences (a
    chunk of a sequence; records, masks and ``n_frames`` count from it). ``hints[i]``:
    where sequence ``i``'s hands are expected, one tuple per camera (:func:`hand_hints`
    of the previous frame's fit, set by the runner; empty: none), passed to the
    segmentation of each view.
    """

    def __init__(self, roots: List[Path], infos: List[SequenceInfo], n_frames: int,
                 segments: List[Optional[SegmentConfig]], keep_masks: bool = False, views: int = 1,
                 depth: bool = True, colour: bool = False, nails: Optional[str] = None, first: int = 0):
        self.roots, self.infos, self.n_frames, self.segments = roots, infos, n_frames, segments
        self.first = first
        self.layouts = [SequenceLayout(r) for r in roots]
        self.keep_masks, self.views, self.depth, self.colour = keep_masks, views, depth, colour
        self.nails, self._nail_detector = nails, None
        self.masks: List[Dict[int, Optional[tuple]]] = [{} for _ in roots]  # per sequence, per frame
        self.hints: List[list] = [[] for _ in roots]
        self._last: Optional[FrameRecord] = None
        self._detections: Dict[tuple, Optional[list]] = {}

    def record(self, f: int) -> FrameRecord:
        """Frame ``f`` of every sequence (read once; the last frame read is kept)."""
        if self._last is None or self._last.index != f:
            self._last = self._read(f)
        return self._last

    def _read(self, f: int) -> FrameRecord:
        views, depths, colours, segmentations, errors = [], [], [], [], []
        g = self.first + f  # the sequences' frame
        for i, (root, info, seg) in enumerate(zip(self.roots, self.infos, self.segments)):
            depth, view, colour, s, err = None, None, None, None, ""
            if g < info.frames:
                try:
                    if self.depth and self.views == 1:
                        depth, s = read_frame(root, info, g, seg, self.hints[i][0] if self.hints[i] else ())
                        view = depth
                    elif self.depth:
                        view, s = read_rig_frame(root, info, g, seg, self.hints[i])
                        depth = view[0]
                    if self.colour:
                        colour = [self._colour_view(i, c, g) for c in range(self.views)]
                        colour = colour[0] if self.views == 1 else colour
                except (SequenceError, SegmentationError) as e:  # the tracker keeps the previous pose
                    depth, view, colour, err = None, None, None, str(e)
                if self.keep_masks:
                    self.masks[i][f] = None if s is None else (np.packbits(s.mask), np.packbits(s.cut))
            views.append(view)
            depths.append(depth)
            colours.append(colour)
            segmentations.append(s)
            errors.append(err)
        return FrameRecord(f, views, depths, colours, segmentations, errors)

    def _colour_view(self, i: int, camera: int, f: int) -> ColourView:
        """Frame ``f`` of a colour view, with its nail detections when the energy reads
        them (``nails``): the camera's ``salient.json`` where it has one (``"auto"``),
        else the shipped colour nail detector's (:data:`NAIL_SCORE`, at most
        :data:`NAIL_DETECTIONS`)."""
        detections = self._salient(i, camera) if self.nails == "auto" else None
        view = read_colour(self.layouts[i], camera, f, detections)
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
            path = self.layouts[i].salient(camera)
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
            yield self.record(f).views

    def colour_frames(self) -> Iterator[list]:
        for f in range(self.n_frames):
            yield self.record(f).colours

    def masks_of(self, i: int, f: int, shape: tuple) -> Optional[tuple]:
        """(hands' mask, forearm cut) of sequence ``i``'s frame ``f`` (of the reader), or None."""
        return unpack_masks(self.masks[i].get(f), shape)


def unpack_masks(packed: Optional[tuple], shape: tuple) -> Optional[tuple]:
    """The (hands' mask, forearm cut) boolean images a :class:`FrameReader` kept packed."""
    if packed is None:
        return None
    n = shape[0] * shape[1]
    return tuple(np.unpackbits(p, count=n).reshape(shape).astype(bool) for p in packed)


def read_colour(seq: SequenceLayout, camera: int, f: int, detections: Optional[list] = None) -> ColourView:
    """A colour view as the tracker takes it: the image, the protocol's ``occluders/``
    mask of the frame where the folder has one (ignored pixels), and the frame's salient
    point detections."""
    image = read_rgb(seq.rgb(f, camera))
    occluders = seq.occluders(f, camera)
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


def read_frame(root: Path, info: SequenceInfo, f: int, segment: Optional[SegmentConfig], hints: tuple = ()):
    """(depth mm of camera 0 with only the hands' pixels when segmented, segmentation or
    None); ``hints``: the segmentation's (:func:`hand_hints`)."""
    seq = SequenceLayout(root)
    path = seq.depth(f)
    depth = read_depth(path, info.depth_unit_mm)
    if segment is None:
        return depth, None
    rgb_path = seq.rgb(f)
    rgb = read_rgb(rgb_path) if segment.mode == "skin" and rgb_path.is_file() else None
    seg = segment_hands(depth, info.cameras[0], segment, frame=str(path), rgb=rgb,
                        sides=model_sides(tuple(info.models)), hints=hints)
    return seg.apply(depth), seg


def read_rig_frame(root: Path, info: SequenceInfo, f: int, segment: Optional[SegmentConfig], hints: Sequence = ()
                   ) -> tuple:
    """(depth mm of every view, camera 0's segmentation or None) of a camera rig's frame
    (``hints``: each camera's, :func:`hand_hints`; empty: none).

    Segmented, each view keeps its hands' pixels; a view in which no hand is found is
    all unknown (NaN), so it costs nothing, and the frame fails only when no view finds
    a hand."""
    seq = SequenceLayout(root)
    views = [read_depth(seq.depth(f, c), info.depth_unit_mm) for c in range(len(info.cameras))]
    if segment is None:
        return views, None
    out, segs, errors = [], [], []
    for c, depth in enumerate(views):
        try:
            sg = segment_hands(depth, info.cameras[c], segment, frame=str(seq.depth(f, c)),
                               sides=model_sides(tuple(info.models)), hints=hints[c] if c < len(hints) else ())
            out.append(sg.apply(depth))
            segs.append(sg)
        except SegmentationError as err:
            out.append(np.full(depth.shape, np.nan, np.float32))
            segs.append(None)
            errors.append(str(err))
    if all(sg is None for sg in segs):
        raise SegmentationError(f"frame {f}: no view finds a hand ({errors[0]})")
    return out, segs[0]


def segment_for_search(segment: Optional[SegmentConfig], scene: Scene) -> SegmentConfig:
    """The segmentation that seeds a search: the sequence's, else the automatic one with
    as many hands as the scene has."""
    if segment is not None:
        return segment
    return SegmentConfig(hands=max(1, sum(m.kind == "hand" for m in scene.models)))


def segment_of(info: SequenceInfo, given: Optional[SegmentConfig]) -> Optional[SegmentConfig]:
    """The segmentation of a sequence: the one given, else its ``sequence.json``'s."""
    if given is not None:
        return None if given.mode == "none" else given
    if info.segmentation:
        try:
            cfg = SegmentConfig.from_dict(info.segmentation)
        except (TypeError, ValueError) as err:
            raise SequenceError(f"{info.name}: sequence.json segmentation: {err}") from None
        if cfg.localiser and not Path(cfg.localiser).is_file():
            raise SequenceError(f"{info.name}: sequence.json segmentation: its localiser {cfg.localiser} is gone "
                                "(give --segment auto, with --localiser ONNX for another one)")
        return cfg
    return None


def render_pose(scene: Scene, renderer, theta: torch.Tensor, cam) -> tuple:
    """(the scene posed at one pose (D,), its render in ``cam``: the maps of the models'
    pixel box only (``RenderResult.origin`` says where it lies; :func:`whole_maps` pastes
    it into the image), no normals)."""
    with torch.no_grad():
        posed = scene(theta[None])
        return posed, renderer(posed.vertices, cam, normals=False, crop=True)


def whole_maps(render: RenderResult, shape: Optional[tuple]) -> tuple:
    """(depth (H, W) mm, 0 elsewhere; model ids (H, W), -1 elsewhere) of a render's first
    problem as numpy images of ``shape`` (H, W), from a cropped render or a whole one
    (``shape`` may then be None)."""
    ids, depth = render.model_id[0], render.depth[0]
    if render.origin is not None:
        if shape is None:
            raise ValueError("a cropped render (RenderResult.origin set) needs the image's shape (H, W)")
        box = (0, shape[0], 0, shape[1])
        ids, depth = window_map(ids, render.origin, box, -1), window_map(depth, render.origin, box, 0)
    return depth.cpu().numpy(), ids.cpu().numpy()


def hand_hints(scene: Scene, rendered: RenderResult, shape: Optional[tuple]) -> tuple:
    """Where a render (:func:`render_pose`'s, cropped; ``shape``: the image's (H, W);
    None only for a whole render) shows each hand of the scene: one (H, W) depth map (mm, 0
    elsewhere) per hand model, scene order, left out where a hand is not in view; the
    localiser's hints for the next frame
    (:meth:`~torchhand.salient.localiser.HandLocaliser.locate`)."""
    depth, ids = whole_maps(rendered, shape)
    hints = []
    for k, m in enumerate(scene.models):
        if is_hand(m):
            own = ids == k
            if own.any():
                hints.append(np.where(own, depth, 0).astype(np.float32))
    return tuple(hints)


def pose_fit(scene: Scene, renderer, theta: torch.Tensor, cam, data: np.ndarray,
             segmentation: Optional[Segmentation] = None, rendered: Optional[tuple] = None) -> FitCheck:
    """The fit check of a scene at one pose (D,) against data (H, W) mm: the silhouette
    IoU and median depth residual, how surrounded its hands are by the measured surface
    (the segmentation's measured depth, else ``data``), and, where the frame was
    segmented by the hand localiser, its independent measures
    (:func:`~torchhand.scoring.metrics.fit_check`; each hand model is compared with the
    located hand of its side, else the one in its place; with the blob rules deciding
    after a localiser found too little, its classes still count). ``rendered``: the
    pose's :func:`render_pose`, where the caller has it."""
    posed, render = render_pose(scene, renderer, theta, cam) if rendered is None else rendered
    model, ids = whole_maps(render, (cam.height, cam.width))
    seg = segmentation
    surround = _surround(scene, ids, model, data if seg is None or seg.measured is None else seg.measured,
                         float(cam.fx))
    if seg is None or seg.labels is None:
        return fit_check(model, data, surround=surround)
    with torch.no_grad():
        joints = scene_standard_joints(scene, posed)[0]
        T = cam.T_cw.to(joints)
        uv = project_points(joints @ T[:3, :3].T + T[:3, 3], cam.K.to(joints)).cpu().numpy()
    hands = [m for m in scene.models if is_hand(m)]
    located_uv = np.full((21 * len(hands), 2), np.nan)
    conf, z = np.zeros(21 * len(hands)), np.full(21 * len(hands), np.nan)
    for j, m in enumerate(hands):
        loc = next((h for h in seg.located if h.side == m.side), None)
        if loc is None and j < len(seg.located):
            loc = seg.located[j]
        if loc is not None:
            located_uv[21 * j:21 * j + 21], conf[21 * j:21 * j + 21] = loc.uv, loc.confidence
            z[21 * j:21 * j + 21] = loc.z
    return fit_check(model, data, seg.mask, seg.labels, uv, located_uv, conf, z, float(cam.fx), surround=surround)


def _surround(scene: Scene, ids: np.ndarray, model: np.ndarray, measured: np.ndarray, focal: float) -> list:
    """Each hand model's :func:`~torchhand.scoring.metrics.surrounded` in a render's model
    ids and depth (:func:`whole_maps`), scene order (NaN: not in view)."""
    return [surrounded(ids == k, model, ids >= 0, measured, focal) for k, m in enumerate(scene.models) if is_hand(m)]


def hand_sides(scene: Scene) -> tuple:
    """The sides (``"left"`` / ``"right"``) of a scene's hands, in scene order, that the
    localiser looks for."""
    return tuple(m.side for m in scene.models if m.kind == "hand" and m.side)


@lru_cache(maxsize=None)
def model_sides(names: tuple) -> tuple:
    """:func:`hand_sides` of the scene of these model names (read once per process)."""
    return hand_sides(Scene.from_names(list(names)))
