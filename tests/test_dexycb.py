"""The DexYCB reader (torchhand.data.datasets.dexycb) on a tiny sample written here in
DexYCB's published layout: a shipped right hand rendered into three calibrated cameras
(the master second in meta.yml's order), labels in each camera's frame in metres, the
last frame without a hand pose (-1, as DexYCB marks it)."""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml
from scipy.ndimage import distance_transform_edt

from torchhand.app.cli import DATASET_FORMATS, main
from torchhand.data.datasets import FORMATS
from torchhand.data.datasets.dexycb import (DEXYCB_JOINT_NAMES, DEXYCB_TO_STANDARD, STANDARD_FROM_DEXYCB,
                                           import_dexycb, write_dexycb)
from torchhand.data.layout import (SequenceError, SequenceLayout, read_depth, read_joints21, read_joints21_valid,
                                   read_sequence_info)
from torchhand.geometry.camera import Camera
from torchhand.geometry.camera_rig import look_at
from torchhand.geometry.render import Renderer
from torchhand.io.foreign_files import ForeignFileError
from torchhand.model.joints21 import STANDARD_JOINT_NAMES, scene_standard_joints
from torchhand.model.scene import Scene

FRAMES = 3
SERIALS = ["836212060125", "839512060362", "840412060917"]
MASTER = SERIALS[1]
CENTRE = np.array([10.0, -20.0, 560.0])  # mm, in the master camera
#: the parent of each standard joint but the wrist
PARENTS = [0, 1, 2, 3, 0, 5, 6, 7, 0, 9, 10, 11, 0, 13, 14, 15, 0, 17, 18, 19]


def _cameras():
    """serial -> (Camera in the master's frame (mm), fx, fy, ppx, ppy)."""
    out = {}
    for k, s in enumerate(SERIALS):
        if s == MASTER:
            T = torch.eye(4, dtype=torch.float64)
        else:
            az = math.radians(-40.0 if k == 0 else 45.0)
            eye = CENTRE + 520.0 * np.array([-math.sin(az), -0.3, -math.cos(az)])
            T = look_at(eye.tolist(), CENTRE.tolist())
        fx, fy, ppx, ppy = 612.0 + 3 * k, 611.0 + 2 * k, 318.5 + 2 * k, 242.0 - k
        out[s] = (Camera.from_intrinsics(fx, fy, ppx, ppy, 640, 480, T_cw=T, name=s, dtype=torch.float64),
                  fx, fy, ppx, ppy)
    return out


class Sample:
    """A DexYCB root holding one sequence; ``joints`` (N, 21, 3) mm in the master's frame."""

    def __init__(self, root: Path, joints: np.ndarray):
        self.root, self.joints = root, joints
        self.src = root / "20200709-weiy" / "20200709_141754"

    def copy(self, dest: Path) -> "Sample":
        shutil.copytree(self.root, dest)
        return Sample(dest, self.joints)


@pytest.fixture(scope="module")
def sample(tmp_path_factory) -> Sample:
    scene = Scene.from_names(["hand_right"], dtype=torch.float64)
    theta = scene.zero_pose(FRAMES)
    with torch.no_grad():
        rest = scene(theta).vertices[0].mean(0)
        theta[:, :3] = torch.as_tensor(CENTRE) - rest
        theta[1, 3:6] = torch.tensor([0.2, -0.3, 0.1], dtype=theta.dtype)
        posed = scene(theta)
        joints = scene_standard_joints(scene, posed).numpy()  # (N, 21, 3) master frame, mm
    s = Sample(tmp_path_factory.mktemp("dexycb"), joints)
    cams = {ser: cam for ser, (cam, *_) in _cameras().items()}
    renderer = Renderer(scene.faces, scene.face_model_id, scene.face_bone_id)
    with torch.no_grad():
        depth = {ser: renderer(posed.vertices, cam).depth.numpy() for ser, cam in cams.items()}
    labelled = joints.copy()
    labelled[-1] = np.nan  # no hand pose in the last frame
    write_dexycb(s.root, "20200709-weiy", "20200709_141754", cams, MASTER, depth, labelled,
                 extrinsics="20200702-afternoon")
    # what the published files hold besides what the reader reads
    ext = s.root / "calibration" / "extrinsics_20200702-afternoon" / "extrinsics.yml"
    table = yaml.safe_load(ext.read_text())
    table["extrinsics"]["apriltag"] = [1.0, 0, 0, 0.1, 0, 1.0, 0, 0.2, 0, 0, 1.0, 0.9]
    ext.write_text(yaml.safe_dump(table))
    for f in (s.root / "calibration" / "intrinsics").iterdir():
        f.write_text(yaml.safe_dump({**yaml.safe_load(f.read_text()),
                                     "depth": {"fx": 380.0, "fy": 380.0, "ppx": 320.0, "ppy": 240.0}}))
    meta = yaml.safe_load((s.src / "meta.yml").read_text())
    (s.src / "meta.yml").write_text(yaml.safe_dump({**meta, "ycb_ids": [2, 5, 11], "ycb_grasp_ind": 0}))
    return s


def test_the_joint_order_is_the_standard_one():
    assert sorted(STANDARD_FROM_DEXYCB) == sorted(STANDARD_JOINT_NAMES)
    assert sorted(STANDARD_FROM_DEXYCB.values()) == sorted(DEXYCB_JOINT_NAMES)
    assert DEXYCB_TO_STANDARD.tolist() == list(range(21))
    assert STANDARD_FROM_DEXYCB["thumb_cmc"] == "thumb_mcp" and STANDARD_FROM_DEXYCB["little_tip"] == "little_tip"
    assert sorted(FORMATS) == sorted(DATASET_FORMATS) and "dexycb" in FORMATS


def test_rig_units_order_and_validity(sample, tmp_path):
    info = import_dexycb(sample.src, tmp_path / "seq")
    seq = SequenceLayout(tmp_path / "seq")
    back = read_sequence_info(seq.root)
    assert [c.name for c in back.cameras] == [MASTER, SERIALS[0], SERIALS[2]]  # camera 0 = the master
    assert back.models == ["hand_right"] and back.frames == FRAMES and back.has_rgb
    assert torch.allclose(back.cameras[0].T_cw.double(), torch.eye(4, dtype=torch.float64), atol=1e-6)
    cams = _cameras()
    for cam, ser in zip(back.cameras, [MASTER, SERIALS[0], SERIALS[2]]):
        ref, fx, fy, ppx, ppy = cams[ser]
        assert (cam.fx, cam.fy, cam.cx, cam.cy) == pytest.approx((fx, fy, ppx, ppy))
        assert torch.allclose(cam.T_cw.double(), ref.T_cw, atol=1e-3)  # mm, master = world
    assert info.source["master"] == MASTER and info.source["frames_without_pose"] == [FRAMES - 1]
    j3, j2 = read_joints21(seq.gt)
    valid = read_joints21_valid(seq.gt)
    assert j3.shape == (FRAMES, 3, 21, 3) and j2.shape == (FRAMES, 3, 21, 2) and valid.shape == (FRAMES, 21)
    assert valid[:-1].all() and not valid[-1].any() and np.isnan(j3[-1]).all() and np.isnan(j2[-1]).all()
    np.testing.assert_allclose(j3[:-1, 0], sample.joints[:-1], atol=0.05)  # mm and the order, camera 0's frame
    bones = lambda j: np.linalg.norm(j[:, 1:] - j[:, PARENTS], axis=-1)  # noqa: E731
    np.testing.assert_allclose(bones(j3[:-1, 1]), bones(sample.joints[:-1]), atol=0.05)  # every camera: rigid
    chirality = lambda j: np.sign(np.einsum("ni,ni->n", np.cross(j[:, 5] - j[:, 0], j[:, 17] - j[:, 0]),  # noqa: E731
                                            j[:, 2] - j[:, 0]))
    for c in range(3):
        assert np.array_equal(chirality(j3[:-1, c]), chirality(sample.joints[:-1]))
    for k in range(FRAMES):
        assert seq.depth(k, 2).read_bytes() == (sample.src / SERIALS[2] / f"aligned_depth_to_color_{k:06d}.png").read_bytes()
        assert seq.rgb(k, 1).is_file()


def test_joints_project_onto_each_cameras_hand(sample, tmp_path):
    import_dexycb(sample.src, tmp_path / "seq")
    seq = SequenceLayout(tmp_path / "seq")
    info = read_sequence_info(seq.root)
    j3, j2 = read_joints21(seq.gt)
    for c, cam in enumerate(info.cameras):
        uv = cam.to(dtype=torch.float64).project(torch.from_numpy(j3[:-1, 0])).numpy()  # world = camera 0
        np.testing.assert_allclose(uv, j2[:-1, c], atol=0.05)  # the rig agrees with each camera's 2D labels
        for k in range(FRAMES - 1):
            off_hand = distance_transform_edt(read_depth(seq.depth(k, c)) == 0)  # px to the nearest hand pixel
            u, v = np.round(uv[k]).astype(int).T
            assert off_hand[v, u].max() <= 10, (c, k, off_hand[v, u])


def test_a_frame_without_hand_is_scored_as_absent(sample, tmp_path):
    from torchhand.scoring.metrics import joint_scores

    import_dexycb(sample.src, tmp_path / "seq")
    gt = SequenceLayout(tmp_path / "seq").gt
    j3, _ = read_joints21(gt)
    pred = np.nan_to_num(j3[:, 0], nan=0.0) + np.array([3.0, 4.0, 0.0])  # 5 mm off; frame 2 predicted anywhere
    s = joint_scores(pred, j3[:, 0], read_joints21_valid(gt))
    assert s.mpjpe_mm == pytest.approx(5.0)


def test_camera_subset(sample, tmp_path):
    info = import_dexycb(sample.src, tmp_path / "seq", cameras=[SERIALS[2], SERIALS[0]])
    assert [c.name for c in info.cameras] == [SERIALS[0], SERIALS[2]]  # no master: meta.yml's order
    assert torch.allclose(info.cameras[0].T_cw.double(), torch.eye(4, dtype=torch.float64), atol=1e-6)
    j3, _ = read_joints21(SequenceLayout(tmp_path / "seq").gt)
    T = _cameras()[SERIALS[0]][0].T_cw.numpy()
    np.testing.assert_allclose(j3[:-1, 0], sample.joints[:-1] @ T[:3, :3].T + T[:3, 3], atol=0.05)
    with pytest.raises(SequenceError, match=r"meta.yml: --cameras 123: give distinct serials .*\(123 not listed\)"):
        import_dexycb(sample.src, tmp_path / "x", cameras=["123"])


def test_tagged_yaml_is_read_and_code_is_refused(sample, tmp_path):
    s = sample.copy(tmp_path / "data")
    meta = s.src / "meta.yml"
    meta.write_text(meta.read_text().replace("serials:", "serials: !!python/tuple"))
    assert import_dexycb(s.src, tmp_path / "seq").frames == FRAMES
    meta.write_text(meta.read_text() + "oops: !!python/object/apply:os.system ['echo ran']\n")
    with pytest.raises(ForeignFileError, match=re.escape(str(meta))):
        import_dexycb(s.src, tmp_path / "x")
    assert not (tmp_path / "x").exists()


def _break(s: Sample, case: str) -> str:
    """Damage the sample copy ``s`` as ``case`` says; return the message expected."""
    calib = s.root / "calibration"
    cam = s.src / SERIALS[0]
    if case == "intrinsics":
        (calib / "intrinsics" / f"{SERIALS[2]}_640x480.yml").unlink()
        return rf"intrinsics/{SERIALS[2]}_640x480.yml: not found"
    if case == "serial":
        path = calib / "extrinsics_20200702-afternoon" / "extrinsics.yml"
        data = yaml.safe_load(path.read_text())
        del data["extrinsics"][SERIALS[0]]
        path.write_text(yaml.safe_dump(data))
        return rf"extrinsics.yml: no extrinsics for camera {SERIALS[0]}"
    if case == "extrinsics":
        shutil.rmtree(calib / "extrinsics_20200702-afternoon")
        return r"extrinsics_20200702-afternoon/extrinsics.yml: not found"
    if case == "camera_count":
        shutil.rmtree(s.src / SERIALS[2])
        return rf"meta.yml: lists 3 cameras, .* holds 2 camera folders; missing: {SERIALS[2]}"
    if case == "depth_count":
        (cam / "aligned_depth_to_color_000001.png").unlink()
        return rf"{SERIALS[0]}: 3 colour, 2 depth and 3 label files, but .*meta.yml has num_frames 3"
    if case == "label_count":
        (cam / "labels_000002.npz").unlink()
        return rf"{SERIALS[0]}: 3 colour, 3 depth and 2 label files"
    if case == "label_shape":
        np.savez(cam / "labels_000001.npz", joint_3d=np.zeros((1, 20, 3), np.float32),
                 joint_2d=np.zeros((1, 20, 2), np.float32))
        return r"labels_000001.npz: joint_3d \(1, 20, 3\) and joint_2d \(1, 20, 2\), expected \(1, 21, 3\)"
    if case == "depth_kind":
        assert cv2.imwrite(str(cam / "aligned_depth_to_color_000000.png"), np.zeros((480, 640, 3), np.uint8))
        return r"aligned_depth_to_color_000000.png: a depth frame must be a single-channel 16-bit PNG"
    raise AssertionError(case)


@pytest.mark.parametrize("case", ["intrinsics", "serial", "extrinsics", "camera_count", "depth_count", "label_count",
                                  "label_shape", "depth_kind"])
def test_bad_input_is_named_and_nothing_is_written(sample, tmp_path, case):
    s = sample.copy(tmp_path / "data")
    message = _break(s, case)
    out = tmp_path / "seq"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(SequenceError, match=message):
        import_dexycb(s.src, out, force=True)
    assert [p.name for p in out.iterdir()] == ["keep.txt"] and sorted(p.name for p in tmp_path.iterdir()) == ["data", "seq"]


def test_nothing_is_written_over(sample, tmp_path):
    out = tmp_path / "seq"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="not empty"):
        import_dexycb(sample.src, out)
    assert (out / "keep.txt").read_text() == "mine"


def test_cli(sample, tmp_path, capsys):
    assert main(["import", "--format", "dexycb", str(sample.src), "--out", str(tmp_path / "seq")]) == 0
    assert "imported 3 frames of dexycb sequence" in capsys.readouterr().out
    assert len(json.loads((tmp_path / "seq" / "sequence.json").read_text())["cameras"]) == 3
    assert main(["import", "--format", "dexycb", str(sample.src), "--out", str(tmp_path / "two"),
                 "--cameras", f"{SERIALS[1]},{SERIALS[2]}"]) == 0
    assert len(read_sequence_info(tmp_path / "two").cameras) == 2
    assert main(["import", "--format", "dexycb", str(sample.src), "--out", str(tmp_path / "x"), "--cameras", "9"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("torchhand import: error: ") and "9 not listed" in err and "\n" not in err
    assert main(["import", "--format", "fpha", str(sample.src), "--out", str(tmp_path / "y"), "--cameras", "9"]) == 2
    assert "--cameras cannot be given with it" in capsys.readouterr().err


def test_labels_that_disagree_with_the_calibration_are_warned_about(sample, tmp_path):
    s = sample.copy(tmp_path / "data")
    path = s.src / SERIALS[2] / "labels_000001.npz"
    with np.load(path) as z:
        labels = dict(z)
    labels["joint_3d"] = labels["joint_3d"] + np.float32(0.02)  # 20 mm off in that camera
    np.savez(path, **labels)
    with pytest.warns(UserWarning, match=rf"{SERIALS[2]}/labels_000001.npz: its joints, moved to camera 0 by the "
                                         rf"extrinsics, lie up to 34.6 mm from those of .*{MASTER}/labels_000001.npz"):
        import_dexycb(s.src, tmp_path / "seq")


def test_eval_scores_a_prediction_against_the_imported_joints(sample, tmp_path, capsys):
    from torchhand.data.layout import write_joints21

    assert main(["import", "--format", "dexycb", str(sample.src), "--out", str(tmp_path / "seq")]) == 0
    info = read_sequence_info(tmp_path / "seq")
    j3, j2 = read_joints21(SequenceLayout(tmp_path / "seq").gt)
    pred = np.nan_to_num(j3[:, :1], nan=0.0) + np.array([3.0, 4.0, 0.0])  # camera 0, 5 mm off
    world = torch.from_numpy(pred[:, 0])
    pred3 = np.stack([(world @ c.T_cw.double()[:3, :3].T + c.T_cw.double()[:3, 3]).numpy() for c in info.cameras], 1)
    pred2 = np.stack([c.to(dtype=torch.float64).project(world).numpy() for c in info.cameras], 1)
    (tmp_path / "out").mkdir()
    write_joints21(tmp_path / "out", pred3, pred2)
    scores = tmp_path / "scores.json"
    assert main(["eval", str(tmp_path / "out"), "--gt", str(tmp_path / "seq"), "--json", str(scores)]) == 0
    r = json.loads(scores.read_text())
    assert r["mpjpe_mm"] == pytest.approx(5.0) and r["joints21"]["scored_joints"] == 21 * (FRAMES - 1)
    assert 0 < r["mean_px"] < 10 and r["pa_mpjpe_mm"] == pytest.approx(0.0, abs=1e-6) and r["lost_frames"] == 0
    assert len(r["joints21"]["per_camera_px"]) == 3
    assert "standard 21 joints: MPJPE 5.00 mm" in capsys.readouterr().out


@pytest.mark.slow  # end to end: import, track and score a sequence, twice
def test_eval_dataset_imports_tracks_scores_and_resumes(sample, tmp_path, capsys):
    from torchhand.app.dataset_eval import RESULTS_NAME

    split = tmp_path / "mine.txt"
    split.write_text(str(sample.src.relative_to(sample.root)) + "\n")
    run = tmp_path / "run"
    base = ["eval-dataset", "dexycb", str(sample.root), "--split", str(split), "--out", str(run), "--cameras", MASTER]
    assert main(base) == 0  # one camera: the automatic initialisation places the hand in one depth view
    table = json.loads((run / RESULTS_NAME).read_text())
    (row,) = table["sequences"]
    assert row["status"] == "ok" and row["frames"] == FRAMES and row["sequence"] == "20200709-weiy_20200709_141754"
    # the pipeline, not the tracking's accuracy: a floating hand auto-initialised in one view of 3 frames
    assert np.isfinite([row[k] for k in ("mpjpe_mm", "pa_mpjpe_mm", "mean_px")]).all() and table["overall"]["sequences"] == 1
    assert table["overall"]["mpjpe_mm"] == row["mpjpe_mm"]
    log = run / "track" / row["sequence"] / "track_log.json"
    stamp = log.stat().st_mtime_ns
    assert "MPJPE" in capsys.readouterr().out
    assert main(base) == 0
    assert log.stat().st_mtime_ns == stamp  # resumed: nothing tracked again
    assert json.loads((run / RESULTS_NAME).read_text())["sequences"] == table["sequences"]
    assert main(base + ["--energy", "LO"]) == 1  # other settings: that sequence is refused, named
    assert "tracked with other settings" in capsys.readouterr().err
    assert main(base + ["--segment", "blobs"]) == 1  # imported with another segmentation: refused too
    assert "imported with another segmentation" in capsys.readouterr().err


def test_dataset_splits(tmp_path):
    from torchhand.app.dataset_eval import DEXYCB_SPLITS, split_sequences
    from torchhand.core.errors import UsageError

    for subject in ("20200709-weiy", "20200813-ceppner"):
        for k in range(100):
            (tmp_path / subject / f"20200709_{k:06d}").mkdir(parents=True)
    val = split_sequences("dexycb", tmp_path, "s0_val")
    assert len(val) == 40 and val[0].src.name == "20200709_000004" and val[0].options == {}
    with pytest.raises(UsageError, match="20200813-ceppner: 0 sequence folders|20200820-amousavian: 0 sequence"):
        split_sequences("dexycb", tmp_path, "s1_train")
    assert set(DEXYCB_SPLITS) == {f"s{k}_{s}" for k in range(4) for s in ("train", "val", "test")}
    (tmp_path / "train" / "ABF10" / "depth").mkdir(parents=True)
    assert [s.name for s in split_sequences("ho3d", tmp_path, "train")] == ["ABF10"]
    with pytest.raises(UsageError, match="--split nope: not a list file nor a split of ho3d"):
        split_sequences("ho3d", tmp_path, "nope")


def test_segmentation_is_stored_for_a_rig_and_one_camera(sample, tmp_path):
    seg = {"mode": "auto", "hands": 1, "near": 200.0, "far": 1500.0, "remove_plane": False}
    rig = import_dexycb(sample.src, tmp_path / "rig", segmentation=seg)
    assert rig.segmentation == seg and read_sequence_info(tmp_path / "rig").segmentation == seg
    one = import_dexycb(sample.src, tmp_path / "one", segmentation=seg, cameras=[MASTER])
    assert read_sequence_info(tmp_path / "one").segmentation == seg and len(one.cameras) == 1
