"""Collision detection and the conic-distance-field penalty (thesis Eq. 4.9-4.13).

The triangle test is checked against an edge-through-triangle reference, the broad
phase against brute force, the pair sets against python-fcl on posed thesis hands
and objects, the penalty against its closed form and the term's Jacobian against
finite differences.
"""

import numpy as np
import pytest
import torch

from torchhand.geometry.intersections import (
    CollisionMesh,
    collision_energy,
    collision_loss,
    conic_field,
    detect_collisions,
    pair_sets,
    triangles_intersect,
)
from torchhand.data.synth import demo_motion
from torchhand.tracking.energies import Collision, TrackState, Weighted, collision, parse_energy
from torchhand.model.scene import Scene


# ------------------------------------------------------------------ helpers
def _segment_hits_triangle(p0, p1, tri):
    """Slow reference: does the closed segment p0-p1 cross the triangle (Moller-Trumbore)?"""
    d = p1 - p0
    e1, e2 = tri[1] - tri[0], tri[2] - tri[0]
    h = np.cross(d, e2)
    a = e1 @ h
    if abs(a) < 1e-12:
        return False
    f = 1.0 / a
    s = p0 - tri[0]
    u = f * (s @ h)
    q = np.cross(s, e1)
    v = f * (d @ q)
    t = f * (e2 @ q)
    return u >= 0 and v >= 0 and u + v <= 1 and 0 <= t <= 1


def _reference_intersect(p, q):
    """Generic (non-coplanar) triangles intersect iff an edge of one crosses the other."""
    return any(_segment_hits_triangle(a[i], a[(i + 1) % 3], b) for a, b in ((p, q), (q, p)) for i in range(3))


@pytest.fixture(scope="module")
def demo():
    """Two thesis hands and the ball (the shipped demo motion), float64."""
    sf = demo_motion(dtype=torch.float64)
    return sf.scene, sf.theta


def _pushed(scene, theta, amount, model="hand_left", towards="hand_right"):
    """theta with ``model`` moved by ``amount`` of the way to ``towards`` (interpenetration)."""
    theta = theta.clone()
    with torch.no_grad():
        V = scene(theta).vertices
    a, b = scene.vertex_slices[model], scene.vertex_slices[towards]
    s = scene.slices[model]
    theta[:, s.start : s.start + 3] += amount * (V[:, b].mean(1) - V[:, a].mean(1))
    return theta


def _fcl_pairs(vertices, faces, groups, tested=None):
    """Intersecting pairs between face groups with python-fcl. groups: face index
    arrays; tested(a, b): whether groups a and b are tested (default all). Pairs come
    back as sorted scene face index tuples."""
    import fcl

    objs = []
    for g in groups:
        m = fcl.BVHModel()
        m.beginModel(0, 0)
        m.addSubModel(vertices, faces[g].astype(np.int32))
        m.endModel()
        objs.append(fcl.CollisionObject(m, fcl.Transform()))
    out = set()
    for a in range(len(objs)):
        for b in range(a + 1, len(objs)):
            if tested is not None and not tested(a, b):
                continue
            req = fcl.CollisionRequest(num_max_contacts=10**7, enable_contact=False)
            res = fcl.CollisionResult()
            fcl.collide(objs[a], objs[b], req, res)
            for c in res.contacts:
                s, t = int(groups[a][c.b1]), int(groups[b][c.b2])
                out.add((min(s, t), max(s, t)))
    return out


# ------------------------------------------------------------ triangle test
def test_triangle_test_matches_edge_crossing_reference_on_random_triangles():
    g = torch.Generator().manual_seed(0)
    p = torch.rand(1500, 3, 3, generator=g, dtype=torch.float64)
    q = torch.rand(1500, 3, 3, generator=g, dtype=torch.float64) + 0.3
    hit = triangles_intersect(p, q).numpy()
    ref = np.array([_reference_intersect(a, b) for a, b in zip(p.numpy(), q.numpy())])
    assert 0.05 < ref.mean() < 0.95  # both outcomes are exercised
    assert (hit == ref).all()


def test_triangle_test_coplanar_touching_and_batched_shapes():
    t = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=torch.float64)
    cases = [
        (t + torch.tensor([0.2, 0.2, 0.0], dtype=torch.float64), True),  # coplanar, overlapping
        (t + torch.tensor([2.0, 0.0, 0.0], dtype=torch.float64), False),  # coplanar, apart
        (t + torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), True),  # coplanar, sharing a vertex
        (torch.tensor([[0.2, 0.2, -1], [0.2, 0.2, 1], [0.3, 0.5, 1]], dtype=torch.float64), True),  # piercing
        (torch.tensor([[0.2, 0.2, 0.1], [0.2, 0.2, 1], [0.3, 0.5, 1]], dtype=torch.float64), False),  # above
    ]
    q = torch.stack([c for c, _ in cases])
    got = triangles_intersect(t.expand(len(cases), 3, 3), q)
    assert got.tolist() == [h for _, h in cases]
    assert triangles_intersect(t[None].float(), q[:1].float()).shape == (1,)


# ------------------------------------------------------------- broad phase
def test_detection_equals_brute_force_on_a_small_mesh():
    """Two copies of the ball, one pushed into the other: the hierarchy finds exactly
    the pairs an all-pairs test finds."""
    scene = Scene.from_names(["ball", "cube"], dtype=torch.float64)
    theta = scene.zero_pose(2).double()
    with torch.no_grad():
        V0 = scene(theta).vertices
    cb, cc = V0[0, scene.vertex_slices["ball"]].mean(0), V0[0, scene.vertex_slices["cube"]].mean(0)
    s = scene.slices["ball"]
    theta[0, s.start : s.start + 3] = (cc - cb) + torch.tensor([26.0, 3.0, 2.0], dtype=torch.float64)  # through a face
    theta[1, s.start : s.start + 3] = (cc - cb) + torch.tensor([24.0, 25.0, 22.0], dtype=torch.float64)  # a corner
    with torch.no_grad():
        V = scene(theta).vertices
    mesh = CollisionMesh.from_scene(scene, leaf_size=4)
    found = pair_sets(detect_collisions(V, mesh), 2)
    fb, fc = scene.faces[scene.face_model_id == 0], scene.faces[scene.face_model_id == 1]
    ib, ic = torch.nonzero(scene.face_model_id == 0)[:, 0], torch.nonzero(scene.face_model_id == 1)[:, 0]
    for b in range(2):
        P, Q = V[b][fb], V[b][fc]  # all pairs whose boxes overlap, then the exact test
        near = ((P.amin(1)[:, None] <= Q.amax(1)[None]) & (Q.amin(1)[None] <= P.amax(1)[:, None])).all(-1)
        i, j = torch.nonzero(near).unbind(1)
        hit = triangles_intersect(P[i], Q[j])
        ref = {(int(ib[a]), int(ic[c])) for a, c in zip(i[hit].tolist(), j[hit].tolist())}
        assert len(ref) > 20
        assert found[b] == ref


# --------------------------------------------------------- against python-fcl
@pytest.mark.slow
@pytest.mark.parametrize("amount", [0.25, 0.45])
def test_pair_sets_equal_fcl_for_two_hands_and_the_ball(demo, amount):
    pytest.importorskip("fcl")
    scene, theta = demo
    th = _pushed(scene, theta[[5, 33]], amount)
    with torch.no_grad():
        V = scene(th).vertices
    mesh = CollisionMesh.from_scene(scene, self_collisions=False)
    found = pair_sets(detect_collisions(V, mesh), 2)
    F = scene.faces.numpy()
    groups = [np.nonzero(scene.face_model_id.numpy() == k)[0] for k in range(3)]
    for b in range(2):
        ref = _fcl_pairs(V[b].numpy(), F, groups)
        assert len(ref) > 50
        assert found[b] == ref


def test_pair_sets_equal_fcl_for_a_hand_grasping_into_an_object():
    pytest.importorskip("fcl")
    scene = Scene.from_names(["hand_right", "cube"], dtype=torch.float64)
    sf = demo_motion(dtype=torch.float64)
    theta = torch.cat([sf.theta[[12], :37], scene.zero_pose(1)[:, 37:].double()], 1)
    with torch.no_grad():
        V = scene(theta).vertices
    s = scene.slices["cube"]
    hand, cube = V[0, scene.vertex_slices["hand_right"]], V[0, scene.vertex_slices["cube"]]
    theta[0, s.start : s.start + 3] = hand.mean(0) - cube.mean(0) + torch.tensor([0.0, 30.0, 0.0], dtype=torch.float64)
    with torch.no_grad():
        V = scene(theta).vertices
    found = pair_sets(detect_collisions(V, CollisionMesh.from_scene(scene)), 1)[0]
    groups = [np.nonzero(scene.face_model_id.numpy() == k)[0] for k in range(2)]
    ref = _fcl_pairs(V[0].numpy(), scene.faces.numpy(), groups)
    between = {p for p in found if scene.face_model_id[p[0]] != scene.face_model_id[p[1]]}
    assert len(ref) > 20 and between == ref


def test_self_collisions_equal_fcl_between_parts(demo):
    """A fist curled past its flexion limits (fingers into the palm) with two fingers
    spread into each other. Self pairs equal fcl's pairs between the parts that may
    collide (part meshes tested pairwise)."""
    pytest.importorskip("fcl")
    scene = Scene.from_names(["hand_right"], dtype=torch.float64)
    model = scene.models[0]
    theta = scene.zero_pose(1).double()
    for k, name in enumerate(model.dof_names):
        if name.endswith(":y") and "_Hand" not in name and not name.startswith("RFing.0"):
            theta[0, k] = -1.9  # flexion, beyond the limits on purpose
        if name in ("RFing.2_0:z", "RFing.3_0:z"):
            theta[0, k] = 0.5
    with torch.no_grad():
        V = scene(theta).vertices
    mesh = CollisionMesh.from_scene(scene)
    found = pair_sets(detect_collisions(V, mesh), 1)[0]
    assert len(found) > 20
    part = mesh.face_part.numpy()
    assert not any(mesh.excluded[part[s], part[t]] for s, t in found)
    groups = [np.nonzero(part == p)[0] for p in range(mesh.num_parts)]
    ref = _fcl_pairs(V[0].numpy(), scene.faces.numpy(), groups, lambda a, b: not bool(mesh.excluded[a, b]))
    assert found == ref


def test_no_self_collisions_at_rest_and_separated_models_have_none(demo):
    scene, theta = demo
    with torch.no_grad():
        rest = scene(scene.zero_pose(1).double()).vertices
    assert len(detect_collisions(rest, CollisionMesh.from_scene(scene, models=["hand_right"]))) == 0
    th = theta[[0]].clone()
    s = scene.slices["hand_left"]
    th[0, s.start] += 500.0
    with torch.no_grad():
        V = scene(th).vertices
    pairs = detect_collisions(V, CollisionMesh.from_scene(scene, self_collisions=False, models=["hand_left", "ball"]))
    assert len(pairs) == 0


# ------------------------------------------------------------------- penalty
def test_conic_field_closed_form_on_the_axis_and_outside_the_cone():
    tri = torch.tensor([[1.0, 0, 0], [-0.5, 3**0.5 / 2, 0], [-0.5, -(3**0.5) / 2, 0]], dtype=torch.float64)  # r = 1
    sigma = 0.5
    depth = torch.tensor([0.0, 0.25, 0.5, 2.0, 5.0], dtype=torch.float64)
    pts = torch.stack([torch.zeros_like(depth), torch.zeros_like(depth), -depth], -1)  # behind, on the axis
    psi = conic_field(pts, tri.expand(len(depth), 3, 3), sigma)
    # Phi = 0 on the axis; Upsilon(x) = -x + 1 - sigma for sigma = 0.5 everywhere below sigma
    assert torch.allclose(psi, (depth + 1 - sigma) ** 2)
    # in front beyond the apex, and far off the axis: no penalty
    out = conic_field(torch.tensor([[0.0, 0, 0.6], [10.0, 0, -0.1]], dtype=torch.float64), tri.expand(2, 3, 3), sigma)
    assert (out == 0).all()
    # Upsilon is continuous at +-sigma for another sigma: Psi is continuous along the axis
    s2 = 0.3
    x = torch.tensor([-s2 - 1e-9, -s2 + 1e-9, s2 - 1e-9], dtype=torch.float64)
    p2 = conic_field(torch.stack([0 * x, 0 * x, x], -1), tri.expand(3, 3, 3), s2)
    assert abs(p2[0] - p2[1]) < 1e-6 and p2[2] < 1e-12


def test_conic_field_gradcheck_and_finite_gradients_at_singular_points():
    g = torch.Generator().manual_seed(1)
    tri = torch.tensor([[0.0, 0, 0], [2, 0, 0], [0, 2, 0]], dtype=torch.float64)
    pts = torch.rand(20, 3, generator=g, dtype=torch.float64) * torch.tensor([1.0, 1.0, -2.0]) + 0.05
    tris = (tri + 0.01 * torch.randn(20, 3, 3, generator=g, dtype=torch.float64)).requires_grad_()
    pts.requires_grad_()
    assert torch.autograd.gradcheck(lambda p, t: conic_field(p, t), (pts, tris))
    # on the axis (lateral distance 0) and a degenerate receiver: finite, no NaN
    o = torch.tensor([[2 / 3 * 0 + 1.0, 1.0, -1.0]], dtype=torch.float64, requires_grad=True)
    degenerate = torch.tensor([[[0.0, 0, 0], [1, 1, 1], [2, 2, 2]]], dtype=torch.float64, requires_grad=True)
    val = conic_field(o, tri[None]) + conic_field(o, degenerate)
    val.sum().backward()
    assert torch.isfinite(o.grad).all() and torch.isfinite(degenerate.grad).all()
    assert conic_field(o.detach(), degenerate.detach()).item() == 0.0


def test_collision_loss_backward_gives_a_descent_direction(demo):
    """loss.backward() through posing: a small step of the left hand's translation
    against the gradient lowers the penalty of the detected pairs (Eq. 4.13 holds C
    fixed while stepping, as the tracker does)."""
    scene, theta = demo
    th = _pushed(scene, theta[[10]], 0.2).requires_grad_()
    mesh = CollisionMesh.from_scene(scene, self_collisions=False)
    V = scene(th).vertices
    pairs = detect_collisions(V, mesh)
    loss = collision_energy(V, scene.faces, pairs).sum()
    assert torch.allclose(loss, collision_loss(V, mesh).sum())
    loss.backward()
    assert loss.item() > 0 and torch.isfinite(th.grad).all()
    s = scene.slices["hand_left"]
    g = th.grad[0, s.start : s.start + 3]
    step = th.detach().clone()
    step[0, s.start : s.start + 3] -= 0.05 * g / g.norm()  # 0.05 mm
    with torch.no_grad():
        after = collision_energy(scene(step).vertices, scene.faces, pairs).sum()
    assert after < loss.detach()


def test_energy_forms_agree_and_jacobian_matches_finite_differences(demo):
    scene, theta = demo
    th = _pushed(scene, theta[[4, 40]], 0.28)
    posed = scene(th)
    state = TrackState(scene, th, th, posed, None, None, None, None)
    plane = Weighted(Collision(metric="point-to-plane"), collision.DEFAULT_WEIGHT)
    point = Weighted(Collision(metric="point-to-point"), collision.DEFAULT_WEIGHT)
    found = plane.prepare(state)
    found3 = point.prepare(state)
    assert (found.counts.diagnostics["pairs"] > 0).all() and (found.counts.correspondences == 0).all()  # no data pairs
    r, J = plane.residuals(th, posed, found, True)[:2]
    r3, J3 = point.residuals(th, posed, found3, True)[:2]
    assert r3.shape[1] == 3 * r.shape[1]
    assert torch.allclose((r**2).sum(1), (r3**2).sum(1))
    # the term's energy is gamma_c times Eq. 4.13
    pairs = detect_collisions(posed.vertices, plane.term.mesh_for(scene))
    assert torch.allclose((r**2).sum(1), 10.0 * collision_energy(posed.vertices, scene.faces, pairs))
    eps = 1e-6
    for d in [0, 4, 37, 39, 37 + 12, 37 + 30, 74, 76]:
        tp, tm = th.clone(), th.clone()
        tp[:, d] += eps
        tm[:, d] -= eps
        fd = (plane.residuals(tp, scene(tp), found, False).r - plane.residuals(tm, scene(tm), found, False).r) / (2 * eps)
        assert torch.allclose(fd, J[:, :, d], rtol=1e-5, atol=1e-5 * (1 + J[:, :, d].abs().max())), d


def test_parse_energy_with_collisions():
    assert [t.name for t in parse_energy("LO+C")] == ["m2d", "d2m", "collision", "anatomy", "regularization",
                                                      "chain_smoothness"]
    with pytest.raises(ValueError, match="twice"):
        parse_energy("LO+CC")


# ----------------------------------------------------------------- bad input
def test_bad_input_gives_clear_errors_or_documented_skips():
    scene = Scene.from_names(["ball", "cube"], dtype=torch.float64)
    mesh = CollisionMesh.from_scene(scene)
    V = scene(scene.zero_pose(1).double()).vertices
    with pytest.raises(ValueError, match="NaN"):
        detect_collisions(V.clone().index_fill_(1, torch.tensor([3]), float("nan")), mesh)
    with pytest.raises(ValueError, match="vertices must have shape"):
        detect_collisions(V[0], mesh)
    with pytest.raises(ValueError, match="index vertex"):
        detect_collisions(V[:, :10], mesh)
    # empty meshes: no pairs, zero energy
    empty = CollisionMesh(torch.zeros(0, 3, dtype=torch.int64), torch.zeros(0, dtype=torch.int64),
                          torch.zeros(0, 0, dtype=torch.bool))
    pairs = detect_collisions(V, empty)
    assert len(pairs) == 0
    assert collision_energy(V, empty.faces, pairs).tolist() == [0.0]
    # a zero-area triangle crossing another: skipped, never NaN
    verts = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.2, -1], [0.2, 0.2, 0], [0.2, 0.2, 1]]],
                         dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
    m = CollisionMesh(faces, torch.tensor([0, 1]), torch.zeros(2, 2, dtype=torch.bool), rest_vertices=verts[0])
    assert len(detect_collisions(verts, m)) == 0
    with pytest.raises(ValueError, match="symmetric"):
        CollisionMesh(faces, torch.tensor([0, 1]), torch.tensor([[False, True], [False, False]]))
    with pytest.raises(ValueError, match="power of two"):
        CollisionMesh(faces, torch.tensor([0, 1]), torch.zeros(2, 2, dtype=torch.bool), leaf_size=3)
    with pytest.raises(KeyError, match="no models"):
        CollisionMesh.from_scene(scene, models=["hand_left"])
    # a model with a single part (no collision zones) works: nothing to self-collide
    assert len(detect_collisions(V, CollisionMesh.from_scene(Scene.from_names(["ball"], dtype=torch.float64)))) == 0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA not available")
def test_cuda_matches_cpu(demo):
    scene, theta = demo
    th = _pushed(scene, theta[[7]], 0.3)
    with torch.no_grad():
        V = scene(th).vertices
    mesh = CollisionMesh.from_scene(scene)
    cpu = detect_collisions(V, mesh)
    gpu = detect_collisions(V.cuda(), mesh)
    assert pair_sets(cpu, 1) == pair_sets(gpu, 1)
    e_cpu = collision_energy(V, scene.faces, cpu)
    e_gpu = collision_energy(V.cuda(), scene.faces.cuda(), gpu)
    assert torch.allclose(e_cpu, e_gpu.cpu())
