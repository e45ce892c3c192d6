"""Scale-out benchmark: 8 sequences tracked with 1 and 2 workers, local processes and
Ray (docs/benchmarks.md).

    python eval/bench_scale.py --json out/bench_scale.json [--sequences 8 --frames 20]

The sequences are the shipped demo motion's right hand from frame 7k, back and forth
over its 60 frames for as many frames as asked (kinect noise),
one sequence per task (the CPU default). Timed side by side in one run:

- ``sequential``: ``torchhand track`` with one worker (this process, after one warm-up
  sequence: its first tracking fills its caches);
- ``local_2``: two worker processes forked from the workers' server, which is started
  before the clock (``worker_server_start_s``), as the command line starts it when it
  parses ``--workers`` while it imports torchhand itself (their fork included);
- ``ray_1`` / ``ray_2``: a local Ray instance with 1 / 2 CPUs, started before the clock
  (as a running cluster is), the workers' start and imports included;
- what limits ``local_2``: ``task_slowdown_2_workers``, how much longer a task takes
  while the other worker runs one than in the sequential run (the cores share caches,
  memory and the host's load; the scale-out shares nothing else), and
  ``speedup_2_workers_ideal`` = 2 / that slowdown, the speed-up of two workers that
  lose no time outside their tasks and finish together; ``local_vs_ideal`` is the
  measured speed-up over it (1: nothing lost to starting, dispatching and balancing).

With ``--repeats R`` the sequential and ``local_2`` runs are made R times, alternating,
so that a change of the machine's load falls on both: ``pairs`` holds each pair's
figures, and ``speedup_2_workers_local``, ``task_slowdown_2_workers``,
``speedup_2_workers_ideal`` and ``local_vs_ideal`` are their medians; the other figures
are those of the first pair.

Per task, the events the workers send (start, done, in this process's clock) give the
time the task itself ran. ``ray_overhead_s_per_task`` is the wall time of the 1-CPU Ray
run not spent inside a task, per task, once its worker runs (dispatch, results,
scheduling); ``ray_worker_start_s`` the one-off start of a worker (process and
imports; ``ray_2_workers_start_s`` that of the 2-CPU run, two starting at once); ``ray_task_slowdown`` how much longer a task takes under Ray than in the
sequential run (Ray's own processes share the cores); ``ray_overhead_of_100_frame_sequence``
both as a fraction of a 100-frame sequence's time. ``*_after_start`` speedups count the
frames/s once the workers run. Every run's θ, the repeats' too, is checked equal to the
first sequential run's to the last bit.

With ``--long N``, one more sequence of N frames is tracked in one pass by one worker
and with ``--chunk N/2`` by two (``torchhand track --workers 2 --chunk``):
``speedup_chunked_2_workers`` is their wall time ratio, and
``chunked_keypoint_deviation_mm`` the mean distance of the chunked run's keypoints
from the one-pass run's over the second chunk's frames (the first chunk's are equal to
the last bit, which is checked).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine, set_threads, write_json  # noqa: E402

from torchhand.app.scaleout import CHUNK_OVERLAP, TrackJob, chunk_windows, track_many  # noqa: E402
from torchhand.data.layout import OutputLayout, read_sequence_info  # noqa: E402
from torchhand.data.synth import SyntheticFrames, demo_motion, write_synthetic_sequence  # noqa: E402
from torchhand.model.scene import Scene  # noqa: E402


def make_sequences(root: Path, n: int, frames: int) -> list:
    demo = demo_motion()
    scene = Scene.from_names(["hand_right"], dtype=demo.theta.dtype)
    right = demo.scene.slices["hand_right"]
    out = []
    period = 2 * (len(demo.theta) - 1)
    for k in range(n):
        # from frame 7k of the motion, back and forth over it (as long as --frames asks)
        t = (7 * k + np.arange(frames)) % period
        idx = torch.as_tensor(np.where(t < len(demo.theta), t, period - t))
        th = demo.theta[idx][:, right]
        fr = SyntheticFrames(scene, th, demo.cameras, f"seq{k:02d}", {"format": "demo back and forth", "start": 7 * k})
        out.append(write_synthetic_sequence(fr, root / f"seq{k:02d}", noise="kinect", seed=k, rgb=False))
    return out


def timed(seqs, out: Path, **kw) -> dict:
    events = []
    t0 = time.perf_counter()
    run = track_many(seqs, out, TrackJob(), progress=False,
                     on_event=lambda e: events.append((time.perf_counter() - t0, *e)), **kw)
    wall = time.perf_counter() - t0
    assert run["failed"] == 0, run
    starts = {i: t for t, i, kind, _ in events if kind == "start"}
    ends = {i: t for t, i, kind, _ in events if kind == "done"}
    pid = {i: v for _, i, kind, v in events if kind == "start"}
    task_s = [ends[i] - starts[i] for i in ends]
    first = min(starts.values())
    used = len(set(pid.values()))
    return {"wall_s": wall, "frames_per_s": run["frames"] / wall, "tasks": run["tasks"],
            "task_s_mean": statistics.mean(task_s), "first_start_s": first, "workers_used": used,
            # after the workers started: the wall time not spent inside a task, per task and worker
            "dispatch_s_per_task": (wall - first - sum(task_s) / used) / (len(task_s) / used)}


def chunked(seqs: list, tmp: Path) -> dict:
    """One long sequence in one pass (one worker) and in two chunks (two workers)."""
    n = read_sequence_info(seqs[0]).frames
    one = timed(seqs, tmp / "long_one")
    two = timed(seqs, tmp / "long_two", workers=2, chunk=(n + 1) // 2)
    a, b = (OutputLayout(tmp / d / seqs[0].name) for d in ("long_one", "long_two"))
    first = chunk_windows(n, (n + 1) // 2, CHUNK_OVERLAP)[0][2]  # the first chunk's frames
    assert np.array_equal(np.load(a.theta)[:first], np.load(b.theta)[:first]), "the first chunk differs from one pass"
    dev = np.linalg.norm(np.load(a.keypoints_3d)[first:] - np.load(b.keypoints_3d)[first:], axis=-1)
    return {"long_frames": n, "long_one_pass": one, "long_chunked_2": two,
            "speedup_chunked_2_workers": one["wall_s"] / two["wall_s"],
            "chunked_keypoint_deviation_mm": float(dev.mean())}


def start_worker_server() -> float:
    """Start the local workers' server and wait until it has imported what it preloads
    (a worker forked from it ran a no-op): seconds."""
    from concurrent.futures import ProcessPoolExecutor

    from torchhand.app.workers import start_server, worker_context

    t0 = time.perf_counter()
    start_server(2)
    with ProcessPoolExecutor(max_workers=1, mp_context=worker_context("torchhand.app.scaleout")) as pool:
        pool.submit(os.getpid).result()
    return time.perf_counter() - t0


def local_pairs(seqs: list, tmp: Path, repeats: int) -> tuple:
    """``repeats`` pairs of runs, the sequential one and ``local_2``, alternating so that a
    change of the machine's load falls on both, after one warm-up sequence (this
    process's first tracking fills its caches and loads its kernels, which a worker's
    does too, within its tasks). The workers' server is started before the first
    ``local_2``, as the command line starts it when it parses ``--workers``: ([(sequential,
    local_2, their output folders)], the server's start in seconds)."""
    timed(seqs[:1], tmp / "warmup")
    pairs, server_s = [], None
    for r in range(repeats):
        a = timed(seqs, tmp / f"seq{r}")
        if server_s is None:
            server_s = start_worker_server()
        pairs.append((a, timed(seqs, tmp / f"local2_{r}", workers=2), (f"seq{r}", f"local2_{r}")))
    return pairs, server_s


def pair_figures(pairs: list) -> dict:
    """Per pair and their medians: the speed-up of two workers, a task's slowdown beside
    another worker, the ideal speed-up that allows and the share of it reached."""
    rows = [{"sequential_s": a["wall_s"], "local_2_s": b["wall_s"], "speedup": a["wall_s"] / b["wall_s"],
             "task_slowdown": b["task_s_mean"] / a["task_s_mean"]} for a, b, _ in pairs]
    for row in rows:
        row["ideal"] = 2 / row["task_slowdown"]
        row["local_vs_ideal"] = row["speedup"] / row["ideal"]
    med = {k: statistics.median(row[k] for row in rows) for k in ("speedup", "task_slowdown", "ideal", "local_vs_ideal")}
    return {"pairs": rows, "speedup_2_workers_local": med["speedup"], "task_slowdown_2_workers": med["task_slowdown"],
            "speedup_2_workers_ideal": med["ideal"], "local_vs_ideal": med["local_vs_ideal"]}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--sequences", type=int, default=8)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--no-ray", action="store_true")
    ap.add_argument("--repeats", type=int, default=1,
                    help="pairs of sequential and local_2 runs, alternating (the medians of their figures are reported)")
    ap.add_argument("--long", type=int, default=0, help="frames of the one long sequence tracked in chunks (0: none)")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error(f"--repeats must be 1 or more, got {args.repeats}")
    set_threads(1)
    result = {"sequences": args.sequences, "frames_per_sequence": args.frames, **machine()}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        seqs = make_sequences(tmp / "data", args.sequences, args.frames)
        pairs, result["worker_server_start_s"] = local_pairs(seqs, tmp, args.repeats)
        runs = {"sequential": pairs[0][0], "local_2": pairs[0][1]}
        folders = [f for _, _, fs in pairs for f in fs]
        if not args.no_ray:
            import ray

            from torchhand.app.scaleout import connect_ray

            for n in (1, 2):
                t0 = time.perf_counter()
                connect_ray("local", n)
                result[f"ray_start_s_{n}"] = time.perf_counter() - t0
                runs[f"ray_{n}"] = timed(seqs, tmp / f"ray{n}", ray="local")
                folders.append(f"ray{n}")
                ray.shutdown()
        if args.long:
            result.update(chunked(make_sequences(tmp / "long", 1, args.long), tmp))
        for folder in folders:  # every run, repeats included, against the first sequential one
            for s in seqs:
                same = np.array_equal(np.load(OutputLayout(tmp / folder / s.name).theta),
                                      np.load(OutputLayout(tmp / "seq0" / s.name).theta))
                assert same, f"{folder}: {s.name} differs from the sequential run"
    result["runs"] = runs
    result.update(pair_figures(pairs))
    seq = runs["sequential"]
    result["seconds_per_frame"] = seq["wall_s"] / (args.sequences * args.frames)

    def steady(r):  # frames/s once the workers run
        return args.sequences * args.frames / (r["wall_s"] - r["first_start_s"])

    result["speedup_2_workers_local_after_start"] = steady(runs["local_2"]) / steady(seq)
    if "ray_2" in runs:
        result.update(ray_figures(runs, result["seconds_per_frame"], steady))
    write_json(args.json, result)
    return result


def ray_figures(runs: dict, seconds_per_frame: float, steady) -> dict:
    """The Ray runs against each other and the (first) sequential run (module docstring)."""
    seq, r1, r2 = runs["sequential"], runs["ray_1"], runs["ray_2"]
    out = {"speedup_2_workers_ray": r1["wall_s"] / r2["wall_s"],
           "speedup_2_workers_ray_after_start": steady(r2) / steady(r1),
           "speedup_ray_2_vs_sequential": seq["wall_s"] / r2["wall_s"],
           "ray_worker_start_s": r1["first_start_s"], "ray_2_workers_start_s": r2["first_start_s"],
           "ray_overhead_s_per_task": r1["dispatch_s_per_task"],
           "ray_task_slowdown": r1["task_s_mean"] / seq["task_s_mean"] - 1}  # Ray's own processes' CPU
    hundred = 100 * seconds_per_frame
    out["ray_overhead_of_100_frame_sequence"] = (r1["dispatch_s_per_task"] + out["ray_task_slowdown"] * hundred) / hundred
    return out


if __name__ == "__main__":
    main()
