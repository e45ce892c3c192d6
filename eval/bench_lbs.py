"""Linear blend skinning, forward + backward: torchhand vs smplx on identical inputs.

    python eval/bench_lbs.py --json out/bench_lbs.json [--batch-sizes 1,64,1024] [--repeats N] [--threads T]

The thesis right hand (10,002 vertices, 20 bones) is posed with random poses within
its limits. For every batch size B, in one process and on the same tensors:

* ``torchhand`` (dense and sparse CSR skinning matrix): given bone motions
  ``G: (B, J, 4, 4)`` that require grad, ``v = torchhand.model.skinning.lbs(G, P)`` with the
  static ``P = skinning_matrix(...)``; loss ``(v * w).sum()``; gradient w.r.t. ``G``.
  ``torchhand_ms`` is the layout the model uses by default (``model.skinning_matrix``);
  the other layout is reported as an extra key.
* ``smplx`` (skinning step only): :func:`smplx_skinning`, the lines of
  ``smplx.lbs.lbs`` from ``# 5. Do skinning`` onward, with ``A = G`` (smplx's
  ``rel_transforms`` are exactly the motions relative to the rest pose), the dense
  ``(V, J)`` weights and the rest vertices as ``v_posed``; same loss, gradient w.r.t. ``A``.
* ``smplx_full_lbs``: the complete ``smplx.lbs.lbs`` call for this mesh with zero
  shape blend shapes (``shapedirs`` V x 3 x 1), zero pose blend shapes (``posedirs``
  (J-1)*9 x V*3), a ``J_regressor`` that reproduces the bone origins exactly, the
  model's ``parents`` and the local rotation matrices of the same poses
  (``pose2rot=False``), plus the global translation added as smplx's body models do.
  It therefore also includes smplx's shape/pose blend shapes, joint regression and
  forward kinematics (``batch_rigid_transform``); gradient w.r.t. rotations and translation.

Before timing, the script checks that all variants give the same posed vertices
(max abs diff < 1e-3 mm in float32) and that torchhand's and smplx's gradients w.r.t.
the bone transforms agree; it exits with an error otherwise.

Each cell (batch size x method) is warmed up, then timed with ``time.perf_counter``
over ``--repeats`` forward + backward steps (default: enough for ~1.5 s per cell);
the methods of one batch size are timed round-robin, so that load from other
processes hits all of them alike; the median is reported (the minimum too). Writes::

    {"B1": {"torchhand_ms": a, "smplx_ms": b, "speedup": b / a, "torchhand_dense_ms": ...,
            "torchhand_sparse_ms": ..., "smplx_full_lbs_ms": ..., ...},
     "B64": {...}, "B1024": {...},
     "vertices": 10002, "bones": 20, "threads": n, "torch": "2.x", "torchhand_default": "dense"}
"""

from __future__ import annotations

import argparse
import gc
import importlib.metadata
import json
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Callable, Dict, List

import torch
from tqdm import tqdm

import smplx
import smplx.lbs

SMPLX_VERSION = importlib.metadata.version("smplx")

from torchhand.model.articulated import load_model
from torchhand.model.skinning import dense_weights, lbs, skinning_matrix

TOL_MM = 1e-3  # max abs difference of posed vertices (float32, mm)
GRAD_RTOL = 1e-4  # max abs gradient difference relative to the gradient's max abs value
TARGET_SPEEDUP = 2.0  # issue target at the largest batch size


# --------------------------------------------------------------------------- smplx
def smplx_skinning(A: torch.Tensor, W: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """The skinning step of ``smplx.lbs.lbs`` (smplx 0.1.28), unchanged.

    smplx has no separately importable skinning function, so the lines below are
    smplx's own, from ``# 5. Do skinning`` to ``verts = ...``, with only the inputs
    renamed: ``A`` (B, J, 4, 4) = smplx's ``A`` (rel_transforms), ``W`` (V, J) =
    ``lbs_weights``, ``v`` (B, V, 3) = ``v_posed``; ``num_joints`` is ``A.shape[1]``
    instead of ``J_regressor.shape[0]`` (the same number).
    """
    batch_size = A.shape[0]
    dtype, device = A.dtype, A.device
    lbs_weights, v_posed = W, v
    # ---- begin: smplx/lbs.py, lbs(), "# 5. Do skinning:" onward ----
    # 5. Do skinning:
    # W is N x V x (J + 1)
    W = lbs_weights.unsqueeze(dim=0).expand([batch_size, -1, -1])
    # (N x V x (J + 1)) x (N x (J + 1) x 16)
    num_joints = A.shape[1]  # smplx: J_regressor.shape[0]
    T = torch.matmul(W, A.view(batch_size, num_joints, 16)) \
        .view(batch_size, -1, 4, 4)

    homogen_coord = torch.ones([batch_size, v_posed.shape[1], 1],
                               dtype=dtype, device=device)
    v_posed_homo = torch.cat([v_posed, homogen_coord], dim=2)
    v_homo = torch.matmul(T, torch.unsqueeze(v_posed_homo, dim=-1))

    verts = v_homo[:, :, :3, 0]
    # ---- end of smplx's lines ----
    return verts


def joint_regressor(vertices: torch.Tensor, joints: torch.Tensor, k: int = 8) -> torch.Tensor:
    """(J, V) regressor with ``R @ vertices == joints``: for every joint the minimum-norm
    affine combination of its k nearest vertices (computed in float64)."""
    v = vertices.double()
    q = joints.double()
    R = torch.zeros(q.shape[0], v.shape[0], dtype=torch.float64)
    for j in range(q.shape[0]):
        ids = torch.cdist(q[j : j + 1], v)[0].topk(k, largest=False).indices
        M = torch.cat([v[ids].T, torch.ones(1, k, dtype=torch.float64)], 0)  # (4, k)
        rhs = torch.cat([q[j], torch.ones(1, dtype=torch.float64)])
        R[j, ids] = torch.linalg.pinv(M) @ rhs
    return R


def local_rotations(G: torch.Tensor, parents: torch.Tensor) -> torch.Tensor:
    """Rotation matrices smplx's ``batch_rigid_transform`` needs to reproduce G:
    R_0 = rot(G_0), R_j = rot(G_parent)^T rot(G_j). (B, J, 4, 4) -> (B, J, 3, 3)."""
    Rw = G[..., :3, :3]
    R = Rw.clone()
    R[:, 1:] = Rw[:, parents[1:]].transpose(-1, -2) @ Rw[:, 1:]
    return R


# ---------------------------------------------------------------------- timing
def time_cells(steps: Dict[str, Callable[[], object]], repeats: int | None, bar: tqdm, warmup: int = 3,
               target_s: float = 1.5, min_repeats: int = 5, max_repeats: int = 500) -> Dict[str, Dict]:
    """Median wall time (ms) of every step (one cell each) after ``warmup`` calls.

    The steps are timed round-robin (one call of each in turn) so that a change in
    the machine's load hits all of them alike. ``repeats`` None gives each step
    enough repeats for ~target_s seconds of its own time, calibrated on the warm-up
    calls after the first. ``bar`` advances by one per finished cell (fractionally
    while it runs).
    """
    need: Dict[str, int] = {}
    for name, step in steps.items():
        bar.set_postfix_str(f"warm-up {name}")
        warm: List[float] = []
        for _ in range(warmup):
            t0 = time.perf_counter()
            step()
            warm.append(time.perf_counter() - t0)
        if repeats is None:  # calibrate on the warm-up calls after the first
            one = statistics.median(warm[1:] or warm)
            need[name] = int(min(max_repeats, max(min_repeats, math.ceil(target_s / max(one, 1e-6)))))
        else:
            need[name] = repeats
    times: Dict[str, List[float]] = {name: [] for name in steps}
    bar.set_postfix_str("timing " + ", ".join(steps))
    start = bar.n
    while any(len(times[n]) < need[n] for n in steps):
        for name, step in steps.items():
            if len(times[name]) >= need[name]:
                continue
            t0 = time.perf_counter()
            step()
            times[name].append(time.perf_counter() - t0)
        bar.update(sum(len(times[n]) / need[n] for n in steps) + start - bar.n)
    return {
        n: {"median_ms": 1e3 * statistics.median(t), "min_ms": 1e3 * min(t), "repeats": len(t)}
        for n, t in times.items()
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", required=True, type=Path, help="output JSON file")
    ap.add_argument("--batch-sizes", default="1,64,1024", help="comma-separated batch sizes")
    ap.add_argument("--repeats", type=int, default=None, help="timed steps per cell (default: ~1.5 s per cell)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: all cores)")
    ap.add_argument("--no-full-lbs", action="store_true", help="skip the full smplx.lbs.lbs column")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    threads = args.threads or len(os.sched_getaffinity(0))
    torch.set_num_threads(threads)
    load_start = os.getloadavg()
    batch_sizes = [int(b) for b in args.batch_sizes.split(",") if b.strip()]
    gen = torch.Generator().manual_seed(args.seed)

    model = load_model("hand_right")  # float32
    V, J = model.num_vertices, model.num_bones
    default_layout = "dense" if model.skinning_matrix.layout == torch.strided else "sparse"
    W = dense_weights(model.skin_index, model.skin_weight, J)  # (V, J)
    density = float((W != 0).float().mean())
    P = {
        "dense": skinning_matrix(model.vertices_rest, model.skin_index, model.skin_weight, J, sparse=False),
        "sparse": skinning_matrix(model.vertices_rest, model.skin_index, model.skin_weight, J, sparse=True),
    }
    # smplx inputs for the full lbs: zero blend shapes, exact joint regressor.
    joints_rest = model.rest_transforms[:, :3, 3]
    J_regressor = joint_regressor(model.vertices_rest, joints_rest).float()
    reg_err = float((J_regressor @ model.vertices_rest - joints_rest).abs().max())
    shapedirs = torch.zeros(V, 3, 1)
    posedirs = torch.zeros((J - 1) * 9, V * 3)
    parents = model.parents.clone()

    print(f"hand_right: {V} vertices, {J} bones, weight density {density:.1%}, "
          f"model default skinning matrix: {default_layout}; torch {torch.__version__}, "
          f"smplx {SMPLX_VERSION}, {threads} threads; "
          f"J_regressor max error {reg_err:.2e} mm")

    methods = ["torchhand_dense", "torchhand_sparse", "smplx"] + ([] if args.no_full_lbs else ["smplx_full_lbs"])
    results: Dict[str, Dict] = {}
    failures: List[str] = []
    bar = tqdm(total=len(batch_sizes) * len(methods), desc="lbs bench",
               bar_format="{l_bar}{bar}| {n:.1f}/{total} cells [{elapsed}<{remaining}{postfix}]")
    for B in batch_sizes:
        # ------------------------------------------------------------ inputs
        theta = model.zero_pose(B)
        lo, hi = model.lower.clone(), model.upper.clone()
        fin = torch.isfinite(lo) & torch.isfinite(hi)
        u = torch.rand(B, model.num_dofs, generator=gen)
        theta[:, fin] = lo[fin] + (hi[fin] - lo[fin]) * u[:, fin]
        theta[:, :3] = 50.0 * torch.randn(B, 3, generator=gen)  # mm
        theta[:, 3:6] = 0.5 * torch.randn(B, 3, generator=gen)  # rad
        with torch.no_grad():
            G0 = model.kinematics(theta).G.contiguous()  # (B, J, 4, 4)
        w = torch.randn(B, V, 3, generator=gen)  # random loss weights
        v_posed = model.vertices_rest.expand(B, V, 3)  # smplx's v_posed (no blend shapes)
        rot0 = local_rotations(G0, parents).contiguous()  # (B, J, 3, 3)
        c = joints_rest[0]
        transl0 = G0[:, 0, :3, 3] - c + (G0[:, 0, :3, :3] @ c)  # G_root = [R, c + t - R c]

        G = G0.clone().requires_grad_(True)
        rot = rot0.clone().requires_grad_(True)
        transl = transl0.clone().requires_grad_(True)
        betas = torch.zeros(B, 1)

        def run(name):
            if name.startswith("torchhand"):
                v = lbs(G, P[name.split("_")[1]])
                inputs = [G]
            elif name == "smplx":
                v = smplx_skinning(G, W, v_posed)
                inputs = [G]
            else:
                v, _ = smplx.lbs.lbs(betas, rot, model.vertices_rest, shapedirs, posedirs,
                                     J_regressor, parents, W, pose2rot=False)
                v = v + transl[:, None]  # global translation, as smplx's body models add it
                inputs = [rot, transl]
            loss = (v * w).sum()
            grads = torch.autograd.grad(loss, inputs)
            return v, grads

        # ------------------------------------------------------------ checks
        out = {m: run(m) for m in methods}
        ref_v, ref_g = out["smplx"]
        for m in methods:
            if m == "smplx":
                continue
            dv = float((out[m][0].detach() - ref_v.detach()).abs().max())
            line = f"B={B} {m} vs smplx skinning: max |dv| = {dv:.2e} mm"
            bad = not dv < TOL_MM  # also catches NaN
            if m.startswith("torchhand"):
                g, gr = out[m][1][0], ref_g[0]
                dg = float((g - gr).abs().max() / gr.abs().max().clamp_min(1e-30))
                line += f", max |dG| / max |G.grad| = {dg:.2e}"
                bad |= not dg < GRAD_RTOL
            if bad:
                failures.append(line)
            tqdm.write(line)
        if failures:
            bar.close()
            print(f"FAILED: torchhand and smplx disagree (tolerances: {TOL_MM} mm, gradient {GRAD_RTOL} "
                  "relative):\n  " + "\n  ".join(failures), file=sys.stderr)
            return 1
        del out, ref_v, ref_g

        # ------------------------------------------------------------ timing
        gc.collect()
        bar.set_description(f"lbs bench B={B}")
        cell = time_cells({m: (lambda m=m: run(m)) for m in methods}, args.repeats, bar)
        row = {
            "torchhand_ms": cell[f"torchhand_{default_layout}"]["median_ms"],
            "smplx_ms": cell["smplx"]["median_ms"],
        }
        row["speedup"] = row["smplx_ms"] / row["torchhand_ms"]
        row["torchhand_dense_ms"] = cell["torchhand_dense"]["median_ms"]
        row["torchhand_sparse_ms"] = cell["torchhand_sparse"]["median_ms"]
        if "smplx_full_lbs" in cell:
            row["smplx_full_lbs_ms"] = cell["smplx_full_lbs"]["median_ms"]
            row["speedup_vs_full_lbs"] = row["smplx_full_lbs_ms"] / row["torchhand_ms"]
        row["min_ms"] = {m: cell[m]["min_ms"] for m in methods}
        row["repeats"] = {m: cell[m]["repeats"] for m in methods}
        results[f"B{B}"] = row
    bar.close()

    results.update({
        "vertices": V,
        "bones": J,
        "threads": threads,
        "torch": torch.__version__,
        "smplx": SMPLX_VERSION,
        "torchhand_default": default_layout,
        "weight_density": density,
        "dtype": "float32",
        "machine": f"{platform.machine()}, {len(os.sched_getaffinity(0))} cores",
        "loadavg_1min": {"start": load_start[0], "end": os.getloadavg()[0]},
    })
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(results, indent=2))

    # ------------------------------------------------------------ table
    cols = ["torchhand_dense", "torchhand_sparse", "smplx", "smplx_full_lbs"]
    for what in ("median", "min"):
        print(f"\n{what} ms of forward + backward ({threads} thread(s); torchhand default = {default_layout}):")
        print("| B | torchhand dense | torchhand sparse CSR | smplx skinning | smplx full lbs | speedup |")
        print("|---:|---:|---:|---:|---:|---:|")
        for B in batch_sizes:
            r = results[f"B{B}"]
            if what == "median":
                ms = {c: r.get(f"{c}_ms") for c in cols}
            else:
                ms = {c: r["min_ms"].get(c) for c in cols}
            cells = [f"{ms[c]:.2f}" if ms[c] is not None else "-" for c in cols]
            speed = ms["smplx"] / ms[f"torchhand_{default_layout}"]
            print(f"| {B} | " + " | ".join(cells) + f" | {speed:.2f}x |")
    last = results[f"B{max(batch_sizes)}"]
    ok = last["speedup"] >= TARGET_SPEEDUP
    print(f"\nB={max(batch_sizes)}: speedup {last['speedup']:.2f}x "
          f"({'meets' if ok else 'MISSES'} the target of {TARGET_SPEEDUP:.0f}x); wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
