"""The thesis' recording layout (depth/NNN.yml, rgb/NNN.png, joints_2D_GT/NNN.txt) and its conversion."""

import json
import os

import cv2
import numpy as np
import pytest

from torchhand.geometry.camera import kinect_camera
from torchhand.data.layout import SequenceError, read_depth, read_init_pose, read_rgb, read_sequence_info
from torchhand.data.recording import (
    RECORDING_SHAPE,
    convert_recording,
    list_recording_frames,
    read_recording_frame,
    write_recording_sample,
)

H, W = RECORDING_SHAPE


def _bump_depth(k: int, dtype=np.uint16) -> np.ndarray:
    """A wall at 1000 mm with a sphere (radius 80 mm) bulging towards the camera; 0 = hole."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    cx, cy = 300.0 + 10 * k, 240.0
    r2 = ((u - cx) ** 2 + (v - cy) ** 2) * (80.0 / 100.0) ** 2  # 100 px radius ~ 80 mm
    depth = 1000.0 - np.sqrt(np.clip(80.0**2 - r2, 0.0, None))
    depth[:10, :10] = 0.0  # no measurement
    if dtype == np.uint16:
        return np.round(depth).astype(np.uint16)
    return (depth + 0.25).astype(np.float32)  # fractional mm


def _rgb(k: int) -> np.ndarray:
    rng = np.random.default_rng(k)
    return rng.integers(0, 256, (H, W, 3), dtype=np.uint8)


JOINTS = {0: {1: (310.5, 200.25), 2: (330.0, 210.0), 7: (12.0, 470.75)}, 2: {1: (320.5, 201.0)}}


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    root = tmp_path_factory.mktemp("rec") / "seq01"
    depths = [_bump_depth(k) for k in range(3)]
    rgbs = [_rgb(k) for k in range(3)]
    write_recording_sample(root, depths, rgbs, JOINTS)
    return root, depths, rgbs


def test_sample_layout_and_read_back(sample):
    root, depths, rgbs = sample
    assert sorted(p.name for p in (root / "depth").iterdir()) == ["000.yml", "001.yml", "002.yml"]
    assert sorted(p.name for p in (root / "joints_2D_GT").iterdir()) == ["000.txt", "002.txt"]
    fs = cv2.FileStorage(str(root / "depth" / "000.yml"), cv2.FILE_STORAGE_READ)
    assert fs.getNode("depth").mat().dtype == np.uint16  # written as 16U
    fs.release()
    assert list_recording_frames(root) == [0, 1, 2]
    for k in range(3):
        frame = read_recording_frame(root, k)
        assert frame.depth.dtype == np.float32 and frame.depth.shape == (H, W)
        np.testing.assert_array_equal(frame.depth, depths[k].astype(np.float32))
        np.testing.assert_array_equal(frame.rgb, rgbs[k])
        assert frame.joints_2d == JOINTS.get(k)
    assert read_recording_frame(root, 1).joints_2d is None


def test_float32_depth_round_trip_and_convert(tmp_path):
    depths = [_bump_depth(1, np.float32)]
    root = write_recording_sample(tmp_path / "rec", depths)
    fs = cv2.FileStorage(str(root / "depth" / "000.yml"), cv2.FILE_STORAGE_READ)
    assert fs.getNode("depth").mat().dtype == np.float32  # written as 32F
    fs.release()
    frame = read_recording_frame(root, 0)
    np.testing.assert_array_equal(frame.depth, depths[0])  # exact, fractional mm included
    assert frame.rgb is None and frame.joints_2d is None
    out = convert_recording(root, tmp_path / "out", ["hand_right"], progress=False)
    np.testing.assert_array_equal(read_depth(out / "depth" / "000000.png"), np.round(depths[0]))
    assert not (out / "rgb").exists() and not (out / "gt").exists() and not (out / "init_pose.json").exists()
    assert read_sequence_info(out).has_rgb is False


def test_convert(sample, tmp_path):
    root, depths, rgbs = sample
    theta = np.linspace(-0.5, 0.5, 7)
    out = convert_recording(root, tmp_path / "converted", ["hand_right", "ball"], init_theta=theta, progress=False)
    assert out == tmp_path / "converted"
    info = read_sequence_info(out)
    kinect = kinect_camera()
    assert info.name == "seq01" and info.frames == 3 and info.models == ["hand_right", "ball"]
    assert info.has_rgb and info.depth_unit_mm == 1.0
    assert len(info.cameras) == 1
    cam = info.cameras[0]
    assert (cam.width, cam.height) == (640, 480)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (525.0, 525.0, 319.5, 239.5)
    np.testing.assert_array_equal(cam.K.numpy(), kinect.K.numpy())
    assert info.source == {"format": "hands-in-action recording", "path": str(root)}
    np.testing.assert_allclose(read_init_pose(out), theta)
    for k in range(3):
        np.testing.assert_array_equal(read_depth(out / "depth" / f"{k:06d}.png"), np.round(depths[k]))
        np.testing.assert_array_equal(read_rgb(out / "rgb" / f"{k:06d}.png"), rgbs[k])
    ann = json.loads((out / "gt" / "annotations_2d.json").read_text())
    assert ann["frames"] == {str(k): {str(j): list(xy) for j, xy in joints.items()} for k, joints in JOINTS.items()}
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary folders left


def test_frame_numbers_sorted_numerically(tmp_path):
    root = write_recording_sample(tmp_path / "rec", [_bump_depth(k) for k in range(3)], digits=1,
                                  joints_2d={2: {5: (1.0, 2.0)}})
    os.rename(root / "depth" / "2.yml", root / "depth" / "10.yml")
    os.rename(root / "joints_2D_GT" / "2.txt", root / "joints_2D_GT" / "0010.txt")
    os.rename(root / "depth" / "1.yml", root / "depth" / "02.yml")
    assert list_recording_frames(root) == [0, 2, 10]
    assert read_recording_frame(root, 10).joints_2d == {5: (1.0, 2.0)}
    np.testing.assert_array_equal(read_recording_frame(root, 2).depth, _bump_depth(1))
    with pytest.warns(UserWarning, match="renumbered"):
        out = convert_recording(root, tmp_path / "out", ["hand_right"], progress=False)
    info = read_sequence_info(out)
    assert info.frames == 3 and info.source["frame_numbers"] == [0, 2, 10]
    np.testing.assert_array_equal(read_depth(out / "depth" / "000002.png"), _bump_depth(2))
    assert json.loads((out / "gt" / "annotations_2d.json").read_text())["frames"] == {"2": {"5": [1.0, 2.0]}}


def _write_yml(path, **nodes):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for key, value in nodes.items():
        fs.write(key, value)
    fs.release()


@pytest.fixture()
def one_frame(tmp_path):
    return write_recording_sample(tmp_path / "rec", [_bump_depth(0)])


def test_missing_depth_file(one_frame):
    with pytest.raises(SequenceError, match=r"depth.001\.yml.*not found"):
        read_recording_frame(one_frame, 1)


@pytest.mark.parametrize("case, pattern", [
    ("no_node", "no node named 'depth'"),
    ("garbage", "unreadable"),
    ("wrong_size", r"shape \(240, 320\)"),
    ("metres", "metres"),
    ("nan", "NaN"),
])
def test_bad_depth_file(one_frame, case, pattern):
    path = one_frame / "depth" / "000.yml"
    if case == "no_node":
        _write_yml(path, image=_bump_depth(0))
    elif case == "garbage":
        path.write_text("depth: [1, 2\n")
    elif case == "wrong_size":
        _write_yml(path, depth=np.full((240, 320), 900, np.uint16))
    elif case == "metres":
        _write_yml(path, depth=np.full((H, W), 0.8, np.float32))
    elif case == "nan":
        d = np.full((H, W), 900.0, np.float32)
        d[5, 5] = np.nan
        _write_yml(path, depth=d)
    with pytest.raises(SequenceError, match=pattern) as err:
        read_recording_frame(one_frame, 0)
    assert str(path) in str(err.value)
    with pytest.raises(SequenceError, match=pattern):
        convert_recording(one_frame, one_frame.parent / "out", ["hand_right"], progress=False)
    assert not (one_frame.parent / "out").exists()  # nothing half-written


def test_metres_with_depth_scale(one_frame):
    path = one_frame / "depth" / "000.yml"
    _write_yml(path, depth=np.full((H, W), 0.75, np.float32))
    np.testing.assert_allclose(read_recording_frame(one_frame, 0, depth_scale=1000.0).depth, 750.0)


def test_bad_joint_line(one_frame):
    (one_frame / "joints_2D_GT").mkdir()
    (one_frame / "joints_2D_GT" / "000.txt").write_text("1 10 20\n2 oops 3\n")
    with pytest.raises(SequenceError, match=r"000\.txt, line 2"):
        read_recording_frame(one_frame, 0)


def test_refuses_non_empty_out(sample, tmp_path):
    root = sample[0]
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(FileExistsError):
        convert_recording(root, out, ["hand_right"], progress=False)
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]
    assert (out / "keep.txt").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    convert_recording(root, out, ["hand_right"], force=True, progress=False)
    assert read_sequence_info(out).frames == 3 and not (out / "keep.txt").exists()
    with pytest.raises(ValueError, match="must not be"):
        convert_recording(root, root / "converted", ["hand_right"], force=True, progress=False)


def test_sample_writer_refuses_non_empty(one_frame):
    with pytest.raises(FileExistsError):
        write_recording_sample(one_frame, [_bump_depth(0)])
