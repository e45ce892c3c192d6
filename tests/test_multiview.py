"""Tracking with camera rigs: the view problems of the tracker, the colour terms (edges,
optical flow) and their bad input."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
import torch

from torchhand.data.layout import camera_dir, frame_name, read_depth, read_rgb, read_sequence_info
from torchhand.data.synth import demo_motion, with_camera_ring, write_synthetic_sequence
from torchhand.geometry.camera import Camera
from torchhand.model.scene import Scene
from torchhand.tracking.energies import Edges, OpticalFlow, default_priors, parse_energy
from torchhand.tracking.preprocess import preprocess_colour
from torchhand.tracking.tracker import Tracker, TrackerConfig

F64 = torch.float64


@pytest.fixture(scope="module")
def ring(tmp_path_factory):
    """The demo's first three frames seen by a ring of 8 cameras (shaded colour, clean
    depth): (scene, cameras, gt theta (3, D), colour [frame][view], depth [frame][view])."""
    frames = with_camera_ring(demo_motion(slice(0, 3), dtype=F64), 8)
    root = write_synthetic_sequence(frames, tmp_path_factory.mktemp("ring") / "seq", noise="none", colour="shaded",
                                    progress=False)
    info = read_sequence_info(root)
    colour = [[read_rgb(camera_dir(root, k) / "rgb" / frame_name(f)) for k in range(8)] for f in range(3)]
    depth = [[read_depth(camera_dir(root, k) / "depth" / frame_name(f)) for k in range(8)] for f in range(3)]
    nails = np.load(root / "gt" / "salient_2d.npy"), np.load(root / "gt" / "salient_visible.npy")
    return frames.scene, info.cameras, torch.as_tensor(np.load(root / "gt" / "theta.npy")), colour, depth, nails


def _shifted(scene, theta, shift) -> torch.Tensor:
    """theta with every model moved by ``shift`` (mm)."""
    out = theta.clone()
    for sl in scene.slices.values():
        out[:, sl.start : sl.start + 3] += torch.tensor(shift, dtype=theta.dtype)
    return out


def _keypoint_error(scene, a, b) -> float:
    with torch.no_grad():
        return float((scene(a).keypoints - scene(b).keypoints).norm(dim=-1).mean())


@pytest.mark.slow
def test_a_rig_of_one_camera_is_the_single_camera_tracker(ring):
    scene, cams, gt, _, depth, _ = ring
    start = _shifted(scene, gt[:1], [4.0, -3.0, 5.0])
    cfg = TrackerConfig(max_iterations=6, first_frame_iterations=6)
    single = Tracker(scene, cfg).track_frame([depth[0][0]], [cams[0]], start, first=True)
    rig = Tracker(scene, cfg).track_frame([[depth[0][0]]], [[cams[0]]], start, first=True)
    assert torch.equal(single.theta, rig.theta) and torch.equal(single.energy, rig.energy)


def test_a_rigs_views_are_cut_to_their_hands_with_the_same_geometry(ring):
    from torchhand.tracking.views import crop_views

    scene, cams, gt, _, depth, _ = ring
    tracker = Tracker(scene, TrackerConfig())
    with torch.no_grad():
        posed = scene(gt[:1])
    views, rigs = crop_views([depth[0][:4]], [tuple(cams[:4])], posed.vertices, tracker.renderer, 8)
    (h, w), (H, W) = views[0][0].shape, depth[0][0].shape
    assert h * w < 0.6 * H * W and all(c.width == w and c.height == h for c in rigs[0])
    for d, full, cam, crop in zip(views[0], depth[0][:4], cams[:4], rigs[0]):
        dc, dr = float(cam.cx - crop.cx), float(cam.cy - crop.cy)  # the crop's origin in the image
        assert dc == int(dc) and dr == int(dr) and np.array_equal(d, full[int(dr):int(dr) + h, int(dc):int(dc) + w])
        uv, uv_crop = cam.project(posed.keypoints), crop.project(posed.keypoints)
        torch.testing.assert_close(uv_crop + torch.tensor([dc, dr], dtype=uv.dtype), uv)
        assert d[d > 0].size and (d > 0).sum() == (full > 0).sum()  # every hand pixel kept
    # a pose before the cameras leaves the views whole
    far = _shifted(scene, gt[:1], [0.0, 0.0, -2000.0])
    with torch.no_grad():
        same = crop_views([depth[0][:4]], [tuple(cams[:4])], scene(far).vertices, tracker.renderer, 8)
    assert same[0][0][0] is depth[0][0] and same[1][0][0] is cams[0]


@pytest.mark.slow
def test_a_rig_tracked_on_cut_views_and_a_shared_budget_lands_where_whole_views_do(ring):
    scene, cams, gt, _, depth, _ = ring
    start = _shifted(scene, gt[:1], [4.0, -3.0, 5.0])
    cfg = TrackerConfig(max_iterations=4, first_frame_iterations=4, rig_budget=None)
    runs = {}
    for name, c in (("whole", replace(cfg, crop_views=False)), ("cut", cfg), ("budget", replace(cfg, rig_budget=2.0))):
        runs[name] = Tracker(scene, c).track_frame([depth[0][:4]], [cams[:4]], start, first=True)
    from torchhand.tracking.views import CROP_MARGIN, crop_views

    with torch.no_grad():  # the tracker's cut at this start is a real one
        cut, _ = crop_views([depth[0][:4]], [tuple(cams[:4])], scene(start).vertices, Tracker(scene, cfg).renderer,
                            cfg.render_margin + CROP_MARGIN)
    assert cut[0][0].size < 0.8 * depth[0][0].size
    assert _keypoint_error(scene, runs["cut"].theta, runs["whole"].theta) < 0.05
    assert _keypoint_error(scene, runs["budget"].theta, gt[:1]) < _keypoint_error(scene, start, gt[:1]) / 4
    # four views on a budget of two: about half the pairs of the whole caps
    assert 0.3 < int(runs["budget"].correspondences[0]) / int(runs["cut"].correspondences[0]) < 0.7
    assert Tracker(scene, TrackerConfig()).frame_states.share(8) == 0.25
    with pytest.raises(ValueError, match="rig_budget"):
        TrackerConfig(rig_budget=0.0)


@pytest.mark.slow
def test_depth_views_of_a_rig_are_tracked_together(ring):
    scene, cams, gt, _, depth, _ = ring
    start = _shifted(scene, gt[:1], [6.0, -4.0, 8.0])
    cfg = TrackerConfig(max_iterations=15, first_frame_iterations=15)
    res = Tracker(scene, cfg).track_frame([depth[0][:3]], [cams[:3]], start, first=True)
    assert _keypoint_error(scene, start, gt[:1]) > 8.0
    assert _keypoint_error(scene, res.theta, gt[:1]) < 1.0
    one = Tracker(scene, cfg).track_frame([depth[0][0]], [cams[0]], start, first=True)
    assert int(res.correspondences[0]) > 1.5 * int(one.correspondences[0])  # every view's pairs count


@pytest.mark.slow
@pytest.mark.parametrize("energy, limit", [("E+C", 2.5), ("E+C+O", 1.5)])
def test_colour_views_are_tracked_by_edges_and_flow(ring, energy, limit):
    scene, cams, gt, colour, _, _ = ring
    tracker = Tracker(scene, TrackerConfig(energy=energy))
    theta, errors = gt[:1], []
    for f in range(3):
        res = tracker.track_frame(None, [cams], theta, first=(f == 0), colours=[colour[f]])
        assert bool(res.valid[0]), res.notes
        theta = res.theta
        errors.append(_keypoint_error(scene, theta, gt[f : f + 1]))
    assert np.mean(errors) < limit, errors


@pytest.mark.slow
def test_models_outside_the_view_find_no_pairs_and_stay_in_place(ring):
    """Models beside the view (in front of the camera, outside its image): the cropped
    renders are empty, and the frame stays where it was (only the priors act) with a
    note, in colour and depth."""
    scene, cams, gt, colour, depth, _ = ring
    aside = cams[0].T_cw[0, :3].to(F64) * 2000.0  # the camera's x axis in the world: 2 m to its right
    away = _shifted(scene, gt[:1], aside.tolist())
    cfg = dict(max_iterations=3, first_frame_iterations=3)
    runs = [("E+C+O", None, [[colour[0][0]]]), ("LO", [[depth[0][0]]], None)]
    for energy, depths, colours in runs:
        res = Tracker(scene, TrackerConfig(energy=energy, **cfg)).track_frame(depths, [[cams[0]]], away, first=True,
                                                                              colours=colours)
        assert int(res.correspondences[0]) == 0, energy
        assert "no correspondences" in res.notes[0], (energy, res.notes)
        assert torch.isfinite(res.theta).all(), energy
        for sl in scene.slices.values():  # no data term moves the models
            assert (res.theta[0, sl.start : sl.start + 3] - away[0, sl.start : sl.start + 3]).abs().max() < 0.5


@pytest.mark.slow
def test_larger_images_of_the_ring_are_tracked_closer(tmp_path):
    """Nothing in the colour terms assumes 640x480, and the pixel is what limits them: from
    the true pose, the edges of 4 views at twice the size (the same field of view) keep
    the hands closer to it than at the thesis' size."""
    errors = []
    for scale in (1, 2):
        frames = with_camera_ring(demo_motion(slice(0, 1), dtype=F64), 4, scale=scale)
        root = write_synthetic_sequence(frames, tmp_path / f"x{scale}", noise="none", colour="shaded", depth=False,
                                        progress=False)
        info = read_sequence_info(root)
        assert {(c.width, c.height, c.fx) for c in info.cameras} == {(640 * scale, 480 * scale, 525.0 * scale)}
        colour = [read_rgb(camera_dir(root, k) / "rgb" / frame_name(0)) for k in range(4)]
        gt = torch.as_tensor(np.load(root / "gt" / "theta.npy"))
        res = Tracker(frames.scene, TrackerConfig(energy="E+C")).track_frame(None, [info.cameras], gt, first=True,
                                                                              colours=[colour])
        assert bool(res.valid[0]), res.notes
        errors.append(_keypoint_error(frames.scene, res.theta, gt))
    assert errors[1] < 2.0 and errors[1] < 0.8 * errors[0], errors


def test_edge_pairs_at_the_true_pose_are_close(ring):
    scene, cams, gt, colour, _, _ = ring
    tracker = Tracker(scene, TrackerConfig(energy="E"))
    cols = [preprocess_colour(colour[0][k], cams[k], dtype=F64) for k in range(8)]
    view, _ = tracker.states(gt[:1], [None] * 8, list(cams), colours=cols, views=8)
    term = Edges()
    found = term.prepare(view)
    assert bool((found.counts.correspondences > 50).all())  # every view sees edges of the hands
    res = term.residuals(view.theta, view.posed, found, jacobian=False)
    d = res.r.view(8, -1, 2).norm(dim=-1)[res.mask > 0]
    assert float(d.median()) < 1.5  # mm: about a pixel


@pytest.mark.parametrize("make", [Edges, lambda: OpticalFlow(sigma=None)], ids=["edges", "flow"])
def test_colour_term_jacobians_match_finite_differences(ring, make):
    scene, cams, gt, colour, _, _ = ring
    tracker = Tracker(scene, TrackerConfig(energy="E"))
    prev = [preprocess_colour(colour[0][k], cams[k], dtype=F64) for k in range(2)]
    cols = [preprocess_colour(colour[1][k], cams[k], previous=prev[k].gray, dtype=F64) for k in range(2)]
    theta = _shifted(scene, gt[1:2], [1.0, -1.0, 2.0])
    view, _ = tracker.states(theta, [None] * 2, list(cams[:2]), previous=gt[:1], colours=cols, views=2)
    term = make()
    prepared = term.prepare(view)
    assert int(prepared.counts.correspondences.sum()) > 50
    res = term.residuals(view.theta, view.posed, prepared, jacobian=True)
    eps = 1e-6
    for j in (0, 2, 4, 10, 30):
        tp = view.theta.clone()
        tp[:, j] += eps
        fd = (term.residuals(tp, scene(tp), prepared, jacobian=False).r - res.r) / eps
        assert torch.allclose(fd, res.J[:, :, j], atol=1e-4 * max(1.0, float(res.J[:, :, j].abs().max())))


def test_rig_bad_input_is_named(ring):
    scene, cams, gt, colour, depth, _ = ring
    tracker = Tracker(scene, TrackerConfig(energy="E+C"))
    with pytest.raises(ValueError, match="needs colour images"):
        tracker.track_frame([depth[0][:2]], [cams[:2]], gt[:1])
    with pytest.raises(ValueError, match="needs depth frames"):
        Tracker(scene, TrackerConfig(energy="LO")).track_frame(None, [cams[:2]], gt[:1], colours=[colour[0][:2]])
    with pytest.raises(ValueError, match=r"views \[1\] have no colour image"):
        tracker.track_frame(None, [cams[:2]], gt[:1], colours=[[colour[0][0], None]])
    with pytest.raises(ValueError, match="3 colour images for a rig of 2 views"):
        tracker.track_frame(None, [cams[:2]], gt[:1], colours=[colour[0][:3]])
    small = Camera(cams[1].K, cams[1].T_cw, 320, 240)
    with pytest.raises(ValueError, match="same image size"):
        tracker.track_frame(None, [[cams[0], small]], gt[:1], colours=[colour[0][:2]])
    with pytest.raises(ValueError, match=r"shape \(480, 640, 3\)"):
        tracker.track_frame(None, [cams[:2]], gt[:1], colours=[[colour[0][0], colour[0][1][:100]]])
    # a whole frame missing is a frame without data: the pose is kept and flagged
    res = tracker.track_frame(None, [cams[:2]], gt[:1], colours=[None])
    assert not bool(res.valid[0]) and "missing colour frame" in res.notes[0]
    assert [t.needs for t in parse_energy("E+O+C")][:3] == ["colour", "colour", None]


@pytest.mark.slow
def test_track_command_on_colour_views(tmp_path, capsys):
    from torchhand.app.cli import main

    seq, out = tmp_path / "views", tmp_path / "out"
    assert main(["synth", "--demo", "--frames", ":3", "--views", "4", "--protocol", "ballan", "--out", str(seq)]) == 0
    assert main(["track", str(seq), "--energy", "E+C+O", "--viz", "--out", str(out)]) == 0
    res = out / read_sequence_info(seq).name
    kp2 = np.load(res / "keypoints_2d.npy")
    assert kp2.shape[:2] == (3, 4)  # every frame in every camera
    import cv2

    for c in range(4):
        overlay = cv2.imread(str(res / "overlays" / f"cam{c}" / frame_name(2)))
        assert overlay is not None and overlay.shape[:2] == (480, 640), c
    video = cv2.VideoCapture(str(res / "overlays.mp4"))
    assert int(video.get(cv2.CAP_PROP_FRAME_COUNT)) == 3  # one picture of every view per frame
    video.release()
    assert "fit: not measured (no depth views)" in capsys.readouterr().out  # not "IoU nan"
    assert main(["eval", str(res), "--gt", str(seq), "--json", str(tmp_path / "eval.json")]) == 0
    import json

    report = json.loads((tmp_path / "eval.json").read_text())
    assert report["models"]["hand_right"]["mean_mm"] < 12.0, report["models"]  # 4 views, the noise protocol
    # the depth terms on colour views: a clear message, nothing written
    capsys.readouterr()
    assert main(["track", str(seq), "--out", str(tmp_path / "lo")]) == 1
    err = capsys.readouterr().err
    name = read_sequence_info(seq).name
    assert (f"torchhand track: error: {name}: {seq}: colour views only (sequence.json has_depth false, "
            "no depth/), but the energy's terms read depth") in err
    assert "; nothing written" in err and "torchhand track: 1 of 1 sequences failed" in err
    assert not (tmp_path / "lo" / name).exists()


@pytest.mark.slow
def test_nails_pull_the_salient_vertices_onto_their_detections(ring):
    from torchhand.tracking.energies import Nails
    from torchhand.tracking.preprocess import ColourView

    scene, cams, gt, colour, _, (uv, seen) = ring
    views = []
    for k in range(8):  # the true nail centres a camera sees, and one false detection far from any
        det = np.concatenate([uv[0, k][seen[0, k]], [[5.0, 5.0]]])
        views.append(ColourView(colour[0][k], None, det))
    start = _shifted(scene, gt[:1], [5.0, -4.0, 3.0])
    cfg = TrackerConfig(first_frame_iterations=15)
    res = Tracker(scene, cfg, [Nails()] + default_priors()).track_frame(None, [cams], start, first=True,
                                                                         colours=[views])
    # ten nails in eight views: the hands' global position is found from them alone
    assert int(res.correspondences[0]) >= 20
    assert _keypoint_error(scene, res.theta, gt[:1]) < 0.5 * _keypoint_error(scene, start, gt[:1])
    with pytest.raises(ValueError, match="gate_px"):
        Nails(gate_px=0)


@pytest.mark.slow
def test_the_swarm_never_returns_worse_than_its_start(ring):
    scene, cams, gt, colour, _, _ = ring
    start = _shifted(scene, gt[:1], [3.0, 0.0, 0.0])
    cfg = TrackerConfig(energy="E+C", solver="pso", particles=4, generations=2)
    res = Tracker(scene, cfg).track_frame(None, [cams[:2]], start, colours=[colour[0][:2]])
    assert bool(res.valid[0]) and int(res.iterations[0]) == 2
    tracker = Tracker(scene, replace(cfg, swarm_spread=(0.0, 0.0, 0.0)))  # every particle at the start
    still = tracker.track_frame(None, [cams[:2]], start, colours=[colour[0][:2]])
    assert torch.equal(still.theta, tracker.clamp(start))
    tracker.reset(start)  # a box of its own (the swarm's (B, D) bounds): the same box, the same result
    own = tracker.track_frame(None, [cams[:2]], start, colours=[colour[0][:2]])
    assert tracker.bounds[0].shape == start.shape and torch.equal(own.theta, still.theta)
    assert 0 < float(res.energy[0]) <= float(still.energy[0]) + 1e-9
    with pytest.raises(ValueError, match="particles"):
        TrackerConfig(solver="pso", particles=1)
    with pytest.raises(ValueError, match="solver"):
        TrackerConfig(solver="hope")


def test_the_default_prediction_follows_the_energy_and_the_scene():
    assert TrackerConfig().motion_prediction() == 1.0  # hands and rigid objects: constant velocity
    assert TrackerConfig().motion_prediction(chains=True) == 0.0  # depth on a rope: the previous pose
    assert TrackerConfig(energy="E+C+O+S").motion_prediction(chains=True) == 1.0  # colour views
    assert TrackerConfig(energy="LO+E").motion_prediction(chains=True) == 0.0
    assert TrackerConfig(energy="E+C", prediction=0.5).motion_prediction(chains=True) == 0.5
    assert Tracker(Scene.from_names(["hand_right", "hand_left", "rope"])).has_chains
    assert not Tracker(Scene.from_names(["hand_right", "hand_left", "ball", "pipe"])).has_chains
    with pytest.raises(ValueError, match="prediction"):
        TrackerConfig(prediction=-1.0)


def test_a_rig_of_mixed_image_sizes_is_refused_by_name(tmp_path):
    import json

    from torchhand.app.runner import TrackOptions, track_sequences

    seq = tmp_path / "views"
    write_synthetic_sequence(with_camera_ring(demo_motion(slice(0, 1)), 2), seq, colour="shaded", depth=False,
                             progress=False)
    meta = json.loads((seq / "sequence.json").read_text())
    meta["cameras"][1]["width"], meta["cameras"][1]["height"] = 320, 240
    (seq / "sequence.json").write_text(json.dumps(meta))
    [summary] = track_sequences([seq], tmp_path / "out", TrackOptions(TrackerConfig(energy="E+C")), progress=False)
    assert summary["status"] == "failed" and "camera 1 is 320x240 px" in summary["error"]
    assert not (tmp_path / "out" / "demo").exists()


@pytest.mark.slow
def test_nail_detections_come_from_salient_json_or_the_shipped_detector(tmp_path):
    """``--nails auto`` reads each camera's ``salient.json``; ``--nails detector`` (and a
    camera without the file, e.g. a user's own recording) runs the shipped colour nail
    detector, whose detections lie on the nails."""
    import json

    from torchhand.app.cli import main
    from torchhand.app.frames import FrameReader as _Frames
    from torchhand.app.options import NAIL_DETECTIONS

    seq = tmp_path / "views"
    assert main(["synth", "--demo", "--frames", ":2", "--views", "3", "--protocol", "ballan", "--out", str(seq)]) == 0
    info = read_sequence_info(seq)
    listed = json.loads((camera_dir(seq, 1) / "salient.json").read_text())["frames"][0]
    (camera_dir(seq, 2) / "salient.json").unlink()  # camera 2 as a user's own recording
    auto = _Frames([seq], [info], 2, [None], views=3, depth=False, colour=True, nails="auto")
    np.testing.assert_allclose(auto._colour_view(0, 1, 0).salient, np.reshape(listed, (-1, 2)))  # the file's
    frames = _Frames([seq], [info], 2, [None], views=3, depth=False, colour=True, nails="detector")
    assert not np.array_equal(frames._colour_view(0, 1, 0).salient, auto._colour_view(0, 1, 0).salient)
    np.testing.assert_array_equal(auto._colour_view(0, 2, 0).salient, frames._colour_view(0, 2, 0).salient)
    uv, seen = np.load(seq / "gt" / "salient_2d.npy"), np.load(seq / "gt" / "salient_visible.npy")
    found = total = on_nail = detections = 0
    for c in range(3):
        det = frames._colour_view(0, c, 0).salient
        assert det.shape[1] == 2 and len(det) <= NAIL_DETECTIONS
        if len(det):  # on a nail, seen or partly hidden (its centre vertex behind the finger)
            on_nail += int((np.linalg.norm(det[:, None] - uv[0, c][None], axis=-1).min(1) <= 8.0).sum())
            detections += len(det)
        gt = uv[0, c][seen[0, c]]
        if len(det) and len(gt):
            found += int((np.linalg.norm(gt[:, None] - det[None], axis=-1).min(1) <= 8.0).sum())
        total += len(gt)
    # under the protocol's 100 circles a frame: most detections are nails, most seen nails found
    assert total >= 10 and found >= 0.7 * total and on_nail >= 0.6 * detections, (found, total, on_nail, detections)
    out = tmp_path / "out"
    assert main(["track", str(seq), "--energy", "E+C+S", "--nails", "detector", "--out", str(out)]) == 0
    log = json.loads((out / info.name / "track_log.json").read_text())
    assert log["settings"]["nails"] == "detector"


def test_a_segmented_rig_keeps_each_views_hands_and_leaves_a_blind_view_unknown(tmp_path):
    from torchhand.app.frames import read_rig_frame
    from torchhand.data.layout import read_sequence_info
    from torchhand.tracking.segmentation import SegmentConfig, SegmentationError

    frames = with_camera_ring(demo_motion(slice(0, 1), dtype=F64), 2)
    frames = frames.__class__(Scene.from_names(["hand_right"], dtype=F64),
                              frames.theta[:, frames.scene.slices["hand_right"]], frames.cameras, "rig", {})
    seq = write_synthetic_sequence(frames, tmp_path / "seq", noise="none", depth=True, rgb=False, progress=False)
    info = read_sequence_info(seq)
    blind = camera_dir(seq, 1) / "depth" / frame_name(0)
    cv2.imwrite(str(blind), np.zeros((info.cameras[1].height, info.cameras[1].width), np.uint16))
    views, seg0 = read_rig_frame(seq, info, 0, SegmentConfig(mode="blobs"))
    assert len(views) == 2 and seg0 is not None and seg0.mask.any()
    assert np.isnan(views[1]).all()  # camera 1 sees no hand: all unknown, it costs nothing
    assert (views[0][~seg0.mask & ~np.isnan(views[0])] == 0).all()
    cv2.imwrite(str(camera_dir(seq, 0) / "depth" / frame_name(0)),
                np.zeros((info.cameras[0].height, info.cameras[0].width), np.uint16))
    with pytest.raises(SegmentationError, match="no view finds a hand"):
        read_rig_frame(seq, info, 0, SegmentConfig(mode="blobs"))
