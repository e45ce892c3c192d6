"""Read the thesis' public RGB-D recordings and convert them to torchhand sequences.

Source: the "Hands in Action" recordings (Tzionas, PhD thesis 2016), one folder per
sequence, captured with a Primesense/Kinect camera (fx = fy = 525, cx = 319.5,
cy = 239.5, 640x480; :func:`torchhand.geometry.camera.kinect_camera`)::

    REC/
      depth/000.yml            OpenCV FileStorage YAML, node ``depth``: 480x640 matrix,
                               16U (millimetres) or 32F (millimetres, or another unit
                               given by ``depth_scale``); 0 = no measurement
      rgb/000.png              optional 8-bit colour, 640x480
      joints_2D_GT/000.txt     optional manual 2D annotation, one line per joint:
                               ``id x y`` (pixels); only some frames have a file

Frame numbers are the file names read as integers: any zero-padding width works
(``7.yml``, ``007.yml``, ``000007.yml``) and frames are sorted numerically. The
frames of a recording are those with a file in ``depth/``.

Target: torchhand's own layout (:mod:`torchhand.data.layout`)::

    SEQ/
      sequence.json            kinect camera, model names, frame count, source
                               {"format": "hands-in-action recording", "path": REC}
      init_pose.json           theta of frame 0, only when ``init_theta`` is given
      depth/000000.png         16-bit depth in millimetres (rounded; 0 = no measurement)
      rgb/000000.png           8-bit colour, when every frame of the recording has one
      gt/annotations_2d.json   the manual 2D labels, when the recording has any:
                               {"frames": {"<k>": {"<id>": [x, y], ...}}, ...}

Frame ``k`` of the converted sequence is the ``k``-th recording frame in numerical
order; it equals the recording's own frame number unless the recording does not
start at 0 or has gaps, in which case ``sequence.json``'s ``source`` also lists the
original ``frame_numbers``. The 2D annotations are the thesis' sparse manual labels,
kept exactly as stored: their joint ids follow the recording's own numbering and are
**not** mapped to torchhand's 21 hand keypoints (``HAND_KEYPOINT_NAMES``), and frames
without a label file have no entry.

:func:`write_recording_sample` writes the thesis layout (used to make test samples).
Errors in the input raise :class:`~torchhand.data.layout.SequenceError` naming the file.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import tempfile
import warnings
from pathlib import Path
from typing import Dict, List, Mapping, NamedTuple, Optional, Sequence, Tuple, Union

import cv2
import numpy as np
from tqdm import tqdm

from torchhand.geometry.camera import kinect_camera
from torchhand.data.layout import (SequenceError, SequenceInfo, SequenceLayout, write_depth, write_rgb,
                                   write_sequence_info)

__all__ = [
    "RECORDING_FORMAT",
    "RECORDING_SHAPE",
    "RecordingFrame",
    "list_recording_frames",
    "read_recording_frame",
    "write_recording_sample",
    "convert_recording",
]

RECORDING_FORMAT = "hands-in-action recording"
RECORDING_SHAPE = (480, 640)  # (H, W) of the thesis' Kinect frames
DEPTH_DIR, RGB_DIR, JOINTS_DIR = "depth", "rgb", "joints_2D_GT"
DEPTH_SUFFIX, RGB_SUFFIX, JOINTS_SUFFIX = ".yml", ".png", ".txt"
DEPTH_NODE = "depth"

_FRAME_STEM = re.compile(r"^[0-9]+$")
_MAX_PADDING = 12  # widths probed when looking up the file of one frame

Joints2D = Dict[int, Tuple[float, float]]


class RecordingFrame(NamedTuple):
    """One frame of a thesis recording.

    rgb: (H, W, 3) uint8 in RGB order, or None when the frame has no colour image.
    depth: (H, W) float32 depth in millimetres, 0 where there is no measurement.
    joints_2d: {joint id: (x, y) pixels} from ``joints_2D_GT/``, or None when the frame
        was not annotated. Ids are the recording's own, not torchhand keypoint indices.
    """

    rgb: Optional[np.ndarray]
    depth: np.ndarray
    joints_2d: Optional[Joints2D]


# ---------------------------------------------------------------- files of a frame
def _check_frame_index(k) -> int:
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 0:
        raise ValueError(f"frame number must be a non-negative int, got {k!r}")
    return int(k)


def _scan(folder: Path, suffix: str) -> Dict[int, Path]:
    """{frame number: path} of the files ``<digits><suffix>`` in folder ({} if it is missing)."""
    found: Dict[int, Path] = {}
    if not folder.is_dir():
        return found
    for path in folder.iterdir():
        if path.suffix != suffix or not _FRAME_STEM.match(path.stem) or not path.is_file():
            continue
        k = int(path.stem)
        if k in found:
            first, second = sorted([found[k].name, path.name])
            raise SequenceError(f"{folder}: frame {k} has two files, {first} and {second}")
        found[k] = path
    return found


def _find(folder: Path, k: int, suffix: str) -> Optional[Path]:
    """The file of frame k in folder, whatever its zero-padding; None if there is none."""
    names = sorted({f"{k:0{width}d}{suffix}" for width in range(1, _MAX_PADDING + 1)})
    hits = [folder / n for n in names if (folder / n).is_file()]
    if len(hits) > 1:
        raise SequenceError(f"{folder}: frame {k} has several files: {', '.join(p.name for p in hits)}")
    return hits[0] if hits else None


def _depth_folder(root: Path) -> Path:
    folder = root / DEPTH_DIR
    if not folder.is_dir():
        raise SequenceError(f"{folder}: folder not found; {root} is not a Hands-in-Action recording "
                            f"(expected {DEPTH_DIR}/NNN{DEPTH_SUFFIX})")
    return folder


# ---------------------------------------------------------------- readers
def _read_depth_yml(path: Path, depth_scale: Optional[float]) -> np.ndarray:
    if not path.is_file():
        raise SequenceError(f"{path}: depth file not found")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as err:  # OpenCV >= 5 wraps parse errors in SystemError
        cause = err.__cause__ if err.__cause__ is not None else err
        msg = str(cause).strip().splitlines()[-1] if str(cause).strip() else type(cause).__name__
        raise SequenceError(f"{path}: unreadable OpenCV YAML file ({msg})") from None
    try:
        if not fs.isOpened():
            raise SequenceError(f"{path}: unreadable OpenCV YAML file")
        node = fs.getNode(DEPTH_NODE)
        if node.isNone():
            raise SequenceError(f"{path}: no node named {DEPTH_NODE!r} (expected '{DEPTH_NODE}: !!opencv-matrix')")
        if not node.isMap():
            raise SequenceError(f"{path}: node {DEPTH_NODE!r} is not an OpenCV matrix")
        try:
            mat = node.mat()
        except cv2.error as err:
            raise SequenceError(f"{path}: node {DEPTH_NODE!r} is not a valid OpenCV matrix "
                                f"({str(err).strip().splitlines()[-1]})") from None
    finally:
        fs.release()
    if mat is None:
        raise SequenceError(f"{path}: node {DEPTH_NODE!r} is not an OpenCV matrix")
    if mat.shape != RECORDING_SHAPE:
        raise SequenceError(f"{path}: depth matrix has shape {mat.shape}, expected {RECORDING_SHAPE} "
                            "(rows x cols, single channel)")
    if mat.dtype not in (np.uint16, np.float32, np.float64):
        raise SequenceError(f"{path}: depth matrix has type {mat.dtype}; expected 16U (mm) or 32F")
    if mat.dtype != np.uint16:
        if np.isnan(mat).any():
            raise SequenceError(f"{path}: depth contains {int(np.isnan(mat).sum())} NaN values")
        if np.isinf(mat).any():
            raise SequenceError(f"{path}: depth contains {int(np.isinf(mat).sum())} infinite values")
        if (mat < 0).any():
            raise SequenceError(f"{path}: depth contains {int((mat < 0).sum())} negative values")
    depth = mat.astype(np.float32)
    if depth_scale is not None:
        return depth * np.float32(depth_scale)
    valid = depth[depth > 0]
    if valid.size and np.median(valid) < 20:
        raise SequenceError(
            f"{path}: median depth {float(np.median(valid)):.3g} is implausibly small for millimetres; the "
            f"map looks like metres (pass depth_scale=1000.0, millimetres per stored unit)")
    return depth


def _read_rgb_png(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise SequenceError(f"{path}: unreadable colour image")
    if img.shape[:2] != RECORDING_SHAPE:
        raise SequenceError(f"{path}: colour image is {img.shape[1]}x{img.shape[0]}, expected "
                            f"{RECORDING_SHAPE[1]}x{RECORDING_SHAPE[0]}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _read_joints_txt(path: Path) -> Joints2D:
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise SequenceError(f"{path}: not a text file ({err})") from None
    joints: Joints2D = {}
    for line_no, line in enumerate(text.splitlines(), 1):
        tokens = line.split("#", 1)[0].replace(",", " ").split()
        if not tokens:
            continue
        where = f"{path}, line {line_no}"
        if len(tokens) != 3:
            raise SequenceError(f"{where}: expected 'id x y', got {line.strip()!r}")
        try:
            jid_f, x, y = (float(t) for t in tokens)
        except ValueError:
            raise SequenceError(f"{where}: expected numbers 'id x y', got {line.strip()!r}") from None
        if not jid_f.is_integer():
            raise SequenceError(f"{where}: joint id {tokens[0]!r} is not an integer")
        if not (math.isfinite(x) and math.isfinite(y)):
            raise SequenceError(f"{where}: non-finite coordinates {line.strip()!r}")
        jid = int(jid_f)
        if jid in joints:
            raise SequenceError(f"{where}: joint {jid} is annotated twice")
        joints[jid] = (x, y)
    return joints


def _read_frame(depth_path: Path, rgb_path: Optional[Path], joints_path: Optional[Path],
                depth_scale: Optional[float]) -> RecordingFrame:
    depth = _read_depth_yml(depth_path, depth_scale)
    rgb = _read_rgb_png(rgb_path) if rgb_path is not None else None
    joints = _read_joints_txt(joints_path) if joints_path is not None else None
    return RecordingFrame(rgb, depth, joints)


def _check_depth_scale(depth_scale) -> Optional[float]:
    if depth_scale is None:
        return None
    scale = float(depth_scale)
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"depth_scale must be a positive number of millimetres per stored unit, got {depth_scale!r}")
    return scale


def list_recording_frames(root) -> List[int]:
    """Frame numbers of a recording (its ``depth/*.yml`` files), sorted numerically.

    Raises SequenceError if ``depth/`` is missing or two files name the same frame.
    """
    return sorted(_scan(_depth_folder(Path(root)), DEPTH_SUFFIX))


def read_recording_frame(root, k: int, *, depth_scale: Optional[float] = None) -> RecordingFrame:
    """Read frame number ``k`` of a thesis recording.

    Args:
        root: the recording folder (with ``depth/``, optionally ``rgb/``, ``joints_2D_GT/``).
        k: frame number as in the file names (any zero-padding).
        depth_scale: millimetres per stored depth unit (e.g. 1000 for a 32F map in
            metres). None: the values are millimetres, and a map whose median valid
            value is below 20 is rejected as probably metres.

    Returns:
        RecordingFrame(rgb or None, depth (480, 640) float32 mm, joints_2d or None).

    Raises:
        SequenceError naming the file: missing depth file, unreadable YAML, no ``depth``
        node, wrong matrix size or type, NaN/inf/negative depth, metres-looking depth,
        unreadable or wrongly sized colour image, malformed annotation line.
    """
    root = Path(root)
    k = _check_frame_index(k)
    scale = _check_depth_scale(depth_scale)
    folder = _depth_folder(root)
    depth_path = _find(folder, k, DEPTH_SUFFIX)
    if depth_path is None:
        raise SequenceError(f"{folder / f'{k:03d}{DEPTH_SUFFIX}'}: depth file not found (frame {k})")
    return _read_frame(depth_path, _find(root / RGB_DIR, k, RGB_SUFFIX), _find(root / JOINTS_DIR, k, JOINTS_SUFFIX), scale)


# ---------------------------------------------------------------- writer (test samples)
def _is_empty_dir(path: Path) -> bool:
    return path.is_dir() and next(path.iterdir(), None) is None


def write_recording_sample(
    root,
    depth_frames: Sequence[np.ndarray],
    rgb_frames: Optional[Sequence[Optional[np.ndarray]]] = None,
    joints_2d: Optional[Union[Mapping[int, Mapping[int, Sequence[float]]], Sequence[Optional[Mapping]]]] = None,
    *,
    digits: int = 3,
) -> Path:
    """Write a recording in the thesis layout (frames numbered 0, 1, ...).

    Args:
        root: folder to create; must be missing or empty (FileExistsError otherwise).
        depth_frames: (480, 640) arrays; uint16 is written as 16U, float32/float64 as 32F.
        rgb_frames: None, or one (480, 640, 3) uint8 RGB image (or None) per frame.
        joints_2d: None, {frame: {joint id: (x, y)}}, or one {id: (x, y)} (or None) per
            frame; frames without labels get no ``joints_2D_GT`` file.
        digits: zero-padding width of the file names (3 in the thesis).

    Returns:
        root as a Path. All inputs are checked before anything is written.
    """
    root = Path(root)
    if root.exists() and not _is_empty_dir(root):
        raise FileExistsError(f"{root} exists and is not an empty folder; refusing to write a recording into it")
    depths = _checked_depths(depth_frames)
    n = len(depths)
    rgbs: List[Optional[np.ndarray]] = [None] * n
    if rgb_frames is not None:
        if len(rgb_frames) != n:
            raise ValueError(f"rgb_frames has {len(rgb_frames)} images for {n} depth frames")
        for i, img in enumerate(rgb_frames):
            if img is None:
                continue
            img = np.asarray(img)
            if img.shape != RECORDING_SHAPE + (3,) or img.dtype != np.uint8:
                raise ValueError(f"rgb_frames[{i}] must be a {RECORDING_SHAPE + (3,)} uint8 image, "
                                 f"got {img.dtype} with shape {img.shape}")
            rgbs[i] = img
    labels = _checked_labels(joints_2d, n)
    for sub in (DEPTH_DIR,) + ((RGB_DIR,) if any(r is not None for r in rgbs) else ()) + \
               ((JOINTS_DIR,) if labels else ()):
        (root / sub).mkdir(parents=True, exist_ok=True)
    for k in range(n):
        stem = f"{k:0{digits}d}"
        fs = cv2.FileStorage(str(root / DEPTH_DIR / f"{stem}{DEPTH_SUFFIX}"), cv2.FILE_STORAGE_WRITE)
        try:
            fs.write(DEPTH_NODE, depths[k])
        finally:
            fs.release()
        if rgbs[k] is not None:
            write_rgb(root / RGB_DIR / f"{stem}{RGB_SUFFIX}", rgbs[k])
        if k in labels:
            lines = [f"{jid} {x!r} {y!r}\n" for jid, (x, y) in sorted(labels[k].items())]
            (root / JOINTS_DIR / f"{stem}{JOINTS_SUFFIX}").write_text("".join(lines))
    return root


def _checked_depths(depth_frames: Sequence[np.ndarray]) -> List[np.ndarray]:
    """The depth frames as uint16 (16U) or float32 (32F) recording arrays, or a clear error."""
    depths = []
    for i, d in enumerate(depth_frames):
        d = np.asarray(d)
        if d.shape != RECORDING_SHAPE:
            raise ValueError(f"depth_frames[{i}] has shape {d.shape}, expected {RECORDING_SHAPE}")
        if d.dtype == np.uint16:
            depths.append(d)
        elif d.dtype in (np.float32, np.float64):
            if not np.isfinite(d).all() or (d < 0).any():
                raise ValueError(f"depth_frames[{i}] contains NaN, inf or negative values")
            depths.append(d.astype(np.float32))
        else:
            raise TypeError(f"depth_frames[{i}] has dtype {d.dtype}; expected uint16 (16U) or float32 (32F)")
    return depths


def _checked_labels(joints_2d, n: int) -> Dict[int, "Joints2D"]:
    """``write_recording_sample``'s 2D labels by frame, checked against n frames."""
    labels: Dict[int, Joints2D] = {}
    if joints_2d is not None:
        items = joints_2d.items() if isinstance(joints_2d, Mapping) else enumerate(joints_2d)
        for k, joints in items:
            if joints is None:
                continue
            k = _check_frame_index(k)
            if k >= n:
                raise ValueError(f"joints_2d has labels for frame {k} but there are only {n} depth frames")
            clean: Joints2D = {}
            for jid, xy in joints.items():
                x, y = (float(v) for v in xy)
                if not (math.isfinite(x) and math.isfinite(y)):
                    raise ValueError(f"joints_2d[{k}][{jid}] is not finite: {xy!r}")
                clean[int(jid)] = (x, y)
            labels[k] = clean
    return labels


# ---------------------------------------------------------------- conversion
def _overlaps(a: Path, b: Path) -> bool:
    a, b = a.resolve(), b.resolve()
    return a == b or a in b.parents or b in a.parents


def convert_recording(
    root,
    out,
    models: Union[str, Sequence[str]],
    init_theta: Optional[np.ndarray] = None,
    name: Optional[str] = None,
    force: bool = False,
    *,
    depth_scale: Optional[float] = None,
    progress: bool = True,
) -> Path:
    """Convert a thesis recording to a torchhand sequence folder (layouts in the module docstring).

    Args:
        root: the recording folder.
        out: the sequence folder to write; must be missing or empty unless ``force``.
        models: model names (or ``.npz`` paths) in the order of their slices in theta.
        init_theta: (D,) pose of frame 0, written to ``init_pose.json`` when given.
        name: sequence name; defaults to the recording folder's name.
        force: replace a non-empty ``out`` (the whole folder is replaced).
        depth_scale: millimetres per stored depth unit, see :func:`read_recording_frame`.
        progress: show a tqdm progress bar over frames.

    The sequence is written to a temporary folder next to ``out`` and moved into place
    at the end, so an error in any frame leaves ``out`` as it was.

    Returns:
        out as a Path.

    Raises:
        FileExistsError: ``out`` is not empty and ``force`` is False (nothing is touched).
        ValueError: ``out`` and ``root`` overlap, or a bad argument.
        SequenceError: a bad recording (the message names the file).
    """
    root, out = Path(root), Path(out)
    models, init_theta = _check_conversion(root, out, models, init_theta, force)
    scale = _check_depth_scale(depth_scale)
    name = name if name is not None else root.resolve().name
    depth_files, rgb_files, joint_files = _recording_files(root)
    numbers = sorted(depth_files)
    has_rgb = rgb_files is not None
    source: Dict = {"format": RECORDING_FORMAT, "path": str(root)}
    if numbers != list(range(len(numbers))):
        warnings.warn(f"{root / DEPTH_DIR}: frame numbers are not 0..{len(numbers) - 1} (first {numbers[0]}, "
                      f"last {numbers[-1]}); frames are renumbered consecutively", stacklevel=2)
        source["frame_numbers"] = numbers

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    try:
        seq = SequenceLayout(tmp)
        frames_2d = _convert_frames(seq, numbers, depth_files, rgb_files, joint_files, scale, f"convert {name}",
                                    progress)
        if joint_files:
            seq.gt.root.mkdir()
            annotations = {
                "source": f"{RECORDING_FORMAT}: {JOINTS_DIR}/",
                "units": "px",
                "note": "sparse manual labels; joint ids follow the recording's own numbering and are not "
                        "torchhand keypoint indices; frames without labels have no entry",
                "frames": frames_2d,
            }
            seq.gt.annotations_2d.write_text(json.dumps(annotations))
        info = SequenceInfo(name=name, cameras=[kinect_camera()], models=models, frames=len(numbers),
                            depth_unit_mm=1.0, has_rgb=has_rgb, source=source)
        write_sequence_info(tmp, info, init_theta)
        _move_into_place(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def _check_conversion(root: Path, out: Path, models, init_theta, force: bool) -> tuple:
    """(models as a list of str, init_theta as a float64 vector or None) of
    :func:`convert_recording`'s arguments, or a clear error before anything is written."""
    if not root.is_dir():
        raise SequenceError(f"{root}: recording folder not found")
    if _overlaps(root, out):
        raise ValueError(f"out ({out}) must not be, contain or lie inside the recording folder ({root})")
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out} exists and is not a folder")
    if out.is_dir() and not _is_empty_dir(out) and not force:
        raise FileExistsError(f"{out} is not empty; pass force=True to replace it")
    if isinstance(models, (str, os.PathLike)):
        models = [models]
    models = [str(m) for m in models]
    if not models:
        raise ValueError("models must name at least one model")
    if init_theta is not None:
        init_theta = np.asarray(init_theta, np.float64)
        if init_theta.ndim != 1 or not np.isfinite(init_theta).all():
            raise ValueError(f"init_theta must be a finite (D,) vector, got shape {init_theta.shape}")
    return models, init_theta


def _recording_files(root: Path) -> tuple:
    """(depth, colour, joint label files) of a recording, each {frame number: path};
    colour is None unless every depth frame has an image (a warning says so), and
    labels of frames without depth are left out (with a warning)."""
    depth_files = _scan(_depth_folder(root), DEPTH_SUFFIX)
    numbers = sorted(depth_files)
    if not numbers:
        raise SequenceError(f"{root / DEPTH_DIR}: no depth frames (expected NNN{DEPTH_SUFFIX} files)")
    rgb_files = _scan(root / RGB_DIR, RGB_SUFFIX)
    joint_files = _scan(root / JOINTS_DIR, JOINTS_SUFFIX)
    has_rgb = all(k in rgb_files for k in numbers)
    if rgb_files and not has_rgb:
        missing = [k for k in numbers if k not in rgb_files]
        warnings.warn(f"{root / RGB_DIR}: {len(missing)} of {len(numbers)} frames have no colour image "
                      f"(first: {missing[0]}); the converted sequence has no rgb/", stacklevel=3)
    orphans = sorted(set(joint_files) - set(depth_files))
    if orphans:
        warnings.warn(f"{root / JOINTS_DIR}: annotations of frames {orphans[:10]} have no depth frame and "
                      "are not converted", stacklevel=3)
    return depth_files, rgb_files if has_rgb else None, joint_files


def _convert_frames(seq: SequenceLayout, numbers: List[int], depth_files: dict, rgb_files: Optional[dict],
                    joint_files: dict, scale: float, desc: str, progress: bool) -> Dict[str, Dict[str, List[float]]]:
    """Write the recording's frames ``numbers`` as frames 0, 1, ... of ``seq`` (depth, and
    colour when ``rgb_files``); returns the 2D joint labels by frame."""
    seq.depth_dir().mkdir()
    if rgb_files is not None:
        seq.rgb_dir().mkdir()
    frames_2d: Dict[str, Dict[str, List[float]]] = {}
    for i, k in enumerate(tqdm(numbers, desc=desc, unit="frame", disable=not progress)):
        frame = _read_frame(depth_files[k], rgb_files[k] if rgb_files is not None else None, joint_files.get(k), scale)
        write_depth(seq.depth(i), frame.depth)
        if frame.rgb is not None:
            write_rgb(seq.rgb(i), frame.rgb)
        if frame.joints_2d is not None:
            frames_2d[str(i)] = {str(j): [x, y] for j, (x, y) in sorted(frame.joints_2d.items())}
    return frames_2d


def _move_into_place(tmp: Path, out: Path) -> None:
    """Rename tmp to out; a previous out (empty, or replaced under force) is removed."""
    if not out.exists():
        tmp.rename(out)
        return
    if _is_empty_dir(out):
        out.rmdir()
        tmp.rename(out)
        return
    old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
    old.rmdir()
    out.rename(old)
    try:
        tmp.rename(out)
    except BaseException:
        old.rename(out)
        raise
    shutil.rmtree(old, ignore_errors=True)
