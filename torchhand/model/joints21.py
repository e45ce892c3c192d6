"""The standard 21 hand joints, placed on a posed hand model (docs/model.md, "The standard
21 joints").

Order: the wrist (0), then thumb, index, middle, ring and little finger, four joints each
from the base outwards, so the tips are 4, 8, 12, 16 and 20. How each is placed:

- **wrist**: the wrist joint centre, the origin of the hand skeleton's root bone (the
  joint the global rotation turns about; for the thesis hands it lies inside the mesh,
  ~15 mm from where the forearm is cut).
- **finger joints**: joint centres, the origins of the three most distal bones of the
  finger's chain (MCP, PIP, DIP; for the thumb, whose chain has three bones, CMC, MCP,
  IP).
- **tip**: a point on the tip surface, the vertex of the finger's ``<finger>_tip`` group
  that lies farthest along its distal bone in the rigging pose, posed by skinning. A mesh
  vertex is on the surface in every pose and moves smoothly with theta (LBS is linear in
  the bone motions); an argmax taken per pose would jump between vertices.

Fingers are found by name, never by bone index: the distal bone of a finger is the bone
that dominates the skinning of its ``<finger>_tip`` vertex group, and its chain is read
off the kinematic tree, so any hand with fingertip groups gets the 21 joints.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from torchhand.io.assets import FINGER_NAMES
from torchhand.model.articulated import ArticulatedModel, ModelOutput
from torchhand.model.scene import Scene, SceneOutput
from torchhand.model.skinning import lbs_jacobian

__all__ = ["STANDARD_JOINT_NAMES", "JointSources", "joint_sources", "standard_joints", "standard_joint_jacobian",
           "is_hand", "scene_joint_names",
           "scene_standard_joints"]

_FINGER_JOINTS = {"thumb": ("cmc", "mcp", "ip", "tip")}
_DEFAULT_JOINTS = ("mcp", "pip", "dip", "tip")

#: The 21 standard joints, wrist first, then four per finger (thumb..little) from the base outwards.
STANDARD_JOINT_NAMES = ("wrist",) + tuple(
    f"{f}_{j}" for f in FINGER_NAMES for j in _FINGER_JOINTS.get(f, _DEFAULT_JOINTS))


class JointSources(NamedTuple):
    """Where the 21 joints come from on one model.

    Attributes:
        bones: (16,) int64 bone whose origin is each non-tip joint (wrist, then the three
            joints of each finger), in :data:`STANDARD_JOINT_NAMES` order without the tips.
        tip_vertices: (5,) int64 vertex of each fingertip (thumb..little).
    """

    bones: torch.Tensor
    tip_vertices: torch.Tensor


def _finger_chain(model: ArticulatedModel, finger: str) -> tuple:
    """(chain of bone ids from the hand's root child to the distal bone, the tip vertex)."""
    a = model.assets
    group = f"{finger}_tip"
    if group not in a.groups:
        raise ValueError(f"model {model.name!r} has no vertex group {group!r}, so its 21 joints cannot be placed; "
                         f"groups: {sorted(a.groups)}")
    ids = np.asarray(a.groups[group], np.int64)
    distal = int(np.bincount(a.skin_index[ids, 0], minlength=model.num_bones).argmax())
    parents = np.asarray(a.parents)
    if np.any(parents == distal):
        raise ValueError(f"model {model.name!r}: {group} is skinned mostly to bone {a.bone_names[distal]!r}, "
                         "which has child bones, so it is not a distal bone")
    chain = [distal]
    while parents[chain[-1]] >= 0:
        chain.append(int(parents[chain[-1]]))
    chain = chain[::-1][1:]  # without the root
    if len(chain) < 3:
        raise ValueError(f"model {model.name!r}: the {finger} has {len(chain)} bones; 3 or more are needed for "
                         "its three joints")
    rest = a.rest_transforms[distal]
    along = (a.vertices[ids] - rest[:3, 3]) @ rest[:3, 0]  # distance along the distal bone
    return chain, int(ids[np.argmax(along)])


def joint_sources(model: ArticulatedModel) -> JointSources:
    """The bones and tip vertices of the 21 joints of a hand ``model`` (module docstring),
    on the model's device. Raises ValueError for a model without fingertip groups."""
    roots = np.nonzero(np.asarray(model.assets.parents) < 0)[0]
    if len(roots) != 1:
        raise ValueError(f"model {model.name!r} has {len(roots)} root bones; a hand has one")
    bones, tips = [int(roots[0])], []
    for finger in FINGER_NAMES:
        chain, tip = _finger_chain(model, finger)
        bones += chain[-3:]
        tips.append(tip)
    dev = model.vertices_rest.device
    return JointSources(torch.as_tensor(bones, device=dev), torch.as_tensor(tips, device=dev))


def standard_joints(posed: ModelOutput, model: ArticulatedModel, sources: JointSources | None = None) -> torch.Tensor:
    """The 21 standard joints of a posed hand.

    Args:
        posed: the model's output for a pose (vertices (B, V, 3), G (B, J, 4, 4)).
        model: the hand model that posed it.
        sources: :func:`joint_sources` of ``model``, to skip finding them again.
    Returns:
        (B, 21, 3) mm in :data:`STANDARD_JOINT_NAMES` order; differentiable in the pose.
    """
    src = joint_sources(model) if sources is None else sources
    origins = model.joints_from(posed.G)[:, src.bones]  # (B, 16, 3)
    tips = posed.vertices[:, src.tip_vertices]  # (B, 5, 3)
    B = origins.shape[0]
    fingers = torch.cat([origins[:, 1:].reshape(B, 5, 3, 3), tips[:, :, None]], dim=2)  # (B, 5, 4, 3)
    return torch.cat([origins[:, :1], fingers.reshape(B, 20, 3)], dim=1)


def standard_joint_jacobian(posed: ModelOutput, model: ArticulatedModel, sources: JointSources | None = None
                            ) -> torch.Tensor:
    """(B, 21, 3, D) analytic Jacobian of :func:`standard_joints` with respect to the
    model's theta: each joint centre as a point rigidly attached to its bone, each tip
    as its skinned vertex (:func:`~torchhand.model.skinning.lbs_jacobian`)."""
    src = joint_sources(model) if sources is None else sources
    G, twists = posed.G, posed.twists
    bones = src.bones[:, None]
    origins = lbs_jacobian(G, twists, model.rest_transforms[src.bones, :3, 3], bones,
                           torch.ones_like(bones, dtype=G.dtype), model.dof_bone, model.descendants)
    tips = model.jacobian(None, src.tip_vertices, fk=(G, twists))
    B, D = origins.shape[0], origins.shape[-1]
    fingers = torch.cat([origins[:, 1:].reshape(B, 5, 3, 3, D), tips[:, :, None]], dim=2)
    return torch.cat([origins[:, :1], fingers.reshape(B, 20, 3, D)], dim=1)


def is_hand(model: ArticulatedModel) -> bool:
    """The model has the five ``<finger>_tip`` vertex groups the 21 joints are placed with."""
    return all(f"{f}_tip" in model.assets.groups for f in FINGER_NAMES)


def scene_joint_names(scene: Scene) -> list:
    """``"<model>/<joint>"`` of :func:`scene_standard_joints`, 21 per hand in scene order."""
    return [f"{n}/{j}" for n, m in zip(scene.names, scene.models) if is_hand(m) for j in STANDARD_JOINT_NAMES]


def scene_standard_joints(scene: Scene, posed: SceneOutput) -> torch.Tensor:
    """(B, 21 x hands, 3) the 21 joints of each hand of ``scene`` (objects have none), in
    scene order; (B, 0, 3) for a scene without hands."""
    joints = [standard_joints(out, m) for m, out in zip(scene.models, posed.models) if is_hand(m)]
    return torch.cat(joints, 1) if joints else posed.vertices.new_zeros(posed.vertices.shape[0], 0, 3)
