"""Linear blend skinning and its analytic Jacobian (torchhand.model.skinning, ArticulatedModel)."""

from __future__ import annotations

import pytest
import torch

from conftest import random_theta
from torchhand.model.kinematics import forward_kinematics
from torchhand.model.skinning import dense_weights, lbs, lbs_dense_reference, lbs_jacobian, skinning_matrix

F64 = torch.float64
ARTICULATED = ["hand_right", "hand_left", "pipe", "rope"]


def _autograd_vertex_jacobian(model, theta, ids):
    """(B, N, 3, D) d vertices[ids] / d theta by autograd (forward mode, vectorised).

    Forward-mode AD does not go through sparse CSR products, so the rope is posed
    through a copy whose skinning matrix is dense (the same numbers); the sparse path's
    gradient is checked against the dense one in a separate test.
    """
    if model.skinning_matrix.layout != torch.strided:
        model = _dense_twin(model)
    # one pose at a time: a batched call would also compute the (zero) cross-pose blocks
    return torch.cat([
        torch.autograd.functional.jacobian(lambda t: model(t).vertices[:, ids], theta[b : b + 1],
                                           vectorize=True, strategy="forward-mode")[:, :, :, 0]
        for b in range(theta.shape[0])
    ])


def _dense_twin(model):
    """The same model with a dense skinning matrix (copy.deepcopy cannot copy CSR buffers)."""
    from torchhand.model.articulated import ArticulatedModel

    twin = ArticulatedModel(model.assets, dtype=model.lower.dtype)
    twin.skinning_matrix = model.skinning_matrix.to_dense()
    return twin


def _rel_err(a, b):
    return ((a - b).abs().max() / b.abs().max()).item()


# ======================================================================== LBS
@pytest.mark.parametrize("name", ["hand_right", "rope", "pipe"])
def test_lbs_dense_and_sparse_match_dense_reference(model64, name):
    model = model64(name)
    J = model.num_bones
    theta = random_theta(model, 3, torch.Generator().manual_seed(20))
    G = forward_kinematics(theta, model.tree).G
    W = dense_weights(model.skin_index, model.skin_weight, J)
    ref = lbs_dense_reference(G, model.vertices_rest, W)
    P_dense = skinning_matrix(model.vertices_rest, model.skin_index, model.skin_weight, J, sparse=False)
    P_csr = skinning_matrix(model.vertices_rest, model.skin_index, model.skin_weight, J, sparse=True)
    assert P_dense.layout == torch.strided and P_csr.layout == torch.sparse_csr
    assert P_dense.shape == P_csr.shape == (model.num_vertices, 4 * J)
    for P in (P_dense, P_csr):
        out = lbs(G, P)
        assert out.shape == (3, model.num_vertices, 3)
        torch.testing.assert_close(out, ref, rtol=0, atol=1e-10)


def test_lbs_reference_is_the_weighted_sum_of_bone_transforms():
    """Two bones, hand-computed: v = 0.25 G_0 v0 + 0.75 G_1 v0."""
    G = torch.eye(4, dtype=F64).repeat(1, 2, 1, 1)
    G[0, 1, :3, 3] = torch.tensor([4.0, 0.0, 0.0], dtype=F64)
    G[0, 1, :3, :3] = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=F64)
    v0 = torch.tensor([[1.0, 2.0, 3.0]], dtype=F64)
    W = torch.tensor([[0.25, 0.75]], dtype=F64)
    expected = 0.25 * v0 + 0.75 * (torch.tensor([-2.0, 1.0, 3.0], dtype=F64) + torch.tensor([4.0, 0, 0], dtype=F64))
    torch.testing.assert_close(lbs_dense_reference(G, v0, W)[0], expected, rtol=0, atol=1e-15)
    idx, w = torch.tensor([[1, 0]]), torch.tensor([[0.75, 0.25]], dtype=F64)
    for sparse in (False, True):
        P = skinning_matrix(v0, idx, w, 2, sparse=sparse)
        torch.testing.assert_close(lbs(G, P)[0], expected, rtol=0, atol=1e-15)


def test_default_skinning_matrix_layout_follows_density(model64):
    # dense products beat CSR on CPU for all shipped models (eval/bench_lbs.py)
    assert model64("hand_right").skinning_matrix.layout == torch.strided
    assert model64("rope").skinning_matrix.layout == torch.strided


@pytest.mark.parametrize("name", ["hand_right", "hand_left", "ball", "cube", "pipe", "rope"])
def test_rest_pose_reproduces_template_and_keypoints(model64, name):
    model = model64(name)
    out = model(model.zero_pose(2))
    torch.testing.assert_close(out.vertices, model.vertices_rest.expand(2, -1, -1), rtol=0, atol=1e-9)
    torch.testing.assert_close(out.keypoints, model.keypoint_rest.expand(2, -1, -1), rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", ["hand_right", "rope"])
def test_rest_pose_reproduces_template_in_float32(name):
    from torchhand import load_model

    model = load_model(name)  # float32
    out = model(model.zero_pose(1))
    assert out.vertices.dtype == torch.float32
    scale = model.vertices_rest.abs().max()
    torch.testing.assert_close(out.vertices[0], model.vertices_rest, rtol=0, atol=1e-6 * scale.item())


def test_gradient_through_sparse_lbs_equals_dense(model64):
    model = model64("rope")
    dense = _dense_twin(model)
    theta = random_theta(model, 2, torch.Generator().manual_seed(21))
    target = torch.randn(2, model.num_vertices, 3, generator=torch.Generator().manual_seed(22), dtype=F64)
    grads = []
    for m in (model, dense):
        t = theta.clone().requires_grad_()
        loss = ((m(t).vertices - target) ** 2).sum()
        grads.append(torch.autograd.grad(loss, t)[0])
    assert torch.isfinite(grads[0]).all()
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-10, atol=1e-8)


# ================================================================== Jacobians
@pytest.mark.parametrize("name", ARTICULATED)
def test_analytic_vertex_jacobian_matches_autograd(model64, name):
    model = model64(name)
    theta = random_theta(model, 1 if name == "rope" else 2, torch.Generator().manual_seed(23))
    ids = torch.linspace(0, model.num_vertices - 1, 300).round().long()
    J = model.jacobian(theta, ids)
    assert J.shape == (len(theta), 300, 3, model.num_dofs)
    err = _rel_err(J, _autograd_vertex_jacobian(model, theta, ids))
    assert err < 1e-6, f"{name}: analytic Jacobian differs from autograd by {err:.3g} (relative)"


@pytest.mark.parametrize("name", ["hand_right", "hand_left"])
def test_analytic_vertex_jacobian_is_exact_on_rigid_models(rigid_model64, name):
    """With re-orthonormalised rest frames the hands' analytic Jacobian equals autograd
    to 1e-12 (pipe and rope are rigid as shipped: covered by the test above)."""
    model = rigid_model64(name)
    theta = random_theta(model, 1, torch.Generator().manual_seed(24))
    ids = torch.linspace(0, model.num_vertices - 1, 150).round().long()
    err = _rel_err(model.jacobian(theta, ids), _autograd_vertex_jacobian(model, theta, ids))
    assert err < 1e-12


@pytest.mark.parametrize("name", ["hand_right", "hand_left"])
def test_keypoint_jacobian_matches_autograd(model64, name):
    model = model64(name)
    theta = random_theta(model, 2, torch.Generator().manual_seed(25))
    Jk = model.keypoint_jacobian(theta)
    assert Jk.shape == (2, 21, 3, 37)
    full = torch.autograd.functional.jacobian(lambda t: model(t).keypoints, theta, vectorize=True)
    auto = torch.stack([full[b, :, :, b] for b in range(2)])
    err = _rel_err(Jk, auto)
    assert err < 1e-6, f"{name}: keypoint Jacobian differs from autograd by {err:.3g} (relative)"


@pytest.mark.parametrize("name", ["hand_right", "rope"])
def test_jacobian_with_vertex_ids_equals_rows_of_full_jacobian(model64, name):
    model = model64(name)
    theta = random_theta(model, 2, torch.Generator().manual_seed(26))
    full = model.jacobian(theta)
    assert full.shape == (2, model.num_vertices, 3, model.num_dofs)
    ids = torch.randperm(model.num_vertices, generator=torch.Generator().manual_seed(27))[:97]
    # matrix products of other sizes may sum in another order: equal to rounding
    torch.testing.assert_close(model.jacobian(theta, ids), full[:, ids], rtol=0, atol=1e-12)
    fk = model.kinematics(theta)  # passing precomputed kinematics gives the same
    torch.testing.assert_close(model.jacobian(theta, ids, fk=fk), model.jacobian(theta, ids), rtol=0, atol=0)


def test_jacobian_with_per_batch_vertex_ids_equals_rows_of_full_jacobian(model64):
    model = model64("hand_left")
    theta = random_theta(model, 3, torch.Generator().manual_seed(31))
    full = model.jacobian(theta)
    ids = torch.stack([torch.randperm(model.num_vertices, generator=torch.Generator().manual_seed(s))[:40]
                       for s in range(3)])  # (B, N): another subset per pose
    J = model.jacobian(theta, ids)
    assert J.shape == (3, 40, 3, model.num_dofs)
    for b in range(3):
        torch.testing.assert_close(J[b], full[b, ids[b]], rtol=1e-12, atol=1e-12)  # another product path


def test_jacobian_of_dof_is_zero_on_vertices_it_does_not_move(model64):
    model = model64("hand_right")
    theta = random_theta(model, 1, torch.Generator().manual_seed(28))
    J = model.jacobian(theta)[0]  # (V, 3, D)
    d = model.dof_index("RFing.2_2:y")  # a distal joint
    bone = int(model.dof_bone[d])
    W = dense_weights(model.skin_index, model.skin_weight, model.num_bones)
    unaffected = W[:, model.descendants[:, bone]].sum(1) == 0
    assert unaffected.sum() > 1000 and (~unaffected).sum() > 10
    assert (J[unaffected, :, d] == 0).all()
    assert J[~unaffected, :, d].abs().amax() > 1e-3


@pytest.mark.parametrize("name", ["hand_right", "rope"])
def test_batch_of_5_equals_5_batches_of_1(model64, name):
    model = model64(name)
    theta = random_theta(model, 5, torch.Generator().manual_seed(29))
    ids = torch.arange(0, model.num_vertices, 50)
    out5 = model(theta)
    J5 = model.jacobian(theta, ids)
    Jk5 = model.keypoint_jacobian(theta)
    for b in range(5):
        out1 = model(theta[b : b + 1])
        for a5, a1 in zip(out5, out1):
            torch.testing.assert_close(a5[b : b + 1], a1, rtol=1e-13, atol=1e-11)
        torch.testing.assert_close(J5[b : b + 1], model.jacobian(theta[b : b + 1], ids), rtol=1e-13, atol=1e-11)
        torch.testing.assert_close(Jk5[b : b + 1], model.keypoint_jacobian(theta[b : b + 1]), rtol=1e-13, atol=1e-11)


def test_lbs_jacobian_of_one_hot_points_equals_rigid_twist_jacobian(model64):
    """A point rigidly attached to bone j (weight 1): J = omega_d x x + u_d for DoFs driving j."""
    model = model64("pipe")
    tree = model.tree
    theta = random_theta(model, 1, torch.Generator().manual_seed(30))
    G, tw = forward_kinematics(theta, tree)
    pts = torch.tensor([[10.0, 2.0, -3.0], [200.0, 5.0, 1.0]], dtype=F64)
    bones = torch.tensor([[0], [1]])
    J = lbs_jacobian(G, tw, pts, bones, torch.ones(2, 1, dtype=F64), tree.dof_bone, tree.descendants)[0]
    for i, j in enumerate([0, 1]):
        x = G[0, j, :3, :3] @ pts[i] + G[0, j, :3, 3]
        expected = torch.cross(tw[0, :, 3:], x.expand(model.num_dofs, 3), dim=-1) + tw[0, :, :3]
        expected = expected * tree.descendants[j, tree.dof_bone][:, None]
        torch.testing.assert_close(J[i], expected.T, rtol=0, atol=1e-12)
