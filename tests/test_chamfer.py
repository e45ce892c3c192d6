"""Generalised Chamfer matching of silhouette contours (thesis Ch. 3.4)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from torchhand.geometry.chamfer import (CHAMFER_KINDS, ChamferConfig, boundary_pixels, circular_distance,
                                        contour_boxes, contour_marks, match_contour, mark_groups, orientation_bin,
                                        silhouette_contour)
from torchhand.geometry.neighbors import NEIGHBOR_BACKENDS, default_neighbor_backend


def _disc(shape=(200, 300), centre=(150, 100), r=60):
    m = np.zeros(shape, np.uint8)
    cv2.circle(m, centre, r, 1, -1)
    return m


def test_circular_distances_and_bins():
    a = torch.tensor([0.1, 0.1, 0.1])
    b = torch.tensor([2 * math.pi - 0.1, 0.1 + math.pi, 0.6])
    assert torch.allclose(circular_distance(a, b), torch.tensor([0.2, math.pi, 0.5]), atol=1e-6)
    assert torch.allclose(circular_distance(a, b, signed=False), torch.tensor([0.2, 0.0, 0.5]), atol=1e-6)
    phi = torch.tensor([0.0, 2 * math.pi - 0.01, math.pi / 8 + 0.01, math.pi])
    assert orientation_bin(phi, 16).tolist() == [0, 0, 1, 8]
    assert orientation_bin(phi, 8, signed=False).tolist() == [0, 0, 1, 0]
    with pytest.raises(ValueError, match="unknown Chamfer"):
        ChamferConfig("DCH")
    with pytest.raises(ValueError, match="bins"):
        ChamferConfig("DCH-DT3", bins=1)


def test_contour_orientation_is_the_outward_normal():
    m = _disc()
    pix, phi = silhouette_contour(m)
    assert len(pix) > 300 and m[pix[:, 0], pix[:, 1]].all()  # on the silhouette's boundary
    radial = np.arctan2(pix[:, 0] - 100, pix[:, 1] - 150)
    err = np.rad2deg(circular_distance(torch.as_tensor(phi), torch.as_tensor(radial)).numpy())
    assert err.mean() < 5 and err.max() < 12
    # a hole's boundary faces into the hole
    cv2.circle(m, (150, 100), 20, 0, -1)
    pix, phi = silhouette_contour(m)
    r = np.hypot(pix[:, 0] - 100, pix[:, 1] - 150)
    inner = r < 40
    err = np.rad2deg(circular_distance(torch.as_tensor(phi[inner]), torch.as_tensor(
        np.arctan2(pix[inner, 0] - 100, pix[inner, 1] - 150) + np.pi)).numpy())
    assert inner.sum() > 50 and float(err.mean()) < 12  # a small hole: coarser segments
    assert silhouette_contour(np.zeros((10, 10)))[0].shape == (0, 2)
    b = boundary_pixels(torch.as_tensor(_disc() > 0)[None])[0].numpy()
    assert abs(b.sum() - len(silhouette_contour(_disc())[0])) < 0.1 * b.sum()


@pytest.mark.parametrize("kind", CHAMFER_KINDS)
def test_every_distance_pairs_a_shifted_silhouette(kind):
    m = _disc()
    pix, phi = silhouette_contour(m)
    q, qphi = silhouette_contour(np.roll(m, 4, axis=1))  # the model 4 px to the right
    cfg = ChamferConfig(kind)
    marks, image = contour_marks(pix, phi, m.shape, cfg)
    res = match_contour(cfg, torch.as_tensor(marks)[None], torch.as_tensor(image)[None], torch.as_tensor(q)[None],
                        torch.as_tensor(qphi)[None], torch.ones(1, len(q), dtype=torch.bool))
    assert res.pixel.shape[1] == (2 if kind == "DCH-Quant2" else 1) * len(q)
    ok = res.valid[0]
    assert ok.float().mean() > (0.45 if kind == "DCH-Quant2" else 0.9)
    d = (res.pixel[0][ok] - torch.as_tensor(q)[res.source[0][ok]]).double().norm(dim=-1)
    assert float(d.median()) <= 4.5 + (2.0 if kind == "DCH-Quant2" else 0.0)
    assert bool((marks[res.pixel[0][ok][:, 0], res.pixel[0][ok][:, 1]] >= 0).all())  # contour pixels only
    # the mean pull of the pairs points back left, towards the data
    pull = (res.pixel[0][ok] - torch.as_tensor(q)[res.source[0][ok]]).double().mean(0)
    assert float(pull[1]) < -1.0


@pytest.mark.parametrize("kind", CHAMFER_KINDS)
def test_boxes_computed_once_give_the_same_pairs(kind):
    """The boxes a tracker computes once per frame (contour_boxes) pair exactly as the
    boxes match_contour computes itself; backends that do not use them get None."""
    m = _disc()
    pix, phi = silhouette_contour(m)
    q, qphi = silhouette_contour(np.roll(m, 7, axis=0))
    cfg = ChamferConfig(kind)
    marks, image = contour_marks(pix, phi, m.shape, cfg)
    assert int(marks.max()) + 1 <= mark_groups(cfg) and (mark_groups(cfg) > 1) == (kind in ("DCH-Quant", "DCH-Quant2",
                                                                                             "DCH-DT3"))
    marks, image = torch.as_tensor(marks)[None], torch.as_tensor(image)[None]
    args = (torch.as_tensor(q)[None], torch.as_tensor(qphi)[None], torch.ones(1, len(q), dtype=torch.bool))
    backend = default_neighbor_backend()
    boxes = contour_boxes(cfg, marks, backend)
    assert (boxes is None) == (backend != "warp")
    if boxes is not None:
        assert boxes.shape == (mark_groups(cfg), 4)
    want = match_contour(cfg, marks, image, *args, backend=backend)
    got = match_contour(cfg, marks, image, *args, backend=backend, boxes=boxes)
    assert all(torch.equal(a, b) for a, b in zip(got, want)) and int(got.valid.sum()) > 100
    assert {contour_boxes(cfg, marks, b) is None for b in NEIGHBOR_BACKENDS if b != "warp"} == {True}


def test_orientation_decides_the_pair():
    # two parallel edges 6 px apart facing opposite ways; a rim point facing left, 2 px
    # from the right-facing edge, pairs with it under CH but with the left-facing one
    # under the directional distances
    H, W = 40, 40
    pix = np.array([[r, 20] for r in range(H)] + [[r, 26] for r in range(H)])
    phi = np.array([math.pi] * H + [0.0] * H)  # column 20 faces left, column 26 right
    q = torch.tensor([[[20, 24]]])
    qphi = torch.tensor([[math.pi]])
    ok = torch.ones(1, 1, dtype=torch.bool)
    cols = {}
    for kind in CHAMFER_KINDS:
        cfg = ChamferConfig(kind, lam=25.0)
        marks, image = contour_marks(pix, phi, (H, W), cfg)
        res = match_contour(cfg, torch.as_tensor(marks)[None], torch.as_tensor(image)[None], q, qphi, ok)
        cols[kind] = [int(c) for c, v in zip(res.pixel[0, :, 1], res.valid[0]) if v]
    assert cols["CH"] == [26]
    assert cols["DCH-Thres"] == []  # the nearest pixel faces the other way: dropped
    assert cols["DCH-Quant"] == [20] and cols["DCH-DT3"] == [20]
    assert 20 in cols["DCH-Quant2"]
    # DT3 without the orientation term is CH
    cfg = ChamferConfig("DCH-DT3", lam=0.0)
    marks, image = contour_marks(pix, phi, (H, W), cfg)
    assert int(match_contour(cfg, torch.as_tensor(marks)[None], torch.as_tensor(image)[None], q, qphi,
                             ok).pixel[0, 0, 1]) == 26
