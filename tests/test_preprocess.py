"""Depth preprocessing: the cropped filters equal the whole-image ones; bad frames."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchhand.tracking.preprocess as pp
from torchhand.geometry.camera import kinect_camera
from torchhand.geometry.render import render
from torchhand.model.scene import Scene


@pytest.fixture(scope="module")
def hand_depth():
    scene = Scene.from_names(["hand_right"])
    model = scene.models[0]
    theta = model.zero_pose(1)
    theta[0, :3] = torch.tensor([40.0, -30.0, 500.0]) - model.vertices_rest.mean(0)
    cam = kinect_camera()
    with torch.no_grad():
        depth = render(scene(theta).vertices, scene.faces, cam).depth[0].numpy()
    rng = np.random.default_rng(0)
    noisy = np.where(depth > 0, depth + rng.normal(0, 1.5, depth.shape), 0).astype(np.float32)
    noisy[200:204, 300:303] = 0  # a sensor dropout inside the hand
    return noisy, cam


@pytest.mark.parametrize("config", [pp.PreprocessConfig(), pp.PreprocessConfig(bilateral=None, hole_size=3)],
                         ids=["default", "no-bilateral"])
def test_cropped_preprocessing_equals_the_whole_image(hand_depth, config, monkeypatch):
    depth, cam = hand_depth
    cropped = pp.preprocess_depth(depth, cam, config)
    monkeypatch.setattr(pp, "_crop_box", lambda valid, margin: (0, valid.shape[0], 0, valid.shape[1]))
    whole = pp.preprocess_depth(depth, cam, config)
    assert len(cropped.edges) > 100
    for name in ("depth", "mask", "points", "normals", "edges", "edge_depth", "raw"):
        a, b = getattr(cropped, name), getattr(whole, name)
        assert a.shape == b.shape, name
        assert torch.allclose(a.double(), b.double(), atol=1e-4), name


def test_crop_box_is_clipped_at_the_image_border():
    valid = np.zeros((10, 12), bool)
    valid[0, 11] = valid[4, 5] = True
    assert pp._crop_box(valid, 3) == (0, 8, 2, 12)


def test_bad_frames_name_the_problem():
    cam = kinect_camera()
    with pytest.raises(pp.EmptyFrameError, match="no valid depth"):
        pp.preprocess_depth(np.zeros((480, 640), np.float32), cam)
    with pytest.raises(pp.EmptyFrameError, match="no valid depth"):
        pp.preprocess_depth(np.full((480, 640), np.nan, np.float32), cam)
    with pytest.raises(ValueError, match=r"depth must have shape \(480, 640\)"):
        pp.preprocess_depth(np.zeros((240, 320), np.float32), cam)
    with pytest.raises(ValueError, match="mask must have shape"):
        pp.preprocess_depth(np.full((480, 640), 500, np.float32), cam, mask=np.ones((2, 2), bool))
