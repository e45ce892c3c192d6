"""Conversion between the thesis' MOTION rows (per-bone world transforms) and theta.

``theta_to_motion`` is exact (forward kinematics). ``motion_to_theta`` inverts it by
batched Levenberg-Marquardt over all frames at once: every bone frame is
represented by its origin and three points on its axes, and theta is fitted so
that the model's bone frames match the MOTION frames. Where a MOTION file moves a
bone in a way the joint axes of LIMITS cannot express exactly (the thesis data
does this by up to ~2 degrees at the thumb's metacarpal), the fit is the
least-squares compromise.

``pose_like_viewer`` poses vertices the way the original viewer does,
``v_k = sum_b w_b(v) Mk_b M0_b^-1 v``; it is the reference the round trip is
checked against (eval/check_hia_roundtrip.py).
"""

from __future__ import annotations

from typing import Dict

import numpy as np
import torch

from torchhand.model.kinematics import ROOT_DOFS, SLOT_ORDER, rotation_about_axis, so3_log
from torchhand.model.articulated import ArticulatedModel
from torchhand.model.skinning import lbs, lbs_jacobian
from torchhand.optim.levenberg_marquardt import levenberg_marquardt

__all__ = ["motion_to_theta", "theta_to_motion", "pose_like_viewer", "motion_tensor"]

_FRAME_SCALE = 20.0  # mm: length of the axis points that carry a bone's orientation


def motion_tensor(model: ArticulatedModel, motion: Dict[str, np.ndarray]) -> torch.Tensor:
    """Stack a MOTION dict into (N, J, 4, 4) in the model's bone order and dtype."""
    missing = [b for b in model.bone_names if b not in motion]
    if missing:
        raise KeyError(f"MOTION has no rows for bones {missing} of model {model.name!r}")
    M = np.stack([np.asarray(motion[b]) for b in model.bone_names], 1)
    return torch.as_tensor(M, dtype=model.lower.dtype, device=model.lower.device)


def theta_to_motion(model: ArticulatedModel, theta: torch.Tensor) -> Dict[str, np.ndarray]:
    """(N, D) poses -> bone name -> (N, 4, 4) world transforms T_j(theta)."""
    T = model.bone_transforms(theta).detach().cpu().double().numpy()
    return {b: T[:, j] for j, b in enumerate(model.bone_names)}


def motion_to_theta(
    model: ArticulatedModel,
    motion: Dict[str, np.ndarray] | torch.Tensor,
    iterations: int = 30,
    refine_vertices: int = 500,
    motion_rest: Dict[str, np.ndarray] | torch.Tensor | None = None,
) -> torch.Tensor:
    """Fit theta (N, D) to MOTION transforms.

    Two stages, each one batched LM over all frames: (1) bone frames (origin and
    axis points) from an exact root initialisation; (2) when ``refine_vertices`` > 0,
    that many evenly spread mesh vertices posed by the MOTION's own skinning
    (``sum_j w_j Mk_j M0_j^-1 v``), so that where the joint axes cannot express a
    MOTION row exactly, the residual is spread over the mesh instead of concentrated
    at the far end of a bone.

    Args:
        model: the model the MOTION belongs to (its rigging pose must be MOTION row 0).
        motion: bone name -> (N, 4, 4), or a tensor (N, J, 4, 4) in bone order.
        iterations: LM iterations per stage.
        refine_vertices: number of vertices for stage 2 (0 skips it).
        motion_rest: the MOTION's own rest pose (row 0; bone -> (4, 4) or (J, 4, 4)).
            When given, the fit targets Mk M0^-1, so a model whose rigging frames were
            built differently (e.g. the rope's, from SKEL) still reproduces the
            viewer's posing. Without it, MOTION row 0 must equal the model's rigging pose.
    Returns:
        (N, D) theta in the model's dtype and device, not clamped to the limits.
    """
    M = motion if isinstance(motion, torch.Tensor) else motion_tensor(model, motion)
    rest = model.rest_transforms
    if motion_rest is not None:
        # Fit the motion relative to its own rest pose, Mk M0^-1 (what the viewer
        # applies), re-expressed in this model's bone frames.
        M0 = motion_rest if isinstance(motion_rest, torch.Tensor) else motion_tensor(
            model, {b: np.asarray(m)[None] for b, m in motion_rest.items()})[0]
        M = M @ torch.linalg.inv(M0) @ rest
    G_target = M @ torch.linalg.inv(rest)  # (N, J, 4, 4)
    theta = _fit_bone_frames(model, M, _start_pose(model, M, G_target), iterations)
    if refine_vertices <= 0:
        return _wrap_angles(theta)
    return _wrap_angles(_fit_vertices(model, G_target, theta, refine_vertices, iterations))


def _start_pose(model: ArticulatedModel, M: torch.Tensor, G_target: torch.Tensor) -> torch.Tensor:
    """(N, D) start of :func:`motion_to_theta`'s fit: the root exact,
    ``G_root = [R, c + t - R c]``, the joints from :func:`_joint_angles_per_bone`.
    ``M``: (N, J, 4, 4) the bone frames to fit; ``G_target``: their ``M T_j(0)^-1``."""
    N = M.shape[0]
    c = model.rest_transforms[0, :3, 3]
    R = G_target[:, 0, :3, :3]
    t = G_target[:, 0, :3, 3] - c + (R @ c)
    theta0 = model.zero_pose(N)
    theta0[:, :3] = t
    theta0[:, 3:6] = so3_log(R)
    theta0[:, ROOT_DOFS:] = _joint_angles_per_bone(model, M)
    return theta0


def _fit_bone_frames(model: ArticulatedModel, M: torch.Tensor, theta0: torch.Tensor, iterations: int) -> torch.Tensor:
    """Stage 1 of :func:`motion_to_theta`: (N, D) theta whose bone frames match ``M``
    (N, J, 4, 4), four points per bone (its origin and axis points), LM from ``theta0``."""
    N, J = M.shape[:2]
    rest = model.rest_transforms
    # Four points per bone: origin and axis points, in the rigging pose.
    axes = torch.cat([rest.new_zeros(1, 3), _FRAME_SCALE * torch.eye(3, dtype=rest.dtype, device=rest.device)])
    local = torch.cat([axes, axes.new_ones(4, 1)], 1)  # (4, 4) homogeneous rows
    pts_rest = torch.einsum("jrc,pc->jpr", rest[:, :3, :], local).reshape(J * 4, 3)
    bone_of = torch.arange(J, device=rest.device).repeat_interleave(4)[:, None]
    target = torch.einsum("njrc,pc->njpr", M[..., :3, :], local).reshape(N, J * 4 * 3)
    ones = torch.ones_like(bone_of, dtype=rest.dtype)
    tree = model.tree

    def residuals(theta, with_jacobian):
        fk = model.kinematics(theta)
        Gp = fk.G[:, bone_of[:, 0]]
        x = (Gp[..., :3, :3] @ pts_rest[..., None])[..., 0] + Gp[..., :3, 3]
        r = x.reshape(N, -1) - target
        if not with_jacobian:
            return r, None
        Jac = lbs_jacobian(fk.G, fk.twists, pts_rest, bone_of, ones, tree.dof_bone, tree.descendants)
        return r, Jac.reshape(N, -1, model.num_dofs)

    return levenberg_marquardt(residuals, theta0, max_iterations=iterations, step_tolerance=1e-7).theta


def _fit_vertices(model: ArticulatedModel, G_target: torch.Tensor, theta: torch.Tensor, refine_vertices: int,
                  iterations: int) -> torch.Tensor:
    """Stage 2 of :func:`motion_to_theta`: (N, D) theta refined, by LM from ``theta``,
    on ``refine_vertices`` evenly spread mesh vertices posed by the MOTION's own
    skinning with ``G_target`` (N, J, 4, 4)."""
    N = G_target.shape[0]
    V = model.num_vertices
    tree = model.tree
    ids = torch.linspace(0, V - 1, min(refine_vertices, V), device=model.rest_transforms.device).round().long()
    v0 = model.vertices_rest[ids]
    idx, w = model.skin_index[ids], model.skin_weight[ids]
    Gk = G_target[:, idx, :3, :]  # (N, n, K, 3, 4): the MOTION's own skinning
    target_v = (w[None, ..., None] * ((Gk[..., :3] @ v0[None, :, None, :, None])[..., 0] + Gk[..., 3])).sum(2)
    target_v = target_v.reshape(N, -1)

    def vertex_residuals(theta, with_jacobian):
        fk = model.kinematics(theta)
        x = lbs(fk.G, model.skinning_matrix)[:, ids]
        r = x.reshape(N, -1) - target_v
        if not with_jacobian:
            return r, None
        Jac = lbs_jacobian(fk.G, fk.twists, v0, idx, w, tree.dof_bone, tree.descendants)
        return r, Jac.reshape(N, -1, model.num_dofs)

    return levenberg_marquardt(vertex_residuals, theta, max_iterations=iterations, step_tolerance=1e-7).theta


def _wrap_angles(theta: torch.Tensor) -> torch.Tensor:
    """Revolute angles into (-pi, pi]: the fit may land on a 2 pi-equivalent angle."""
    a = theta[:, ROOT_DOFS:]
    return torch.cat([theta[:, :ROOT_DOFS], torch.atan2(torch.sin(a), torch.cos(a))], 1)


def _joint_angles_per_bone(model: ArticulatedModel, M: torch.Tensor) -> torch.Tensor:
    """Initial joint angles (N, D - 6): each bone's slots fitted to its own rotation
    relative to its parent, all bones and frames as one batch of small LM problems.

    Starting the whole-skeleton fit from here instead of from zero avoids the local
    minima of long chains (the rope's 35 joints)."""
    N, J = M.shape[:2]
    used = model.slot_used
    bones = torch.nonzero(used.any(1))[:, 0]
    if len(bones) == 0:
        return M.new_zeros(N, 0)
    par = model.parents[bones]
    rel = M[:, par, :3, :3].transpose(-1, -2) @ M[:, bones, :3, :3]  # (N, n, 3, 3)
    rest = model.rest_transforms
    rel0 = rest[par, :3, :3].transpose(-1, -2) @ rest[bones, :3, :3]
    target = (rel0.transpose(-1, -2) @ rel).reshape(-1, 3, 3)  # rotation in the bone frame
    axes = (model.slot_axes * used[..., None])[bones].expand(N, -1, -1, -1).reshape(-1, 3, 3)

    def rotation(x):  # x: (P, 3) -> (P, 3, 3), slots in SLOT_ORDER
        R = torch.eye(3, dtype=x.dtype, device=x.device).expand(len(x), 3, 3)
        for s in SLOT_ORDER:
            R = R @ rotation_about_axis(axes[:, s], x[:, s])
        return R

    def residuals(x, with_jacobian):
        r = (rotation(x) - target).reshape(len(x), 9)
        if not with_jacobian:
            return r, None
        eps = 1e-6  # 3 parameters: central differences are exact enough for a start value
        cols = [(rotation(x + eps * e) - rotation(x - eps * e)).reshape(len(x), 9) / (2 * eps)
                for e in torch.eye(3, dtype=x.dtype, device=x.device)]
        return r, torch.stack(cols, -1)

    x = levenberg_marquardt(residuals, M.new_zeros(len(target), 3), max_iterations=30, step_tolerance=1e-9).theta
    x = x.reshape(N, len(bones), 3)
    out = M.new_zeros(N, J, 3)
    out[:, bones] = x
    return out[:, used]  # (N, D - 6) in DoF order (bones, then x, y, z slots)


def pose_like_viewer(vertices: torch.Tensor, weights: torch.Tensor, M: torch.Tensor, M0: torch.Tensor) -> torch.Tensor:
    """The viewer's skinning: v_k = sum_b w_b Mk_b M0_b^-1 v.

    Args:
        vertices: (V, 3) rest vertices; weights: (V, J) as stored in SKIN.
        M: (N, J, 4, 4) MOTION rows of the frames; M0: (J, 4, 4) row 0.
    Returns:
        (N, V, 3).
    """
    A = M @ torch.linalg.inv(M0)
    vh = torch.cat([vertices, vertices.new_ones(len(vertices), 1)], 1)
    return torch.einsum("vj,njrc,vc->nvr", weights, A[:, :, :3, :], vh)
