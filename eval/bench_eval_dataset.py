"""``torchhand eval-dataset`` over one and two worker processes (docs/scaleout.md).

    python eval/bench_eval_dataset.py --hia-root ../shared/data/hands_in_action --json out/bench_eval_dataset.json

``--sequences`` windows of ``--frames`` frames of the thesis motion ``--motion`` (one
right hand) are rendered with the kinect noise model (``torchhand synth``'s renderer)
and written in DexYCB's published layout, one camera each
(:func:`torchhand.data.datasets.dexycb.write_dexycb`), under one root with a split
file listing them. Then ``torchhand eval-dataset dexycb ROOT --split FILE --out DIR``
runs as a user runs it (a fresh process, a fresh ``--out``), with ``--workers 1`` and
``--workers 2``, alternating, ``--repeats`` times each: import, automatic
initialisation, tracking with the defaults and scoring of every sequence. Reported:
each run's wall time (median of the repeats), ``speedup_2_workers`` (one worker's
median over two workers'), and the overall MPJPE of both (the same numbers: the task
does not depend on the worker count).

The reference for the speed-up, in the same alternation: two independent
``torchhand eval-dataset`` processes started at once, each with one worker on half of
the split (``two_processes``; ``speedup_2_processes``: one worker's median over theirs).
They share nothing but the machine, so their speed-up is what two cores give this work
here; ``workers_vs_processes`` is the two workers' speed-up over it (1: the scale-out
loses nothing to its distribution of the work).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine, run_together, write_json  # noqa: E402

from torchhand.data.datasets.dexycb import write_dexycb  # noqa: E402
from torchhand.data.layout import SequenceLayout, read_depth, read_joints21, read_sequence_info  # noqa: E402
from torchhand.data.synth import thesis_motion, write_synthetic_sequence  # noqa: E402
from torchhand.geometry.camera import Camera  # noqa: E402

SERIAL = "840412060917"


def write_root(hia_root: Path, motion: str, sequences: int, frames: int, root: Path) -> Path:
    """The DexYCB root of the benchmark and its split file."""
    names = []
    for k in range(sequences):
        fr = thesis_motion(hia_root, motion, slice(k * frames, (k + 1) * frames), dtype=torch.float32)
        fr.name = f"hia_{motion}_{k * frames}"
        seq = write_synthetic_sequence(fr, root / "renders" / fr.name, noise="kinect", seed=k, rgb=False,
                                       progress=False)
        info = read_sequence_info(seq)
        layout = SequenceLayout(seq)
        depth = torch.stack([torch.as_tensor(read_depth(layout.depth(f), info.depth_unit_mm))
                             for f in range(info.frames)]).numpy()
        joints = read_joints21(layout.gt)[0][:, 0]  # (N, 21, 3) mm in camera 0
        c = info.cameras[0]  # the master: the joints are in its frame
        master = Camera.from_intrinsics(c.fx, c.fy, c.cx, c.cy, c.width, c.height)
        name = f"20201022_{110000 + k:06d}"
        write_dexycb(root / "dexycb", "bench-subject", name, {SERIAL: master}, SERIAL, {SERIAL: depth}, joints)
        names.append(f"bench-subject/{name}")
    split = root / "split.txt"
    split.write_text("\n".join(names) + "\n")
    return split


def command(root: Path, split: Path, out: Path, workers: int) -> list:
    """The ``torchhand eval-dataset`` command line of a run."""
    exe = Path(sys.executable).parent / "torchhand"
    return [str(exe), "eval-dataset", "dexycb", str(root), "--split", str(split), "--out", str(out),
            "--workers", str(workers)]


def run(root: Path, split: Path, out: Path, workers: int) -> tuple:
    """(wall seconds, results.json) of one ``torchhand eval-dataset`` process."""
    secs = run_together([command(root, split, out, workers)])
    return secs, json.loads((out / "results.json").read_text())


def halves(split: Path) -> tuple:
    """The split file's sequences in two files, the first half and the rest."""
    names = split.read_text().split()
    out = []
    for k, part in enumerate((names[: len(names) // 2], names[len(names) // 2:])):
        out.append(split.with_name(f"{split.stem}_half{k}.txt"))
        out[-1].write_text("\n".join(part) + "\n")
    return tuple(out)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hia-root", type=Path, required=True)
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--motion", default="12", help="a one-hand thesis sequence")
    ap.add_argument("--sequences", type=int, default=4)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args(argv)
    if args.sequences < 2 or args.repeats < 1:
        ap.error("--sequences must be 2 or more (two halves) and --repeats 1 or more")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        split = write_root(args.hia_root, args.motion, args.sequences, args.frames, tmp)
        parts = halves(split)
        times = {"1_worker": [], "2_workers": [], "two_processes": []}
        overall = {}
        for r in range(args.repeats):
            for w, key in ((1, "1_worker"), (2, "2_workers")):
                secs, res = run(tmp / "dexycb", split, tmp / f"out_{w}_{r}", w)
                times[key].append(secs)
                overall[key] = res["overall"]
                mpjpe = res["overall"].get("mpjpe_mm", float("nan"))
                print(f"workers {w}, repeat {r}: {secs:.1f} s, MPJPE {mpjpe:.2f} mm", flush=True)
            secs = run_together([command(tmp / "dexycb", part, tmp / f"out_half{k}_{r}", 1)
                                 for k, part in enumerate(parts)])
            times["two_processes"].append(secs)
            print(f"two processes on half the split each, repeat {r}: {secs:.1f} s", flush=True)
    med = {k: statistics.median(t) for k, t in times.items()}
    write_json(args.json, {"machine": machine(), "sequences": args.sequences, "frames": args.frames,
                           "motion": args.motion, "seconds": times, "median_seconds": med,
                           "speedup_2_workers": med["1_worker"] / med["2_workers"],
                           "speedup_2_processes": med["1_worker"] / med["two_processes"],
                           "workers_vs_processes": med["two_processes"] / med["2_workers"],
                           "overall_1_worker": overall["1_worker"], "overall_2_workers": overall["2_workers"]})


if __name__ == "__main__":
    main()
