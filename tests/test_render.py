"""Tests for torchhand.geometry.render."""

from __future__ import annotations

import math

import pytest
import torch
import trimesh

from torchhand.geometry.camera import Camera, kinect_camera
from torchhand.geometry.raycast import BACKENDS
from torchhand.geometry.render import RenderResult, Renderer, render, silhouette_edges, visible_vertices, window

RADIUS = 50.0
CENTRE_Z = 500.0

try:
    import warp  # noqa: F401

    HAVE_WARP = True
except ImportError:  # pragma: no cover - a dependency
    HAVE_WARP = False

AVAILABLE = [b for b in BACKENDS if HAVE_WARP or not b.startswith("warp")]


@pytest.fixture(params=AVAILABLE)
def backend(request):
    return request.param


@pytest.fixture(scope="module")
def sphere():
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=RADIUS)
    vertices = torch.tensor(mesh.vertices, dtype=torch.float32) + torch.tensor([0.0, 0.0, CENTRE_Z])
    faces = torch.tensor(mesh.faces, dtype=torch.int64)
    return vertices, faces


@pytest.fixture()
def sphere_render(sphere, backend):
    vertices, faces = sphere
    return render(vertices, faces, kinect_camera(), backend=backend)


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


def test_two_boxes_ids_and_occlusion(backend):
    near_v, near_f = _box([-40.0, 0.0, 400.0], [100.0, 100.0, 20.0])
    far_v, far_f = _box([40.0, 0.0, 600.0], [150.0, 150.0, 20.0])
    vertices = torch.cat([near_v, far_v])
    faces = torch.cat([near_f, far_f + near_v.shape[0]])
    model = torch.cat([torch.full((near_f.shape[0],), 3), torch.full((far_f.shape[0],), 7)])
    bone = torch.arange(faces.shape[0])
    cam = kinect_camera()
    r = render(vertices, faces, cam, face_model_id=model, face_bone_id=bone, backend=backend)
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


def test_batch_with_different_poses(sphere, backend):
    vertices, faces = sphere
    batch = torch.stack([vertices, vertices + torch.tensor([30.0, 0.0, 100.0])])
    r = render(batch, faces, kinect_camera(), backend=backend)
    assert r.depth.shape == (2, 480, 640)
    assert not torch.equal(r.depth[0], r.depth[1])
    # The sphere's minimum z moves by exactly the z offset.
    nearest = [float(d[d > 0].min()) for d in r.depth]
    assert abs(nearest[1] - nearest[0] - 100.0) < 0.5
    assert r.depth[1].nonzero()[:, 1].float().mean() > r.depth[0].nonzero()[:, 1].float().mean() + 10  # moved right
    single = render(batch[1], faces, kinect_camera(), backend=backend)
    torch.testing.assert_close(single.depth[0], r.depth[1])


def test_normals_off_changes_nothing_else(sphere, backend):
    vertices, faces = sphere
    batch = torch.stack([vertices + torch.tensor([-60.0, 10.0, 0.0]), vertices + torch.tensor([290.0, 0.0, 0.0])])
    cam = kinect_camera()
    full = render(batch, faces, cam, backend=backend)
    without = render(batch, faces, cam, normals=False, backend=backend)
    assert int(full.depth[1, :, -1].gt(0).sum()) > 0  # the second sphere leaves the image
    assert without.normals is None
    for name, a, b in zip(RenderResult._fields, full, without):
        assert name in ("normals", "origin") or torch.equal(a, b), name
    assert full.origin is None and without.origin is None


def test_a_cropped_render_is_the_box_of_the_whole_one(sphere, backend):
    vertices, faces = sphere
    batch = torch.stack([vertices + torch.tensor([-60.0, 10.0, 0.0]), vertices + torch.tensor([290.0, 0.0, 0.0])])
    cam = kinect_camera()
    renderer = Renderer(faces, backend=backend)
    whole = renderer(batch, cam)
    rows, cols = torch.nonzero(whole.depth.amax((0, 2)))[:, 0], torch.nonzero(whole.depth.amax((0, 1)))[:, 0]
    r0, r1, c0, c1 = int(rows.min()) - 5, int(rows.max()) + 6, int(cols.min()) - 7, 640
    box = (r0, r1, c0, c1)  # the meshes' box with an empty border (the right sphere leaves the image)
    full = renderer(batch, cam, box=box)
    crop = renderer(batch, cam, box=box, crop=True)
    assert crop.origin == (r0, c0) and crop.depth.shape == (2, r1 - r0, c1 - c0)
    assert int(crop.silhouette_edges.sum()) > 100
    for name in RenderResult._fields[:7]:
        a, b = getattr(full, name), getattr(crop, name)
        assert torch.equal(a, getattr(whole, name)), name
        assert torch.equal(a[:, r0:r1, c0:c1], b), name
    back = window(crop, (0, 480, 0, 640))  # the whole images again
    assert back.origin == (0, 0) and window(full, (0, 480, 0, 640)) is full
    for name in RenderResult._fields[:7]:
        assert torch.equal(getattr(back, name), getattr(full, name)), name
    # a window that reaches past the crop (and the image) is empty there
    part = window(crop, (r1 - 30, r1 + 20, 600, 700))
    assert part.origin == (r1 - 30, 600) and part.depth.shape == (2, 50, 100)
    assert torch.equal(part.depth[:, :30, :40], full.depth[:, r1 - 30 : r1, 600:])
    assert bool((part.face_id[:, 30:] == -1).all()) and bool((part.depth[:, :, 40:] == 0).all())
    assert torch.equal(visible_vertices(crop, faces, len(vertices)), visible_vertices(full, faces, len(vertices), box))
    # a box beyond the image is clamped to it; several cameras keep their own axis
    edge = renderer(batch, [cam, cam], box=(-10, 500, 600, 700), crop=True)
    assert edge.origin == (0, 600) and edge.depth.shape == (2, 2, 480, 40)
    assert torch.equal(edge.depth[:, 1], whole.depth[:, :, 600:])
    # meshes that miss the image: one empty pixel
    aside = renderer(batch + torch.tensor([5000.0, 0.0, 0.0]), cam, crop=True)
    assert aside.depth.shape == (2, 1, 1) and bool((aside.face_id == -1).all()) and aside.origin == (0, 0)
    with pytest.raises(ValueError, match="crop needs the pixel box"):
        renderer.caster(batch, renderer._views([cam], False, 2, batch.device), crop=True)


def test_extrinsics_move_the_scene(sphere, backend):
    vertices, faces = sphere
    T = torch.eye(4)
    T[:3, 3] = torch.tensor([0.0, 0.0, 100.0])  # world origin 100 mm further from the camera
    r = render(vertices, faces, kinect_camera(T), backend=backend)
    assert abs(float(r.depth[0, 240, 320]) - (CENTRE_Z + 100 - RADIUS)) < 0.5
    torch.testing.assert_close(r.normals[0, 240, 320], torch.tensor([0.0, 0.0, -1.0]), atol=0.05, rtol=0)


def test_empty_scene_and_nothing_in_view(sphere, backend):
    vertices, faces = sphere
    cam = kinect_camera()
    for r in (
        render(vertices, faces[:0], cam, backend=backend),
        render(vertices - torch.tensor([0.0, 0.0, 2 * CENTRE_Z]), faces, cam, backend=backend),  # behind the camera
        render(vertices, faces, kinect_camera(torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0]))), backend=backend),
    ):
        assert (r.depth == 0).all() and r.depth.dtype == torch.float32
        for ids in (r.face_id, r.model_id, r.bone_id):
            assert ids.dtype == torch.int64 and (ids == -1).all()
        assert (r.normals == 0).all() and not r.silhouette_edges.any() and (r.barycentric == 0).all()
        assert not visible_vertices(r, faces, vertices.shape[0]).any()


@pytest.mark.skipif(not HAVE_WARP, reason="warp-lang not installed")
@pytest.mark.parametrize("cropped", [False, True])
def test_warp_derived_maps_equal_torch(cropped):
    """The Warp backends' ids and contours (one kernel) are torch's, pixel for pixel,
    with depth jumps at the threshold exactly and the box's own border."""
    from torchhand.geometry.raycast import Hits
    from torchhand.geometry.render import derive

    gen = torch.Generator().manual_seed(3)
    N, H, W, F = 3, 40, 50, 30
    face = torch.randint(-1, F, (N, H, W), generator=gen)
    depth = torch.where(face >= 0, 500 + 40 * torch.rand(N, H, W, generator=gen), torch.zeros(N, H, W))
    face[0, 3:9, 3:27], depth[0, 3:9, 3:27] = 1, 500.0  # a flat patch holding two jumps:
    depth[0, 5, 7] = 510.0  # one of the threshold, beside (5, 6): no edge
    depth[0, 5, 24] = 510.5  # one just above it, beside (5, 23): an edge
    model_ids, bone_ids = torch.randint(0, 3, (F,), generator=gen), torch.randint(0, 20, (F,), generator=gen)
    box = (0, H, 0, W) if cropped else (3, 35, 4, 44)
    args = (Hits(face, depth, torch.zeros(N, H, W, 2)), None, torch.zeros(F, 3, dtype=torch.int64), model_ids,
            bone_ids, 1, [], 10.0, False, box, cropped)
    ref, got = derive(*args, warp=False), derive(*args, warp=True)
    assert not ref.silhouette_edges[0, 5, 6] and ref.silhouette_edges[0, 5, 23]
    for name in ("model_id", "bone_id", "silhouette_edges"):
        assert torch.equal(getattr(got, name), getattr(ref, name)), name
    assert int(got.silhouette_edges.sum()) > 100


@pytest.mark.skipif(not HAVE_WARP, reason="warp-lang not installed")
@pytest.mark.parametrize("crop", [False, True])
def test_warp_pixel_kernels_split_rows_alike(sphere, crop):
    """The pixel kernels' threads per box row (one on a CPU, one per pixel on a GPU) do
    not change a render: both splits, and one between, run here on the CPU."""
    from torchhand.geometry.raycast import RayCaster

    vertices, faces = sphere
    cam = kinect_camera()
    batch = torch.stack([vertices, vertices + torch.tensor([30.0, -20.0, 40.0])])
    box = (150, 330, 230, 420)
    results = []
    for split in (None, 7, 10 ** 6):
        renderer = Renderer(faces, face_bone_id=torch.arange(faces.shape[0]) % 5,
                            caster=RayCaster(faces, "warp", row_split=split))
        results.append(renderer(batch, cam, normals=True, box=box, crop=crop))
    assert int((results[0].face_id >= 0).sum()) > 10000 and int(results[0].silhouette_edges.sum()) > 500
    for other in results[1:]:
        for a, b in zip(results[0][:7], other[:7]):
            assert torch.equal(a, b)


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


def test_render_float64_vertices(sphere, backend):
    vertices, faces = sphere
    r = render(vertices.double(), faces, kinect_camera(), backend=backend)
    assert r.depth.dtype == torch.float32 and r.normals.dtype == torch.float32
    assert abs(float(r.depth[0, 240, 320]) - (CENTRE_Z - RADIUS)) < 0.5


@pytest.fixture(scope="module")
def hands_and_ball():
    """Two hands and the ball, two poses (the second with bent fingers, touching), and a
    camera off the world origin."""
    from torchhand.model.scene import Scene

    scene = Scene.from_names(["hand_right", "hand_left", "ball"])
    theta = scene.zero_pose(2)
    for k, name in enumerate(scene.names):
        sl = scene.slices[name]
        c = scene.models[k].vertices_rest.mean(0)
        theta[:, sl.start : sl.start + 3] = torch.tensor([30.0 * k - 30.0, 10.0 * k, 480.0]) - c
    theta[1, 6:] += 0.2
    T = torch.eye(4)
    T[:3, 3] = torch.tensor([5.0, -8.0, 20.0])
    with torch.no_grad():
        V = scene(theta).vertices
    return scene, V, kinect_camera(T)


def _ties_only(a, b, faces, vertices):
    """Where two renders name different faces, the faces share a vertex (the pixel centre
    lies on their common edge or corner, up to float32 rounding)."""
    diff = (a.face_id != b.face_id) & (a.face_id >= 0) & (b.face_id >= 0)
    fa, fb = a.face_id[diff], b.face_id[diff]
    shared = (faces[fa][:, :, None] == faces[fb][:, None, :]).any(-1).any(-1)
    return int(diff.sum()), bool(shared.all()) if len(fa) else True


@pytest.mark.skipif(not HAVE_WARP, reason="NVIDIA Warp is not installed")
@pytest.mark.parametrize("backend", [b for b in BACKENDS if b != "open3d"])
def test_backends_agree_with_open3d(hands_and_ball, backend):
    """Depth to 1e-3 mm, ids and face ids equal except on exact ties, on two hands and the
    ball in two poses (42k triangles)."""
    scene, V, cam = hands_and_ball
    args = (V, scene.faces, cam, scene.face_model_id, scene.face_bone_id)
    ref, r = render(*args, backend="open3d"), render(*args, backend=backend)
    hit = ref.face_id >= 0
    assert int(hit.sum()) > 20000 and torch.equal(hit, r.face_id >= 0)
    assert (r.depth - ref.depth).abs().max() < 1e-3
    n, ties = _ties_only(r, ref, scene.faces, V)
    assert n < 20 and ties, n
    same = r.face_id == ref.face_id
    assert torch.equal(r.model_id[same], ref.model_id[same]) and torch.equal(r.bone_id[same], ref.bone_id[same])
    # the same hit points to 1e-3 mm (barycentrics of slivers are sensitive to the ray's rounding)
    b_, rr, cc = torch.nonzero(same & hit, as_tuple=True)
    tri = V[b_[:, None], scene.faces[r.face_id[b_, rr, cc]]]

    def point(bary):
        u, v = bary[b_, rr, cc].double().unbind(-1)
        return (1 - u - v)[:, None] * tri[:, 0] + u[:, None] * tri[:, 1] + v[:, None] * tri[:, 2]

    assert (point(r.barycentric) - point(ref.barycentric)).norm(dim=-1).max() < 1e-3
    torch.testing.assert_close(r.normals[same], ref.normals[same], atol=1e-5, rtol=0)
    assert torch.equal(r.silhouette_edges, ref.silhouette_edges)


@pytest.mark.parametrize("per_problem", [False, True])
def test_views_of_a_rig_and_per_problem_cameras(hands_and_ball, backend, per_problem):
    """B problems x C cameras in one call equal the single-camera renders."""
    scene, V, cam = hands_and_ball
    T = torch.eye(4)
    T[:3, 3] = torch.tensor([-40.0, 0.0, 60.0])
    other = kinect_camera(T)
    renderer = Renderer(scene.faces, scene.face_model_id, scene.face_bone_id, backend=backend)
    if per_problem:  # problem 0 sees cam, problem 1 sees other
        r = renderer(V, [cam, other], per_problem=True)
        assert r.depth.shape == (2, 1, 480, 640)
        pairs = [(0, 0, cam), (1, 0, other)]
    else:
        r = renderer(V, [cam, other])
        assert r.depth.shape == (2, 2, 480, 640)
        pairs = [(b, c, x) for b in range(2) for c, x in enumerate([cam, other])]
    for b, c, camera in pairs:
        one = renderer(V[b : b + 1], camera)
        for name, x, y in zip(RenderResult._fields[:7], r, one):
            torch.testing.assert_close(x[b, c], y[0], msg=name)


def test_render_bad_geometry_is_refused(sphere, backend):
    vertices, faces = sphere
    cam = kinect_camera()
    bad = faces.clone()
    bad[7] = torch.tensor([5, 5, 9])
    with pytest.raises(ValueError, match=r"degenerate triangles .* rows \[7\]"):
        render(vertices, bad, cam, backend=backend)
    with pytest.raises(ValueError, match="no problems"):
        render(vertices[None, :0].expand(0, -1, -1), faces, cam, backend=backend)
    nan = vertices[None].repeat(2, 1, 1)
    nan[1, 11, 0] = float("inf")
    with pytest.raises(ValueError, match=r"finite.*\[\[1, 11\]\]"):
        render(nan, faces, cam, backend=backend)
    with pytest.raises(ValueError, match="backend must be one of"):
        render(vertices, faces, cam, backend="embree")
    with pytest.raises(ValueError, match="share one image size"):
        render(vertices, faces, [cam, Camera.from_intrinsics(500, 500, 160, 120, 320, 240)], backend=backend)


def test_missing_warp_names_the_package(sphere, monkeypatch):
    """Without Warp the warp backends say what to install, and open3d still renders."""
    import builtins
    import sys

    from torchhand.geometry import raycast, warp_kernels

    real_import = builtins.__import__

    def no_warp(name, *args, **kwargs):
        if name == "warp" or name.startswith("warp."):
            raise ImportError("No module named 'warp'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_warp)
    monkeypatch.delitem(sys.modules, "warp", raising=False)
    warp_kernels._warp.cache_clear()
    try:
        vertices, faces = sphere
        assert raycast.default_backend() == "open3d"
        with pytest.raises(ImportError, match=r"pip install warp-lang"):
            render(vertices, faces, kinect_camera(), backend="warp")
        r = render(vertices, faces, kinect_camera())  # the default falls back to open3d
        assert int((r.depth > 0).sum()) > 1000
    finally:
        warp_kernels._warp.cache_clear()


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA not available")
@pytest.mark.parametrize("backend", [b for b in AVAILABLE if b != "open3d"])
def test_render_cuda_agrees_with_the_cpu(hands_and_ball, backend):
    scene, V, cam = hands_and_ball
    args = (scene.faces, cam, scene.face_model_id, scene.face_bone_id)
    cpu = render(V, *args, backend=backend)
    r = render(V.cuda(), scene.faces.cuda(), cam.to("cuda"), scene.face_model_id.cuda(), scene.face_bone_id.cuda(),
               backend=backend)
    assert all(x.is_cuda for x in r[:7] if x is not None)
    assert (r.depth.cpu() - cpu.depth).abs().max() < 1e-3
    n, ties = _ties_only(r._replace(face_id=r.face_id.cpu()), cpu, scene.faces, V)
    assert n < 20 and ties
    assert visible_vertices(r, scene.faces.cuda(), V.shape[1]).is_cuda


@pytest.mark.parametrize("backend", [b for b in AVAILABLE if b == "warp"])
def test_back_face_culling_keeps_the_first_hits(hands_and_ball, backend):
    """Leaving out faces turned away from the camera changes nothing for closed meshes
    seen from outside, even where the models interpenetrate (both hands and the ball)."""
    scene, V, cam = hands_and_ball
    args = (V, scene.faces, cam, scene.face_model_id, scene.face_bone_id)
    full, culled = render(*args, backend=backend), render(*args, cull_back_faces=True, backend=backend)
    hit = full.depth > 0
    assert int(hit.sum()) > 20000
    assert torch.equal(hit, culled.depth > 0)
    torch.testing.assert_close(culled.depth, full.depth, atol=1e-3, rtol=0)
    same = (culled.face_id == full.face_id)[hit].float().mean()
    assert same > 0.999  # a ray through a shared edge may report either face
    assert torch.equal(culled.model_id, full.model_id) and torch.equal(culled.silhouette_edges, full.silhouette_edges)


def test_visible_vertices_against_a_loop(hands_and_ball):
    scene, V, cam = hands_and_ball
    r = render(V, scene.faces, cam, normals=False)
    vis = visible_vertices(r, scene.faces, scene.num_vertices)
    for b in range(V.shape[0]):
        hit = torch.unique(r.face_id[b][r.face_id[b] >= 0])
        expected = torch.zeros(scene.num_vertices, dtype=torch.bool)
        expected[scene.faces[hit].reshape(-1)] = True
        assert torch.equal(vis[b], expected)


@pytest.mark.parametrize("cull", [False, True])
def test_depth_alone_is_the_full_renders_depth(hands_and_ball, backend, cull):
    """``Renderer.depth`` (with ``"warp"``: the depth test's float32 plane depth, no exact
    hits) covers the same pixels as the full render's depth and agrees with it to 1e-4
    relative, for one camera and for a rig of two seen by every problem."""
    scene, V, camera = hands_and_ball
    renderer = Renderer(scene.faces, backend=backend, cull_back_faces=cull)
    full = renderer(V, camera, normals=False).depth
    alone = renderer.depth(V, camera)
    assert alone.shape == full.shape and torch.equal(alone > 0, full > 0)
    assert float(((alone - full).abs() / full.clamp(min=1.0)).max()) < 1e-4
    rig = [camera, kinect_camera()]
    assert renderer.depth(V, rig).shape == renderer(V, rig, normals=False).depth.shape == (2, 2, 480, 640)
