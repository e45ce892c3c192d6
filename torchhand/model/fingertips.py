"""Fingertip vertex sets of a scene's hands (thesis Fig. 4.2 d-f): the model side of the
salient-point term (Eq. 4.14-4.15) and of the detector's training targets; and the
finger nails, Ballan et al.'s salient points (Sec. 4.1: "the vertices corresponding to
the center of each nail were marked as salient vertices").

Where a nail is: the thesis hand models have no nail geometry, so the nail of a finger
is the part of its fingertip vertex group (``<finger>_tip``) whose rest-pose normals lie
within ``max_angle_deg`` of the finger's dorsal direction. The dorsal direction is read
off the kinematics, not assumed: the last bone's flexion axis (its joint slot with the
widest range) turned the way of the larger joint limit moves the tip towards the palm,
and the back of the finger faces the other way. Any hand model with fingertip groups
and joint limits gets nails this way."""

from __future__ import annotations

from typing import List, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F

from torchhand.geometry.mesh import face_corners, face_normals
from torchhand.io.assets import FINGER_NAMES
from torchhand.model.scene import Scene

__all__ = ["FingertipSets", "fingertip_faces", "nail_faces", "nail_vertices"]


class FingertipSets(NamedTuple):
    """The P = 5 x (number of hands) fingertips of a scene.

    Attributes:
        index: (P, G) int64 padded vertex ids (into the scene's vertices) of each
            ``<finger>_tip`` group.
        mask: (P, G) bool, True for the real entries of ``index``.
        face_tip: (F,) int64 fingertip of each scene face whose three vertices all
            belong to one group, else -1.
        names: P strings ``"<model>/<finger>_tip"``.
    """

    index: torch.Tensor
    mask: torch.Tensor
    face_tip: torch.Tensor
    names: List[str]


def fingertip_faces(scene: Scene) -> FingertipSets:
    """The fingertip vertex groups of the hands of ``scene`` (objects have none), on the CPU."""
    groups, names = [], []
    for name, model in zip(scene.names, scene.models):
        if not all(f"{f}_tip" in model.assets.groups for f in FINGER_NAMES):
            continue  # objects have no fingertips
        start = scene.vertex_slices[name].start
        for f in FINGER_NAMES:
            groups.append(torch.as_tensor(model.assets.groups[f"{f}_tip"], dtype=torch.int64) + start)
            names.append(f"{name}/{f}_tip")
    V = scene.num_vertices
    faces = scene.faces.cpu()
    G = max((len(g) for g in groups), default=1)
    index = torch.zeros(len(groups), G, dtype=torch.int64)
    mask = torch.zeros(len(groups), G, dtype=torch.bool)
    vertex_tip = torch.full((V,), -1, dtype=torch.int64)
    for p, g in enumerate(groups):
        index[p, : len(g)] = g
        mask[p, : len(g)] = True
        vertex_tip[g] = p
    t = vertex_tip[faces]
    face_tip = torch.where((t[:, 0] >= 0) & (t[:, 0] == t[:, 1]) & (t[:, 0] == t[:, 2]), t[:, 0], -1)
    return FingertipSets(index, mask, face_tip, names)


def _rest_vertices(scene: Scene) -> torch.Tensor:
    v = torch.zeros(scene.num_vertices, 3, dtype=torch.float64)
    for name, model in zip(scene.names, scene.models):
        v[scene.vertex_slices[name]] = torch.as_tensor(model.assets.vertices, dtype=torch.float64)
    return v


def nail_faces(scene: Scene, max_angle_deg: float = 60.0) -> torch.Tensor:
    """(F,) bool: the scene's faces that are finger nails (module docstring); all False
    for a scene without hands."""
    tips = fingertip_faces(scene)
    faces = scene.faces.cpu()
    nail = torch.zeros(len(faces), dtype=torch.bool)
    if not tips.names:
        return nail
    rest = _rest_vertices(scene)
    n = F.normalize(face_normals(face_corners(rest[None], faces))[0], dim=-1)
    cos_max = float(np.cos(np.deg2rad(max_angle_deg)))
    for p, tip in enumerate(tips.names):
        model_name, finger = tip.split("/")
        model = scene.models[scene.names.index(model_name)]
        a = model.assets
        group = np.asarray(a.groups[finger], np.int64)
        bone = int(np.bincount(a.skin_index[group, 0]).argmax())
        used = np.nonzero(a.slot_used[bone])[0]
        if len(used) == 0:
            raise ValueError(f"model {model_name}: the bone {a.bone_names[bone]} of {finger} has no joint, so the "
                             "back of the finger (where the nail is) cannot be told from the pad")
        span = a.slot_limits[bone, used, 1] - a.slot_limits[bone, used, 0]
        k = used[int(np.argmax(span))]
        lo, hi = a.slot_limits[bone, k]
        flex = 1.0 if abs(hi) >= abs(lo) else -1.0
        R, origin = a.rest_transforms[bone, :3, :3], a.rest_transforms[bone, :3, 3]
        axis = R @ a.slot_axes[bone, k]
        towards_palm = flex * np.cross(axis, a.vertices[group].mean(0) - origin)
        dorsal = -towards_palm / max(np.linalg.norm(towards_palm), 1e-12)
        on_tip = tips.face_tip == p
        nail |= on_tip & ((n @ torch.as_tensor(dorsal)) > cos_max)
    return nail


def nail_vertices(scene: Scene, max_angle_deg: float = 60.0) -> torch.Tensor:
    """(P,) int64 the salient vertex of each fingertip of :func:`fingertip_faces` (same
    order): the nail's vertex nearest to the area-weighted centre of its faces."""
    tips = fingertip_faces(scene)
    nail = nail_faces(scene, max_angle_deg)
    rest = _rest_vertices(scene)
    faces = scene.faces.cpu()
    tri = face_corners(rest[None], faces)[0]  # (F, 3, 3)
    area = face_normals(tri[None])[0].norm(dim=-1) / 2
    out = torch.zeros(len(tips.names), dtype=torch.int64)
    for p, name in enumerate(tips.names):
        sel = nail & (tips.face_tip == p)
        if not bool(sel.any()):
            raise ValueError(f"{name}: no fingertip face faces the back of the finger, so it has no nail")
        centre = (tri[sel].mean(1) * area[sel, None]).sum(0) / area[sel].sum()
        ids = torch.unique(faces[sel])
        out[p] = ids[torch.argmin((rest[ids] - centre).norm(dim=-1))]
    return out
