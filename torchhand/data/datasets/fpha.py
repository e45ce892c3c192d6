"""The First-Person Hand Action benchmark (FPHA; Garcia-Hernando et al., CVPR 2018), as
published (github.com/guiggh/hand_pose_action), read into a torchhand sequence folder.

The published layout; one sequence is one repetition of an action by a subject::

    <root>/Video_files/<subject>/<action>/<seq>/depth/depth_0000.png   16-bit, mm, 640x480
    <root>/Hand_pose_annotation_v1/<subject>/<action>/<seq>/skeleton.txt

``skeleton.txt`` holds one line per frame: the frame number ``t`` (of ``depth_<t:04d>.png``)
and 63 numbers, the 21 joints' x y z in mm. FPHA's README calls them world coordinates,
and its own example projects them with the depth intrinsics and no transform: they are in
the depth camera's frame (the published extrinsics lead to the colour camera only). So
camera 0 of the sequence is the depth camera with the published intrinsics and ``T_cw``
the identity, and the joints are written as they are, in mm. The annotated hand is the
right one (``hand_right``); the recordings run at 30 fps.

FPHA orders the joints ``[Wrist, TMCP, IMCP, MMCP, RMCP, PMCP, TPIP, TDIP, TTIP, IPIP, IDIP,
ITIP, MPIP, MDIP, MTIP, RPIP, RDIP, RTIP, PPIP, PDIP, PTIP]``: the five finger bases first,
then each finger's remaining joints. Its thumb joints are named as a finger's, from the
base: TMCP is the thumb's CMC, TPIP its MCP, TDIP its IP (:data:`STANDARD_FROM_FPHA`).

What the reader refuses (a :class:`~torchhand.data.layout.SequenceError` naming the file,
before anything is written) and what it warns about:

- no ``skeleton.txt`` where the layout puts it, a skeleton with no usable line, or one
  whose coordinates look like metres: refused;
- a depth frame that is not a single-channel 16-bit PNG of 640x480, or a gap in the depth
  frame numbers: refused;
- a skeleton line that is not a frame number and 63 finite numbers, or that repeats a
  frame number: a warning naming ``file:line``; the frame keeps its depth and gets NaN
  joints (3D and 2D), which scoring leaves out (:func:`torchhand.scoring.metrics.valid_joints`);
  so does a frame the skeleton has no line for. ``sequence.json`` lists these frames
  (``source.frames_without_pose``);
- depth and skeleton frame counts that differ: a warning naming both; the frames both
  have (``0 .. min - 1``) are imported.
"""

from __future__ import annotations

import os
import re
import shutil
import warnings
from pathlib import Path
from typing import Callable, Dict, List, NamedTuple, Optional, Tuple

import numpy as np
import torch

from torchhand.data.importing import check_depth_pngs, check_intrinsics
from torchhand.data.layout import SequenceError, SequenceInfo, SequenceLayout, write_joints21, write_sequence_info
from torchhand.geometry.camera import Camera
from torchhand.io.output_dir import commit_dir, partial_dir
from torchhand.model.joints21 import STANDARD_JOINT_NAMES

__all__ = ["FPHA_INTRINSICS", "FPHA_JOINT_NAMES", "STANDARD_FROM_FPHA", "FPHA_TO_STANDARD", "Skeleton",
           "fpha_camera", "fpha_files", "read_skeleton", "import_fpha", "write_imported", "check_out_folder"]

VIDEO_DIR, POSE_DIR, SKELETON_FILE = "Video_files", "Hand_pose_annotation_v1", "skeleton.txt"
WIDTH, HEIGHT, FPS = 640, 480, 30.0
_DEPTH_NAME = re.compile(r"depth_(\d+)\.png")

#: The published intrinsics of the depth camera (Intel RealSense SR300), px.
FPHA_INTRINSICS = {"fx": 475.065948, "fy": 475.065857, "cx": 315.944855, "cy": 245.287079}

#: FPHA's joint order, as ``skeleton.txt`` lists the joints.
FPHA_JOINT_NAMES = ("Wrist", "TMCP", "IMCP", "MMCP", "RMCP", "PMCP", "TPIP", "TDIP", "TTIP", "IPIP", "IDIP", "ITIP",
                    "MPIP", "MDIP", "MTIP", "RPIP", "RDIP", "RTIP", "PPIP", "PDIP", "PTIP")

#: Each standard joint (:data:`~torchhand.model.joints21.STANDARD_JOINT_NAMES`) and the FPHA joint it is.
STANDARD_FROM_FPHA = {
    "wrist": "Wrist",
    "thumb_cmc": "TMCP", "thumb_mcp": "TPIP", "thumb_ip": "TDIP", "thumb_tip": "TTIP",
    "index_mcp": "IMCP", "index_pip": "IPIP", "index_dip": "IDIP", "index_tip": "ITIP",
    "middle_mcp": "MMCP", "middle_pip": "MPIP", "middle_dip": "MDIP", "middle_tip": "MTIP",
    "ring_mcp": "RMCP", "ring_pip": "RPIP", "ring_dip": "RDIP", "ring_tip": "RTIP",
    "little_mcp": "PMCP", "little_pip": "PPIP", "little_dip": "PDIP", "little_tip": "PTIP",
}

#: (21,) index into FPHA's order of each standard joint: ``standard = fpha[..., FPHA_TO_STANDARD, :]``.
FPHA_TO_STANDARD = np.array([FPHA_JOINT_NAMES.index(STANDARD_FROM_FPHA[n]) for n in STANDARD_JOINT_NAMES])


class Skeleton(NamedTuple):
    """A ``skeleton.txt``: joints (T, 21, 3) float64 mm in FPHA's order, NaN for a frame
    without a usable line (T: the last frame number + 1); valid (T,) bool."""

    joints: np.ndarray
    valid: np.ndarray


def fpha_camera() -> Camera:
    """FPHA's depth camera: the published intrinsics, 640x480, the identity ``T_cw``."""
    k = FPHA_INTRINSICS
    return Camera.from_intrinsics(k["fx"], k["fy"], k["cx"], k["cy"], WIDTH, HEIGHT, name="fpha_depth")


def fpha_files(src) -> Tuple[List[Path], Path]:
    """(the depth frames in frame order, ``skeleton.txt``) of the sequence folder
    ``src`` = ``<root>/Video_files/<subject>/<action>/<seq>`` (module docstring)."""
    src = Path(os.path.abspath(src))
    layout = f"<root>/{VIDEO_DIR}/<subject>/<action>/<seq>"
    if not src.is_dir():
        raise SequenceError(f"{src}: not a folder (give an FPHA sequence folder, {layout})")
    if len(src.parts) < 5 or src.parts[-4] != VIDEO_DIR:
        raise SequenceError(f"{src}: not an FPHA sequence folder (expected {layout})")
    skeleton = src.parents[3] / POSE_DIR / Path(*src.parts[-3:]) / SKELETON_FILE
    if not skeleton.is_file():
        raise SequenceError(f"{skeleton}: not found (the hand pose of {src}; FPHA keeps it in "
                            f"<root>/{POSE_DIR}/<subject>/<action>/<seq>/{SKELETON_FILE})")
    depth_dir = src / "depth"
    numbered = {int(m[1]): p for p in (depth_dir.iterdir() if depth_dir.is_dir() else [])
                if (m := _DEPTH_NAME.fullmatch(p.name))}
    if not numbered:
        raise SequenceError(f"{depth_dir}: no depth_NNNN.png frames")
    gaps = [k for k in range(max(numbered) + 1) if k not in numbered]
    if gaps:
        raise SequenceError(f"{depth_dir / f'depth_{gaps[0]:04d}.png'}: missing ({len(gaps)} frame numbers missing "
                            f"of 0..{max(numbered)}; the frames must be numbered from 0 without gaps)")
    return [numbered[k] for k in range(len(numbered))], skeleton


def _parse_line(line: str) -> Tuple[Optional[str], int, Optional[np.ndarray]]:
    """(problem or None, frame number, (63,) coordinates) of one ``skeleton.txt`` line."""
    tokens = line.split()
    if len(tokens) != 64:
        return f"{len(tokens)} numbers, expected 64 (the frame number, then 21 joints' x y z)", -1, None
    try:
        t, xyz = int(tokens[0]), np.array(tokens[1:], np.float64)
    except ValueError:
        return "not a frame number and 63 numbers", -1, None
    if t < 0:
        return f"negative frame number {t}", -1, None
    if not np.isfinite(xyz).all():
        return "NaN or inf among the coordinates", -1, None
    return None, t, xyz


def read_skeleton(path) -> Skeleton:
    """Read an FPHA ``skeleton.txt`` (module docstring: a bad line is a warning and the
    frame gets NaN joints; a file without a usable line, or in metres, a SequenceError)."""
    path = Path(path)
    rows: Dict[int, np.ndarray] = {}
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        problem, t, xyz = _parse_line(line)
        if problem is None and t in rows:
            problem = f"frame {t} given again (its first line is kept)"
        if problem is not None:
            warnings.warn(f"{path}:{n}: {problem}; that frame gets no joints", stacklevel=2)
            continue
        rows[t] = xyz
    if not rows:
        raise SequenceError(f"{path}: no line holds a frame number and 63 coordinates (21 joints x y z, mm)")
    joints = np.full((max(rows) + 1, 21, 3), np.nan)
    for t, xyz in rows.items():
        joints[t] = xyz.reshape(21, 3)
    largest = float(np.nanmax(np.abs(joints)))
    if largest < 10:
        raise SequenceError(f"{path}: the largest coordinate is {largest:.3g}; FPHA's joints are in mm, these look "
                            "like metres")
    return Skeleton(joints, np.isfinite(joints).all(axis=(1, 2)))


def _common_frames(files: List[Path], skeleton: Skeleton, path: Path) -> int:
    """How many frames to import: those both the depth and the skeleton have (warned when they differ)."""
    n = min(len(files), len(skeleton.valid))
    if len(files) != len(skeleton.valid):
        warnings.warn(f"{files[0].parent}: {len(files)} depth frames, but {path} has frames 0..{len(skeleton.valid) - 1}"
                      f" ({len(skeleton.valid)}); the {n} frames both have are imported", stacklevel=3)
    return n


def check_out_folder(out: Path, force: bool) -> None:
    """A clear error, before anything is read or written, when ``out`` is a file or a
    non-empty folder and not ``force``."""
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not force:
        raise FileExistsError(f"{out} is not empty; choose a new folder or pass --force to replace its content")


def import_fpha(src, out, force: bool = False, segmentation: Optional[Dict] = None) -> SequenceInfo:
    """Write the sequence folder ``out`` from one FPHA sequence (module docstring).

    Args:
        src: ``<root>/Video_files/<subject>/<action>/<seq>``; its skeleton is read from
            ``<root>/Hand_pose_annotation_v1/<subject>/<action>/<seq>/skeleton.txt``.
        out: sequence folder to create (must be new or empty unless ``force``).
        force: replace a non-empty ``out``.
        segmentation: hand-segmentation settings stored in ``sequence.json`` (as
            :func:`torchhand.data.importing.import_depth_folder` stores them).
    Returns:
        the written :class:`SequenceInfo`: camera 0 the depth camera, ``hand_right``, the
        depth frames copied byte for byte (1 mm per unit), and in ``gt/`` the standard 21
        joints (``keypoints21_3d.npy``: (N, 1, 21, 3) mm, ``keypoints21_2d.npy``: (N, 1, 21,
        2) px), NaN in frames without a pose. Everything is checked first and written into
        a hidden folder renamed to ``out`` at the end, so a failure leaves ``out`` as it was.
    """
    out = Path(out)
    files, skeleton_path = fpha_files(src)
    check_out_folder(out, force)
    H, W = check_depth_pngs(files, "FPHA's depth frames are 16-bit millimetres")
    check_intrinsics({**FPHA_INTRINSICS, "width": WIDTH, "height": HEIGHT}, W, H, str(files[0].parent))
    skeleton = read_skeleton(skeleton_path)
    n = _common_frames(files, skeleton, skeleton_path)
    joints = skeleton.joints[:n][:, FPHA_TO_STANDARD]  # (n, 21, 3) mm, camera 0
    camera = fpha_camera()
    pixels = camera.project(torch.from_numpy(joints)).numpy()
    pixels[~(joints[..., 2] > 0)] = np.nan  # behind the camera, or no pose
    src = files[0].parents[1]
    source = {"format": "fpha", "imported_from": str(src), "skeleton": str(skeleton_path),
              "subject": src.parts[-3], "action": src.parts[-2], "sequence": src.parts[-1],
              "files": [p.name for p in files[:n]],
              "frames_without_pose": np.nonzero(~skeleton.valid[:n])[0].tolist()}
    info = SequenceInfo(out.name, [camera], ["hand_right"], n, FPS, 1.0, False, source, segmentation)

    def copy_depth(seq: SequenceLayout) -> None:
        seq.depth_dir().mkdir()
        for k in range(n):
            shutil.copyfile(files[k], seq.depth(k))

    write_imported(out, info, force, copy_depth, joints, pixels)
    return info


def write_imported(out: Path, info: SequenceInfo, force: bool, write_frames: Callable[[SequenceLayout], None],
                   joints: np.ndarray, pixels: np.ndarray, valid: Optional[np.ndarray] = None) -> None:
    """Write a dataset's sequence folder ``out`` atomically: ``write_frames`` fills a hidden
    folder beside it, then the standard 21 joints (N, 21, 3) mm and (N, 21, 2) px of camera 0
    (or (N, C, 21, 3) and (N, C, 21, 2), one slice per camera of a rig), their validity
    ``valid`` (N, 21) when given, and ``info`` are written and the folder is renamed to
    ``out``; a failure removes it."""
    partial = partial_dir(out.absolute())
    if joints.ndim == 3:
        joints, pixels = joints[:, None], pixels[:, None]
    try:
        seq = SequenceLayout(partial)
        write_frames(seq)
        seq.gt.root.mkdir()
        write_joints21(seq.gt, joints, pixels, valid)
        write_sequence_info(partial, info)
        commit_dir(partial, out.absolute(), force)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
