"""Import a user's depth recording: a folder of 16-bit depth PNGs (and optional colour
images) becomes a torchhand sequence folder (datasets/README.md layout).

Frames are taken in the natural order of their file names (``30.png`` before
``110.png``); the depth images are copied byte for byte, their unit kept as
``depth_unit_mm`` in ``sequence.json``, so nothing of the recording is rounded away. The
original name of every frame is kept in ``sequence.json`` (``source.files``).
A segmentation setting (:mod:`torchhand.tracking.segmentation`) can be stored with the
sequence, so that ``torchhand track`` and ``torchhand init`` segment it the same way.

The thesis' own recordings (YAML depth, joints files) have their converter in
:mod:`torchhand.data.recording`.
"""

from __future__ import annotations

import glob
import json
import re
import shutil
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import cv2
import numpy as np

from torchhand.data.layout import SequenceError, SequenceInfo, SequenceLayout, write_sequence_info
from torchhand.geometry.camera import Camera
from torchhand.io.assets import find_model
from torchhand.io.output_dir import prepare_output_dir

__all__ = ["Intrinsics", "read_intrinsics", "natural_key", "check_intrinsics", "check_depth_pngs", "depth_files",
           "import_depth_folder"]


class Intrinsics(dict):
    """fx, fy, cx, cy in px (pixel centres at integers, OpenCV's convention)."""


def read_intrinsics(path) -> Intrinsics:
    """An intrinsics JSON file: ``{"fx": .., "fy": .., "cx": .., "cy": ..}`` (optionally
    ``width``, ``height``, ``depth_unit_mm``), or a torchhand camera dict with ``K``."""
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"--intrinsics {path}: file not found") from None
    except json.JSONDecodeError as err:
        raise ValueError(f"--intrinsics {path}: invalid JSON ({err})") from None
    if "K" in d:
        K = np.asarray(d["K"], np.float64)
        d = {**d, "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}
    missing = [k for k in ("fx", "fy", "cx", "cy") if k not in d]
    if missing:
        raise ValueError(f"--intrinsics {path}: missing {missing} (expected fx, fy, cx, cy in pixels)")
    return Intrinsics({k: d[k] for k in ("fx", "fy", "cx", "cy", "width", "height", "depth_unit_mm") if k in d})


def natural_key(name: str) -> List:
    """Sort key: digit runs compare as numbers (``"30.png" < "110.png"``)."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def check_intrinsics(k: Dict, width: int, height: int, where: str) -> None:
    """Raise ValueError (naming ``where``) unless fx, fy, cx, cy are plausible pixels for a
    ``width`` x ``height`` image (and ``k``'s optional width and height match it)."""
    for name in ("fx", "fy", "cx", "cy"):
        v = k.get(name)
        if v is None or not isinstance(v, (int, float)) or not np.isfinite(v):
            raise ValueError(f"{where}: intrinsics {name} must be a finite number of pixels, got {v!r}")
    for name in ("fx", "fy"):
        if k[name] <= 0:
            raise ValueError(f"{where}: focal length {name} = {k[name]} must be positive (pixels)")
        if not 0.2 * max(width, height) <= k[name] <= 20 * max(width, height):
            raise ValueError(f"{where}: focal length {name} = {k[name]} px is implausible for a {width}x{height} "
                             "image (expected 0.2-20 times the image size; give it in pixels, not mm)")
    if not (0 <= k["cx"] < width and 0 <= k["cy"] < height):
        raise ValueError(f"{where}: principal point ({k['cx']}, {k['cy']}) lies outside the {width}x{height} image")
    for name, size in (("width", width), ("height", height)):
        if name in k and int(k[name]) != size:
            raise ValueError(f"{where}: the intrinsics are for {name} {k[name]}, the images have {size}")


def check_depth_pngs(files: Sequence[Path], hint: str = "") -> Tuple[int, int]:
    """(H, W) of the depth frames ``files``; a SequenceError naming the file unless every
    one is a readable single-channel 16-bit PNG of one size (``hint``: said after a wrong kind)."""
    size = None
    for p in files:
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise SequenceError(f"{p}: unreadable PNG")
        if img.ndim != 2 or img.dtype != np.uint16:
            kind = "colour" if img.ndim == 3 else f"{img.dtype}"
            raise SequenceError(f"{p}: a depth frame must be a single-channel 16-bit PNG, got a {kind} image "
                                f"of shape {img.shape}" + (f" ({hint})" if hint else ""))
        if size is None:
            size, first = img.shape, p
        elif img.shape != size:
            raise SequenceError(f"{p}: {img.shape[1]}x{img.shape[0]} pixels, but {first.name} is "
                                f"{size[1]}x{size[0]}: all frames of a sequence must have one size")
    return size


def depth_files(src: Path) -> List[Path]:
    """The ``.png`` files of the folder ``src`` in natural order; a SequenceError naming
    it when it is no folder or holds none."""
    if not src.is_dir():
        raise SequenceError(f"{src}: not a folder (give the folder holding the depth PNGs)")
    files = sorted((p for p in src.iterdir() if p.suffix.lower() == ".png" and p.is_file()),
                   key=lambda p: natural_key(p.name))
    if not files:
        raise SequenceError(f"{src}: no .png files (expected 16-bit depth PNGs)")
    return files


def import_depth_folder(src, out, intrinsics: Dict, depth_unit_mm: float, models: Sequence[str] = ("hand_right",),
                        rgb: Optional[str] = None, fps: float = 30.0, segmentation: Optional[Dict] = None,
                        force: bool = False) -> SequenceInfo:
    """Write the sequence folder ``out`` from the depth PNGs of ``src``.

    Args:
        src: folder of single-channel 16-bit PNGs, one per frame.
        out: sequence folder to create (must be new or empty unless ``force``).
        intrinsics: fx, fy, cx, cy in px (:func:`read_intrinsics`).
        depth_unit_mm: millimetres per depth unit (RealSense SR305: 0.125, Kinect: 1).
        models: the scene, shipped names or model ``.npz`` paths (checked to exist).
        rgb: optional glob of colour images, one per depth frame, matched by natural order.
        segmentation: settings stored in ``sequence.json`` for ``track`` and ``init``.
    Returns:
        the written :class:`SequenceInfo`. Every frame is checked before anything is
        written, so a bad recording leaves no partial folder.
    """
    src = Path(src)
    files = depth_files(src)
    if not (isinstance(depth_unit_mm, (int, float)) and np.isfinite(depth_unit_mm) and depth_unit_mm > 0):
        raise ValueError(f"--depth-unit-mm must be a positive number of millimetres, got {depth_unit_mm!r}")
    for m in models:
        find_model(m)
    H, W = check_depth_pngs(files, "8-bit or colour images are not depth; pass colour with --rgb")
    check_intrinsics(intrinsics, W, H, str(src))
    rgb_files: List[Path] = []
    if rgb:
        rgb_files = sorted((Path(p) for p in glob.glob(rgb)), key=lambda p: natural_key(p.name))
        if len(rgb_files) != len(files):
            raise SequenceError(f"--rgb {rgb}: {len(rgb_files)} colour images for {len(files)} depth frames")
        for p in rgb_files:
            img = cv2.imread(str(p), cv2.IMREAD_COLOR)
            if img is None or img.shape[:2] != (H, W):
                raise SequenceError(f"{p}: colour image unreadable or not {W}x{H}")
    camera = Camera.from_intrinsics(float(intrinsics["fx"]), float(intrinsics["fy"]), float(intrinsics["cx"]),
                                    float(intrinsics["cy"]), W, H, name="camera0")
    out = prepare_output_dir(out, force)
    seq = SequenceLayout(out)
    seq.depth_dir().mkdir()
    for k, p in enumerate(files):
        shutil.copyfile(p, seq.depth(k))
    if rgb_files:
        seq.rgb_dir().mkdir()
        for k, p in enumerate(rgb_files):
            img = cv2.imread(str(p), cv2.IMREAD_COLOR)
            if not cv2.imwrite(str(seq.rgb(k)), img):
                raise OSError(f"cannot write {seq.rgb(k)}")
    source = {"imported_from": str(src.resolve()), "files": [p.name for p in files]}
    if rgb_files:
        source["rgb_files"] = [str(p) for p in rgb_files]
    info = SequenceInfo(out.name, [camera], list(models), len(files), fps, float(depth_unit_mm), bool(rgb_files),
                        source, segmentation)
    write_sequence_info(out, info)
    return info
