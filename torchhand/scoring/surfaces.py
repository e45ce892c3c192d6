"""Scores of a reconstructed surface and of an estimated object trajectory against the
truth (in-hand scanning, thesis Ch. 5), and of tracked vertices against true ones
(rigging, thesis Ch. 6: :func:`vertex_errors`).

The reconstruction is first aligned rigidly to the true mesh (from a given start, then
point-to-point ICP on dense surface samples: the error of the shape, not of where its
frame happens to lie); the errors are then distances between uniform samples of the
two surfaces: each sample to the nearest point of the *other surface* (not to its
samples), both ways.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["SurfaceErrors", "surface_errors", "trajectory_errors", "score_scan", "vertex_errors"]


class SurfaceErrors(NamedTuple):
    """mean_mm: the symmetric mean surface distance (mean of the two directions);
    hausdorff95_mm: the larger of the two directions' 95th percentiles;
    to_truth_mm / from_truth_mm: mean of each direction (accuracy / completeness);
    watertight: of the reconstruction; alignment: (4, 4) reconstruction -> truth."""

    mean_mm: float
    hausdorff95_mm: float
    to_truth_mm: float
    from_truth_mm: float
    watertight: bool
    alignment: np.ndarray


def _tmesh(v, f):
    import trimesh

    return trimesh.Trimesh(np.asarray(v, np.float64), np.asarray(f, np.int64), process=False)


def _distance(points: np.ndarray, mesh) -> np.ndarray:
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy().astype(np.float64)


def surface_errors(vertices: np.ndarray, faces: np.ndarray, truth_vertices: np.ndarray, truth_faces: np.ndarray,
                   start: np.ndarray = np.eye(4), samples: int = 20000, seed: int = 0,
                   icp_distance: float = 10.0) -> SurfaceErrors:
    """Score a reconstruction (V, 3), (F, 3) against the truth (mm).

    ``start``: (4, 4) initial reconstruction -> truth transform (e.g. from the first
    frame's poses), refined by point-to-point ICP (open3d, pairs within
    ``icp_distance`` mm) on ``samples`` surface samples.
    """
    import open3d as o3d
    import trimesh

    rec, tru = _tmesh(vertices, faces), _tmesh(truth_vertices, truth_faces)
    watertight = bool(rec.is_watertight)
    rs = np.asarray(trimesh.sample.sample_surface(rec, samples, seed=seed)[0])
    ts = np.asarray(trimesh.sample.sample_surface(tru, samples, seed=seed + 1)[0])
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(rs))
    dst = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(ts))
    T = np.asarray(start, np.float64)
    for d in (icp_distance, icp_distance / 3):
        T = o3d.pipelines.registration.registration_icp(
            src, dst, d, T, o3d.pipelines.registration.TransformationEstimationPointToPoint(),
            o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=60)).transformation
    moved = rs @ T[:3, :3].T + T[:3, 3]
    rec_moved = _tmesh(np.asarray(vertices) @ T[:3, :3].T + T[:3, 3], faces)
    a = _distance(moved, tru)  # reconstruction -> truth
    b = _distance(ts, rec_moved)  # truth -> reconstruction
    return SurfaceErrors(float((a.mean() + b.mean()) / 2), float(max(np.percentile(a, 95), np.percentile(b, 95))),
                         float(a.mean()), float(b.mean()), watertight, T)


def trajectory_errors(poses: np.ndarray, truth: np.ndarray, vertices: np.ndarray, max_points: int = 2000) -> dict:
    """Errors of an object's motion relative to frame 0 (the first estimated frame).

    Args:
        poses: (N, 4, 4) estimated object -> camera (NaN rows: not estimated).
        truth: (N, 4, 4) true mesh -> camera.
        vertices: (M, 3) the true mesh's vertices (its own coordinates).
    Returns:
        per frame and summarised (mean, max): ``rotation_deg`` and ``translation_mm`` (of
        the mesh's centre) of the estimated motion against the true one; ``add_mm``: the
        mean distance between the mesh's vertices moved by the two motions; ``add_s_mm``:
        from each truly moved vertex to the nearest vertex moved by the estimate (ADD-S:
        a symmetric object's motion counts up to its symmetry, as for the tracker's
        scores); ``frames``.
    """
    from scipy.spatial import cKDTree

    ok = np.isfinite(poses).all((1, 2))
    if not ok.any():
        raise ValueError("trajectory_errors: no frame has an estimated pose")
    k0 = int(np.argmax(ok))
    V = np.asarray(vertices, np.float64)
    if len(V) > max_points:
        V = V[np.random.default_rng(0).choice(len(V), max_points, replace=False)]
    pts0 = V @ truth[k0][:3, :3].T + truth[k0][:3, 3]
    centre = pts0.mean(0)
    rot, tra, add, adds = [], [], [], []
    for k in np.nonzero(ok)[0]:
        Me = poses[k] @ np.linalg.inv(poses[k0])
        Mg = truth[k] @ np.linalg.inv(truth[k0])
        dR = Me[:3, :3] @ Mg[:3, :3].T
        rot.append(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
        tra.append(np.linalg.norm((Me[:3, :3] @ centre + Me[:3, 3]) - (Mg[:3, :3] @ centre + Mg[:3, 3])))
        pe, pg = pts0 @ Me[:3, :3].T + Me[:3, 3], pts0 @ Mg[:3, :3].T + Mg[:3, 3]
        add.append(np.linalg.norm(pe - pg, axis=1).mean())
        adds.append(cKDTree(pe).query(pg)[0].mean())

    def summary(x):
        x = np.array(x)
        return {"mean": float(x.mean()), "max": float(x.max())}

    return {"rotation_deg": summary(rot), "translation_mm": summary(tra), "add_mm": summary(add),
            "add_s_mm": summary(adds), "frames": int(ok.sum())}


def score_scan(scan_dir, sequence_dir) -> dict:
    """Score the output of ``torchhand scan`` (``model.npz``, ``object_pose.npy``)
    against a synthetic scan's ``gt/object.ply`` and ``gt/object_pose.npy``: the
    surface (:func:`surface_errors`, started from frame 0's poses) and the motion
    (:func:`trajectory_errors`)."""
    from pathlib import Path

    from torchhand.data.layout import SequenceLayout
    from torchhand.io.assets import load_assets
    from torchhand.io.mesh_files import read_object_mesh

    scan_dir, gt = Path(scan_dir), SequenceLayout(sequence_dir).gt
    model = load_assets(scan_dir / "model.npz")
    truth = read_object_mesh(gt.object_mesh)
    poses = np.load(scan_dir / "object_pose.npy")
    true_poses = np.load(gt.object_pose)
    ok = np.isfinite(poses).all((1, 2))
    k0 = int(np.argmax(ok))
    start = np.linalg.inv(true_poses[k0]) @ poses[k0]
    surf = surface_errors(model.vertices, model.faces, truth.vertices, truth.faces, start)
    return {"mean_mm": surf.mean_mm, "hausdorff95_mm": surf.hausdorff95_mm, "to_truth_mm": surf.to_truth_mm,
            "from_truth_mm": surf.from_truth_mm, "watertight": surf.watertight,
            "alignment": surf.alignment.tolist(), "trajectory": trajectory_errors(poses, true_poses, truth.vertices)}


def vertex_errors(vertices: np.ndarray, truth: np.ndarray) -> dict:
    """Per-frame errors of tracked (N, V, 3) vertices against the true (N, V', 3) ones (mm).

    ``closest_mm`` (N,): the thesis' measure of Table 6.2 (Eq. 6.13 read as distances):
    the mean over both vertex sets of each vertex's distance to the nearest vertex of the
    other set, which does not see a surface sliding along itself (a tube's roll);
    ``same_order_mm`` (N,) (when V == V'): the mean distance of corresponding vertices.
    Also their means over the frames.
    """
    from scipy.spatial import cKDTree

    P, G = np.asarray(vertices, np.float64), np.asarray(truth, np.float64)
    if P.ndim != 3 or G.ndim != 3 or P.shape[0] != G.shape[0] or P.shape[2] != 3 or G.shape[2] != 3:
        raise ValueError(f"vertices and truth must be (N, V, 3) with the same N, got {P.shape} and {G.shape}")
    closest = np.array([(cKDTree(g).query(p)[0].sum() + cKDTree(p).query(g)[0].sum()) / (len(p) + len(g))
                        for p, g in zip(P, G)])
    out = {"closest_mm": closest, "mean_closest_mm": float(closest.mean())}
    if P.shape[1] == G.shape[1]:
        same = np.linalg.norm(P - G, axis=-1).mean(1)
        out.update(same_order_mm=same, mean_same_order_mm=float(same.mean()))
    return out

