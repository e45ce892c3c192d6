"""Multi-view colour synthesis for Ballan et al.'s tracker: the camera ring, the nails,
the shading, the paper's noise protocol and ``torchhand synth --views``."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from torchhand.app.cli import main
from torchhand.data.ballan_protocol import BallanProtocol, protocol, simulate_detections, structural_noise
from torchhand.data.layout import camera_dir, frame_name, read_rgb, read_sequence_info
from torchhand.data.synth import demo_motion, with_camera_ring, write_synthetic_sequence
from torchhand.geometry.camera_rig import camera_ring, look_at
from torchhand.model.fingertips import fingertip_faces, nail_faces, nail_vertices


def test_camera_ring_looks_at_the_centre():
    cams = camera_ring(8, 650.0)
    assert len(cams) == 8 and torch.equal(cams[0].T_cw, torch.eye(4, dtype=torch.float64))
    pts = torch.tensor([[[0.0, 0.0, 650.0], [0.0, -80.0, 650.0]]], dtype=torch.float64)
    centres = []
    for cam in cams:
        uv = cam.project(pts)[0]
        assert torch.allclose(uv[0], torch.tensor([319.5, 239.5], dtype=torch.float64), atol=1e-6)
        assert uv[1, 1] < uv[0, 1] - 40  # up stays up in every view
        assert abs(float((cam.centre - pts[0, 0]).norm()) - 650.0) < 1e-6
        centres.append(cam.centre)
    # all around: the azimuths of the centres about the vertical cover the circle
    az = sorted(np.degrees(np.arctan2(float(c[0]), 650.0 - float(c[2]))) % 360 for c in centres)
    assert np.allclose(np.diff(az), 45.0, atol=1e-6)
    with pytest.raises(ValueError, match="coincide"):
        look_at((0, 0, 0), (0, 0, 0))
    with pytest.raises(ValueError, match="parallel"):
        look_at((0, 0, 0), (0, 1, 0))
    with pytest.raises(ValueError, match="count"):
        camera_ring(0)


def test_nails_are_on_the_back_of_the_fingers():
    frames = demo_motion(slice(0, 1))
    scene = frames.scene
    tips = fingertip_faces(scene)
    nail = nail_faces(scene)
    for p in range(len(tips.names)):  # a patch of each fingertip, not all of it
        on = int((nail & (tips.face_tip == p)).sum())
        assert 0.15 * int((tips.face_tip == p).sum()) < on < 0.6 * int((tips.face_tip == p).sum())
    ids = nail_vertices(scene)
    assert len(ids) == 10 and len(set(ids.tolist())) == 10
    for v in ids.tolist():  # each salient vertex is a corner of a nail face
        assert bool(nail[(scene.faces == v).any(1)].any())
    # the demo's first frame shows the backs of both hands to camera 0: the nails face
    # it, and the camera opposite sees none of them
    from torchhand.data.synth import _salient_in_view
    from torchhand.geometry.render import Renderer

    cams = with_camera_ring(frames, 8).cameras
    with torch.no_grad():
        posed = scene(frames.theta[:1].to(scene.lower.dtype))
    r = Renderer(scene.faces, scene.face_model_id, scene.face_bone_id)
    seen = []
    for k in (0, 4):
        cam = cams[k].to(dtype=posed.vertices.dtype)
        seen.append(int(_salient_in_view(posed.vertices[:, ids], cam, r(posed.vertices, cam).depth)[1].sum()))
    assert seen[0] >= 8 and seen[1] == 0


def test_detections_follow_the_protocol():
    p = BallanProtocol()
    rng = np.random.default_rng(0)
    truth = rng.uniform(0, 50000, (5000, 2))  # far apart: an outlier is never near another point
    det = simulate_detections(truth, rng, p)
    from scipy.spatial import cKDTree

    d, _ = cKDTree(truth).query(det)
    near = d < 25  # 5 sigma of the jitter
    assert abs(near.sum() / len(truth) - 0.7) < 0.03  # the detection rate
    assert abs((~near).sum() / len(truth) - 0.1) < 0.02  # about one outlier per ten points
    assert d.max() < 200 + 30
    assert abs(np.std(det[near] - truth[cKDTree(truth).query(det[near])[1]]) - 5.0) < 0.3
    inside = simulate_detections(truth - 500, np.random.default_rng(1), p, size=(640, 480))
    assert (inside >= -0.5).all() and (inside[:, 0] < 639.5).all() and (inside[:, 1] < 479.5).all()
    img = np.full((480, 640, 3), 128, np.uint8)
    noisy, mask = structural_noise(img, np.random.default_rng(2), p)
    assert 0.15 < mask.mean() < 0.6 and (noisy[~mask] == 128).all() and (noisy[mask] != 128).mean() > 0.9
    with pytest.raises(ValueError, match="detection_rate"):
        BallanProtocol(detection_rate=1.5)
    with pytest.raises(ValueError, match="unknown noise protocol"):
        protocol("hope")
    with pytest.raises(ValueError, match="uint8"):
        structural_noise(img.astype(np.float32), rng, p)


@pytest.mark.slow
def test_synth_views_with_the_protocol(tmp_path):
    frames = with_camera_ring(demo_motion(slice(0, 2)), 3)
    clean = write_synthetic_sequence(frames, tmp_path / "clean", colour="shaded", depth=False, progress=False)
    noisy = write_synthetic_sequence(frames, tmp_path / "noisy", colour="shaded", depth=False, protocol="ballan",
                                     progress=False)
    info = read_sequence_info(noisy)
    assert len(info.cameras) == 3 and not info.has_depth and info.has_rgb
    assert info.source["protocol"]["name"] == "ballan"
    for c in range(3):
        d = camera_dir(noisy, c)
        assert not (d / "depth").exists()
        for k in range(2):
            a, b = read_rgb(camera_dir(clean, c) / "rgb" / frame_name(k)), read_rgb(d / "rgb" / frame_name(k))
            import cv2

            circles = cv2.imread(str(d / "occluders" / frame_name(k)), cv2.IMREAD_GRAYSCALE) > 0
            assert a.shape == (480, 640, 3) and circles.mean() > 0.1
            assert np.array_equal(a[~circles], b[~circles]) and not np.array_equal(a, b)
        dets = json.loads((d / "salient.json").read_text())["frames"]
        assert len(dets) == 2
    vis = np.load(noisy / "gt" / "salient_visible.npy")
    uv = np.load(noisy / "gt" / "salient_2d.npy")
    assert vis.shape == (2, 3, 10) and uv.shape == (2, 3, 10, 2) and vis[:, 0].sum() >= 16
    # camera 0's detections lie near its visible nail centres (or are the outliers)
    det0 = np.asarray(json.loads((noisy / "salient.json").read_text())["frames"][0]).reshape(-1, 2)
    d = np.linalg.norm(det0[:, None] - uv[0, 0][vis[0, 0]][None], axis=-1).min(1)
    assert len(det0) >= 3 and (d < 25).mean() >= 0.6
    # the background differs between views and is textured
    bg = read_rgb(camera_dir(clean, 1) / "rgb" / frame_name(0)).astype(float)
    assert bg.std() > 10


@pytest.mark.slow
def test_synth_views_command_line(tmp_path, capsys):
    assert main(["synth", "--demo", "--frames", ":2", "--views", "2", "--depth", "--out", str(tmp_path / "s")]) == 0
    assert "2 colour and depth views" in capsys.readouterr().out
    info = read_sequence_info(tmp_path / "s")
    assert info.has_depth and (tmp_path / "s" / "cam1" / "depth" / frame_name(1)).is_file()
    # the tracker refuses colour-only views with a clear message, and the two flags need --views
    assert main(["synth", "--demo", "--frames", ":2", "--views", "2", "--out", str(tmp_path / "c")]) == 0
    capsys.readouterr()
    assert main(["track", str(tmp_path / "c"), "--out", str(tmp_path / "t")]) == 1
    err = capsys.readouterr().err
    name = read_sequence_info(tmp_path / "c").name
    assert (f"torchhand track: error: {name}: {tmp_path / 'c'}: colour views only (sequence.json has_depth false, "
            "no depth/), but the energy's terms read depth") in err
    assert "(--energy E+C+O)" in err and "; nothing written" in err
    assert "torchhand track: 1 of 1 sequences failed" in err
    assert not (tmp_path / "t" / name).exists()
    # larger images of the same ring: 1.5 x 640x480, the focal length scaled with them
    assert main(["synth", "--demo", "--frames", ":1", "--views", "2", "--image-scale", "1.5",
                 "--out", str(tmp_path / "big")]) == 0
    big = read_sequence_info(tmp_path / "big")
    assert [(c.width, c.height, c.fx) for c in big.cameras] == [(960, 720, 787.5)] * 2
    assert read_rgb(camera_dir(tmp_path / "big", 1) / "rgb" / frame_name(0)).shape == (720, 960, 3)
    assert main(["synth", "--demo", "--frames", ":1", "--views", "2", "--image-scale", "0",
                 "--out", str(tmp_path / "y")]) == 2
    assert "--image-scale" in capsys.readouterr().err and not (tmp_path / "y").exists()
    for bad in (["--protocol", "ballan"], ["--depth"], ["--image-scale", "2"]):
        assert main(["synth", "--demo", "--frames", ":2", "--out", str(tmp_path / "x"), *bad]) == 2
        assert "--views" in capsys.readouterr().err
        assert not (tmp_path / "x").exists()
