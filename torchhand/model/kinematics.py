"""Forward kinematics in twist form (thesis Ch. 4.2.1, Eq. 4.1-4.4).

A model's pose is ``theta: (B, D)``. Every model has one root bone carrying the
global rigid motion (6 DoF) and any number of child bones carrying up to three
revolute joints each (``K_j <= 3`` in the thesis' notation).

Conventions (chosen where the thesis leaves the choice open, see docs/model.md):

* ``G_j(theta) = T_j(theta) T_j(0)^-1`` is the motion of bone ``j`` relative to the
  rigging pose; it is exactly the matrix that linear blend skinning (Eq. 4.1) needs.
* Each revolute joint is the twist ``xi = (-omega x q, omega)`` of its axis
  ``omega`` (unit, rigging-pose world frame) through the bone's joint position ``q``.
  A bone's relative motion is the product of its joints' exponentials,
  ``hat T_j = prod_k exp(theta_jk hat xi_jk)`` (in the order x, y, z of the LIMITS
  file), and ``G_j = G_p(j) hat T_j`` (Eq. 4.4 written for ``G``).
* The global rigid motion uses six coordinates ``(t, r)``: the rotation vector
  ``r`` rotates about the root joint's rigging position ``c``, then ``t``
  translates: ``G_root = [R(r), c + t - R(r) c]``. Compared with one twist about
  the camera origin this decouples translation from rotation, which keeps the
  Gauss-Newton normal equations well conditioned (the hand is ~600 mm from the
  origin); ``theta = 0`` is still the rigging pose.

The tree is flattened once into index tensors and evaluated one depth level at a
time, so all bones of a level go through one batched matmul.
"""

from __future__ import annotations

from typing import NamedTuple, Tuple

import torch

__all__ = [
    "KinematicTree",
    "FKResult",
    "skew",
    "rotation_about_axis",
    "so3_exp",
    "so3_log",
    "so3_left_jacobian",
    "forward_kinematics",
    "point_jacobian",
]

ROOT_DOFS = 6  # (tx, ty, tz, rx, ry, rz) of the root bone
#: Order of a bone's revolute joints in the product prod_k exp(theta_k xi_k):
#: leftmost first: x, y, z as the rows of LIMITS (see docs/model.md).
SLOT_ORDER = (0, 1, 2)


class KinematicTree(NamedTuple):
    """Index tensors describing one model's skeleton and its degrees of freedom.

    J bones, D = 6 + number of revolute joints, S = 3 revolute slots per bone.

    parents: (J,) int64, parent bone of each bone, -1 for the root (bone 0).
    levels: tuple of (n_l,) int64 tensors, the bones at depth 1, 2, ... (the root is
        depth 0 and not listed).
    joint_rest: (J, 3) joint position (bone origin) in the rigging pose, world mm.
    slot_dof: (J, S) int64, the column of theta driving each revolute slot, -1 if unused.
    slot_axis: (J, S, 3) unit rotation axes in the rigging-pose world frame
        (zero for unused slots).
    dof_bone: (D,) int64, the bone each DoF moves (the root for the first 6).
    descendants: (J, J) bool, ``descendants[j, k]`` is true if bone j is bone k or
        lies below it, i.e. if DoFs of bone k move bone j.
    """

    parents: torch.Tensor
    levels: Tuple[torch.Tensor, ...]
    joint_rest: torch.Tensor
    slot_dof: torch.Tensor
    slot_axis: torch.Tensor
    dof_bone: torch.Tensor
    descendants: torch.Tensor

    @property
    def num_dofs(self) -> int:
        return int(self.dof_bone.shape[0])


class FKResult(NamedTuple):
    """G: (B, J, 4, 4) bone motions relative to the rigging pose, T_j(theta) T_j(0)^-1.
    twists: (B, D, 6) spatial twist ``(u, omega)`` of every DoF at theta, such that
        d x / d theta_d = omega_d x x + u_d for any point x rigidly moved by a bone
        that DoF d drives (the columns of the spatial manipulator Jacobian).
    """

    G: torch.Tensor
    twists: torch.Tensor


def skew(v: torch.Tensor) -> torch.Tensor:
    """Cross-product matrix. v: (..., 3) -> (..., 3, 3) with skew(a) @ b = a x b."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(v.shape[:-1] + (3, 3))


def rotation_about_axis(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula for a known unit axis (exact at angle 0, no division).

    Args:
        axis: (..., 3) unit vectors (a zero axis gives the identity).
        angle: (...) radians.
    Returns:
        (..., 3, 3) rotation matrices exp(angle * skew(axis)).
    """
    K = skew(axis)
    s = torch.sin(angle)[..., None, None]
    c = (1.0 - torch.cos(angle))[..., None, None]
    eye = torch.eye(3, dtype=axis.dtype, device=axis.device)
    return eye + s * K + c * (K @ K)


def _sinc_terms(theta2: torch.Tensor):
    """a = sin(t)/t, b = (1-cos t)/t^2, c = (t - sin t)/t^3 as functions of t^2.

    Taylor series below 1e-4 rad^2 keep values and gradients exact at zero without
    an epsilon in a denominator.
    """
    small = theta2 < 1e-4
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    t = safe2.sqrt()
    a = torch.where(small, 1 - theta2 / 6 + theta2**2 / 120, torch.sin(t) / t)
    b = torch.where(small, 0.5 - theta2 / 24 + theta2**2 / 720, (1 - torch.cos(t)) / safe2)
    c = torch.where(small, 1.0 / 6 - theta2 / 120 + theta2**2 / 5040, (t - torch.sin(t)) / (safe2 * t))
    return a, b, c


def so3_exp(rotvec: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of a rotation vector. rotvec: (..., 3) -> (..., 3, 3)."""
    a, b, _ = _sinc_terms((rotvec * rotvec).sum(-1))
    K = skew(rotvec)
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device)
    return eye + a[..., None, None] * K + b[..., None, None] * (K @ K)


def so3_left_jacobian(rotvec: torch.Tensor) -> torch.Tensor:
    """Left Jacobian of SO(3): the spatial angular velocity is J_l(r) dr.

    rotvec: (..., 3) -> (..., 3, 3).
    """
    _, b, c = _sinc_terms((rotvec * rotvec).sum(-1))
    K = skew(rotvec)
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device)
    return eye + b[..., None, None] * K + c[..., None, None] * (K @ K)


def so3_log(R: torch.Tensor) -> torch.Tensor:
    """Rotation vector of a rotation matrix. R: (..., 3, 3) -> (..., 3), angle in [0, pi].

    Used to initialise conversions, not inside solver iterations. Goes through the
    quaternion, which is stable near 0 and near pi.
    """
    m = R
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    # Shepperd's method: pick the largest of 4 candidate quaternion components.
    cand = torch.stack(
        [1 + tr, 1 + 2 * m[..., 0, 0] - tr, 1 + 2 * m[..., 1, 1] - tr, 1 + 2 * m[..., 2, 2] - tr], -1
    )
    i = cand.argmax(-1, keepdim=True)
    w = torch.stack(
        [
            torch.stack([1 + tr, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
            torch.stack([m[..., 2, 1] - m[..., 1, 2], cand[..., 1], m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]], -1),
            torch.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], cand[..., 2], m[..., 1, 2] + m[..., 2, 1]], -1),
            torch.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1], cand[..., 3]], -1),
        ],
        -2,
    )
    q = torch.take_along_dim(w, i[..., None], dim=-2).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True)
    q = torch.where(q[..., :1] < 0, -q, q)  # w >= 0 gives the angle in [0, pi]
    vec = q[..., 1:]
    s = vec.norm(dim=-1)
    angle = 2 * torch.atan2(s, q[..., 0])
    # angle / sin(angle / 2) -> 2 as s -> 0
    scale = torch.where(s < 1e-8, 2.0 / q[..., 0].clamp_min(1e-8), angle / s.clamp_min(1e-30))
    return vec * scale[..., None]


def _rigid(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3), (..., 3) -> (..., 4, 4)."""
    top = torch.cat([R, t[..., None]], -1)
    bottom = torch.zeros(R.shape[:-2] + (1, 4), dtype=R.dtype, device=R.device)
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], -2)


def forward_kinematics(theta: torch.Tensor, tree: KinematicTree) -> FKResult:
    """Bone motions and DoF twists of one model (Eq. 4.1-4.4).

    Args:
        theta: (B, D) pose; theta[:, 0:3] root translation (mm), theta[:, 3:6] root
            rotation vector (rad), theta[:, 6:] revolute joint angles (rad).
        tree: the model's :class:`KinematicTree`.
    Returns:
        :class:`FKResult` with G (B, J, 4, 4) and twists (B, D, 6).
    """
    B = theta.shape[0]
    J, S = tree.slot_dof.shape
    padded = torch.cat([theta, theta.new_zeros(B, 1)], 1)  # index -1 -> angle 0
    angles = padded[:, tree.slot_dof]  # (B, J, S)
    R_slot = rotation_about_axis(tree.slot_axis.expand(B, J, S, 3), angles)  # (B, J, S, 3, 3)

    # Cumulative products R_0, R_0 R_1, R_0 R_1 R_2 give the joint rotation of every bone
    # and, for the twists, the rotation applied before each slot.
    eye = torch.eye(3, dtype=theta.dtype, device=theta.device)
    before = [None] * S
    R_joint = R_slot.new_zeros(B, J, 3, 3) + eye
    for s in SLOT_ORDER:
        before[s] = R_joint
        R_joint = R_joint @ R_slot[:, :, s]
    q = tree.joint_rest.expand(B, J, 3)
    L = _rigid(R_joint, q - (R_joint @ q[..., None])[..., 0])  # rotation about q_j

    t, r = theta[:, 0:3], theta[:, 3:6]
    R_root = so3_exp(r)
    c = tree.joint_rest[0].expand(B, 3)
    root = _rigid(R_root, c + t - (R_root @ c[..., None])[..., 0])

    G = torch.empty(B, J, 4, 4, dtype=theta.dtype, device=theta.device)
    G[:, 0] = root
    for level in tree.levels:
        G[:, level] = G[:, tree.parents[level]] @ L[:, level]

    # Twists of the revolute slots: omega' = R_parent (R_0..R_{s-1}) omega_s,
    # through the current joint position q' = G_parent q_j.
    parent = tree.parents.clamp_min(0)
    G_par = G[:, parent]  # (B, J, 4, 4); the root row is unused
    q_now = (G_par[..., :3, :3] @ q[..., None])[..., 0] + G_par[..., :3, 3]  # (B, J, 3)
    pre = torch.stack(before, 2)  # (B, J, S, 3, 3)
    omega = (G_par[:, :, None, :3, :3] @ pre @ tree.slot_axis[None, ..., None])[..., 0]  # (B, J, S, 3)
    u = torch.cross(q_now[:, :, None].expand_as(omega), omega, dim=-1)
    slot_twist = torch.cat([u, omega], -1)  # (B, J, S, 6)

    D = tree.num_dofs
    twists = theta.new_zeros(B, D + 1, 6)
    flat_dof = tree.slot_dof.reshape(-1).clone()
    flat_dof[flat_dof < 0] = D  # unused slots write into a scratch row
    twists = twists.index_copy(1, flat_dof, slot_twist.reshape(B, J * S, 6))
    # Root: translations are pure (u = e_i); rotations spin about the moved root joint c + t.
    eye = eye.expand(B, 3, 3)
    w_root = so3_left_jacobian(r).transpose(-1, -2)  # rows are omega of r_x, r_y, r_z
    u_root = torch.cross((c + t)[:, None].expand(B, 3, 3), w_root, dim=-1)
    root_tw = torch.cat([torch.cat([eye, torch.zeros_like(eye)], -1), torch.cat([u_root, w_root], -1)], 1)
    twists = torch.cat([root_tw, twists[:, ROOT_DOFS:D]], 1)
    return FKResult(G, twists)


def point_jacobian(
    twists: torch.Tensor, weighted_points: torch.Tensor, weight_sums: torch.Tensor
) -> torch.Tensor:
    """Jacobian of blended points from per-DoF twists.

    For x = sum_j w_j G_j x0, d x / d theta_d = omega_d x S_d + W_d u_d with
    S_d = sum_{j driven by d} w_j G_j x0 and W_d = sum_{j driven by d} w_j.

    Args:
        twists: (B, D, 6) from :func:`forward_kinematics`.
        weighted_points: (B, N, D, 3) S_d for every point and DoF.
        weight_sums: (N, D) or (B, N, D) W_d.
    Returns:
        (B, N, 3, D).
    """
    u, omega = twists[..., :3], twists[..., 3:]
    J = torch.cross(omega[:, None].expand_as(weighted_points), weighted_points, dim=-1)
    J = J + weight_sums[..., None] * u[:, None]
    return J.transpose(-1, -2)
