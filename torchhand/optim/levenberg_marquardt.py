"""Batched Levenberg-Marquardt for stacked least-squares residuals (thesis Ch. 4.2.2.7).

Every batch element is an independent problem with its own damping; steps are
accepted or rejected per element with ``torch.where`` (as in theseus' LM), so one
badly conditioned frame does not slow down or spoil the others. Box bounds (the
joint limits) are enforced by projecting each step.

The solver sees a problem through three calls (:class:`LeastSquaresProblem`):
``linearize`` at its current iterate (the start, then the steps it accepted),
``evaluate`` at a candidate step, and ``accept`` telling which problems took the
candidate. A plain function ``f(theta, with_jacobian) -> (r, J)`` is adapted by
:class:`FunctionProblem`. When to stop early is the caller's rule, given as an
argument (``keep_going``).
"""

from __future__ import annotations

from typing import Callable, NamedTuple, Optional, Tuple, Union

import torch

from torchhand.core.profiling import stage

__all__ = ["LMResult", "LeastSquaresProblem", "FunctionProblem", "levenberg_marquardt", "solve_damped", "solve_normal",
           "NormalEquations", "normal_equations"]

ResidualFn = Callable[[torch.Tensor, bool], Tuple[torch.Tensor, Optional[torch.Tensor]]]


class NormalEquations(NamedTuple):
    """A linearisation as the LM step reads it: ``H`` (B, D, D) = J^T J, ``g`` (B, D) =
    J^T r and ``cost`` (B,) = |r|^2. A problem whose :meth:`LeastSquaresProblem.linearize`
    returns these (a fused objective that accumulates them itself) never hands the
    solver its (B, m, D) Jacobian."""

    H: torch.Tensor
    g: torch.Tensor
    cost: torch.Tensor


def normal_equations(r: torch.Tensor, J: torch.Tensor) -> NormalEquations:
    """:class:`NormalEquations` of residuals r (B, m) and their Jacobian J (B, m, D)."""
    Jt = J.transpose(1, 2)
    return NormalEquations(Jt @ J, (Jt @ r[..., None])[..., 0], (r * r).sum(-1))


class LeastSquaresProblem:
    """A batch of least-squares problems as :func:`levenberg_marquardt` calls it.

    The solver calls :meth:`linearize` at its current iterate only (the clamped start,
    then after steps it accepted), :meth:`evaluate` at candidates only, and
    :meth:`accept` after every candidate, so an implementation can keep what it
    computed at the candidate (the posed scene, say) and follow the solver's iterate
    without recomputing it.
    """

    def linearize(self, theta: torch.Tensor):  # pragma: no cover - interface
        """(r (B, m), J (B, m, D)), or their :class:`NormalEquations`, at the solver's
        current iterate ``theta`` (B, D)."""
        raise NotImplementedError

    def evaluate(self, theta: torch.Tensor) -> torch.Tensor:  # pragma: no cover - interface
        """r (B, m) at a candidate ``theta`` (B, D)."""
        raise NotImplementedError

    def accept(self, mask: torch.Tensor) -> None:
        """The solver took the last candidate for the problems of ``mask`` (B,) bool
        (nothing to do by default)."""


class FunctionProblem(LeastSquaresProblem):
    """A :class:`LeastSquaresProblem` of a function ``f(theta, with_jacobian) -> (r (B,
    m), J (B, m, D) or None)``."""

    def __init__(self, fn: ResidualFn):
        if not callable(fn):
            raise TypeError(f"expected a residual function f(theta, with_jacobian), got {type(fn).__name__}")
        self.fn = fn

    def linearize(self, theta):
        return self.fn(theta, True)

    def evaluate(self, theta):
        return self.fn(theta, False)[0]


class LMResult(NamedTuple):
    """What a solve found and counted.

    Attributes:
        theta: (B, D) solution.
        cost: (B,) final sum of squared residuals.
        iterations: (B,) accepted steps per problem.
        converged: (B,) bool.
        damping: (B,) final lambda (to warm-start the next solve).
        rejected: (B,) steps tried and rejected per problem (retries included).
        evaluations: residual evaluations, with or without Jacobian, of the whole batch.
        going: the host list of ``keep_going(theta, iterations)`` at the returned theta
            when it was read together with the retry check, else None (see
            :func:`levenberg_marquardt`).
    """

    theta: torch.Tensor
    cost: torch.Tensor
    iterations: torch.Tensor
    converged: torch.Tensor
    damping: torch.Tensor
    rejected: torch.Tensor
    evaluations: int
    going: Optional[list] = None


def solve_damped(J: torch.Tensor, r: torch.Tensor, damping: torch.Tensor) -> torch.Tensor:
    """Solve (J^T J + lambda diag(J^T J) + lambda I) delta = -J^T r per problem.

    J: (B, m, D), r: (B, m), damping: (B,). Returns delta (B, D).
    Marquardt's scaling by diag(J^T J) keeps the step invariant to the units of
    theta (mm for translations, rad for angles); the extra ``lambda I`` keeps DoFs
    that no residual observes at their current value.
    """
    JtJ = J.transpose(1, 2) @ J
    g = (J.transpose(1, 2) @ r[..., None])[..., 0]
    return solve_normal(JtJ, g, damping)


def solve_normal(JtJ: torch.Tensor, g: torch.Tensor, damping: torch.Tensor) -> torch.Tensor:
    """:func:`solve_damped` from the normal equations: JtJ (B, D, D), g (B, D) = J^T r,
    damping (B,) -> delta (B, D)."""
    lam = damping[:, None]
    diag = torch.diagonal(JtJ, dim1=1, dim2=2)
    A = JtJ + torch.diag_embed(lam * diag + lam)
    L, info = torch.linalg.cholesky_ex(A)
    delta = -torch.cholesky_solve(g[..., None], L)[..., 0]
    return torch.where((info == 0)[:, None], delta, torch.zeros_like(delta))


def levenberg_marquardt(
    problem: Union[LeastSquaresProblem, ResidualFn],
    theta0: torch.Tensor,
    lower: Optional[torch.Tensor] = None,
    upper: Optional[torch.Tensor] = None,
    max_iterations: int = 50,
    damping: float | torch.Tensor = 1e-3,
    step_tolerance: float = 0.0,
    check_every: int = 5,
    retries: int = 0,
    keep_going: Optional[Callable[[torch.Tensor, torch.Tensor], torch.Tensor]] = None,
) -> LMResult:
    """Minimise sum(r(theta)^2) for a batch of independent problems.

    Args:
        problem: a :class:`LeastSquaresProblem`, or ``f(theta, with_jacobian) -> (r (B,
            m), J (B, m, D) or None)``.
        theta0: (B, D) start; lower, upper: (D,) or (B, D) box bounds (may hold +-inf).
        max_iterations: iteration budget per problem; damping: initial lambda, a float or
            (B,) per problem.
        step_tolerance: a problem converges when the largest |delta| of an accepted
            step falls below it (in theta units); check_every: the loop exits early once
            every problem has converged, checked every ``check_every`` iterations.
        retries: a rejected step is tried again with ten times the damping, up to this
            many times within one iteration, reusing r and J (only the residuals at the
            new candidate are evaluated); the loop then syncs with the host once per
            attempt that could be followed by another, to stop when all accepted.
        keep_going: optional stopping rule ``keep_going(theta (B, D), iterations (B,)) ->
            (B,) bool``, read in the same transfer as that retry check, so a caller gets
            a per-problem flag at the solution without a second sync
            (:attr:`LMResult.going`).
    Returns:
        :class:`LMResult`.
    """
    theta = _clamp(theta0, lower, upper)
    B, dev = theta.shape[0], theta.device
    lam = torch.as_tensor(damping, dtype=theta.dtype, device=dev).expand(B).clone()
    iters, rejected = torch.zeros(B, dtype=torch.int64, device=dev), torch.zeros(B, dtype=torch.int64, device=dev)
    done = torch.zeros(B, dtype=torch.bool, device=dev)
    problem = problem if isinstance(problem, LeastSquaresProblem) else FunctionProblem(problem)
    ne = _linearize(problem, theta)
    evaluations, cost, host_status = 1, ne.cost, None
    for it in range(max_iterations):
        host_status = None
        if lower is not None or upper is not None:
            ne = _freeze_active_bounds(ne, theta, lower, upper)
        todo = ~done  # problems still looking for an acceptable step in this iteration
        for attempt in range(retries + 1):
            with stage("solve", work=lambda: _solve_work(ne.H)):
                delta = solve_normal(ne.H, ne.g, lam)
            cand = _clamp(theta + delta, lower, upper)
            r_new = problem.evaluate(cand)
            evaluations += 1
            cost_new = (r_new * r_new).sum(-1)
            accept = (cost_new < cost) & todo
            rejected = rejected + (todo & ~accept).long()
            theta = torch.where(accept[:, None], cand, theta)
            problem.accept(accept)
            lam = torch.where(accept, lam * 0.1, torch.where(todo, lam * 10, lam)).clamp(1e-9, 1e9)
            iters = iters + accept.long()
            done = done | (accept & (delta.abs().amax(-1) <= step_tolerance)) | (lam >= 1e9)
            cost = torch.where(accept, cost_new, cost)
            todo = todo & ~accept & ~done
            if attempt < retries:
                if keep_going is None:
                    if not bool(todo.any()):
                        break
                    continue
                with stage("host sync"):
                    flags = torch.cat([todo.any()[None], keep_going(theta, iters).bool()]).tolist()  # one transfer
                if not flags[0]:
                    host_status = flags[1:]
                    break
        if (it + 1) % check_every == 0 and bool(done.all()):
            break
        if it + 1 < max_iterations:
            ne = _linearize(problem, theta)
            evaluations += 1
    return LMResult(theta, cost, iters, done, lam, rejected, evaluations, host_status)


def _linearize(problem: LeastSquaresProblem, theta: torch.Tensor) -> NormalEquations:
    """The problem's linearisation at ``theta`` as normal equations (formed once, shared
    by the retries of a step)."""
    lin = problem.linearize(theta)
    if isinstance(lin, NormalEquations):
        return lin
    r, J = lin
    with stage("normal equations", work=lambda: _normal_work(J)):
        return normal_equations(r, J)


def _normal_work(J: torch.Tensor) -> tuple:
    """(flops, bytes) of J^T J and J^T r (2 m D^2 + 2 m D), J read once."""
    B, m, D = J.shape
    return B * 2.0 * m * D * (D + 1), 4.0 * B * m * D


def _solve_work(H: torch.Tensor) -> tuple:
    """(flops, bytes) of the damped Cholesky solve: D^3 / 3 + 2 D^2, H read once."""
    B, D = H.shape[:2]
    return B * (D ** 3 / 3.0 + 2.0 * D * D), 4.0 * B * D * D


def _freeze_active_bounds(ne: NormalEquations, theta, lower, upper) -> NormalEquations:
    """Zero the Jacobian columns of variables held at a bound by the gradient (their rows
    and columns of J^T J and their entries of J^T r).

    Without this, clamping the full step moves the free variables by a step computed
    as if the held ones could move too; that step is rejected and the damping crawls.
    """
    g = ne.g  # gradient of 0.5 |r|^2
    held = torch.zeros_like(theta, dtype=torch.bool)
    if lower is not None:
        held |= (theta <= lower) & (g > 0)
    if upper is not None:
        held |= (theta >= upper) & (g < 0)
    free = (~held).to(ne.H.dtype)
    return NormalEquations(ne.H * free[:, :, None] * free[:, None, :], g * free, ne.cost)


def _clamp(theta, lower, upper):
    if lower is not None:
        theta = torch.maximum(theta, lower)
    if upper is not None:
        theta = torch.minimum(theta, upper)
    return theta
