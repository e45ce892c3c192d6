"""Hand size: a model resized by a global scale and one length factor per finger.

A finger's bones are the bones that carry its keypoints (``<finger>_mcp`` to
``<finger>_tip``: the three phalanges of the index to the little finger; the thumb's
metacarpal and two phalanges). Every bone ``b`` gets a scale ``s_b``: the global scale
times its finger's factor (the global scale alone for the forearm and the palm). The
skeleton keeps its topology, joint axes and limits; each bone's segment to a child
joint is scaled by the bone's own scale, ``p'_c = p'_b + s_b (p_c - p_b)`` (the root
joint stays where it is), and the surface is carried along by the skinning weights:
``v' = sum_b w_b (p'_b + s_b (v - p_b))``, the same for the keypoints on their bone.
A finger's factor so changes its length and, with it, its thickness (uniformly about
each joint); the palm follows the global scale.
"""

from __future__ import annotations

import dataclasses
from typing import Dict, Mapping

import numpy as np
import torch

from torchhand.io.assets import ModelAssets
from torchhand.model.articulated import ArticulatedModel

__all__ = ["finger_bones", "bone_scales", "pose_resized", "resize_hand", "FINGERS"]

#: the fingers, in the order of their factors
FINGERS = ("thumb", "index", "middle", "ring", "little")


def finger_bones(assets: ModelAssets) -> Dict[str, np.ndarray]:
    """The bones of each finger: those carrying its keypoints (``<finger>_...``)."""
    out = {}
    for f in FINGERS:
        bones = sorted({int(b) for n, b in zip(assets.keypoint_names, assets.keypoint_bones) if n.startswith(f + "_")})
        if not bones:
            raise ValueError(f"model {assets.name!r} has no {f} keypoints: it is not a hand with the 21 keypoints")
        out[f] = np.array(bones, np.int64)
    return out


def bone_scales(model: ArticulatedModel, scale, fingers) -> torch.Tensor:
    """(B, J) per-bone scales from (B,) global scales and (B, 5) finger factors (in the
    order of :data:`FINGERS`)."""
    scale = torch.as_tensor(scale, dtype=model.rest_transforms.dtype, device=model.rest_transforms.device)
    fingers = torch.as_tensor(fingers, dtype=scale.dtype, device=scale.device)
    s = scale.reshape(-1, 1).expand(-1, model.num_bones).clone()
    for k, bones in enumerate(finger_bones(model.assets).values()):
        s[:, torch.as_tensor(bones, device=s.device)] *= fingers.reshape(-1, len(FINGERS))[:, k : k + 1]
    return s


def pose_resized(model: ArticulatedModel, G: torch.Tensor, scales: torch.Tensor) -> tuple:
    """The surface and keypoints of ``model`` resized by per-bone ``scales`` (B, J), posed
    by the bone motions ``G`` (B, J, 4, 4) of the model itself (``model(theta).G``),
    exactly as the resized model (:func:`resize_hand`) poses itself by linear blend
    skinning: resizing changes no bone's rotation, only where its joint is, so one pose
    of the model poses every resized copy. Returns ((B, V, 3) vertices, (B, P, 3)
    keypoints, (B, J, 3) joints); with ``G`` the identity, the resized rest pose."""
    B, J = scales.shape
    p = model.rest_transforms[:, :3, 3]  # (J, 3) rest joints
    W = torch.zeros(model.num_vertices, J, dtype=p.dtype, device=p.device)
    W.scatter_add_(1, model.skin_index, model.skin_weight)
    eye = torch.eye(3, dtype=p.dtype, device=p.device).expand(B, J, 3, 3)
    rest_joints = _joints(model, eye, torch.zeros_like(scales[..., None].expand(B, J, 3)), scales)
    # the resized rest surface: every vertex scaled about its bones' joints, blended
    shift = rest_joints - scales[..., None] * p
    rest = (W @ scales.T).T[..., None] * model.vertices_rest + torch.einsum("vj,bji->bvi", W, shift)
    kb = model.keypoint_bones
    rest_kp = scales[:, kb, None] * model.keypoint_rest + shift[:, kb]
    # posed by the resized skeleton's bone motions [R_b | q_b(theta) - R_b q_b(0)]
    R = G[..., :3, :3]
    joints = _joints(model, R, G[..., :3, 3], scales)
    offset = joints - torch.einsum("bjik,bjk->bji", R, rest_joints)
    verts = torch.einsum("vj,bjik,bvk->bvi", W, R, rest) + torch.einsum("vj,bji->bvi", W, offset)
    keypoints = torch.einsum("bpik,bpk->bpi", R[:, kb], rest_kp) + offset[:, kb]
    return verts, keypoints, joints


def _joints(model: ArticulatedModel, R: torch.Tensor, t: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """(B, J, 3) joints of the resized skeleton posed by rotations R and translations t of
    the model's bone motions: each bone's segment to a child joint is rigid with the bone
    and scaled by its scale; the root joint is where the model's is."""
    p = model.rest_transforms[:, :3, 3]
    out = [torch.einsum("bij,j->bi", R[:, 0], p[0]) + t[:, 0]]
    parents = model.parents.tolist()
    for b in range(1, len(parents)):  # parents come first
        a = parents[b]
        out.append(out[a] + scales[:, a, None] * torch.einsum("bij,j->bi", R[:, a], p[b] - p[a]))
    return torch.stack(out, 1)


def resize_hand(assets: ModelAssets, scale: float = 1.0, fingers: Mapping[str, float] = (),
                name: str | None = None) -> ModelAssets:
    """``assets`` resized: ``scale`` globally and ``fingers[f]`` more for finger ``f``
    (a length factor, 1 = unchanged; fingers left out keep 1). Returns new assets
    (named ``name``, default the model's)."""
    fingers = dict(fingers)
    unknown = set(fingers) - set(FINGERS)
    if unknown:
        raise ValueError(f"unknown fingers {sorted(unknown)}; the fingers are {FINGERS}")
    for k, v in [("scale", scale)] + list(fingers.items()):
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"{k} must be a finite factor > 0, got {v!r}")
    model = ArticulatedModel(assets, dtype=torch.float64)
    s = bone_scales(model, [float(scale)], [[float(fingers.get(f, 1.0)) for f in FINGERS]])
    eye = torch.eye(4, dtype=torch.float64).expand(1, model.num_bones, 4, 4)
    with torch.no_grad():
        verts, keypoints, joints = pose_resized(model, eye, s)
    rest = assets.rest_transforms.copy()
    rest[:, :3, 3] = joints[0].numpy()
    factors = ", ".join(f"{f} {fingers.get(f, 1.0):.3f}" for f in FINGERS)
    return dataclasses.replace(assets, name=name or assets.name, rest_transforms=rest,
                               vertices=verts[0].numpy(), bone_lengths=assets.bone_lengths * s[0].numpy(),
                               keypoint_rest=keypoints[0].numpy(),
                               source=f"{assets.source}, resized: scale {scale:.3f}; {factors}")
