"""Association of fingertip detections to model fingertips (thesis Eq. 4.14; Ballan
et al. 2012, Eq. 3), solved exactly as an assignment problem.

The integer program chooses, for S detections and T model fingertips, assignments
e_st (cost w_st), false positives alpha_s (cost lambda w_s) and unassigned
fingertips beta_t (cost lambda), with every detection and fingertip used exactly
once. It is a linear assignment on the (S + T) x (T + S) matrix::

            fingertips t          "false positive" s'
    s   [  w_st               |  lambda w_s if s' = s, else forbidden ]
    t'  [  lambda if t' = t,  |  0                                    ]
        [  else forbidden     |                                       ]

which scipy's ``linear_sum_assignment`` solves exactly (Hungarian / LAPJV).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.optimize import linear_sum_assignment

__all__ = ["Association", "associate"]


class Association(NamedTuple):
    """detection: (K,) int64 and fingertip: (K,) int64 indices of the assigned pairs;
    false_positive: (S,) bool detections left unassigned; unassigned: (T,) bool
    fingertips without a detection; cost: the optimal objective of Eq. 4.14."""

    detection: np.ndarray
    fingertip: np.ndarray
    false_positive: np.ndarray
    unassigned: np.ndarray
    cost: float


def associate(cost: np.ndarray, lam: float, detection_weight: np.ndarray | None = None) -> Association:
    """Solve Eq. 4.14.

    Args:
        cost: (S, T) w_st >= 0, the cost of assigning detection s to fingertip t
            (``inf`` forbids a pair).
        lam: lambda, the cost of leaving a fingertip unassigned (and, times w_s, of
            declaring a detection a false positive).
        detection_weight: (S,) w_s (default 1; the thesis' alternative is c_s / c_thr).
    Returns:
        :class:`Association`. A pair is assigned only when that is cheaper than
        lambda (w_s + 1), its cost as a false positive plus an unmatched fingertip.
    """
    cost = np.asarray(cost, np.float64)
    if cost.ndim != 2:
        raise ValueError(f"cost must be an (S, T) matrix, got shape {cost.shape}")
    if np.isnan(cost).any() or (cost < 0).any():
        raise ValueError("cost must be non-negative and not NaN")
    if not lam >= 0:
        raise ValueError(f"lambda must be >= 0, got {lam}")
    S, T = cost.shape
    ws = np.ones(S) if detection_weight is None else np.asarray(detection_weight, np.float64)
    if ws.shape != (S,):
        raise ValueError(f"detection_weight must have shape ({S},), got {ws.shape}")
    if S == 0 or T == 0:
        return Association(np.zeros(0, np.int64), np.zeros(0, np.int64), np.ones(S, bool), np.ones(T, bool),
                           float(lam * ws.sum() + lam * T))
    finite = np.isfinite(cost)
    big = 1.0 + 2.0 * (cost[finite].sum() + lam * (ws.sum() + T))  # larger than any feasible solution
    M = np.full((S + T, T + S), big)
    M[:S, :T] = np.where(finite, cost, big)
    M[np.arange(S), T + np.arange(S)] = lam * ws
    M[S + np.arange(T), np.arange(T)] = lam
    M[S:, T:] = 0.0
    rows, cols = linear_sum_assignment(M)
    pair = (rows < S) & (cols < T)
    det, tip = rows[pair].astype(np.int64), cols[pair].astype(np.int64)
    fp = np.ones(S, bool)
    fp[det] = False
    un = np.ones(T, bool)
    un[tip] = False
    total = float(cost[det, tip].sum() + lam * (ws[fp].sum() + un.sum()))
    return Association(det, tip, fp, un, total)
