"""Batched Levenberg-Marquardt (torchhand.optim.levenberg_marquardt)."""

from __future__ import annotations

import math

import pytest
import torch

from torchhand.optim.levenberg_marquardt import levenberg_marquardt, solve_damped

F64 = torch.float64
INF = math.inf

# Problem kinds, all with 2 unknowns and 2 residuals:
ROSENBROCK, LINEAR = 0, 1
A = torch.tensor([[3.0, 1.0], [1.0, 2.0]], dtype=F64)
X_LIN = torch.tensor([2.0, -1.0], dtype=F64)
B_LIN = A @ X_LIN


def make_residuals(kinds: torch.Tensor, log: list | None = None):
    """r = [10 (y - x^2), 1 - x] (Rosenbrock, minimum (1, 1)) or A x - b (minimum X_LIN)."""
    rosen = (kinds == ROSENBROCK)[:, None]

    def residuals(theta, with_jacobian):
        if log is not None:
            log.append(theta.detach().clone())
        x, y = theta[:, 0], theta[:, 1]
        r_rosen = torch.stack([10 * (y - x * x), 1 - x], -1)
        r_lin = theta @ A.T - B_LIN
        r = torch.where(rosen, r_rosen, r_lin)
        if not with_jacobian:
            return r, None
        one, zero = torch.ones_like(x), torch.zeros_like(x)
        J_rosen = torch.stack([torch.stack([-20 * x, 10 * one], -1), torch.stack([-one, zero], -1)], -2)
        J = torch.where(rosen[..., None], J_rosen, A.expand(len(x), 2, 2))
        return r, J

    return residuals


def test_batch_of_independent_problems_reaches_known_minima():
    kinds = torch.tensor([ROSENBROCK, LINEAR, ROSENBROCK, LINEAR])
    theta0 = torch.tensor([[-1.2, 1.0], [0.0, 0.0], [2.0, -3.0], [100.0, 50.0]], dtype=F64)
    res = levenberg_marquardt(make_residuals(kinds), theta0, max_iterations=100, step_tolerance=1e-12)
    expected = torch.tensor([[1.0, 1.0], [2.0, -1.0], [1.0, 1.0], [2.0, -1.0]], dtype=F64)
    torch.testing.assert_close(res.theta, expected, rtol=0, atol=1e-8)
    assert (res.cost < 1e-16).all()
    assert res.converged.all()
    assert (res.iterations > 0).all()
    assert res.iterations.dtype == torch.int64 and res.cost.shape == (4,)


def test_problem_already_at_minimum_stays_while_others_move():
    kinds = torch.tensor([ROSENBROCK, ROSENBROCK, LINEAR])
    theta0 = torch.tensor([[1.0, 1.0], [-1.2, 1.0], [5.0, 5.0]], dtype=F64)
    res = levenberg_marquardt(make_residuals(kinds), theta0, max_iterations=60)
    assert torch.equal(res.theta[0], theta0[0])  # exactly unchanged
    assert res.iterations[0] == 0 and res.cost[0] == 0
    assert res.converged[0]  # its damping grew until it gave up
    assert (res.iterations[1:] > 0).all()
    torch.testing.assert_close(res.theta[1:], torch.tensor([[1.0, 1.0], [2.0, -1.0]], dtype=F64), rtol=0, atol=1e-8)


def test_batched_solution_equals_each_problem_solved_alone():
    """Per-problem damping: a hard problem in the batch changes nothing for the others."""
    kinds = torch.tensor([ROSENBROCK, LINEAR, ROSENBROCK, ROSENBROCK])
    theta0 = torch.tensor([[-1.2, 1.0], [7.0, 3.0], [1.0, 1.0], [-3.0, 8.0]], dtype=F64)
    batch = levenberg_marquardt(make_residuals(kinds), theta0, max_iterations=15)
    for b in range(4):
        alone = levenberg_marquardt(make_residuals(kinds[b : b + 1]), theta0[b : b + 1], max_iterations=15)
        torch.testing.assert_close(batch.theta[b : b + 1], alone.theta, rtol=1e-12, atol=1e-12)
        assert batch.iterations[b] == alone.iterations[0]
        torch.testing.assert_close(batch.cost[b : b + 1], alone.cost, rtol=1e-12, atol=1e-15)


BOUNDED_KINDS = torch.tensor([ROSENBROCK, LINEAR, ROSENBROCK])
BOUNDED_THETA0 = torch.tensor([[-1.2, 1.0], [0.0, 0.0], [3.0, 3.0]], dtype=F64)  # problem 2 starts outside
BOUNDED_LOWER = torch.tensor([[-INF, -INF], [-INF, -0.5], [-2.0, -2.0]], dtype=F64)
BOUNDED_UPPER = torch.tensor([[0.5, INF], [INF, INF], [2.0, 2.0]], dtype=F64)


def test_bounds_are_respected_at_every_evaluation():
    log = []
    res = levenberg_marquardt(make_residuals(BOUNDED_KINDS, log), BOUNDED_THETA0, lower=BOUNDED_LOWER,
                              upper=BOUNDED_UPPER, max_iterations=100)
    assert len(log) > 100
    for th in log:
        assert ((th >= BOUNDED_LOWER) & (th <= BOUNDED_UPPER)).all()
    assert torch.equal(log[0][2], torch.tensor([2.0, 2.0], dtype=F64))  # the start is projected first
    assert res.theta[0, 0] == 0.5 and res.theta[1, 1] == -0.5  # the bounds are active
    # problem 2: the unconstrained minimum (1, 1) lies inside its box
    torch.testing.assert_close(res.theta[2], torch.tensor([1.0, 1.0], dtype=F64), rtol=0, atol=1e-8)
    # bounded problems still improve a lot on their start
    r0, _ = make_residuals(BOUNDED_KINDS)(BOUNDED_THETA0.clamp(BOUNDED_LOWER, BOUNDED_UPPER), False)
    assert (res.cost < 0.1 * (r0 * r0).sum(-1)).all()


def test_active_bounds_reach_the_constrained_minimum():
    res = levenberg_marquardt(make_residuals(BOUNDED_KINDS), BOUNDED_THETA0, lower=BOUNDED_LOWER,
                              upper=BOUNDED_UPPER, max_iterations=100)
    # problem 0: x <= 0.5 -> minimum on the bound at (0.5, 0.25)
    torch.testing.assert_close(res.theta[0], torch.tensor([0.5, 0.25], dtype=F64), rtol=0, atol=1e-6)
    # problem 1: y >= -0.5 cuts off (2, -1): the minimum is the 1-D least-squares x on y = -0.5
    x_best = (A[:, 0] @ (B_LIN - A[:, 1] * -0.5)) / (A[:, 0] @ A[:, 0])
    torch.testing.assert_close(res.theta[1], torch.stack([x_best, torch.tensor(-0.5, dtype=F64)]),
                               rtol=0, atol=1e-6)


def test_shared_1d_bounds_equal_per_problem_bounds():
    kinds = torch.tensor([LINEAR, ROSENBROCK])
    theta0 = torch.tensor([[0.0, 0.0], [-1.2, 1.0]], dtype=F64)
    lower = torch.tensor([-INF, -0.5], dtype=F64)
    upper = torch.tensor([1.5, INF], dtype=F64)
    shared = levenberg_marquardt(make_residuals(kinds), theta0, lower=lower, upper=upper, max_iterations=40)
    per = levenberg_marquardt(make_residuals(kinds), theta0, lower=lower.expand(2, 2), upper=upper.expand(2, 2),
                              max_iterations=40)
    assert torch.equal(shared.theta, per.theta)
    assert (shared.theta[:, 0] <= 1.5).all() and (shared.theta[:, 1] >= -0.5).all()


def test_cost_never_increases_and_is_the_final_sum_of_squares():
    kinds = torch.tensor([ROSENBROCK])
    theta0 = torch.tensor([[-1.2, 1.0]], dtype=F64)
    costs = []
    for it in (1, 2, 5, 10, 20):
        res = levenberg_marquardt(make_residuals(kinds), theta0, max_iterations=it)
        r, _ = make_residuals(kinds)(res.theta, False)
        torch.testing.assert_close(res.cost, (r * r).sum(-1), rtol=1e-14, atol=0)
        costs.append(res.cost.item())
    assert all(b <= a for a, b in zip(costs, costs[1:]))


def test_solve_damped_tends_to_least_squares_and_keeps_unobserved_dofs():
    g = torch.Generator().manual_seed(70)
    J = torch.randn(3, 6, 4, generator=g, dtype=F64)
    r = torch.randn(3, 6, generator=g, dtype=F64)
    delta = solve_damped(J, r, torch.full((3,), 1e-12, dtype=F64))
    ref = torch.linalg.lstsq(J, -r[..., None]).solution[..., 0]
    torch.testing.assert_close(delta, ref, rtol=1e-8, atol=1e-8)
    # a DoF that no residual observes gets no step (the lambda I term)
    J[:, :, 2] = 0
    delta = solve_damped(J, r, torch.full((3,), 1e-3, dtype=F64))
    assert torch.isfinite(delta).all() and (delta[:, 2] == 0).all()
    # larger damping gives shorter steps
    small = solve_damped(J, r, torch.full((3,), 1e-3, dtype=F64)).norm(dim=-1)
    large = solve_damped(J, r, torch.full((3,), 1e3, dtype=F64)).norm(dim=-1)
    assert (large < small).all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_linear_problem_solves_in_both_dtypes(dtype):
    A32, b32 = A.to(dtype), B_LIN.to(dtype)

    def residuals(theta, with_jacobian):
        r = theta @ A32.T - b32
        return r, (A32.expand(len(theta), 2, 2) if with_jacobian else None)

    res = levenberg_marquardt(residuals, torch.zeros(1, 2, dtype=dtype), max_iterations=30)
    assert res.theta.dtype == dtype
    torch.testing.assert_close(res.theta[0], X_LIN.to(dtype), rtol=1e-4, atol=1e-4)


def test_retries_end_an_iteration_with_an_accepted_step_and_reuse_the_jacobian():
    """With a tiny damping the Gauss-Newton step on Rosenbrock from (-1.2, 1) is
    rejected; with retries the same iteration tries again with more damping (one
    Jacobian, several residual evaluations) until a step is accepted, and the problem
    already at its minimum stays put."""
    kinds = torch.tensor([ROSENBROCK, ROSENBROCK])
    theta0 = torch.tensor([[-1.2, 1.0], [1.0, 1.0]], dtype=F64)
    calls = []

    def counted(theta, with_jacobian):
        calls.append(with_jacobian)
        return make_residuals(kinds)(theta, with_jacobian)

    plain = levenberg_marquardt(counted, theta0, max_iterations=1, damping=1e-9)
    assert plain.iterations.tolist() == [0, 0]  # rejected, no retry
    calls.clear()
    res = levenberg_marquardt(counted, theta0, max_iterations=1, damping=1e-9, retries=20)
    assert calls.count(True) == 1 and calls.count(False) > 1
    assert res.iterations.tolist() == [1, 0]
    assert res.cost[0] < 24.2 and torch.equal(res.theta[1], theta0[1])  # 24.2: the cost at theta0
    assert res.damping[0] > 1e-9
