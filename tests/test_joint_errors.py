"""MPJPE, PA-MPJPE, root-relative MPJPE, PCK/AUC and 2D px with validity masks
(torchhand.scoring.metrics), each against a slow, obviously correct reference."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import orthogonal_procrustes
from scipy.optimize import minimize, minimize_scalar
from scipy.spatial.transform import Rotation

from torchhand.scoring.metrics import (PCK_THRESHOLDS_MM, auc, joint_errors, joint_scores, mean_px, mpjpe, pa_mpjpe,
                                       pck_curve, per_joint_mean, rr_mpjpe, similarity_align, valid_joints)

RNG = np.random.default_rng(0)


def hands(n=6, p=21):
    return RNG.normal(0.0, 40.0, (n, p, 3)) + np.array([0.0, 0.0, 600.0])


def similar(x, seed=1):
    """x (N, P, 3) moved by a random similarity per frame, and the transforms."""
    rng = np.random.default_rng(seed)
    R = Rotation.random(len(x), random_state=seed).as_matrix()
    s = rng.uniform(0.5, 2.0, len(x))
    t = rng.normal(0.0, 100.0, (len(x), 1, 3))
    return s[:, None, None] * np.einsum("nij,npj->npi", R, x) + t


def slow_pa_error(pred, gt):
    """One frame: centre, scipy's orthogonal Procrustes (a rotation when it is one), then
    the best scale by a 1-D search."""
    a, b = pred - pred.mean(0), gt - gt.mean(0)
    R, _ = orthogonal_procrustes(a, b)
    assert np.linalg.det(R) > 0  # the data below never needs a reflection
    res = minimize_scalar(lambda s: np.square(s * a @ R - b).sum(), bounds=(1e-3, 1e3), method="bounded",
                          options=dict(xatol=1e-12))
    return np.linalg.norm(res.x * a @ R - b, axis=-1).mean()


def test_similar_copies_have_zero_pa_error():
    gt = hands()
    pred = similar(gt)
    assert mpjpe(pred, gt) > 10.0
    assert pa_mpjpe(pred, gt) == pytest.approx(0.0, abs=1e-8)
    np.testing.assert_allclose(similarity_align(pred, gt), gt, atol=1e-8)


def test_a_reflected_copy_is_not_aligned():
    gt = hands()
    pred = gt * np.array([-1.0, 1.0, 1.0])
    assert pa_mpjpe(pred, gt) > 5.0


def test_pa_mpjpe_matches_the_slow_reference():
    gt = hands(n=5)
    pred = similar(gt + RNG.normal(0.0, 3.0, gt.shape), seed=3)
    ref = np.mean([slow_pa_error(p, g) for p, g in zip(pred, gt)])
    assert pa_mpjpe(pred, gt) == pytest.approx(ref, rel=1e-6)


def test_pa_fit_is_optimal_in_least_squares():
    """No similarity found by a general optimiser fits better than the closed form."""
    gt = hands(n=1, p=8)
    pred = gt[0] + RNG.normal(0.0, 10.0, gt[0].shape)
    ours = np.square(similarity_align(pred[None], gt)[0] - gt[0]).sum()

    def cost(v):
        return np.square(np.exp(v[0]) * Rotation.from_rotvec(v[1:4]).apply(pred) + v[4:] - gt[0]).sum()

    best = minimize(cost, np.r_[0.0, 0.0, 0.0, 0.0, gt[0].mean(0) - pred.mean(0)], method="BFGS").fun
    assert ours <= best + 1e-6
    assert ours == pytest.approx(best, rel=1e-4)


def test_absent_joints_are_left_out_not_zero():
    gt = hands(n=4)
    pred = gt + 5.0 / np.sqrt(3.0)  # every joint 5 mm off
    bad = gt.copy()
    bad[0, 3] = np.nan
    bad[1, 7] = -1.0  # a dataset's missing joint
    mask = np.ones(gt.shape[:2], bool)
    mask[2, 11] = False
    pred_far = pred.copy()
    pred_far[[0, 1, 2], [3, 7, 11]] = 1e6  # far predictions of absent joints change nothing
    assert valid_joints(bad, mask).sum() == gt.shape[0] * gt.shape[1] - 3
    assert mpjpe(pred_far, bad, mask) == pytest.approx(5.0)
    e = joint_errors(pred_far, bad, mask)
    assert np.isnan(e[[0, 1, 2], [3, 7, 11]]).all()
    assert rr_mpjpe(pred_far, bad, mask) == pytest.approx(0.0, abs=1e-9)
    assert pa_mpjpe(pred_far, bad, mask) == pytest.approx(0.0, abs=1e-8)
    assert np.isnan(mpjpe(pred, np.full_like(gt, np.nan)))


def test_a_present_joint_without_prediction_is_an_error():
    gt = hands(n=1)
    pred = gt.copy()
    pred[0, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite prediction"):
        mpjpe(pred, gt)


def test_root_relative_against_a_loop():
    gt = hands(n=3)
    pred = gt + RNG.normal(0.0, 4.0, gt.shape)
    ref = np.mean([np.linalg.norm((p - p[0]) - (g - g[0]), axis=-1).mean() for p, g in zip(pred, gt)])
    assert rr_mpjpe(pred, gt) == pytest.approx(ref)
    gt_no_root = gt.copy()
    gt_no_root[1, 0] = np.nan  # frame 1 has no wrist: left out
    ref = np.mean([np.linalg.norm((p - p[0]) - (g - g[0]), axis=-1).mean() for p, g in zip(pred[[0, 2]], gt[[0, 2]])])
    assert rr_mpjpe(pred, gt_no_root) == pytest.approx(ref)


def test_scores_table_pck_and_auc():
    gt = hands(n=4)
    pred = gt + RNG.normal(0.0, 8.0, gt.shape)
    gt[0, 5] = np.nan
    s = joint_scores(pred, gt)
    e = np.linalg.norm(pred - gt, axis=-1)
    assert s.mpjpe_mm == pytest.approx(np.nanmean(e))
    assert s.per_joint_mm.shape == (21,)
    np.testing.assert_allclose(s.per_joint_mm, np.nanmean(e, 0))
    curve = pck_curve(e[~np.isnan(e)])
    np.testing.assert_allclose(s.pck, curve)
    assert s.auc_0_50 == pytest.approx(auc(PCK_THRESHOLDS_MM, curve))
    assert s.pa_mpjpe_mm <= s.mpjpe_mm and s.rr_mpjpe_mm > 0
    same = joint_scores(gt, gt)
    assert (same.mpjpe_mm, same.rr_mpjpe_mm, same.auc_0_50) == (0.0, 0.0, 1.0)
    assert same.pa_mpjpe_mm == pytest.approx(0.0, abs=1e-8)


def test_mean_px_with_visibility_per_camera():
    gt = RNG.uniform(0.0, 640.0, (3, 2, 21, 2))  # (N, C, P, 2)
    pred = gt + np.array([3.0, 4.0])  # 5 px everywhere
    pred[:, 1, :4] += 100.0
    visible = np.ones(gt.shape[:3], bool)
    visible[:, 1, :4] = False  # occluded in camera 1
    assert mean_px(pred, gt, visible) == pytest.approx(5.0)
    assert mean_px(pred, gt) > 5.0
    per_camera = per_joint_mean(np.moveaxis(joint_errors(pred, gt, visible), 1, -1))
    np.testing.assert_allclose(per_camera, [5.0, 5.0])
