"""The on-disk sequence layout (datasets/README.md): image, JSON and gt/ round trips, and
errors that name the offending file."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
import torch

from torchhand.geometry.camera import Camera
from torchhand.data.layout import (
    FORMAT,
    Poses,
    SequenceError,
    SequenceInfo,
    camera_dir,
    frame_name,
    read_depth,
    read_init_pose,
    read_poses,
    read_rgb,
    read_sequence_info,
    write_depth,
    write_poses,
    write_rgb,
    write_sequence_info,
)


def _rot(axis, deg):
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    x, y, z = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    return np.eye(3) + s * K + (1 - c) * K @ K


def _T(axis=(0.3, -1.0, 0.2), deg=25.0, t=(120.0, -35.5, 410.25)):
    T = np.eye(4)
    T[:3, :3] = _rot(axis, deg)
    T[:3, 3] = t
    return T


# ------------------------------------------------------------------ names and folders
def test_frame_name_and_camera_dir(tmp_path):
    assert frame_name(0) == "000000.png"
    assert frame_name(1234) == "001234.png"
    assert camera_dir(tmp_path, 0) == tmp_path
    assert camera_dir(tmp_path, 2) == tmp_path / "cam2"


# ------------------------------------------------------------------ depth
def test_depth_round_trip_mm_rounding_and_invalid(tmp_path):
    d = np.full((6, 8), 750.0)
    d[0, 0] = 500.4  # rounds down
    d[0, 1] = 500.6  # rounds up
    d[1, 0] = 0.0  # no measurement
    d[1, 1] = np.nan  # -> 0
    d[1, 2] = -12.0  # -> 0 (clipped)
    d[1, 3] = np.inf  # -> 0
    d[2, 0] = 70000.0  # clipped at 65535
    d[3, 3] = 1234.49
    p = tmp_path / "d.png"
    write_depth(p, d)
    raw = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and raw.shape == (6, 8)
    back = read_depth(p)
    assert back.dtype == np.float32 and back.shape == (6, 8)
    assert back[0, 0] == 500 and back[0, 1] == 501
    assert back[1, 0] == 0 and back[1, 1] == 0 and back[1, 2] == 0 and back[1, 3] == 0
    assert back[2, 0] == 65535
    assert back[3, 3] == 1234
    assert back[5, 7] == 750
    # everything is within half a millimetre of the finite, in-range input
    ok = np.isfinite(d) & (d > 0) & (d < 65535)
    assert np.abs(back[ok] - d[ok]).max() <= 0.5


def test_depth_unit_scales_values(tmp_path):
    p = tmp_path / "d.png"
    write_depth(p, np.full((4, 4), 4000.0))
    assert np.all(read_depth(p, unit_mm=0.25) == 1000.0)


def test_depth_all_invalid_is_accepted(tmp_path):
    p = tmp_path / "d.png"
    write_depth(p, np.zeros((4, 5)))
    assert np.all(read_depth(p) == 0)


def test_depth_missing_file_names_it(tmp_path):
    p = tmp_path / "depth" / "000003.png"
    with pytest.raises(SequenceError, match="000003.png"):
        read_depth(p)


def test_depth_garbage_bytes_names_file(tmp_path):
    p = tmp_path / "000000.png"
    p.write_bytes(b"this is not a png\x00\x01\x02" * 20)
    with pytest.raises(SequenceError) as err:
        read_depth(p)
    assert str(p) in str(err.value)


def test_depth_8bit_png_is_rejected_naming_file(tmp_path):
    p = tmp_path / "eight.png"
    cv2.imwrite(str(p), np.full((5, 5), 200, np.uint8))
    with pytest.raises(SequenceError) as err:
        read_depth(p)
    assert str(p) in str(err.value) and "16-bit" in str(err.value)


def test_depth_colour_8bit_png_is_rejected(tmp_path):
    p = tmp_path / "colour.png"
    cv2.imwrite(str(p), np.full((5, 5, 3), 200, np.uint8))
    with pytest.raises(SequenceError, match="16-bit"):
        read_depth(p)


def test_depth_16bit_three_channel_png_is_rejected(tmp_path):
    p = tmp_path / "colour16.png"
    img = np.zeros((4, 4, 3), np.uint16)
    img[..., 0], img[..., 1], img[..., 2] = 1000, 2000, 3000
    assert cv2.imwrite(str(p), img)
    assert cv2.imread(str(p), cv2.IMREAD_UNCHANGED).shape == (4, 4, 3)
    with pytest.raises(SequenceError, match="single-channel"):
        read_depth(p)


def test_depth_in_metres_is_rejected_naming_file(tmp_path):
    p = tmp_path / "metres.png"
    m = np.tile(np.arange(4, dtype=np.uint16), (6, 2))  # 0..3: "metres"
    cv2.imwrite(str(p), m)
    with pytest.raises(SequenceError) as err:
        read_depth(p)
    assert str(p) in str(err.value)
    assert "metres" in str(err.value)
    assert "depth_unit_mm" in str(err.value)


# ------------------------------------------------------------------ rgb
def test_rgb_round_trip_keeps_channel_order(tmp_path):
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (7, 9, 3), dtype=np.uint8)
    img[0, 0] = (255, 0, 0)  # pure red
    p = tmp_path / "rgb.png"
    write_rgb(p, img)
    back = read_rgb(p)
    assert back.dtype == np.uint8 and back.shape == (7, 9, 3)
    np.testing.assert_array_equal(back, img)
    # stored as BGR on disk (OpenCV convention): red is the last channel there
    assert tuple(cv2.imread(str(p))[0, 0]) == (0, 0, 255)


def test_rgb_missing_or_garbage_names_file(tmp_path):
    with pytest.raises(SequenceError, match="nothere.png"):
        read_rgb(tmp_path / "nothere.png")
    p = tmp_path / "junk.png"
    p.write_bytes(b"\x89PNG but not really")
    with pytest.raises(SequenceError, match="junk.png"):
        read_rgb(p)


# ------------------------------------------------------------------ sequence.json / init_pose.json
def _info():
    cam0 = Camera.from_intrinsics(525.0, 526.5, 319.5, 239.5, 640, 480, name="kinect", dtype=torch.float64)
    cam1 = Camera.from_intrinsics(600.0, 600.0, 160.25, 120.75, 320, 240, T_cw=torch.as_tensor(_T()), name="side",
                                  dtype=torch.float64)
    return SequenceInfo("seq_x", [cam0, cam1], ["hand_right", "ball"], 17, fps=15.0, depth_unit_mm=1.0,
                        has_rgb=True, source={"format": "test", "seed": 3})


def test_sequence_info_round_trip(tmp_path):
    info = _info()
    theta0 = np.linspace(-1, 1, 7)
    write_sequence_info(tmp_path, info, init_theta=theta0)
    d = json.loads((tmp_path / "sequence.json").read_text())
    assert d["format"] == FORMAT == "torchhand-sequence/1"
    back = read_sequence_info(tmp_path)
    assert back.name == "seq_x" and back.frames == 17 and back.fps == 15.0
    assert back.models == ["hand_right", "ball"] and back.has_rgb is True
    assert back.depth_unit_mm == 1.0 and back.source == {"format": "test", "seed": 3}
    assert [c.name for c in back.cameras] == ["kinect", "side"]
    assert [(c.width, c.height) for c in back.cameras] == [(640, 480), (320, 240)]
    for c, ref in zip(back.cameras, info.cameras):
        np.testing.assert_allclose(c.K.double().numpy(), ref.K.numpy(), rtol=1e-6)
        np.testing.assert_allclose(c.T_cw.double().numpy(), ref.T_cw.numpy(), rtol=1e-6, atol=1e-4)
    # the non-identity extrinsics survive (not replaced by the identity)
    assert not np.allclose(back.cameras[1].T_cw.double().numpy(), np.eye(4))
    assert np.allclose(back.cameras[0].T_cw.double().numpy(), np.eye(4))
    # a point maps the same way through the stored camera
    X = torch.tensor([[[10.0, -20.0, 700.0]]], dtype=torch.float64)
    np.testing.assert_allclose(back.cameras[1].project(X.float()).double().numpy(),
                               info.cameras[1].project(X).numpy(), atol=1e-3)
    np.testing.assert_array_equal(read_init_pose(tmp_path), theta0)


def test_init_pose_is_optional_to_write_but_required_to_read(tmp_path):
    write_sequence_info(tmp_path, _info())
    assert (tmp_path / "sequence.json").is_file()
    assert not (tmp_path / "init_pose.json").exists()
    with pytest.raises(SequenceError, match="init_pose.json"):
        read_init_pose(tmp_path)


def test_init_pose_with_nan_is_rejected(tmp_path):
    (tmp_path / "init_pose.json").write_text(json.dumps({"theta": [0.0, float("nan")]}))
    with pytest.raises(SequenceError, match="init_pose.json"):
        read_init_pose(tmp_path)


def test_missing_sequence_json_names_file(tmp_path):
    with pytest.raises(SequenceError) as err:
        read_sequence_info(tmp_path)
    assert str(tmp_path / "sequence.json") in str(err.value)


def test_wrong_format_string_names_file(tmp_path):
    write_sequence_info(tmp_path, _info())
    d = json.loads((tmp_path / "sequence.json").read_text())
    d["format"] = "torchhand-sequence/0"
    (tmp_path / "sequence.json").write_text(json.dumps(d))
    with pytest.raises(SequenceError) as err:
        read_sequence_info(tmp_path)
    msg = str(err.value)
    assert str(tmp_path / "sequence.json") in msg and "torchhand-sequence/0" in msg and FORMAT in msg


def test_invalid_json_and_missing_keys_name_file(tmp_path):
    (tmp_path / "sequence.json").write_text("{not json")
    with pytest.raises(SequenceError, match="sequence.json"):
        read_sequence_info(tmp_path)
    (tmp_path / "sequence.json").write_text(json.dumps({"format": FORMAT, "name": "x", "frames": 1}))
    with pytest.raises(SequenceError, match="models"):
        read_sequence_info(tmp_path)


def test_non_rigid_camera_is_rejected(tmp_path):
    write_sequence_info(tmp_path, _info())
    d = json.loads((tmp_path / "sequence.json").read_text())
    d["cameras"][1]["T_cw"][0][0] = 2.0  # a scale: not a rigid transform
    (tmp_path / "sequence.json").write_text(json.dumps(d))
    with pytest.raises(SequenceError, match="sequence.json"):
        read_sequence_info(tmp_path)


# ------------------------------------------------------------------ gt/ poses
def _poses(N=4, C=2, P=3, D=5, valid=None):
    rng = np.random.default_rng(1)
    return Poses(rng.normal(size=(N, D)), rng.normal(size=(N, C, P, 3)) * 100, rng.normal(size=(N, C, P, 2)) * 50,
                 ["hand_right"], [f"dof{k}" for k in range(D)], [f"hand_right/kp{k}" for k in range(P)], valid)


def test_poses_round_trip_with_valid_flags(tmp_path):
    p = _poses(valid=np.array([True, False, True, False]))
    write_poses(tmp_path / "gt", p)
    assert sorted(f.name for f in (tmp_path / "gt").iterdir()) == [
        "keypoints_2d.npy", "keypoints_3d.npy", "meta.json", "theta.npy"]
    meta = json.loads((tmp_path / "gt" / "meta.json").read_text())
    assert meta["frames"] == 4 and meta["valid"] == [True, False, True, False]
    back = read_poses(tmp_path / "gt")
    np.testing.assert_array_equal(back.theta, p.theta)
    np.testing.assert_array_equal(back.keypoints_3d, p.keypoints_3d)
    np.testing.assert_array_equal(back.keypoints_2d, p.keypoints_2d)
    assert back.theta.dtype == np.float64 and back.keypoints_3d.shape == (4, 2, 3, 3)
    assert back.models == p.models and back.dof_names == p.dof_names and back.keypoint_names == p.keypoint_names
    assert back.valid.dtype == bool
    np.testing.assert_array_equal(back.valid, [True, False, True, False])


def test_poses_default_valid_all_true(tmp_path):
    p = _poses()
    assert p.valid.dtype == bool and p.valid.all()
    write_poses(tmp_path, p)
    meta = json.loads((tmp_path / "meta.json").read_text())
    del meta["valid"]  # older files without flags: every frame valid
    (tmp_path / "meta.json").write_text(json.dumps(meta))
    assert read_poses(tmp_path).valid.tolist() == [True] * 4


def test_poses_frame_mismatch_in_memory():
    with pytest.raises(ValueError, match="frames"):
        Poses(np.zeros((3, 2)), np.zeros((2, 1, 1, 3)), np.zeros((2, 1, 1, 2)), [], [], [])


def test_read_poses_missing_theta_names_it(tmp_path):
    write_poses(tmp_path, _poses())
    (tmp_path / "theta.npy").unlink()
    with pytest.raises(SequenceError) as err:
        read_poses(tmp_path)
    assert "theta.npy" in str(err.value) and str(tmp_path) in str(err.value)


def test_read_poses_corrupt_array_names_it(tmp_path):
    write_poses(tmp_path, _poses())
    (tmp_path / "keypoints_3d.npy").write_bytes(b"garbage")
    with pytest.raises(SequenceError, match="keypoints_3d.npy"):
        read_poses(tmp_path)


def test_read_poses_inconsistent_frame_counts_is_sequence_error_naming_folder(tmp_path):
    p = _poses()
    write_poses(tmp_path, p)
    np.save(tmp_path / "theta.npy", p.theta[:3])  # 3 poses, 4 frames of keypoints
    with pytest.raises(SequenceError) as err:
        read_poses(tmp_path)
    assert str(tmp_path) in str(err.value)
