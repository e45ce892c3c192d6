"""Association of detections to fingertips (Eq. 4.14) and the salient term (Eq. 4.15)."""

import itertools

import numpy as np
import pytest
import torch

from torchhand.geometry.camera import kinect_camera
from torchhand.tracking.energies import Salient, TrackState, parse_energy
from torchhand.tracking.energies.salient_points import simulated_detector
from torchhand.tracking.preprocess import preprocess_depth
from torchhand.geometry.render import render
from torchhand.salient.association import associate
from torchhand.model.fingertips import fingertip_faces
from torchhand.model.scene import Scene


def _brute_force(cost, lam, ws):
    """Eq. 4.14 by enumerating every partial one-to-one assignment."""
    S, T = cost.shape
    best = np.inf
    for k in range(min(S, T) + 1):
        for dets in itertools.combinations(range(S), k):
            for tips in itertools.permutations(range(T), k):
                c = sum(cost[s, t] for s, t in zip(dets, tips))
                c += lam * sum(ws[s] for s in range(S) if s not in dets) + lam * (T - k)
                best = min(best, c)
    return best


@pytest.mark.parametrize("seed", range(6))
def test_association_is_the_optimum_of_the_integer_program(seed):
    rng = np.random.default_rng(seed)
    S, T = rng.integers(0, 5), rng.integers(1, 5)
    cost = rng.uniform(0, 3, (S, T))
    cost[rng.uniform(size=(S, T)) < 0.2] = np.inf  # some forbidden pairs
    ws = rng.uniform(0.5, 2.0, S)
    lam = float(rng.uniform(0.2, 1.5))
    a = associate(cost, lam, ws)
    assert a.cost == pytest.approx(_brute_force(cost, lam, ws))
    assert len(set(a.detection)) == len(a.detection) and len(set(a.fingertip)) == len(a.fingertip)
    assert np.isfinite(cost[a.detection, a.fingertip]).all()
    assert a.false_positive.sum() + len(a.detection) == S and a.unassigned.sum() + len(a.fingertip) == T


def test_association_rules_and_errors():
    # a pair is taken only when cheaper than a false positive plus an unmatched fingertip
    a = associate(np.array([[1.9], [2.1]]), 1.0)
    assert a.detection.tolist() == [0] and a.false_positive.tolist() == [False, True]
    assert len(associate(np.array([[2.5]]), 1.0).detection) == 0
    assert associate(np.zeros((0, 3)), 1.0).unassigned.all()
    with pytest.raises(ValueError, match="non-negative"):
        associate(np.array([[-1.0]]), 1.0)
    with pytest.raises(ValueError, match="detection_weight"):
        associate(np.ones((2, 2)), 1.0, np.ones(3))


@pytest.fixture(scope="module")
def hand_frame():
    """hand_right facing the thesis camera, its render, a depth frame and the fingertip
    centres' pixels, float64."""
    scene = Scene.from_names(["hand_right"], dtype=torch.float64)
    cam = kinect_camera(dtype=torch.float64)
    theta = scene.zero_pose(1).double()
    with torch.no_grad():
        rest = scene(theta).vertices
    # put the hand 450 mm in front of the camera, palm towards it
    centre = rest[0].mean(0)
    target = cam.T_wc[:3, :3] @ torch.tensor([0.0, 0.0, 450.0], dtype=torch.float64) + cam.T_wc[:3, 3]
    theta[0, :3] = target - centre
    with torch.no_grad():
        posed = scene(theta)
    rend = render(posed.vertices, scene.faces, cam, scene.face_model_id, scene.face_bone_id)
    depth = rend.depth[0].numpy()
    index, mask, _, _ = fingertip_faces(scene)
    tips = (posed.vertices[0][index] * mask[..., None]).sum(1) / mask.sum(1, keepdim=True)
    uv = cam.project(tips[None])[0].numpy()
    z = cam.to_camera(tips[None])[0, :, 2].numpy()
    return scene, cam, theta, depth, uv, z


def _state(scene, cam, theta, depth):
    with torch.no_grad():
        posed = scene(theta)
    rend = render(posed.vertices, scene.faces, cam, scene.face_model_id, scene.face_bone_id)
    frame = preprocess_depth(depth, cam, dtype=torch.float64)
    return TrackState(scene, theta, theta, posed, [frame], [cam], rend, None), posed


def test_salient_term_pulls_displaced_fingertips_and_jacobian_is_exact(hand_frame):
    scene, cam, theta, depth, uv, z = hand_frame
    # fingertips seen at their own pixel (the surface there is the fingertip's front)
    visible = [k for k in range(len(uv)) if abs(depth[int(round(uv[k, 1])), int(round(uv[k, 0]))] - z[k]) < 12.0]
    assert len(visible) >= 2
    rows = np.c_[uv[visible], np.full(len(visible), 5.0)]
    # near_mm = 15: the centroid of a fingertip's visible vertices (front and sides) lies
    # up to ~10 mm behind that of the detected front surface
    term = Salient(detector=simulated_detector(lambda d: rows), near_mm=15.0)
    # at the true pose every fingertip is near its detection: associated, but no pairs
    state, posed = _state(scene, cam, theta, depth)
    found = term.prepare(state).counts
    assert found.diagnostics["assigned"][0] == len(visible) and found.correspondences[0] == 0
    # move the hand 15 mm: the same detections now pull the fingertips back
    moved = theta.clone()
    moved[0, 0] += 20.0
    state, posed = _state(scene, cam, moved, depth)
    prepared = term.prepare(state)
    found = prepared.counts
    assert found.diagnostics["assigned"][0] == len(visible) and found.correspondences[0] > 0
    r, J = term.residuals(moved, posed, prepared, True)[:2]
    assert r.shape == (1, 3 * int(found.correspondences[0])) and J.shape == (1, r.shape[1], scene.num_dofs)
    # residual x components are about the 20 mm shift
    rx = r.view(1, -1, 3)[0, :, 0]
    assert 10.0 < float(rx.mean()) < 30.0
    eps = 1e-6
    for d in [0, 1, 4, 20, 30]:
        tp, tm = moved.clone(), moved.clone()
        tp[0, d] += eps
        tm[0, d] -= eps
        fd = (term.residuals(tp, scene(tp), prepared, False).r - term.residuals(tm, scene(tm), prepared, False).r) / (2 * eps)
        assert torch.allclose(fd, J[:, :, d], atol=1e-6 * (1 + J[:, :, d].abs().max()))
    # a Gauss-Newton step on the translation alone moves the hand back
    Jt = J[0, :, :3]
    step = -torch.linalg.lstsq(Jt, r[0]).solution
    assert step[0] < -8.0


def test_salient_term_drops_detections_off_the_surface_or_below_min_score(hand_frame):
    scene, cam, theta, depth, uv, z = hand_frame
    k = int(np.argmin(np.abs(depth[np.round(uv[:, 1]).astype(int), np.round(uv[:, 0]).astype(int)] - z)))
    rows = np.array([[5.0, 5.0, 9.0],  # on no surface
                     [uv[k, 0], uv[k, 1], 0.2],  # on a fingertip, but not confident
                     [uv[k, 0], uv[k, 1], 0.9]])  # on a fingertip, confident
    term = Salient(detector=simulated_detector(lambda d: rows), min_score=0.5)
    state, _ = _state(scene, cam, theta, depth)
    cent, clouds, boxes, conf = term._regions(state.frames[0], cam)
    assert len(cent) == 1 and conf.tolist() == pytest.approx([0.9]) and len(clouds[0]) > 0
    moved = theta.clone()
    moved[0, 0] += 20.0
    state, posed = _state(scene, cam, moved, depth)
    found = term.prepare(state).counts
    assert found.diagnostics["assigned"][0] == 1 and found.correspondences[0] > 0
    none = Salient(detector=simulated_detector(lambda d: None))
    prepared = none.prepare(state)
    found = prepared.counts
    assert found.diagnostics["assigned"][0] == 0 and found.correspondences[0] == 0
    assert none.residuals(moved, posed, prepared, True).r.shape == (1, 0)


def test_parse_energy_with_salient_points():
    priors = ["anatomy", "regularization", "chain_smoothness"]
    assert [t.name for t in parse_energy("LO+S")] == ["m2d", "d2m", "salient", *priors]
    assert [t.name for t in parse_energy("LO+CS")] == ["m2d", "d2m", "collision", "salient", *priors]
