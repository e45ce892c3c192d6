"""Robust losses (torchhand.optim.robust_loss) and the term wrappers that apply them."""

from __future__ import annotations

import pytest
import torch

from torchhand.optim.robust_loss import LOSSES, Cauchy, Huber, Squared, Truncated, robust_loss

F64 = torch.float64


@pytest.mark.parametrize("name", sorted(LOSSES))
def test_weight_is_the_derivative_of_rho(name):
    loss = robust_loss(name, scale=2.0)
    s = torch.linspace(0.0, 30.0, 301, dtype=F64)[1:].requires_grad_()
    c2 = torch.tensor(4.0, dtype=F64)
    (g,) = torch.autograd.grad(loss.rho(s, c2).sum(), s)
    # the truncated loss has a jump in rho' at c^2: compare away from it
    away = (s - c2).abs() > 0.2
    torch.testing.assert_close(loss.weight(s, c2)[away], g[away])
    zero = torch.zeros(1, dtype=F64)
    assert float(loss.rho(zero, c2)) == 0.0 and float(loss.weight(zero, c2)) == 1.0
    w = loss.weight(s.detach(), c2)
    assert ((w >= 0) & (w <= 1)).all()
    # what the solver multiplies rows by, from the row norms
    torch.testing.assert_close(loss.sqrt_weight(s.detach().sqrt(), c2.sqrt()) ** 2, w)


def test_losses_match_their_formulas():
    s, c2 = torch.tensor([1.0, 9.0, 25.0], dtype=F64), torch.tensor(9.0, dtype=F64)
    torch.testing.assert_close(Cauchy(3.0).weight(s, c2), 1 / (1 + s / 9))
    torch.testing.assert_close(Huber(3.0).rho(s, c2), torch.tensor([1.0, 9.0, 2 * 3 * 5 - 9.0], dtype=F64))
    torch.testing.assert_close(Truncated(3.0).rho(s, c2), torch.tensor([1.0, 9.0, 9.0], dtype=F64))
    torch.testing.assert_close(Squared().weight(s, c2), torch.ones(3, dtype=F64))


def test_relative_scale_is_the_lower_median_per_group_and_problem():
    """c = max(scale, relative x median |r|) over the real rows of each (problem, group),
    against a loop with torch.median (the lower median, as the tracker used)."""
    g = torch.Generator().manual_seed(0)
    B, n, G = 3, 40, 3
    s = torch.rand(B, n, generator=g, dtype=F64) * 10  # row norms
    mask = torch.rand(B, n, generator=g) < 0.8
    mask[2] = False  # a problem without rows
    group = torch.randint(0, G, (B, n), generator=g)
    group[1] = 0  # groups 1 and 2 of problem 1 are empty
    loss = Cauchy(scale=3.0, relative=2.0)
    c = loss.scales(s, mask, group, G)
    for b in range(B):
        for k in range(G):
            rows = mask[b] & (group[b] == k)
            want = max(3.0, 2.0 * float(s[b][rows].median())) if rows.any() else 3.0
            torch.testing.assert_close(c[b][group[b] == k], torch.full_like(c[b][group[b] == k], want))
    sw = loss.sqrt_weights(s, mask, group, G)
    assert (sw[~mask] == 0).all() and (sw[mask] > 0).all()
    torch.testing.assert_close(sw[mask], (1 + (s / c) ** 2).rsqrt()[mask])
    torch.testing.assert_close(Cauchy(3.0).scales(s, mask, group, G), torch.full_like(s, 3.0))


def test_bad_loss_arguments_are_refused():
    with pytest.raises(ValueError, match="scale"):
        Cauchy(0.0)
    with pytest.raises(ValueError, match="relative"):
        Huber(1.0, relative=-2.0)
    with pytest.raises(ValueError, match="unknown robust loss"):
        robust_loss("l1")


def test_weighted_and_robust_wrap_any_term():
    """Weighted scales r and J by sqrt(w) and the unmatched energy by w; Robust scales each
    row by sqrt(rho') at the residuals of prepare and keeps those weights."""
    from torchhand.tracking.energies.base import EnergyTerm, Prepared, Residuals, counts
    from torchhand.tracking.energies.wrappers import Robust, Weighted

    class Linear(EnergyTerm):  # r = theta - target, two rows of dim 2
        name = "linear"

        def prepare(self, state):
            return Prepared(counts(1, correspondences=torch.tensor([2]), unmatched=torch.tensor([4.0], dtype=F64)))

        def residuals(self, theta, posed, prepared, jacobian=True):
            target = torch.tensor([[0.0, 0.0, 3.0, 4.0]], dtype=F64)
            J = torch.eye(4, dtype=F64)[None] if jacobian else None
            return Residuals(theta - target, J, 2)

    class State:
        theta = torch.zeros(1, 4, dtype=F64)
        posed = None
        correspondences = torch.tensor([10])

    w = Weighted(Linear(), 0.25)
    f = w.prepare(State())
    assert float(f.counts.unmatched) == 1.0 and int(f.counts.correspondences) == 2 and not w.prior
    res = w.residuals(State.theta, None, f)
    torch.testing.assert_close(res.r, -0.5 * torch.tensor([[0.0, 0.0, 3.0, 4.0]], dtype=F64))
    torch.testing.assert_close(res.J, 0.5 * torch.eye(4, dtype=F64)[None])
    per = Weighted(Linear(), 0.4, per_correspondence=True)  # w = 0.4 x C_all = 4
    assert per.prior
    pf = per.prepare(State())
    assert float(pf.counts.unmatched) == 16.0
    torch.testing.assert_close(per.residuals(State.theta, None, pf).r, 2.0 * Linear().residuals(State.theta, None,
                                                                                                 pf.inner).r)
    rob = Robust(Linear(), Cauchy(5.0))
    rf = rob.prepare(State())  # row norms 0 and 5: weights 1 and 1 / (1 + 1)
    moved = torch.ones(1, 4, dtype=F64)
    r = rob.residuals(moved, None, rf).r
    plain = Linear().residuals(moved, None, rf.inner).r
    torch.testing.assert_close(r, plain * torch.tensor([[1.0, 1.0, 0.5 ** 0.5, 0.5 ** 0.5]], dtype=F64))
    with pytest.raises(TypeError, match="RobustLoss"):
        Robust(Linear(), "cauchy")
    with pytest.raises(ValueError, match="weight"):
        Weighted(Linear(), -1.0)
