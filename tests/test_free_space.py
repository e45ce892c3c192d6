"""The free-space term (F) and the data labels by 3D proximity."""

from __future__ import annotations

import pytest
import torch

from torchhand.geometry.camera import kinect_camera
from torchhand.geometry.render import render
from torchhand.tracking.energies import FreeSpace, ModelToData, parse_energy
from torchhand.tracking.labels import label_by_proximity
from torchhand.tracking.preprocess import preprocess_depth
from torchhand.tracking.tracker import Tracker, TrackerConfig

F64 = torch.float64


@pytest.fixture(scope="module")
def hand_and_ball(scene_at):
    """A right hand 450 mm in front of the camera with a ball 110 mm to its side, clean depth."""
    scene, theta = scene_at(["hand_right", "ball"], [(-40.0, 0.0, 450.0), (70.0, 0.0, 460.0)])
    cam = kinect_camera(dtype=F64)
    with torch.no_grad():
        depth = render(scene(theta).vertices, scene.faces, cam).depth[0]
    return scene, theta, cam, depth


def _prepared(scene, theta, cam, depth, term=None):
    tracker = Tracker(scene, TrackerConfig(energy="LO+F"))
    frame = preprocess_depth(depth, cam, tracker.config.preprocess, dtype=F64)
    state = tracker.states(theta, [frame], [cam]).view
    term = FreeSpace() if term is None else term
    return term, term.prepare(state), state


def test_no_free_space_at_the_true_pose(hand_and_ball):
    scene, theta, cam, depth = hand_and_ball
    _, found, _ = _prepared(scene, theta, cam, depth)
    assert int(found.counts.diagnostics["pixels"][0]) == 0


def test_a_model_moved_off_its_data_is_pulled_back(hand_and_ball):
    """The ball moved 8 mm sideways: its pixels beyond the data pair up, and the
    gradient of the term's energy on the ball's x translation points back."""
    scene, theta, cam, depth = hand_and_ball
    b = scene.slices["ball"]
    for dx in (8.0, -8.0):
        moved = theta.clone()
        moved[0, b.start] += dx
        term, found, state = _prepared(scene, moved, cam, depth)
        assert int(found.counts.diagnostics["pixels"][0]) > 20
        res = term.residuals(moved, state.posed, found, True)
        grad = (res.J.transpose(1, 2) @ res.r[..., None])[0, :, 0]  # d(E/2)/d theta
        assert float(grad[b.start]) * dx > 0  # descent moves the ball back
        rows = res.r.view(1, -1, 2).norm(dim=-1)[0]
        hand_rows = rows[: term.max_pixels]
        assert float(hand_rows.abs().max()) == 0.0  # the hand did not move: no pull on it


@pytest.mark.parametrize("backend", ["cpu", "torch"])
def test_every_neighbour_backend_pairs_free_space_pixels_alike(hand_and_ball, backend):
    """The nearest data pixel of each free-space pixel is exact with every backend: the
    same pixels are kept (their distance to the data lies within the tolerance and the
    radius alike), with the same vertices; only ties between equidistant data pixels
    may pick another pixel."""
    pytest.importorskip("warp")
    scene, theta, cam, depth = hand_and_ball
    moved = theta.clone()
    moved[0, scene.slices["ball"].start] += 8.0
    rows = [_prepared(scene, moved, cam, depth, FreeSpace(backend=b))[1].rows for b in ("warp", backend)]
    assert int(sum(r.mask.sum() for r in rows[0])) > 20
    for a, b in zip(*rows):
        assert torch.equal(a.mask, b.mask) and torch.equal(a.ids, b.ids)


def test_a_model_behind_data_is_occluded_not_in_free_space(hand_and_ball):
    """Data in front of the model is an occluder, no evidence against it: with a board
    300 mm from the camera in front of the ball, the ball moved 8 mm sideways gets no
    pairs (without the board it does)."""
    scene, theta, cam, depth = hand_and_ball
    b = scene.slices["ball"]
    moved = theta.clone()
    moved[0, b.start] += 8.0
    with torch.no_grad():
        rend = render(scene(theta).vertices, scene.faces, cam, scene.face_model_id)
    rows, cols = torch.nonzero(rend.model_id[0] == 1, as_tuple=True)
    board = depth.clone()
    board[rows.min() - 30 : rows.max() + 30, cols.min() - 30 : cols.max() + 30] = 300.0
    _, found, _ = _prepared(scene, moved, cam, depth)
    assert int(found.counts.diagnostics["pixels"][0]) > 20
    _, found, _ = _prepared(scene, moved, cam, board)
    assert int(found.counts.diagnostics["free"][0]) == 0


def test_data_far_behind_the_model_is_free_space(hand_and_ball):
    """A wall 300 mm behind everything: the ball moved onto the wall is in free space."""
    scene, theta, cam, depth = hand_and_ball
    wall = torch.where(depth > 0, depth, torch.full_like(depth, 760.0))
    b = scene.slices["ball"]
    moved = theta.clone()
    moved[0, b.start + 1] += 10.0
    _, found, _ = _prepared(scene, moved, cam, wall)
    assert int(found.counts.diagnostics["pixels"][0]) > 20


@pytest.mark.slow
def test_lo_f_tracks_a_displaced_ball_back(hand_and_ball):
    scene, theta, cam, depth = hand_and_ball
    b = scene.slices["ball"]
    start = theta.clone()
    start[0, b.start] += 8.0
    tracker = Tracker(scene, TrackerConfig(energy="LO+F"))
    res = tracker.track_frame([depth], [cam], start, first=True)
    assert abs(float(res.theta[0, b.start] - theta[0, b.start])) < 1.0


def test_free_space_arguments_are_checked():
    with pytest.raises(ValueError, match="margin"):
        FreeSpace(margin=-1)
    with pytest.raises(ValueError, match="radius"):
        FreeSpace(radius=0)
    with pytest.raises(ValueError, match="tolerance"):
        FreeSpace(tolerance=-1)
    with pytest.raises(ValueError, match="max_pixels"):
        FreeSpace(max_pixels=0)
    assert any(type(t).__name__ == "Weighted" and "FreeSpace" in repr(t) for t in parse_energy("LO+F"))
    with pytest.raises(ValueError, match="twice"):
        parse_energy("LO+FF")


# ------------------------------------------------------------------ labels by 3D proximity
def test_labels_follow_the_nearest_surface_in_3d(hand_and_ball):
    """Every data pixel of the true render is labelled with the model rendered there
    (except within a few mm of where the models meet); data 100 mm behind both is left
    unlabelled, though it borders them in the image."""
    scene, theta, cam, depth = hand_and_ball
    far = torch.where(depth > 0, depth, torch.zeros_like(depth))
    far[200:280, 0:60] = 700.0  # a patch far behind, at the image's side
    frame = preprocess_depth(far, cam, dtype=F64)
    with torch.no_grad():
        posed = scene(theta)
        rend = render(posed.vertices, scene.faces, cam, scene.face_model_id, scene.face_bone_id)
    labels = label_by_proximity([frame], [cam], posed.vertices, scene.vertex_model_id, 30.0)[0]
    seen = (rend.model_id[0] >= 0) & frame.mask
    agree = (labels[seen] == rend.model_id[0][seen]).double().mean()
    assert agree > 0.999
    assert (labels[200:280, 0:60] == -1).all()


def test_labels_without_data_near_any_model_are_empty(hand_and_ball):
    scene, theta, cam, depth = hand_and_ball
    frame = preprocess_depth(depth, cam, dtype=F64)
    away = theta.clone()
    away[0, 2] += 200.0
    away[0, scene.slices["ball"].start + 2] += 200.0
    with torch.no_grad():
        labels = label_by_proximity([frame], [cam], scene(away).vertices, scene.vertex_model_id, 30.0)
    assert (labels == -1).all()


@pytest.mark.slow
def test_the_labelling_is_a_tracker_option(hand_and_ball):
    scene, theta, cam, depth = hand_and_ball
    with pytest.raises(ValueError, match="labels must be one of"):
        TrackerConfig(labels="nearest")
    with pytest.raises(ValueError, match="label_distance"):
        TrackerConfig(label_distance=0)
    for labels in ("proximity", "rendered"):
        tracker = Tracker(scene, TrackerConfig(labels=labels), terms=[ModelToData()])
        res = tracker.track_frame([depth], [cam], theta, first=True)
        assert bool(res.valid[0]) and int(res.correspondences[0]) > 100
