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
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine, write_json  # noqa: E402

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


def run(root: Path, split: Path, out: Path, workers: int) -> tuple:
    """(wall seconds, results.json) of one ``torchhand eval-dataset`` process."""
    exe = Path(sys.executable).parent / "torchhand"
    cmd = [str(exe), "eval-dataset", "dexycb", str(root), "--split", str(split), "--out", str(out),
           "--workers", str(workers)]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} exited {done.returncode}:\n{done.stderr[-2000:]}")
    return time.perf_counter() - t0, json.loads((out / "results.json").read_text())


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hia-root", type=Path, required=True)
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--motion", default="12", help="a one-hand thesis sequence")
    ap.add_argument("--sequences", type=int, default=4)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        split = write_root(args.hia_root, args.motion, args.sequences, args.frames, tmp)
        times = {1: [], 2: []}
        overall = {}
        for r in range(args.repeats):
            for w in (1, 2):
                secs, res = run(tmp / "dexycb", split, tmp / f"out_{w}_{r}", w)
                times[w].append(secs)
                overall[w] = res["overall"]
                mpjpe = res["overall"].get("mpjpe_mm", float("nan"))
                print(f"workers {w}, repeat {r}: {secs:.1f} s, MPJPE {mpjpe:.2f} mm", flush=True)
    med = {w: statistics.median(t) for w, t in times.items()}
    write_json(args.json, {"machine": machine(), "sequences": args.sequences, "frames": args.frames,
                           "motion": args.motion, "seconds": times, "median_seconds": med,
                           "speedup_2_workers": med[1] / med[2], "overall_1_worker": overall[1],
                           "overall_2_workers": overall[2]})


if __name__ == "__main__":
    main()
