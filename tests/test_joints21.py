"""The standard 21 joints on the shipped hands (torchhand.model.joints21)."""

from __future__ import annotations

import copy

import pytest
import torch

from torchhand.model.joints21 import (STANDARD_JOINT_NAMES, joint_sources, scene_joint_names, scene_standard_joints,
                                      standard_joints)
from torchhand.model.scene import Scene

HANDS = ("hand_right", "hand_left")
FINGERS = ("thumb", "index", "middle", "ring", "little")


def fist(model, amount: float = 0.8) -> torch.Tensor:
    """(1, D) a fist: every flexion joint (range over 1 rad) at ``amount`` of its larger limit."""
    lo, hi = model.lower, model.upper
    span = (hi - lo).nan_to_num(0.0, posinf=0.0, neginf=0.0)
    bend = torch.where(hi.abs() >= lo.abs(), hi, lo) * amount
    return torch.where(span > 1.0, bend, torch.zeros_like(bend))[None]


def poses(model):
    rest = model.zero_pose(1)
    moved = rest.clone()
    moved[:, :3] = torch.tensor([10.0, -20.0, 600.0], dtype=rest.dtype)
    moved[:, 3:6] = torch.tensor([0.3, -1.1, 0.4], dtype=rest.dtype)
    return torch.cat([rest, fist(model), moved, fist(model) + moved])


def test_names_and_order():
    assert len(STANDARD_JOINT_NAMES) == 21 and STANDARD_JOINT_NAMES[0] == "wrist"
    assert [STANDARD_JOINT_NAMES[i] for i in (4, 8, 12, 16, 20)] == [f"{f}_tip" for f in FINGERS]
    assert STANDARD_JOINT_NAMES[1:4] == ("thumb_cmc", "thumb_mcp", "thumb_ip")
    assert STANDARD_JOINT_NAMES[5:8] == ("index_mcp", "index_pip", "index_dip")


@pytest.mark.parametrize("name", HANDS)
def test_shape_and_joint_centres(name, model64):
    model = model64(name)
    theta = poses(model)
    out = model(theta)
    joints = standard_joints(out, model)
    assert joints.shape == (4, 21, 3) and joints.dtype == torch.float64
    # Finger joints are bone origins, as the model's own keypoints (same order but the tips).
    knuckles = [i for i in range(1, 21) if i % 4 != 0]
    torch.testing.assert_close(joints[:, knuckles], out.keypoints[:, knuckles])
    # The wrist is the root joint, about which the global rotation turns: it only translates.
    torch.testing.assert_close(joints[2, 0] - joints[0, 0], theta[2, :3])


@pytest.mark.parametrize("name", HANDS)
def test_bone_lengths_fix_the_order(name, model64):
    """Consecutive joints of a finger are bone lengths apart in every pose; the wrist is
    nearest the middle finger's base; each finger's joints move away from the wrist."""
    model = model64(name)
    joints = standard_joints(model(poses(model)), model)
    src = joint_sources(model)
    fingers = joints[:, 1:].reshape(-1, 5, 4, 3)
    steps = (fingers[:, :, 1:] - fingers[:, :, :-1]).norm(dim=-1)  # (B, 5, 3)
    lengths = model.bone_lengths[src.bones[1:].reshape(5, 3)[:, :2]]  # (5, 2) the bones between the joints
    torch.testing.assert_close(steps[:, :, :2], lengths.expand(4, 5, 2), atol=1e-3, rtol=0)
    # rigid bones; the tip vertex is skinned almost only to the distal bone
    torch.testing.assert_close(steps, steps[:1].expand_as(steps), atol=0.1, rtol=0)
    rest = fingers[0]
    from_wrist = (rest - joints[0, 0]).norm(dim=-1)
    assert bool((from_wrist[:, 1:] > from_wrist[:, :-1]).all())
    lengths = steps[0].sum(-1)  # finger lengths from the base joint: middle longest, little shortest of the four
    assert lengths[2] == lengths[1:].max() and lengths[4] == lengths[1:].min()


@pytest.mark.parametrize("name", HANDS)
def test_thumb_on_the_side_of_the_hand(name, model64):
    """Palm towards the viewer, fingers up: a right hand's thumb is on the viewer's right."""
    model = model64(name)
    rest, closed = standard_joints(model(poses(model)[:2]), model)
    up = rest[9] - rest[0]  # wrist -> middle MCP
    palm = (closed[[8, 12, 16, 20]] - rest[[8, 12, 16, 20]]).mean(0)  # fingertips close towards the palm
    side = torch.dot(rest[1] - rest[9], torch.linalg.cross(up, palm))
    assert (side > 0) == (model.side == "right")


@pytest.mark.parametrize("name", HANDS)
def test_tips_on_the_surface(name, model64):
    model = model64(name)
    out = model(poses(model))
    joints = standard_joints(out, model)
    tips = joints[:, [4, 8, 12, 16, 20]]
    nearest = torch.cdist(tips, out.vertices).min(-1).values
    assert float(nearest.max()) < 2.0
    # The tip lies beyond the end of the distal bone (the model's own tip keypoint).
    dip = joints[0, [3, 7, 11, 15, 19]]
    assert bool(((tips[0] - dip).norm(dim=-1) > (out.keypoints[0, [4, 8, 12, 16, 20]] - dip).norm(dim=-1)).all())


def test_gradient_finite_and_batched(model64):
    model = model64("hand_right")
    theta = poses(model).clone().requires_grad_(True)
    joints = standard_joints(model(theta), model)
    joints.square().sum().backward()
    assert torch.isfinite(theta.grad).all() and theta.grad.abs().sum() > 0
    one = standard_joints(model(theta[1:2].detach()), model)
    torch.testing.assert_close(one[0], joints[1].detach())


def test_float32_and_sources_reused():
    from torchhand import load_model

    model = load_model("hand_left")
    out = model(model.zero_pose(2))
    src = joint_sources(model)
    assert src.bones.shape == (16,) and src.tip_vertices.shape == (5,)
    torch.testing.assert_close(standard_joints(out, model, src), standard_joints(out, model))


def test_a_model_without_fingertips_is_refused(model64):
    with pytest.raises(ValueError, match="thumb_tip"):
        joint_sources(model64("ball"))


def test_on_the_device_as_on_the_cpu(device, model64):
    """The sources and joints follow the model to any device."""
    cpu = model64("hand_right")
    theta = poses(cpu)
    expected = standard_joints(cpu(theta), cpu)
    model = copy.deepcopy(cpu).to(device)
    src = joint_sources(model)
    assert src.bones.device == src.tip_vertices.device == model.vertices_rest.device
    got = standard_joints(model(theta.to(device)), model, src)
    assert got.device.type == torch.device(device).type
    torch.testing.assert_close(got.cpu(), expected, atol=1e-6, rtol=0)


def test_scene_joints_skip_objects(model64):
    scene = Scene.from_names(["hand_right", "ball", "hand_left"], dtype=torch.float64)
    theta = scene.zero_pose(2)
    posed = scene(theta)
    joints = scene_standard_joints(scene, posed)
    names = scene_joint_names(scene)
    assert joints.shape == (2, 42, 3) and len(names) == 42
    assert names[0] == "hand_right/wrist" and names[21] == "hand_left/wrist" and names[-1] == "hand_left/little_tip"
    torch.testing.assert_close(joints[:, 21:], standard_joints(posed.models[2], scene.models[2]))
    ball = Scene.from_names(["ball"], dtype=torch.float64)
    assert scene_standard_joints(ball, ball(torch.zeros(1, ball.num_dofs, dtype=torch.float64))).shape == (1, 0, 3)
