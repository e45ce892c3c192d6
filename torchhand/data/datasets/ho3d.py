"""HO-3D (v2 and v3; Hampali et al., CVPR 2020), as published
(github.com/shreyashampali/ho3d), read into a torchhand sequence folder.

The published layout; one sequence is one folder of a split (``train``, ``evaluation``)::

    <root>/<split>/<SEQ>/rgb/NNNN.jpg     colour, 640x480 (v2: .png)
    <root>/<split>/<SEQ>/depth/NNNN.png   8-bit, 3 channels: depth packed in R and G
    <root>/<split>/<SEQ>/meta/NNNN.pkl    a dict per frame: camMat, handJoints3D, ...

Depth: ``depth_m = (R + 256 G) * 0.00012498664727900177`` (:data:`DEPTH_SCALE_M`; B is
unused); it is written as 16-bit millimetres, rounded (the packing's step is 0.125 mm).

Meta pickles (read with :func:`torchhand.io.foreign_files.read_pickle`, which admits
builtin containers and numpy arrays only): ``camMat`` the 3x3 intrinsics, the same for
every frame of a sequence; ``handJoints3D`` the right hand's 21 joints (21, 3) in metres in
the OpenGL camera frame (y up, z towards the viewer). torchhand's camera frame has x right,
y down, z forward: the joints are multiplied by diag(1, -1, -1) and by 1000. In the
evaluation split ``handJoints3D`` holds the root joint only (3,): the wrist is written and
the other 20 joints are NaN (``source.joints``: ``"root only"``).

Joint order: MANO's 16 (wrist; index, middle, little, ring, thumb, three each from the
base) and the five tips (thumb, index, middle, ring, little); :data:`HO3D_TO_STANDARD`
picks them in the standard 21 order (HO-3D's ``jointsMapManoToSimple``).

Errors in the input raise :class:`~torchhand.data.layout.SequenceError` (or, for a
pickle that asks for a class, :class:`~torchhand.io.foreign_files.ForeignFileError`)
naming the file, before anything is written.
"""

from __future__ import annotations

from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch

from torchhand.data.datasets.fpha import check_out_folder, write_imported
from torchhand.data.datasets.nyu import read_packed_png
from torchhand.data.importing import check_intrinsics
from torchhand.data.layout import SequenceError, SequenceInfo, SequenceLayout, read_rgb, write_depth, write_rgb
from torchhand.geometry.camera import Camera
from torchhand.io.foreign_files import read_pickle

__all__ = ["DEPTH_SCALE_M", "HO3D_TO_STANDARD", "OPENGL_TO_CAMERA", "read_ho3d_depth", "read_ho3d_meta",
           "ho3d_files", "import_ho3d"]

#: metres per unit of the packed depth value R + 256 G
DEPTH_SCALE_M = 0.00012498664727900177
#: standard joint k (torchhand.model.joints21) is HO-3D's joint HO3D_TO_STANDARD[k]
HO3D_TO_STANDARD = (0, 13, 14, 15, 16, 1, 2, 3, 17, 4, 5, 6, 18, 10, 11, 12, 19, 7, 8, 9, 20)
#: HO-3D's OpenGL camera frame (y up, z backwards) -> torchhand's (y down, z forward)
OPENGL_TO_CAMERA = np.array([1.0, -1.0, -1.0])
WIDTH, HEIGHT = 640, 480


def read_ho3d_depth(path) -> np.ndarray:
    """An HO-3D depth frame -> (H, W) float64 depth in mm, ``(R + 256 G) * DEPTH_SCALE_M * 1000``;
    an image that is not 8-bit with 3 channels is refused, naming the file."""
    path = Path(path)
    img = read_packed_png(path, "an HO-3D depth frame", "depth in R and G")
    # OpenCV reads BGR: R is channel 2, G channel 1
    packed = img[..., 2].astype(np.float64) + 256.0 * img[..., 1]
    return packed * (DEPTH_SCALE_M * 1000.0)


def read_ho3d_meta(path) -> Tuple[np.ndarray, np.ndarray]:
    """(camMat (3, 3), joints (21, 3) mm in torchhand's camera frame, standard order) of an
    HO-3D meta pickle; a root-only handJoints3D (3,) gives the wrist and NaN elsewhere."""
    path = Path(path)
    meta = read_pickle(path)
    if not isinstance(meta, dict):
        raise SequenceError(f"{path}: an HO-3D meta pickle holds a dict, got {type(meta).__name__}")
    K, joints = meta.get("camMat"), meta.get("handJoints3D")
    K = None if K is None else np.asarray(K, np.float64)
    if K is None or K.shape != (3, 3) or not np.isfinite(K).all():
        raise SequenceError(f"{path}: camMat must be a finite 3x3 matrix, got "
                            f"{'none' if K is None else K.shape}")
    j = None if joints is None else np.asarray(joints, np.float64)
    if j is None or j.shape not in ((21, 3), (3,)):
        raise SequenceError(f"{path}: handJoints3D must have shape (21, 3) or (3,) (the root joint), got "
                            f"{'none' if j is None else j.shape}")
    if j.shape == (3,):
        full = np.full((21, 3), np.nan)
        full[0] = j
        j = full
    return K, j[list(HO3D_TO_STANDARD)] * OPENGL_TO_CAMERA * 1000.0


def ho3d_files(src) -> Tuple[List[Path], List[Path], Optional[List[Path]]]:
    """(depth, meta, rgb or None) files of an HO-3D sequence folder, in frame order; counts
    that differ are refused naming the folders."""
    src = Path(src)
    if not src.is_dir():
        raise SequenceError(f"{src}: not a folder (give one HO-3D sequence, <root>/<split>/<SEQ>)")
    depth = sorted((src / "depth").glob("*.png"))
    meta = sorted((src / "meta").glob("*.pkl"))
    if not depth:
        raise SequenceError(f"{src / 'depth'}: no depth PNGs (an HO-3D sequence holds depth/, meta/ and rgb/)")
    if len(meta) != len(depth):
        raise SequenceError(f"{src}: {len(depth)} depth frames but {len(meta)} meta pickles")
    rgb = sorted(p for p in (src / "rgb").glob("*") if p.suffix.lower() in (".jpg", ".png"))
    if rgb and len(rgb) != len(depth):
        raise SequenceError(f"{src}: {len(depth)} depth frames but {len(rgb)} colour frames")
    stems = [[p.stem for p in files] for files in (depth, meta, rgb) if files]
    if any(s != stems[0] for s in stems):
        raise SequenceError(f"{src}: the frame numbers of depth/, meta/ and rgb/ differ")
    return depth, meta, rgb or None


def _read_metas(meta: List[Path]) -> Tuple[np.ndarray, np.ndarray, bool]:
    """(camMat of the first frame, joints (N, 21, 3) mm, root only?); a camMat that changes is refused."""
    K0, joints = None, []
    for p in meta:
        K, j = read_ho3d_meta(p)
        if K0 is None:
            K0 = K
        elif not np.allclose(K, K0, rtol=0, atol=1e-6):
            raise SequenceError(f"{p}: camMat differs from that of {meta[0]}; a sequence has one camera")
        joints.append(j)
    joints = np.stack(joints)
    return K0, joints, bool(np.isnan(joints[:, 1:]).all())


def import_ho3d(src, out, force: bool = False, segmentation: Optional[Dict] = None) -> SequenceInfo:
    """Write the sequence folder ``out`` from one HO-3D sequence folder (module docstring).

    Returns the written :class:`SequenceInfo`: camera 0 from the first camMat, ``hand_right``,
    16-bit mm depth, colour when the sequence has it, and in ``gt/`` the standard 21 joints
    (N, 1, 21, 3) mm and their projections (N, 1, 21, 2) px. Everything is checked first and
    written into a hidden folder renamed to ``out`` at the end, so a failure leaves ``out`` as it was.
    """
    src, out = Path(src), Path(out)
    depth_files, meta_files, rgb_files = ho3d_files(src)
    check_out_folder(out, force)
    K, joints, root_only = _read_metas(meta_files)
    check_intrinsics({"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}, WIDTH, HEIGHT,
                     str(meta_files[0]))
    camera = Camera.from_intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], WIDTH, HEIGHT, name="ho3d")
    pixels = camera.project(torch.from_numpy(joints)).numpy()
    pixels[~(joints[..., 2] > 0)] = np.nan
    n = len(depth_files)
    source = {"format": "ho3d", "imported_from": str(src.resolve()), "sequence": src.name,
              "split": src.parent.name, "files": [p.name for p in depth_files],
              "joints": "root only (the evaluation split): the other 20 joints are NaN" if root_only else "21"}
    info = SequenceInfo(out.name, [camera], ["hand_right"], n, 30.0, 1.0, rgb_files is not None, source,
                        segmentation)

    def write_frames(seq: SequenceLayout) -> None:
        seq.depth_dir().mkdir(parents=True)
        for k, p in enumerate(depth_files):
            depth = read_ho3d_depth(p)
            if depth.shape != (HEIGHT, WIDTH):
                raise SequenceError(f"{p}: {depth.shape[1]}x{depth.shape[0]} pixels, HO-3D frames are 640x480")
            write_depth(seq.depth(k), depth)
        if rgb_files is not None:
            seq.rgb_dir().mkdir(parents=True)
            for k, p in enumerate(rgb_files):
                write_rgb(seq.rgb(k), read_rgb(p))

    write_imported(out, info, force, write_frames, joints, pixels)
    return info
