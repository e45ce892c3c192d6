"""Fingertip detector: Hough voting, peak picking, AP, ONNX parity, shipped weights,
input checks, training resume."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from conftest import requires_cuda
from torchhand.salient import (DEFAULT_ONNX, DEFAULT_WEIGHTS, SalientConfig, SalientDetector, SalientNet,
                               average_precision, detect_peaks, export_onnx, hough_votes)
from torchhand.salient.training_data import VISIBLE_MM2, SalientFrames


def _random_net(seed: int = 0) -> SalientNet:
    """A small net with random weights everywhere (also the zero-initialised head)."""
    torch.manual_seed(seed)
    net = SalientNet(SalientConfig(channels=(4, 6), dilations=(1, 2)))
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.randn_like(p) * 0.5)
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
    return net.eval()


def _depth(B, H, W, seed=0):
    g = torch.Generator().manual_seed(seed)
    d = 500 + 300 * torch.rand(B, 1, H, W, generator=g)
    return d * (torch.rand(B, 1, H, W, generator=g) > 0.1)  # some invalid pixels


def _hough_reference(scores, offsets, Hh, Wh):
    """Slow bilinear splatting, one vote at a time."""
    B, _, h, w = scores.shape
    out = torch.zeros(B, 1, Hh, Wh, dtype=torch.float64)
    for b in range(B):
        for i in range(h):
            for j in range(w):
                px = 4 * j + 1.5 + float(offsets[b, 0, i, j])
                py = 4 * i + 1.5 + float(offsets[b, 1, i, j])
                hx, hy = (px - 0.5) / 2, (py - 0.5) / 2
                x0, y0 = int(np.floor(hx)), int(np.floor(hy))
                for cy, wy in ((y0, 1 - (hy - y0)), (y0 + 1, hy - y0)):
                    for cx, wx in ((x0, 1 - (hx - x0)), (x0 + 1, hx - x0)):
                        if 0 <= cx < Wh and 0 <= cy < Hh:
                            out[b, 0, cy, cx] += float(scores[b, 0, i, j]) * wx * wy
    return out


# ------------------------------------------------------------------------ network


def test_shapes():
    net = _random_net()
    out = net(_depth(2, 64, 96))
    assert out.logits.shape == (2, 1, 16, 24)
    assert out.offsets.shape == (2, 2, 16, 24)
    assert out.hough.shape == (2, 1, 32, 48)
    assert all(torch.isfinite(t).all() for t in out)


def test_votes_match_reference():
    g = torch.Generator().manual_seed(1)
    scores = torch.rand(2, 1, 5, 6, generator=g, dtype=torch.float64)
    offsets = 12 * torch.randn(2, 2, 5, 6, generator=g, dtype=torch.float64)  # some votes leave the map
    got = hough_votes(scores, offsets, 10, 12)
    torch.testing.assert_close(got, _hough_reference(scores, offsets, 10, 12), rtol=1e-12, atol=1e-12)


def test_votes_off_the_map_are_dropped():
    # far outside on every side, on the last cell's centre, and just past either edge
    scores = torch.ones(1, 1, 2, 3, dtype=torch.float64)
    offsets = torch.zeros(1, 2, 2, 3, dtype=torch.float64)
    offsets[0, :, 0, 0] = torch.tensor([-1e4, 0.0])
    offsets[0, :, 0, 1] = torch.tensor([0.0, 1e4])
    offsets[0, :, 0, 2] = torch.tensor([1e4, -1e4])
    offsets[0, :, 1, 0] = torch.tensor([2 * 5 + 0.5 - 1.5, 2 * 3 + 0.5 - 5.5])  # lands on cell (3, 5)
    offsets[0, :, 1, 1] = torch.tensor([-5.1, -3.0])  # 0.1 px left of cell (1, 0)'s centre
    offsets[0, :, 1, 2] = torch.tensor([1.1, -3.0])  # 0.1 px right of cell (1, 5)'s centre
    got = hough_votes(scores, offsets, 4, 6)
    torch.testing.assert_close(got, _hough_reference(scores, offsets, 4, 6), rtol=1e-12, atol=1e-12)
    assert got[0, 0, 3, 5] == 1.0
    # the two edge votes lose the 5 % that falls off the map, the rest is dropped
    torch.testing.assert_close(float(got.sum()), 2.9, rtol=0, atol=1e-6)  # offsets given in float32


def test_zero_offsets_vote_at_cell_centre():
    scores = torch.zeros(1, 1, 6, 8, dtype=torch.float64)
    scores[0, 0, 2, 3] = 1.0
    hough = hough_votes(scores, torch.zeros(1, 2, 6, 8, dtype=torch.float64), 12, 16)
    # Cell (2, 3) is centred on pixel (13.5, 9.5) = Hough coordinate (6.5, 4.5): four quarters.
    expect = torch.zeros(12, 16, dtype=torch.float64)
    expect[4:6, 6:8] = 0.25
    torch.testing.assert_close(hough[0, 0], expect)
    det = detect_peaks(hough, threshold=0.1, nms_radius=1)[0]
    torch.testing.assert_close(det.uv, torch.tensor([[13.5, 9.5]], dtype=torch.float64))


def test_constant_offsets_shift_the_peak():
    scores = torch.zeros(1, 1, 8, 8)
    scores[0, 0, 3:5, 3:5] = 1.0  # a blob of four voters, all pointing at one place
    offsets = torch.zeros(1, 2, 8, 8)
    offsets[0, 0] = 6.0
    offsets[0, 1] = -4.0
    base = detect_peaks(hough_votes(scores, torch.zeros_like(offsets), 16, 16), threshold=0.1)[0]
    moved = detect_peaks(hough_votes(scores, offsets, 16, 16), threshold=0.1)[0]
    assert len(base.uv) == len(moved.uv) == 1
    torch.testing.assert_close(moved.uv - base.uv, torch.tensor([[6.0, -4.0]]), atol=1e-5, rtol=0)


def test_forward_votes_point_at_the_fingertip():
    """End to end through forward: a head that predicts constant offsets moves the peak."""
    net = SalientNet(SalientConfig(channels=(4, 4), dilations=(1,))).eval()
    with torch.no_grad():
        net.head.bias.copy_(torch.tensor([5.0, 0.5, 0.25]))  # score ~1 everywhere; offset (4, 2) px
    depth = torch.full((1, 1, 32, 32), 600.0)
    with torch.no_grad():
        hough = net(depth).hough
    # Every cell votes 4 px right and 2 px down of its centre: the map is the cell
    # grid shifted by (2, 1) Hough cells; the first column and row get no votes.
    assert float(hough[0, 0, :, 0].max()) < float(hough[0, 0, 8, 8]) * 0.5
    assert float(hough[0, 0, 0, :].max()) < float(hough[0, 0, 8, 8]) * 0.9


def test_detect_peaks_nms_threshold_topk():
    h = torch.zeros(1, 1, 20, 20)
    h[0, 0, 5, 5] = 5.0
    h[0, 0, 5, 6] = 4.0  # neighbour of the first: suppressed
    h[0, 0, 15, 15] = 3.0
    h[0, 0, 2, 15] = 1.0  # below the threshold
    det = detect_peaks(h, threshold=2.0, nms_radius=2)[0]
    assert det.score.tolist() == [5.0, 3.0]
    assert abs(float(det.uv[1, 0]) - 30.5) < 1e-6 and abs(float(det.uv[1, 1]) - 30.5) < 1e-6
    # the suppressed neighbour pulls the refined position of the first peak towards it
    assert 10.5 < float(det.uv[0, 0]) < 12.5
    assert len(detect_peaks(h, threshold=2.0, max_detections=1)[0].score) == 1
    assert len(detect_peaks(h, threshold=0.5, nms_radius=0)[0].score) == 4
    with pytest.raises(ValueError, match=r"\(B, 1, Hh, Wh\)"):
        detect_peaks(h[0])



def test_logits_rescore_the_peaks():
    """With the score logits, a detection's score is its Hough value times the squared
    probability of the score cell under it, and the detections are re-sorted."""
    h = torch.zeros(1, 1, 20, 20, dtype=torch.float64)
    h[0, 0, 5, 5] = 5.0  # pixel (10.5, 10.5): score cell (2, 2), centred on (9.5, 9.5)
    h[0, 0, 15, 15] = 3.0  # pixel (30.5, 30.5): score cell (7, 7), centred on (29.5, 29.5)
    logits = torch.full((1, 1, 10, 10), -8.0, dtype=torch.float64)
    logits[0, 0, 2, 2] = 0.0  # p = 0.5
    logits[0, 0, 7, 7] = 8.0  # p ~ 1
    plain = detect_peaks(h, threshold=2.0, nms_radius=2)[0]
    det = detect_peaks(h, threshold=2.0, nms_radius=2, logits=logits)[0]
    torch.testing.assert_close(det.uv, plain.uv.flip(0))
    p = torch.sigmoid(torch.tensor(8.0, dtype=torch.float64))
    torch.testing.assert_close(det.score, torch.stack([3.0 * p ** 2, torch.tensor(5.0 * 0.25, dtype=torch.float64)]))
    with pytest.raises(ValueError, match=r"logits must be a tensor of shape \(1, 1, 10, 10\)"):
        detect_peaks(h, logits=logits[:, :, :5])

# ---------------------------------------------------------------------------- AP


def test_average_precision_hand_computed():
    # Frame 0: two fingertips; frame 1: one fingertip.
    gt = [np.array([[10.0, 10.0], [50.0, 50.0]]), np.array([[100.0, 100.0]])]
    det_uv = [np.array([[12.0, 10.0], [11.0, 11.0], [80.0, 80.0]]), np.array([[104.0, 103.0]])]
    det_s = [np.array([0.9, 0.8, 0.7]), np.array([0.6])]
    pr = average_precision(det_uv, det_s, gt, radius=10.0)
    # sorted: TP (0.9), FP duplicate (0.8), FP (0.7), TP (0.6): precision 1, 1/2, 1/3, 1/2;
    # recall 1/3, 1/3, 1/3, 2/3. Interpolated: 1 on (0, 1/3], 1/2 on (1/3, 2/3], 0 after.
    np.testing.assert_allclose(pr.precision, [1, 0.5, 1 / 3, 0.5])
    np.testing.assert_allclose(pr.recall, [1 / 3, 1 / 3, 1 / 3, 2 / 3])
    assert pr.ap == pytest.approx(1 / 3 + 0.5 / 3)
    assert pr.num_gt == 3
    # An ignored point swallows the false positive at (80, 80): precision 1, 1/2, 2/3.
    pr2 = average_precision(det_uv, det_s, gt, radius=10.0, gt_ignore=[np.array([[82.0, 80.0]]), np.zeros((0, 2))])
    assert pr2.ap == pytest.approx(1 / 3 + (2 / 3) / 3)
    assert average_precision([np.zeros((0, 2))], [np.zeros(0)], [np.zeros((0, 2))]).ap == 1.0


# ------------------------------------------------------------------------- ONNX


def test_onnx_parity_on_another_size(tmp_path):
    ort = pytest.importorskip("onnxruntime")
    net = _random_net(3)
    path = export_onnx(net, tmp_path / "net.onnx", height=48, width=64)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    for H, W in ((80, 44), (48, 64)):
        x = _depth(2, H, W, seed=H)
        got = sess.run(None, {"depth": x.numpy()})
        with torch.no_grad():
            ref = net(x)
        for name, a, b in zip(ref._fields, ref, got):
            assert a.shape == b.shape, name
            np.testing.assert_allclose(b, a.numpy(), atol=1e-4, rtol=0, err_msg=name)


# ------------------------------------------------------------------ shipped model


@pytest.fixture(scope="module")
def rendered_frame():
    from torchhand.data.synth import demo_motion
    from torchhand.salient.training_data import render_salient_frames

    return render_salient_frames(demo_motion(frames=slice(30, 31)), seed=3, progress=False)


def _check_hits(dets, frame, max_px=4.0):
    gt = frame.uv[0][frame.area_mm2[0] >= VISIBLE_MM2]
    assert len(gt) >= 5
    d = np.linalg.norm(gt[:, None] - dets.uv.cpu().numpy()[None], axis=-1)
    found = (d.min(1) if d.size else np.full(len(gt), np.inf)) <= max_px
    assert found.mean() >= 0.7, (gt, dets.uv)


def test_shipped_weights_detect_fingertips(rendered_frame):
    det = SalientDetector.load()
    dets = det.detect(rendered_frame.image[0])
    _check_hits(dets, rendered_frame)
    assert (dets.depth > 0).float().mean() > 0.5
    # torch input, and an odd size (padded internally): same detections
    d2 = det.detect(torch.from_numpy(rendered_frame.image[0][:478, :637].astype(np.float32)))
    _check_hits(d2, rendered_frame)


def test_shipped_onnx_matches_torch(rendered_frame):
    pytest.importorskip("onnxruntime")
    a = SalientDetector.load().detect(rendered_frame.image[0])
    b = SalientDetector.load_onnx().detect(rendered_frame.image[0])
    torch.testing.assert_close(a.uv, b.uv, atol=1e-3, rtol=0)
    torch.testing.assert_close(a.score, b.score, atol=1e-3, rtol=1e-4)


def test_shipped_files_are_small():
    assert DEFAULT_WEIGHTS.stat().st_size < 1_000_000 and DEFAULT_ONNX.stat().st_size < 1_000_000


# -------------------------------------------------------------------- bad input


def test_bad_input_errors(tmp_path):
    det = SalientDetector(_random_net())
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        det.detect(np.zeros((1, 48, 64), np.float32))
    with pytest.raises(TypeError, match="numpy array or torch tensor"):
        det.detect([[1.0]])
    with pytest.raises(TypeError, match="dtype"):
        det.detect(np.zeros((48, 64), bool))
    bad = np.full((48, 64), 600.0, np.float32)
    bad[3, 4] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        det.detect(bad)
    with pytest.raises(ValueError, match="negative"):
        det.detect(-np.nan_to_num(bad))
    with pytest.raises(ValueError, match="one depth channel"):
        det.net(torch.zeros(1, 3, 48, 64))
    with pytest.raises(ValueError, match="multiples of 4"):
        det.net(torch.zeros(1, 1, 50, 64))
    with pytest.raises(TypeError, match="floating point"):
        det.net(torch.zeros(1, 1, 48, 64, dtype=torch.int32))


def test_empty_frame_gives_no_detections():
    det = SalientDetector(_random_net(), threshold=0.0)
    for frame in (np.zeros((48, 64), np.uint16), torch.zeros(37, 41)):
        d = det.detect(frame)
        assert d.uv.shape == (0, 2) and d.score.shape == (0,) and d.depth.shape == (0,)


def test_bad_weight_files(tmp_path):
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="garbage.pt"):
        SalientDetector.load(garbage)
    other = tmp_path / "other.pt"
    torch.save({"weight": torch.zeros(3)}, other)
    with pytest.raises(ValueError, match="other.pt.*format"):
        SalientDetector.load(other)
    wrong = tmp_path / "wrong.pt"
    net = _random_net()
    net.save(wrong)
    blob = torch.load(wrong, weights_only=True)
    blob["config"]["channels"] = [5, 7]  # config and tensors disagree
    torch.save(blob, wrong)
    with pytest.raises(ValueError, match="wrong.pt.*do not fit"):
        SalientDetector.load(wrong)
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        SalientDetector.load(tmp_path / "missing.pt")
    bad_onnx = tmp_path / "bad.onnx"
    bad_onnx.write_bytes(b"\x00\x01garbage")
    with pytest.raises(ValueError, match="bad.onnx"):
        SalientDetector.load_onnx(bad_onnx)


def test_save_load_roundtrip(tmp_path):
    net = _random_net(5)
    loaded = SalientNet.load(net.save(tmp_path / "w.pt"))
    x = _depth(1, 32, 48)
    with torch.no_grad():
        torch.testing.assert_close(net(x).hough, loaded(x).hough)


@requires_cuda
def test_cuda_matches_cpu():
    net = _random_net(7)
    x = _depth(1, 64, 80)
    with torch.no_grad():
        ref = net(x)
        got = net.to("cuda")(x.cuda())
    for a, b in zip(ref, got):
        torch.testing.assert_close(b.cpu(), a, atol=1e-4, rtol=1e-4)
    det = SalientDetector(net, device="cuda", threshold=0.0)
    assert det.detect(x[0, 0].numpy()).uv.device.type == "cuda"


# ------------------------------------------------------------------------ training


def _fake_frames(n=6, seed=0):
    g = np.random.default_rng(seed)
    depth = (600 + 100 * g.random((n, 96, 128))).astype(np.uint16)
    uv = np.full((n, 10, 2), np.nan, np.float32)
    z = np.full((n, 10), np.nan, np.float32)
    area = np.zeros((n, 10), np.float32)
    uv[:, :3] = g.uniform(10, 90, (n, 3, 2))
    z[:, :3] = 610.0
    area[:, :3] = [100.0, 100.0, 10.0]
    return SalientFrames(depth, uv, z, area, np.array(["fake"] * n))


def _tiny_cfg(**kw):
    from train.salient_detector import TrainConfig

    base = dict(steps=4, batch_size=2, crop=48, checkpoint_every=2, network={"channels": [4, 4], "dilations": [1]})
    base.update(kw)
    return TrainConfig(**base)


def test_train_resume_is_exact(tmp_path):
    from train.salient_detector import train

    data = _fake_frames()
    cfg = _tiny_cfg()
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    straight = train(cfg, tmp_path / "a", data, data, resume=False, progress=False)
    train(cfg, tmp_path / "b", data, data, resume=False, progress=False, stop_at=2)
    resumed = train(cfg, tmp_path / "b", data, data, resume=True, progress=False)
    for (k, a), b in zip(straight.state_dict().items(), resumed.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=0, atol=0, msg=k)
    half = SalientNet(SalientConfig(**cfg.network))
    half.load_state_dict(torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=False)["model"])
    assert half.state_dict()["head.weight"].abs().sum() > 0


def test_fine_tuning_starts_from_given_weights(tmp_path):
    from train.salient_detector import train

    data = _fake_frames()
    cfg = _tiny_cfg()
    start = SalientNet(SalientConfig(**cfg.network))
    with torch.no_grad():
        start.head.bias.fill_(0.25)
    start.save(tmp_path / "start.pt")
    (tmp_path / "ft").mkdir()
    # learning rate 0: the parameters stay exactly the starting weights
    tuned = train(_tiny_cfg(lr=0.0, init_weights=str(tmp_path / "start.pt")), tmp_path / "ft", data, data,
                  resume=False, progress=False)
    torch.testing.assert_close(tuned.head.bias, start.head.bias)
    other = SalientNet(SalientConfig(channels=(5, 5), dilations=(1,)))
    other.save(tmp_path / "other.pt")
    with pytest.raises(SystemExit, match="other.pt"):
        train(_tiny_cfg(init_weights=str(tmp_path / "other.pt")), tmp_path / "ft", data, data, resume=False,
              progress=False)


def test_cli_refuses_overwrite_and_config_mismatch(tmp_path):
    from dataclasses import asdict

    from train.salient_detector import TrainConfig, main

    run = tmp_path / "run"
    run.mkdir()
    (run / "done.json").write_text("{}")
    with pytest.raises(SystemExit, match="finished run.*--force"):
        main(["--out", str(run)])
    (run / "config.json").write_text(json.dumps(asdict(TrainConfig(steps=4))))
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({"steps": 5}))
    with pytest.raises(SystemExit, match=r"cfg\.json.*steps"):
        main(["--out", str(run), "--resume", "--config", str(cfg)])
    cfg.write_text(json.dumps({"stepz": 5}))
    with pytest.raises(SystemExit, match=r"cfg\.json.*unknown config field.*stepz"):
        main(["--out", str(run), "--config", str(cfg)])


def test_fingertips_the_sensor_does_not_measure_are_not_ground_truth():
    """The visible area counts only pixels with a depth measurement: a hand nearer
    than the Kinect's 400 mm range has no ground-truth fingertip, and masking the
    sensed pixels masks the area."""
    from torchhand.data.synth import demo_motion
    from torchhand.geometry.render import render
    from torchhand.model.fingertips import fingertip_faces
    from torchhand.salient.training_data import fingertip_targets, render_salient_frames

    frames = demo_motion(frames=slice(30, 31))
    scene, cam = frames.scene, frames.cameras[0]
    with torch.no_grad():
        V = scene(frames.theta.to(scene.lower.dtype)).vertices
    res = render(V, scene.faces, cam.to(dtype=V.dtype), scene.face_model_id, scene.face_bone_id)
    tips = fingertip_faces(scene)
    full = fingertip_targets(V, res.face_id, cam.to(dtype=V.dtype), tips).area_mm2
    assert int((full >= VISIBLE_MM2).sum()) >= 5
    left = torch.zeros_like(res.face_id, dtype=torch.bool)
    left[..., : cam.width // 2] = True
    half = fingertip_targets(V, res.face_id, cam.to(dtype=V.dtype), tips, sensed=left).area_mm2
    assert (half <= full).all() and float(half.sum()) < float(full.sum())
    none = fingertip_targets(V, res.face_id, cam.to(dtype=V.dtype), tips, sensed=~torch.ones_like(left)).area_mm2
    assert float(none.abs().sum()) == 0.0
    with pytest.raises(ValueError, match="sensed"):
        fingertip_targets(V, res.face_id, cam.to(dtype=V.dtype), tips, sensed=left[..., 1:])
    # the same frame moved so that its farthest point is 390 mm from the camera: nothing in range
    near = frames.theta.clone()
    z_far = float(cam.to(dtype=V.dtype).to_camera(V)[..., 2].max())
    axis = cam.T_cw[2, :3].to(near.dtype)  # the optical axis in the world frame
    for sl in scene.slices.values():  # every model's global translation, towards the camera
        near[:, sl.start : sl.start + 3] -= (z_far - 390.0) * axis
    moved = dataclasses.replace(frames, theta=near)
    out = render_salient_frames(moved, seed=0, background=False, progress=False)
    assert (out.image[0] > 0).mean() < 0.01 and float(out.area_mm2[0].max()) == 0.0, out.area_mm2


def test_random_background_stays_behind_the_models_and_spheres_only_add_blobs():
    from torchhand.salient.training_data import random_background

    far = torch.tensor([500.0, 700.0, 900.0])
    plain = random_background(far, 120, 160, torch.Generator().manual_seed(4))
    blobs = random_background(far, 120, 160, torch.Generator().manual_seed(4), max_spheres=3, focal_px=200.0)
    for bg in (plain, blobs):
        assert bg.shape == (3, 120, 160)
        assert ((bg == 0) | (bg >= far[:, None, None] + 20 - 1e-3)).all()
    # the plane and boxes are the same draws; a sphere is only ever in front of them
    changed = blobs != plain
    assert changed.any()
    assert ((blobs[changed] < plain[changed]) | (plain[changed] == 0)).all()


def _torchrun(args, cwd):
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("WORLD_SIZE", "RANK", "LOCAL_RANK")}
    return subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                           "-m", "train.salient_detector", *args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=300)


@pytest.mark.slow
def test_ddp_two_processes_match_one_and_resume_exactly(tmp_path):
    """torchrun with 2 CPU ranks (gloo): the loss curve of the single-process run at the
    same global batch (BatchNorm statistics are per rank on CPU, hence the tolerance),
    and an interrupted run resumed to the same weights, bit for bit."""
    from pathlib import Path

    from torchhand.salient.training_data import save_frames
    from train.salient_detector import main

    repo = Path(__file__).resolve().parents[1]
    cfg = _tiny_cfg(steps=6, batch_size=8, checkpoint_every=1, threads=1)
    cfg_file = tmp_path / "cfg.json"
    cfg_file.write_text(json.dumps({"steps": 6, "batch_size": 8, "crop": 48, "checkpoint_every": 1, "threads": 1,
                                    "network": cfg.network}))
    cache = tmp_path / "cache" / cfg.data_key()
    cache.mkdir(parents=True)
    save_frames(_fake_frames(12), cache / "train.npz")
    save_frames(_fake_frames(4), cache / "val.npz")
    common = ["--config", str(cfg_file), "--cache", str(tmp_path / "cache"), "--no-progress"]
    assert main(["--out", str(tmp_path / "one"), *common]) == 0
    for args in (["--out", str(tmp_path / "two")], ["--out", str(tmp_path / "cut"), "--stop-at", "3"],
                 ["--out", str(tmp_path / "cut"), "--resume"]):
        r = _torchrun(args + common, repo)
        assert r.returncode == 0, r.stderr[-3000:]

    def losses(run):
        return [json.loads(line)["loss"] for line in (tmp_path / run / "log.jsonl").read_text().splitlines()]

    one, two, cut = losses("one"), losses("two"), losses("cut")
    assert len(one) == len(two) == len(cut) == 6
    assert cut == two  # resumed exactly
    np.testing.assert_allclose(two, one, rtol=0.01)  # measured: within 0.07 %
    a = torch.load(tmp_path / "two" / "salient_fingertips.pt", weights_only=False)
    b = torch.load(tmp_path / "cut" / "salient_fingertips.pt", weights_only=False)
    for k in a["state_dict"]:
        torch.testing.assert_close(a["state_dict"][k], b["state_dict"][k], rtol=0, atol=0, msg=k)
    assert json.loads((tmp_path / "two" / "done.json").read_text())["world_size"] == 2


# ------------------------------------------------------------ colour (nails, Ballan)


def _random_colour_net(seed: int = 0) -> SalientNet:
    torch.manual_seed(seed)
    net = SalientNet(SalientConfig(channels=(4, 6), dilations=(1, 2), modality="colour"))
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.randn_like(p) * 0.5)
    return net.eval()


def test_colour_network_onnx_parity_and_save_load(tmp_path):
    ort = pytest.importorskip("onnxruntime")
    net = _random_colour_net(1)
    x = 255 * torch.rand(2, 3, 52, 36, generator=torch.Generator().manual_seed(0))
    path = export_onnx(net, tmp_path / "nails.onnx", height=48, width=64)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    assert [i.name for i in sess.get_inputs()] == ["rgb"]
    got = sess.run(None, {"rgb": x.numpy()})
    with torch.no_grad():
        ref = net(x)
    for name, a, b in zip(ref._fields, ref, got):
        np.testing.assert_allclose(b, a.numpy(), atol=1e-4, rtol=0, err_msg=name)
    net.save(tmp_path / "nails.pt")
    back = SalientDetector.load(tmp_path / "nails.pt")
    assert back.modality == "colour" and back.net.config == net.config
    onnx_det = SalientDetector.load_onnx(path)
    assert onnx_det.modality == "colour"
    image = (255 * np.random.default_rng(0).random((50, 70, 3))).astype(np.uint8)
    a, b = back.detect(image), onnx_det.detect(image)
    torch.testing.assert_close(a.uv, b.uv, atol=1e-3, rtol=0)
    assert float(a.depth.abs().sum()) == 0.0  # no depth on colour frames


def test_colour_detector_bad_input_is_named():
    det = SalientDetector(_random_colour_net())
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        det.detect(np.zeros((48, 64), np.float32))  # a depth frame given to the colour detector
    with pytest.raises(ValueError, match="0..255"):
        det.detect(np.full((48, 64, 3), 300.0, np.float32))
    with pytest.raises(TypeError, match="uint8 or float"):
        det.detect(np.zeros((48, 64, 3), np.int32))
    with pytest.raises(ValueError, match="RGB in 0..255"):
        det.net(torch.zeros(1, 1, 48, 64))
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        SalientDetector(_random_net()).detect(np.zeros((48, 64, 3), np.uint8))  # colour to the depth detector
    with pytest.raises(ValueError, match="modality"):
        SalientConfig(modality="infrared")
    with pytest.raises(ValueError, match="modality"):
        SalientDetector.load(modality="thermal")


@pytest.fixture(scope="module")
def colour_frames():
    from torchhand.data.synth import demo_motion
    from torchhand.salient.training_data import render_salient_frames

    # frames 30..33: cameras 0..3 of the ring (frame k by camera k mod 8)
    return render_salient_frames(demo_motion(frames=slice(30, 34)), seed=3, progress=False, modality="colour")


@pytest.mark.slow
def test_colour_frames_label_the_visible_nails(colour_frames):
    from torchhand.data.synth import demo_motion
    from torchhand.salient.training_data import VISIBLE_NAIL_MM2, render_salient_frames, visible_mm2

    f = colour_frames
    assert f.image.shape == (4, 480, 640, 3) and f.image.dtype == np.uint8 and visible_mm2(f) == VISIBLE_NAIL_MM2
    seen = (f.area_mm2 >= VISIBLE_NAIL_MM2).sum(1)
    assert seen.min() >= 1 and seen.sum() >= 20, seen  # every view sees nails, from the back most
    # a nail is part of its fingertip: never more visible area than the depth labels' tip
    depth = render_salient_frames(demo_motion(frames=slice(30, 31)), seed=3, progress=False, noise=None,
                                  background=False)
    assert (f.area_mm2[0] <= depth.area_mm2[0] + 1e-3).all() and float(f.area_mm2[0].sum()) > 0
    # the nail points are pale pixels: brighter than the mean of the hand's skin around them
    img = f.image[0].astype(np.float32).sum(-1)
    for (u, v), a in zip(f.uv[0], f.area_mm2[0]):
        if a >= 40:
            patch = img[int(round(v)) - 6: int(round(v)) + 7, int(round(u)) - 6: int(round(u)) + 7]
            assert img[int(round(v)), int(round(u))] >= np.median(patch) - 1, (u, v)
    with pytest.raises(ValueError, match="modality"):
        render_salient_frames(demo_motion(frames=slice(0, 1)), modality="ir", progress=False)


def test_shipped_nail_detector_finds_the_nails(colour_frames):
    from torchhand.salient import DEFAULT_NAIL_ONNX, DEFAULT_NAIL_WEIGHTS
    from torchhand.salient.training_data import VISIBLE_NAIL_MM2

    assert DEFAULT_NAIL_WEIGHTS.stat().st_size < 1_000_000 and DEFAULT_NAIL_ONNX.stat().st_size < 1_000_000
    det = SalientDetector.load(modality="colour")
    ort_det = SalientDetector.load_onnx(modality="colour")
    found = total = 0
    for k in range(len(colour_frames.image)):
        gt = colour_frames.uv[k][colour_frames.area_mm2[k] >= VISIBLE_NAIL_MM2]
        d = det.detect(colour_frames.image[k])
        top = d.uv[: len(gt)].numpy()  # as many detections as nails, the best first
        dist = np.linalg.norm(gt[:, None] - top[None], axis=-1)
        found += int((dist.min(1) <= 6.0).sum()) if dist.size else 0
        total += len(gt)
        o = ort_det.detect(colour_frames.image[k])
        torch.testing.assert_close(d.uv, o.uv, atol=1e-3, rtol=0)
    assert found >= 0.7 * total, (found, total)


def test_colour_training_batches_and_targets():
    from train.salient_detector import sample_batch, targets

    g = np.random.default_rng(0)
    n = 4
    image = (255 * g.random((n, 96, 128, 3))).astype(np.uint8)
    uv = np.full((n, 10, 2), np.nan, np.float32)
    z = np.full((n, 10), np.nan, np.float32)
    area = np.zeros((n, 10), np.float32)
    uv[:, :2] = g.uniform(20, 70, (n, 2, 2))
    z[:, :2] = 600.0
    area[:, :2] = [60.0, 5.0]  # one nail visible, one barely
    data = SalientFrames(image, uv, z, area, np.array(["fake"] * n))
    cfg = _tiny_cfg(modality="colour", crop=48, batch_size=4)
    x, tips, visible, ignore = sample_batch(data, cfg, torch.Generator().manual_seed(0))
    assert x.shape == (4, 3, 48, 48) and float(x.min()) >= 0 and float(x.max()) <= 255
    assert visible[:, 0].all() and ignore[:, 1].all()
    positive, weight, _ = targets(x, tips, visible, ignore, cfg)
    assert positive.shape == (4, 12, 12) and bool(positive.any()) and float(weight.min()) == 0.0
