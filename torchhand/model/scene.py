"""Scene: several articulated models (hands, objects) posed from one parameter tensor.

``theta: (B, D)`` is the concatenation of the models' poses in scene order; the
two thesis hands plus the rope give D = 37 + 37 + 76 = 150 (thesis Ch. 4.2.1)::

    scene = Scene.from_names(["hand_right", "hand_left", "rope"])
    scene.num_dofs                       # 150
    scene.slices["hand_left"]            # slice(37, 74)
    out = scene(theta)                   # vertices (B, V_total, 3), keypoints, per model
"""

from __future__ import annotations

from typing import Dict, List, NamedTuple, Optional, Sequence

import torch
from torch import nn

from torchhand.core.check import check_tensor
from torchhand.geometry.mesh import vertex_faces
from torchhand.model.articulated import ArticulatedModel, ModelOutput, load_model

__all__ = ["Scene", "SceneOutput"]


class SceneOutput(NamedTuple):
    """vertices: (B, V, 3) all models' vertices concatenated in scene order;
    keypoints: (B, P, 3) all models' keypoints concatenated (objects have none);
    models: per-model :class:`ModelOutput`, in scene order."""

    vertices: torch.Tensor
    keypoints: torch.Tensor
    models: List[ModelOutput]

    def select(self, index: torch.Tensor) -> "SceneOutput":
        """The batch elements ``index`` (a (B,) bool mask or indices) of every field."""
        return SceneOutput(self.vertices[index], self.keypoints[index],
                           [ModelOutput(*(x[index] for x in m)) for m in self.models])


class Scene(nn.Module):
    """Models sharing one parameter tensor.

    Args:
        models: the models, in the order of their slices in theta.
        names: unique names (default: each model's name).
    """

    def __init__(self, models: Sequence[ArticulatedModel], names: Optional[Sequence[str]] = None):
        super().__init__()
        if not models:
            raise ValueError("a scene needs at least one model")
        names = list(names) if names is not None else [m.name for m in models]
        if len(set(names)) != len(names) or len(names) != len(models):
            raise ValueError(f"scene model names must be unique, one per model; got {names}")
        dtypes = {m.lower.dtype for m in models}
        if len(dtypes) != 1:
            raise TypeError(f"all models of a scene must share one dtype, got {dtypes}")
        self.names: List[str] = names
        self.models = nn.ModuleList(models)
        self.slices: Dict[str, slice] = {}
        self.vertex_slices: Dict[str, slice] = {}
        self.keypoint_slices: Dict[str, slice] = {}
        start = vstart = kstart = 0
        faces, face_model, face_bone, vertex_model, vertex_part = [], [], [], [], []
        bones = 0
        for k, (n, m) in enumerate(zip(names, models)):
            self.slices[n] = slice(start, start + m.num_dofs)
            self.vertex_slices[n] = slice(vstart, vstart + m.num_vertices)
            self.keypoint_slices[n] = slice(kstart, kstart + len(m.keypoint_names))
            faces.append(m.faces + vstart)
            face_model.append(torch.full((len(m.faces),), k, dtype=torch.int64))
            face_bone.append(m.vertex_bone[m.faces[:, 0]])  # part of a face = part of its first vertex
            vertex_model.append(torch.full((m.num_vertices,), k, dtype=torch.int64))
            vertex_part.append(m.vertex_bone + bones)
            bones += m.num_bones
            start += m.num_dofs
            vstart += m.num_vertices
            kstart += len(m.keypoint_names)
        self.dof_names: List[str] = [f"{n}/{d}" for n, m in zip(names, models) for d in m.dof_names]
        self.keypoint_names: List[str] = [f"{n}/{p}" for n, m in zip(names, models) for p in m.keypoint_names]
        self.register_buffer("faces", torch.cat(faces), persistent=False)
        self.register_buffer("face_model_id", torch.cat(face_model), persistent=False)
        self.register_buffer("face_bone_id", torch.cat(face_bone), persistent=False)
        self.register_buffer("vertex_model_id", torch.cat(vertex_model), persistent=False)
        # each vertex's dominant bone, numbered over the scene (model k's bones after those of models < k)
        self.register_buffer("vertex_bone_id", torch.cat(vertex_part), persistent=False)
        self.num_bones = bones
        self.register_buffer("vertex_faces", vertex_faces(self.faces, vstart), persistent=False)  # one-rings

    @classmethod
    def from_names(cls, names: Sequence[str], dtype: torch.dtype = torch.float32, device=None) -> "Scene":
        """Scene of shipped models (or model ``.npz`` paths), e.g. ``["hand_right", "ball"]``."""
        return cls([load_model(n, dtype=dtype, device=device) for n in names])

    # ---------------------------------------------------------------- queries
    @property
    def num_dofs(self) -> int:
        return len(self.dof_names)

    @property
    def num_vertices(self) -> int:
        return int(self.vertex_model_id.shape[0])

    @property
    def lower(self) -> torch.Tensor:
        """(D,) lower joint limits (-inf for the global DoF)."""
        return torch.cat([m.lower for m in self.models])

    @property
    def upper(self) -> torch.Tensor:
        return torch.cat([m.upper for m in self.models])

    def model(self, name: str) -> ArticulatedModel:
        if name not in self.slices:
            raise KeyError(f"scene has no model {name!r}; models: {self.names}")
        return self.models[self.names.index(name)]

    def dof_index(self, name: str) -> int:
        """Column of a DoF named ``"<model>/<bone>:<axis>"``."""
        try:
            return self.dof_names.index(name)
        except ValueError:
            raise KeyError(f"scene has no DoF {name!r} (e.g. {self.dof_names[:3]}...)") from None

    def split(self, theta: torch.Tensor) -> Dict[str, torch.Tensor]:
        """(B, D) -> model name -> (B, D_model) views."""
        return {n: theta[:, s] for n, s in self.slices.items()}

    def join(self, poses: Dict[str, torch.Tensor]) -> torch.Tensor:
        """Model name -> (B, D_model) back to (B, D)."""
        missing = [n for n in self.names if n not in poses]
        if missing:
            raise KeyError(f"poses missing for models {missing}")
        return torch.cat([poses[n] for n in self.names], 1)

    def zero_pose(self, batch_size: int = 1) -> torch.Tensor:
        return torch.cat([m.zero_pose(batch_size) for m in self.models], 1)

    def check_theta(self, theta: torch.Tensor, name: str = "theta") -> torch.Tensor:
        m0 = self.models[0]
        check_tensor(theta, name, ("B", self.num_dofs), device=m0.lower.device, finite=True)
        if theta.dtype != m0.lower.dtype:
            raise TypeError(f"{name} has dtype {theta.dtype} but the scene is {m0.lower.dtype}")
        return theta

    def joint_motion(self, a: SceneOutput, b: SceneOutput) -> torch.Tensor:
        """(B,) mm: how far the models moved from pose ``a`` to pose ``b``, the largest
        over the models of each model's mean displacement: of its joints (bone origins)
        for a hand, the thesis' stopping measure (Ch. 4.3.1.4), and of its vertices
        for an object, whose few bone origins miss its rotation (a ball's lies at its
        centre). Per model, so that a small object's motion is not averaged away by
        the hands'."""
        moved = []
        for m, ma, mb in zip(self.models, a.models, b.models):
            if m.kind == "hand":
                pa, pb = m.joints_from(ma.G), m.joints_from(mb.G)
            else:
                pa, pb = ma.vertices, mb.vertices
            moved.append((pb - pa).norm(dim=-1).mean(-1))
        return torch.stack(moved, -1).amax(-1)

    # ----------------------------------------------------------------- posing
    def forward(self, theta: torch.Tensor, validate: bool = True) -> SceneOutput:
        """Pose every model. theta: (B, D) -> :class:`SceneOutput`."""
        if validate:
            self.check_theta(theta)
        outs = [m(theta[:, s], validate=False) for m, s in zip(self.models, self.slices.values())]
        return SceneOutput(torch.cat([o.vertices for o in outs], 1), torch.cat([o.keypoints for o in outs], 1), outs)

    def jacobian(self, theta: torch.Tensor, outputs: Optional[SceneOutput] = None) -> torch.Tensor:
        """(B, V, 3, D) analytic Jacobian of all vertices (block diagonal over models).

        Large: prefer :meth:`ArticulatedModel.jacobian` with vertex subsets per model.
        """
        B = theta.shape[0]
        J = theta.new_zeros(B, self.num_vertices, 3, self.num_dofs)
        for k, (n, m) in enumerate(zip(self.names, self.models)):
            fk = None if outputs is None else (outputs.models[k].G, outputs.models[k].twists)
            J[:, self.vertex_slices[n], :, self.slices[n]] = m.jacobian(theta[:, self.slices[n]], fk=fk)
        return J

    def vertex_jacobian(self, outputs: SceneOutput, vertex_ids: torch.Tensor) -> torch.Tensor:
        """(B, N, 3, D) Jacobian of some scene vertices, for ``outputs`` at theta.

        vertex_ids: (B, N) int64 scene vertex indices (any models, repeats allowed).
        Each model contributes only its own vertices' rows and its own columns.
        """
        B, N = vertex_ids.shape
        like = outputs.vertices
        J = like.new_zeros(B, N, 3, self.num_dofs)
        for k, (n, m) in enumerate(zip(self.names, self.models)):
            vs, cols = self.vertex_slices[n], self.slices[n]
            mine = (vertex_ids >= vs.start) & (vertex_ids < vs.stop)
            n_k = int(mine.sum(1).max()) if N else 0
            if n_k == 0:
                continue
            # this model's columns first in every row, so its Jacobian is (B, n_k) only
            order = torch.argsort((~mine).to(torch.int8), dim=1, stable=True)[:, :n_k]
            local = (torch.gather(vertex_ids, 1, order) - vs.start).clamp(0, m.num_vertices - 1)
            Jk = m.jacobian(None, local, fk=(outputs.models[k].G, outputs.models[k].twists))
            Jk = Jk * torch.gather(mine, 1, order)[..., None, None].to(like.dtype)
            Jm = like.new_zeros(B, N, 3, cols.stop - cols.start)
            Jm.scatter_(1, order[..., None, None].expand_as(Jk), Jk)
            J[..., cols] = Jm
        return J

    def clamp(self, theta: torch.Tensor) -> torch.Tensor:
        return torch.cat([m.clamp(theta[:, s]) for m, s in zip(self.models, self.slices.values())], 1)

    def limit_violation(self, theta: torch.Tensor) -> torch.Tensor:
        return torch.cat([m.limit_violation(theta[:, s]) for m, s in zip(self.models, self.slices.values())], 1)
