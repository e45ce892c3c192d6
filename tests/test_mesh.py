"""Vertex one-rings and normals."""

from __future__ import annotations

import torch
import trimesh

from torchhand.geometry.mesh import is_closed_outward, vertex_faces, vertex_normals
from torchhand.model.scene import Scene


def test_vertex_normals_match_trimesh_and_subsets_match_all():
    scene = Scene.from_names(["hand_right", "ball"], dtype=torch.float64)
    theta = scene.zero_pose(2)
    theta[1, :3] += torch.tensor([5.0, -3.0, 2.0])
    theta[1, 6:12] += 0.2
    V = scene(theta).vertices
    full = vertex_normals(V, scene.faces)
    ref = trimesh.Trimesh(V[0].numpy(), scene.faces.numpy(), process=False).vertex_normals
    # trimesh weights faces by angle, not area: directions agree closely on this fine mesh
    assert float((full[0] * torch.tensor(ref)).sum(-1).median()) > 0.999
    ids = torch.randperm(scene.num_vertices, generator=torch.Generator().manual_seed(0))[:300]
    torch.testing.assert_close(vertex_normals(V, scene.faces, ids, scene.vertex_faces), full[:, ids])
    per_batch = torch.stack([ids, ids.flip(0)])
    torch.testing.assert_close(vertex_normals(V, scene.faces, per_batch, scene.vertex_faces),
                               torch.stack([full[0, ids], full[1, ids.flip(0)]]))
    # few ids take the normals of their own faces, many those of every face: the same
    assert ids.numel() * scene.vertex_faces.shape[1] < scene.faces.shape[0]
    every = torch.arange(scene.num_vertices).flip(0)
    assert every.numel() * scene.vertex_faces.shape[1] > scene.faces.shape[0]
    many = vertex_normals(V, scene.faces, every, scene.vertex_faces)
    torch.testing.assert_close(many, full[:, every])
    assert torch.equal(vertex_normals(V, scene.faces, ids, scene.vertex_faces), many[:, scene.num_vertices - 1 - ids])


def test_vertex_faces_lists_every_face_of_a_vertex():
    faces = torch.tensor([[0, 1, 2], [0, 2, 3], [3, 2, 4]])
    ring = vertex_faces(faces, 6)
    assert ring.shape == (6, 3)
    as_sets = [set(r[r < 3].tolist()) for r in ring]
    assert as_sets == [{0, 1}, {0}, {0, 1, 2}, {1, 2}, {2}, set()]


def test_closed_outward_meshes_are_recognised():
    box = trimesh.creation.box(extents=(10, 20, 30))
    V, F = torch.tensor(box.vertices), torch.tensor(box.faces)
    assert is_closed_outward(V, F)
    assert not is_closed_outward(V, F.flip(1))  # inward normals
    assert not is_closed_outward(V, F[1:])  # a hole
    flipped = F.clone()
    flipped[0] = flipped[0].flip(0)  # one face wound the other way
    assert not is_closed_outward(V, flipped)
    for name in ("hand_right", "hand_left", "ball", "cube", "pipe", "rope"):
        model = Scene.from_names([name]).models[0]
        assert is_closed_outward(model.vertices_rest, model.faces), name
