"""Neighbour queries (torchhand.geometry.neighbors): the Warp kernels against brute force,
and the batched helpers of the energy terms against loops."""

from __future__ import annotations

import pytest
import torch

from torchhand.geometry.neighbors import (PointIndex, marked_boxes, nearest_marked_pixel,
                                          pixel_hash)
from torchhand.tracking.energies.base import bone_inliers, stride_subsample

try:
    import warp  # noqa: F401

    HAVE_WARP = True
except ImportError:  # pragma: no cover
    HAVE_WARP = False

needs_warp = pytest.mark.skipif(not HAVE_WARP, reason="NVIDIA Warp is not installed")


def _points(seed=0, n=3000):
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(n, 3, generator=g) * torch.tensor([200.0, 150.0, 100.0]) + torch.tensor([-100.0, -50.0, 400.0])
    problem = torch.randint(0, 3, (n,), generator=g)
    group = torch.randint(0, 2, (n,), generator=g)
    q = pts[torch.randint(0, n, (3, 500), generator=g)] + torch.randn(3, 500, 3, generator=g) * 6.0
    qgroup = torch.randint(-1, 2, (3, 500), generator=g)
    return pts, problem, group, q, qgroup


def _slow_nearest(pts, problem, group, q, problems, qgroup, radius):
    out = torch.full(qgroup.shape, -1, dtype=torch.int64)
    for b in range(q.shape[0]):
        for i in range(q.shape[1]):
            if qgroup[b, i] < 0:
                continue
            cand = torch.nonzero((problem == problems[b]) & (group == qgroup[b, i]))[:, 0]
            d = (pts[cand] - q[b, i]).norm(dim=-1)
            if len(d) and d.min() <= radius:
                out[b, i] = cand[d.argmin()]
    return out


@pytest.mark.parametrize("backend", ["torch", "cpu", pytest.param("warp", marks=needs_warp)])
def test_point_index_finds_the_nearest_of_the_same_problem_and_group(backend):
    pts, problem, group, q, qgroup = _points()
    problems = torch.tensor([2, 0, 1])  # rows of queries belong to these problems
    index = PointIndex(pts, problem, group, 3, 2, 10.0, backend)
    got = index.nearest(q, problems, qgroup)
    want = _slow_nearest(pts, problem, group, q, problems, qgroup, 10.0)
    # the same distance (equal points are a measure-zero event here)
    assert torch.equal(got >= 0, want >= 0) and int((got >= 0).sum()) > 300 and int((got < 0).sum()) > 100
    found = got >= 0
    d_got = (pts[got[found]] - q[found]).norm(dim=-1)
    d_want = (pts[want[found]] - q[found]).norm(dim=-1)
    torch.testing.assert_close(d_got, d_want, atol=1e-4, rtol=0)
    assert (problem[got[found]] == problems[:, None].expand_as(got)[found]).all()
    assert (group[got[found]] == qgroup[found]).all()
    smaller = index.nearest(q, problems, qgroup, radius=4.0)
    assert int((smaller >= 0).sum()) < int(found.sum())
    with pytest.raises(ValueError, match="exceeds"):
        index.nearest(q, problems, qgroup, radius=11.0)


@needs_warp
@pytest.mark.parametrize("cell", [0.7, 1.25, 3.0, 10.0])
def test_point_index_cells_of_any_size_find_the_same_nearest(cell):
    """The grid's cell only sets where a query's growing radius starts: the result is the
    exact nearest for any cell (the labels use an eighth of their radius)."""
    pts, problem, group, q, qgroup = _points()
    problems = torch.tensor([2, 0, 1])
    got = PointIndex(pts, problem, group, 3, 2, 10.0, "warp", cell=cell).nearest(q, problems, qgroup)
    want = PointIndex(pts, problem, group, 3, 2, 10.0, "warp").nearest(q, problems, qgroup)
    assert torch.equal(got, want) and int((got >= 0).sum()) > 300


@pytest.mark.parametrize("backend", ["torch", "cpu", pytest.param("warp", marks=needs_warp)])
def test_point_index_any_point_finds_a_point_where_the_nearest_is_found(backend):
    pts, problem, group, q, qgroup = _points()
    problems = torch.tensor([2, 0, 1])
    index = PointIndex(pts, problem, group, 3, 2, 10.0, backend)
    nearest, some = index.nearest(q, problems, qgroup), index.nearest(q, problems, qgroup, any_point=True)
    assert torch.equal(some >= 0, nearest >= 0)
    found = some >= 0
    assert ((pts[some[found]] - q[found]).norm(dim=-1) <= 10.0 + 1e-5).all()
    assert (group[some[found]] == qgroup[found]).all()
    assert (problem[some[found]] == problems[:, None].expand_as(some)[found]).all()


@needs_warp
def test_point_index_radius_is_inclusive():
    pts = torch.tensor([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 0.0, 10.5]])
    zero = torch.zeros(3, dtype=torch.int64)
    q = torch.tensor([[[0.0, 0.0, 10.0], [20.0, 0.0, 0.0], [0.0, -10.0, 0.0]]])
    for backend in ("warp", "cpu", "torch"):
        index = PointIndex(pts, zero, zero, 1, 1, 10.0, backend)
        got = index.nearest(q, torch.tensor([0]), torch.zeros(1, 3, dtype=torch.int64))
        assert got.tolist() == [[2, 1, 0]], backend  # 0.5 beats 10; a distance of exactly 10 counts


def _marks(seed=0):
    g = torch.Generator().manual_seed(seed)
    marks = torch.full((2, 60, 80), -1, dtype=torch.int64)
    ring = torch.zeros(60, 80, dtype=torch.bool)
    v, u = torch.meshgrid(torch.arange(60.0), torch.arange(80.0), indexing="ij")
    r = ((v - 30) ** 2 + (u - 40) ** 2).sqrt()
    ring = (r > 14) & (r < 15.2)  # a circle: many equidistant pixels
    marks[0][ring] = 0
    marks[0, 5:9, 60:75] = 1
    marks[1][torch.rand(60, 80, generator=g) < 0.01] = 1
    queries = torch.stack([torch.randint(0, 60, (2, 400), generator=g), torch.randint(0, 80, (2, 400), generator=g)], -1)
    groups = torch.randint(-1, 2, (2, 400), generator=g)
    radius = torch.randint(3, 30, (2, 400), generator=g)
    return marks, queries, groups, radius


@needs_warp
def test_nearest_marked_pixel_warp_equals_brute_force():
    marks, queries, groups, radius = _marks()
    got = nearest_marked_pixel(marks, queries, groups, radius, 2, "warp")
    want = nearest_marked_pixel(marks, queries, groups, radius, 2, "torch")
    assert int((got[..., 0] >= 0).sum()) > 200 and int((got[..., 0] < 0).sum()) > 100
    assert torch.equal(got, want)  # ties broken the same way: by the pixel hash
    found = got[..., 0] >= 0
    assert (marks[torch.arange(2)[:, None].expand_as(groups)[found], got[found][:, 0], got[found][:, 1]]
            == groups[found]).all()
    d = (got - queries).double().norm(dim=-1)
    assert (d[found] <= radius[found].double()).all()


@needs_warp
def test_marked_boxes_given_once_search_the_same():
    """Boxes computed once (marked_boxes) give what the search computes itself; boxes of
    another group count are refused."""
    marks, queries, groups, radius = _marks()
    boxes = marked_boxes(marks, 2)
    assert boxes.shape == (4, 4)
    for i in range(2):
        for k in range(2):
            pix = torch.nonzero(marks[i] == k)
            if len(pix) == 0:  # image 1 has no pixel of group 0: an empty box
                assert (i, k) == (1, 0) and boxes[i * 2 + k, 0] > boxes[i * 2 + k, 1]
                continue
            want = [*pix[:, 0].aminmax(), *pix[:, 1].aminmax()]
            assert boxes[i * 2 + k].tolist() == [int(x) for x in want]
    got = nearest_marked_pixel(marks, queries, groups, radius, 2, "warp", boxes=boxes)
    assert torch.equal(got, nearest_marked_pixel(marks, queries, groups, radius, 2, "warp"))
    with pytest.raises(ValueError, match=r"boxes must be marked_boxes\(marks, 2\)"):
        nearest_marked_pixel(marks, queries, groups, radius, 2, "warp", boxes=marked_boxes(marks, 3))


@pytest.mark.parametrize("backend", ["torch", "cpu"] + (["warp"] if HAVE_WARP else []))
def test_query_rows_can_share_marks_images(backend):
    """Rows that name their image (``images``) get what copies of it would give; a
    wrong count is refused."""
    marks, queries, groups, radius = _marks()
    images = torch.tensor([1, 0, 1, 1])
    q, g, r = queries[images.tolist()], groups[images.tolist()], radius[images.tolist()]
    q[2:] = q[2:].flip(1)  # rows on one image need not be alike
    want = nearest_marked_pixel(marks[images], q, g, r, 2, backend)
    assert torch.equal(nearest_marked_pixel(marks, q, g, r, 2, backend, images=images), want)
    assert int((want[..., 0] >= 0).sum()) > 400
    with pytest.raises(ValueError, match="one marks image per query row"):
        nearest_marked_pixel(marks, q, g, r, 2, backend, images=images[:3])
    with pytest.raises(ValueError, match="one image per query row"):
        nearest_marked_pixel(marks, q, g, r, 2, backend)


def test_nearest_marked_pixel_scipy_is_exact_too():
    marks, queries, groups, radius = _marks()
    got = nearest_marked_pixel(marks, queries, groups, radius, 2, "cpu")
    want = nearest_marked_pixel(marks, queries, groups, radius, 2, "torch")
    assert torch.equal(got[..., 0] >= 0, want[..., 0] >= 0)
    found = want[..., 0] >= 0
    d = lambda p: ((p - queries) ** 2).sum(-1)  # noqa: E731
    assert torch.equal(d(got)[found], d(want)[found])  # the same distance; ties may differ


def test_nearest_marked_pixel_is_the_exact_nearest():
    marks, queries, groups, radius = _marks(1)
    got = nearest_marked_pixel(marks, queries, groups, torch.full_like(radius, 1000), 2, "torch")
    for b in range(2):
        for i in range(0, 400, 7):
            if groups[b, i] < 0:
                continue
            pix = torch.nonzero(marks[b] == groups[b, i])
            if len(pix) == 0:
                assert (got[b, i] == -1).all()
                continue
            d2 = ((pix - queries[b, i]) ** 2).sum(-1)
            best = d2.min()
            assert ((got[b, i] - queries[b, i]) ** 2).sum() == best
            tied = pix[d2 == best]
            assert torch.equal(got[b, i], tied[pixel_hash(tied[:, 0], tied[:, 1]).argmin()])


def test_stride_subsample_equals_the_loop():
    g = torch.Generator().manual_seed(0)
    mask = torch.rand(4, 500, generator=g) < torch.tensor([[0.9], [0.3], [0.01], [0.0]])
    index, ok = stride_subsample(mask, 100)
    for b in range(4):
        pos = torch.nonzero(mask[b])[:, 0]
        if len(pos) > 100:
            want = pos[torch.floor(torch.arange(100).double() * (len(pos) - 1) / 99).long()]
        else:
            want = pos
        assert torch.equal(index[b][ok[b]], want) and int(ok[b].sum()) == len(want)


def test_batched_bone_inliers_equal_the_per_problem_rule():
    g = torch.Generator().manual_seed(3)
    d = torch.rand(3, 200, generator=g, dtype=torch.float64) * 10
    d[:, ::17] += 40
    bone = torch.randint(0, 5, (3, 200), generator=g)
    keep = torch.rand(3, 200, generator=g) < 0.8
    got = bone_inliers(d, bone, keep, 5, 2.0)
    for b in range(3):
        assert torch.equal(got[b], bone_inliers(d[b], bone[b], keep[b], 5, 2.0))
    assert not got.all() and got.float().mean() > 0.8
