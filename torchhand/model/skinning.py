"""Linear blend skinning (thesis Eq. 4.1) and its analytic Jacobian.

``V(theta) = sum_j kappa_Vj T_j(theta) T_j(0)^-1 V(0) = sum_j kappa_Vj G_j V(0)``.

Because the rest vertices are fixed, the sum is linear in the entries of the bone
motions ``G``: with the static *skinning matrix* ``P[v, 4j + c] = kappa_vj V_c(0)``
(homogeneous coordinate c), all posed vertices of a batch are one product of a
(3B, 4J) matrix with ``P^T``: one GEMM in the forward pass and one in the backward
pass. ``P`` is dense by default; a sparse CSR ``P`` is supported (see
:func:`skinning_matrix`) but was slower on CPU for every shipped model.

Weights are stored compactly as ``skin_index: (V, K)`` / ``skin_weight: (V, K)``
(K = the largest number of non-zero weights of a vertex, padded with weight 0).
"""

from __future__ import annotations

import torch


__all__ = ["skinning_matrix", "lbs", "lbs_dense_reference", "lbs_jacobian", "dense_weights"]

# Below this fraction of non-zeros P is stored as sparse CSR by default. On CPU the
# dense product was faster for every shipped model (hands ~45 % dense, rope ~18 %;
# eval/bench_lbs.py, docs/benchmarks.md), so by default P is dense; sparse=True remains
# available for rigs with many more bones.
SPARSE_DENSITY = 0.0


def dense_weights(skin_index: torch.Tensor, skin_weight: torch.Tensor, num_bones: int) -> torch.Tensor:
    """(V, K) ids and weights -> (V, J) dense weight matrix."""
    W = skin_weight.new_zeros(skin_index.shape[0], num_bones)
    return W.scatter_add(1, skin_index, skin_weight)


def skinning_matrix(
    vertices: torch.Tensor, skin_index: torch.Tensor, skin_weight: torch.Tensor, num_bones: int,
    sparse: bool | None = None,
) -> torch.Tensor:
    """Static matrix P with ``lbs(G, P) = sum_j w_j G_j v``.

    Args:
        vertices: (V, 3) rest vertices.
        skin_index: (V, K) int64 bone ids; skin_weight: (V, K) weights.
        num_bones: J.
        sparse: force a sparse CSR (True) or dense (False) result; by default sparse
            when the density is below ``SPARSE_DENSITY``.
    Returns:
        (V, 4 J) matrix, dense or sparse CSR.
    """
    V = vertices.shape[0]
    W = dense_weights(skin_index, skin_weight, num_bones)  # (V, J)
    vh = torch.cat([vertices, vertices.new_ones(V, 1)], 1)  # (V, 4)
    P = (W[:, :, None] * vh[:, None, :]).reshape(V, 4 * num_bones)
    density = (W != 0).float().mean().item() if V else 1.0
    if sparse is None:
        sparse = density < SPARSE_DENSITY
    return P.to_sparse_csr() if sparse else P


def lbs(G: torch.Tensor, P: torch.Tensor) -> torch.Tensor:
    """Posed vertices by linear blend skinning (Eq. 4.1).

    Args:
        G: (B, J, 4, 4) bone motions relative to the rigging pose.
        P: (V, 4 J) skinning matrix from :func:`skinning_matrix` (dense or CSR).
    Returns:
        (B, V, 3) posed vertices.
    """
    B, J = G.shape[:2]
    if P.layout != torch.strided:
        # Gm[4j + c, 3b + r] = G[b, j, r, c]
        Gm = G[:, :, :3, :].permute(1, 3, 0, 2).reshape(4 * J, 3 * B)
        return torch.sparse.mm(P, Gm).reshape(-1, B, 3).transpose(0, 1)
    # (3B, 4J) @ (4J, V): the long dimension V is the output's fast axis, so P is read
    # once in its stored order (measured 2x faster at B = 1 than P @ (4J, 3B)).
    Gr = G[:, :, :3, :].permute(0, 2, 1, 3).reshape(3 * B, 4 * J)
    return (Gr @ P.mT).view(B, 3, -1).transpose(1, 2)


def lbs_dense_reference(G: torch.Tensor, vertices: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Slow, obviously-correct LBS: sum_j w_vj (G_j [v; 1]). (B,J,4,4),(V,3),(V,J) -> (B,V,3)."""
    vh = torch.cat([vertices, vertices.new_ones(vertices.shape[0], 1)], 1)
    per_bone = torch.einsum("bjrc,vc->bvjr", G[:, :, :3, :], vh)
    return torch.einsum("vj,bvjr->bvr", weights, per_bone)


def lbs_jacobian(
    G: torch.Tensor,
    twists: torch.Tensor,
    vertices: torch.Tensor,
    skin_index: torch.Tensor,
    skin_weight: torch.Tensor,
    dof_bone: torch.Tensor,
    descendants: torch.Tensor,
) -> torch.Tensor:
    """Analytic Jacobian d V(theta) / d theta of skinned points.

    Args:
        G: (B, J, 4, 4) and twists: (B, D, 6) from ``forward_kinematics``.
        vertices: (N, 3) rest positions of the points (a subset of the mesh, or
            keypoints with one-hot weights), or (B, N, 3) for a different subset per
            batch element.
        skin_index, skin_weight: (N, K), or (B, N, K) with batched vertices.
        dof_bone: (D,) bone of each DoF; descendants: (J, J) bool (see KinematicTree).
    Returns:
        (B, N, 3, D).
    """
    # Dense form, all matrix products: x_j = G_j x0 for every bone, the blend weights
    # W (N, J) scattered from the sparse influences, and A[j, d] = "DoF d moves bone j",
    # so S_d = sum_j W_j A_jd x_j and W_d = sum_j W_j A_jd; then dx/dtheta_d =
    # omega_d x S_d + W_d u_d (see kinematics.point_jacobian), written out per axis in a
    # (B, D, N) layout, where N is the contiguous axis (8x faster than gathers and a
    # batched cross product on CPU).
    B, J = G.shape[:2]
    W = skin_weight.new_zeros(*skin_index.shape[:-1], J).scatter_add_(-1, skin_index, skin_weight)
    A = descendants[:, dof_bone].to(G.dtype)  # (J, D)
    vh = torch.cat([vertices, vertices.new_ones(*vertices.shape[:-1], 1)], -1)  # ([B,] N, 4)
    x = G[:, :, :3, :].reshape(B, 3 * J, 4) @ vh.mT  # (B, 3J, N)
    Y = (x.view(B, J, 3, -1) * W.mT[..., :, None, :]).view(B, J, -1)  # weighted bone positions
    S = (A.mT @ Y).view(B, A.shape[1], 3, -1)  # (B, D, 3, N)
    u, w = twists[..., :3, None], twists[..., 3:, None]  # (B, D, 3, 1)
    Wd = (W @ A).mT  # ([B,] D, N)
    s0, s1, s2 = S.unbind(2)
    Jt = torch.stack([w[:, :, 1] * s2 - w[:, :, 2] * s1 + Wd * u[:, :, 0],
                      w[:, :, 2] * s0 - w[:, :, 0] * s2 + Wd * u[:, :, 1],
                      w[:, :, 0] * s1 - w[:, :, 1] * s0 + Wd * u[:, :, 2]], -1)  # (B, D, N, 3)
    return Jt.permute(0, 2, 3, 1)
