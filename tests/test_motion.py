"""MOTION rows <-> theta (torchhand.model.motion)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from conftest import random_theta
from torchhand.io import assets_from_thesis, read_motion, sequence_models, write_motion
from torchhand.model.articulated import ArticulatedModel
from torchhand.model.motion import motion_tensor, motion_to_theta, pose_like_viewer, theta_to_motion

F64 = torch.float64


def test_theta_to_motion_gives_world_bone_frames(model64):
    model = model64("hand_right")
    theta = random_theta(model, 4, torch.Generator().manual_seed(60))
    motion = theta_to_motion(model, theta)
    assert list(motion) == model.bone_names
    assert all(isinstance(M, np.ndarray) and M.shape == (4, 4, 4) and M.dtype == np.float64 for M in motion.values())
    T = model.bone_transforms(theta)
    np.testing.assert_array_equal(motion_tensor(model, motion).numpy(), T.numpy())
    # at theta = 0 the frames are the rigging pose (MOTION row 0)
    rest = theta_to_motion(model, model.zero_pose(1))
    np.testing.assert_allclose(np.stack([rest[b][0] for b in model.bone_names]), model.rest_transforms.numpy(),
                               rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", ["hand_right", "pipe"])
def test_motion_to_theta_recovers_random_in_limit_poses(model64, name):
    model = model64(name)
    theta = random_theta(model, 4, torch.Generator().manual_seed(61))
    recovered = motion_to_theta(model, theta_to_motion(model, theta))
    assert recovered.shape == theta.shape and recovered.dtype == F64
    err = (model(recovered).vertices - model(theta).vertices).norm(dim=-1).max()
    assert err < 1e-3, f"{name}: vertices differ by {err:.3g} mm"


@pytest.mark.parametrize("scale, batch", [(0.2, 2), (1.0, 1)], ids=["small", "full-range"])
def test_motion_to_theta_recovers_in_limit_rope_poses(model64, scale, batch):
    model = model64("rope")
    theta = scale * random_theta(model, batch, torch.Generator().manual_seed(61))
    recovered = motion_to_theta(model, theta_to_motion(model, theta), refine_vertices=0)
    err = (model(recovered).vertices - model(theta).vertices).norm(dim=-1).max()
    assert err < 1e-3, f"vertices differ by {err:.3g} mm"


def test_motion_to_theta_recovers_in_limit_joint_angles(model64):
    model = model64("hand_right")
    theta = random_theta(model, 8, torch.Generator().manual_seed(1))
    recovered = motion_to_theta(model, theta_to_motion(model, theta), refine_vertices=0)
    assert model.limit_violation(recovered).abs().max() < 1e-6
    torch.testing.assert_close(recovered, theta, rtol=0, atol=1e-6)


def test_motion_round_trip_through_a_motion_file(model64, tmp_path):
    model = model64("hand_left")
    theta = random_theta(model, 2, torch.Generator().manual_seed(62), margin=0.05)
    path = tmp_path / "Model_Hand_L.MOTION"
    write_motion(path, theta_to_motion(model, theta))
    assert "Lower Arm L" in read_motion(path)  # the bone name with spaces survives
    recovered = motion_to_theta(model, read_motion(path), refine_vertices=0)
    err = (model(recovered).vertices - model(theta).vertices).norm(dim=-1).max()
    assert err < 1e-3


def test_motion_tensor_missing_bone_raises_key_error(model64):
    model = model64("pipe")
    motion = theta_to_motion(model, model.zero_pose(1))
    del motion[model.bone_names[1]]
    with pytest.raises(KeyError, match=model.bone_names[1]):
        motion_tensor(model, motion)


def test_pose_like_viewer_at_rest_row_returns_template(model64):
    model = model64("hand_right")
    from torchhand.model.skinning import dense_weights

    W = dense_weights(model.skin_index, model.skin_weight, model.num_bones)
    M0 = model.rest_transforms
    out = pose_like_viewer(model.vertices_rest, W, M0[None], M0)
    torch.testing.assert_close(out[0], model.vertices_rest, rtol=0, atol=1e-9)


def test_pose_like_viewer_equals_model_for_exact_motion(rigid_model64):
    """For MOTION produced by the model itself, the viewer's skinning is the model's."""
    model = rigid_model64("hand_right")
    from torchhand.model.skinning import dense_weights

    W = dense_weights(model.skin_index, model.skin_weight, model.num_bones)
    theta = random_theta(model, 2, torch.Generator().manual_seed(63))
    M = model.bone_transforms(theta)
    ref = pose_like_viewer(model.vertices_rest, W, M, model.rest_transforms)
    torch.testing.assert_close(model(theta).vertices, ref, rtol=0, atol=1e-9)


@pytest.mark.slow
def test_real_motion_sequence_01_posed_via_theta_matches_viewer(hia_root, real_right_hand):
    files = real_right_hand
    _, bounds = sequence_models(hia_root, "01")
    model = ArticulatedModel(assets_from_thesis(files), dtype=F64)
    M_all = motion_tensor(model, files.motion)
    rows = torch.arange(20) + bounds.motion_offset  # video frame k uses MOTION row k + offset
    M = M_all[rows]
    theta = motion_to_theta(model, M)
    order = [files.skin.bone_names.index(b) for b in model.bone_names]
    W = torch.as_tensor(files.skin.weights[:, order])
    with torch.no_grad():
        ours = model(theta).vertices
        ref = pose_like_viewer(model.vertices_rest, W, M, M_all[0])
    err = (ours - ref).norm(dim=-1)
    assert err.median() < 0.5 and err.max() < 2.0, f"median {err.median():.3f} mm, max {err.max():.3f} mm"
    # the hand actually moves over these frames (the check is not trivially at rest)
    assert (ref - model.vertices_rest).norm(dim=-1).max() > 10.0


def test_motion_rest_makes_the_fit_independent_of_the_bone_frame_convention():
    """A MOTION whose bone frames are rotated about their own x axes (another rigging
    convention) poses the mesh identically; with ``motion_rest`` the fit reproduces it."""
    from torchhand.model.articulated import load_model
    from torchhand.model.skinning import dense_weights

    model = load_model("hand_right", dtype=F64)
    g = torch.Generator().manual_seed(5)
    theta = model.zero_pose(4)
    theta[:, 6:] = (model.lower[6:] + (model.upper[6:] - model.lower[6:]) * torch.rand(4, 31, generator=g, dtype=F64))
    theta[:, :3] = 10 * torch.randn(4, 3, generator=g, dtype=F64)
    M = model.bone_transforms(theta)
    c, s = torch.cos(torch.tensor(0.7, dtype=F64)), torch.sin(torch.tensor(0.7, dtype=F64))
    Rx = torch.eye(4, dtype=F64)
    Rx[1, 1], Rx[1, 2], Rx[2, 1], Rx[2, 2] = c, -s, s, c
    M_other = M @ Rx  # same motion, other bone-frame convention
    M0_other = model.rest_transforms @ Rx
    W = dense_weights(model.skin_index, model.skin_weight, model.num_bones)
    ref = pose_like_viewer(model.vertices_rest, W, M_other, M0_other)
    fitted = motion_to_theta(model, M_other, motion_rest=M0_other)
    err = (model(fitted).vertices - ref).norm(dim=-1).max()
    assert err < 1e-3, float(err)
    wrong = motion_to_theta(model, M_other, refine_vertices=0)  # without motion_rest
    assert (model(wrong).vertices - ref).norm(dim=-1).max() > 1.0
