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
        ids/000000.png         8-bit per-pixel model id of camera 0: 0 background, k+1 model k
        salient_2d.npy         (N, C, P, 2) float64 px: the nail centres in each camera
        salient_visible.npy    (N, C, P) bool: the nail centre is seen (colour renders)

A tracker's output folder uses the ``gt/`` layout (without ``ids/``), so ground
truth scored against itself gives 0.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import cv2
import numpy as np

from torchhand.geometry.camera import Camera

__all__ = [
    "FORMAT",
    "SequenceInfo",
    "SequenceError",
    "read_init_pose",
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
]

FORMAT = "torchhand-sequence/1"


class SequenceError(ValueError):
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
    return f"{k:06d}.png"


def camera_dir(root: Path, camera: int) -> Path:
    """Folder holding the images of a camera: the sequence root for camera 0, else cam<k>/."""
    return Path(root) if camera == 0 else Path(root) / f"cam{camera}"


def write_sequence_info(root, info: SequenceInfo, init_theta: Optional[np.ndarray] = None) -> None:
    root = Path(root)
    (root / "sequence.json").write_text(json.dumps(info.to_dict(), indent=2))
    if init_theta is not None:
        (root / "init_pose.json").write_text(json.dumps({"theta": [float(x) for x in np.asarray(init_theta).ravel()]}))


def read_sequence_info(root) -> SequenceInfo:
    root = Path(root)
    path = root / "sequence.json"
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
    path = Path(root) / "init_pose.json"
    if not path.is_file():
        raise SequenceError(f"{path} not found: the tracker needs the pose of frame 0")
    theta = np.asarray(json.loads(path.read_text())["theta"], np.float64)
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
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    np.save(folder / "theta.npy", np.asarray(poses.theta, np.float64))
    np.save(folder / "keypoints_3d.npy", np.asarray(poses.keypoints_3d, np.float64))
    np.save(folder / "keypoints_2d.npy", np.asarray(poses.keypoints_2d, np.float64))
    meta = {"models": poses.models, "dof_names": poses.dof_names, "keypoint_names": poses.keypoint_names,
            "frames": int(len(poses.theta)), "valid": np.asarray(poses.valid, bool).tolist()}
    (folder / "meta.json").write_text(json.dumps(meta))


def read_poses(folder) -> Poses:
    folder = Path(folder)
    need = ["meta.json", "theta.npy", "keypoints_3d.npy", "keypoints_2d.npy"]
    missing = [n for n in need if not (folder / n).is_file()]
    if missing:
        raise SequenceError(f"{folder}: missing {missing} (expected the gt/ layout of datasets/README.md)")
    meta = json.loads((folder / "meta.json").read_text())
    arrays = {}
    for n in need[1:]:
        try:
            arrays[n] = np.load(folder / n, allow_pickle=False)
        except ValueError as err:
            raise SequenceError(f"{folder / n}: unreadable ({err})") from None
    try:
        return Poses(arrays["theta.npy"], arrays["keypoints_3d.npy"], arrays["keypoints_2d.npy"], meta["models"],
                     meta["dof_names"], meta["keypoint_names"],
                     np.asarray(meta.get("valid", [True] * len(arrays["theta.npy"]))))
    except ValueError as err:
        raise SequenceError(f"{folder}: {err}") from None
