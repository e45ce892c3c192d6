"""The HO-3D reader (torchhand.data.datasets.ho3d) on a tiny sample built here: a shipped
hand rendered at an HO-3D-like camMat, its depth packed into R/G of 8-bit PNGs as HO-3D
does, and meta pickles of numpy arrays in HO-3D's joint order and OpenGL frame (metres)."""

from __future__ import annotations

import pickle
import re
import shutil

import cv2
import numpy as np
import pytest
import torch

from torchhand.data.datasets.ho3d import DEPTH_SCALE_M, HO3D_TO_STANDARD, import_ho3d
from torchhand.data.layout import SequenceError, SequenceLayout, read_joints21, read_sequence_info
from torchhand.geometry.camera import Camera
from torchhand.geometry.render import render
from torchhand.io.foreign_files import ForeignFileError
from torchhand.model.joints21 import standard_joints

FRAMES = 2
K = np.array([[614.6, 0.0, 312.4], [0.0, 614.9, 241.2], [0.0, 0.0, 1.0]])
CALLS = []


def _record(*args):
    CALLS.append(args)


class _Crafted:
    def __reduce__(self):
        return (_record, ("ran",))


@pytest.fixture(scope="module")
def rendered():
    from torchhand import load_model

    model = load_model("hand_right", dtype=torch.float64)
    theta = model.zero_pose(FRAMES)
    theta[:, :3] = torch.tensor([20.0, -10.0, 500.0], dtype=theta.dtype) - model.vertices_rest.mean(0)
    theta[1, 3:6] = torch.tensor([0.2, -0.3, 0.1], dtype=theta.dtype)
    cam = Camera.from_intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], 640, 480, name="k").to(dtype=theta.dtype)
    with torch.no_grad():
        posed = model(theta)
        depth = render(posed.vertices, model.faces, cam, normals=False).depth.numpy()
        joints = standard_joints(posed, model).numpy()
    return depth, joints  # (F, 480, 640) mm float, (F, 21, 3) mm standard order


def _pack(path, depth_mm):
    packed = np.round(depth_mm / (DEPTH_SCALE_M * 1000.0)).astype(np.int64)
    bgr = np.stack([np.zeros_like(packed), packed >> 8, packed & 255], -1).astype(np.uint8)
    assert cv2.imwrite(str(path), bgr)


def _meta(joints_mm, camMat=K):
    ho3d = np.empty((21, 3))
    ho3d[list(HO3D_TO_STANDARD)] = joints_mm
    return {"camMat": camMat.copy(), "handJoints3D": ho3d / 1000.0 * np.array([1.0, -1.0, -1.0]),
            "objName": "006_mustard_bottle"}


def _write(folder, depth, joints, metas=None):
    for sub in ("rgb", "depth", "meta"):
        (folder / sub).mkdir(parents=True)
    for k in range(FRAMES):
        _pack(folder / "depth" / f"{k:04d}.png", depth[k])
        assert cv2.imwrite(str(folder / "rgb" / f"{k:04d}.jpg"), np.full((480, 640, 3), 90, np.uint8))
        with open(folder / "meta" / f"{k:04d}.pkl", "wb") as f:
            pickle.dump(metas[k] if metas else _meta(joints[k]), f, protocol=2)
    return folder


@pytest.fixture
def sample(tmp_path, rendered):
    depth, joints = rendered
    return _write(tmp_path / "train" / "ABF10", depth, joints), depth, joints


def test_depth_joints_and_frame(sample, tmp_path):
    src, depth, joints = sample
    info = import_ho3d(src, tmp_path / "seq")
    seq = SequenceLayout(tmp_path / "seq")
    assert info.frames == FRAMES and info.models == ["hand_right"] and info.has_rgb
    back = read_sequence_info(seq.root)
    cam = back.cameras[0]
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == pytest.approx((614.6, 614.9, 312.4, 241.2, 640, 480))
    for k in range(FRAMES):
        stored = cv2.imread(str(seq.depth(k)), cv2.IMREAD_UNCHANGED)
        assert stored.dtype == np.uint16
        assert ((stored > 0) == (depth[k] > 0)).all()
        assert np.abs(stored - depth[k]).max() <= 0.5 + 0.125  # mm, rounded after the 0.125 mm packing
        assert seq.rgb(k).is_file()
    j3, j2 = read_joints21(seq.gt)
    assert j3.shape == (FRAMES, 1, 21, 3) and j2.shape == (FRAMES, 1, 21, 2)
    assert np.abs(j3[:, 0] - joints).max() < 1e-3  # standard order, mm, camera frame
    for k in range(FRAMES):  # the joints project onto the hand
        for u, v in j2[k, 0]:
            window = depth[k, int(round(v)) - 3:int(round(v)) + 4, int(round(u)) - 3:int(round(u)) + 4]
            assert (window > 0).any(), (u, v)
    assert back.source["format"] == "ho3d" and back.source["joints"] == "21"


def test_root_only_metas(tmp_path, rendered):
    depth, joints = rendered
    metas = [{"camMat": K, "handJoints3D": joints[k, 0] / 1000.0 * np.array([1.0, -1.0, -1.0])} for k in range(FRAMES)]
    src = _write(tmp_path / "evaluation" / "SM1", depth, joints, metas)
    info = import_ho3d(src, tmp_path / "seq")
    j3, _ = read_joints21(SequenceLayout(tmp_path / "seq").gt)
    assert np.abs(j3[:, 0, 0] - joints[:, 0]).max() < 1e-6 and np.isnan(j3[:, 0, 1:]).all()
    assert info.source["joints"].startswith("root only")


def test_crafted_pickle_is_refused_unrun(sample, tmp_path):
    src, _, _ = sample
    bad = src / "meta" / "0001.pkl"
    with open(bad, "wb") as f:
        pickle.dump({"camMat": K, "handJoints3D": _Crafted()}, f)
    with pytest.raises(ForeignFileError, match=re.escape(str(bad))):
        import_ho3d(src, tmp_path / "seq")
    assert CALLS == [] and not (tmp_path / "seq").exists()


@pytest.mark.parametrize("case, message", [
    ("grey", "0000.png: an HO-3D depth frame is an 8-bit PNG with 3 channels (depth in R and G), got uint16 with 1 channel(s)"),
    ("no_cam", "0001.pkl: camMat must be a finite 3x3 matrix, got none"),
    ("joints", "0001.pkl: handJoints3D must have shape (21, 3) or (3,) (the root joint), got (20, 3)"),
    ("cam_change", "0001.pkl: camMat differs from that of "),
    ("count", ": 2 depth frames but 1 meta pickles"),
    ("rgb_count", ": 2 depth frames but 1 colour frames"),
])
def test_bad_input_is_named(sample, tmp_path, case, message):
    src, _, joints = sample
    meta = _meta(joints[1])
    if case == "grey":
        assert cv2.imwrite(str(src / "depth" / "0000.png"), np.ones((480, 640), np.uint16))
    elif case == "count":
        (src / "meta" / "0001.pkl").unlink()
    elif case == "rgb_count":
        (src / "rgb" / "0001.jpg").unlink()
    else:
        if case == "no_cam":
            del meta["camMat"]
        elif case == "joints":
            meta["handJoints3D"] = meta["handJoints3D"][:20]
        else:
            meta["camMat"] = K + np.diag([1.0, 0.0, 0.0])
        with open(src / "meta" / "0001.pkl", "wb") as f:
            pickle.dump(meta, f)
    with pytest.raises(SequenceError, match=re.escape(message)):
        import_ho3d(src, tmp_path / "seq")
    assert not (tmp_path / "seq").exists()


def test_refuses_to_overwrite(sample, tmp_path):
    src, _, _ = sample
    out = tmp_path / "seq"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    with pytest.raises(FileExistsError, match="not empty"):
        import_ho3d(src, out)
    assert (out / "keep.txt").read_text() == "x"
    import_ho3d(src, out, force=True)
    assert not (out / "keep.txt").exists() and (out / "sequence.json").is_file()


def test_cli(sample, tmp_path, capsys):
    from torchhand.app.cli import main

    src, _, _ = sample
    assert main(["import", "--format", "ho3d", str(src), "--out", str(tmp_path / "seq")]) == 0
    assert "imported 2 frames of ho3d sequence" in capsys.readouterr().out
    shutil.rmtree(src / "meta")
    assert main(["import", "--format", "ho3d", str(src), "--out", str(tmp_path / "x")]) == 2
    assert main(["import", "--format", "ho3d", str(src), "--out", str(tmp_path / "y"), "--camera", "2"]) == 2
