"""Rigged models of articulated objects (thesis Ch. 6): the cotangent Laplacian, the
motion segmentation, the kinematic topology, the deformable tracking and ``torchhand rig``."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

pytest.importorskip("pygel3d")

from torchhand.data.chains import chain_joints, chain_motion, chain_object  # noqa: E402
from torchhand.io.assets import save_assets  # noqa: E402
from torchhand.io.thesis import FormatError  # noqa: E402
from torchhand.model.articulated import ArticulatedModel  # noqa: E402
from torchhand.reconstruction.deformable import DeformConfig, cotangent_laplacian, embed  # noqa: E402
from torchhand.reconstruction.motion_segments import merge_rigid_parts, segment_motion  # noqa: E402
from torchhand.reconstruction.rigging import Skeleton, build_rig, fit_rig  # noqa: E402
from torchhand.scoring.surfaces import vertex_errors  # noqa: E402


@pytest.fixture(scope="module")
def chain3():
    return chain_object((100.0, 90.0, 90.0), ("z", "y"), name="chain3")


def _trajectories(assets, frames=40, seed=3):
    """The first ``frames`` of a 200-frame chain motion (joint 1 bends to 60 degrees, joint
    2 bends and straightens again over frames 0-100)."""
    model = ArticulatedModel(assets, dtype=torch.float64)
    th = chain_motion(assets, 200, seed=seed).theta.double()[:100:100 // frames]
    with torch.no_grad():
        return model(th).vertices.numpy(), th


def test_cotangent_laplacian_of_a_sphere():
    import trimesh

    r = 50.0
    s = trimesh.creation.icosphere(subdivisions=4, radius=r)
    L = cotangent_laplacian(s.vertices, s.faces)
    assert np.abs(L @ np.ones(len(s.vertices))).max() < 1e-9  # constants are harmonic
    LV = L @ s.vertices
    # mean curvature normal 2H n = 2/r n, scaled by 2/3: the thesis' |A_i| is half the
    # one-ring's area, the Voronoi area about a third
    mag = np.linalg.norm(LV, axis=1)
    assert abs(mag.mean() - (2 / 3) * 2 / r) < 0.03 * 2 / r
    outward = (LV * s.vertices).sum(1) / (mag * r)
    assert outward.min() > 0.99  # along the normal (L = D - W: a vertex minus its neighbours' mean)


def test_embedding_carries_the_fine_mesh(chain3):
    emb = embed(chain3.vertices, chain3.faces, 800)
    assert len(emb.coarse_vertices) <= 820
    err = np.linalg.norm(emb.apply(emb.coarse_vertices) - chain3.vertices, axis=1)
    assert err.max() < 0.25 and err.mean() < 0.01  # open3d's closest points are float32
    # a rigid motion of the coarse mesh moves the fine one rigidly
    R = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    moved = emb.apply(emb.coarse_vertices @ R.T + [5, 0, 0])
    assert np.linalg.norm(moved - (chain3.vertices @ R.T + [5, 0, 0]), axis=1).max() < 0.25


@pytest.mark.slow
def test_motion_segmentation_finds_the_links(chain3):
    traj, _ = _trajectories(chain3)
    seg = segment_motion(traj, chain3.vertices, chain3.faces)
    assert seg.parts == 3
    # the thesis' interval (Eq. 6.7) sees this slow bend only at its higher threshold
    assert segment_motion(traj, chain3.vertices, chain3.faces, interval="thesis", refine=False).parts < 3
    assert segment_motion(traj, chain3.vertices, chain3.faces, interval="thesis", lambda_thr=0.9).parts == 3
    # each link's vertices (away from the blend zones) in one part
    x = chain3.vertices[:, 0]
    for lo, hi in ((-140, -50), (-30, 40), (60, 140)):
        sel = (x > lo) & (x < hi)
        assert np.bincount(seg.labels[sel]).max() > 0.98 * sel.sum()
    # an object that only moves rigidly is one part
    model = ArticulatedModel(chain3, dtype=torch.float64)
    _, th = _trajectories(chain3)
    th[:, 6:] = 0
    with torch.no_grad():
        rigid = model(th).vertices.numpy()
    assert segment_motion(rigid, chain3.vertices, chain3.faces).parts == 1


@pytest.mark.slow
def test_refinement_keeps_an_extra_cluster_only_where_it_is_a_joint(chain3):
    traj, _ = _trajectories(chain3)
    ev = segment_motion(traj, chain3.vertices, chain3.faces, refine=False).eigenvalues
    low = float(ev[1] + ev[2]) / 2  # a threshold that sees two clusters only
    two = segment_motion(traj, chain3.vertices, chain3.faces, lambda_thr=low, refine=False)
    assert two.clusters == 2 and two.parts == 2 and two.refined == ()
    seg = segment_motion(traj, chain3.vertices, chain3.faces, lambda_thr=low)
    # the third cluster survives the merge; the fourth is joined again, so it stops there
    assert seg.clusters == 3 and seg.parts == 3 and len(seg.refined) == 1 and "kept" in seg.refined[0]
    x = chain3.vertices[:, 0]
    for lo, hi in ((-140, -50), (-30, 40), (60, 140)):
        sel = (x > lo) & (x < hi)
        assert np.bincount(seg.labels[sel]).max() > 0.98 * sel.sum()
    # without the merge there is nothing to test a cut with: no refinement
    assert segment_motion(traj, chain3.vertices, chain3.faces, lambda_thr=low, merge_ratio=0).clusters == 2


def test_redundant_parts_are_joined(chain3):
    traj, _ = _trajectories(chain3)
    x = chain3.vertices[:, 0]
    links = np.digitize(x, chain_joints(chain3)[:, 0])  # the true links, cut at the joints
    # the middle link cut in two (a false joint), with a tracking-like error on top
    labels = np.where((links == 1) & (x > 5), 3, links)
    noisy = traj + np.random.default_rng(0).normal(0, 0.5, traj.shape)
    merged, lines = merge_rigid_parts(noisy, chain3.vertices, chain3.faces, labels)
    assert len(lines) == 1 and int(merged.max()) + 1 == 3
    for link in range(3):  # one part per link again
        assert len(np.unique(merged[links == link])) == 1
    assert len(np.unique(merged)) == 3 and len({merged[links == k][0] for k in range(3)}) == 3
    # the true joints are never joined, however small the ratio allowed
    kept, none = merge_rigid_parts(noisy, chain3.vertices, chain3.faces, links, merge_ratio=1.0)
    assert none == () and int(kept.max()) + 1 == 3
    with pytest.raises(ValueError, match="merge_ratio"):
        segment_motion(traj, chain3.vertices, chain3.faces, merge_ratio=-1)


@pytest.mark.slow
def test_rig_from_true_trajectories(chain3):
    traj, th = _trajectories(chain3)
    seg = segment_motion(traj, chain3.vertices, chain3.faces)
    rig = build_rig(chain3.vertices, chain3.faces, traj, seg.labels, "learned")
    assert rig.assets.num_bones == 3 and list(rig.assets.parents) in ([-1, 0, 1], [-1, 0, 0])
    true = chain_joints(chain3)
    d = np.linalg.norm(rig.joints[:, None] - true[None], axis=-1).min(0)
    assert d.max() < 1.0
    assert list(rig.joint_dofs) == [1, 1]  # hinges
    assert np.array_equal(rig.assets.vertices, chain3.vertices) and np.array_equal(rig.assets.faces, chain3.faces)
    model = ArticulatedModel(rig.assets, dtype=torch.float64)
    for f in (0, 20, 39):
        pose = fit_rig(model, traj[f])
        with torch.no_grad():
            v = model(pose[None]).vertices[0].numpy()
        assert np.linalg.norm(v - traj[f], axis=1).mean() < 1.5


def test_rig_of_a_coarse_chain_from_its_true_parts():
    """The default tier's rig: a coarse two-link chain (16 mm edges), its true links as
    the parts, ten frames of its motion."""
    chain = chain_object((110.0, 110.0), ("z",), edge=16.0, name="coarse")
    traj, _ = _trajectories(chain, frames=10)
    parts = np.digitize(chain.vertices[:, 0], chain_joints(chain)[:, 0])
    # the tube's axis as its curve skeleton (pygel3d's skeletonisation takes tens of seconds here)
    x = np.linspace(-110.0, 110.0, 23)
    skeleton = Skeleton(np.stack([x, 0 * x, 0 * x], 1), np.stack([np.arange(22), np.arange(1, 23)], 1),
                        np.abs(chain.vertices[:, :1] - x[None]).argmin(1))
    rig = build_rig(chain.vertices, chain.faces, traj, parts, "coarse", skeleton=skeleton)
    assert rig.assets.num_bones == 2 and list(rig.assets.parents) == [-1, 0]
    assert np.linalg.norm(rig.joints[0] - chain_joints(chain)[0]) < 3.0 and list(rig.joint_dofs) == [1]
    assert np.array_equal(rig.assets.vertices, chain.vertices) and np.array_equal(rig.assets.faces, chain.faces)
    model = ArticulatedModel(rig.assets, dtype=torch.float64)
    pose = fit_rig(model, traj[-1], iterations=10, samples=500)
    with torch.no_grad():
        v = model(pose[None]).vertices[0].numpy()
    assert np.linalg.norm(v - traj[-1], axis=1).mean() < 2.0


def test_stretch_term_keeps_edge_lengths_and_leaves_rotations_free(chain3):
    from scipy.sparse.linalg import spsolve

    from torchhand.reconstruction.deformable import _Problem, _stretch_rhs

    problem = _Problem(chain3.vertices, chain3.faces, DeformConfig())
    T = problem.template
    R = torch.as_tensor([[0.0, -0.6, 0.8], [0.6, 0.64, 0.48], [-0.8, 0.48, 0.36]], dtype=torch.float64)
    for free in (T, T @ R.T + torch.tensor([3.0, -2.0, 9.0], dtype=torch.float64)):  # no force on a rigid motion
        grad = problem.K3 @ free.numpy().reshape(-1) - _stretch_rhs(problem, free).reshape(-1)
        assert np.abs(grad).max() < 1e-9
    # a tube stretched by 20 % along its axis: one solve restores the template's edge lengths
    stretched = T * torch.tensor([1.2, 1.0, 1.0], dtype=torch.float64)
    rhs = _stretch_rhs(problem, stretched).reshape(-1)
    anchor = 1e-6 * stretched.numpy().reshape(-1)  # the translation the term does not fix
    import scipy.sparse as sp

    X = spsolve((problem.K3 + 1e-6 * sp.eye(problem.K3.shape[0])).tocsc(), rhs + anchor).reshape(-1, 3)
    i, j = problem.arap_i, problem.arap_j
    l0 = np.linalg.norm(chain3.vertices[i] - chain3.vertices[j], axis=1)
    before = np.abs(np.linalg.norm(stretched.numpy()[i] - stretched.numpy()[j], axis=1) - l0).mean()
    after = np.abs(np.linalg.norm(X[i] - X[j], axis=1) - l0).mean()
    assert after < 0.2 * before
    extent = X[:, 0].max() - X[:, 0].min()
    assert abs(extent - np.ptp(chain3.vertices[:, 0])) < 0.05 * np.ptp(chain3.vertices[:, 0])
    with pytest.raises(ValueError, match="stretch must be >= 0"):
        from torchhand.reconstruction.deformable import _gates

        _gates(DeformConfig(stretch=-1))


def test_vertex_errors_known_shift():
    v = np.random.default_rng(0).normal(size=(3, 50, 3)) * 40
    e = vertex_errors(v + [0, 0, 2.0], v)
    assert abs(e["mean_same_order_mm"] - 2.0) < 1e-9
    assert e["mean_closest_mm"] <= 2.0 + 1e-9
    assert vertex_errors(v, v)["mean_closest_mm"] == 0
    with pytest.raises(ValueError, match="same N"):
        vertex_errors(v, v[:2])


@pytest.fixture(scope="module")
def chain_sequence(tmp_path_factory):
    from torchhand.data.synth import write_synthetic_sequence

    root = tmp_path_factory.mktemp("rig")
    assets = chain_object((110.0, 110.0), ("z",), name="chain2")
    models = root / "models"
    models.mkdir()
    save_assets(assets, models / "chain2.npz")
    fr = chain_motion(assets, 20, seed=2)
    fr.theta[:, :6] = fr.theta[:1, :6]  # held in place
    fr.theta[:, 6] = torch.linspace(0, 0.8, 20)  # bends by 46 degrees, 2.3 a frame
    seq = write_synthetic_sequence(fr, root / "seq", noise="none", rgb=False, progress=False)
    return root, seq, assets


@pytest.mark.slow
def test_rig_folder_end_to_end(chain_sequence, monkeypatch):
    from torchhand.app.rig import rig_folder

    root, seq, assets = chain_sequence
    monkeypatch.setenv("TORCHHAND_MODELS", str(root / "models"))
    out = root / "rigged"
    log = rig_folder(seq, "chain2", out, deform=DeformConfig(max_vertices=800), progress=False)
    assert log["parts"] == 2, log["notes"]
    # the boundary centroid alone was 15 mm off here (the part near a small bend moves little)
    assert np.linalg.norm(np.asarray(log["joints_mm"])[0] - chain_joints(assets)[0]) < 8.0
    for name in ("model.npz", "segments.ply", "skeleton.png", "skeleton.json", "rig_log.json",
                 "deformable/vertices.npy", "track/theta.npy"):
        assert (out / name).is_file(), name
    tracked = np.load(out / "track" / "vertices" / f"{log['name']}.npy")
    assert tracked.shape == (20, len(assets.vertices), 3) and tracked.dtype == np.float32
    # scored against the truth in camera 0's coordinates
    from torchhand.data.layout import read_poses, read_sequence_info

    cam = read_sequence_info(seq).cameras[0].to(dtype=torch.float64)
    model = ArticulatedModel(assets, dtype=torch.float64)
    with torch.no_grad():
        truth = cam.to_camera(model(torch.as_tensor(read_poses(seq / "gt").theta)).vertices).numpy()
    assert vertex_errors(tracked, truth)["mean_closest_mm"] < 3.0
    assert json.loads((out / "skeleton.json").read_text())["parts"] == 2


def test_rig_bad_input(chain_sequence, monkeypatch, tmp_path):
    import trimesh

    from torchhand.app.rig import RigError, rig_folder

    root, seq, assets = chain_sequence
    monkeypatch.setenv("TORCHHAND_MODELS", str(root / "models"))
    with pytest.raises(RigError, match="at least 10 frames"):
        rig_folder(seq, "chain2", tmp_path / "a", frames=5)
    holed = trimesh.Trimesh(assets.vertices, assets.faces[:-10], process=False)
    holed.export(tmp_path / "holed.ply")
    with pytest.raises(FormatError, match="not closed"):
        rig_folder(seq, tmp_path / "holed.ply", tmp_path / "b")
    import dataclasses

    holed_model = dataclasses.replace(assets, name="holed", faces=assets.faces[:-10])
    save_assets(holed_model, tmp_path / "holed.npz")
    with pytest.raises(FormatError, match="template .*holed.npz: the mesh is not closed"):
        rig_folder(seq, tmp_path / "holed.npz", tmp_path / "b")
    metres = trimesh.Trimesh(assets.vertices / 1000, assets.faces, process=False)
    metres.export(tmp_path / "metres.ply")
    with pytest.raises(FormatError, match="metres"):
        rig_folder(seq, tmp_path / "metres.ply", tmp_path / "c")
    other = trimesh.creation.icosphere(radius=30)
    other.export(tmp_path / "ball.ply")
    with pytest.raises(RigError, match="template-pose"):
        rig_folder(seq, tmp_path / "ball.ply", tmp_path / "d")
    with pytest.raises(RigError, match="rigid"):
        rig_folder(seq, "chain2", tmp_path / "e", template_pose=np.eye(4) * 2)
    with pytest.raises(RigError, match="not in the sequence"):
        rig_folder(seq, "chain2", tmp_path / "f", hands=["hand_right"])
    assert not any((tmp_path / n).exists() for n in "abcdef")


@pytest.mark.slow
def test_rigid_object_gives_a_rigid_model(tmp_path, monkeypatch):
    from torchhand.app.rig import rig_folder
    from torchhand.data.synth import write_synthetic_sequence

    assets = chain_object((110.0, 110.0), ("z",), name="stiff")
    (tmp_path / "models").mkdir()
    save_assets(assets, tmp_path / "models" / "stiff.npz")
    monkeypatch.setenv("TORCHHAND_MODELS", str(tmp_path / "models"))
    fr = chain_motion(assets, 12, seed=4, amplitude_deg=0.0)
    seq = write_synthetic_sequence(fr, tmp_path / "seq", noise="none", rgb=False, progress=False)
    log = rig_folder(seq, "stiff", tmp_path / "out", deform=DeformConfig(max_vertices=600), progress=False,
                     track=False)
    assert log["parts"] == 1 and "rigid" in log["notes"][0]
    from torchhand.io.assets import load_assets

    model = load_assets(tmp_path / "out" / "model.npz")
    assert model.num_bones == 1 and not model.slot_used.any()


def test_rig_command_line(chain_sequence, monkeypatch, tmp_path, capsys):
    from torchhand.app.cli import main

    root, seq, _ = chain_sequence
    monkeypatch.setenv("TORCHHAND_MODELS", str(root / "models"))
    assert main(["rig", str(seq), "--template", str(tmp_path / "none.ply"), "--out", str(tmp_path / "o")]) == 2
    assert "none.ply not found" in capsys.readouterr().err
    assert main(["rig", str(seq), "--template", "chain2", "--out", str(tmp_path / "o"), "--frames", "4"]) == 2
    assert "at least 10 frames" in capsys.readouterr().err
    pose = tmp_path / "pose.json"
    pose.write_text("[[1, 0, 0]]")
    assert main(["rig", str(seq), "--template", "chain2", "--out", str(tmp_path / "o"), "--template-pose",
                 str(pose)]) == 2
    assert "rigid (4, 4)" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
