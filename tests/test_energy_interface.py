"""The energy-term interface as a newcomer meets it: the worked example of
docs/architecture.md ("A new term, from the interface alone") is run as written, its
Jacobian checked against finite differences, and it is tracked with."""

import dataclasses
import re
from pathlib import Path

import pytest
import torch

from torchhand.geometry.camera import kinect_camera
from torchhand.model.scene import Scene
from torchhand.optim.robust_loss import Cauchy
from torchhand.tracking.energies import Robust, Weighted
from torchhand.tracking.tracker import Tracker

F64 = torch.float64
DOC = Path(__file__).resolve().parents[1] / "docs" / "architecture.md"


@pytest.fixture(scope="module")
def example():
    text = DOC.read_text()
    section = text[text.index("### A new term, from the interface alone"):]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    namespace: dict = {}
    exec(compile(code, str(DOC), "exec"), namespace)  # the docs' block, as written
    return namespace


@pytest.fixture(scope="module")
def hand():
    scene = Scene.from_names(["hand_right"], dtype=F64)
    theta = scene.zero_pose(1)
    theta[0, :3] = torch.tensor([0.0, 0.0, 450.0], dtype=F64)
    return scene, theta


def test_the_documented_term_has_an_exact_jacobian_and_frozen_data(example, hand):
    scene, theta = hand
    ids = torch.tensor([10, 2000, 7000])
    with torch.no_grad():
        targets = scene(theta).vertices[0, ids] + torch.tensor([3.0, -2.0, 1.0], dtype=F64)
    term = example["Markers"](ids, targets)
    tracker = Tracker(scene, terms=[term])
    state = tracker.states(theta, [None], [kinect_camera(dtype=F64)]).pose
    prepared = term.prepare(state)
    assert int(prepared.counts.correspondences[0]) == 3
    with pytest.raises(dataclasses.FrozenInstanceError):  # a wrapper cannot change a term's data in place
        prepared.ids = ids
    res = term.residuals(theta, scene(theta), prepared)
    torch.testing.assert_close(res.r.view(3, 3), -torch.tensor([3.0, -2.0, 1.0], dtype=F64).expand(3, 3))
    eps = 1e-6
    for d in (0, 3, 5, 12, 30):
        tp, tm = theta.clone(), theta.clone()
        tp[0, d] += eps
        tm[0, d] -= eps
        fd = (term.residuals(tp, scene(tp), prepared, False).r - term.residuals(tm, scene(tm), prepared, False).r)
        torch.testing.assert_close(fd / (2 * eps), res.J[..., d], atol=1e-6, rtol=1e-5)
    # weights and robust losses wrap it with no code of its own
    w = Weighted(term, 4.0)
    torch.testing.assert_close(w.residuals(theta, scene(theta), w.prepare(state)).r, 2.0 * res.r)
    rob = Robust(term, Cauchy(1e6))
    torch.testing.assert_close(rob.residuals(theta, scene(theta), rob.prepare(state)).r, res.r)


def test_the_documented_term_tracks(example, hand):
    """Markers spread over the hand, moved with it (6 mm and 0.1 rad): the solver puts the
    model's vertices on them."""
    scene, theta = hand
    goal = theta.clone()
    goal[0, :3] += torch.tensor([6.0, -4.0, 5.0], dtype=F64)
    goal[0, 3:6] += torch.tensor([0.05, -0.1, 0.05], dtype=F64)
    ids = torch.arange(0, scene.num_vertices, 500)
    with torch.no_grad():
        targets = scene(goal).vertices[0, ids]
    term = example["Markers"](ids, targets)
    tracker = Tracker(scene, terms=[term])
    sol = tracker.solve(theta, theta, [None], [kinect_camera(dtype=F64)], 20, 0.0)
    with torch.no_grad():
        err = (scene(sol.theta).vertices[0, ids] - targets).norm(dim=-1).max()
    assert float(err) < 0.05, float(err)
