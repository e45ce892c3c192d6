"""Coarse proxies of a model: the same skeleton, limits and keypoints on a decimated mesh.

A global search renders its particles at a few dozen pixels, where a 20 000-face hand
and a 2 000-face one give the same depth maps to within a pixel's size, for a tenth
of the rendering work. The proxy's mesh is open3d's quadric decimation of the model's
rest mesh; each of its vertices takes the skinning weights of the nearest vertex of
the full mesh, so the proxy follows the same pose exactly as the model does::

    coarse = coarse_model(load_model("hand_right"), faces=2000)
    coarse(theta).keypoints == model(theta).keypoints     # same skeleton
"""

from __future__ import annotations

import dataclasses

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from torchhand.model.articulated import ArticulatedModel

__all__ = ["coarse_model"]


def coarse_model(model: ArticulatedModel, faces: int = 2000) -> ArticulatedModel:
    """``model`` with its mesh decimated to about ``faces`` triangles (the model itself
    when it has no more than that). Vertex groups are dropped (their ids refer to the
    full mesh); everything else is the model's."""
    if faces < 4:
        raise ValueError(f"faces must be >= 4, got {faces}")
    assets = model.assets
    if len(assets.faces) <= faces:
        return model
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(assets.vertices, np.float64)),
                                     o3d.utility.Vector3iVector(np.asarray(assets.faces, np.int32)))
    small = mesh.simplify_quadric_decimation(target_number_of_triangles=int(faces))
    small.remove_degenerate_triangles()
    small.remove_unreferenced_vertices()
    verts = np.asarray(small.vertices, np.float64)
    tris = np.asarray(small.triangles, np.int64)
    _, near = cKDTree(assets.vertices).query(verts)
    coarse = dataclasses.replace(assets, vertices=verts, faces=tris, skin_index=assets.skin_index[near],
                                 skin_weight=assets.skin_weight[near], groups={},
                                 source=f"{assets.source} (decimated to {len(tris)} faces)")
    return ArticulatedModel(coarse, dtype=model.rest_transforms.dtype).to(model.rest_transforms.device)
