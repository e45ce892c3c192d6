"""The on-disk layout of a torchhand sequence (documented in datasets/README.md).

::

    SEQ/
      sequence.json            cameras, scene, frame count, units, provenance
      init_pose.json           theta of frame 0 (the tracker starts from it)
      depth/000000.png         16-bit depth in millimetres, camera 0 (0 = no measurement)
      rgb/000000.png           optional 8-bit colour, camera 0
      cam1/depth/000000.png    further cameras (multi-view) use cam<k>/ sub-folders
      salient.json             optional, per camera folder: salient point detections
                               per frame (``torchhand synth --protocol ballan``)
      occluders/000000.png     optional, per camera folder: 255 where the protocol's
                               circles cover the colour image
      gt/                      ground truth, kept apart (a tracker must not read it)
        meta.json              models, dof_names, keypoint_names, cameras
        theta.npy              (N, D) float64 poses
        keypoints_3d.npy       (N, C, P, 3) float64 mm, in each camera's frame
        keypoints_2d.npy       (N, C, P, 2) float64 px
        keypoints21_3d.npy     optional, (N, C, 21 x hands, 3) float64 mm: the standard 21
                               joints of each hand (docs/model.md), in each camera's frame;
                               NaN or all -1 where a dataset lacks a joint
        keypoints21_2d.npy     optional, (N, C, 21 x hands, 2) float64 px; NaN or -1 where
                               a joint is not seen
        keypoints21_valid.npy  optional, (N, 21 x hands) bool: the joint is annotated in the
                               frame (a dataset's validity mask; scoring leaves the others out)
        ids/000000.png         8-bit per-pixel model id of camera 0: 0 background, k+1 model k
        salient_2d.npy         (N, C, P, 2) float64 px: the nail centres in each camera
        salient_visible.npy    (N, C, P) bool: the nail centre is seen (colour renders)
        joints_dataset_3d.npy  (imported public datasets) (N, C, J, 3) float64 mm: the
                               dataset's own J joints, in each camera's frame
        joints_dataset_2d.npy  (N, C, J, 2) float64 px: their projections
        joints_dataset.json    their names and standard-21 counterparts

A tracker's output folder uses the ``gt/`` layout (without ``ids/``), so ground
truth scored against itself gives 0, and adds its own files (:class:`OutputLayout`).

This module is the one authority for these paths: :class:`SequenceLayout`,
:class:`GroundTruthLayout` and :class:`OutputLayout` name every file of a sequence
folder and of a tracker's output folder; no other module joins them by hand.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import cv2
import numpy as np

from torchhand.core.errors import UsageError
from torchhand.geometry.camera import Camera

__all__ = [
    "FORMAT",
    "SequenceInfo",
    "SequenceError",
    "read_init_pose",
    "write_init_pose",
    "write_sequence_info",
    "read_sequence_info",
    "frame_name",
    "camera_dir",
    "write_depth",
    "read_depth",
    "write_rgb",
    "read_rgb",
    "write_poses",
    "read_poses",
    "Poses",
    "write_joints21",
    "read_joints21",
    "read_joints21_valid",
    "SequenceLayout",
    "PosesLayout",
    "GroundTruthLayout",
    "OutputLayout",
    "TRACK_SUMMARY",
]

FORMAT = "torchhand-sequence/1"


class SequenceError(UsageError):
    """A sequence folder is missing files or is inconsistent; the message names the path."""


@dataclass
class SequenceInfo:
    """Contents of ``sequence.json``.

    cameras: one :class:`Camera` per view (camera 0 is the main one).
    models: model names (shipped, in ``models/``) or paths to model ``.npz`` files,
        in the order of their slices in theta.
    frames: number of frames; fps: frame rate; depth_unit_mm: millimetres per unit of
        the stored 16-bit depth (1 for our files).
    segmentation: optional hand-segmentation settings for real scenes
        (:class:`torchhand.tracking.segmentation.SegmentConfig` as a dict), written by
        ``torchhand import``; None: the data is the hands and objects alone.
    has_depth: False for colour views only (``torchhand synth --views N`` without
        ``--depth``): no ``depth/`` folders.
    """

    name: str
    cameras: List[Camera]
    models: List[str]
    frames: int
    fps: float = 30.0
    depth_unit_mm: float = 1.0
    has_rgb: bool = False
    source: Dict = field(default_factory=dict)
    segmentation: Optional[Dict] = None
    has_depth: bool = True

    def to_dict(self) -> Dict:
        d = {"format": FORMAT, "name": self.name, "frames": self.frames, "fps": self.fps,
             "depth_unit_mm": self.depth_unit_mm, "has_rgb": self.has_rgb, "has_depth": self.has_depth,
             "models": self.models,
             "cameras": [c.to_dict() for c in self.cameras], "source": self.source}
        if self.segmentation is not None:
            d["segmentation"] = self.segmentation
        return d


def frame_name(k: int) -> str:
    """The file name of frame ``k`` in every per-frame folder (``000123.png``)."""
    return f"{k:06d}.png"


def camera_dir(root: Path, camera: int) -> Path:
    """Folder holding the images of a camera: the sequence root for camera 0, else cam<k>/."""
    return Path(root) if camera == 0 else Path(root) / f"cam{camera}"


#: The run summary of ``torchhand track`` in its ``--out`` folder, beside the sequences' folders.
TRACK_SUMMARY = "track_summary.json"


class _Entry:
    """A file or folder of a layout, named once: ``theta = _Entry("theta.npy")`` makes
    ``layout.theta`` the path ``layout.root / "theta.npy"``."""

    def __init__(self, name: str, doc: str = ""):
        self.name, self.__doc__ = name, doc or f"``{name}``"

    def __get__(self, layout, owner=None):
        return self if layout is None else layout.root / self.name


class _Folder:
    """A folder whose files a layout names; ``root`` is kept as a :class:`Path`."""

    root: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))

    def __fspath__(self) -> str:
        return str(self.root)


@dataclass(frozen=True)
class PosesLayout(_Folder):
    """The ``gt/`` layout of poses and keypoints (ground truth, or a tracker's output)."""

    root: Path
    meta = _Entry("meta.json", "models, dof_names, keypoint_names, frames, per-frame valid flags")
    theta = _Entry("theta.npy", "(N, D) float64 poses")
    keypoints_3d = _Entry("keypoints_3d.npy", "(N, C, P, 3) float64 mm, in each camera's frame")
    keypoints_2d = _Entry("keypoints_2d.npy", "(N, C, P, 2) float64 px")
    keypoints21_3d = _Entry("keypoints21_3d.npy", "(N, C, 21 x hands, 3) float64 mm: the standard 21 joints of "
                            "each hand, in each camera's frame")
    keypoints21_2d = _Entry("keypoints21_2d.npy", "(N, C, 21 x hands, 2) float64 px: the standard 21 joints")
    keypoints21_valid = _Entry("keypoints21_valid.npy", "(N, 21 x hands) bool, optional: the joint is annotated "
                               "in the frame (a dataset's validity mask)")

    @property
    def arrays(self) -> List[Path]:
        """The pose arrays, in the order :class:`Poses` takes them."""
        return [self.theta, self.keypoints_3d, self.keypoints_2d]


@dataclass(frozen=True)
class GroundTruthLayout(PosesLayout):
    """A sequence's ``gt/`` folder: the poses, and what synthesis and recordings add."""

    ids_dir = _Entry("ids")
    salient_2d = _Entry("salient_2d.npy", "(N, C, P, 2) float64 px: the nail centres in each camera")
    salient_visible = _Entry("salient_visible.npy", "(N, C, P) bool: the nail centre is seen")
    annotations_2d = _Entry("annotations_2d.json", "sparse manual 2D labels of a converted thesis recording")
    object_pose = _Entry("object_pose.npy", "(N, 4, 4) poses of the scanned object, mesh -> camera, mm")
    object_mesh = _Entry("object.ply", "the scanned object's mesh")
    object_meta = _Entry("object.json", "the scanned object's mesh file and the grasp")
    joints_dataset_3d = _Entry("joints_dataset_3d.npy", "(N, C, J, 3) float64 mm: a public dataset's own joints "
                               "(not the standard 21), in each camera's frame")
    joints_dataset_2d = _Entry("joints_dataset_2d.npy", "(N, C, J, 2) float64 px: a public dataset's own joints")
    joints_dataset_meta = _Entry("joints_dataset.json", "the dataset's joint names and their standard-21 counterparts")

    def ids(self, frame: int) -> Path:
        """8-bit per-pixel model id of camera 0 (0 background, k+1 model k)."""
        return self.ids_dir / frame_name(frame)


@dataclass(frozen=True)
class SequenceLayout(_Folder):
    """Every path of a sequence folder (module docstring; datasets/README.md).

    ``SequenceLayout(root).depth(12, camera=1)`` is ``root/cam1/depth/000012.png``."""

    root: Path
    info = _Entry("sequence.json", "cameras, scene, frame count, units, provenance")
    init_pose = _Entry("init_pose.json", "theta of frame 0 (the tracker starts from it)")
    init_overlay = _Entry("init_overlay.png", "the picture ``torchhand init`` draws of the pose it found")

    def camera(self, camera: int = 0) -> Path:
        """The folder of a camera's images: the root for camera 0, else ``cam<k>/``."""
        return camera_dir(self.root, camera)

    def depth_dir(self, camera: int = 0) -> Path:
        return self.camera(camera) / "depth"

    def rgb_dir(self, camera: int = 0) -> Path:
        return self.camera(camera) / "rgb"

    def occluders_dir(self, camera: int = 0) -> Path:
        return self.camera(camera) / "occluders"

    def depth(self, frame: int, camera: int = 0) -> Path:
        return self.depth_dir(camera) / frame_name(frame)

    def rgb(self, frame: int, camera: int = 0) -> Path:
        return self.rgb_dir(camera) / frame_name(frame)

    def occluders(self, frame: int, camera: int = 0) -> Path:
        """The protocol's occluder mask of a colour frame (255 where circles cover it)."""
        return self.occluders_dir(camera) / frame_name(frame)

    def salient(self, camera: int = 0) -> Path:
        """A camera's salient point detections, per frame."""
        return self.camera(camera) / "salient.json"

    @property
    def gt(self) -> GroundTruthLayout:
        """Ground truth, kept apart: a tracker never reads it."""
        return GroundTruthLayout(self.root / "gt")


@dataclass(frozen=True)
class OutputLayout(PosesLayout):
    """A tracker's output folder for one sequence: the ``gt/`` layout of the tracked
    poses, the MOTION files, the log, and what ``--viz``, ``--write-render`` and
    ``--write-vertices`` add."""

    track_log = _Entry("track_log.json", "every frame's log and fit quality, and the run's settings")
    motion_dir = _Entry("motion")
    overlays_dir = _Entry("overlays")
    overlays_video = _Entry("overlays.mp4")
    render_dir = _Entry("render")
    vertices_dir = _Entry("vertices")

    def motion(self, model: str) -> Path:
        """``motion/<Model>.MOTION`` (``model``: the thesis' file name of the model)."""
        return self.motion_dir / f"{model}.MOTION"

    def overlay_dir(self, camera: Optional[int] = None) -> Path:
        return self.overlays_dir if camera is None else self.overlays_dir / f"cam{camera}"

    def overlay(self, frame: int, camera: Optional[int] = None) -> Path:
        """One camera's overlay: ``overlays/NNNNNN.png``, of a rig ``overlays/cam<k>/NNNNNN.png``."""
        return self.overlay_dir(camera) / frame_name(frame)

    def render(self, frame: int) -> Path:
        """The rendered depth of the fitted models (16-bit mm)."""
        return self.render_dir / frame_name(frame)

    def vertices(self, model: str) -> Path:
        """A model's posed vertices per frame, camera 0's coordinates."""
        return self.vertices_dir / f"{model}.npy"


def write_sequence_info(root, info: SequenceInfo, init_theta: Optional[np.ndarray] = None) -> None:
    seq = SequenceLayout(root)
    seq.info.write_text(json.dumps(info.to_dict(), indent=2))
    if init_theta is not None:
        write_init_pose(root, init_theta)


def write_init_pose(root, theta) -> None:
    """``init_pose.json``: the theta of frame 0, as the tracker reads it."""
    SequenceLayout(root).init_pose.write_text(json.dumps({"theta": [float(x) for x in np.asarray(theta).ravel()]}))


def read_sequence_info(root) -> SequenceInfo:
    root = Path(root)
    path = SequenceLayout(root).info
    if not path.is_file():
        raise SequenceError(f"{path} not found: {root} is not a torchhand sequence folder")
    try:
        d = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise SequenceError(f"{path}: invalid JSON ({err})") from None
    if d.get("format") != FORMAT:
        raise SequenceError(f"{path}: format is {d.get('format')!r}, expected {FORMAT!r}")
    missing = [k for k in ("name", "frames", "models", "cameras") if k not in d]
    if missing:
        raise SequenceError(f"{path}: missing keys {missing}")
    try:
        cams = [Camera.from_dict(c) for c in d["cameras"]]
    except (ValueError, TypeError) as err:
        raise SequenceError(f"{path}: bad camera entry ({err})") from None
    return SequenceInfo(d["name"], cams, list(d["models"]), int(d["frames"]), float(d.get("fps", 30.0)),
                        float(d.get("depth_unit_mm", 1.0)), bool(d.get("has_rgb", False)), d.get("source", {}),
                        d.get("segmentation"), bool(d.get("has_depth", True)))


def read_init_pose(root) -> np.ndarray:
    path = SequenceLayout(root).init_pose
    if not path.is_file():
        raise SequenceError(f"{path} not found: the tracker needs the pose of frame 0")
    try:
        theta = np.asarray(json.loads(path.read_text())["theta"], np.float64)
    except (ValueError, KeyError, TypeError) as err:
        raise SequenceError(f"{path}: expected {{\"theta\": [numbers]}} ({type(err).__name__}: {err})") from None
    if not np.isfinite(theta).all():
        raise SequenceError(f"{path}: theta contains NaN or inf")
    return theta


# ---------------------------------------------------------------- images
def write_depth(path, depth_mm: np.ndarray) -> None:
    """(H, W) float depth in mm -> 16-bit PNG (rounded; 0 = invalid; clipped at 65535)."""
    d = np.nan_to_num(np.asarray(depth_mm, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    if not cv2.imwrite(str(path), np.clip(np.round(d), 0, 65535).astype(np.uint16)):
        raise OSError(f"cannot write {path}")


def read_depth(path, unit_mm: float = 1.0) -> np.ndarray:
    """16-bit PNG -> (H, W) float32 depth in mm. Warns when values look like metres."""
    path = Path(path)
    if not path.is_file():
        raise SequenceError(f"{path}: depth frame not found")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SequenceError(f"{path}: unreadable image (not a PNG?)")
    if img.ndim != 2 or img.dtype != np.uint16:
        raise SequenceError(f"{path}: depth must be a single-channel 16-bit PNG, got {img.dtype} with shape {img.shape}")
    depth = img.astype(np.float32) * unit_mm
    valid = depth[depth > 0]
    if valid.size and np.median(valid) < 20:
        # A 16-bit map whose values are 0..10 is almost surely metres (or decimetres).
        raise SequenceError(
            f"{path}: median depth {np.median(valid):.1f} mm is implausibly small; the map looks like "
            "metres, but torchhand stores millimetres (set depth_unit_mm in sequence.json)")
    return depth


def write_rgb(path, rgb: np.ndarray) -> None:
    """(H, W, 3) uint8 RGB -> PNG."""
    if not cv2.imwrite(str(path), cv2.cvtColor(np.asarray(rgb, np.uint8), cv2.COLOR_RGB2BGR)):
        raise OSError(f"cannot write {path}")


def read_rgb(path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise SequenceError(f"{path}: colour frame not found or unreadable")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


# ----------------------------------------------------------- poses (gt/)
@dataclass
class Poses:
    """Poses and keypoints of a sequence: ground truth or a tracker's output.

    theta: (N, D); keypoints_3d: (N, C, P, 3) mm, camera frames; keypoints_2d:
    (N, C, P, 2) px; models, dof_names, keypoint_names: labels; valid: (N,) bool,
    False for frames a tracker flagged (kept but not trusted).
    """

    theta: np.ndarray
    keypoints_3d: np.ndarray
    keypoints_2d: np.ndarray
    models: List[str]
    dof_names: List[str]
    keypoint_names: List[str]
    valid: Optional[np.ndarray] = None

    def __post_init__(self) -> None:
        N = len(self.theta)
        if self.keypoints_3d.shape[0] != N or self.keypoints_2d.shape[0] != N:
            raise ValueError(f"theta has {N} frames but keypoints have {self.keypoints_3d.shape[0]} and "
                             f"{self.keypoints_2d.shape[0]}")
        if self.valid is None:
            self.valid = np.ones(N, bool)


def write_poses(folder, poses: Poses) -> None:
    """``folder`` (a path or a :class:`PosesLayout`) receives the ``gt/`` layout."""
    out = PosesLayout(Path(folder))
    out.root.mkdir(parents=True, exist_ok=True)
    np.save(out.theta, np.asarray(poses.theta, np.float64))
    np.save(out.keypoints_3d, np.asarray(poses.keypoints_3d, np.float64))
    np.save(out.keypoints_2d, np.asarray(poses.keypoints_2d, np.float64))
    meta = {"models": poses.models, "dof_names": poses.dof_names, "keypoint_names": poses.keypoint_names,
            "frames": int(len(poses.theta)), "valid": np.asarray(poses.valid, bool).tolist()}
    out.meta.write_text(json.dumps(meta))


def read_poses(folder) -> Poses:
    """The poses of a folder in the ``gt/`` layout (a path or a :class:`PosesLayout`)."""
    folder = PosesLayout(Path(folder))
    missing = [p.name for p in [folder.meta] + folder.arrays if not p.is_file()]
    if missing:
        raise SequenceError(f"{folder.root}: missing {missing} (expected the gt/ layout of datasets/README.md)")
    try:
        meta = json.loads(folder.meta.read_text())
    except ValueError as err:
        raise SequenceError(f"{folder.meta}: invalid JSON ({err})") from None
    arrays = []
    for path in folder.arrays:
        try:
            arrays.append(np.load(path, allow_pickle=False))
        except ValueError as err:
            raise SequenceError(f"{path}: unreadable ({err})") from None
    try:
        return Poses(*arrays, meta["models"], meta["dof_names"], meta["keypoint_names"],
                     np.asarray(meta.get("valid", [True] * len(arrays[0]))))
    except KeyError as err:
        raise SequenceError(f"{folder.meta}: missing key {err}") from None
    except ValueError as err:
        raise SequenceError(f"{folder.root}: {err}") from None


def write_joints21(folder, joints_3d: np.ndarray, joints_2d: np.ndarray, valid: Optional[np.ndarray] = None) -> None:
    """``folder`` (a path or a :class:`PosesLayout`, already holding the poses) receives the
    standard 21 joints of its hands: joints_3d (N, C, 21 x hands, 3) mm, joints_2d
    (N, C, 21 x hands, 2) px, and when given their validity ``valid`` (N, 21 x hands) bool."""
    out = PosesLayout(Path(folder))
    if joints_3d.shape[:3] != joints_2d.shape[:3] or joints_3d.shape[2] % 21:
        raise ValueError(f"21-joint arrays {joints_3d.shape} and {joints_2d.shape} do not match (N, C, 21 x hands)")
    if valid is not None and np.shape(valid) != (joints_3d.shape[0], joints_3d.shape[2]):
        raise ValueError(f"21-joint validity {np.shape(valid)} does not match (N, 21 x hands) of {joints_3d.shape}")
    np.save(out.keypoints21_3d, np.asarray(joints_3d, np.float64))
    np.save(out.keypoints21_2d, np.asarray(joints_2d, np.float64))
    if valid is not None:
        np.save(out.keypoints21_valid, np.asarray(valid, bool))


def read_joints21(folder) -> Optional[tuple]:
    """(joints_3d, joints_2d) of :func:`write_joints21` in ``folder``, or None where the
    folder has none."""
    folder = PosesLayout(Path(folder))
    if not (folder.keypoints21_3d.is_file() and folder.keypoints21_2d.is_file()):
        return None
    try:
        j3, j2 = np.load(folder.keypoints21_3d, allow_pickle=False), np.load(folder.keypoints21_2d, allow_pickle=False)
    except ValueError as err:
        raise SequenceError(f"{folder.root}: unreadable 21-joint arrays ({err})") from None
    if j3.ndim != 4 or j2.ndim != 4 or j3.shape[:3] != j2.shape[:3] or j3.shape[2] % 21 or j3.shape[3] != 3:
        raise SequenceError(f"{folder.root}: 21-joint arrays {j3.shape} and {j2.shape}, expected (N, C, 21 x hands, 3) "
                            "and (N, C, 21 x hands, 2)")
    return j3, j2


def read_joints21_valid(folder) -> Optional[np.ndarray]:
    """The (N, 21 x hands) bool validity of :func:`write_joints21` in ``folder``, or None
    where the folder has none (then NaN or all -1 marks an absent joint)."""
    path = PosesLayout(Path(folder)).keypoints21_valid
    if not path.is_file():
        return None
    try:
        valid = np.load(path, allow_pickle=False)
    except ValueError as err:
        raise SequenceError(f"{path}: unreadable ({err})") from None
    if valid.dtype != bool or valid.ndim != 2 or valid.shape[1] % 21:
        raise SequenceError(f"{path}: {valid.dtype} {valid.shape}, expected bool (N, 21 x hands)")
    return valid
