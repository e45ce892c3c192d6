"""The physics term P (thesis Eq. 4.16) and its Bullet simulation."""

from __future__ import annotations

import warnings

import pytest
import torch

pytest.importorskip("pybullet")

from torchhand.model.scene import Scene  # noqa: E402
from torchhand.tracking.energies import Physics, counts, parse_energy  # noqa: E402
from torchhand.tracking.energies.physics import PhysicsPairs  # noqa: E402
from torchhand.tracking.simulation import GraspSimulation, contact_bones, part_vertices  # noqa: E402

F64 = torch.float64


@pytest.fixture(scope="module")
def hand_ball(scene_at):
    """A right hand and the ball, both centred 450 mm in front of the camera."""
    return scene_at(["hand_right", "ball"], [(0.0, 0.0, 450.0), (0.0, 0.0, 450.0)])


def test_parts_and_contact_zones_come_from_the_model_files(hand_ball):
    scene, _ = hand_ball
    hand = scene.models[0]
    parts = part_vertices(hand)
    assert sum(len(p) for p in parts) == hand.num_vertices  # every vertex in one part
    bones = contact_bones(hand)  # the ZONES file's top zone: the phalanges
    assert len(bones) == 14 and 0 not in bones
    assert all(hand.bone_names[j].split("_")[-1] in ("0", "1", "2") for j in bones)


def test_an_unsupported_object_falls_and_a_far_hand_cannot_hold_it(hand_ball):
    """The ball 300 mm beside the hand: it falls (far more than 3 mm in 3.5 s) and no
    finger part is within 10 mm, so no support is found."""
    scene, theta = hand_ball
    away = theta.clone()
    away[0, scene.slices["ball"].start] += 300.0
    with torch.no_grad():
        out = scene(away)
    verts = {k: o.vertices[0].numpy() for k, o in enumerate(out.models)}
    sim = GraspSimulation(scene)
    assert sim.displacement(verts)[1] > 1000.0
    support = sim.best_support(verts)[1]
    assert not support.stable and support.parts == []


def test_physics_jacobian_matches_finite_differences(hand_ball):
    scene, theta = hand_ball
    term = Physics()
    vh = torch.tensor([[100, 2000, 5000]])
    vo = torch.tensor([[3, 50, 400]])
    prepared = PhysicsPairs(counts(1), scene, ((0, 1, vh, vo, torch.ones(1, 3, dtype=F64)),))
    start = theta.clone()
    start[0, 6:] += 0.05
    r, J = term.residuals(start, scene(start), prepared, True)[:2]
    eps = 1e-6
    cols = []
    for d in range(scene.num_dofs):
        e = torch.zeros_like(start)
        e[0, d] = eps
        cols.append((term.residuals(start + e, scene(start + e), prepared, False).r
                     - term.residuals(start - e, scene(start - e), prepared, False).r) / (2 * eps))
    J_fd = torch.stack(cols, -1)
    assert (J - J_fd).abs().max() / J_fd.abs().max() < 1e-6
    # Eq. 4.16: the residual is V_i - X_i, hand vertex minus object vertex
    out = scene(start)
    assert torch.allclose(r.view(1, 3, 3), out.models[0].vertices[0, vh[0]] - out.models[1].vertices[0, vo[0]])


def test_a_scene_without_a_rigid_object_says_so_once(hand_ball):
    from torchhand.geometry.camera import kinect_camera
    from torchhand.geometry.render import render
    from torchhand.tracking.tracker import Tracker, TrackerConfig

    scene = Scene.from_names(["hand_right"], dtype=F64)
    theta = hand_ball[1][:, : scene.num_dofs]
    cam = kinect_camera(dtype=F64)
    with torch.no_grad():
        depth = render(scene(theta).vertices, scene.faces, cam).depth[0]
    tracker = Tracker(scene, TrackerConfig(energy="LO+P", max_iterations=3, first_frame_iterations=3))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(2):
            res = tracker.track_frame([depth], [cam], theta, first=True)
            assert torch.isfinite(res.theta).all()
    said = [w for w in caught if "physics term does nothing" in str(w.message)]
    assert len(said) == 1


def test_parse_energy_adds_the_weighted_physics_term():
    from torchhand.tracking.energies import Weighted
    from torchhand.tracking.energies.physics import DEFAULT_WEIGHT

    terms = [t for t in parse_energy("LO+CSP") if isinstance(t, Weighted) and isinstance(t.term, Physics)]
    assert len(terms) == 1 and terms[0].weight == DEFAULT_WEIGHT == 10.0
    assert not any(isinstance(getattr(t, "term", t), Physics) for t in parse_energy("LO+CS"))


@pytest.mark.slow
def test_a_held_cube_gets_supporting_fingers_and_the_term_pulls_them_on(hia_root):
    """Frame 50 of "Moving a cube" (sequence 20) as the thesis' motion poses it: the
    cube falls from the hand (no table is modelled); moving two finger parts onto it holds
    it to within the 3 mm of the stability test, and the term pairs those parts' nearest
    vertices with the cube's, whose distances it then shrinks."""
    from torchhand.data.synth import thesis_motion
    from torchhand.geometry.camera import kinect_camera
    from torchhand.tracking.preprocess import preprocess_depth
    from torchhand.tracking.tracker import Tracker, TrackerConfig
    from torchhand.geometry.render import render

    frames = thesis_motion(hia_root, "20", slice(50, 51))
    scene = Scene.from_names(frames.scene.names, dtype=F64)
    theta = frames.theta.double()
    with torch.no_grad():
        posed = scene(theta)
    sim = GraspSimulation(scene)
    support = sim.best_support({k: o.vertices[0].numpy() for k, o in enumerate(posed.models)})[1]
    assert not support.stable and support.displacement > 1000.0
    assert 2 <= len(support.parts) <= 4 and support.supported < 3.0
    assert all(k == 0 and j in contact_bones(scene.models[0]) for k, j in support.parts)

    cam = kinect_camera(dtype=F64)
    with torch.no_grad():
        depth = render(posed.vertices, scene.faces, cam).depth[0]
    tracker = Tracker(scene, TrackerConfig(energy="LO"))
    state = tracker.states(theta, [preprocess_depth(depth, cam, dtype=F64)], [cam]).pose
    term = Physics()
    found = term.prepare(state)
    assert int(found.counts.diagnostics["unstable"][0]) == 1
    assert int(found.counts.diagnostics["contact_parts"][0]) == len(support.parts)
    r = term.residuals(theta, posed, found, False).r.view(-1, 3)
    assert r.shape[0] == len(support.parts) and (r.norm(dim=-1) < 12.0).all()  # parts within 10 mm (+ a vertex)
