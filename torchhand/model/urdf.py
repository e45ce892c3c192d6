"""Export a model's kinematic tree as URDF (for ROS tools, pytorch-kinematics, ...).

Layout of the exported robot (J bones; ``<bone>`` is the torchhand bone name)::

    <root bone>                                  root link = root bone frame T_0(0)
      -- <bone>:x (revolute, origin = rest offset) --> <bone>__x
      -- <bone>:y (revolute, origin = identity)    --> <bone>__y
      -- <bone>:z (revolute, origin = identity)    --> <bone>
    <bone without revolute slots>
      -- <bone>:fixed (fixed, origin = rest offset) --> <bone>

Conventions (see :mod:`torchhand.model.kinematics`):

* **Units: metres.** torchhand works in millimetres; every URDF length is the
  torchhand length times :data:`MM_TO_M`. Angles are radians in both.
* **The global 6 DoF are not in the URDF.** The root link is the root bone in its
  rigging frame; ``theta[:, 0:6]`` becomes a base transform,
  :func:`root_transform`, so that the world frame of bone ``j`` is
  ``root_transform(model, theta) @ FK_urdf(j)`` (metres), where ``FK_urdf(j)`` is the
  URDF forward kinematics of link ``j`` relative to the root link.
* **Joint order.** A bone's revolute joints are chained in ``SLOT_ORDER`` (x, y, z),
  the first one carrying the rest offset ``inv(T_p(0)) T_j(0)`` of the bone relative
  to its parent, the others an identity origin; every ``<axis>`` is the slot axis in
  the bone frame. This reproduces ``T_j(theta) = T_p(theta) inv(T_p(0)) T_j(0)
  Rot_x Rot_y Rot_z`` exactly. Joint names are the torchhand DoF names
  (``"<bone>:<axis>"``); use :func:`urdf_joint_values` to reorder ``theta[:, 6:]``
  into a URDF library's joint order.
* **Names are kept as they are** (``"Lower Arm R"`` keeps its spaces; the XML writer
  escapes what needs escaping). URDF allows any string as a link or joint name and
  pytorch-kinematics accepts them; ROS tf2 discourages spaces in frame names, so
  rename the bones before exporting if the URDF is meant for tf2.
  :func:`urdf_link_name` gives the link name of a bone or of its intermediate links.
* **Rest frames are made rigid.** URDF origins are rigid transforms, while the hand
  assets store ``T_j(0)`` with 6 significant digits, so their rotation blocks are
  orthonormal only to ~1e-6. The export uses the nearest rotation (SVD polar factor)
  of each rest frame, which changes nothing for exactly orthonormal frames (the
  shipped objects) and moves the hand frames by at most the stored round-off.
* Links carry no geometry and no inertia; ``effort`` and ``velocity`` limits are
  required by URDF for revolute joints but torchhand has no dynamics, so they are
  placeholders (keyword arguments of :func:`model_to_urdf`).
"""

from __future__ import annotations

import os
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Union

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from torchhand.core.check import check_tensor
from torchhand.model.kinematics import ROOT_DOFS, SLOT_ORDER, so3_exp
from torchhand.io.assets import ModelAssets

__all__ = [
    "MM_TO_M",
    "model_to_urdf",
    "urdf_link_name",
    "urdf_joint_names",
    "urdf_joint_values",
    "root_transform",
    "rigid_rest_transforms",
]

#: URDF lengths are metres, torchhand lengths millimetres.
MM_TO_M = 1e-3
_AXES = "xyz"


def _assets(model_or_assets) -> ModelAssets:
    """The :class:`ModelAssets` of an ``ArticulatedModel`` or the assets themselves."""
    if isinstance(model_or_assets, ModelAssets):
        return model_or_assets
    assets = getattr(model_or_assets, "assets", None)
    if isinstance(assets, ModelAssets):
        return assets
    raise TypeError(
        f"expected an ArticulatedModel or ModelAssets, got {type(model_or_assets).__name__}"
    )


def urdf_link_name(bone: str, axis: Optional[str] = None) -> str:
    """Name of the URDF link of a bone, or of the intermediate link after one of its joints.

    Bone names are used unchanged (spaces included, see the module notes).

    Args:
        bone: torchhand bone name.
        axis: None for the bone's own link; ``"x"``, ``"y"`` or ``"z"`` for the link
            between the bone's joint ``<bone>:<axis>`` and its next joint.
    Returns:
        ``bone`` or ``f"{bone}__{axis}"``.
    """
    if axis is None:
        return bone
    if axis not in _AXES:
        raise ValueError(f"axis must be one of 'x', 'y', 'z' or None, got {axis!r}")
    return f"{bone}__{axis}"


def urdf_joint_names(model_or_assets) -> List[str]:
    """Revolute joint names of the export, in theta order: ``model.dof_names[6:]``."""
    return _assets(model_or_assets).dof_names[ROOT_DOFS:]


def rigid_rest_transforms(model_or_assets) -> np.ndarray:
    """Rest frames T_j(0) with their rotation replaced by the nearest rotation.

    The nearest rotation in the Frobenius norm is the polar factor ``U V^T`` of the
    SVD ``R = U S V^T`` (with the sign fix that keeps det = +1); translations are
    kept. This is what the URDF encodes (see the module notes).

    Returns:
        (J, 4, 4) float64, world frames in mm.
    """
    rest = np.array(_assets(model_or_assets).rest_transforms, dtype=np.float64)
    U, _, Vt = np.linalg.svd(rest[:, :3, :3])
    d = np.sign(np.linalg.det(U @ Vt))
    U[:, :, 2] *= d[:, None]
    rest[:, :3, :3] = U @ Vt
    return rest


def _fmt(values: Sequence[float]) -> str:
    """Shortest round-trip decimal of each value (``repr`` of a float is exact).

    Round-off noise below 1e-15 (e.g. ``rpy`` of an identity rotation) is written as
    0 for readability; that is far below any tolerance of a float64 consumer.
    """
    return " ".join(repr(0.0 if abs(v) < 1e-15 else float(v)) for v in values)


def _origin(parent: ET.Element, T: np.ndarray) -> None:
    """Append ``<origin xyz rpy>`` of a rigid transform given in mm.

    URDF ``rpy`` are fixed-axis angles: roll about X, then pitch about Y, then yaw
    about Z, i.e. ``R = Rz(yaw) Ry(pitch) Rx(roll)``; that is scipy's extrinsic
    ``"xyz"`` sequence (lower case = extrinsic). Near pitch = +-90 deg scipy reports
    gimbal lock but still returns angles that reproduce R.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # gimbal lock: result is still exact
        rpy = Rotation.from_matrix(T[:3, :3]).as_euler("xyz")
    ET.SubElement(parent, "origin", xyz=_fmt(T[:3, 3] * MM_TO_M), rpy=_fmt(rpy))


def model_to_urdf(
    model_or_assets,
    path: Union[str, os.PathLike, None] = None,
    overwrite: bool = False,
    *,
    effort: float = 1.0,
    velocity: float = 10.0,
) -> str:
    """URDF of a model's kinematic tree (metres, radians; see the module notes).

    Args:
        model_or_assets: an ``ArticulatedModel`` or its :class:`ModelAssets`.
        path: if given, also write the URDF there (UTF-8).
        overwrite: replace an existing file at ``path``.
        effort: placeholder ``<limit effort>`` of every revolute joint (N m).
        velocity: placeholder ``<limit velocity>`` of every revolute joint (rad/s).
    Returns:
        The URDF document as a string (no encoding declaration, so that it can be
        passed to lxml-based parsers such as pytorch-kinematics as ``str`` or, after
        ``.encode()``, as bytes).
    Raises:
        FileExistsError: ``path`` exists and ``overwrite`` is False (nothing written).
        ValueError: a joint has lower > upper limits, or a generated link or joint
            name collides with another one.
    """
    assets = _assets(model_or_assets)
    rest = rigid_rest_transforms(assets)
    names = list(assets.bone_names)

    robot = ET.Element("robot", name=assets.name)
    robot.append(ET.Comment(
        f" torchhand model {assets.name!r}: lengths in metres (torchhand mm x {MM_TO_M:g}), angles in "
        "radians. The root link is the root bone in its rigging frame; the global 6-DoF motion "
        "theta[:, 0:6] is not part of this URDF, apply torchhand.model.urdf.root_transform as the base "
        "transform. Joint names are torchhand DoF names '<bone>:<axis>'. "
    ))
    links: List[str] = [urdf_link_name(names[0])]
    joints: List[str] = []
    ET.SubElement(robot, "link", name=links[0])
    for j in range(1, len(names)):
        _add_bone(robot, assets, rest, j, links, joints, effort, velocity)

    for kind, used in (("link", links), ("joint", joints)):
        dup = sorted({n for n in used if used.count(n) > 1})
        if dup:
            raise ValueError(f"model {assets.name!r}: URDF {kind} names {dup} are not unique "
                             "(a bone name collides with a generated '<bone>__<axis>' name)")

    ET.indent(robot, space="  ")
    xml = '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"
    if path is not None:
        _write(Path(path), xml, overwrite)
    return xml


def _add_bone(robot: ET.Element, assets: ModelAssets, rest: np.ndarray, j: int, links: List[str],
              joints: List[str], effort: float, velocity: float) -> None:
    """Append bone ``j``'s joints and links to ``robot`` (and their names to ``links``
    and ``joints``): a fixed joint for a bone without DoF, else one revolute joint per
    used slot, chained through ``<bone>__<axis>`` links, the last ending at the bone's
    link. ``rest``: (J, 4, 4) the rigid rest transforms."""
    names = assets.bone_names
    bone, p = names[j], int(assets.parents[j])

    def add_link(name: str) -> None:
        links.append(name)
        ET.SubElement(robot, "link", name=name)

    # Rest offset of the bone in its parent's frame: inv(T_p(0)) T_j(0).
    offset = np.linalg.inv(rest[p]) @ rest[j]
    slots = [s for s in SLOT_ORDER if assets.slot_used[j, s]]
    parent_link = urdf_link_name(names[p])
    if not slots:
        joint = ET.SubElement(robot, "joint", name=f"{bone}:fixed", type="fixed")
        joints.append(joint.get("name"))
        ET.SubElement(joint, "parent", link=parent_link)
        ET.SubElement(joint, "child", link=urdf_link_name(bone))
        _origin(joint, offset)
        add_link(urdf_link_name(bone))
        return
    for k, s in enumerate(slots):
        lower, upper = (float(v) for v in assets.slot_limits[j, s])
        if not lower <= upper:
            raise ValueError(f"model {assets.name!r}: joint {bone}:{_AXES[s]} has lower limit {lower} > upper {upper}")
        last = k == len(slots) - 1
        child_link = urdf_link_name(bone) if last else urdf_link_name(bone, _AXES[s])
        joint = ET.SubElement(robot, "joint", name=f"{bone}:{_AXES[s]}", type="revolute")
        joints.append(joint.get("name"))
        ET.SubElement(joint, "parent", link=parent_link)
        ET.SubElement(joint, "child", link=child_link)
        # Only the first joint carries the rest offset; the others rotate about
        # the same origin (all slots of a bone act at the bone's joint position).
        _origin(joint, offset if k == 0 else np.eye(4))
        axis = assets.slot_axes[j, s] / np.linalg.norm(assets.slot_axes[j, s])
        ET.SubElement(joint, "axis", xyz=_fmt(axis))
        ET.SubElement(joint, "limit", lower=repr(lower), upper=repr(upper),
                      effort=repr(float(effort)), velocity=repr(float(velocity)))
        add_link(child_link)
        parent_link = child_link


def _write(path: Path, text: str, overwrite: bool) -> None:
    """Write atomically (temporary file + rename), refusing to replace unless asked."""
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def _check_theta(model_or_assets, theta: torch.Tensor) -> ModelAssets:
    assets = _assets(model_or_assets)
    check_tensor(theta, "theta", ("B", len(assets.dof_names)), finite=True)
    if not theta.is_floating_point():
        raise TypeError(f"theta must be a floating tensor, got {theta.dtype}")
    return assets


def urdf_joint_values(
    model_or_assets, theta: torch.Tensor, joint_names: Optional[Sequence[str]] = None
) -> Union[Dict[str, torch.Tensor], torch.Tensor]:
    """Revolute angles ``theta[:, 6:]`` for the exported URDF's joints.

    Args:
        model_or_assets: an ``ArticulatedModel`` or its :class:`ModelAssets`.
        theta: (B, D) pose.
        joint_names: the joint order of the consumer, e.g. pytorch-kinematics'
            ``chain.get_joint_parameter_names()`` (depth-first, not torchhand's
            breadth-first bone order). None returns a dict instead.
    Returns:
        ``{joint name: (B,) angles}`` if ``joint_names`` is None, else a (B, n)
        tensor with column i the angle of ``joint_names[i]``.
    Raises:
        KeyError: a name in ``joint_names`` is not a revolute joint of the model.
    """
    assets = _check_theta(model_or_assets, theta)
    column = {n: ROOT_DOFS + i for i, n in enumerate(urdf_joint_names(assets))}
    if joint_names is None:
        return {n: theta[:, c] for n, c in column.items()}
    unknown = [n for n in joint_names if n not in column]
    if unknown:
        raise KeyError(f"model {assets.name!r} has no revolute joints {unknown}; joints: {list(column)}")
    index = torch.as_tensor([column[n] for n in joint_names], dtype=torch.int64, device=theta.device)
    return theta.index_select(1, index)


def root_transform(model_or_assets, theta: torch.Tensor, metres: bool = True) -> torch.Tensor:
    """World frame of the URDF root link: the base transform carrying ``theta[:, 0:6]``.

    ``T_root(theta) = G_root(theta) T_0(0)`` with ``G_root = [R(r), c + t - R(r) c]``
    (rotation vector r about the root joint c, then translation t; see
    :mod:`torchhand.model.kinematics`) and T_0(0) made rigid as in the export. The world
    frame of bone j is ``root_transform(...) @ FK_urdf(j)``.

    Args:
        model_or_assets: an ``ArticulatedModel`` or its :class:`ModelAssets`.
        theta: (B, D) pose (only the first 6 columns are used).
        metres: translation in metres (True, matches the URDF) or in mm.
    Returns:
        (B, 4, 4) rigid transforms, dtype and device of theta.
    """
    assets = _check_theta(model_or_assets, theta)
    rest = torch.as_tensor(rigid_rest_transforms(assets)[0], dtype=theta.dtype, device=theta.device)
    t, r = theta[:, 0:3], theta[:, 3:6]
    R = so3_exp(r)  # (B, 3, 3)
    c = rest[:3, 3]
    T = theta.new_zeros(theta.shape[0], 4, 4)
    T[:, :3, :3] = R @ rest[:3, :3]
    # G_root maps the root bone's origin c to R c + (c + t - R c) = c + t.
    T[:, :3, 3] = (c + t) * (MM_TO_M if metres else 1.0)
    T[:, 3, 3] = 1
    return T
