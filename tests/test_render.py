"""Tests for torchhand.geometry.render."""

from __future__ import annotations

import math

import pytest
import torch
import trimesh

from torchhand.geometry.camera import Camera, kinect_camera
from torchhand.geometry.render import RenderResult, render, silhouette_edges, visible_vertices

RADIUS = 50.0
CENTRE_Z = 500.0


@pytest.fixture(scope="module")
def sphere():
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=RADIUS)
    vertices = torch.tensor(mesh.vertices, dtype=torch.float32) + torch.tensor([0.0, 0.0, CENTRE_Z])
    faces = torch.tensor(mesh.faces, dtype=torch.int64)
    return vertices, faces


@pytest.fixture(scope="module")
def sphere_render(sphere):
    vertices, faces = sphere
    return render(vertices, faces, kinect_camera())


def _box(centre, extents):
    mesh = trimesh.creation.box(extents=extents)
    vertices = torch.tensor(mesh.vertices, dtype=torch.float32) + torch.tensor(centre, dtype=torch.float32)
    return vertices, torch.tensor(mesh.faces, dtype=torch.int64)


def _analytic_sphere_depth(camera: Camera) -> torch.Tensor:
    """(H, W) z depth of the exact sphere, 0 where missed (camera at the origin)."""
    rows = torch.arange(camera.height, dtype=torch.float64)
    v, u = torch.meshgrid(rows, torch.arange(camera.width, dtype=torch.float64), indexing="ij")
    d = torch.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, torch.ones_like(u)], -1)
    # |t d - c|^2 = r^2 with c = (0, 0, Z): a t^2 - 2 Z t + Z^2 - r^2 = 0, nearer root.
    a = (d * d).sum(-1)
    disc = CENTRE_Z**2 - a * (CENTRE_Z**2 - RADIUS**2)
    t = (CENTRE_Z - disc.clamp(min=0).sqrt()) / a
    return torch.where(disc > 0, t, torch.zeros_like(t))  # d has unit z, so t is z


def test_sphere_depth(sphere_render):
    r = sphere_render
    assert isinstance(r, RenderResult)
    assert r.depth.shape == (1, 480, 640) and r.depth.dtype == torch.float32
    assert abs(float(r.depth[0, 240, 320]) - (CENTRE_Z - RADIUS)) < 0.5
    exact = _analytic_sphere_depth(kinect_camera())
    both = (r.depth[0] > 0) & (exact > 0)
    err = (r.depth[0].double() - exact)[both].abs()
    # The inscribed polyhedron lies behind the sphere; worst near the grazing limb.
    assert err.max() < 3.0
    v, u = torch.meshgrid(torch.arange(480.0), torch.arange(640.0), indexing="ij")
    inner = both & ((u - 319.5) ** 2 + (v - 239.5) ** 2 < (0.8 * 52.5) ** 2)
    assert (r.depth[0].double() - exact)[inner].abs().max() < 0.5


def test_sphere_silhouette_area_and_edges(sphere_render):
    r = sphere_render
    r_px = 525.0 * RADIUS / CENTRE_Z
    area = int((r.depth > 0).sum())
    assert abs(area / (math.pi * r_px**2) - 1) < 0.03
    # Edge pixels form a one-pixel ring on the silhouette: roughly its perimeter.
    n_edges = int(r.silhouette_edges.sum())
    assert 0.8 * 2 * math.pi * r_px < n_edges < 1.6 * 2 * math.pi * r_px
    assert not r.silhouette_edges[0, 240, 320]
    assert bool((r.depth[r.silhouette_edges] > 0).all())
    ids = r.face_id[0]
    assert int(ids[0, 0]) == -1 and int(ids[240, 320]) >= 0
    assert bool(((r.model_id == -1) == (r.depth == 0)).all()) and bool(((r.bone_id == -1) == (r.depth == 0)).all())


def test_sphere_normals_and_barycentric(sphere, sphere_render):
    vertices, faces = sphere
    r = sphere_render
    n = r.normals[0, 240, 320]
    torch.testing.assert_close(n, torch.tensor([0.0, 0.0, -1.0]), atol=0.05, rtol=0)
    hit = r.depth[0] > 0
    torch.testing.assert_close(r.normals[0][hit].norm(dim=-1), torch.ones(int(hit.sum())), atol=1e-4, rtol=0)
    assert (r.normals[0][~hit] == 0).all()
    # Normals face the camera everywhere.
    K = kinect_camera().K
    v, u = torch.meshgrid(torch.arange(480.0), torch.arange(640.0), indexing="ij")
    rays = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)
    assert ((r.normals[0] * rays).sum(-1)[hit] < 0).all()
    # Barycentric coordinates reconstruct the hit point.
    rows, cols = hit.nonzero(as_tuple=True)
    tri = vertices[faces[r.face_id[0, rows, cols]]]  # (P, 3, 3)
    bu, bv = r.barycentric[0, rows, cols].unbind(-1)
    point = (1 - bu - bv)[:, None] * tri[:, 0] + bu[:, None] * tri[:, 1] + bv[:, None] * tri[:, 2]
    torch.testing.assert_close(point[:, 2], r.depth[0, rows, cols], atol=1e-2, rtol=0)
    torch.testing.assert_close(point[:, :2], r.depth[0, rows, cols, None] * rays[rows, cols, :2], atol=1e-2, rtol=0)


def test_visible_vertices_front_half(sphere, sphere_render):
    vertices, faces = sphere
    vis = visible_vertices(sphere_render, faces, vertices.shape[0])
    assert vis.shape == (1, vertices.shape[0]) and vis.dtype == torch.bool
    z = vertices[:, 2]
    # The visible cap ends at z = Z - r^2 / Z (tangent cone), slightly before the equator.
    assert vis[0, z < CENTRE_Z - RADIUS**2 / CENTRE_Z - 10].all()
    assert not vis[0, z > CENTRE_Z].any()


def test_two_boxes_ids_and_occlusion():
    near_v, near_f = _box([-40.0, 0.0, 400.0], [100.0, 100.0, 20.0])
    far_v, far_f = _box([40.0, 0.0, 600.0], [150.0, 150.0, 20.0])
    vertices = torch.cat([near_v, far_v])
    faces = torch.cat([near_f, far_f + near_v.shape[0]])
    model = torch.cat([torch.full((near_f.shape[0],), 3), torch.full((far_f.shape[0],), 7)])
    bone = torch.arange(faces.shape[0])
    cam = kinect_camera()
    r = render(vertices, faces, cam, face_model_id=model, face_bone_id=bone)
    probes = [[-60.0, 0.0, 390.0], [0.0, 0.0, 390.0], [70.0, 0.0, 590.0], [0.0, 200.0, 500.0]]
    pixels = cam.project(torch.tensor([probes]))
    cols, rows = pixels[0].round().long().unbind(-1)
    ids, depth = r.model_id[0, rows, cols], r.depth[0, rows, cols]
    assert ids.tolist() == [3, 3, 7, -1]  # second point: boxes overlap there, the near one wins
    torch.testing.assert_close(depth[:3], torch.tensor([390.0, 390.0, 590.0]), atol=1e-3, rtol=0)
    assert (r.bone_id == torch.where(r.face_id >= 0, r.face_id, -1)).all()
    assert (r.face_id[0, rows[:2], cols[:2]] < near_f.shape[0]).all()
    assert r.face_id[0, rows[2], cols[2]] >= near_f.shape[0]
    # The near box's border over the far box is an occluding edge; the far box is not marked there.
    row = int(rows[0])
    edge_cols = r.silhouette_edges[0, row].nonzero()[:, 0]
    near_right = int(cam.project(torch.tensor([[[10.0, 0.0, 390.0]]]))[0, 0, 0].floor())
    assert near_right in edge_cols.tolist() and near_right + 1 not in edge_cols.tolist()


def test_batch_with_different_poses(sphere):
    vertices, faces = sphere
    batch = torch.stack([vertices, vertices + torch.tensor([30.0, 0.0, 100.0])])
    r = render(batch, faces, kinect_camera())
    assert r.depth.shape == (2, 480, 640)
    assert not torch.equal(r.depth[0], r.depth[1])
    # The sphere's minimum z moves by exactly the z offset.
    nearest = [float(d[d > 0].min()) for d in r.depth]
    assert abs(nearest[1] - nearest[0] - 100.0) < 0.5
    assert r.depth[1].nonzero()[:, 1].float().mean() > r.depth[0].nonzero()[:, 1].float().mean() + 10  # moved right
    single = render(batch[1], faces, kinect_camera())
    torch.testing.assert_close(single.depth[0], r.depth[1])


def test_cropped_render_equals_the_whole_image(sphere, monkeypatch):
    """Outputs are computed on the union of the projected boxes; casting every pixel of
    the image gives the same maps, also for a batch whose boxes differ and touch the
    image border."""
    import torchhand.geometry.render as tr
    vertices, faces = sphere
    batch = torch.stack([vertices + torch.tensor([-60.0, 10.0, 0.0]), vertices + torch.tensor([290.0, 0.0, 0.0])])
    cam = kinect_camera()
    cropped = render(batch, faces, cam)
    monkeypatch.setattr(tr, "_regions_of_interest", lambda v, c: [(0, c.height, 0, c.width)] * v.shape[0])
    whole = render(batch, faces, cam)
    assert int(cropped.silhouette_edges.sum()) > 100
    assert int(cropped.depth[1, :, -1].gt(0).sum()) > 0  # the second sphere leaves the image
    for name, a, b in zip(RenderResult._fields, cropped, whole):
        assert torch.equal(a, b), name
    without = render(batch, faces, cam, normals=False)
    assert without.normals is None
    for name, a, b in zip(RenderResult._fields, cropped, without):
        assert name == "normals" or torch.equal(a, b), name


def test_extrinsics_move_the_scene(sphere):
    vertices, faces = sphere
    T = torch.eye(4)
    T[:3, 3] = torch.tensor([0.0, 0.0, 100.0])  # world origin 100 mm further from the camera
    r = render(vertices, faces, kinect_camera(T))
    assert abs(float(r.depth[0, 240, 320]) - (CENTRE_Z + 100 - RADIUS)) < 0.5
    torch.testing.assert_close(r.normals[0, 240, 320], torch.tensor([0.0, 0.0, -1.0]), atol=0.05, rtol=0)


def test_empty_scene_and_nothing_in_view(sphere):
    vertices, faces = sphere
    cam = kinect_camera()
    for r in (
        render(vertices, faces[:0], cam),
        render(vertices - torch.tensor([0.0, 0.0, 2 * CENTRE_Z]), faces, cam),  # behind the camera
    ):
        assert (r.depth == 0).all() and r.depth.dtype == torch.float32
        for ids in (r.face_id, r.model_id, r.bone_id):
            assert ids.dtype == torch.int64 and (ids == -1).all()
        assert (r.normals == 0).all() and not r.silhouette_edges.any() and (r.barycentric == 0).all()
        assert not visible_vertices(r, faces, vertices.shape[0]).any()


def test_silhouette_edges_threshold():
    depth = torch.zeros(1, 6, 8)
    depth[0, 1:5, 1:4] = 500.0
    depth[0, 1:5, 4:7] = 505.0  # 5 mm step: not an edge at 10 mm, an edge at 2 mm
    edges = silhouette_edges(depth)
    assert not edges[0, 2, 3] and edges[0, 1, 1] and not edges[0, 0, 0]
    assert silhouette_edges(depth, threshold=2.0)[0, 2, 3] and not silhouette_edges(depth, threshold=2.0)[0, 2, 4]


def test_render_bad_inputs(sphere):
    vertices, faces = sphere
    cam = kinect_camera()
    bad = vertices.clone()
    bad[3, 1] = float("nan")
    with pytest.raises(ValueError, match="vertices must be finite"):
        render(bad, faces, cam)
    with pytest.raises(ValueError, match=r"vertices must have shape \(B, V, 3\) or \(V, 3\)"):
        render(vertices[:, :2], faces, cam)
    with pytest.raises(ValueError, match=r"faces must have shape \(F, 3\)"):
        render(vertices, faces.flatten(), cam)
    with pytest.raises(TypeError, match="faces must have an integer dtype"):
        render(vertices, faces.float(), cam)
    with pytest.raises(ValueError, match="faces must index vertices"):
        render(vertices, faces + vertices.shape[0], cam)
    with pytest.raises(ValueError, match=r"face_model_id must have shape \(F,\)"):
        render(vertices, faces, cam, face_model_id=torch.zeros(3, dtype=torch.int64))
    with pytest.raises(TypeError, match="camera must be"):
        render(vertices, faces, cam.K)


def test_render_float64_vertices(sphere):
    vertices, faces = sphere
    r = render(vertices.double(), faces, kinect_camera())
    assert r.depth.dtype == torch.float32 and r.normals.dtype == torch.float32
    assert abs(float(r.depth[0, 240, 320]) - (CENTRE_Z - RADIUS)) < 0.5


def test_render_cuda(sphere):
    if not torch.cuda.is_available():
        pytest.skip("CUDA not available")
    vertices, faces = sphere
    cpu = render(vertices, faces, kinect_camera())
    r = render(vertices.cuda(), faces.cuda(), kinect_camera().to("cuda"))
    assert all(t.is_cuda for t in r)
    torch.testing.assert_close(r.depth.cpu(), cpu.depth)
    torch.testing.assert_close(r.normals.cpu(), cpu.normals, atol=1e-5, rtol=0)
    assert visible_vertices(r, faces.cuda(), vertices.shape[0]).is_cuda


def test_back_face_culling_keeps_the_first_hits():
    """Leaving out faces turned away from the camera changes nothing for closed meshes
    seen from outside, even where the models interpenetrate (both hands and the ball)."""
    from torchhand.model.scene import Scene

    scene = Scene.from_names(["hand_right", "hand_left", "ball"])
    theta = scene.zero_pose(2)
    for k, name in enumerate(scene.names):
        sl = scene.slices[name]
        c = scene.models[k].vertices_rest.mean(0)
        theta[:, sl.start : sl.start + 3] = torch.tensor([30.0 * k - 30.0, 10.0 * k, 480.0]) - c
    theta[1, 6:] += 0.2  # another pose, fingers bent
    T = torch.eye(4)
    T[:3, 3] = torch.tensor([5.0, -8.0, 20.0])
    cam = kinect_camera(T)
    with torch.no_grad():
        V = scene(theta).vertices
    args = (V, scene.faces, cam, scene.face_model_id, scene.face_bone_id)
    full, culled = render(*args), render(*args, cull_back_faces=True)
    hit = full.depth > 0
    assert int(hit.sum()) > 20000
    assert torch.equal(hit, culled.depth > 0)
    torch.testing.assert_close(culled.depth, full.depth, atol=1e-3, rtol=0)
    same = (culled.face_id == full.face_id)[hit].float().mean()
    assert same > 0.999  # a ray through a shared edge may report either face
    assert torch.equal(culled.model_id, full.model_id) and torch.equal(culled.silhouette_edges, full.silhouette_edges)
