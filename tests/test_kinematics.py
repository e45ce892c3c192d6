"""SO(3) helpers and forward kinematics (torchhand.model.kinematics)."""

from __future__ import annotations

import math

import pytest
import torch
from scipy.spatial.transform import Rotation

from conftest import random_theta, tolerance
from torchhand.model.kinematics import (
    forward_kinematics,
    rotation_about_axis,
    skew,
    so3_exp,
    so3_left_jacobian,
    so3_log,
)

F64 = torch.float64


def _random_rotvecs(n: int, max_angle: float, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    axis = torch.randn(n, 3, generator=g, dtype=F64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    return axis * torch.rand(n, 1, generator=g, dtype=F64) * max_angle


def _vee(S: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) skew part -> (..., 3)."""
    A = 0.5 * (S - S.transpose(-1, -2))
    return torch.stack([A[..., 2, 1], A[..., 0, 2], A[..., 1, 0]], -1)


# ================================================================== SO(3)
def test_skew_matrix_is_cross_product(device, dtype):
    g = torch.Generator().manual_seed(0)
    a = torch.randn(5, 3, generator=g, dtype=F64).to(device, dtype)
    b = torch.randn(5, 3, generator=g, dtype=F64).to(device, dtype)
    torch.testing.assert_close((skew(a) @ b[..., None])[..., 0], torch.cross(a, b, dim=-1), **tolerance(dtype))
    torch.testing.assert_close(skew(a), -skew(a).transpose(-1, -2))


def test_so3_exp_matches_scipy_from_rotvec(device, dtype):
    r = torch.cat([_random_rotvecs(200, 2 * math.pi, seed=1), _random_rotvecs(50, 1e-3, seed=2),
                   torch.zeros(1, 3, dtype=F64)])
    ref = torch.as_tensor(Rotation.from_rotvec(r.numpy()).as_matrix())
    R = so3_exp(r.to(device, dtype))
    assert R.dtype == dtype and R.device.type == device.type
    torch.testing.assert_close(R.cpu().double(), ref, rtol=0, atol=1e-12 if dtype == F64 else 2e-6)


def test_so3_exp_broadcasts_leading_dims():
    r = _random_rotvecs(24, 3.0).reshape(2, 3, 4, 3)
    R = so3_exp(r)
    assert R.shape == (2, 3, 4, 3, 3)
    torch.testing.assert_close(R.reshape(24, 3, 3), so3_exp(r.reshape(24, 3)), rtol=0, atol=0)


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-6, 1e-3, 1e-2, 0.5, 2.0, 3.0, math.pi - 1e-4, math.pi - 1e-7])
def test_so3_log_inverts_so3_exp(angle):
    g = torch.Generator().manual_seed(3)
    axis = torch.randn(64, 3, generator=g, dtype=F64)
    r = axis / axis.norm(dim=-1, keepdim=True) * angle
    back = so3_log(so3_exp(r))
    torch.testing.assert_close(back, r, rtol=0, atol=1e-10)


def test_so3_log_of_identity_is_exactly_zero():
    r = so3_log(torch.eye(3, dtype=F64).expand(4, 3, 3))
    assert torch.equal(r, torch.zeros(4, 3, dtype=F64))


def test_so3_log_at_angle_pi_returns_a_valid_rotation_vector():
    r = torch.tensor([[math.pi, 0, 0], [0, -math.pi, 0], [1.0, 2.0, -2.0]], dtype=F64)
    r[2] = r[2] / r[2].norm() * math.pi
    R = so3_exp(r)
    back = so3_log(R)
    torch.testing.assert_close(back.norm(dim=-1), torch.full((3,), math.pi, dtype=F64), rtol=0, atol=1e-7)
    torch.testing.assert_close(so3_exp(back), R, rtol=0, atol=1e-7)  # r or -r


def test_so3_log_matches_scipy_as_rotvec():
    R = Rotation.random(100, random_state=5)
    ref = torch.as_tensor(R.as_rotvec())
    torch.testing.assert_close(so3_log(torch.as_tensor(R.as_matrix())), ref, rtol=0, atol=1e-10)


def test_rotation_matrices_are_orthonormal_with_det_one(device, dtype):
    r = _random_rotvecs(300, 3 * math.pi, seed=4).to(device, dtype)
    g = torch.Generator().manual_seed(7)
    angle = (torch.rand(300, generator=g, dtype=F64) * 20 - 10).to(device, dtype)
    axis = r / r.norm(dim=-1, keepdim=True)
    eye = torch.eye(3, dtype=dtype, device=device)
    for R in (so3_exp(r), rotation_about_axis(axis, angle)):
        tol = tolerance(dtype)
        torch.testing.assert_close(R.transpose(-1, -2) @ R, eye.expand_as(R), **tol)
        torch.testing.assert_close(torch.linalg.det(R), torch.ones_like(angle), **tol)


def test_rotation_about_axis_equals_so3_exp_of_axis_times_angle():
    r = _random_rotvecs(100, 3.0, seed=8)
    angle = r.norm(dim=-1)
    axis = r / angle[:, None]
    torch.testing.assert_close(rotation_about_axis(axis, angle), so3_exp(r), rtol=0, atol=1e-14)
    # a zero axis gives the identity whatever the angle
    torch.testing.assert_close(rotation_about_axis(torch.zeros(3, dtype=F64), torch.tensor(1.3, dtype=F64)),
                               torch.eye(3, dtype=F64), rtol=0, atol=0)


def test_so3_exp_gradient_at_exactly_zero_is_finite_and_equals_generators():
    r = torch.zeros(3, dtype=F64, requires_grad=True)
    R = so3_exp(r)
    rows = []
    for k in range(9):  # d R_k / d r via torch.autograd.grad, one entry at a time
        (g,) = torch.autograd.grad(R.reshape(-1)[k], r, retain_graph=True)
        rows.append(g)
    dR = torch.stack(rows).reshape(3, 3, 3)  # [row, col, i]
    assert torch.isfinite(dR).all()
    expected = skew(torch.eye(3, dtype=F64)).permute(1, 2, 0)  # dR/dr_i at 0 = skew(e_i)
    torch.testing.assert_close(dR, expected, rtol=0, atol=1e-15)


def test_so3_exp_second_derivative_at_zero_is_finite():
    r = torch.zeros(3, dtype=F64, requires_grad=True)
    (g,) = torch.autograd.grad(so3_exp(r)[0, 0], r, create_graph=True)
    (h,) = torch.autograd.grad(g.sum(), r)
    assert torch.isfinite(h).all()


def test_so3_left_jacobian_gradient_at_exactly_zero_is_finite():
    r = torch.zeros(3, dtype=F64, requires_grad=True)
    Jl = so3_left_jacobian(r)
    torch.testing.assert_close(Jl.detach(), torch.eye(3, dtype=F64), rtol=0, atol=0)
    dJ = torch.stack([torch.autograd.grad(Jl.reshape(-1)[k], r, retain_graph=True)[0] for k in range(9)])
    assert torch.isfinite(dJ).all()
    # J_l(r) = I + K/2 + O(|r|^2): d J_l / d r_i at 0 = skew(e_i) / 2
    expected = 0.5 * skew(torch.eye(3, dtype=F64)).permute(1, 2, 0)
    torch.testing.assert_close(dJ.reshape(3, 3, 3), expected, rtol=0, atol=1e-15)


@pytest.mark.parametrize("max_angle", [1e-3, 0.02, 1.0, 3.0])
def test_so3_left_jacobian_matches_finite_difference_of_spatial_angular_velocity(max_angle):
    """skew(J_l(r) dr) = (d R / d t) R^T for R = so3_exp(r + t dr)."""
    r = _random_rotvecs(20, max_angle, seed=9)
    Jl = so3_left_jacobian(r)
    h = 1e-6
    R = so3_exp(r)
    for i in range(3):
        e = torch.zeros(3, dtype=F64)
        e[i] = 1
        dR = (so3_exp(r + h * e) - so3_exp(r - h * e)) / (2 * h)
        S = dR @ R.transpose(-1, -2)
        torch.testing.assert_close(S, -S.transpose(-1, -2), rtol=0, atol=1e-8)  # it is skew
        torch.testing.assert_close(Jl[..., i], _vee(S), rtol=0, atol=1e-8)


# ====================================================== forward kinematics
@pytest.mark.parametrize("name", [pytest.param("hand_right", marks=pytest.mark.slow), "rope"])
def test_forward_kinematics_gradcheck_wrt_theta(model64, name):
    model = model64(name)
    tree = model.tree
    theta = random_theta(model, 1, torch.Generator().manual_seed(11)).requires_grad_()
    # full gradcheck on the hand; the rope (36 bones, 76 DoF, 576 outputs) in fast mode
    assert torch.autograd.gradcheck(lambda t: forward_kinematics(t, tree).G, (theta,),
                                    fast_mode=(name == "rope"))


@pytest.mark.parametrize("name", ["hand_right", "hand_left", "pipe", "rope"])
def test_forward_kinematics_at_zero_is_identity(model64, name):
    model = model64(name)
    fk = forward_kinematics(model.zero_pose(2), model.tree)
    assert fk.G.shape == (2, model.num_bones, 4, 4) and fk.twists.shape == (2, model.num_dofs, 6)
    torch.testing.assert_close(fk.G, torch.eye(4, dtype=F64).expand_as(fk.G), rtol=0, atol=0)


@pytest.mark.parametrize("name", [pytest.param("hand_right", marks=pytest.mark.slow), "hand_left", "pipe", "rope"])
def test_twists_equal_autograd_derivative_of_attached_points(model64, name):
    """d(G_j x0)/d theta_d == omega_d x (G_j x0) + u_d if DoF d drives bone j, else 0."""
    model = model64(name)
    tree = model.tree
    J, D = model.num_bones, model.num_dofs
    g = torch.Generator().manual_seed(12)
    theta = random_theta(model, 1, g)
    # 3 points per bone, within ~50 mm of the bone's rest origin
    x0 = tree.joint_rest[:, None] + 50 * (torch.rand(J, 3, 3, generator=g, dtype=F64) - 0.5)

    def points(t):
        G = forward_kinematics(t, tree).G
        return (G[:, :, None, :3, :3] @ x0[None, ..., None])[..., 0] + G[:, :, None, :3, 3]  # (1, J, 3, 3)

    x = points(theta)[0]
    auto = torch.autograd.functional.jacobian(points, theta, vectorize=True, strategy="forward-mode")
    auto = auto[0, ..., 0, :]  # (J, P, 3, D)
    tw = forward_kinematics(theta, tree).twists[0]  # (D, 6)
    u, w = tw[..., :3], tw[..., 3:]
    pred = torch.cross(w.expand(J, 3, D, 3), x[:, :, None].expand(J, 3, D, 3), dim=-1) + u
    drives = tree.descendants[:, tree.dof_bone]  # (J, D): DoF d moves bone j
    pred = (pred * drives[:, None, :, None]).transpose(-1, -2)  # (J, P, 3, D)
    assert (auto[~drives[:, None, None, :].expand_as(auto)] == 0).all()
    err = (pred - auto).abs().max() / auto.abs().max()
    assert err < 1e-6, f"{name}: twists differ from autograd by {err:.3g} (relative)"


@pytest.mark.parametrize("name", ["hand_right", "hand_left", "pipe", "rope"])
def test_twists_equal_autograd_derivative_to_machine_precision_on_rigid_models(rigid_model64, name):
    """With orthonormal rest frames (hands re-orthonormalised, see conftest.rigid_model64)
    the twists are the exact derivative (1e-10 relative)."""
    model = rigid_model64(name)
    tree = model.tree
    theta = random_theta(model, 1, torch.Generator().manual_seed(13))
    x0 = tree.joint_rest + torch.tensor([3.0, -4.0, 5.0], dtype=F64)

    def points(t):
        G = forward_kinematics(t, tree).G[0]
        return (G[:, :3, :3] @ x0[..., None])[..., 0] + G[:, :3, 3]

    auto = torch.autograd.functional.jacobian(points, theta, vectorize=True,
                                              strategy="forward-mode")[:, :, 0]  # (J, 3, D)
    tw = forward_kinematics(theta, tree).twists[0]
    x = points(theta)
    pred = torch.cross(tw[None, :, 3:].expand(len(x), -1, 3), x[:, None].expand(-1, tw.shape[0], 3), dim=-1)
    pred = (pred + tw[None, :, :3]) * tree.descendants[:, tree.dof_bone][..., None]
    torch.testing.assert_close(pred.transpose(1, 2), auto, rtol=0, atol=1e-10 * auto.abs().max().item())


def test_root_translation_and_rotation_semantics(model64):
    """G_root = [R(r), c + t - R c]: t translates every bone; r rotates about the root joint c."""
    model = model64("hand_right")
    tree = model.tree
    c = tree.joint_rest[0]
    theta = model.zero_pose(1)
    theta[0, :3] = torch.tensor([10.0, -20.0, 30.0], dtype=F64)
    G = forward_kinematics(theta, tree).G[0]
    torch.testing.assert_close(G[:, :3, 3], torch.tensor([10.0, -20.0, 30.0], dtype=F64).expand(model.num_bones, 3))
    torch.testing.assert_close(G[:, :3, :3], torch.eye(3, dtype=F64).expand(model.num_bones, 3, 3))
    theta = model.zero_pose(1)
    theta[0, 3:6] = torch.tensor([0.3, -0.2, 0.5], dtype=F64)
    G = forward_kinematics(theta, tree).G[0]
    torch.testing.assert_close(G[0, :3, :3] @ c + G[0, :3, 3], c, rtol=0, atol=1e-12)  # c is fixed
    torch.testing.assert_close(G[0, :3, :3], so3_exp(theta[0, 3:6]), rtol=0, atol=1e-15)


def test_revolute_dof_moves_only_its_bone_and_descendants(model64):
    model = model64("hand_right")
    tree = model.tree
    d = model.dof_index("RFing.1_0:y")
    bone = int(tree.dof_bone[d])
    theta = model.zero_pose(1)
    theta[0, d] = 0.4
    G = forward_kinematics(theta, tree).G[0]
    moved = (G - torch.eye(4, dtype=F64)).abs().amax((-1, -2)) > 1e-12
    expected = tree.descendants[:, bone]
    assert torch.equal(moved, expected)
    assert model.bone_names[bone] == "RFing.1_0" and expected.sum() == 3  # the bone, _1 and _2
