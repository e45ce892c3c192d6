"""DexYCB (Chao et al., CVPR 2021), as published (github.com/NVlabs/dex-ycb-toolkit), read
into a torchhand sequence folder: every camera of a recording becomes one rig.

The published layout; one sequence is one grasp recorded by 8 RealSense cameras::

    <root>/<subject>/<YYYYMMDD_HHMMSS>/meta.yml          serials, num_frames, mano_sides, extrinsics, ...
    <root>/<subject>/<YYYYMMDD_HHMMSS>/<serial>/color_000000.jpg                 640x480 colour
    <root>/<subject>/<YYYYMMDD_HHMMSS>/<serial>/aligned_depth_to_color_000000.png  uint16 mm, in the colour camera
    <root>/<subject>/<YYYYMMDD_HHMMSS>/<serial>/labels_000000.npz   joint_3d (1, 21, 3) m, joint_2d (1, 21, 2) px
    <root>/calibration/intrinsics/<serial>_640x480.yml    color: {fx, fy, ppx, ppy}
    <root>/calibration/extrinsics_<name>/extrinsics.yml   master: <serial>; extrinsics: {<serial>: 12 floats}

Cameras: the depth is aligned to the colour camera, so each camera's intrinsics are the
``color`` block of its intrinsics file (``ppx``, ``ppy`` the principal point). The
extrinsics are 3x4 row-major camera-to-master transforms in metres (``X_master = R X_c +
t``). Camera 0 of the sequence is the master (the first selected camera when the master
is not selected), the others follow in ``meta.yml``'s order; world coordinates are camera
0's, in mm, so camera k's ``T_cw`` is ``inv(T_master_k) @ T_master_0`` with t in mm. A
rotation block is projected onto the nearest rotation (the file's rounding); one farther
than 0.01 from orthonormal is refused.

Labels: ``joint_3d`` is the MANO fit's 21 joints in metres in that camera's frame;
``joint_2d`` their projections in px; both are -1 where the frame has no hand pose
(before the hand enters). DexYCB's joint order is manopth's (``dex_ycb_toolkit``'s
``_MANO_JOINTS``): the wrist, then thumb, index, middle, ring and little finger, four
joints each from the base outwards, tips last. Its thumb joints are named as a finger's
(thumb_mcp, thumb_pip, thumb_dip: MANO's thumb1..3, the CMC, MCP and IP joints), so the
order is the standard one joint for joint (:data:`DEXYCB_TO_STANDARD` is the identity).

Ground truth (``gt/``): per frame the 21 joints in each camera's frame, mm, from the
labels of the first camera (camera 0 first) that has the hand, moved by the rig
(``keypoints21_3d.npy`` (N, C, 21, 3)); each camera's own 2D labels
(``keypoints21_2d.npy`` (N, C, 21, 2)); ``keypoints21_valid.npy`` (N, 21), False in frames
without a hand pose (their joints are NaN; ``source.frames_without_pose`` lists them).
Cameras whose labels, moved to camera 0, disagree with those by more than
:data:`AGREE_MM` are warned about, naming the file (the calibration does not fit the labels).

Refused, naming the file, before anything is written (a
:class:`~torchhand.data.layout.SequenceError`, or a
:class:`~torchhand.io.foreign_files.ForeignFileError` for a YAML file that is not plain
data): a missing ``meta.yml``, intrinsics or extrinsics file; a serial the extrinsics
lack; camera folders that disagree with ``meta.yml``'s serials; colour, depth and label
counts that differ from each other or from ``num_frames``; labels of other shapes; depth
that is not 16-bit single-channel of 640x480.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Dict, List, NamedTuple, Optional, Sequence, Tuple

import numpy as np
import torch

from torchhand.data.datasets.fpha import check_out_folder, write_imported
from torchhand.data.importing import check_depth_pngs, check_intrinsics
from torchhand.data.layout import SequenceError, SequenceInfo, SequenceLayout, read_rgb, write_rgb
from torchhand.geometry.camera import Camera
from torchhand.io.foreign_files import read_yaml
from torchhand.model.joints21 import STANDARD_JOINT_NAMES

__all__ = ["DEXYCB_JOINT_NAMES", "STANDARD_FROM_DEXYCB", "DEXYCB_TO_STANDARD", "AGREE_MM", "DexYCBMeta",
           "DexYCBCamera", "read_dexycb_meta", "read_dexycb_calibration", "dexycb_files", "read_dexycb_labels",
           "dexycb_rig", "import_dexycb", "write_dexycb"]

WIDTH, HEIGHT, FPS = 640, 480, 30.0
COLOR, DEPTH, LABELS = "color_{:06d}.jpg", "aligned_depth_to_color_{:06d}.png", "labels_{:06d}.npz"

#: DexYCB's joint order (the labels' ``joint_3d`` rows), as its toolkit names them.
DEXYCB_JOINT_NAMES = ("wrist",) + tuple(f"{f}_{j}" for f in ("thumb", "index", "middle", "ring", "little")
                                        for j in ("mcp", "pip", "dip", "tip"))

#: Each standard joint (:data:`~torchhand.model.joints21.STANDARD_JOINT_NAMES`) and the DexYCB joint it is:
#: the thumb's mcp/pip/dip are its CMC, MCP and IP joints.
STANDARD_FROM_DEXYCB = {s: d for s, d in zip(STANDARD_JOINT_NAMES, DEXYCB_JOINT_NAMES)}

#: (21,) index into DexYCB's order of each standard joint (the identity): ``standard = dexycb[..., DEXYCB_TO_STANDARD, :]``.
DEXYCB_TO_STANDARD = np.array([DEXYCB_JOINT_NAMES.index(STANDARD_FROM_DEXYCB[n]) for n in STANDARD_JOINT_NAMES])

#: mm: two cameras' labels of one frame, moved to camera 0, farther apart than this are warned about
AGREE_MM = 5.0

_HANDS = {"right": "hand_right", "left": "hand_left"}


class DexYCBMeta(NamedTuple):
    """A sequence's ``meta.yml``: camera serials (str), frames, the hand model
    (``hand_right``/``hand_left`` from ``mano_sides``), the extrinsics' name."""

    path: Path
    serials: List[str]
    frames: int
    model: str
    extrinsics: str


class DexYCBCamera(NamedTuple):
    """One camera of the rig: serial, intrinsics (fx, fy, cx, cy px), camera-to-master
    (4, 4) float64 with t in mm."""

    serial: str
    intrinsics: Dict[str, float]
    to_master: np.ndarray


def _root(src: Path) -> Path:
    """``<root>`` of ``<root>/<subject>/<YYYYMMDD_HHMMSS>``."""
    return src.parents[1]


def read_dexycb_meta(src) -> DexYCBMeta:
    """The ``meta.yml`` of the sequence folder ``src`` (module docstring)."""
    src = Path(src)
    path = src / "meta.yml"
    if not src.is_dir():
        raise SequenceError(f"{src}: not a folder (give one DexYCB sequence, <root>/<subject>/<YYYYMMDD_HHMMSS>)")
    if not path.is_file():
        raise SequenceError(f"{path}: not found (a DexYCB sequence folder holds meta.yml and one folder per camera)")
    meta = read_yaml(path)
    if not isinstance(meta, dict):
        raise SequenceError(f"{path}: expected a mapping with serials, num_frames, mano_sides, extrinsics")
    missing = [k for k in ("serials", "num_frames", "mano_sides", "extrinsics") if k not in meta]
    if missing:
        raise SequenceError(f"{path}: missing {', '.join(missing)}")
    serials, sides, frames = meta["serials"], meta["mano_sides"], meta["num_frames"]
    if not isinstance(serials, list) or not serials or len(set(map(str, serials))) != len(serials):
        raise SequenceError(f"{path}: serials must be a non-empty list of distinct camera serials, got {serials!r}")
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        raise SequenceError(f"{path}: num_frames must be a positive integer, got {frames!r}")
    if not isinstance(sides, list) or len(sides) != 1 or sides[0] not in _HANDS:
        raise SequenceError(f"{path}: mano_sides must list one hand, 'right' or 'left', got {sides!r}")
    return DexYCBMeta(path, [str(s) for s in serials], frames, _HANDS[sides[0]], str(meta["extrinsics"]))


def _intrinsics(root: Path, serial: str) -> Dict[str, float]:
    path = root / "calibration" / "intrinsics" / f"{serial}_{WIDTH}x{HEIGHT}.yml"
    if not path.is_file():
        raise SequenceError(f"{path}: not found (the intrinsics of camera {serial}; DexYCB keeps them in "
                            f"<root>/calibration/intrinsics/<serial>_{WIDTH}x{HEIGHT}.yml)")
    data = read_yaml(path)
    color = data.get("color") if isinstance(data, dict) else None
    if not isinstance(color, dict) or any(k not in color for k in ("fx", "fy", "ppx", "ppy")):
        raise SequenceError(f"{path}: expected color: {{fx, fy, ppx, ppy}} (the colour camera's intrinsics)")
    k = {"fx": color["fx"], "fy": color["fy"], "cx": color["ppx"], "cy": color["ppy"]}
    check_intrinsics(k, WIDTH, HEIGHT, str(path))
    return {n: float(v) for n, v in k.items()}


def _rigid_mm(values, path: Path, serial: str) -> np.ndarray:
    """(4, 4) float64 of 12 row-major floats (metres), rotation made exact, t in mm."""
    try:
        T = np.asarray(values, np.float64).reshape(3, 4)
    except (TypeError, ValueError):
        raise SequenceError(f"{path}: extrinsics of {serial} must be 12 numbers (a 3x4 matrix), got {values!r}") from None
    if not np.isfinite(T).all():
        raise SequenceError(f"{path}: extrinsics of {serial} hold NaN or inf")
    U, _, Vt = np.linalg.svd(T[:, :3])
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    if np.abs(R - T[:, :3]).max() > 1e-2 or np.linalg.det(T[:, :3]) <= 0:
        raise SequenceError(f"{path}: extrinsics of {serial}: the 3x3 block is not a rotation (camera-to-master, "
                            "row-major 3x4 in metres)")
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R, T[:, 3] * 1000.0
    if np.abs(out[:3, 3]).max() > 20_000:
        raise SequenceError(f"{path}: extrinsics of {serial} move the camera {np.abs(out[:3, 3]).max() / 1000:.0f} m; "
                            "DexYCB's translations are in metres")
    return out


def read_dexycb_calibration(src, serials: Sequence[str], extrinsics: str) -> Tuple[str, List[DexYCBCamera]]:
    """(master serial, the cameras ``serials``) from ``<root>/calibration`` of the sequence ``src``."""
    root = _root(Path(os.path.abspath(src)))
    path = root / "calibration" / f"extrinsics_{extrinsics}" / "extrinsics.yml"
    if not path.is_file():
        raise SequenceError(f"{path}: not found (the extrinsics {extrinsics!r} that meta.yml names)")
    data = read_yaml(path)
    table = data.get("extrinsics") if isinstance(data, dict) else None
    if not isinstance(table, dict) or "master" not in data:
        raise SequenceError(f"{path}: expected master: <serial> and extrinsics: {{<serial>: 12 numbers}}")
    table = {str(k): v for k, v in table.items()}
    master = str(data["master"])
    for s in list(serials) + [master]:
        if s not in table:
            raise SequenceError(f"{path}: no extrinsics for camera {s} (it has {', '.join(sorted(table))})")
    return master, [DexYCBCamera(s, _intrinsics(root, s), _rigid_mm(table[s], path, s)) for s in serials]


def _select(meta: DexYCBMeta, master: str, cameras: Optional[Sequence[str]]) -> List[str]:
    """The serials to import, camera 0 first: the master when selected, then meta.yml's order."""
    chosen = list(meta.serials) if cameras is None else [str(c).strip() for c in cameras]
    unknown = [c for c in chosen if c not in meta.serials]
    if unknown or not chosen or len(set(chosen)) != len(chosen):
        raise SequenceError(f"{meta.path}: --cameras {','.join(chosen)}: give distinct serials among "
                            f"{', '.join(meta.serials)}" + (f" ({', '.join(unknown)} not listed)" if unknown else ""))
    ordered = [s for s in meta.serials if s in chosen]
    return sorted(ordered, key=lambda s: s != master)


def dexycb_files(src, meta: DexYCBMeta, serials: Sequence[str]) -> Dict[str, Dict[str, List[Path]]]:
    """Per serial ``{"color", "depth", "labels"}`` file lists of ``meta.frames`` frames;
    camera folders other than meta.yml's serials, and counts that differ, are refused."""
    src = Path(src)
    folders = sorted(p.name for p in src.iterdir() if p.is_dir())
    if sorted(meta.serials) != folders:
        extra, absent = sorted(set(folders) - set(meta.serials)), sorted(set(meta.serials) - set(folders))
        raise SequenceError(f"{meta.path}: lists {len(meta.serials)} cameras, {src} holds {len(folders)} camera "
                            "folders" + (f"; missing: {', '.join(absent)}" if absent else "")
                            + (f"; not listed: {', '.join(extra)}" if extra else ""))
    files = {}
    for s in serials:
        d = src / s
        kinds = {"color": sorted(d.glob("color_*.jpg")), "depth": sorted(d.glob("aligned_depth_to_color_*.png")),
                 "labels": sorted(d.glob("labels_*.npz"))}
        counts = {k: len(v) for k, v in kinds.items()}
        if len(set(counts.values())) != 1 or counts["depth"] != meta.frames:
            raise SequenceError(f"{d}: {counts['color']} colour, {counts['depth']} depth and {counts['labels']} label "
                                f"files, but {meta.path} has num_frames {meta.frames}")
        expected = {k: [d / fmt.format(i) for i in range(meta.frames)]
                    for k, fmt in (("color", COLOR), ("depth", DEPTH), ("labels", LABELS))}
        for k, paths in expected.items():
            gap = next((p for p in paths if not p.is_file()), None)
            if gap is not None:
                raise SequenceError(f"{gap}: missing (frames are numbered 0..{meta.frames - 1} without gaps)")
        files[s] = expected
    return files


def read_dexycb_labels(path) -> Tuple[np.ndarray, np.ndarray]:
    """(joints (21, 3) mm, pixels (21, 2)) of a ``labels_NNNNNN.npz`` in the standard order,
    NaN where DexYCB writes -1 (no hand pose in the frame)."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            j3, j2 = z["joint_3d"], z["joint_2d"]
    except KeyError as err:
        raise SequenceError(f"{path}: no {err} array (DexYCB labels hold joint_3d and joint_2d)") from None
    except (OSError, ValueError) as err:
        raise SequenceError(f"{path}: not a readable .npz ({err})") from None
    if j3.shape != (1, 21, 3) or j2.shape != (1, 21, 2):
        raise SequenceError(f"{path}: joint_3d {j3.shape} and joint_2d {j2.shape}, expected (1, 21, 3) and (1, 21, 2)")
    j3, j2 = j3[0, DEXYCB_TO_STANDARD].astype(np.float64), j2[0, DEXYCB_TO_STANDARD].astype(np.float64)
    j3 = np.where((j3 == -1).all(-1, keepdims=True), np.nan, j3 * 1000.0)
    j2 = np.where((j2 == -1).all(-1, keepdims=True), np.nan, j2)
    return j3, j2


def dexycb_rig(cameras: Sequence[DexYCBCamera]) -> List[Camera]:
    """The torchhand cameras of ``cameras`` (camera 0 first): world = camera 0's frame, mm."""
    master_from_0 = cameras[0].to_master
    out = []
    for c in cameras:
        T_cw = np.linalg.inv(c.to_master) @ master_from_0
        k = c.intrinsics
        out.append(Camera.from_intrinsics(k["fx"], k["fy"], k["cx"], k["cy"], WIDTH, HEIGHT, T_cw=torch.from_numpy(T_cw),
                                          name=c.serial, dtype=torch.float64).to(dtype=torch.float32))
    return out


def _joints(files, serials: List[str], rig: List[Camera]) -> Tuple[np.ndarray, np.ndarray]:
    """(joints (N, C, 21, 3) mm in each camera's frame, pixels (N, C, 21, 2)) (module docstring)."""
    C, N = len(serials), len(files[serials[0]]["labels"])
    T_wc = np.stack([np.linalg.inv(c.T_cw.double().numpy()) for c in rig])  # camera -> world (= camera 0)
    T_cw = np.stack([c.T_cw.double().numpy() for c in rig])
    joints, pixels = np.full((N, C, 21, 3), np.nan), np.full((N, C, 21, 2), np.nan)
    for k in range(N):
        world = []
        for c, s in enumerate(serials):
            j3, pixels[k, c] = read_dexycb_labels(files[s]["labels"][k])
            world.append(j3 @ T_wc[c, :3, :3].T + T_wc[c, :3, 3])
        have = [c for c in range(C) if np.isfinite(world[c]).all()]
        if not have:
            continue
        ref = world[have[0]]
        for c in have[1:]:
            gap = float(np.linalg.norm(world[c] - ref, axis=-1).max())
            if gap > AGREE_MM:
                warnings.warn(f"{files[serials[c]]['labels'][k]}: its joints, moved to camera 0 by the extrinsics, lie "
                              f"up to {gap:.1f} mm from those of {files[serials[have[0]]]['labels'][k]}", stacklevel=3)
        joints[k] = np.einsum("cij,pj->cpi", T_cw[:, :3, :3], ref) + T_cw[:, None, :3, 3]
    return joints, pixels


def import_dexycb(src, out, force: bool = False, segmentation: Optional[Dict] = None,
                  cameras: Optional[Sequence[str]] = None) -> SequenceInfo:
    """Write the sequence folder ``out`` from one DexYCB sequence (module docstring).

    Args:
        src: ``<root>/<subject>/<YYYYMMDD_HHMMSS>``; the calibration is read from ``<root>/calibration``.
        out: sequence folder to create (must be new or empty unless ``force``).
        force: replace a non-empty ``out``.
        segmentation: hand-segmentation settings stored in ``sequence.json`` (applied to
            every view of the rig: a view that finds no hand costs nothing).
        cameras: serials to import (default: all of ``meta.yml``).
    Returns:
        the written :class:`SequenceInfo`: one camera per serial (camera 0 the master),
        the hand of ``mano_sides``, depth copied byte for byte (mm), colour as PNG, and
        ``gt/`` (module docstring). Everything is checked first and written into a hidden
        folder renamed to ``out`` at the end, so a failure leaves ``out`` as it was.
    """
    src, out = Path(os.path.abspath(src)), Path(out)
    meta = read_dexycb_meta(src)
    master, _ = read_dexycb_calibration(src, [], meta.extrinsics)
    serials = _select(meta, master, cameras)
    files = dexycb_files(src, meta, serials)
    check_out_folder(out, force)
    _, calib = read_dexycb_calibration(src, serials, meta.extrinsics)
    for s in serials:
        H, W = check_depth_pngs(files[s]["depth"], "DexYCB's aligned depth is 16-bit millimetres")
        if (W, H) != (WIDTH, HEIGHT):
            raise SequenceError(f"{files[s]['depth'][0]}: {W}x{H} pixels, DexYCB's frames are {WIDTH}x{HEIGHT}")
    rig = dexycb_rig(calib)
    joints, pixels = _joints(files, serials, rig)
    valid = np.isfinite(joints[:, 0]).all(-1)  # (N, 21)
    source = {"format": "dexycb", "imported_from": str(src), "subject": src.parent.name, "sequence": src.name,
              "serials": serials, "master": master, "extrinsics": meta.extrinsics,
              "frames_without_pose": np.nonzero(~valid.any(-1))[0].tolist()}
    info = SequenceInfo(out.name, rig, [meta.model], meta.frames, FPS, 1.0, True, source, segmentation)

    def write_frames(seq: SequenceLayout) -> None:
        for c, s in enumerate(serials):
            seq.depth_dir(c).mkdir(parents=True)
            seq.rgb_dir(c).mkdir(parents=True)
            for k in range(meta.frames):
                seq.depth(k, c).write_bytes(files[s]["depth"][k].read_bytes())
                rgb = read_rgb(files[s]["color"][k])
                if rgb.shape[:2] != (HEIGHT, WIDTH):
                    raise SequenceError(f"{files[s]['color'][k]}: {rgb.shape[1]}x{rgb.shape[0]} pixels, DexYCB's "
                                        f"frames are {WIDTH}x{HEIGHT}")
                write_rgb(seq.rgb(k, c), rgb)

    write_imported(out, info, force, write_frames, joints, pixels, valid)
    return info


def write_dexycb(root, subject: str, sequence: str, cameras: Dict[str, Camera], master: str,
                 depth: Dict[str, np.ndarray], joints: np.ndarray, side: str = "right",
                 extrinsics: str = "torchhand") -> Path:
    """Write one sequence in DexYCB's published layout (module docstring), e.g. renders
    to run a DexYCB pipeline on, or this reader's tests: ``<root>/calibration/`` (each
    camera's intrinsics file and an extrinsics file named ``extrinsics``; a calibration
    already there is kept, so several sequences share one root) and
    ``<root>/<subject>/<sequence>/`` with ``meta.yml`` and, per camera, colour (a grey
    picture of where there is depth), depth (uint16 mm) and labels.

    Args:
        cameras: serial -> camera, ``T_cw`` in the master camera's frame (mm).
        master: the master's serial (its ``T_cw`` the identity).
        depth: serial -> (N, 480, 640) depth in mm (NaN or 0: none).
        joints: (N, 21, 3) the standard joints in the master's frame, mm; a frame of
            NaN has no hand pose (labels -1, as DexYCB marks them).
    Returns:
        the sequence folder. Refuses one that exists.
    """
    import cv2
    import yaml

    root = Path(root)
    src = root / subject / sequence
    if src.exists():
        raise FileExistsError(f"{src} exists: choose another sequence name")
    serials = list(cameras)
    if master not in cameras:
        raise ValueError(f"master {master!r} is not one of the cameras {serials}")
    if not np.allclose(cameras[master].T_cw.double().cpu().numpy(), np.eye(4), atol=1e-9):
        raise ValueError(f"the master camera {master}'s T_cw must be the identity (the cameras in its frame)")
    joints = np.asarray(joints, np.float64)
    N = len(joints)
    if joints.shape != (N, 21, 3) or any(np.shape(depth[s]) != (N, HEIGHT, WIDTH) for s in serials):
        raise ValueError(f"joints (N, 21, 3) and one (N, {HEIGHT}, {WIDTH}) depth per camera expected, got "
                         f"{joints.shape} and {[np.shape(depth[s]) for s in serials]}")
    calib = root / "calibration"
    ext = calib / f"extrinsics_{extrinsics}" / "extrinsics.yml"
    if ext.is_file():  # shared by the root's sequences: it must hold these cameras
        held = yaml.safe_load(ext.read_text()).get("extrinsics", {})
        missing = [s for s in serials
                   if s not in held or not (calib / "intrinsics" / f"{s}_{WIDTH}x{HEIGHT}.yml").is_file()]
        if missing:
            raise ValueError(f"{ext} exists without cameras {missing}: give another extrinsics name")
    else:
        (calib / "intrinsics").mkdir(parents=True, exist_ok=True)
        ext.parent.mkdir(parents=True, exist_ok=True)
        table = {}
        for s, cam in cameras.items():
            intr = {"color": {"fx": float(cam.fx), "fy": float(cam.fy), "ppx": float(cam.cx), "ppy": float(cam.cy)}}
            (calib / "intrinsics" / f"{s}_{WIDTH}x{HEIGHT}.yml").write_text(yaml.safe_dump(intr))
            T = np.linalg.inv(cam.T_cw.double().cpu().numpy())  # camera -> master
            T[:3, 3] /= 1000.0
            table[s] = [float(v) for v in T[:3].ravel()]
        ext.write_text(yaml.safe_dump({"extrinsics": table, "master": master}))
    src.mkdir(parents=True)
    meta = {"serials": serials, "num_frames": N, "mano_sides": [side], "mano_calib": [subject],
            "extrinsics": extrinsics}
    (src / "meta.yml").write_text(yaml.safe_dump(meta))
    absent = ~np.isfinite(joints).all(axis=(1, 2))
    for s, cam in cameras.items():
        d = src / s
        d.mkdir()
        T = cam.T_cw.double().cpu().numpy()
        j3 = joints @ T[:3, :3].T + T[:3, 3]
        j2 = cam.project(torch.from_numpy(np.nan_to_num(joints)).to(cam.T_cw.dtype)).double().cpu().numpy()
        for k in range(N):
            img = np.round(np.nan_to_num(np.asarray(depth[s][k], np.float64))).astype(np.uint16)
            cv2.imwrite(str(d / DEPTH.format(k)), img)
            grey = np.where(img[..., None] > 0, 200, 40).astype(np.uint8)
            cv2.imwrite(str(d / COLOR.format(k)), grey.repeat(3, -1))
            lab3, lab2 = j3[k][None].astype(np.float32) / 1000.0, j2[k][None].astype(np.float32)
            if absent[k]:
                lab3, lab2 = -np.ones((1, 21, 3), np.float32), -np.ones((1, 21, 2), np.float32)
            np.savez(d / LABELS.format(k), joint_3d=lab3, joint_2d=lab2)
    return src
