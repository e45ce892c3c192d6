"""What a tracking run is asked for: one frozen, picklable record shared by the runner
(:func:`torchhand.app.runner.track_sequences`) and the scale-out's tasks
(:class:`torchhand.app.scaleout.TrackJob`), and the settings it writes to every
``track_log.json``."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from typing import Optional, Tuple

from torchhand.core.check import check_choice, check_number
from torchhand.tracking.initialization import InitConfig
from torchhand.tracking.segmentation import SegmentConfig
from torchhand.tracking.tracker import TrackerConfig

__all__ = ["TrackOptions", "REINIT_IOU", "NAIL_SCORE", "NAIL_DETECTIONS", "NAIL_SOURCES"]

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


@dataclass(frozen=True)
class TrackOptions:
    """The options of a tracking run, the same for every sequence of it.

    config: the tracker's (energy, iterations, solver, ...). device: the torch device.
    viz: overlay PNGs and an MP4 per sequence (drawn after the sequence is tracked;
        where the sequence folder has ``gt/``, its skeletons beside the tracked ones).
    segment: the hand segmentation of every frame (:mod:`torchhand.tracking.segmentation`;
        only the hands' pixels reach the tracker); None: what each ``sequence.json``
        says (``torchhand import`` stores it), else none. A frame without a hand-sized
        blob keeps the previous pose and is flagged, like a missing frame.
    write_render: also each frame's rendered model depth, ``render/NNNNNN.png`` (16-bit
        mm), so that the fit can be checked independently.
    write_vertices: also ``vertices/<model>.npy`` per model, its posed vertices per
        frame in camera 0's coordinates ((N, V, 3) float32 mm), for scoring any model
        against ground-truth vertices.
    reinit_iou: a frame (after the first) whose silhouette IoU is below it is
        re-initialised (0: never; see :func:`~torchhand.app.runner.track_sequences`).
    init_config: the automatic initialisation's and re-initialisation's search.
    models: the scene of every sequence instead of its ``sequence.json``'s (shipped
        names or model files, e.g. a hand resized by ``torchhand calibrate``; the same
        number of models of the same kinds, so that ``init_pose.json`` still fits).
    nails: the source of the colour views' nail detections (:data:`NAIL_SOURCES`).
    """

    config: TrackerConfig = field(default_factory=TrackerConfig)
    device: str = "cpu"
    viz: bool = False
    segment: Optional[SegmentConfig] = None
    write_render: bool = False
    write_vertices: bool = False
    reinit_iou: float = REINIT_IOU
    init_config: InitConfig = field(default_factory=InitConfig)
    models: Optional[Tuple[str, ...]] = None
    nails: str = "auto"

    def __post_init__(self) -> None:
        if not isinstance(self.config, TrackerConfig):
            raise TypeError(f"config must be a TrackerConfig, got {type(self.config).__name__}")
        check_choice(self.nails, "nails", NAIL_SOURCES)
        check_number(self.reinit_iou, "reinit_iou", low=0, inclusive=True, high=1)
        if self.models is not None:
            object.__setattr__(self, "models", tuple(str(m) for m in self.models))

    def settings(self) -> dict:
        """Everything of the run that changes its tracked poses, as JSON
        (``track_log.json`` ``settings``; ``--resume`` refuses a folder tracked with
        other settings)."""
        return json.loads(json.dumps({
            "command": "track", "tracker": dataclasses.asdict(self.config),
            "segment": None if self.segment is None else dataclasses.asdict(self.segment),
            "reinit_iou": self.reinit_iou, "init": dataclasses.asdict(self.init_config),
            "models": None if self.models is None else list(self.models), "device": str(self.device),
            "nails": self.nails}))
