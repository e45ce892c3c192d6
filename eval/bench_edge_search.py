"""The edge term's nearest-pixel search with the edge images' boxes computed on every
search (before) and given once per frame (:func:`torchhand.geometry.chamfer.contour_boxes`,
what the edge term does now), alternately in one process.

    python eval/bench_edge_search.py --json out/bench_edge_search.json

The images: ``--views`` random edge images of 1280x960 with 3 % of their pixels marked
(one group, as DCH-Thres marks them), searched by 400 rim pixels each within 40 px.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from torchhand.geometry.neighbors import marked_boxes, nearest_marked_pixel


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--json", type=Path, required=True)
    p.add_argument("--views", type=int, default=8)
    p.add_argument("--repeats", type=int, default=20)
    args = p.parse_args(argv)
    g = torch.Generator().manual_seed(0)
    V, H, W, n = args.views, 960, 1280, 400
    marks = torch.full((V, H, W), -1, dtype=torch.int64)
    marks[torch.rand(V, H, W, generator=g) < 0.03] = 0
    q = torch.stack([torch.randint(0, H, (V, n), generator=g), torch.randint(0, W, (V, n), generator=g)], -1)
    groups, radius = torch.zeros(V, n, dtype=torch.int64), torch.full((V, n), 40)
    boxes = marked_boxes(marks, 1)
    want = nearest_marked_pixel(marks, q, groups, radius, 1, "warp")
    if not torch.equal(nearest_marked_pixel(marks, q, groups, radius, 1, "warp", boxes=boxes), want):
        raise RuntimeError("the search with given boxes differs from the search that computes them")
    computed = given = 0.0
    for _ in range(args.repeats):
        t = time.perf_counter()
        nearest_marked_pixel(marks, q, groups, radius, 1, "warp")
        computed += time.perf_counter() - t
        t = time.perf_counter()
        nearest_marked_pixel(marks, q, groups, radius, 1, "warp", boxes=boxes)
        given += time.perf_counter() - t
    result = {"views": V, "image": [W, H], "queries_per_view": n, "threads": torch.get_num_threads(),
              "ms_boxes_computed": 1e3 * computed / args.repeats, "ms_boxes_given": 1e3 * given / args.repeats,
              "speedup": computed / given}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=1))
    print(f"boxes computed {result['ms_boxes_computed']:.1f} ms, given {result['ms_boxes_given']:.1f} ms "
          f"({result['speedup']:.1f}x)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
