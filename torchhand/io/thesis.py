"""Readers and writers for the file formats of the thesis' "Hands in Action" data.

Every reader takes a path, returns numpy arrays or small typed records, and raises
:class:`FormatError` naming the file, the line and what was expected when the
content is missing, truncated or inconsistent. Units are millimetres and degrees
exactly as stored; conversion to radians happens when a model is built.

Formats (see ``datasets/README.md`` for the full notes):

``OFF``      triangle mesh in rest pose.
``SKEL``     first line: number of MOTION rows; then triples (parent, child, length).
``SKIN``     number of bones, their names, then one row of weights per vertex.
``LIMITS``   per bone: name; 4 flags (translation, rot-x, rot-y, rot-z);
             3 rows of rotation axes (bone frame); 3 rows ``min max`` in degrees.
``MOTION``   per bone: name, then one row per frame: 9 numbers R (row-major) + 3 t.
``VOI``      vertex ids of the fingertips, groups separated by blank lines.
``ZONES``    number of parts, part names, then one threshold per part.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, NamedTuple, Tuple

import numpy as np

__all__ = [
    "FormatError",
    "Mesh",
    "SkeletonFile",
    "SkinFile",
    "BoneLimits",
    "ZonesFile",
    "IndexBounds",
    "CalibratedCamera",
    "ThesisModelFiles",
    "read_off",
    "read_skel",
    "read_skin",
    "read_limits",
    "read_motion",
    "write_motion",
    "read_voi",
    "read_zones",
    "read_models_info",
    "read_index_bounds",
    "read_calibration",
    "read_thesis_model",
    "sequence_models",
]

class FormatError(ValueError):
    """A thesis file is missing, truncated or inconsistent.

    The message names the file and, where it applies, the 1-based line number.
    """


def _fail(path, msg: str, line: int | None = None) -> FormatError:
    where = f"{path}" if line is None else f"{path}, line {line}"
    return FormatError(f"{where}: {msg}")


def _read_lines(path) -> List[str]:
    path = Path(path)
    if not path.is_file():
        raise FormatError(f"{path}: file not found")
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
    except UnicodeDecodeError as err:
        raise FormatError(f"{path}: not a text file ({err})") from None
    return text.splitlines()


def _floats(path, line_no: int, text: str, count: int | None = None) -> List[float]:
    try:
        values = [float(tok) for tok in text.split()]
    except ValueError:
        raise _fail(path, f"expected numbers, got {text.strip()!r}", line_no) from None
    if count is not None and len(values) != count:
        raise _fail(path, f"expected {count} numbers, got {len(values)}", line_no)
    if not np.all(np.isfinite(values)):
        raise _fail(path, "non-finite number", line_no)
    return values


def _is_number_row(text: str) -> bool:
    toks = text.split()
    if not toks:
        return False
    try:
        [float(t) for t in toks]
    except ValueError:
        return False
    return True


def _counted_lines(path, what: str) -> Tuple[int, List[Tuple[int, str]]]:
    """Non-blank stripped lines (with 1-based numbers) of a file whose first line is
    an integer count; returns (count, remaining lines)."""
    lines = [(i + 1, l.strip()) for i, l in enumerate(_read_lines(path))]
    lines = [(n, l) for n, l in lines if l]
    if not lines:
        raise _fail(path, "empty file")
    try:
        return int(lines[0][1]), lines[1:]
    except ValueError:
        raise _fail(path, f"first line must be the number of {what}, got {lines[0][1]!r}", lines[0][0]) from None


# --------------------------------------------------------------------------- OFF
class Mesh(NamedTuple):
    """vertices: (V, 3) float64 mm; faces: (F, 3) int64 vertex ids."""

    vertices: np.ndarray
    faces: np.ndarray


def read_off(path) -> Mesh:
    """Read a triangle mesh in OFF format (through trimesh, without re-processing).

    The header counts are checked against the content, so a truncated file is
    reported instead of silently loading fewer vertices.
    """
    import trimesh

    lines = _read_lines(path)
    body = [(i + 1, l) for i, l in enumerate(lines) if l.strip() and not l.lstrip().startswith("#")]
    if not body or body[0][1].strip().upper() != "OFF":
        raise _fail(path, "expected the header 'OFF' on the first line", 1)
    if len(body) < 2:
        raise _fail(path, "missing the counts line 'V F E'", 2)
    line_no, counts = body[1]
    nums = _floats(path, line_no, counts)
    if len(nums) < 2:
        raise _fail(path, "expected 'num_vertices num_faces num_edges'", line_no)
    n_v, n_f = int(nums[0]), int(nums[1])
    if len(body) < 2 + n_v + n_f:
        raise _fail(
            path,
            f"truncated: header promises {n_v} vertices and {n_f} faces, "
            f"file has {len(body) - 2} data lines",
        )
    with open(path, "rb") as fh:
        try:
            mesh = trimesh.load(fh, file_type="off", process=False, maintain_order=True)
        except Exception as err:  # trimesh raises many types; report them uniformly
            raise _fail(path, f"cannot parse OFF mesh: {err}") from None
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if vertices.shape != (n_v, 3) or faces.shape != (n_f, 3):
        raise _fail(
            path,
            f"expected {n_v} vertices and {n_f} triangles, parsed "
            f"{len(vertices)} vertices and {len(faces)} triangles (only triangles are supported)",
        )
    if not np.all(np.isfinite(vertices)):
        raise _fail(path, "vertex coordinates contain NaN or inf")
    if faces.size and (faces.min() < 0 or faces.max() >= n_v):
        raise _fail(path, f"face vertex ids must lie in [0, {n_v}), got [{faces.min()}, {faces.max()}]")
    return Mesh(vertices, faces)


# -------------------------------------------------------------------------- SKEL
class SkeletonFile(NamedTuple):
    """num_motion_rows: rows per bone in the matching MOTION file.
    bones: (parent name, child name, child bone length in mm), in file order.
    """

    num_motion_rows: int
    bones: List[Tuple[str, str, float]]


def read_skel(path) -> SkeletonFile:
    rows, rest = _counted_lines(path, "motion rows")
    if len(rest) % 3 != 0 or not rest:
        raise _fail(path, f"expected triples 'parent / child / length', got {len(rest)} lines after the header")
    bones = []
    for k in range(0, len(rest), 3):
        (_, parent), (_, child), (n_len, length) = rest[k : k + 3]
        bones.append((parent, child, _floats(path, n_len, length, 1)[0]))
    return SkeletonFile(rows, bones)


# -------------------------------------------------------------------------- SKIN
class SkinFile(NamedTuple):
    """bone_names: J names; weights: (V, J) float64, rows as stored (not renormalised)."""

    bone_names: List[str]
    weights: np.ndarray


def read_skin(path, num_vertices: int | None = None, sum_tolerance: float = 1e-2) -> SkinFile:
    """Read skinning weights; check the vertex count and that every row sums to 1.

    Args:
        num_vertices: expected number of rows (the OFF's vertex count), if known.
        sum_tolerance: largest accepted ``|sum(w) - 1|`` per vertex. The thesis files
            store 4 decimals, so rows sum to 1 within 6e-4.
    """
    lines = _read_lines(path)
    if len(lines) < 2:
        raise _fail(path, "expected the bone count and the bone names on the first two lines")
    try:
        n_bones = int(lines[0].strip())
    except ValueError:
        raise _fail(path, f"first line must be the number of bones, got {lines[0].strip()!r}", 1) from None
    names = _split_bone_names(lines[1])
    if len(names) != n_bones:
        raise _fail(path, f"expected {n_bones} bone names, got {len(names)}", 2)
    rows = []
    for i, text in enumerate(lines[2:], start=3):
        if not text.strip():
            continue
        rows.append(_floats(path, i, text, n_bones))
    weights = np.asarray(rows, dtype=np.float64).reshape(-1, n_bones)
    if num_vertices is not None and len(weights) != num_vertices:
        raise _fail(path, f"has {len(weights)} weight rows but the mesh has {num_vertices} vertices")
    if (weights < 0).any():
        v = int(np.argwhere(weights < 0)[0, 0])
        raise _fail(path, f"negative skinning weight for vertex {v}", v + 3)
    dev = np.abs(weights.sum(1) - 1.0)
    if len(dev) and dev.max() > sum_tolerance:
        v = int(dev.argmax())
        raise _fail(path, f"weights of vertex {v} sum to {weights[v].sum():.4f}, expected 1", v + 3)
    return SkinFile(names, weights)


def _split_bone_names(text: str) -> List[str]:
    """Bone names are whitespace separated, but "Lower Arm R" contains spaces."""
    toks = text.split()
    names: List[str] = []
    k = 0
    while k < len(toks):
        take = 1
        if toks[k] == "Lower" and toks[k + 1 : k + 2] == ["Arm"]:
            take = 3 if toks[k + 2 : k + 3] in (["R"], ["L"]) else 2
        names.append(" ".join(toks[k : k + take]))
        k += take
    return names


# ------------------------------------------------------------------------ LIMITS
@dataclass(frozen=True)
class BoneLimits:
    """Degrees of freedom of one bone.

    translation: the bone translates freely (the root).
    rotation: (3,) bool, which of the three axes rotate.
    axes: (3, 3) rows are the rotation axes in the bone's rest frame.
    limits_deg: (3, 2) ``[min, max]`` per axis in degrees.
    """

    name: str
    translation: bool
    rotation: Tuple[bool, bool, bool]
    axes: np.ndarray
    limits_deg: np.ndarray


def read_limits(path) -> Dict[str, BoneLimits]:
    lines = [(i + 1, l) for i, l in enumerate(_read_lines(path))]
    blocks: List[List[Tuple[int, str]]] = []
    cur: List[Tuple[int, str]] = []
    for n, l in lines:
        if l.strip():
            cur.append((n, l))
        elif cur:
            blocks.append(cur)
            cur = []
    if cur:
        blocks.append(cur)
    if not blocks:
        raise _fail(path, "empty file")
    out: Dict[str, BoneLimits] = {}
    for block in blocks:
        if len(block) != 8:
            raise _fail(path, f"bone block {block[0][1].strip()!r} has {len(block)} lines, expected 8", block[0][0])
        name = block[0][1].strip()
        flags = _floats(path, block[1][0], block[1][1], 4)
        axes = np.array([_floats(path, n, t, 3) for n, t in block[2:5]])
        lim = np.array([_floats(path, n, t, 2) for n, t in block[5:8]])
        out[name] = BoneLimits(name, bool(flags[0]), tuple(bool(f) for f in flags[1:]), axes, lim)
    return out


# ------------------------------------------------------------------------ MOTION
def read_motion(path) -> Dict[str, np.ndarray]:
    """Read per-bone world transforms.

    Returns:
        ordered dict bone name -> (N, 4, 4) float64; row 0 is the rest pose M0.
    """
    lines = _read_lines(path)
    bones: Dict[str, List[List[float]]] = {}
    cur = None
    for i, text in enumerate(lines, start=1):
        if not text.strip():
            continue
        toks = text.split()
        if _is_number_row(text) and cur is not None and len(toks) == 12:
            bones[cur].append(_floats(path, i, text, 12))
            continue
        if _is_number_row(text) and cur is None:
            raise _fail(path, "a row of numbers before the first bone name", i)
        if _is_number_row(text):
            raise _fail(path, f"expected 12 numbers (R row-major + t), got {len(toks)}", i)
        cur = text.strip()
        if cur in bones:
            raise _fail(path, f"bone {cur!r} appears twice", i)
        bones[cur] = []
    if not bones:
        raise _fail(path, "no bones found")
    counts = {b: len(r) for b, r in bones.items()}
    if len(set(counts.values())) != 1 or 0 in counts.values():
        raise _fail(path, f"bones have different numbers of rows (truncated file?): {counts}")
    out = {}
    for b, rows in bones.items():
        a = np.asarray(rows)
        m = np.zeros((len(a), 4, 4))
        m[:, :3, :3] = a[:, :9].reshape(-1, 3, 3)
        m[:, :3, 3] = a[:, 9:]
        m[:, 3, 3] = 1.0
        out[b] = m
    return out


def write_motion(path, motion: Dict[str, np.ndarray], overwrite: bool = False) -> None:
    """Write per-bone transforms (bone -> (N, 4, 4)) in the thesis MOTION layout.

    An existing file is never replaced unless ``overwrite`` is true.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    counts = {b: np.asarray(m).shape for b, m in motion.items()}
    n = {s[0] for s in counts.values()}
    if len(n) != 1 or any(s[1:] != (4, 4) for s in counts.values()):
        raise ValueError(f"motion must map every bone to an (N, 4, 4) array with one N, got {counts}")
    parts = []
    for bone, mats in motion.items():
        mats = np.asarray(mats, dtype=np.float64)
        if not np.isfinite(mats).all():
            raise ValueError(f"motion of bone {bone!r} contains NaN or inf")
        rows = np.concatenate([mats[:, :3, :3].reshape(-1, 9), mats[:, :3, 3]], axis=1)
        parts.append(bone)
        parts.extend(" ".join(f"{x:.9g}" for x in row) + " " for row in rows)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text("\n".join(parts) + "\n")
    os.replace(tmp, path)


# --------------------------------------------------------------- VOI and ZONES
def read_voi(path) -> List[np.ndarray]:
    """Vertex-id groups separated by blank lines, in file order: list of (n_i,) int64.

    Also reads the count-prefixed layout of ``VOIs/VOIs_Model_*.txt`` (a line with
    the group size, a blank line, the ids), returning only the id groups.
    """
    groups: List[List[int]] = [[]]
    for i, text in enumerate(_read_lines(path), start=1):
        if not text.strip():
            if groups[-1]:
                groups.append([])
            continue
        try:
            groups[-1].extend(int(t) for t in text.split())
        except ValueError:
            raise _fail(path, f"expected vertex ids, got {text.strip()!r}", i) from None
    groups = [g for g in groups if g]
    if not groups:
        raise _fail(path, "no vertex groups")
    counted = len(groups) % 2 == 0 and all(
        len(groups[k]) == 1 and groups[k][0] == len(groups[k + 1]) for k in range(0, len(groups), 2)
    )
    if counted:
        groups = groups[1::2]
    return [np.asarray(g, dtype=np.int64) for g in groups]


class ZonesFile(NamedTuple):
    """names: part names (prefixes/suffixes of bone names); thresholds: (P,) per part."""

    names: List[str]
    thresholds: np.ndarray


def read_zones(path) -> ZonesFile:
    n, lines = _counted_lines(path, "parts")
    if len(lines) != 2 * n:
        raise _fail(path, f"expected {n} part names and {n} thresholds, got {len(lines)} lines")
    names = [l for _, l in lines[:n]]
    thr = np.array([_floats(path, k, l, 1)[0] for k, l in lines[n:]])
    return ZonesFile(names, thr)


# ------------------------------------------------------------- Configs / Calib
def read_models_info(path) -> List[str]:
    n, lines = _counted_lines(path, "models")
    names = [l for _, l in lines]
    if len(names) != n:
        raise _fail(path, f"expected {n} model names, got {len(names)}")
    return names


class IndexBounds(NamedTuple):
    """total_aligned: number of video frames; frame k uses MOTION row k + motion_offset."""

    total_aligned: int
    motion_offset: int
    video_offset: int


def read_index_bounds(path) -> IndexBounds:
    vals = {}
    for i, text in enumerate(_read_lines(path), start=1):
        toks = text.split()
        if len(toks) == 2:
            try:
                vals[toks[0]] = int(toks[1])
            except ValueError:
                raise _fail(path, f"expected an integer after {toks[0]!r}", i) from None
    # The keys are spelled as in the original files ("TotalAlligned", "MotionnOffset", ...).
    keys = ("TotalAlligned", "MotionnOffset", "VideoooOffset")
    missing = [k for k in keys if k not in vals]
    if missing:
        raise _fail(path, f"missing entries {missing}")
    return IndexBounds(*(vals[k] for k in keys))


class CalibratedCamera(NamedTuple):
    """scale: depth scale; K: (3, 3); Rt: (3, 4) world -> camera."""

    scale: float
    K: np.ndarray
    Rt: np.ndarray


def read_calibration(path) -> List[CalibratedCamera]:
    """Cameras.txt: per camera 1 line scale, 3 lines K, 3 lines [R|t]."""
    rows = [(i + 1, l) for i, l in enumerate(_read_lines(path)) if l.strip()]
    if not rows or len(rows) % 7 != 0:
        raise _fail(path, f"expected 7 lines per camera (scale, K, [R|t]), got {len(rows)} lines")
    cams = []
    for k in range(0, len(rows), 7):
        scale = _floats(path, rows[k][0], rows[k][1], 1)[0]
        K = np.array([_floats(path, n, t, 3) for n, t in rows[k + 1 : k + 4]])
        Rt = np.array([_floats(path, n, t, 4) for n, t in rows[k + 4 : k + 7]])
        cams.append(CalibratedCamera(scale, K, Rt))
    return cams


# ----------------------------------------------------------- model bundles
@dataclass
class ThesisModelFiles:
    """All files of one model of one sequence, parsed."""

    name: str
    mesh: Mesh
    skeleton: SkeletonFile
    skin: SkinFile
    limits: Dict[str, BoneLimits]
    zones: ZonesFile | None
    voi: List[np.ndarray] | None
    motion: Dict[str, np.ndarray] | None


def read_thesis_model(models_dir, name: str, with_motion: bool = True) -> ThesisModelFiles:
    """Read ``<models_dir>/<name>.{OFF,SKEL,SKIN,LIMITS,ZONES,VOI,MOTION}``.

    OFF, SKEL, SKIN and LIMITS are required; ZONES, VOI and MOTION are optional
    (objects have no VOI; held-out sequences have no MOTION).
    """
    d = Path(models_dir)
    off = d / f"{name}.OFF"
    if not off.is_file():
        have = sorted(p.stem for p in d.glob("*.OFF")) if d.is_dir() else []
        raise FormatError(f"{off}: file not found (models in {d}: {have})")
    mesh = read_off(off)
    skel = read_skel(d / f"{name}.SKEL")
    skin = read_skin(d / f"{name}.SKIN", num_vertices=len(mesh.vertices))
    limits = read_limits(d / f"{name}.LIMITS")
    zones = read_zones(d / f"{name}.ZONES") if (d / f"{name}.ZONES").is_file() else None
    voi = read_voi(d / f"{name}.VOI") if (d / f"{name}.VOI").is_file() else None
    motion = None
    if with_motion and (d / f"{name}.MOTION").is_file():
        motion = read_motion(d / f"{name}.MOTION")
        bad = [b for b in skin.bone_names if b not in motion]
        if bad:
            raise FormatError(f"{d / (name + '.MOTION')}: no rows for skinning bones {bad}")
    if voi is not None:
        for g in voi:
            if g.max() >= len(mesh.vertices):
                raise FormatError(f"{d / (name + '.VOI')}: vertex id {g.max()} >= {len(mesh.vertices)} vertices")
    return ThesisModelFiles(name, mesh, skel, skin, limits, zones, voi, motion)


def sequence_models(hia_root, sequence: str) -> Tuple[List[str], IndexBounds]:
    """Model names and index bounds of sequence ``NN`` under a Hands-in-Action root."""
    cfg = Path(hia_root) / "Configs" / sequence
    return read_models_info(cfg / "MODELS_INFO.txt"), read_index_bounds(cfg / "INDEX_BOUNDS.txt")
