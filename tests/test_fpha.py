"""The FPHA reader (torchhand.data.datasets.fpha): a tiny sequence in FPHA's published
layout, rendered from a shipped hand at FPHA's intrinsics, is imported and read back."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from torchhand.app.cli import DATASET_FORMATS, main
from torchhand.data.datasets import FORMATS
from torchhand.data.datasets.fpha import (FPHA_INTRINSICS, FPHA_JOINT_NAMES, FPHA_TO_STANDARD, STANDARD_FROM_FPHA,
                                          fpha_camera, import_fpha)
from torchhand.data.layout import SequenceError, SequenceLayout, read_joints21, read_sequence_info
from torchhand.geometry.render import Renderer
from torchhand.model.joints21 import STANDARD_JOINT_NAMES, scene_standard_joints
from torchhand.model.scene import Scene

FRAMES = 3
#: the parent of each standard joint but the wrist: each finger's base hangs off the wrist
PARENTS = [0, 1, 2, 3, 0, 5, 6, 7, 0, 9, 10, 11, 0, 13, 14, 15, 0, 17, 18, 19]


class Sample:
    """A rendered FPHA sequence: its folder, skeleton and the hand's joints (N, 21, 3) mm."""

    def __init__(self, root: Path, joints: np.ndarray):
        self.root, self.joints = root, joints
        self.src = root / "Video_files" / "Subject_1" / "put_salt" / "1"
        self.skeleton = root / "Hand_pose_annotation_v1" / "Subject_1" / "put_salt" / "1" / "skeleton.txt"

    def copy(self, dest: Path) -> "Sample":
        import shutil

        shutil.copytree(self.root, dest)
        return Sample(dest, self.joints)


def _skeleton_lines(joints: np.ndarray) -> list:
    """FPHA's lines: the frame number, then the joints in FPHA's order (the inverse of the mapping)."""
    fpha = np.empty_like(joints)
    fpha[:, FPHA_TO_STANDARD] = joints
    return [" ".join([str(t)] + [f"{v:.5f}" for v in row.ravel()]) for t, row in enumerate(fpha)]


@pytest.fixture(scope="module")
def sample(tmp_path_factory) -> Sample:
    scene = Scene.from_names(["hand_right"])
    theta = scene.zero_pose(FRAMES)
    theta[:, 0] = torch.tensor([-40.0, -30.0, -50.0])  # root tx, ty, tz per frame, mm: ~400 mm in front
    theta[:, 1] = torch.tensor([0.0, 10.0, -10.0])
    theta[:, 2] = torch.tensor([400.0, 420.0, 380.0])
    with torch.no_grad():
        posed = scene(theta)
        joints = scene_standard_joints(scene, posed).double().numpy()
        depth = Renderer(scene.faces, scene.face_model_id, scene.face_bone_id)(posed.vertices, fpha_camera()).depth
    s = Sample(tmp_path_factory.mktemp("fpha"), joints)
    (s.src / "depth").mkdir(parents=True)
    for k in range(FRAMES):
        img = np.round(np.nan_to_num(depth[k].numpy())).astype(np.uint16)
        assert cv2.imwrite(str(s.src / "depth" / f"depth_{k:04d}.png"), img)
    s.skeleton.parent.mkdir(parents=True)
    s.skeleton.write_text("\n".join(_skeleton_lines(joints)) + "\n")
    return s


def test_the_mapping_is_a_permutation_of_both_orders():
    assert sorted(STANDARD_FROM_FPHA) == sorted(STANDARD_JOINT_NAMES)
    assert sorted(STANDARD_FROM_FPHA.values()) == sorted(FPHA_JOINT_NAMES)
    assert FPHA_TO_STANDARD.tolist() == [0, 1, 6, 7, 8, 2, 9, 10, 11, 3, 12, 13, 14, 4, 15, 16, 17, 5, 18, 19, 20]
    assert sorted(FORMATS) == sorted(DATASET_FORMATS)


def test_import_reads_joints_in_mm_in_the_depth_camera(sample, tmp_path):
    info = import_fpha(sample.src, tmp_path / "seq")
    back = read_sequence_info(tmp_path / "seq")
    assert back.frames == FRAMES and back.models == ["hand_right"] and back.depth_unit_mm == 1.0
    K = back.cameras[0].K.double()
    assert K[0, 0].item() == pytest.approx(FPHA_INTRINSICS["fx"]) and K[1, 2].item() == pytest.approx(
        FPHA_INTRINSICS["cy"])
    assert torch.equal(back.cameras[0].T_cw, torch.eye(4))
    assert info.source["frames_without_pose"] == [] and info.source["action"] == "put_salt"
    seq = SequenceLayout(tmp_path / "seq")
    for k in range(FRAMES):
        assert seq.depth(k).read_bytes() == (sample.src / "depth" / f"depth_{k:04d}.png").read_bytes()
    j3, j2 = read_joints21(seq.gt)
    assert j3.shape == (FRAMES, 1, 21, 3) and j2.shape == (FRAMES, 1, 21, 2)
    np.testing.assert_allclose(j3[:, 0], sample.joints, atol=1e-3, rtol=0)  # units (mm) and the joint order
    bones = lambda j: np.linalg.norm(j[:, 1:] - j[:, PARENTS], axis=-1)  # noqa: E731
    np.testing.assert_allclose(bones(j3[:, 0]), bones(sample.joints), atol=1e-3)
    chirality = lambda j: np.sign(np.einsum("ni,ni->n", np.cross(j[:, 5] - j[:, 0], j[:, 17] - j[:, 0]),  # noqa: E731
                                            j[:, 2] - j[:, 0]))
    assert np.array_equal(chirality(j3[:, 0]), chirality(sample.joints))
    for k in range(FRAMES):  # the frame: the joints project onto the hand's pixels of the depth camera
        depth = cv2.imread(str(seq.depth(k)), cv2.IMREAD_UNCHANGED).astype(np.float64)
        u, v = np.round(j2[k, 0]).astype(int).T
        on_hand = np.array([(depth[r - 2:r + 3, c - 2:c + 3] > 0).any() for r, c in zip(v, u)])
        assert on_hand.sum() >= 20, (k, np.array(STANDARD_JOINT_NAMES)[~on_hand])
        near = np.abs(depth[v, u] - j3[k, 0, :, 2])[depth[v, u] > 0]
        assert np.median(near) < 30  # mm: joint centres lie inside the hand, tips on its surface


def test_bad_input_is_named(sample, tmp_path):
    s = sample.copy(tmp_path / "data")
    lines = s.skeleton.read_text().splitlines()
    s.skeleton.write_text("\n".join([lines[0], lines[1] + " 7.0", lines[2]]) + "\n")
    with pytest.warns(UserWarning, match=rf"skeleton.txt:2: 65 numbers, expected 64 .*that frame gets no joints"):
        info = import_fpha(s.src, tmp_path / "a")
    j3, j2 = read_joints21(SequenceLayout(tmp_path / "a").gt)
    assert np.isnan(j3[1]).all() and np.isnan(j2[1]).all() and np.isfinite(j3[[0, 2]]).all()
    assert info.source["frames_without_pose"] == [1] and info.frames == FRAMES
    s.skeleton.write_text("\n".join(lines[:2]) + "\n")
    with pytest.warns(UserWarning, match=r"3 depth frames, but .*skeleton.txt has frames 0..1 \(2\); the 2 frames"):
        assert import_fpha(s.src, tmp_path / "b").frames == 2
    s.skeleton.write_text("\n".join(lines) + "\n")
    cv2.imwrite(str(s.src / "depth" / "depth_0001.png"), np.full((480, 640), 7, np.uint8))
    with pytest.raises(SequenceError, match=r"depth_0001.png: a depth frame must be a single-channel 16-bit PNG, "
                                            r"got a uint8 image"):
        import_fpha(s.src, tmp_path / "c")
    s.skeleton.unlink()
    with pytest.raises(SequenceError, match=r"Hand_pose_annotation_v1/Subject_1/put_salt/1/skeleton.txt: not found"):
        import_fpha(s.src, tmp_path / "d")
    with pytest.raises(SequenceError, match="not an FPHA sequence folder"):
        import_fpha(s.src / "depth", tmp_path / "e")
    assert not any((tmp_path / n).exists() for n in "cde")  # checked before anything is written


def test_nothing_is_written_over(sample, tmp_path):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="not empty"):
        import_fpha(sample.src, tmp_path / "mine")
    assert (tmp_path / "mine" / "notes.txt").read_text() == "mine"
    import_fpha(sample.src, tmp_path / "mine", force=True)
    assert not (tmp_path / "mine" / "notes.txt").exists() and read_sequence_info(tmp_path / "mine").frames == FRAMES
    assert [p.name for p in tmp_path.iterdir()] == ["mine"]  # no hidden partial folder left


def test_cli(sample, tmp_path, capsys):
    assert main(["import", "--format", "fpha", str(sample.src), "--out", str(tmp_path / "seq")]) == 0
    assert "imported 3 frames of fpha sequence" in capsys.readouterr().out
    assert json.loads((tmp_path / "seq" / "sequence.json").read_text())["segmentation"]["mode"] == "auto"
    assert main(["import", "--format", "fpha", str(sample.src), "--out", str(tmp_path / "seq")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("torchhand import: error: ") and "is not empty" in err and "\n" not in err
    assert main(["import", "--format", "fpha", str(sample.src), "--out", str(tmp_path / "x"), "--fx", "500"]) == 2
    assert "--fx cannot be given with it" in capsys.readouterr().err
    assert main(["import", "--format", "fpha", str(tmp_path), "--out", str(tmp_path / "y")]) == 2
    assert "not an FPHA sequence folder" in capsys.readouterr().err
    assert main(["import", str(sample.src / "depth"), "--out", str(tmp_path / "z")]) == 2  # without --format: as before
    assert "the camera intrinsics are needed" in capsys.readouterr().err
