"""Tests for torchhand.model.urdf: URDF export checked against torchhand's own kinematics."""

from __future__ import annotations

import dataclasses
import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import torch

pk = pytest.importorskip("pytorch_kinematics")

from torchhand import load_model  # noqa: E402
from torchhand.model.urdf import (  # noqa: E402
    MM_TO_M,
    model_to_urdf,
    rigid_rest_transforms,
    root_transform,
    urdf_joint_names,
    urdf_joint_values,
    urdf_link_name,
)
from torchhand.model.kinematics import rotation_about_axis  # noqa: E402
from torchhand.model.articulated import ArticulatedModel  # noqa: E402

MODELS = ["hand_right", "rope", "pipe"]
NUM_POSES = 16


@pytest.fixture(scope="module")
def models():
    cache = {}

    def get(name):
        if name not in cache:
            cache[name] = load_model(name, dtype=torch.float64)
        return cache[name]

    return get


def _random_poses(model, n: int, seed: int = 0) -> torch.Tensor:
    """(n, D) poses: angles uniform within the limits, root translation in +-100 mm,
    root rotation vector of norm <= 1 rad."""
    gen = torch.Generator().manual_seed(seed)
    f64 = dict(generator=gen, dtype=torch.float64)
    theta = model.zero_pose(n)
    theta[:, 0:3] = (2 * torch.rand(n, 3, **f64) - 1) * 100.0
    direction = torch.randn(n, 3, **f64)
    theta[:, 3:6] = direction / direction.norm(dim=1, keepdim=True) * torch.rand(n, 1, **f64)
    lo, hi = model.lower[6:], model.upper[6:]
    theta[:, 6:] = lo + torch.rand(n, model.num_dofs - 6, **f64) * (hi - lo)
    return theta


def _rest_defect(model) -> float:
    """max |R^T R - I| over the stored rest frames (0 for exactly orthonormal frames)."""
    R = model.assets.rest_transforms[:, :3, :3]
    return float(np.abs(np.einsum("jab,jac->jbc", R, R) - np.eye(3)).max())


def _pk_world(model, xml: str, theta: torch.Tensor) -> torch.Tensor:
    """(B, J, 4, 4) world bone frames in mm from pytorch-kinematics, one batched FK call."""
    chain = pk.build_chain_from_urdf(xml.encode("utf-8")).to(dtype=torch.float64)
    q = urdf_joint_values(model, theta, chain.get_joint_parameter_names())
    frames = chain.forward_kinematics_tensor(q)  # (num_frames, B, 4, 4), metres
    idx = [chain.frame_to_idx[urdf_link_name(b)] for b in model.bone_names]
    world = root_transform(model, theta)[:, None] @ frames[idx].transpose(0, 1)
    world[..., :3, 3] = world[..., :3, 3] / MM_TO_M
    return world


@pytest.mark.parametrize("name", MODELS)
def test_pytorch_kinematics_matches_model(models, name):
    model = models(name)
    theta = _random_poses(model, NUM_POSES)
    world = _pk_world(model, model_to_urdf(model), theta)
    expected = model.bone_transforms(theta)

    pos_err = (world[..., :3, 3] - expected[..., :3, 3]).abs().max().item()
    rot_err = (world[..., :3, :3] - expected[..., :3, :3]).abs().max().item()
    assert pos_err < 1e-4, f"{name}: bone origins differ by {pos_err:.3g} mm"
    # pytorch-kinematics parses URDF origins and axes as float32 (urdf._convert_transform),
    # so exported rotations carry ~6e-8 of round-off per joint, accumulated along a
    # finger (up to 5 joints); any rest-frame defect of the assets adds to it (0 now
    # that the converter projects T_j(0) onto SO(3)). The exact float64 check of the
    # exported numbers is test_urdf_numbers_are_exact below.
    rot_tol = 3e-7 + 4 * _rest_defect(model)
    assert rot_err < rot_tol, f"{name}: bone rotations differ by {rot_err:.3g} (tolerance {rot_tol:.3g})"


def _rpy_matrix(rpy) -> np.ndarray:
    """URDF fixed-axis roll-pitch-yaw written out: Rz(yaw) Ry(pitch) Rx(roll)."""
    (cr, cp, cy), (sr, sp, sy) = np.cos(rpy), np.sin(rpy)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def _float64_urdf_fk(xml: str, joint_values: dict, batch: int) -> dict:
    """World frame (B, 4, 4), metres, of every link of a URDF, evaluated in float64.

    pytorch-kinematics parses origins and axes in float32 (``urdf._convert_transform``),
    which limits it to ~1e-7; this small evaluator checks the exported numbers exactly.
    """
    robot = ET.fromstring(xml)
    joints = {j.find("child").get("link"): j for j in robot.iter("joint")}
    frames = {}

    def frame(link):
        if link not in frames:
            if link not in joints:  # the root link
                frames[link] = torch.eye(4, dtype=torch.float64).expand(batch, 4, 4)
            else:
                j = joints[link]
                origin = torch.eye(4, dtype=torch.float64)
                xyz = [float(v) for v in j.find("origin").get("xyz").split()]
                rpy = [float(v) for v in j.find("origin").get("rpy").split()]
                origin[:3, :3] = torch.as_tensor(_rpy_matrix(np.array(rpy)))
                origin[:3, 3] = torch.tensor(xyz, dtype=torch.float64)
                motion = torch.eye(4, dtype=torch.float64).repeat(batch, 1, 1)
                if j.get("type") == "revolute":
                    axis = torch.tensor([float(v) for v in j.find("axis").get("xyz").split()], dtype=torch.float64)
                    motion[:, :3, :3] = rotation_about_axis(axis.expand(batch, 3), joint_values[j.get("name")])
                frames[link] = frame(j.find("parent").get("link")) @ origin @ motion
        return frames[link]

    for link in robot.iter("link"):
        frame(link.get("name"))
    return frames


@pytest.mark.parametrize("name", MODELS)
def test_urdf_numbers_are_exact(models, name):
    """In float64 the URDF reproduces the model with orthonormalised rest frames exactly."""
    model = models(name)
    rigid = ArticulatedModel(
        dataclasses.replace(model.assets, rest_transforms=rigid_rest_transforms(model)), dtype=torch.float64
    )
    theta = _random_poses(model, NUM_POSES, seed=1)
    xml = model_to_urdf(model)
    frames = _float64_urdf_fk(xml, urdf_joint_values(model, theta), NUM_POSES)
    local = torch.stack([frames[urdf_link_name(b)] for b in model.bone_names], 1)
    # root_transform(metres=False) is in mm, the links in metres: convert the links'
    # translations (world = T_root [R_l, t_l / MM_TO_M]).
    local_mm = local.clone()
    local_mm[..., :3, 3] = local[..., :3, 3] / MM_TO_M
    world = root_transform(model, theta, metres=False)[:, None] @ local_mm
    expected = rigid.bone_transforms(theta)
    assert (world[..., :3, 3] - expected[..., :3, 3]).abs().max().item() < 1e-9
    assert (world[..., :3, :3] - expected[..., :3, :3]).abs().max().item() < 1e-12


@pytest.mark.parametrize("name", MODELS)
def test_joint_names_and_limits(models, name):
    model = models(name)
    chain = pk.build_chain_from_urdf(model_to_urdf(model))
    names = chain.get_joint_parameter_names()
    revolute = model.dof_names[6:]
    # pytorch-kinematics orders joints depth-first, torchhand breadth-first: same set.
    assert sorted(names) == sorted(revolute) and len(names) == len(revolute)
    assert urdf_joint_names(model) == revolute
    lower, upper = chain.get_joint_limits()
    want = {n: (lo, hi) for n, lo, hi in zip(revolute, model.lower[6:].tolist(), model.upper[6:].tolist())}
    assert [(lo, hi) for lo, hi in zip(lower, upper)] == [want[n] for n in names]  # exact: repr round-trips
    # Every bone is a link under its own name; the root link is the root bone.
    assert set(model.bone_names) <= set(chain.get_link_names())
    assert chain.get_link_names()[0] == model.bone_names[0]


def test_rigging_pose_is_identity_offsets(models):
    """At theta = 0 the URDF frames are the (rigid) rest frames: T_root(0) @ FK = T_j(0)."""
    model = models("hand_right")
    theta = model.zero_pose(1)
    err = (_pk_world(model, model_to_urdf(model), theta)[0] - torch.as_tensor(rigid_rest_transforms(model))).abs()
    assert err[:, :3, 3].max() < 1e-5 and err[:, :3, :3].max() < 1e-6  # pk parses origins in float32


def test_write_and_overwrite(models, tmp_path):
    model = models("pipe")
    path = tmp_path / "pipe.urdf"
    xml = model_to_urdf(model, path)
    assert path.read_text(encoding="utf-8") == xml
    path.write_text("sentinel", encoding="utf-8")
    with pytest.raises(FileExistsError):
        model_to_urdf(model, path)
    assert path.read_text(encoding="utf-8") == "sentinel"
    assert model_to_urdf(model, str(path), overwrite=True) == xml
    assert path.read_text(encoding="utf-8") == xml
    assert [p.name for p in tmp_path.iterdir()] == ["pipe.urdf"]  # no temporary file left


def test_names_are_escaped(models):
    assets = dataclasses.replace(models("pipe").assets, bone_names=['Base <&> "1"', "Tip 'x'"])
    xml = model_to_urdf(assets)
    chain = pk.build_chain_from_urdf(xml)
    assert chain.get_joint_parameter_names() == assets.dof_names[6:]
    assert set(assets.bone_names) <= set(chain.get_link_names())


def test_single_bone_model_and_fixed_joints(models):
    robot = ET.fromstring(model_to_urdf(load_model("ball")))
    assert [l.get("name") for l in robot.iter("link")] == ["Bone001"] and not list(robot.iter("joint"))
    # A child bone without revolute slots is attached by a fixed joint.
    assets = models("pipe").assets
    assets = dataclasses.replace(assets, slot_used=np.zeros_like(assets.slot_used))
    (joint,) = ET.fromstring(model_to_urdf(assets)).iter("joint")
    assert joint.get("type") == "fixed" and joint.get("name") == f"{assets.bone_names[1]}:fixed"


def test_name_collision_is_refused(models):
    assets = models("rope").assets
    j = int(np.nonzero(assets.slot_used.sum(1) >= 2)[0][0])  # a bone with an intermediate link
    first_axis = "xyz"[int(np.nonzero(assets.slot_used[j])[0][0])]
    names = list(assets.bone_names)
    names[0] = urdf_link_name(names[j], first_axis)
    with pytest.raises(ValueError, match="not unique"):
        model_to_urdf(dataclasses.replace(assets, bone_names=names))


def test_joint_values_and_errors(models):
    model = models("pipe")
    theta = _random_poses(model, 3)
    values = urdf_joint_values(model, theta)
    assert list(values) == model.dof_names[6:]
    assert torch.equal(values[model.dof_names[6]], theta[:, 6])
    with pytest.raises(KeyError, match="no revolute joints"):
        urdf_joint_values(model, theta, ["nope:x"])
    with pytest.raises(ValueError, match="shape"):
        root_transform(model, theta[:, :5])
    with pytest.raises(TypeError, match="ArticulatedModel or ModelAssets"):
        model_to_urdf("pipe")
    # root_transform is rigid and carries the root translation (theta = 0 -> rest frame).
    T = root_transform(model, theta)
    R = T[:, :3, :3]
    assert torch.allclose(R.transpose(1, 2) @ R, torch.eye(3, dtype=torch.float64).expand(3, 3, 3), atol=1e-12)
    c = model.rest_transforms[0, :3, 3]
    assert torch.allclose(T[:, :3, 3], (c + theta[:, :3]) * MM_TO_M, atol=1e-15)
    assert math.isclose(float(root_transform(model, model.zero_pose(1))[0, 3, 3]), 1.0)
