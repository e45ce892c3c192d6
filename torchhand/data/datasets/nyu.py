"""Read the NYU hand pose dataset (Tompson et al., ACM TOG 2014) as published, and import
one camera of a split as a torchhand sequence folder (datasets/README.md).

Source: one split folder of the download (``dataset/train``, ``dataset/test``)::

    SPLIT/
      joint_data.mat             joint_xyz (3, N, 36, 3) mm and joint_uvd (3, N, 36, 3)
                                 (u px, v px, z mm), one block per camera; joint_names (1, 36)
      depth_<k>_<NNNNNNN>.png    camera k = 1..3, frame NNNNNNN = 1..N: 640x480 8-bit
                                 colour PNG, depth in mm = (G << 8) + B, R unused (0)
      rgb_<k>_..., synthdepth_<k>_...   not read

Camera frame: NYU's xyz have y up (``convert_xyz_to_uvd.m``: ``v = 240 - fy y / z``);
torchhand's camera frame has x right, y down, z forward, so y is negated and x, z kept.
The intrinsics are those of ``convert_xyz_to_uvd.m`` (:data:`NYU_INTRINSICS`), the same
for the three Kinects; each camera's joints are in its own frame.

Joints: the 14 of the evaluation protocol that papers report on
(:data:`NYU_EVAL_JOINTS` into the 36 of ``joint_names``). They are not the standard 21
(docs/model.md): they are stored as the dataset's own ground truth with their names, and
:data:`NYU_TO_STANDARD21` names the standard joint each lies nearest to, where there is one.

Target::

    SEQ/
      sequence.json              the NYU camera, model hand_right, source (split, camera, files)
      depth/000000.png           16-bit depth in mm, the unpacked G/B values (0 = no measurement)
      gt/joints_dataset_3d.npy   (N, 1, 14, 3) float64 mm, torchhand's camera frame
      gt/joints_dataset_2d.npy   (N, 1, 14, 2) float64 px, their projections
      gt/joints_dataset.json     the joint names, their indices in joint_data.mat, their
                                 standard-21 counterparts

Errors in the input raise :class:`~torchhand.data.layout.SequenceError` naming the file.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from typing import List, NamedTuple, Optional

import cv2
import numpy as np
import scipy.io
from tqdm import tqdm

from torchhand.data.layout import SequenceError, SequenceInfo, SequenceLayout, write_depth, write_sequence_info
from torchhand.geometry.camera import Camera
from torchhand.io.output_dir import commit_dir, partial_dir

__all__ = ["NYU_INTRINSICS", "NYU_JOINT_NAMES", "NYU_EVAL_JOINTS", "NYU_EVAL_NAMES", "NYU_TO_STANDARD21",
           "NYUJoints", "read_packed_png", "read_nyu_depth", "read_nyu_joints", "nyu_to_camera_frame", "nyu_camera", "import_nyu"]

#: fx, fy, cx, cy (px) of ``convert_xyz_to_uvd.m``, for 640x480 frames.
NYU_INTRINSICS = {"fx": 588.036865, "fy": 587.075073, "cx": 320.0, "cy": 240.0, "width": 640, "height": 480}

#: The 36 joints of ``joint_names``: F1..F4 are the little, ring, middle and index finger,
#: TH the thumb; KNU3, KNU2, KNU1 the distal, middle and proximal segment (for the thumb:
#: distal, proximal phalanx, metacarpal), A its distal end and B its proximal end.
NYU_JOINT_NAMES = tuple(f"{f}_KNU{s}_{e}" for f in ("F1", "F2", "F3", "F4", "TH") for s in (3, 2, 1)
                        for e in "AB") + tuple(f"PALM_{i}" for i in range(1, 7))

#: The 14 evaluation joints (indices into the 36), in the order papers report them.
NYU_EVAL_JOINTS = (0, 3, 6, 9, 12, 15, 18, 21, 24, 25, 27, 30, 31, 32)
NYU_EVAL_NAMES = tuple(NYU_JOINT_NAMES[i] for i in NYU_EVAL_JOINTS)

#: The standard joint (torchhand.model.joints21) each evaluation joint lies nearest to;
#: None where there is none. By name, as everywhere in torchhand: NYU's tips end the
#: distal segment and PALM_3 sits at the base of the palm, so the distances stay in any
#: comparison (no offset is fitted).
NYU_TO_STANDARD21 = {
    "F1_KNU3_A": "little_tip", "F1_KNU2_B": "little_pip", "F2_KNU3_A": "ring_tip", "F2_KNU2_B": "ring_pip",
    "F3_KNU3_A": "middle_tip", "F3_KNU2_B": "middle_pip", "F4_KNU3_A": "index_tip", "F4_KNU2_B": "index_pip",
    "TH_KNU3_A": "thumb_tip", "TH_KNU3_B": "thumb_ip", "TH_KNU2_B": "thumb_mcp",
    "PALM_1": None, "PALM_2": None, "PALM_3": "wrist",
}

_MAT = "joint_data.mat"
_DEPTH = re.compile(r"depth_(\d+)_(\d+)\.png")
#: largest difference (px) allowed between joint_uvd and the projection of joint_xyz
_UVD_TOLERANCE_PX = 1.0


class NYUJoints(NamedTuple):
    """The arrays of ``joint_data.mat``.

    Attributes:
        xyz: (C, N, 36, 3) float64 mm, NYU's camera frames (y up).
        uvd: (C, N, 36, 3) float64 (u px, v px, z mm).
        names: the 36 joint names.
    """

    xyz: np.ndarray
    uvd: np.ndarray
    names: List[str]


def read_packed_png(path: Path, what: str, packing: str) -> np.ndarray:
    """The (H, W, 3) uint8 BGR image of a depth frame packed into colour channels; one that
    is missing, unreadable or not 8-bit with three channels is refused naming the file
    (``what``: the frame's kind, ``packing``: where its depth lies, for the message)."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SequenceError(f"{path}: depth frame not found or unreadable")
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        channels = 1 if img.ndim == 2 else img.shape[2]
        raise SequenceError(f"{path}: {what} is an 8-bit PNG with 3 channels ({packing}), "
                            f"got {img.dtype} with {channels} channel(s)")
    return img


def read_nyu_depth(path) -> np.ndarray:
    """An NYU depth frame -> (H, W) uint16 depth in mm, ``(G << 8) + B``.

    Refuses, naming the file, an image that is not the packed format: not 8-bit with
    three channels (a grey or 16-bit PNG), or with a non-zero R channel (a colour frame).
    """
    path = Path(path)
    img = read_packed_png(path, "an NYU depth frame", "depth in G and B")
    # OpenCV reads BGR. The format packs depth into G and B only; R = 0 is what a frame
    # packed that way holds, and a non-zero R marks a colour frame (rgb_<k>_...) given instead.
    b, g, r = img[..., 0], img[..., 1], img[..., 2]
    if r.any():
        raise SequenceError(f"{path}: the R channel is non-zero at {int(np.count_nonzero(r))} pixels; NYU depth "
                            "frames hold depth in G (high byte) and B (low byte) only (a colour frame?)")
    return (g.astype(np.uint16) << 8) | b.astype(np.uint16)


def _names(value, mat: Path) -> List[str]:
    arr = np.asarray(value)
    if arr.dtype == object:
        return [str(np.asarray(x).ravel()[0]).strip() if np.asarray(x).size else "" for x in arr.ravel()]
    if arr.dtype.kind == "U":
        return [str(x).strip() for x in arr.ravel()]
    raise SequenceError(f"{mat}: joint_names must hold strings, got {arr.dtype}")


def read_nyu_joints(mat) -> NYUJoints:
    """The joints of an NYU ``joint_data.mat``, checked: joint_xyz and joint_uvd of one
    shape (C, N, 36, 3), and joint_names in NYU's order (:data:`NYU_JOINT_NAMES`)."""
    mat = Path(mat)
    if not mat.is_file():
        raise SequenceError(f"{mat} not found: an NYU split folder holds joint_data.mat beside its depth frames")
    try:
        data = scipy.io.loadmat(str(mat))
    except (ValueError, TypeError, OSError, NotImplementedError, scipy.io.matlab.MatReadError) as err:
        raise SequenceError(f"{mat}: not a readable MATLAB file ({type(err).__name__}: {err})") from None
    missing = [k for k in ("joint_xyz", "joint_uvd", "joint_names") if k not in data]
    if missing:
        raise SequenceError(f"{mat}: missing {missing} (expected joint_xyz, joint_uvd and joint_names)")
    xyz, uvd = (np.asarray(data[k], np.float64) for k in ("joint_xyz", "joint_uvd"))
    for key, arr in (("joint_xyz", xyz), ("joint_uvd", uvd)):
        if arr.ndim != 4 or arr.shape[2:] != (36, 3):
            raise SequenceError(f"{mat}: {key} has shape {arr.shape}, expected (cameras, frames, 36, 3)")
    if xyz.shape != uvd.shape:
        raise SequenceError(f"{mat}: joint_xyz {xyz.shape} and joint_uvd {uvd.shape} differ in shape")
    names = _names(data["joint_names"], mat)
    if tuple(names) != NYU_JOINT_NAMES:
        raise SequenceError(f"{mat}: joint_names are {names[:3]}..., expected NYU's 36 "
                            f"({NYU_JOINT_NAMES[0]}, ..., {NYU_JOINT_NAMES[-1]})")
    return NYUJoints(xyz, uvd, names)


def nyu_to_camera_frame(xyz: np.ndarray) -> np.ndarray:
    """(..., 3) NYU xyz (y up) -> (..., 3) torchhand's camera frame (y down), mm."""
    return xyz * np.array([1.0, -1.0, 1.0])


def nyu_camera(camera: int = 1) -> Camera:
    """The camera of NYU's Kinect ``camera`` (1..3): :data:`NYU_INTRINSICS`, identity pose."""
    k = NYU_INTRINSICS
    return Camera.from_intrinsics(k["fx"], k["fy"], k["cx"], k["cy"], k["width"], k["height"],
                                  name=f"nyu_kinect{camera}")


def _project(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(..., 3) camera-frame mm -> (..., 2) px; NaN where z <= 0."""
    z = np.where(points[..., 2:] > 0, points[..., 2:], np.nan)
    return points[..., :2] / z * K[[0, 1], [0, 1]] + K[:2, 2]


def _depth_files(split: Path, camera: int, n: int, mat: Path) -> List[Path]:
    """The depth frames 1..n of ``camera``, in order; errors name the folder or file."""
    numbers = sorted(int(m.group(2)) for p in split.iterdir()
                     if (m := _DEPTH.fullmatch(p.name)) and int(m.group(1)) == camera)
    if len(numbers) != n:
        raise SequenceError(f"{split}: {len(numbers)} depth_{camera}_*.png files, but {mat} holds {n} frames of "
                            f"camera {camera}")
    files = [split / f"depth_{camera}_{k:07d}.png" for k in range(1, n + 1)]
    absent = [p for p in files if not p.is_file()]
    if absent:
        raise SequenceError(f"{absent[0]} not found: frames are numbered 1..{n} ({len(absent)} missing)")
    return files


def _check_arguments(split: Path, out: Path, camera, frames, force: bool) -> None:
    if not split.is_dir():
        raise SequenceError(f"{split}: not a folder (give an NYU split folder, e.g. dataset/test)")
    if isinstance(camera, bool) or not isinstance(camera, (int, np.integer)):
        raise ValueError(f"camera must be an int 1..3, got {camera!r}")
    if frames is not None and not isinstance(frames, slice):
        raise ValueError(f"frames must be a slice or None, got {type(frames).__name__}")
    a, b = split.resolve(), out.resolve()
    if a == b or a in b.parents or b in a.parents:
        raise ValueError(f"out ({out}) must not be, contain or lie inside the split folder ({split})")
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not force:
        raise FileExistsError(f"{out} is not empty; choose a new folder or pass --force to replace its content")


def _checked_joints(joints: NYUJoints, camera: int, rows: range, mat: Path, K: np.ndarray) -> tuple:
    """(joints_3d (N, 1, 14, 3) mm, joints_2d (N, 1, 14, 2) px) of the chosen frames in
    torchhand's camera frame, after checking joint_uvd against the projection."""
    sel = list(rows)
    j3 = nyu_to_camera_frame(joints.xyz[camera - 1, sel][:, NYU_EVAL_JOINTS])  # (N, 14, 3)
    j2 = _project(j3, K)
    uv = joints.uvd[camera - 1, sel][:, NYU_EVAL_JOINTS, :2]
    gap = np.abs(j2 - uv).max(initial=0.0)
    if not gap <= _UVD_TOLERANCE_PX:
        raise SequenceError(f"{mat}: joint_uvd differs from joint_xyz projected with the NYU intrinsics by up to "
                            f"{gap:.1f} px (camera {camera}): not NYU's convention (v = 240 - fy y / z)")
    return j3[:, None], j2[:, None]


def _write_ground_truth(seq: SequenceLayout, j3: np.ndarray, j2: np.ndarray, mat: Path) -> None:
    seq.gt.root.mkdir()
    np.save(seq.gt.joints_dataset_3d, j3)
    np.save(seq.gt.joints_dataset_2d, j2)
    meta = {"dataset": "NYU hand pose (Tompson et al. 2014)", "source": str(mat.resolve()),
            "names": list(NYU_EVAL_NAMES), "indices": list(NYU_EVAL_JOINTS),
            "standard21": [NYU_TO_STANDARD21[n] for n in NYU_EVAL_NAMES],
            "frame": "torchhand camera frame (x right, y down, z forward), mm"}
    seq.gt.joints_dataset_meta.write_text(json.dumps(meta, indent=1))


def import_nyu(split_dir, out, camera: int = 1, frames: Optional[slice] = None, force: bool = False, *,
               progress: bool = True, segmentation: Optional[dict] = None) -> SequenceInfo:
    """Write the sequence folder ``out`` from one camera of an NYU split (module docstring).

    Args:
        split_dir: an NYU split folder (``train/`` or ``test/``).
        out: sequence folder to write; must be missing or empty unless ``force``.
        camera: NYU's camera number, 1..3 (``depth_<camera>_*.png``).
        frames: which of the split's frames, a slice over 0..N-1 (frame ``k`` is file
            number ``k + 1``); None: all.
        force: replace a non-empty ``out`` (only once the new folder is complete).
        progress: show a tqdm progress bar over the frames.
        segmentation: hand-segmentation settings stored in ``sequence.json`` (as
            :func:`torchhand.data.importing.import_depth_folder` stores them).
    Returns:
        the written :class:`SequenceInfo`. The folder is written beside ``out`` and renamed
        when complete, so a bad frame leaves ``out`` as it was.
    """
    split, out = Path(split_dir), Path(out)
    _check_arguments(split, out, camera, frames, force)
    mat = split / _MAT
    joints = read_nyu_joints(mat)
    cameras, n = joints.xyz.shape[:2]
    if not 1 <= camera <= cameras:
        raise ValueError(f"camera {camera} is out of range: {mat} holds cameras 1..{cameras}")
    files = _depth_files(split, int(camera), n, mat)
    rows = range(n) if frames is None else range(n)[frames]
    if not rows:
        raise ValueError(f"frames {frames} selects none of the {n} frames of {split}")
    cam = nyu_camera(int(camera))
    j3, j2 = _checked_joints(joints, int(camera), rows, mat, cam.K.double().numpy())
    work = partial_dir(out)
    try:
        seq = SequenceLayout(work)
        seq.depth_dir().mkdir()
        size = (cam.height, cam.width)
        for i, k in enumerate(tqdm(rows, desc=f"import {split.name} camera {camera}", unit="frame",
                                   disable=not progress)):
            depth = read_nyu_depth(files[k])
            if depth.shape != size:
                raise SequenceError(f"{files[k]}: {depth.shape[1]}x{depth.shape[0]} pixels, NYU frames are 640x480")
            write_depth(seq.depth(i), depth)
        _write_ground_truth(seq, j3, j2, mat)
        source = {"dataset": "NYU hand pose", "split": str(split.resolve()), "camera": int(camera),
                  "files": [files[k].name for k in rows]}
        info = SequenceInfo(out.name, [cam], ["hand_right"], len(rows), source=source, segmentation=segmentation)
        write_sequence_info(work, info)
        commit_dir(work, out, force)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    return info
