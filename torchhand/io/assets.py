"""Model assets: the data of one articulated model, its ``.npz`` format, and its
construction from the thesis files.

An asset file ``models/<name>.npz`` (``numpy.savez_compressed``, read with
``allow_pickle=False``) holds these arrays (J bones, V vertices, F faces, K weights
per vertex, P keypoints):

==================  ===========  ==================================================
``vertices``        (V, 3) f8    rigging-pose vertices, mm
``faces``           (F, 3) i8    triangles
``skin_index``      (V, K) i8    bone ids of the non-zero weights (padded with 0)
``skin_weight``     (V, K) f8    weights, rows sum to 1 (padded with 0)
``parents``         (J,) i8      parent bone, -1 for the root (bone 0)
``rest_transforms`` (J, 4, 4)    T_j(0), bone frames in the rigging pose
``bone_lengths``    (J,) f8      mm, along the bone's x axis
``slot_axes``       (J, 3, 3)    revolute axes in the bone frame (rows x, y, z)
``slot_used``       (J, 3) bool  which axes rotate
``slot_limits``     (J, 3, 2)    [min, max] per axis, radians
``keypoint_bones``  (P,) i8      bone that carries each keypoint
``keypoint_rest``   (P, 3) f8    keypoint positions in the rigging pose
``group_ids``       (G,) i8      vertex ids of all named groups, concatenated
``group_offsets``   (n+1,) i8    group i is group_ids[offsets[i]:offsets[i+1]]
``meta``            (n,) u1      UTF-8 JSON: name, kind, side, bone_names,
                                 keypoint_names, group_names, zones, source,
                                 symmetry (optional)
==================  ===========  ==================================================
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from torchhand.core.errors import UnknownName
from torchhand.io.thesis import BoneLimits, FormatError, ThesisModelFiles

__all__ = [
    "ModelAssets",
    "HAND_KEYPOINT_NAMES",
    "FINGER_NAMES",
    "THESIS_MODEL_NAMES",
    "SYMMETRIES",
    "assets_from_thesis",
    "rigid_assets",
    "save_assets",
    "load_assets",
    "model_dirs",
    "available_models",
    "find_model",
    "load_demo_motion",
]

FINGER_NAMES = ("thumb", "index", "middle", "ring", "little")
JOINT_NAMES = ("mcp", "pip", "dip", "tip")
#: 21 hand keypoints: the wrist, then per finger (thumb..little) MCP, PIP, DIP, tip.
#: For the thumb the three joints are CMC, MCP and IP (the usual 21-point convention).
HAND_KEYPOINT_NAMES = ("wrist",) + tuple(f"{f}_{j}" for f in FINGER_NAMES for j in JOINT_NAMES)

#: thesis model file names -> torchhand model names
THESIS_MODEL_NAMES = {
    "Model_Hand_R": "hand_right",
    "Model_Hand_L": "hand_left",
    "Model_Object_Ball": "ball",
    "Model_Object_Cube": "cube",
    "Model_Object_Pipe_Gray": "pipe",
    "Model_Object_Pipe_Green_Long": "rope",
}
#: the shape symmetries of the thesis objects (the thesis files do not record them): a
#: symmetric object's pose is scored up to its symmetry (ADD-S, docs/results.md)
SYMMETRIES = ("sphere", "cylinder", "cube")
THESIS_SYMMETRY = {
    "Model_Object_Ball": "sphere",
    "Model_Object_Cube": "cube",
    "Model_Object_Pipe_Gray": "cylinder",
    "Model_Object_Pipe_Green_Long": "cylinder",
}
# Thesis finger index -> anatomical finger (identified from the bone lengths: finger 4
# has three bones, metacarpal lengths grow from 0 to 3).
_THESIS_FINGER = {4: "thumb", 3: "index", 2: "middle", 1: "ring", 0: "little"}


@dataclass
class ModelAssets:
    """Everything that defines one articulated model (numpy, float64, mm, radians)."""

    name: str
    kind: str  # "hand" or "object"
    side: Optional[str]  # "right", "left" or None
    bone_names: List[str]
    parents: np.ndarray
    rest_transforms: np.ndarray
    bone_lengths: np.ndarray
    vertices: np.ndarray
    faces: np.ndarray
    skin_index: np.ndarray
    skin_weight: np.ndarray
    slot_axes: np.ndarray
    slot_used: np.ndarray
    slot_limits: np.ndarray
    keypoint_names: List[str] = field(default_factory=list)
    keypoint_bones: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    keypoint_rest: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    groups: Dict[str, np.ndarray] = field(default_factory=dict)
    zones: Dict[str, float] = field(default_factory=dict)
    source: str = ""
    symmetry: Optional[str] = None  # None, or one of SYMMETRIES (the surface is invariant under it)

    def __post_init__(self) -> None:
        self.validate()

    @property
    def num_bones(self) -> int:
        return len(self.bone_names)

    @property
    def dof_names(self) -> List[str]:
        """Root ``tx, ty, tz, rx, ry, rz`` then ``<bone>:<axis>`` per revolute joint."""
        names = ["root:tx", "root:ty", "root:tz", "root:rx", "root:ry", "root:rz"]
        for j, bone in enumerate(self.bone_names):
            names += [f"{bone}:{'xyz'[s]}" for s in range(3) if self.slot_used[j, s]]
        return names

    def validate(self) -> None:
        """Check shapes and invariants; raise ValueError naming the field."""
        J, V = len(self.bone_names), len(self.vertices)

        def need(ok: bool, what: str) -> None:
            if not ok:
                raise ValueError(f"model {self.name!r}: {what}")

        need(self.kind in ("hand", "object"), f"kind must be 'hand' or 'object', got {self.kind!r}")
        need(self.symmetry is None or self.symmetry in SYMMETRIES,
             f"symmetry must be None or one of {SYMMETRIES}, got {self.symmetry!r}")
        need(self.vertices.shape == (V, 3) and V > 0, f"vertices must be (V, 3) with V > 0, got {self.vertices.shape}")
        need(np.isfinite(self.vertices).all(), "vertices contain NaN or inf")
        need(self.faces.ndim == 2 and self.faces.shape[1] == 3, f"faces must be (F, 3), got {self.faces.shape}")
        need(self.faces.size == 0 or (self.faces.min() >= 0 and self.faces.max() < V), "face ids out of range")
        need(self.parents.shape == (J,), f"parents must be ({J},), got {self.parents.shape}")
        need(J > 0 and self.parents[0] == -1 and (self.parents[1:] >= 0).all(), "bone 0 must be the only root")
        need(all(self.parents[j] < j for j in range(1, J)), "bones must be ordered parents first")
        need(self.rest_transforms.shape == (J, 4, 4), f"rest_transforms must be ({J}, 4, 4)")
        need(self.bone_lengths.shape == (J,), f"bone_lengths must be ({J},)")
        need(self.skin_index.shape == self.skin_weight.shape and self.skin_index.shape[0] == V,
             f"skin_index/skin_weight must both be ({V}, K), got {self.skin_index.shape} and {self.skin_weight.shape}")
        need((self.skin_index >= 0).all() and (self.skin_index < J).all(), "skin_index out of range")
        need(np.abs(self.skin_weight.sum(1) - 1).max() < 1e-6, "skinning weights must sum to 1 per vertex")
        need(self.slot_axes.shape == (J, 3, 3) and self.slot_used.shape == (J, 3)
             and self.slot_limits.shape == (J, 3, 2), "slot_axes/slot_used/slot_limits must be (J,3,3)/(J,3)/(J,3,2)")
        need(not self.slot_used[0].any(), "the root bone carries the 6 global DoF, not revolute joints")
        need(len(self.keypoint_names) == len(self.keypoint_bones) == len(self.keypoint_rest),
             "keypoint_names, keypoint_bones and keypoint_rest must have the same length")
        for g, ids in self.groups.items():
            need(ids.size == 0 or (ids.min() >= 0 and ids.max() < V), f"group {g!r} has vertex ids out of range")


# ----------------------------------------------------------------- from thesis
def _topological_order(parents_by_name: Dict[str, str], names: Sequence[str], path: str) -> List[str]:
    roots = [n for n in names if parents_by_name.get(n) not in names]
    if len(roots) != 1:
        raise FormatError(f"{path}: expected exactly one root bone, found {roots}")
    order, frontier = [], [roots[0]]
    while frontier:
        b = frontier.pop(0)
        order.append(b)
        frontier += [n for n in names if parents_by_name.get(n) == b]
    missing = [n for n in names if n not in order]
    if missing:
        raise FormatError(f"{path}: bones {missing} are not connected to the root {roots[0]!r}")
    return order


def _rest_from_skeleton(order: List[str], parents: np.ndarray, lengths: np.ndarray, path: str) -> np.ndarray:
    """Rigging pose for a serial chain without MOTION: bones along +x, centred at 0.

    The thesis objects (pipe, rope) are meshes centred at the origin along x with
    bone frames aligned to the world; this reproduces that layout.
    """
    if not all(parents[j] == j - 1 for j in range(1, len(order))):
        raise FormatError(f"{path}: no MOTION rest pose and the skeleton is not a serial chain")
    T = np.tile(np.eye(4), (len(order), 1, 1))
    x0 = -lengths.sum() / 2
    T[:, 0, 3] = x0 + np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
    return T


def assets_from_thesis(
    files: ThesisModelFiles, name: str | None = None, source: str = "",
    fingertips: Sequence[np.ndarray] | None = None,
) -> ModelAssets:
    """Build :class:`ModelAssets` from the parsed files of one thesis model.

    The rigging pose T_j(0) is MOTION row 0 when a MOTION file is present, else it is
    derived from the SKEL bone lengths for serial chains (see `_rest_from_skeleton`).
    Skinning weights are renormalised to sum to 1 (the files store 4 decimals).
    ``fingertips``: the 5 full fingertip vertex sets of a hand (``VOIs/VOIs_Model_*.txt``).
    """
    path = files.name
    skin_names = files.skin.bone_names
    parent_of = {c: p for p, c, _ in files.skeleton.bones}
    length_of = {c: l for _, c, l in files.skeleton.bones}
    unknown = [b for b in skin_names if b not in parent_of]
    if unknown:
        raise FormatError(f"{path}.SKIN: bones {unknown} are not in the SKEL file")
    order = _topological_order(parent_of, skin_names, path + ".SKEL")
    index = {b: j for j, b in enumerate(order)}
    parents = np.array([index.get(parent_of[b], -1) for b in order], dtype=np.int64)
    lengths = np.array([length_of[b] for b in order])

    if files.motion is not None:
        rest = np.stack([files.motion[b][0] for b in order])
        # MOTION stores 6 significant digits, so its rotations are off by ~1e-6; project
        # them onto SO(3) so that posed bones stay exactly rigid.
        U, _, Vt = np.linalg.svd(rest[:, :3, :3])
        rest[:, :3, :3] = U @ Vt
    else:
        rest = _rest_from_skeleton(order, parents, lengths, path)

    skin_index, skin_weight = _sparse_skinning(files.skin.weights[:, [skin_names.index(b) for b in order]])
    slot_axes, slot_used, slot_limits = _slots_from_limits(files.limits, order, path)

    kind = "hand" if files.voi is not None and "Hand" in files.name else "object"
    side = None
    if kind == "hand":
        side = "left" if files.name.endswith("_L") else "right"
    kp_names: List[str] = []
    kp_bones: List[int] = []
    kp_rest: List[np.ndarray] = []
    groups: Dict[str, np.ndarray] = {}
    if kind == "hand":
        kp_names, kp_bones, kp_rest = _hand_keypoints(order, parents, rest, lengths, path)
        groups = _fingertip_groups(files.voi, fingertips, len(files.mesh.vertices), path)
    zones = {}
    if files.zones is not None:
        zones = {n: float(t) for n, t in zip(files.zones.names, files.zones.thresholds)}
    return ModelAssets(
        name=name or THESIS_MODEL_NAMES.get(files.name, files.name),
        kind=kind, side=side, bone_names=order, parents=parents, rest_transforms=rest,
        bone_lengths=lengths, vertices=files.mesh.vertices, faces=files.mesh.faces,
        skin_index=skin_index.astype(np.int64), skin_weight=skin_weight,
        slot_axes=slot_axes, slot_used=slot_used, slot_limits=slot_limits,
        keypoint_names=kp_names, keypoint_bones=np.asarray(kp_bones, np.int64),
        keypoint_rest=np.asarray(kp_rest).reshape(-1, 3), groups=groups, zones=zones, source=source,
        symmetry=THESIS_SYMMETRY.get(files.name),
    )


def _sparse_skinning(W: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Skinning weights (V, J), columns in the topological order, renormalised to sum
    to 1 and sparsified: (V, K) bone ids (0 where unused) and (V, K) weights, K the
    largest number of bones of a vertex, the heaviest first."""
    W = W / W.sum(1, keepdims=True)
    K = int((W > 0).sum(1).max())
    skin_index = np.argsort(-W, axis=1, kind="stable")[:, :K]
    skin_weight = np.take_along_axis(W, skin_index, 1)
    skin_index = np.where(skin_weight > 0, skin_index, 0)
    return skin_index, skin_weight


def _slots_from_limits(limits: Dict[str, BoneLimits], order: List[str], path: str
                       ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Degrees of freedom from LIMITS: (J, 3, 3) unit axes, (J, 3) used slots and
    (J, 3, 2) limits (rad) of each bone of ``order``; the root's stay empty (its 6
    global DoF). Names may carry trailing blanks; single-bone objects name their one
    bone differently in LIMITS, e.g. "Ball" vs "Bone001"."""
    J = len(order)
    lim = {k.strip(): v for k, v in limits.items()}
    if J == 1 and len(lim) == 1:
        lim = {order[0]: next(iter(lim.values()))}
    slot_axes = np.zeros((J, 3, 3))
    slot_used = np.zeros((J, 3), bool)
    slot_limits = np.zeros((J, 3, 2))
    for j, b in enumerate(order):
        if b not in lim:
            raise FormatError(f"{path}.LIMITS: no entry for bone {b!r} (have {sorted(lim)})")
        L = lim[b]
        if j == 0:
            continue  # root: 6 free DoF; its LIMITS axes are unused placeholders
        if L.translation:
            raise FormatError(f"{path}.LIMITS: bone {b!r} translates; only the root may translate")
        used = np.array(L.rotation)
        axes = L.axes / np.linalg.norm(L.axes, axis=1, keepdims=True).clip(1e-12)
        slot_axes[j], slot_used[j] = np.where(used[:, None], axes, 0.0), used
        slot_limits[j] = np.where(used[:, None], np.deg2rad(L.limits_deg), 0.0)
    return slot_axes, slot_used, slot_limits


def _finger_bones(order: List[str]) -> Dict[str, List[int]]:
    """Thesis bone names ``{R,L}Fing.<i>_{Hand,0,1,2}`` -> finger -> bone ids."""
    fingers: Dict[str, List[int]] = {}
    for j, b in enumerate(order):
        if "Fing." not in b:
            continue
        i, seg = b.split("Fing.")[1].split("_")
        fingers.setdefault(_THESIS_FINGER[int(i)], []).append(j)
    return fingers


def _hand_keypoints(order, parents, rest, lengths, path):
    fingers = _finger_bones(order)
    if sorted(fingers) != sorted(FINGER_NAMES):
        raise FormatError(f"{path}.SKEL: expected bones of five fingers, found {sorted(fingers)}")

    def tip(j: int) -> np.ndarray:  # child end of bone j, along its x axis
        return rest[j, :3, 3] + lengths[j] * rest[j, :3, 0]

    names, bones, pts = ["wrist"], [0], [tip(0)]
    for f in FINGER_NAMES:
        chain = fingers[f]  # metacarpal, proximal, (middle,) distal
        joints = chain[1:] if len(chain) == 4 else chain  # thumb: CMC, MCP, IP
        for jn, j in zip(JOINT_NAMES[:3], joints):
            names.append(f"{f}_{jn}")
            bones.append(j)
            pts.append(rest[j, :3, 3])
        names.append(f"{f}_tip")
        bones.append(chain[-1])
        pts.append(tip(chain[-1]))
    return names, bones, pts


def _fingertip_groups(voi, fingertips, num_vertices, path) -> Dict[str, np.ndarray]:
    """Vertex groups of the fingertips, both indexed by the thesis finger number.

    The model's VOI file holds rows of 5 annotated vertices (one per finger 0..4),
    the ``VOIs/VOIs_Model_*.txt`` files the full fingertip sets derived from them
    (thesis Fig. 4.2 d-f). ``<finger>_tip`` is the full set when given, else the
    annotated vertices; ``<finger>_tip_marks`` are always the annotated vertices.
    """
    rows = [np.asarray(r) for r in voi]
    if any(len(r) != 5 for r in rows):
        raise FormatError(f"{path}.VOI: expected rows of 5 vertex ids (one per finger), got {[len(r) for r in rows]}")
    marks = np.stack(rows, 1)  # (5 fingers, n marks)
    if fingertips is not None and len(fingertips) != 5:
        raise FormatError(f"fingertip vertex sets of {path}: expected 5 groups, got {len(fingertips)}")
    groups = {}
    for i in range(5):
        finger = _THESIS_FINGER[i]
        tip = np.asarray(fingertips[i] if fingertips is not None else marks[i], np.int64)
        if tip.max() >= num_vertices:
            raise FormatError(f"fingertip set of the {finger} of {path}: vertex id {tip.max()} >= {num_vertices}")
        groups[f"{finger}_tip"] = tip
        groups[f"{finger}_tip_marks"] = marks[i].astype(np.int64)
    return groups


def rigid_assets(name: str, vertices: np.ndarray, faces: np.ndarray, source: str = "",
                 symmetry: Optional[str] = None) -> ModelAssets:
    """A rigid object model (one bone, 6 DoF) of a triangle mesh (V, 3) mm, (F, 3).

    The bone frame is the world frame of ``vertices`` (its root at their origin), so
    the model's pose theta = (t, r) maps a mesh point x to ``so3_exp(r) x + t`` and the
    vertices keep their order.
    """
    V = len(vertices)
    return ModelAssets(
        name=name, kind="object", side=None, bone_names=["object"], parents=np.array([-1], np.int64),
        rest_transforms=np.eye(4)[None], bone_lengths=np.zeros(1), vertices=np.asarray(vertices, np.float64),
        faces=np.asarray(faces, np.int64), skin_index=np.zeros((V, 1), np.int64), skin_weight=np.ones((V, 1)),
        slot_axes=np.zeros((1, 3, 3)), slot_used=np.zeros((1, 3), bool), slot_limits=np.zeros((1, 3, 2)),
        source=source, symmetry=symmetry)


# ------------------------------------------------------------------ npz I/O
_ARRAYS = ("vertices", "faces", "skin_index", "skin_weight", "parents", "rest_transforms", "bone_lengths",
           "slot_axes", "slot_used", "slot_limits", "keypoint_bones", "keypoint_rest")


def save_assets(assets: ModelAssets, path, overwrite: bool = False) -> Path:
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    meta = dict(name=assets.name, kind=assets.kind, side=assets.side, bone_names=assets.bone_names,
                keypoint_names=list(assets.keypoint_names), group_names=list(assets.groups),
                zones=assets.zones, source=assets.source, symmetry=assets.symmetry, format=1)
    ids = [assets.groups[g] for g in assets.groups]
    offsets = np.cumsum([0] + [len(i) for i in ids])
    arrays = {k: getattr(assets, k) for k in _ARRAYS}
    arrays["group_ids"] = np.concatenate(ids) if ids else np.zeros(0, np.int64)
    arrays["group_offsets"] = offsets.astype(np.int64)
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode("utf-8"), dtype=np.uint8)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, path)
    return path


def load_assets(path) -> ModelAssets:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"model file {path} not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as err:
        raise ValueError(f"{path}: not a torchhand model file ({err})") from None
    missing = [k for k in _ARRAYS + ("meta", "group_ids", "group_offsets") if k not in data]
    if missing:
        raise ValueError(f"{path}: missing arrays {missing}")
    meta = json.loads(bytes(data["meta"]).decode("utf-8"))
    off = data["group_offsets"]
    groups = {g: data["group_ids"][off[i]:off[i + 1]] for i, g in enumerate(meta["group_names"])}
    try:
        return ModelAssets(
            name=meta["name"], kind=meta["kind"], side=meta["side"], bone_names=meta["bone_names"],
            keypoint_names=meta["keypoint_names"], groups=groups, zones=meta["zones"], source=meta["source"],
            symmetry=meta.get("symmetry"), **{k: data[k] for k in _ARRAYS},
        )
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None


# ------------------------------------------------------------- default models
def model_dirs() -> List[Path]:
    """Where named models are looked up: $TORCHHAND_MODELS, the installed package's
    assets, then the ``models/`` folder of a source checkout."""
    here = Path(__file__).resolve().parent.parent
    dirs = [Path(p) for p in os.environ.get("TORCHHAND_MODELS", "").split(os.pathsep) if p]
    dirs += [here / "_assets", here.parent / "models"]
    return [d for d in dirs if d.is_dir()]


#: shipped ``.npz`` files in the model folders that are not models
NON_MODEL_FILES = frozenset({"demo_motion"})


def available_models() -> List[str]:
    """Names of the models in :func:`model_dirs` (the demo motion is not a model)."""
    return sorted({p.stem for d in model_dirs() for p in d.glob("*.npz")} - NON_MODEL_FILES)


def find_model(name: str) -> Path:
    """Path of a model given by name (``hand_right``) or by path to an ``.npz``."""
    p = Path(name)
    if p.suffix == ".npz":
        if not p.is_file():
            raise FileNotFoundError(f"model file {p} not found")
        return p
    for d in model_dirs():
        if (d / f"{name}.npz").is_file():
            return d / f"{name}.npz"
    raise UnknownName(f"unknown model {name!r}; available models: {available_models()}")


def load_demo_motion():
    """The shipped demo motion (``demo_motion.npz``, an excerpt of thesis sequence 16):
    the model names and theta (N, D) as a float32 tensor."""
    import torch

    for d in model_dirs():
        p = d / "demo_motion.npz"
        if p.is_file():
            with np.load(p, allow_pickle=False) as z:
                meta = json.loads(bytes(z["meta"]).decode("utf-8"))
                return meta["models"], torch.from_numpy(z["theta"])
    raise FileNotFoundError(f"demo_motion.npz not found in {model_dirs()}")
