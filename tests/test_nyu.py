"""The NYU hand pose dataset reader (torchhand.data.datasets.nyu) on a tiny sample built
here: a shipped hand rendered at the NYU intrinsics, its depth packed into G/B of 8-bit
PNGs and its joints written to joint_data.mat in NYU's convention (y up)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.io
import torch

from torchhand.data.datasets.nyu import (NYU_EVAL_JOINTS, NYU_EVAL_NAMES, NYU_INTRINSICS, NYU_JOINT_NAMES,
                                         NYU_TO_STANDARD21, import_nyu, nyu_camera, read_nyu_depth)
from torchhand.data.layout import SequenceError, SequenceLayout, read_depth, read_sequence_info
from torchhand.geometry.render import render
from torchhand.model.joints21 import STANDARD_JOINT_NAMES, standard_joints

FRAMES = 3

#: the standard joint standing in for each of NYU's 36 in the sample (PALM_1/2 and the
#: segment ends that the subset leaves out get nearby joints)
_SEGMENT = {("3", "A"): "tip", ("3", "B"): "dip", ("2", "A"): "dip", ("2", "B"): "pip", ("1", "A"): "pip",
            ("1", "B"): "mcp"}
_THUMB = {"tip": "tip", "dip": "ip", "pip": "mcp", "mcp": "cmc"}
_FINGER = {"F1": "little", "F2": "ring", "F3": "middle", "F4": "index", "TH": "thumb"}
_PALM = ["index_mcp", "little_mcp", "wrist", "middle_mcp", "ring_mcp", "wrist"]


def _stand_in(name: str) -> str:
    if name.startswith("PALM_"):
        return _PALM[int(name[-1]) - 1]
    finger, knu, end = name.split("_")
    joint = _SEGMENT[(knu[-1], end)]
    return f"thumb_{_THUMB[joint]}" if finger == "TH" else f"{_FINGER[finger]}_{joint}"


STAND_INS = [STANDARD_JOINT_NAMES.index(_stand_in(n)) for n in NYU_JOINT_NAMES]


def _hand_frames(model64):
    """(depth (F, 480, 640) uint16 mm, joints (F, 21, 3) mm camera frame) of the right hand."""
    model = model64("hand_right")
    theta = model.zero_pose(FRAMES)
    gen = torch.Generator().manual_seed(3)
    theta[:, 6:] = model.clamp(torch.rand(FRAMES, model.num_dofs, generator=gen, dtype=theta.dtype) * 0.4)[:, 6:]
    theta[:, :3] = torch.tensor([60.0, -50.0, 520.0], dtype=theta.dtype) - model.vertices_rest.mean(0)
    theta[:, 3:6] = torch.tensor([[0.0, 0.0, 0.0], [0.2, -0.3, 0.1], [-0.2, 0.4, 0.3]], dtype=theta.dtype)
    with torch.no_grad():
        posed = model(theta)
        depth = render(posed.vertices, model.faces, nyu_camera().to(dtype=theta.dtype), normals=False).depth
        joints = standard_joints(posed, model)
    return np.round(depth.numpy()).astype(np.uint16), joints.numpy()


def _pack(path: Path, depth: np.ndarray) -> None:
    """Write depth (H, W) uint16 as NYU does: G the high byte, B the low byte, R 0."""
    bgr = np.stack([depth & 255, depth >> 8, np.zeros_like(depth)], -1).astype(np.uint8)
    assert cv2.imwrite(str(path), bgr)


def _nyu_uvd(xyz: np.ndarray) -> np.ndarray:
    """convert_xyz_to_uvd.m: u = fx x / z + 320, v = 240 - fy y / z, d = z."""
    k = NYU_INTRINSICS
    return np.stack([k["fx"] * xyz[..., 0] / xyz[..., 2] + k["cx"], k["cy"] - k["fy"] * xyz[..., 1] / xyz[..., 2],
                     xyz[..., 2]], -1)


def _write_mat(path: Path, joints: np.ndarray, **override) -> None:
    """joints (F, 21, 3) torchhand camera frame -> joint_data.mat of 3 cameras, 36 joints, y up."""
    xyz = joints[:, STAND_INS] * np.array([1.0, -1.0, 1.0])  # (F, 36, 3), NYU's y up
    xyz = np.repeat(xyz[None], 3, axis=0)
    data = {"joint_xyz": xyz, "joint_uvd": _nyu_uvd(xyz),
            "joint_names": np.array(list(NYU_JOINT_NAMES), dtype=object)[None]}
    data.update(override)
    scipy.io.savemat(str(path), {k: v for k, v in data.items() if v is not None})


@pytest.fixture(scope="module")
def sample(tmp_path_factory, model64_module):
    """An NYU split folder of 3 frames, 3 cameras (the same renders), and what was written."""
    split = tmp_path_factory.mktemp("nyu") / "test"
    split.mkdir()
    depth, joints = _hand_frames(model64_module)
    for cam in (1, 2, 3):
        for k in range(FRAMES):
            _pack(split / f"depth_{cam}_{k + 1:07d}.png", depth[k])
    _write_mat(split / "joint_data.mat", joints)
    return split, depth, joints


@pytest.fixture(scope="module")
def model64_module():
    from torchhand import load_model

    cache = {}
    return lambda name: cache.setdefault(name, load_model(name, dtype=torch.float64))


def test_depth_is_unpacked_exactly(sample, tmp_path):
    split, depth, _ = sample
    assert (depth > 0).sum() > 2000 and depth.max() > 255  # the high byte is used
    assert np.array_equal(read_nyu_depth(split / "depth_1_0000002.png"), depth[1])
    info = import_nyu(split, tmp_path / "seq", progress=False)
    seq = SequenceLayout(tmp_path / "seq")
    assert info.frames == FRAMES and info.models == ["hand_right"] and info.depth_unit_mm == 1.0
    for k in range(FRAMES):
        stored = cv2.imread(str(seq.depth(k)), cv2.IMREAD_UNCHANGED)
        assert stored.dtype == np.uint16 and np.array_equal(stored, depth[k])  # mm, exact
        assert np.array_equal(read_depth(seq.depth(k)), depth[k].astype(np.float32))
    back = read_sequence_info(seq.root)
    cam = back.cameras[0]
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == pytest.approx(
        (588.036865, 587.075073, 320.0, 240.0, 640, 480))
    assert back.source["files"] == [f"depth_1_{k:07d}.png" for k in range(1, 4)] and back.source["camera"] == 1


def test_the_fourteen_joints_in_order_and_in_the_camera_frame(sample, tmp_path):
    split, depth, joints = sample
    import_nyu(split, tmp_path / "seq", camera=2, frames=slice(1, 3), progress=False)
    gt = SequenceLayout(tmp_path / "seq").gt
    j3, j2 = np.load(gt.joints_dataset_3d), np.load(gt.joints_dataset_2d)
    assert j3.shape == (2, 1, 14, 3) and j2.shape == (2, 1, 14, 2)
    meta = json.loads(gt.joints_dataset_meta.read_text())
    assert meta["names"] == list(NYU_EVAL_NAMES) == ["F1_KNU3_A", "F1_KNU2_B", "F2_KNU3_A", "F2_KNU2_B", "F3_KNU3_A",
                                                     "F3_KNU2_B", "F4_KNU3_A", "F4_KNU2_B", "TH_KNU3_A", "TH_KNU3_B",
                                                     "TH_KNU2_B", "PALM_1", "PALM_2", "PALM_3"]
    assert meta["indices"] == list(NYU_EVAL_JOINTS)
    assert meta["standard21"][:2] == ["little_tip", "little_pip"] and meta["standard21"][-3:] == [None, None, "wrist"]
    # each evaluation joint is, exactly, the standard joint written in its place (y back down)
    want = joints[1:3][:, [STAND_INS[i] for i in NYU_EVAL_JOINTS]]
    assert np.abs(j3[:, 0] - want).max() < 1e-9
    for name, std in NYU_TO_STANDARD21.items():
        if std is not None:
            assert _stand_in(name) == std
    # every joint projects onto the hand, at or behind its surface
    for f in range(2):
        for (u, v), z in zip(j2[f, 0], j3[f, 0, :, 2]):
            r, c = int(round(v)), int(round(u))
            window = depth[f + 1, r - 2:r + 3, c - 2:c + 3].astype(float)
            assert (window > 0).any(), (u, v)
            assert z >= window[window > 0].min() - 3.0


def test_bad_input_is_named(sample, tmp_path):
    split, depth, joints = sample
    with pytest.raises(SequenceError, match=re.escape(f"{tmp_path / 'none'}: not a folder")):
        import_nyu(tmp_path / "none", tmp_path / "o")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(SequenceError, match=re.escape(f"{empty / 'joint_data.mat'} not found: an NYU split folder "
                                                      "holds joint_data.mat beside its depth frames")):
        import_nyu(empty, tmp_path / "o")
    for cam in (0, 4):
        with pytest.raises(ValueError, match=re.escape(f"camera {cam} is out of range: {split / 'joint_data.mat'} "
                                                       "holds cameras 1..3")):
            import_nyu(split, tmp_path / "o", camera=cam)

    def broken(name, files=FRAMES, **mat):
        folder = tmp_path / name
        folder.mkdir()
        for k in range(files):
            _pack(folder / f"depth_1_{k + 1:07d}.png", depth[k])
        _write_mat(folder / "joint_data.mat", joints, **mat)
        return folder

    few = broken("few", files=2)
    with pytest.raises(SequenceError, match=re.escape(f"{few}: 2 depth_1_*.png files, but {few / 'joint_data.mat'} "
                                                      "holds 3 frames of camera 1")):
        import_nyu(few, tmp_path / "o")
    gap = broken("gap")
    (gap / "depth_1_0000002.png").rename(gap / "depth_1_0000009.png")
    with pytest.raises(SequenceError, match=re.escape(f"{gap / 'depth_1_0000002.png'} not found: frames are "
                                                      "numbered 1..3 (1 missing)")):
        import_nyu(gap, tmp_path / "o")
    no_xyz = broken("no_xyz", joint_xyz=None)
    with pytest.raises(SequenceError, match=re.escape(f"{no_xyz / 'joint_data.mat'}: missing ['joint_xyz'] "
                                                      "(expected joint_xyz, joint_uvd and joint_names)")):
        import_nyu(no_xyz, tmp_path / "o")
    short = broken("short", joint_xyz=np.zeros((3, FRAMES, 14, 3)))
    with pytest.raises(SequenceError, match=re.escape(f"{short / 'joint_data.mat'}: joint_xyz has shape (3, 3, 14, 3), "
                                                      "expected (cameras, frames, 36, 3)")):
        import_nyu(short, tmp_path / "o")
    renamed = broken("renamed", joint_names=np.array(["J"] * 36, dtype=object)[None])
    with pytest.raises(SequenceError, match=re.escape(f"{renamed / 'joint_data.mat'}: joint_names are ['J', 'J', "
                                                      "'J']..., expected NYU's 36 (F1_KNU3_A, ..., PALM_6)")):
        import_nyu(renamed, tmp_path / "o")
    xyz = np.repeat((joints[:, STAND_INS] * np.array([1.0, -1.0, 1.0]))[None], 3, axis=0)
    flipped = broken("flipped", joint_uvd=_nyu_uvd(xyz * np.array([1.0, -1.0, 1.0])))
    with pytest.raises(SequenceError, match=re.escape(f"{flipped / 'joint_data.mat'}: joint_uvd differs from "
                                                      "joint_xyz projected with the NYU intrinsics by up to")):
        import_nyu(flipped, tmp_path / "o")
    assert not (tmp_path / "o").exists()


def test_frames_that_are_not_packed_depth_are_refused(sample, tmp_path):
    _, depth, _ = sample
    grey, sixteen, colour = tmp_path / "grey.png", tmp_path / "sixteen.png", tmp_path / "colour.png"
    cv2.imwrite(str(grey), (depth[0] & 255).astype(np.uint8))
    cv2.imwrite(str(sixteen), depth[0])
    _pack(colour, depth[0])
    img = cv2.imread(str(colour))
    img[..., 2] = 7
    cv2.imwrite(str(colour), img)
    with pytest.raises(SequenceError, match=re.escape(f"{grey}: an NYU depth frame is an 8-bit PNG with 3 channels "
                                                      "(depth in G and B), got uint8 with 1 channel(s)")):
        read_nyu_depth(grey)
    with pytest.raises(SequenceError, match=re.escape(f"{sixteen}: an NYU depth frame is an 8-bit PNG with 3 channels "
                                                      "(depth in G and B), got uint16 with 1 channel(s)")):
        read_nyu_depth(sixteen)
    with pytest.raises(SequenceError, match=re.escape(f"{colour}: the R channel is non-zero at 307200 pixels; "
                                                      "NYU depth frames hold depth in G (high byte) and B (low "
                                                      "byte) only")):
        read_nyu_depth(colour)
    with pytest.raises(SequenceError, match=re.escape(f"{tmp_path / 'no.png'}: depth frame not found or unreadable")):
        read_nyu_depth(tmp_path / "no.png")


def test_nothing_is_overwritten_unasked(sample, tmp_path):
    split, depth, _ = sample
    out = tmp_path / "seq"
    out.mkdir()
    (out / "mine.txt").write_text("keep")
    with pytest.raises(FileExistsError, match=re.escape(f"{out} is not empty; choose a new folder or pass --force")):
        import_nyu(split, out, progress=False)
    assert (out / "mine.txt").read_text() == "keep"
    with pytest.raises(ValueError, match="must not be, contain or lie inside the split folder"):
        import_nyu(split, split / "seq", progress=False)
    # a bad frame under force leaves the old folder as it was, and no partial folder
    bad = tmp_path / "bad"
    bad.mkdir()
    for f in split.iterdir():
        (bad / f.name).write_bytes(f.read_bytes())
    cv2.imwrite(str(bad / "depth_1_0000003.png"), depth[2])
    with pytest.raises(SequenceError, match="depth_1_0000003.png: an NYU depth frame is an 8-bit PNG"):
        import_nyu(bad, out, force=True, progress=False)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    assert (out / "mine.txt").read_text() == "keep"
    info = import_nyu(split, out, force=True, progress=False)
    assert info.frames == FRAMES and not (out / "mine.txt").exists()
    assert read_sequence_info(out).frames == FRAMES


def test_the_command_imports_a_camera_and_refuses_flags_of_other_formats(sample, tmp_path, capsys):
    """``torchhand import --format nyu SPLIT --out SEQ --camera K``: exit 0 and the
    camera recorded; --camera with another format, or a camera out of range, exit 2."""
    from torchhand.app.cli import main

    split, _, _ = sample
    assert main(["import", "--format", "nyu", str(split), "--out", str(tmp_path / "seq"), "--camera", "2",
                 "--segment", "none"]) == 0
    info = read_sequence_info(tmp_path / "seq")
    assert info.source["camera"] == 2 and info.frames == FRAMES and info.segmentation is None
    assert main(["import", "--format", "fpha", str(split), "--out", str(tmp_path / "x"), "--camera", "2"]) == 2
    assert "--camera cannot be given with it" in capsys.readouterr().err
    assert main(["import", "--format", "nyu", str(split), "--out", str(tmp_path / "y"), "--camera", "4"]) == 2
    assert "camera" in capsys.readouterr().err and not (tmp_path / "y").exists()
