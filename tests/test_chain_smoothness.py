"""E_chain: the rope's consecutive joints bend alike; hands and rigid objects have none."""

from __future__ import annotations

import torch

from torchhand.data.chains import chain_object
from torchhand.model.articulated import ArticulatedModel
from torchhand.model.scene import Scene
from torchhand.tracking.energies import ChainSmoothness, default_priors, parse_energy
from torchhand.tracking.energies.chain_smoothness import MIN_JOINTS, chain_pairs

F64 = torch.float64


def test_pairs_are_the_ropes_consecutive_joints_only():
    scene = Scene.from_names(["hand_right", "rope"], dtype=F64)
    pairs = chain_pairs(scene)
    rope = scene.model("rope")
    start = scene.slices["rope"].start
    assert pairs.shape == (2 * (rope.num_bones - 2), 2)  # 34 joints after the first, about y and z
    names = [rope.dof_names[k - start] for k in pairs.flatten().tolist()]
    assert all(n.startswith("Bone") for n in names)  # never the root's or the hand's DoF
    for a, b in pairs.tolist():  # the same axis, child after parent
        na, nb = rope.dof_names[a - start], rope.dof_names[b - start]
        assert na.split(":")[1] == nb.split(":")[1] and int(nb[4:7]) == int(na[4:7]) + 1
    for names in (["hand_right", "hand_left", "ball"], ["pipe"], ["cube"]):
        assert chain_pairs(Scene.from_names(names)).shape == (0, 2)
    # a mechanism: hinges about the same axis, but too few to be a rope; a long one is
    few = Scene([ArticulatedModel(chain_object([60.0] * 4, ("z",) * 3))], names=["links"])
    assert chain_pairs(few).shape == (0, 2)
    many = Scene([ArticulatedModel(chain_object([30.0] * MIN_JOINTS + [30.0], ("z",) * MIN_JOINTS))], names=["links"])
    assert chain_pairs(many).shape == (MIN_JOINTS - 1, 2)
    assert any(isinstance(getattr(t, "term", None), ChainSmoothness) for t in default_priors())
    assert any(isinstance(getattr(t, "term", None), ChainSmoothness) for t in parse_energy("E+C+O+S"))


def _state(scene, theta):
    class _S:  # what prepare reads
        pass

    s = _S()
    s.scene, s.theta = scene, theta
    return s


def test_a_kink_costs_and_an_even_bend_does_not():
    scene = Scene.from_names(["rope"], dtype=F64)
    term = ChainSmoothness()
    even = torch.zeros(2, scene.num_dofs, dtype=F64)
    even[:, 6::2] = 0.1  # every joint bent by 0.1 rad about y
    p = term.prepare(_state(scene, even))
    assert float(term.residuals(even, None, p, jacobian=False).r.abs().max()) == 0.0
    kink = even.clone()
    kink[1, 6 + 2 * 10] = 0.6  # one joint folded
    r = term.residuals(kink, None, p, jacobian=False).r
    assert float(r[0].abs().max()) == 0.0 and torch.isclose(r[1].pow(2).sum(), torch.tensor(2 * 0.5 ** 2, dtype=F64))


def test_jacobian_matches_finite_differences():
    scene = Scene.from_names(["hand_right", "rope"], dtype=F64)
    term = ChainSmoothness()
    theta = 0.1 * torch.randn(1, scene.num_dofs, dtype=F64, generator=torch.Generator().manual_seed(0))
    p = term.prepare(_state(scene, theta))
    res = term.residuals(theta, None, p)
    eps = 1e-6
    num = torch.stack([(term.residuals(theta + eps * torch.eye(scene.num_dofs, dtype=F64)[k], None, p, False).r
                        - term.residuals(theta - eps * torch.eye(scene.num_dofs, dtype=F64)[k], None, p, False).r)
                       / (2 * eps) for k in range(scene.num_dofs)], -1)
    torch.testing.assert_close(res.J, num, atol=1e-8, rtol=0)
    hands = Scene.from_names(["hand_right"], dtype=F64)
    p = term.prepare(_state(hands, theta[:, :hands.num_dofs]))
    out = term.residuals(theta[:, :hands.num_dofs], None, p)
    assert out.r.shape == (1, 0) and out.J.shape == (1, 0, hands.num_dofs)
