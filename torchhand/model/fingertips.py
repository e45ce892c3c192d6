"""Fingertip vertex sets of a scene's hands (thesis Fig. 4.2 d-f): the model side of the
salient-point term (Eq. 4.14-4.15) and of the detector's training targets."""

from __future__ import annotations

from typing import List, NamedTuple

import torch

from torchhand.io.assets import FINGER_NAMES
from torchhand.model.scene import Scene

__all__ = ["FingertipSets", "fingertip_faces"]


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
