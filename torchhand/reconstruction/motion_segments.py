"""Motion segmentation of a tracked mesh into rigid parts (thesis Ch. 6.4.1, Eq. 6.6-6.12).

About 1000 vertices are sampled evenly over the template (farthest-point sampling,
open3d); their trajectories give pairwise distances

    d^v_ij = max_t | |V_i,t - V_j,t| - |V_i,t-dt - V_j,t-dt| |                (6.8)
    d^n_ij = max_t | acos(N_i,t . N_j,t) - acos(N_i,t-dt . N_j,t-dt) |        (6.9)
    d_ij   = (1 + d^n_ij) d^v_ij                                              (6.10)

(mm and radians), the affinity ``Phi = exp(-lambda d)`` (Eq. 6.6, lambda = 0.1), the
normalised Laplacian ``D^-1/2 (D - Phi) D^-1/2`` (Eq. 6.11-6.12), and as many clusters
as it has eigenvalues below ``lambda_thr``; scikit-learn's spectral clustering (Ng et
al.: the normalised Laplacian's eigenvectors, k-means on their rows) finds them. Every other vertex takes
the cluster of the sample nearest to it along the mesh (Dijkstra over the mesh edges,
scipy).

The thesis compares frames ``dt = 2 max_i,t |V_i,t - V_i,t-1|`` apart (Eq. 6.7, the
displacement in mm read as a number of frames; here at most a quarter of the sequence):
``interval="thesis"``. The default, ``interval="sequence"``, compares any two frames
(the range of each distance over the sequence). Eq. 6.7's interval makes the result
depend on the speed: the same three-link motion sampled at 40 and at 100 frames has
second and third eigenvalues 0.37, 0.81 and 0.73, 0.96 with it, 0.20, 0.57 for both over
the sequence; and on the exact trajectories of ``eval/exp_rig.py``'s slowly bent chains
(dt 3-8 frames) it finds a single part for each of them at lambda_thr 0.7 (third
eigenvalue of the three-link chain 0.95), where the whole sequence finds 2, 2 and 3. (An earlier deformable
tracking drifted along tubes, and over a whole sequence the drift split rigid links;
with the tracking's edge-length term and the merge below it no longer does.)

Choices the thesis leaves open, made here: a cluster that falls apart on the mesh is
split into its connected pieces, and pieces under ``min_part`` of the vertices join the
neighbouring part they share most edges with, so that every part is one connected
piece of surface and can carry one bone.

Redundant parts (thesis Sec. 6.4.2: "redundant bones are removed"): the deformable
tracking of a tube seen from one side slides a little along the tube and bends rigid
links by a few millimetres, which the distance variation reads as motion and splits a
link in two (a two-link chain, 80 + 140 mm with Kinect noise: 3 parts, the extra cut
in the middle of the long link; 150 frames of ``eval/exp_rig.py``'s ``chain2_kinect``
object and motion, rigged once). :func:`merge_rigid_parts` therefore joins two
neighbouring parts when one rigid motion explains both nearly as well as each alone:
the 95th percentile over the frames of the RMS residual of the union's rigid fit is at
most ``merge_ratio`` times that of the worse part. In that chain the false cut scored
3.8 against 3.6 mm alone (ratio 1.06), the true joint 15.8 against 3.6 mm (4.4).

Refinement (``refine``, default on with the merge): the count of eigenvalues below
``lambda_thr`` is only a start. One more cluster is tried, and kept while it survives
the merge (more parts after the merge than before): the merge's rigidity test, not the
threshold alone, decides whether a cut is a joint. An eigenvalue near the threshold then
no longer decides the part count by chance: a three-link object no experiment had used
(90 + 70 + 110 mm, joints about y and z, Kinect noise, 150 frames) has its third
eigenvalue at 0.708, so lambda_thr 0.7 gave 2 parts with joints 47 and 23 mm from the
truth; a third cluster survives the merge (3 parts, joints 1.2 and 2.1 mm off) and a
fourth does not. On the rigs of ``eval/exp_rig.py`` (the pipe, the rope and three
generated chains) the extra cluster is joined again each time, so their parts are as
without it (docs/results.md).
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import numpy as np
import torch

from torchhand.geometry.mesh import vertex_normals

__all__ = ["Segmentation", "segment_motion", "merge_rigid_parts", "rigid_residual", "mesh_edges", "mesh_graph", "sample_vertices",
           "SegmentationError"]


class SegmentationError(ValueError):
    """The trajectories cannot be segmented (too short, no motion)."""


class Segmentation(NamedTuple):
    """labels: (V,) int64 part of every vertex, 0..parts-1 by decreasing size;
    samples: (S,) the sampled vertex ids; eigenvalues: the smallest eigenvalues of the
    normalised Laplacian (ascending); clusters: the clusters found (before parts were
    made connected); dt: the interval in frames; merged: one line per redundant part
    joined to a neighbour (:func:`merge_rigid_parts`); refined: one line per extra
    cluster kept by the refinement (module docstring)."""

    labels: np.ndarray
    samples: np.ndarray
    eigenvalues: np.ndarray
    clusters: int
    dt: int
    merged: tuple = ()
    refined: tuple = ()

    @property
    def parts(self) -> int:
        return int(self.labels.max()) + 1


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """(E, 2) the unique undirected edges of a triangle mesh, smaller id first."""
    f = np.asarray(faces, np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    return np.unique(np.sort(e, 1), axis=0)


def sample_vertices(vertices: np.ndarray, count: int) -> np.ndarray:
    """Ids of ``count`` vertices spread evenly (farthest-point sampling, open3d)."""
    import open3d as o3d

    V = len(vertices)
    if count >= V:
        return np.arange(V)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(vertices, np.float64)))
    picked = np.asarray(pc.farthest_point_down_sample(int(count)).points)
    from scipy.spatial import cKDTree

    ids = cKDTree(vertices).query(picked)[1]
    return np.unique(ids)


def mesh_graph(vertices: np.ndarray, faces: np.ndarray):
    """The (V, V) sparse graph of the mesh edges weighted by their lengths (mm)."""
    import scipy.sparse as sp

    e = mesh_edges(faces)
    w = np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1)
    V = len(vertices)
    return sp.coo_matrix((np.concatenate([w, w]), (np.concatenate([e[:, 0], e[:, 1]]),
                                                    np.concatenate([e[:, 1], e[:, 0]]))), shape=(V, V)).tocsr()


def trajectory_distances(traj: torch.Tensor, normals: torch.Tensor, dt: Optional[int] = None,
                         use_normals: bool = True) -> torch.Tensor:
    """d (Eq. 6.10) between the (T, S, 3) trajectories with their (T, S, 3) normals: the
    largest change of distance (and of normal angle) between frames ``dt`` apart (Eq.
    6.8-6.9), or with ``dt=None`` between any two frames (the range over the sequence)."""
    T = traj.shape[0]
    dv = torch.zeros(traj.shape[1], traj.shape[1], dtype=traj.dtype)
    dn = torch.zeros_like(dv)
    if dt is None:
        lo_d = hi_d = lo_a = hi_a = None
        for t in range(T):
            d = torch.cdist(traj[t], traj[t])
            lo_d, hi_d = (d, d) if lo_d is None else (torch.minimum(lo_d, d), torch.maximum(hi_d, d))
            if use_normals:
                a = torch.arccos((normals[t] @ normals[t].T).clamp(-1, 1))
                lo_a, hi_a = (a, a) if lo_a is None else (torch.minimum(lo_a, a), torch.maximum(hi_a, a))
        dv = hi_d - lo_d
        dn = hi_a - lo_a if use_normals else dn
        return (1 + dn) * dv
    dists, angles = [], []
    for t in range(T):
        d = torch.cdist(traj[t], traj[t])
        a = torch.arccos((normals[t] @ normals[t].T).clamp(-1, 1)) if use_normals else None
        dists.append(d)
        angles.append(a)
        if t >= dt:
            dv = torch.maximum(dv, (d - dists[t - dt]).abs())
            if use_normals:
                dn = torch.maximum(dn, (a - angles[t - dt]).abs())
            dists[t - dt] = angles[t - dt] = None  # no longer needed
    return (1 + dn) * dv


def segment_motion(trajectories: np.ndarray, template: np.ndarray, faces: np.ndarray, lambda_thr: float = 0.7,
                   samples: int = 1000, lam: float = 0.1, use_normals: bool = True, min_part: float = 0.005,
                   interval: str = "sequence", seed: int = 0, merge_ratio: float = 1.5,
                   refine: bool = True) -> Segmentation:
    """Segment the mesh by the motion of its (T, V, 3) vertex trajectories (module
    docstring). ``template``: (V, 3) the rigging-pose vertices (where samples are drawn
    and distances along the mesh measured). ``interval``: ``"sequence"`` (default) compares
    any two frames, ``"thesis"`` frames dt apart (Eq. 6.7). ``merge_ratio``: redundant
    parts are joined (:func:`merge_rigid_parts`; 0 keeps the clusters as they are).
    ``refine``: with the merge, one more cluster is tried while it survives the merge
    (module docstring); False keeps the count of eigenvalues below ``lambda_thr``."""
    from scipy.linalg import eigh
    from scipy.sparse.csgraph import dijkstra
    from sklearn.cluster import spectral_clustering

    traj = np.asarray(trajectories, np.float64)
    T, V = traj.shape[:2]
    if T < 3:
        raise SegmentationError(f"motion segmentation needs at least 3 frames of the object's motion, got {T}")
    if not 0 < lambda_thr < 2:
        raise ValueError(f"lambda_thr must be in (0, 2) (eigenvalues of a normalised Laplacian), got {lambda_thr}")
    if not merge_ratio >= 0:
        raise ValueError(f"merge_ratio must be >= 0 (0: keep every cluster), got {merge_ratio}")
    if interval not in ("sequence", "thesis"):
        raise ValueError(f"interval must be 'sequence' or 'thesis', got {interval!r}")
    step = np.linalg.norm(traj[1:] - traj[:-1], axis=-1).max()
    dt = int(min(max(round(2 * step), 1), max(T // 4, 1)))
    ids = sample_vertices(template, samples)
    X = torch.as_tensor(traj[:, ids])
    N = vertex_normals(torch.as_tensor(traj), torch.as_tensor(np.asarray(faces, np.int64)))[:, ids]
    d = trajectory_distances(X, N, dt if interval == "thesis" else None, use_normals)
    phi = torch.exp(-lam * d).numpy()
    deg = phi.sum(1)
    Dm = 1 / np.sqrt(deg)
    lap = np.eye(len(ids)) - Dm[:, None] * phi * Dm[None]
    evals = eigh(lap, eigvals_only=True, subset_by_index=[0, min(len(ids), 64) - 1])
    graph = mesh_graph(np.asarray(template, np.float64), faces)
    _, _, src = dijkstra(graph, indices=ids, min_only=True, return_predecessors=True)

    def parts_of(k: int) -> tuple:
        """(labels, merged) of k spectral clusters: every vertex by its nearest sample,
        connected parts, redundant ones joined."""
        if k == 1:
            cl = np.zeros(len(ids), np.int64)
        else:
            cl = spectral_clustering(phi, n_clusters=k, random_state=seed, assign_labels="kmeans").astype(np.int64)
        lookup = np.full(V, -1, np.int64)
        lookup[ids] = cl
        labels = lookup[src]
        labels[src < 0] = 0  # vertices on no connected piece with a sample
        labels = _connected_parts(labels, faces, V, min_part)
        if merge_ratio > 0 and labels.max() > 0:
            return merge_rigid_parts(traj, template, faces, labels, merge_ratio)
        return labels, ()

    k = max(int((evals < lambda_thr).sum()), 1)
    labels, merged = parts_of(k)
    refined = []
    while refine and merge_ratio > 0 and k < len(evals) - 1:
        finer, finer_merged = parts_of(k + 1)
        if finer.max() <= labels.max():
            break  # the extra cluster was redundant: the merge joined it again
        refined.append(f"{k + 1} clusters tried (eigenvalue {evals[k]:.3f}, lambda_thr {lambda_thr:g}): "
                       f"{finer.max() + 1} parts after the merge against {labels.max() + 1}, kept")
        k, labels, merged = k + 1, finer, finer_merged
    return Segmentation(labels, ids, evals, k, dt, merged, tuple(refined))


def _connected_parts(labels: np.ndarray, faces: np.ndarray, V: int, min_part: float) -> np.ndarray:
    """Split labels into mesh-connected pieces; merge small pieces into a neighbour;
    number the parts by decreasing size."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    e = mesh_edges(faces)
    same = labels[e[:, 0]] == labels[e[:, 1]]
    g = sp.coo_matrix((np.ones(int(same.sum())), (e[same, 0], e[same, 1])), shape=(V, V))
    _, piece = connected_components(g, directed=False)
    smallest = max(int(min_part * V), 1)
    while True:
        sizes = np.bincount(piece)
        small = [p for p in np.argsort(sizes) if 0 < sizes[p] < smallest]
        if not small or (sizes > 0).sum() == 1:
            break
        p = small[0]
        a, b = piece[e[:, 0]], piece[e[:, 1]]
        touching = np.concatenate([b[(a == p) & (b != p)], a[(b == p) & (a != p)]])
        if len(touching) == 0:
            break  # an isolated piece (a separate shell) stays as it is
        piece[piece == p] = np.bincount(touching).argmax()
    return _by_size(piece)


def _by_size(labels: np.ndarray) -> np.ndarray:
    """The labels renumbered 0.. by decreasing size (ties: the smaller old label first)."""
    _, labels = np.unique(labels, return_inverse=True)
    order = np.argsort(-np.bincount(labels), kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return rank[labels].astype(np.int64)


def rigid_residual(trajectories: np.ndarray, template: np.ndarray, ids: np.ndarray, percentile: float = 95.0) -> float:
    """The ``percentile`` over the frames of the RMS residual (mm) of the best rigid
    motion template -> frame of the vertices ``ids`` (Kabsch)."""
    from torchhand.reconstruction.registration import kabsch_batch

    ids = torch.as_tensor(np.asarray(ids, np.int64))
    src = torch.as_tensor(np.asarray(template, np.float64))[ids]
    X = torch.as_tensor(np.asarray(trajectories, np.float64))[:, ids]
    R, t = kabsch_batch(src, X)
    r = (src @ R.transpose(1, 2) + t[:, None] - X).pow(2).sum(-1).mean(1).sqrt()
    return float(np.percentile(r.numpy(), percentile))


def merge_rigid_parts(trajectories: np.ndarray, template: np.ndarray, faces: np.ndarray, labels: np.ndarray,
                      merge_ratio: float = 1.5, floor_mm: float = 0.5) -> tuple:
    """(labels, merged): neighbouring parts joined, the best pair first, while one rigid
    motion fits their union with a residual (:func:`rigid_residual`) at most
    ``merge_ratio`` times the worse part's own (at least ``floor_mm``, so that exact
    trajectories of two rigid pieces of one link merge too). ``merged``: one line per
    join. Parts are numbered by decreasing size again."""
    labels = np.asarray(labels, np.int64).copy()
    e = mesh_edges(faces)
    merged = []
    own = {p: rigid_residual(trajectories, template, np.nonzero(labels == p)[0]) for p in np.unique(labels)}
    union: dict = {}
    while len(own) > 1:
        a, b = labels[e[:, 0]], labels[e[:, 1]]
        cross = a != b
        pairs = {tuple(sorted(x)) for x in zip(a[cross].tolist(), b[cross].tolist())}
        best = None
        for p, q in sorted(pairs):
            if (p, q) not in union:
                union[p, q] = rigid_residual(trajectories, template, np.nonzero((labels == p) | (labels == q))[0])
            ratio = union[p, q] / max(own[p], own[q], floor_mm)
            if best is None or ratio < best[0]:
                best = (ratio, p, q)
        if best is None or best[0] > merge_ratio:
            break
        ratio, p, q = best
        merged.append(f"parts {p} and {q} joined: one rigid motion fits both to {union[p, q]:.2f} mm "
                      f"(95th percentile RMS; {own[p]:.2f} and {own[q]:.2f} mm alone, ratio {ratio:.2f})")
        labels[labels == q] = p
        own[p] = union[p, q]
        del own[q]
        union = {k: v for k, v in union.items() if p not in k and q not in k}
    return _by_size(labels), tuple(merged)
