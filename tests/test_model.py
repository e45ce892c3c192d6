"""ArticulatedModel and load_model (torchhand.model)."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
import torch

from conftest import random_theta, requires_cuda
from torchhand import HAND_KEYPOINT_NAMES, FINGER_NAMES, load_model
from torchhand.io import assets_from_thesis, read_thesis_model
from torchhand.model.articulated import ArticulatedModel

F64 = torch.float64


# ================================================================= structure
@pytest.mark.parametrize("name, side", [("hand_right", "right"), ("hand_left", "left")])
def test_hand_has_37_dofs_20_bones_21_named_keypoints(model64, name, side):
    model = model64(name)
    assert model.kind == "hand" and model.side == side
    assert model.num_dofs == 37 and len(model.dof_names) == 37
    assert model.num_bones == 20
    assert tuple(model.keypoint_names) == HAND_KEYPOINT_NAMES and len(HAND_KEYPOINT_NAMES) == 21
    assert model.keypoint_rest.shape == (21, 3) and model.keypoint_bones.shape == (21,)
    assert model.dof_names[:6] == ["root:tx", "root:ty", "root:tz", "root:rx", "root:ry", "root:rz"]
    assert model.lower.shape == model.upper.shape == (37,)
    assert torch.isinf(model.lower[:6]).all() and torch.isfinite(model.lower[6:]).all()
    assert (model.lower[6:] <= model.upper[6:]).all()


def test_objects_have_expected_dofs(model64):
    assert [model64(n).num_dofs for n in ("ball", "cube", "pipe", "rope")] == [6, 6, 7, 76]
    assert all(model64(n).kind == "object" and model64(n).keypoint_rest.shape == (0, 3)
               for n in ("ball", "cube", "pipe", "rope"))


def test_scene_of_two_hands_and_rope_has_150_dofs(model64):
    assert sum(model64(n).num_dofs for n in ("hand_right", "hand_left", "rope")) == 150


def test_scene_joint_motion_is_the_mean_joint_shift_of_a_hand_and_sees_a_rolling_ball(model64):
    """The tracker's stopping measure: a hand's mean joint displacement (a 1 mm shift
    moves it 1 mm), an object's mean vertex displacement (a ball rolling about its
    centre moves no bone origin but its vertices), the largest over the models."""
    from torchhand.model.scene import Scene

    scene = Scene([model64("hand_right"), model64("ball")])
    theta = scene.zero_pose(2)
    theta[:, scene.slices["ball"].start + 2] = 120.0  # the ball away from the hand
    a = scene(theta)
    shifted = theta.clone()
    shifted[0, 0] += 1.0  # the hand 1 mm along x
    rolled = theta.clone()
    rolled[1, scene.slices["ball"].start + 3] += 0.1  # the ball rotated 0.1 rad about its centre
    moved = scene.joint_motion(a, scene(shifted))
    torch.testing.assert_close(moved, torch.tensor([1.0, 0.0], dtype=F64))
    moved = scene.joint_motion(a, scene(rolled))
    assert float(moved[0]) == 0.0 and float(moved[1]) > 1.0, moved


def test_joints_from_are_the_origins_of_the_posed_bone_frames(model64):
    model = model64("rope")
    theta = model.zero_pose(2)
    theta[:, 6:] = 0.1 * torch.randn(2, model.num_dofs - 6, generator=torch.Generator().manual_seed(3), dtype=F64)
    theta[1, :3] = torch.tensor([5.0, -2.0, 30.0], dtype=F64)
    theta = model.clamp(theta)
    torch.testing.assert_close(model.joints_from(model(theta).G), model.bone_transforms(theta)[..., :3, 3])


def test_dof_index_and_unknown_names(model64):
    model = model64("hand_right")
    assert model.dof_index("root:rz") == 5
    assert model.dof_names[model.dof_index("RFing.1_0:y")] == "RFing.1_0:y"
    with pytest.raises(KeyError, match="no DoF 'nope'"):
        model.dof_index("nope")
    with pytest.raises(KeyError, match="no vertex group 'nope'") as err:
        model.group("nope")
    assert "index_tip" in str(err.value)  # lists the groups


def test_load_model_unknown_name_raises_lookup_error_listing_available_models():
    with pytest.raises(LookupError) as err:
        load_model("hand_middle")
    msg = str(err.value)
    assert "hand_middle" in msg
    assert all(n in msg for n in ("hand_right", "hand_left", "ball", "cube", "pipe", "rope"))


def test_load_model_from_npz_path_and_device_argument(tmp_path):
    from torchhand.io import find_model

    m = load_model(str(find_model("pipe")), dtype=F64, device="cpu")
    assert m.name == "pipe" and m.vertices_rest.dtype == F64 and m.vertices_rest.device.type == "cpu"


# ================================================================ bad theta
def test_theta_wrong_shape_names_theta_and_expected_shape(model64):
    model = model64("hand_right")
    for bad in (torch.zeros(2, 36, dtype=F64), torch.zeros(37, dtype=F64), torch.zeros(1, 2, 37, dtype=F64)):
        with pytest.raises(ValueError) as err:
            model(bad)
        msg = str(err.value)
        assert "theta" in msg and "(B, 37)" in msg and str(tuple(bad.shape)) in msg


def test_theta_not_a_tensor_raises_type_error(model64):
    with pytest.raises(TypeError, match=r"theta must be a torch.Tensor of shape \(B, 37\)"):
        model64("hand_right")(np.zeros((1, 37)))


def test_theta_wrong_dtype_raises_type_error_naming_both_dtypes(model64):
    model = model64("hand_right")  # float64
    with pytest.raises(TypeError) as err:
        model(torch.zeros(1, 37, dtype=torch.float32))
    msg = str(err.value)
    assert "theta" in msg and "float32" in msg and "float64" in msg


def test_theta_integer_dtype_is_rejected(model64):
    with pytest.raises(TypeError, match="theta"):
        model64("hand_right")(torch.zeros(1, 37, dtype=torch.int64))


@requires_cuda
def test_theta_on_wrong_device_names_both_devices(model64):
    model = model64("hand_right")  # on the CPU
    with pytest.raises(ValueError) as err:
        model(torch.zeros(1, 37, dtype=F64, device="cuda"))
    msg = str(err.value)
    assert "theta" in msg and "cuda" in msg and "cpu" in msg


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_theta_containing_nan_or_inf_is_rejected(model64, value):
    model = model64("hand_right")
    theta = model.zero_pose(3)
    theta[1, 10] = value
    with pytest.raises(ValueError, match="theta contains NaN or inf"):
        model(theta)
    model(theta, validate=False)  # the check can be skipped by callers that validated


def test_bone_transforms_checks_theta(model64):
    with pytest.raises(ValueError, match=r"theta must have shape \(B, 7\)"):
        model64("pipe").bone_transforms(torch.zeros(1, 6, dtype=F64))


# ============================================================ dtype, device, state
@pytest.mark.parametrize("convert", ["to", "double"])
def test_to_float64_converts_every_floating_buffer(convert):
    model = load_model("rope")  # float32, with a sparse CSR skinning matrix
    model = model.to(F64) if convert == "to" else model.double()
    for name, buf in model.named_buffers():
        if buf.is_floating_point():
            assert buf.dtype == F64, name
    assert model.faces.dtype == model.skin_index.dtype == model.parents.dtype == torch.int64
    assert model.descendants.dtype == torch.bool
    out = model(model.zero_pose(2))
    assert out.vertices.dtype == out.G.dtype == out.twists.dtype == F64
    assert model.zero_pose().dtype == F64
    back = model.float()
    assert back.vertices_rest.dtype == back.skinning_matrix.dtype == back.lower.dtype == torch.float32


@pytest.mark.parametrize("name", ["hand_right", "rope"])
def test_model_poses_and_differentiates_on_device_and_dtype(model64, name, device, dtype):
    ref = model64(name)
    model = load_model(name, dtype=dtype, device=device)
    assert model.vertices_rest.device.type == device.type and model.skinning_matrix.dtype == dtype
    theta = random_theta(ref, 2, torch.Generator().manual_seed(50))
    out = model(theta.to(device, dtype))
    assert out.vertices.device.type == device.type and out.vertices.dtype == dtype
    tol = 1e-9 if dtype == F64 else 2e-3  # mm
    assert (out.vertices.cpu().double() - ref(theta).vertices).abs().max() < tol
    ids = torch.arange(0, model.num_vertices, 97, device=device)
    J = model.jacobian(theta.to(device, dtype), ids)
    J_ref = ref.jacobian(theta, ids.cpu())
    assert J.device.type == device.type
    assert ((J.cpu().double() - J_ref).abs().max() / J_ref.abs().max()) < (1e-12 if dtype == F64 else 1e-4)


def test_float32_and_float64_models_agree(model64):
    m32 = load_model("hand_right")
    m64 = model64("hand_right")
    theta = random_theta(m64, 3, torch.Generator().manual_seed(40))
    v64 = m64(theta).vertices
    v32 = m32(theta.float()).vertices
    assert (v32.double() - v64).abs().max() < 1e-3  # mm


def test_state_dict_round_trip_into_fresh_model(model64):
    src = load_model("hand_right", dtype=F64)
    state = src.state_dict()
    assert {"vertices_rest", "faces", "skin_index", "skin_weight", "rest_transforms", "parents",
            "keypoint_rest", "keypoint_bones", "bone_lengths"} <= set(state)
    fresh = load_model("hand_right", dtype=F64)
    fresh.load_state_dict(state)
    for k, v in state.items():
        assert torch.equal(fresh.state_dict()[k], v), k
    theta = random_theta(src, 2, torch.Generator().manual_seed(41))
    for a, b in zip(src(theta), fresh(theta)):
        assert torch.equal(a, b)


def test_load_state_dict_of_other_model_poses_the_loaded_template(tmp_thesis_model):
    t = tmp_thesis_model
    assets = assets_from_thesis(read_thesis_model(t.dir, t.name))
    src = ArticulatedModel(dataclasses.replace(assets, vertices=assets.vertices * 1.5), dtype=F64)
    fresh = ArticulatedModel(assets, dtype=F64)  # same architecture, other template
    fresh.load_state_dict(src.state_dict())
    assert torch.equal(fresh.vertices_rest, src.vertices_rest)
    theta = src.zero_pose(1)
    torch.testing.assert_close(fresh(theta).vertices, src(theta).vertices)


@pytest.mark.parametrize("name", [
    "hand_right",
    "rope",
])
def test_model_can_be_deep_copied(name):
    model = load_model(name, dtype=F64)
    twin = copy.deepcopy(model)
    theta = random_theta(model, 1, torch.Generator().manual_seed(42))
    torch.testing.assert_close(twin(theta).vertices, model(theta).vertices, rtol=0, atol=0)


# ==================================================================== limits
def test_clamp_projects_into_limits_and_leaves_in_range_values_unchanged(model64):
    model = model64("hand_right")
    g = torch.Generator().manual_seed(43)
    inside = random_theta(model, 8, g)
    assert torch.equal(model.clamp(inside), inside)
    wild = inside.clone()
    wild[:, 6:] = (torch.rand(8, 31, generator=g, dtype=F64) - 0.5) * 20  # mostly outside
    wild[:, :6] = torch.tensor([1e4, -1e4, 3e3, 50.0, -50.0, 7.0], dtype=F64)  # root: unbounded
    c = model.clamp(wild)
    assert ((c >= model.lower) & (c <= model.upper)).all()
    assert torch.equal(c[:, :6], wild[:, :6])
    ok = (wild >= model.lower) & (wild <= model.upper)
    assert torch.equal(c[ok], wild[ok])
    assert torch.equal(c[~ok], torch.where(wild > model.upper, model.upper, model.lower).expand_as(c)[~ok])


def test_limit_violation_is_zero_inside_and_signed_excess_outside(model64):
    model = model64("hand_right")
    lo, hi = model.lower, model.upper
    inside = random_theta(model, 4, torch.Generator().manual_seed(44))
    assert torch.equal(model.limit_violation(inside), torch.zeros_like(inside))
    theta = inside.clone()
    d_hi, d_lo = model.dof_index("RFing.1_0:y"), model.dof_index("RFing.2_1:y")
    theta[:, d_hi] = hi[d_hi] + 0.3
    theta[:, d_lo] = lo[d_lo] - 0.2
    theta.requires_grad_()
    v = model.limit_violation(theta)
    expected = torch.zeros_like(inside)
    expected[:, d_hi], expected[:, d_lo] = 0.3, -0.2
    torch.testing.assert_close(v.detach(), expected, rtol=0, atol=1e-12)
    (grad,) = torch.autograd.grad((v**2).sum(), theta)
    assert torch.isfinite(grad).all()
    torch.testing.assert_close(grad, 2 * expected, rtol=0, atol=1e-12)  # d/dtheta of the squared penalty


# ============================================================== properties
def _bone_length_change(model, theta):
    o = model.bone_transforms(theta)[..., :3, 3]
    o0 = model.rest_transforms[:, :3, 3]
    p = model.parents[1:]
    d = (o[:, 1:] - o[:, p]).norm(dim=-1)
    d0 = (o0[1:] - o0[p]).norm(dim=-1)
    return (d - d0).abs().max().item()




@pytest.mark.parametrize("name", [
    "hand_right",
    "hand_left",
    "pipe",
    "rope",
])
def test_bone_lengths_stay_constant_under_random_poses(model64, name):
    model = model64(name)
    theta = random_theta(model, 16, torch.Generator().manual_seed(45))
    assert _bone_length_change(model, theta) < 1e-9


@pytest.mark.parametrize("name", ["hand_right", "hand_left"])
def test_bone_lengths_stay_constant_with_orthonormalised_rest_frames(rigid_model64, name):
    model = rigid_model64(name)
    theta = random_theta(model, 16, torch.Generator().manual_seed(45))
    assert _bone_length_change(model, theta) < 1e-9


@pytest.mark.parametrize("name", [
    "hand_right",
    "hand_left",
    "pipe",
    "rope",
])
def test_posed_bone_motions_are_rigid(model64, name):
    model = model64(name)
    G = model(random_theta(model, 8, torch.Generator().manual_seed(46))).G
    R = G[..., :3, :3]
    err = (R.transpose(-1, -2) @ R - torch.eye(3, dtype=F64)).abs().max()
    assert err < 1e-12
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(R.shape[:-2], dtype=F64), rtol=0, atol=1e-12)


def test_bone_transforms_at_zero_are_rest_transforms(model64):
    model = model64("hand_left")
    torch.testing.assert_close(model.bone_transforms(model.zero_pose(2)),
                               model.rest_transforms.expand(2, -1, -1, -1), rtol=0, atol=1e-12)


def test_root_translation_shifts_all_vertices_and_keypoints(model64):
    model = model64("hand_right")
    theta = random_theta(model, 2, torch.Generator().manual_seed(47))
    shifted = theta.clone()
    t = torch.tensor([12.5, -40.0, 250.0], dtype=F64)
    shifted[:, :3] += t
    a, b = model(theta), model(shifted)
    torch.testing.assert_close(b.vertices, a.vertices + t, rtol=0, atol=1e-9)
    torch.testing.assert_close(b.keypoints, a.keypoints + t, rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", ["hand_right", "hand_left"])
def test_fingertip_groups_lie_near_tip_keypoints(model64, name):
    model = model64(name)
    theta = random_theta(model, 16, torch.Generator().manual_seed(48))
    out = model(theta)
    for finger in FINGER_NAMES:
        ids = model.group(f"{finger}_tip")
        assert ids.ndim == 1 and len(ids) >= 5 and ids.max() < model.num_vertices
        marks = model.group(f"{finger}_tip_marks")
        assert len(marks) >= 1
        centroid = out.vertices[:, ids].mean(1)
        tip = out.keypoints[:, model.keypoint_names.index(f"{finger}_tip")]
        dist = (centroid - tip).norm(dim=-1)
        assert dist.max() < 15.0, f"{name} {finger}: {dist.max():.1f} mm"


def test_fingertip_groups_are_disjoint_and_distinct(model64):
    model = model64("hand_right")
    sets = [set(model.group(f"{f}_tip").tolist()) for f in FINGER_NAMES]
    for i in range(5):
        for j in range(i + 1, 5):
            assert not sets[i] & sets[j], (FINGER_NAMES[i], FINGER_NAMES[j])


def test_keypoints_are_joint_positions(model64):
    """Non-tip keypoints are bone origins: T_j(theta) translation of their bone."""
    model = model64("hand_right")
    theta = random_theta(model, 3, torch.Generator().manual_seed(49))
    out = model(theta)
    T = model.bone_transforms(theta)
    for k, n in enumerate(model.keypoint_names):
        if n == "wrist" or n.endswith("_tip"):
            continue
        torch.testing.assert_close(out.keypoints[:, k], T[:, model.keypoint_bones[k], :3, 3], rtol=0, atol=1e-9)


def test_scene_output_select_equals_posing_the_selected_problems():
    from torchhand.model.scene import Scene

    scene = Scene.from_names(["hand_right", "ball"], dtype=torch.float64)
    gen = torch.Generator().manual_seed(3)
    theta = scene.clamp(scene.lower.clamp(-1, 1) + torch.rand(3, scene.num_dofs, generator=gen, dtype=torch.float64))
    mask = torch.tensor([True, False, True])
    with torch.no_grad():
        picked, direct = scene(theta).select(mask), scene(theta[mask])
    for a, b in zip([picked.vertices, picked.keypoints] + [x for m in picked.models for x in m],
                    [direct.vertices, direct.keypoints] + [x for m in direct.models for x in m]):
        torch.testing.assert_close(a, b, atol=1e-9, rtol=0)  # batch size changes the rounding only
    assert len(picked.models) == 2 and picked.vertices.shape[0] == 2
