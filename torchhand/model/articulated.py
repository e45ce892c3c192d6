"""ArticulatedModel: a thin ``nn.Module`` holding one model's assets as buffers.

The pose is always an input. ``.to(device)``, ``.double()`` and ``state_dict`` work
on every asset because they are buffers::

    model = torchhand.load_model("hand_right")          # 37 DoF
    out = model(theta)                                  # theta: (B, 37)
    out.vertices, out.keypoints                         # (B, 10002, 3), (B, 21, 3)
    J = model.jacobian(theta, vertex_ids)               # (B, N, 3, 37), analytic
"""

from __future__ import annotations

from typing import List, NamedTuple, Optional

import numpy as np
import torch
from torch import nn

from torchhand.core.check import check_tensor
from torchhand.io.assets import ModelAssets, find_model, load_assets
from torchhand.model.kinematics import ROOT_DOFS, FKResult, KinematicTree, forward_kinematics
from torchhand.model.skinning import lbs, lbs_jacobian, skinning_matrix

__all__ = ["ArticulatedModel", "ModelOutput", "load_model"]


class ModelOutput(NamedTuple):
    """vertices: (B, V, 3) mm; keypoints: (B, P, 3) mm; G: (B, J, 4, 4) bone motions
    T_j(theta) T_j(0)^-1; twists: (B, D, 6) DoF twists (see kinematics.FKResult)."""

    vertices: torch.Tensor
    keypoints: torch.Tensor
    G: torch.Tensor
    twists: torch.Tensor


class ArticulatedModel(nn.Module):
    """One hand or object: mesh, kinematic tree, skinning weights, limits, keypoints.

    Args:
        assets: the model's :class:`~torchhand.io.assets.ModelAssets`.
        dtype: floating dtype of the buffers (float32 by default; use float64 for
            gradient checks).
    """

    def __init__(self, assets: ModelAssets, dtype: torch.dtype = torch.float32):
        super().__init__()
        self.assets = assets
        self.name = assets.name
        self.kind = assets.kind
        self.symmetry = assets.symmetry  # None or the shape symmetry (torchhand.io.assets.SYMMETRIES)
        self.side = assets.side
        self.bone_names: List[str] = list(assets.bone_names)
        self.dof_names: List[str] = assets.dof_names
        self.keypoint_names: List[str] = list(assets.keypoint_names)
        f = lambda a: torch.as_tensor(np.asarray(a), dtype=dtype)  # noqa: E731
        i = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.int64)  # noqa: E731

        # Persistent buffers: the assets themselves (saved in state_dict).
        self.register_buffer("vertices_rest", f(assets.vertices))
        self.register_buffer("faces", i(assets.faces))
        self.register_buffer("skin_index", i(assets.skin_index))
        self.register_buffer("skin_weight", f(assets.skin_weight))
        self.register_buffer("rest_transforms", f(assets.rest_transforms))
        self.register_buffer("bone_lengths", f(assets.bone_lengths))
        self.register_buffer("parents", i(assets.parents))
        self.register_buffer("slot_axes", f(assets.slot_axes))
        self.register_buffer("slot_used", torch.as_tensor(np.asarray(assets.slot_used, bool)))
        self.register_buffer("slot_limits", f(assets.slot_limits))
        self.register_buffer("keypoint_bones", i(assets.keypoint_bones))
        self.register_buffer("keypoint_rest", f(assets.keypoint_rest))
        self._derive()
        # Derived buffers must follow the assets when a state_dict is loaded.
        self.register_load_state_dict_post_hook(lambda module, keys: module._derive())

    def _derive(self) -> None:
        """(Re)build the non-persistent buffers that are functions of the assets:
        the skinning matrix, the flattened tree (Eq. 4.4) and the limits."""
        J = self.num_bones
        dev, dt = self.rest_transforms.device, self.rest_transforms.dtype
        i = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.int64, device=dev)  # noqa: E731
        self.register_buffer(
            "skinning_matrix", skinning_matrix(self.vertices_rest, self.skin_index, self.skin_weight, J),
            persistent=False,
        )
        # Dominant bone of each vertex: the thesis' segmentation into parts (Fig. 4.4).
        self.register_buffer("vertex_bone", self.skin_index[:, 0].clone(), persistent=False)
        parents = self.parents.cpu().numpy()
        used = self.slot_used.cpu().numpy()
        depth = np.zeros(J, np.int64)
        for j in range(1, J):
            depth[j] = depth[parents[j]] + 1
        self._num_levels = int(depth.max())
        for d in range(1, self._num_levels + 1):
            self.register_buffer(f"_level{d}", i(np.nonzero(depth == d)[0]), persistent=False)
        slot_dof = -np.ones((J, 3), np.int64)
        slot_dof[used] = ROOT_DOFS + np.arange(int(used.sum()))
        dof_bone = np.concatenate([np.zeros(ROOT_DOFS, np.int64), np.nonzero(used)[0]])
        axes = torch.einsum("jrc,jsc->jsr", self.rest_transforms[:, :3, :3], self.slot_axes)
        axes = axes / axes.norm(dim=-1, keepdim=True).clamp_min(1e-12) * self.slot_used[..., None]
        desc = np.eye(J, dtype=bool)
        for j in range(1, J):  # parents come first, so one pass fills all ancestors
            desc[j] |= desc[parents[j]]
        inf = torch.full((ROOT_DOFS,), float("inf"), dtype=dt, device=dev)
        self.register_buffer("slot_dof", i(slot_dof), persistent=False)
        self.register_buffer("slot_axis", axes, persistent=False)
        self.register_buffer("dof_bone", i(dof_bone), persistent=False)
        self.register_buffer("descendants", torch.as_tensor(desc, device=dev), persistent=False)
        self.register_buffer("lower", torch.cat([-inf, self.slot_limits[..., 0][self.slot_used]]), persistent=False)
        self.register_buffer("upper", torch.cat([inf, self.slot_limits[..., 1][self.slot_used]]), persistent=False)

    # ------------------------------------------------------------- properties
    @property
    def num_dofs(self) -> int:
        return len(self.dof_names)

    @property
    def num_vertices(self) -> int:
        return int(self.vertices_rest.shape[0])

    @property
    def num_bones(self) -> int:
        return len(self.bone_names)

    @property
    def tree(self) -> KinematicTree:
        return KinematicTree(
            parents=self.parents,
            levels=tuple(getattr(self, f"_level{d}") for d in range(1, self._num_levels + 1)),
            joint_rest=self.rest_transforms[:, :3, 3],
            slot_dof=self.slot_dof,
            slot_axis=self.slot_axis,
            dof_bone=self.dof_bone,
            descendants=self.descendants,
        )

    def group(self, name: str) -> torch.Tensor:
        """Vertex ids of a named vertex group (e.g. ``"index_tip"``)."""
        if name not in self.assets.groups:
            raise KeyError(f"model {self.name!r} has no vertex group {name!r}; groups: {sorted(self.assets.groups)}")
        return torch.as_tensor(self.assets.groups[name], device=self.faces.device)

    def dof_index(self, name: str) -> int:
        """Column of theta of a DoF named ``"<bone>:<axis>"`` or ``"root:tx"``."""
        try:
            return self.dof_names.index(name)
        except ValueError:
            raise KeyError(f"model {self.name!r} has no DoF {name!r}; DoFs: {self.dof_names}") from None

    def zero_pose(self, batch_size: int = 1) -> torch.Tensor:
        """(B, D) rigging pose (all zeros)."""
        return self.lower.new_zeros(batch_size, self.num_dofs)

    # ------------------------------------------------------------------ checks
    def check_theta(self, theta: torch.Tensor, name: str = "theta") -> torch.Tensor:
        """Validate a pose: (B, D) floating tensor of the model's dtype and device, finite."""
        check_tensor(theta, name, ("B", self.num_dofs), device=self.lower.device, finite=True)
        if theta.dtype != self.lower.dtype:
            raise TypeError(f"{name} has dtype {theta.dtype} but model {self.name!r} is {self.lower.dtype}")
        return theta

    # ----------------------------------------------------------------- posing
    def kinematics(self, theta: torch.Tensor) -> FKResult:
        """Bone motions G (B, J, 4, 4) and DoF twists (B, D, 6) (no input checks)."""
        return forward_kinematics(theta, self.tree)

    def forward(self, theta: torch.Tensor, validate: bool = True) -> ModelOutput:
        """Pose the model.

        Args:
            theta: (B, D) pose.
            validate: check shape/dtype/device/finiteness (one host sync); solvers
                that already validated their input pass False.
        Returns:
            :class:`ModelOutput`.
        """
        if validate:
            self.check_theta(theta)
        G, twists = self.kinematics(theta)
        vertices = lbs(G, self.skinning_matrix)
        return ModelOutput(vertices, self.keypoints_from(G), G, twists)

    def keypoints_from(self, G: torch.Tensor) -> torch.Tensor:
        """(B, J, 4, 4) -> (B, P, 3) keypoints rigidly attached to their bones."""
        Gk = G[:, self.keypoint_bones]
        return (Gk[..., :3, :3] @ self.keypoint_rest[..., None])[..., 0] + Gk[..., :3, 3]

    def joints_from(self, G: torch.Tensor) -> torch.Tensor:
        """(..., J, 4, 4) -> (..., J, 3) posed bone origins (the joint positions)."""
        origin = self.rest_transforms[:, :3, 3]
        return (G[..., :3, :3] @ origin[..., None])[..., 0] + G[..., :3, 3]

    def bone_transforms(self, theta: torch.Tensor) -> torch.Tensor:
        """World bone frames T_j(theta) = G_j T_j(0): (B, J, 4, 4), as in MOTION files."""
        return self.kinematics(self.check_theta(theta)).G @ self.rest_transforms

    def jacobian(
        self, theta: torch.Tensor, vertex_ids: Optional[torch.Tensor] = None, fk: Optional[FKResult] = None
    ) -> torch.Tensor:
        """Analytic Jacobian of posed vertices w.r.t. theta.

        Args:
            theta: (B, D) (may be None when ``fk`` is given).
            vertex_ids: (N,) int64 subset of vertices, or (B, N) for a different subset
                per batch element (default: all; that is B x V x 3 x D numbers, so
                pass a subset for large batches).
            fk: kinematics already computed for theta, to avoid recomputing it.
        Returns:
            (B, N, 3, D).
        """
        G, twists = fk if fk is not None else self.kinematics(theta)
        ids = slice(None) if vertex_ids is None else vertex_ids
        return lbs_jacobian(G, twists, self.vertices_rest[ids], self.skin_index[ids], self.skin_weight[ids],
                            self.dof_bone, self.descendants)

    def keypoint_jacobian(self, theta: torch.Tensor, fk: Optional[FKResult] = None) -> torch.Tensor:
        """(B, P, 3, D) Jacobian of the keypoints."""
        G, twists = fk if fk is not None else self.kinematics(theta)
        bones = self.keypoint_bones[:, None]
        return lbs_jacobian(G, twists, self.keypoint_rest, bones, torch.ones_like(bones, dtype=G.dtype),
                            self.dof_bone, self.descendants)

    # ----------------------------------------------------------------- limits
    def clamp(self, theta: torch.Tensor) -> torch.Tensor:
        """Project theta into the joint limits (root DoF are unbounded)."""
        return torch.maximum(torch.minimum(theta, self.upper), self.lower)

    def limit_violation(self, theta: torch.Tensor) -> torch.Tensor:
        """(B, D) signed amount outside the limits: theta - upper above, theta - lower
        below, 0 inside. Differentiable (its square is the penalty of Eq. 4.17)."""
        return torch.relu(theta - self.upper) - torch.relu(self.lower - theta)

    def extra_repr(self) -> str:
        return (f"name={self.name!r}, kind={self.kind!r}, bones={self.num_bones}, dofs={self.num_dofs}, "
                f"vertices={self.num_vertices}, faces={int(self.faces.shape[0])}")


def load_model(name: str, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> ArticulatedModel:
    """Load a shipped model by name (``hand_right``, ``hand_left``, ``ball``, ``cube``,
    ``pipe``, ``rope``) or from a path to a model ``.npz``."""
    model = ArticulatedModel(load_assets(find_model(name)), dtype=dtype)
    return model.to(device) if device is not None else model
