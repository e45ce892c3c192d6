"""torchhand import (a user's depth PNGs -> a sequence folder), the hand segmentation of
real scenes, and the batched particle swarm."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from torchhand.app.cli import main
from torchhand.data.importing import import_depth_folder, natural_key, read_intrinsics
from torchhand.data.layout import SequenceError, read_depth, read_sequence_info
from torchhand.geometry.camera import Camera
from torchhand.optim.pso import particle_swarm
from torchhand.tracking.segmentation import SegmentConfig, SegmentationError, segment_hands

SR305 = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real" / "sr305"
INTR = {"fx": 476.007, "fy": 476.007, "cx": 313.683, "cy": 242.755}
CAM = Camera.from_intrinsics(476.007, 476.007, 313.683, 242.755, 640, 480)


def _write_depths(folder: Path, names, shape=(48, 64), value=4000) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for k, n in enumerate(names):
        img = np.zeros(shape, np.uint16)
        img[10:20, 10:20] = value + k
        cv2.imwrite(str(folder / n), img)


SMALL = {"fx": 60.0, "fy": 60.0, "cx": 31.5, "cy": 23.5}


def test_natural_order_and_byte_copy(tmp_path):
    names = ["110.png", "30.png", "50.png", "2.png"]
    _write_depths(tmp_path / "src", names)
    info = import_depth_folder(tmp_path / "src", tmp_path / "seq", SMALL, 0.125)
    assert sorted(names, key=natural_key) == ["2.png", "30.png", "50.png", "110.png"]
    assert info.source["files"] == ["2.png", "30.png", "50.png", "110.png"]
    back = read_sequence_info(tmp_path / "seq")
    assert back.frames == 4 and back.depth_unit_mm == 0.125 and back.segmentation is None
    for k, n in enumerate(["2.png", "30.png", "50.png", "110.png"]):
        assert (tmp_path / "seq" / "depth" / f"{k:06d}.png").read_bytes() == (tmp_path / "src" / n).read_bytes()
    d = read_depth(tmp_path / "seq" / "depth" / "000003.png", back.depth_unit_mm)
    assert d[15, 15] == pytest.approx((4000 + names.index("110.png")) * 0.125)


def test_bad_input_is_named_and_nothing_is_overwritten(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(SequenceError, match="no .png"):
        import_depth_folder(tmp_path / "empty", tmp_path / "o1", SMALL, 1.0)
    _write_depths(tmp_path / "mixed", ["0.png"])
    _write_depths(tmp_path / "mixed", ["1.png"], shape=(40, 64))
    with pytest.raises(SequenceError, match=r"1.png.*one size"):
        import_depth_folder(tmp_path / "mixed", tmp_path / "o2", SMALL, 1.0)
    (tmp_path / "eight").mkdir()
    cv2.imwrite(str(tmp_path / "eight" / "0.png"), np.full((48, 64), 7, np.uint8))
    with pytest.raises(SequenceError, match=r"0.png.*16-bit"):
        import_depth_folder(tmp_path / "eight", tmp_path / "o3", SMALL, 1.0)
    (tmp_path / "colour").mkdir()
    cv2.imwrite(str(tmp_path / "colour" / "0.png"), np.full((48, 64, 3), 7, np.uint16))
    with pytest.raises(SequenceError, match="colour"):
        import_depth_folder(tmp_path / "colour", tmp_path / "o4", SMALL, 1.0)
    _write_depths(tmp_path / "ok", ["0.png"])
    for bad, msg in [({**SMALL, "fx": -1.0}, "positive"), ({**SMALL, "fy": 0.0}, "positive"),
                     ({**SMALL, "cx": 80.0}, "outside"), ({**SMALL, "fx": 1e6}, "implausible")]:
        with pytest.raises(ValueError, match=msg):
            import_depth_folder(tmp_path / "ok", tmp_path / "o5", bad, 1.0)
    assert not (tmp_path / "o5").exists()  # checked before anything is written
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError):
        import_depth_folder(tmp_path / "ok", tmp_path / "mine", SMALL, 1.0)
    assert (tmp_path / "mine" / "notes.txt").read_text() == "mine"
    with pytest.raises(LookupError):
        import_depth_folder(tmp_path / "ok", tmp_path / "o6", SMALL, 1.0, models=["no_such_model"])


def test_cli_import_with_intrinsics_file(tmp_path, capsys):
    _write_depths(tmp_path / "src", ["5.png", "10.png"])
    (tmp_path / "k.json").write_text(json.dumps({**SMALL, "depth_unit_mm": 0.5}))
    assert read_intrinsics(tmp_path / "k.json")["fx"] == 60.0
    rc = main(["import", str(tmp_path / "src"), "--out", str(tmp_path / "seq"), "--intrinsics", str(tmp_path / "k.json")])
    assert rc == 0 and "imported 2 frames" in capsys.readouterr().out
    info = read_sequence_info(tmp_path / "seq")
    assert info.depth_unit_mm == 0.5 and info.segmentation["mode"] == "auto"
    assert main(["import", str(tmp_path / "src"), "--out", str(tmp_path / "s2"), "--fx", "60"]) == 2
    assert "intrinsics" in capsys.readouterr().err


def _disc(depth, centre, radius_px, z):
    yy, xx = np.mgrid[0:480, 0:640]
    depth[(yy - centre[0]) ** 2 + (xx - centre[1]) ** 2 <= radius_px ** 2] = z


def test_segmentation_blobs_and_errors():
    depth = np.zeros((480, 640), np.float32)
    _disc(depth, (240, 200), 45, 500.0)  # ~ 8000 mm^2 at 500 mm: hand-sized
    depth[:, 450:] = 900.0  # a wall, larger than a hand, behind
    seg = segment_hands(depth, CAM, SegmentConfig(mode="blobs"))
    assert abs(seg.mask.sum() - np.pi * 45 ** 2) < 300 and not seg.mask[:, 450:].any()
    _disc(depth, (240, 330), 45, 520.0)
    with pytest.raises(SegmentationError, match="two hand-sized blobs"):
        segment_hands(depth, CAM, SegmentConfig(mode="blobs", strict=True), frame="f7.png")
    two = segment_hands(depth, CAM, SegmentConfig(mode="blobs", hands=2))
    assert len(two.blobs) == 2 and two.blobs[0][240, 200] and two.blobs[1][240, 330]  # left to right
    with pytest.raises(SegmentationError, match=r"f3.png: no depth between"):
        segment_hands(np.zeros((480, 640), np.float32), CAM, SegmentConfig(mode="blobs"), frame="f3.png")
    far_only = np.zeros((480, 640), np.float32)
    far_only[:, 450:] = 900.0
    with pytest.raises(SegmentationError, match="no hand-sized blob"):
        segment_hands(far_only, CAM, SegmentConfig(mode="blobs"))
    assert segment_hands(far_only, CAM, SegmentConfig(mode="range")).mask.sum() == 480 * 190


def test_wrist_cut_on_a_palm_with_a_forearm():
    depth = np.zeros((480, 640), np.float32)
    _disc(depth, (200, 320), 40, 500.0)  # palm, radius 42 mm
    depth[200:480, 300:341] = 500.0  # a forearm 43 mm wide leaving the image at the bottom
    seg = segment_hands(depth, CAM, SegmentConfig(mode="blobs"))
    assert seg.forearm[0] @ np.array([0, 1, 0]) > 0.95
    rows = np.nonzero(seg.mask.any(1))[0]
    # kept up to ~69 mm below the palm centre (about 66 px at 500 mm), the rest cut
    assert 200 + 55 < rows.max() < 200 + 80 and seg.cut[400:, 300:341].all()


@pytest.mark.skipif(not SR305.is_dir(), reason="shared SR305 frames not available")
def test_segmentation_of_real_frames():
    """The hand of the real SR305 frames: hand-sized, in front of the body, the forearm
    cut in every frame where the arm is in view."""
    ok = 0
    files = sorted(SR305.glob("*/*.png"))
    for p in files:
        d = cv2.imread(str(p), cv2.IMREAD_UNCHANGED).astype(np.float32) / 8
        seg = segment_hands(d, CAM, SegmentConfig(mode="blobs"))
        z = d[seg.mask]
        area = np.sum((z / CAM.fx) ** 2)
        body = d[(d > 0) & ~seg.mask & ~seg.cut]
        ok += int(6000 < area < 25000 and np.median(z) < np.median(body) - 40 and seg.cut.any())
    assert ok >= len(files) - 1  # one frame (hand beside a nearer torso edge) is missed: docs/real.md


def test_pso_finds_the_minimum_of_a_batch():
    g = torch.Generator().manual_seed(0)
    target = torch.tensor([[1.0, -2.0, 0.5], [-3.0, 0.0, 2.0]], dtype=torch.float64)

    def cost(x):  # (B, P, D) -> (B, P): a shifted Rastrigin-like bowl per swarm
        e = x - target[:, None]
        return (e ** 2).sum(-1) + 0.5 * (1 - torch.cos(3 * e)).sum(-1)

    init = torch.rand(2, 64, 3, generator=g, dtype=torch.float64) * 10 - 5
    lo, hi = torch.full((3,), -5.0, dtype=torch.float64), torch.full((3,), 5.0, dtype=torch.float64)
    res = particle_swarm(cost, init, lo, hi, generations=60, generator=torch.Generator().manual_seed(1))
    assert torch.allclose(res.best, target, atol=1e-2) and res.evaluations == 61
    assert (res.history[1:] <= res.history[:-1]).all() and (res.particles >= lo).all() and (res.particles <= hi).all()
    again = particle_swarm(cost, init, lo, hi, generations=60, generator=torch.Generator().manual_seed(1))
    assert torch.equal(res.best, again.best)
    with pytest.raises(ValueError, match=r"\(B, P\)"):
        particle_swarm(lambda x: x.sum(-1).sum(-1), init, lo, hi, generations=1)


@pytest.mark.slow
def test_track_with_segmentation_on_a_floating_render(tmp_path, capsys):
    """The range segmentation keeps every pixel of a floating render, so θ is
    bit-identical to tracking without one; a blanked frame under the automatic
    segmentation is flagged with its reason, and the overlays draw the segmentation."""
    import shutil

    seq = tmp_path / "seq"
    shutil.copytree(Path(__file__).resolve().parents[1] / "datasets" / "sample", seq)
    shutil.rmtree(seq / "gt")
    info = read_sequence_info(seq)
    d0 = read_depth(seq / "depth" / "000000.png", info.depth_unit_mm)
    args = ["--iterations", "2", "--first-iterations", "2"]
    assert main(["track", str(seq), "--out", str(tmp_path / "a"), *args]) == 0
    assert main(["track", str(seq), "--out", str(tmp_path / "b"), "--segment", "range", *args]) == 0
    a, b = (np.load(tmp_path / x / info.name / "theta.npy") for x in "ab")
    assert np.array_equal(a, b)
    cv2.imwrite(str(seq / "depth" / "000002.png"), np.zeros_like(d0, np.uint16))
    assert main(["track", str(seq), "--out", str(tmp_path / "c"), "--segment", "auto", "--hands", "2", "--viz",
                 *args]) == 0
    log = json.loads((tmp_path / "c" / info.name / "track_log.json").read_text())["frames"]
    assert not log[2]["valid"] and "000002.png: no depth between" in log[2]["notes"]
    assert log[1]["valid"]
    overlay = cv2.imread(str(tmp_path / "c" / info.name / "overlays" / "000000.png"))
    assert overlay is not None and overlay.shape[:2] == d0.shape and overlay.std() > 0
    assert log[2]["iou"] is None and log[0]["iou"] > 0.5 and log[0]["depth_residual_mm"] < 10


@pytest.mark.slow
def test_fit_quality_and_written_renders(tmp_path):
    from torchhand.scoring.metrics import fit_quality

    d = np.zeros((40, 50))
    d[10:20, 10:20] = 500.0
    assert fit_quality(d, d) == (1.0, 0.0)
    assert fit_quality(d + (d > 0) * 5.0, d) == (1.0, 5.0)
    e = np.zeros_like(d)
    e[10:20, 15:25] = 480.0  # half overlapping, 20 mm nearer
    assert fit_quality(e, d) == pytest.approx((50 / 150, 20.0))
    iou, res = fit_quality(np.roll(d, 25, 1), d)
    assert iou == 0.0 and np.isnan(res)
    assert all(np.isnan(fit_quality(np.zeros_like(d), np.zeros_like(d))))
    import shutil

    seq = tmp_path / "seq"
    shutil.copytree(Path(__file__).resolve().parents[1] / "datasets" / "sample", seq)
    info = read_sequence_info(seq)
    assert main(["track", str(seq), "--out", str(tmp_path / "o"), "--iterations", "2", "--first-iterations", "2",
                 "--write-render"]) == 0
    out = tmp_path / "o" / info.name
    log = json.loads((out / "track_log.json").read_text())["frames"]
    for f in range(info.frames):  # the written render reproduces the logged measure
        model = read_depth(out / "render" / f"{f:06d}.png")
        data = read_depth(seq / "depth" / f"{f:06d}.png", info.depth_unit_mm)
        iou, res = fit_quality(model, data)
        assert iou == pytest.approx(log[f]["iou"], abs=0.01) and abs(res - log[f]["depth_residual_mm"]) <= 1.0
        assert iou > 0.6


@pytest.mark.slow
def test_automatic_initialisation_of_a_rendered_hand():
    """A right hand rendered at the pose of the sample's ground truth, found from its
    segmented depth alone: the particle swarm then LM land within 10 mm mean keypoint
    error."""
    from torchhand.data.layout import read_poses
    from torchhand.model.scene import Scene
    from torchhand.tracking.initialization import initialize_hands
    from torchhand.tracking.tracker import Tracker, TrackerConfig

    root = Path(__file__).resolve().parents[1] / "datasets" / "sample"
    info = read_sequence_info(root)
    gt = read_poses(root / "gt")
    full = Scene.from_names(info.models)
    scene = Scene.from_names(["hand_right"])
    truth = torch.as_tensor(gt.theta[0][full.slices["hand_right"]], dtype=torch.float32)[None]
    tracker = Tracker(scene, TrackerConfig())
    cam = info.cameras[0]
    with torch.no_grad():
        depth = tracker.renderer(scene(truth).vertices, cam, normals=False).depth[0].numpy()
    seg = segment_hands(depth, cam, SegmentConfig(mode="blobs"))
    res = initialize_hands(tracker, depth, cam, seg)
    with torch.no_grad():
        err = (scene(res.theta[None]).keypoints - scene(truth).keypoints).norm(dim=-1).mean()
    assert err < 10.0 and res.cost < 0.2
    # a refine that diverges (LM thrown off the data) is not taken: the swarm's pick is
    solve = tracker.solve

    def diverging(starts, *args, **kwargs):
        out = solve(starts, *args, **kwargs)
        return out._replace(theta=out.theta + torch.tensor([5000.0, 0.0, 9000.0] + [0.0] * (scene.num_dofs - 3)))

    tracker.solve = diverging
    res = initialize_hands(tracker, depth, cam, seg)
    with torch.no_grad():
        err = (scene(res.theta[None]).keypoints - scene(truth).keypoints).norm(dim=-1).mean()
    assert err < 40.0 and res.cost < 0.5


@pytest.mark.slow
def test_restarts_run_independent_swarms_and_refine_their_best_picks_together(monkeypatch):
    """InitConfig(restarts=2, seed=s) runs swarms seeded 2s and 2s + 1 and refines
    ``refine`` picks in all, shared among them, as one batch; the pose kept is the
    candidate of lowest depth discrepancy, on the hand."""
    import torchhand.tracking.initialization as initialization
    from torchhand.data.layout import read_poses
    from torchhand.model.scene import Scene
    from torchhand.tracking.initialization import InitConfig, Initializer
    from torchhand.tracking.tracker import Tracker, TrackerConfig

    root = Path(__file__).resolve().parents[1] / "datasets" / "sample"
    info = read_sequence_info(root)
    cam = info.cameras[0]
    scene = Scene.from_names(["hand_right"])
    tracker = Tracker(scene, TrackerConfig())
    sl = Scene.from_names(info.models).slices["hand_right"]
    truth = torch.as_tensor(read_poses(root / "gt").theta[0][sl], dtype=torch.float32)[None]
    with torch.no_grad():
        depth = tracker.renderer(scene(truth).vertices, cam, normals=False).depth[0].numpy()
    seg = segment_hands(depth, cam, SegmentConfig(mode="blobs"))
    seeds, batches = [], []
    swarm, solve = initialization.particle_swarm, tracker.solve

    def recorded_swarm(*args, generator, **kwargs):
        seeds.append(generator.initial_seed())
        return swarm(*args, generator=generator, **kwargs)

    def recorded_solve(starts, *args, **kwargs):
        batches.append(len(starts))
        return solve(starts, *args, **kwargs)

    monkeypatch.setattr(initialization, "particle_swarm", recorded_swarm)
    tracker.solve = recorded_solve
    res = Initializer(tracker, InitConfig(restarts=2, seed=3, particles=16, generations=8, refine=4))(depth, cam, seg)
    assert seeds == [6, 7] and batches == [4]
    with torch.no_grad():
        err = (scene(res.theta[None]).keypoints - scene(truth).keypoints).norm(dim=-1).mean()
    assert err < 20.0 and res.cost < 0.3
    with pytest.raises(ValueError, match="restarts"):
        InitConfig(restarts=0)


def test_detected_fingertips_seed_the_hand_axis():
    """The fingertips the shipped detector finds on a rendered hand lie near the model's
    fingertips, all on the fingers' side of the blob's centroid (the length axis' sign
    that the initialisation then takes without a forearm)."""
    from torchhand.data.layout import read_poses
    from torchhand.model.scene import Scene
    from torchhand.tracking.initialization import Initializer
    from torchhand.tracking.tracker import Tracker, TrackerConfig

    root = Path(__file__).resolve().parents[1] / "datasets" / "sample"
    info = read_sequence_info(root)
    full = Scene.from_names(info.models)
    scene = Scene.from_names(["hand_right"])
    truth = torch.as_tensor(read_poses(root / "gt").theta[0][full.slices["hand_right"]], dtype=torch.float32)[None]
    tracker = Tracker(scene, TrackerConfig())
    cam = info.cameras[0]
    with torch.no_grad():
        depth = tracker.renderer(scene(truth).vertices, cam, normals=False).depth[0].numpy()
        kp = cam.to_camera(scene(truth).keypoints)[0].numpy()
    seg = segment_hands(depth, cam, SegmentConfig(mode="blobs"))
    tips = Initializer(tracker).fingertips(seg.apply(depth), seg.blobs[0], cam)
    assert len(tips) >= 3
    model_tips = kp[[4, 8, 12, 16, 20]]
    nearest = np.linalg.norm(tips[:, None] - model_tips[None], axis=-1).min(1)
    assert np.median(nearest) < 15.0
    length = (kp[9] - kp[0]) / np.linalg.norm(kp[9] - kp[0])  # wrist -> middle finger base
    centre = np.nonzero(seg.blobs[0])
    z = depth[centre]
    pts = np.stack([(centre[1] - cam.cx) * z / cam.fx, (centre[0] - cam.cy) * z / cam.fy, z], 1)
    assert ((tips[nearest < 15.0] - pts.mean(0)) @ length > 0).mean() >= 0.75


@pytest.mark.slow
@pytest.mark.skipif(not SR305.is_dir(), reason="shared SR305 frames not available")
def test_cli_init_on_a_real_frame(tmp_path, capsys):
    src = tmp_path / "rec"
    src.mkdir()
    import shutil

    shutil.copy(SR305 / "20210326-231615" / "0.png", src / "0.png")
    args = ["--fx", "476.007", "--fy", "476.007", "--cx", "313.683", "--cy", "242.755", "--depth-unit-mm", "0.125"]
    assert main(["import", str(src), "--out", str(tmp_path / "seq"), *args]) == 0
    assert main(["init", str(tmp_path / "seq")]) == 0
    out = capsys.readouterr().out
    iou = float(out.split("silhouette IoU ")[1].split(",")[0])
    assert iou >= 0.7
    overlay = cv2.imread(str(tmp_path / "seq" / "init_overlay.png"))
    assert overlay is not None and overlay.shape[:2] == (480, 640) and overlay.std() > 0
    theta = json.loads((tmp_path / "seq" / "init_pose.json").read_text())["theta"]
    assert len(theta) == 37
    assert main(["init", str(tmp_path / "seq")]) == 2  # an existing init_pose.json is kept
    assert json.loads((tmp_path / "seq" / "init_pose.json").read_text())["theta"] == theta
