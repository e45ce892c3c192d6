"""Articulated test objects with joints at known places: rounded tubes of rigid links
(:func:`chain_object`) and smooth motions of them in front of a camera
(:func:`chain_motion`), the ground truth against which a learned rig is checked
(``eval/exp_rig.py``, docs/rigging.md)."""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from torchhand.geometry.camera import kinect_camera
from torchhand.io.assets import ModelAssets
from torchhand.model.articulated import ArticulatedModel
from torchhand.model.scene import Scene

__all__ = ["chain_object", "chain_motion", "chain_joints"]

_AXES = {"x": 0, "y": 1, "z": 2}


def _tube(length: float, radius: float, edge: float) -> tuple:
    """A closed capsule along x centred at 0, remeshed to edges of about ``edge`` mm."""
    import trimesh

    cap = trimesh.creation.capsule(height=length - 2 * radius, radius=radius, count=[24, 24])
    R = trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0])  # the capsule runs along z
    cap.apply_transform(R)
    v, f = trimesh.remesh.subdivide_to_size(cap.vertices, cap.faces, max_edge=edge)
    mesh = trimesh.Trimesh(v, f, process=True)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces, np.int64)


def chain_object(lengths: Sequence[float] = (120.0, 120.0), axes: Sequence[str] = ("z",), radius: float = 15.0,
                 blend: float = 4.0, edge: float = 8.0, name: str = "chain") -> ModelAssets:
    """A tube of ``len(lengths)`` rigid links along x, joint k between links k and k+1
    turning about the bone-frame axis ``axes[k]`` (``"x"``, ``"y"``, ``"z"``), limits
    +-120 degrees; skinning weights blend linearly over +-``blend`` mm at each joint."""
    if len(axes) != len(lengths) - 1:
        raise ValueError(f"one axis per joint: {len(lengths)} links need {len(lengths) - 1} axes, got {list(axes)}")
    bad = [a for a in axes if a not in _AXES]
    if bad:
        raise ValueError(f"axes must be 'x', 'y' or 'z', got {bad}")
    L = float(sum(lengths))
    v, f = _tube(L, radius, edge)
    J = len(lengths)
    starts = -L / 2 + np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
    rest = np.tile(np.eye(4), (J, 1, 1))
    rest[:, 0, 3] = starts
    W = np.zeros((len(v), J))
    for j in range(J):  # a hat of link j, linear ramps of 2 blend at its ends
        lo = starts[j] if j > 0 else -np.inf
        hi = starts[j] + lengths[j] if j < J - 1 else np.inf
        up = np.clip((v[:, 0] - lo) / (2 * blend) + 0.5, 0, 1) if j > 0 else 1.0
        down = np.clip((hi - v[:, 0]) / (2 * blend) + 0.5, 0, 1) if j < J - 1 else 1.0
        W[:, j] = np.minimum(up, down)
    W /= W.sum(1, keepdims=True)
    K = 2
    idx = np.argsort(-W, 1, kind="stable")[:, :K]
    w = np.take_along_axis(W, idx, 1)
    w /= w.sum(1, keepdims=True)
    idx = np.where(w > 0, idx, 0)
    slot_axes = np.zeros((J, 3, 3))
    slot_used = np.zeros((J, 3), bool)
    slot_limits = np.zeros((J, 3, 2))
    for k, a in enumerate(axes):
        slot_axes[k + 1, 0, _AXES[a]] = 1.0
        slot_used[k + 1, 0] = True
        slot_limits[k + 1, 0] = np.deg2rad([-120.0, 120.0])
    return ModelAssets(name=name, kind="object", side=None, bone_names=[f"link{j}" for j in range(J)],
                       parents=np.arange(-1, J - 1, dtype=np.int64), rest_transforms=rest,
                       bone_lengths=np.asarray(lengths, np.float64), vertices=v, faces=f,
                       skin_index=idx.astype(np.int64),
                       skin_weight=w, slot_axes=slot_axes, slot_used=slot_used, slot_limits=slot_limits,
                       source=f"torchhand.data.chains.chain_object(lengths={list(lengths)}, axes={list(axes)})",
                       symmetry=None)


def chain_joints(assets: ModelAssets) -> np.ndarray:
    """(J-1, 3) the joint positions in the rigging pose (the origins of bones 1..)."""
    return assets.rest_transforms[1:, :3, 3].copy()


def chain_motion(assets: ModelAssets, frames: int = 200, seed: int = 0, amplitude_deg: float = 60.0,
                 distance: float = 650.0):
    """A :class:`~torchhand.data.synth.SyntheticFrames` of the object bending in front of
    a Kinect-like camera: joint k swings through ``amplitude_deg`` on k half periods of a
    sine over the sequence, the whole object turns by up to 10 degrees and drifts by 15 mm (at most about
    0.5 mm a frame: a hand bending an object, not throwing it)."""
    from torchhand.data.synth import SyntheticFrames

    model = ArticulatedModel(assets, dtype=torch.float64)
    g = np.random.default_rng(seed)
    t = np.arange(frames) / max(frames - 1, 1)
    th = np.zeros((frames, model.num_dofs))
    phase = g.uniform(0, 2 * np.pi, size=(model.num_dofs,))
    th[:, 0] = 15 * np.sin(2 * np.pi * 0.5 * t + phase[0])
    th[:, 1] = 10 * np.sin(2 * np.pi * 0.7 * t + phase[1])
    th[:, 2] = distance + 15 * np.sin(2 * np.pi * 0.3 * t + phase[2])
    base = np.array([np.deg2rad(-20.0), 0.0, 0.0])  # tilted towards the camera
    th[:, 3:6] = base + np.deg2rad(10) * np.stack([np.sin(2 * np.pi * f * t + p) for f, p in
                                                   zip((0.4, 0.6, 0.5), phase[3:6])], 1) * [0.5, 0.5, 1.0]
    for d in range(6, model.num_dofs):  # starts straight, bends, straightens (the later joints back and forth)
        th[:, d] = np.deg2rad(amplitude_deg) * np.sin(np.pi * (1 + (d - 6)) * t)
    scene = Scene([model.float()], names=[assets.name])
    return SyntheticFrames(scene, torch.as_tensor(th, dtype=torch.float32), [kinect_camera()], f"{assets.name}_motion",
                           {"format": "torchhand chain motion", "seed": seed, "model": assets.source})
